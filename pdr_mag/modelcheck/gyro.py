"""The ``gyro_bias`` candidate: its start value, and the diagnosis replayed with the bias it finds.

A bias δ left in the gyro after the accelerometer has taken what it observes
(:func:`~pdr_mag.modelcheck.orientation.tilt_gyro_bias`) turns the estimated heading by
``ψ(t) = δ · ∫up_d dt`` (:mod:`.fit`).  A phone's raw gyro may be off by several °/s about its up axis —
the tyrex Nexus 5 by 4.3 °/s, hundreds of degrees over a few minutes — so the fit needs a start value
within a quarter turn of the end: :func:`heading_drift_start` finds one by a grid search.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pdr_mag.modelcheck.fit import (
    FitResult,
    Problem,
    fit_model,
    measurement_times,
    sample_matrices,
    with_track,
)
from pdr_mag.modelcheck.null import above_white, stride_for, subsample
from pdr_mag.modelcheck.orientation import OrientationSettings, estimate_orientation


def heading_drift_start(problem: Problem, fit: FitResult, max_rate: float = 0.4, rate_hz: float = 2.0,
                        chunk: int = 64) -> np.ndarray:
    """Start value of δ: the bias along the phone's mean up axis μ whose heading drift best explains the
    measured field (rad/s, device axes; along μ as far as the accelerometer leaves it free).

    For a rate r the prediction is ``m_i = P_i Rz(r s_i) B_w + b`` (``P_i`` the current model's map of
    sample i, ``s_i = a · ∫up_d dt``, ``a`` that axis scaled to ``a · μ = 1``): linear in ``B_w`` and
    ``b``, solved by their 6 × 6 normal equations for every r of a grid over ±``max_rate`` whose step turns
    the heading by at most 45° over the recording (so the fit that starts from the best one is within its
    basin); the samples are thinned to ``rate_hz``, which a drift does not need more of.
    """
    sub = subsample(problem, stride_for(problem, rate_hz))
    nl = {k: v for k, v in fit.nonlinear.items() if k != "gyro_bias"}
    up = sub.r_dw0[:, :, 2].mean(axis=0)
    mu = up / np.linalg.norm(up)
    # the direction with a unit part along μ that the accelerometer's prior holds least, I⁻¹μ (its prior
    # holds the directions it observes to 10⁻⁴ rad/s, a few degrees off perpendicular to μ: a start of
    # 0.06 rad/s along μ itself would sit far up that prior's wall, and the fit slide out of the basin)
    info = sub.track.tilt_bias.prior_information
    axis = np.linalg.solve(info + 1e-9 * max(float(np.trace(info)), 1.0) * np.eye(3), mu)
    axis = axis / float(axis @ mu)
    s = sub.track.up_integral(measurement_times(sub, nl)) @ axis
    span = max(float(np.ptp(s)), 1e-9)
    step = 0.25 * np.pi / span
    rates = np.arange(-max_rate, max_rate + 0.5 * step, step)
    p = sample_matrices(sub, nl)
    y = sub.mag
    n = len(y)
    best, best_rss = 0.0, np.inf
    for k0 in range(0, len(rates), chunk):
        r = rates[k0:k0 + chunk]
        psi = np.outer(r, s)  # (K, N)
        c, sn = np.cos(psi), np.sin(psi)
        m = np.empty((len(r), n, 3, 3))
        m[..., 0] = p[None, :, :, 0] * c[..., None] + p[None, :, :, 1] * sn[..., None]
        m[..., 1] = -p[None, :, :, 0] * sn[..., None] + p[None, :, :, 1] * c[..., None]
        m[..., 2] = p[None, :, :, 2]
        ata = np.zeros((len(r), 6, 6))
        ata[:, :3, :3] = np.einsum("knji,knjl->kil", m, m)
        ata[:, :3, 3:] = np.transpose(m.sum(axis=1), (0, 2, 1))
        ata[:, 3:, :3] = m.sum(axis=1)
        ata[:, 3:, 3:] = n * np.eye(3)
        aty = np.concatenate([np.einsum("knji,nj->ki", m, y), np.broadcast_to(y.sum(axis=0), (len(r), 3))],
                             axis=1)
        sol = np.linalg.solve(ata + 1e-9 * n * np.eye(6), aty[..., None])[..., 0]
        rss = float(np.sum(y * y)) - np.einsum("ki,ki->k", sol, aty)
        i = int(np.argmin(rss))
        if rss[i] < best_rss:
            best, best_rss = float(r[i]), float(rss[i])
    return best * axis


def replay(problem: Problem, fit: FitResult, gyro, accel, settings: OrientationSettings, max_nfev: int):
    """Re-estimate the orientation with the fitted gyro bias and refit (the diagnosis replayed).

    The estimator starts from ``b_track + δ`` and lets the accelerometer re-estimate what it observes, so
    the bias about the up axis comes from the magnetometer and the rest from the accelerometer.  A bias
    also tilts the estimate between the accelerometer's corrections, which the first-order heading drift
    does not model; the replayed fit is kept when it fits better, the first-order one otherwise (so the
    gyro_bias model nests the current one).  Returns (problem, fit).
    """
    if gyro is None or "gyro_bias" not in fit.nonlinear:
        return problem, fit
    bias = problem.track.gyro_bias + fit.nonlinear["gyro_bias"]
    track = estimate_orientation(gyro[0], gyro[1], accel[0], accel[1], bias, settings)
    p2 = with_track(problem, track)
    init = dict(fit.nonlinear, gyro_bias=np.zeros(3))
    f2 = fit_model(p2, fit.effects, init, max_nfev)
    return (p2, f2) if f2.rss < fit.rss else (problem, fit)


@dataclass(frozen=True)
class AccelerometerBias:
    """The part of the gyro bias the accelerometer sees (the drift of gravity in the gyro frame,
    :class:`~pdr_mag.modelcheck.orientation.TiltBias`), already in the orientation when significant, and
    whether it names ``gyro_bias`` as a missing effect: it does when it is significant and worth naming —
    at least the smallest gyro bias worth naming (0.3 °/s, :data:`~pdr_mag.modelcheck.identify.SMALLEST`),
    or smaller but passing the search's gap rule: the final model's gap (its linear parameters refitted,
    the magnetometer's own part of the bias left out) along the orientation with it, above the white noise,
    is at least ``min_gap_reduction`` below the same along the gyro integrated without it (``gap_with``,
    ``gap_raw_gyro``, µT).  The gap alone would not do: what the final model still leaves unexplained (a
    steel area named as the wrong kind of disturbance) can make a 1.1 °/s bias look small.
    """

    rad_per_s: np.ndarray
    t2: float
    threshold: float
    named: bool = False
    gap_raw_gyro: float | None = None
    gap_with: float | None = None

    def to_dict(self) -> dict:
        def r(v, nd=5):
            return round(float(v), nd) if np.isfinite(v) else None

        return {"rad_per_s": [r(v) for v in self.rad_per_s], "t2": r(self.t2, 2),
                "threshold": r(self.threshold, 2), "named": self.named,
                "gap_raw_gyro": None if self.gap_raw_gyro is None else r(self.gap_raw_gyro, 4),
                "gap_with": None if self.gap_with is None else r(self.gap_with, 4)}


def accelerometer_bias(tilt, gap_now: float, raw_gap, white: float, min_gap_reduction: float,
                       smallest: float) -> AccelerometerBias:
    """The verdict of :class:`AccelerometerBias` on a track's ``tilt_bias``: ``gap_now`` is the final
    model's gap with it (µT), ``raw_gap()`` computes the same along the gyro integrated without it (called
    only when the bias is significant), ``white`` the white noise (µT), ``smallest`` the smallest gyro bias
    worth naming (rad/s)."""
    b = np.asarray(tilt.correction, float)
    if not tilt.significant:
        return AccelerometerBias(b, tilt.t2, tilt.threshold)
    g_raw = float(raw_gap())
    shrinks = above_white(gap_now, white) <= (1.0 - min_gap_reduction) * above_white(g_raw, white)
    named = np.linalg.norm(b) >= smallest or shrinks
    return AccelerometerBias(b, tilt.t2, tilt.threshold, bool(named), g_raw, float(gap_now))
