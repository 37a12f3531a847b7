"""Consensus gravity-aided fit: the hard-iron offset from the clean part of a buffer a disturbance polluted.

A walk that starts next to steel (a backend restarted mid-walk, a recording begun in a car park) fills the
diversity buffer with samples of a field that is not the Earth's: hundreds of µT that move with every step.
They are never redundant with one another, so they outnumber the clean samples — on the tyrex walks started
20 s in, 35–75 of 400 samples are the Earth's field.  A least-squares fit over the whole buffer (even with
the Huber weights of :mod:`pdr_mag.calibration.gravity`) is dragged far off and refused, and nothing is
calibrated for the whole walk.

The disturbance has structure the fit can use: it is spatial, so the samples it touches come in runs of
consecutive times, and a run of clean samples obeys the gravity-aided model of
:mod:`pdr_mag.calibration.gravity` with the reference strength ``F`` and dip ``I`` — the field model's, or
the calibration's.  The search (random sample consensus over time windows instead of random samples):

1. sort the buffer by time; every window of ``consensus_window`` consecutive samples (half-overlapping)
   gives a hypothesis ``b_k`` by the gravity-aided fit (strength and dip equations, F and F sin I with
   their priors) — a window that turns (yaw) fixes ``b`` alone;
2. a sample is an inlier of ``b`` when its calibrated field ``y_i = M(m_i − b)`` has the reference strength
   and dip: ``| |y_i| − F | ≤ consensus_strength_frac · F`` and ``|dip_i − I| ≤ consensus_dip_deg``
   (``dip_i = asin(−y_i·u_i / |y_i|)``) — two conditions a disturbed field meets by chance only, where
   the clean samples of every time meet both;
3. the hypothesis with the most inliers is refitted on its inliers, the inliers found again about the
   refit, and refitted once more; fewer than ``consensus_min_inliers`` inliers: no result.

The result is an ordinary gravity-aided calibration (``method="gravity"``; its covariance from the inliers
alone, scaled for their errors' correlation in time, :func:`pdr_mag.calibration.refit.with_correlated_errors`)
judged by the same rules as every refit; ``extra["consensus"]`` holds the inlier count and share.  It needs
the references (no F, no I: a window cannot fix the offset along the up axis) and is tried only when the
plain fit of the whole buffer is refused.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from pdr_mag.calibration.gravity import fit_model, fit_offset
from pdr_mag.calibration.model import MagCalibration
from pdr_mag.calibration.online_settings import OnlineSettings


def inliers(y: np.ndarray, u: np.ndarray, c: np.ndarray, strength: float, dip_deg: float,
            s: OnlineSettings) -> np.ndarray:
    """Samples whose field ``y − c`` (shaped samples ``y = M m``, centre ``c = M b``) has the reference
    strength and dip within the consensus tolerances (step 2 of the module docstring)."""
    x = y - c
    n = np.linalg.norm(x, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        sin_dip = -np.einsum("ij,ij->i", x, u) / n
    dip = np.degrees(np.arcsin(np.clip(sin_dip, -1.0, 1.0)))
    return (np.abs(n - strength) <= s.consensus_strength_frac * strength) & (
        np.abs(dip - dip_deg) <= s.consensus_dip_deg
    )


def consensus_offset(
    m: np.ndarray,
    u: np.ndarray,
    times: np.ndarray,
    shape: MagCalibration | None,
    strength: float,
    sin_dip: float,
    settings: OnlineSettings,
) -> tuple[np.ndarray, int] | None:
    """The consensus search of the module docstring on raw samples ``m``, unit up vectors ``u`` and their
    ``times``, keeping the soft iron and axes of ``shape`` (None: identity).

    Returns ``(mask, best)``: the inliers of the final offset (a boolean mask over the samples) and the
    number of inliers the best window's hypothesis had; None when no hypothesis reaches
    ``consensus_min_inliers`` or the references are not finite.
    """
    s = settings
    if not (np.isfinite(strength) and strength > 0 and np.isfinite(sin_dip)):
        return None
    k = int(s.consensus_window)
    if len(m) < max(k, s.consensus_min_inliers):
        return None
    mm = shape.matrix if shape is not None else np.eye(3)
    y = m @ mm.T
    uu = u / np.linalg.norm(u, axis=1)[:, None]
    model = fit_model(strength, sin_dip, s.sigma_strength_uT, s.sigma_tilt_deg, s.prior_strength_std_uT,
                      s.prior_dip_std_deg)  # fmt: skip
    dip_deg = float(np.degrees(np.arcsin(np.clip(sin_dip, -1.0, 1.0))))
    order = np.argsort(times, kind="stable")
    best_n, best_c = 0, None
    for a in range(0, len(m) - k + 1, max(k // 2, 1)):
        w = order[a : a + k]
        fit = fit_offset(y[w], uu[w], model)
        if not fit.ok or not np.all(np.isfinite(fit.offset)):
            continue
        n_in = int(np.count_nonzero(inliers(y, uu, fit.offset, strength, dip_deg, s)))
        if n_in > best_n:
            best_n, best_c = n_in, fit.offset
    if best_c is None or best_n < s.consensus_min_inliers:
        return None
    mask = inliers(y, uu, best_c, strength, dip_deg, s)
    for _ in range(2):  # refit on the inliers, and find them again about the refit
        fit = fit_offset(y[mask], uu[mask], model)
        if not fit.ok:
            return None
        mask = inliers(y, uu, fit.offset, strength, dip_deg, s)
        if np.count_nonzero(mask) < s.consensus_min_inliers:
            return None
    return mask, best_n


def with_consensus(cal: MagCalibration, mask: np.ndarray, best: int) -> MagCalibration:
    """``cal`` (the fit of the inliers) marked as a consensus fit: inlier count and share of the buffer."""
    n = int(np.count_nonzero(mask))
    extra = {**cal.extra, "consensus": {"inliers": n, "share": round(n / len(mask), 4), "best_window": best}}
    return replace(cal, extra=extra)
