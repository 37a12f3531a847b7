"""Consensus gravity-aided fit: the hard-iron offset from the clean part of a buffer a disturbance polluted.

A walk that starts next to steel (a backend restarted mid-walk, a recording begun in a car park) fills the
diversity buffer with samples of a field that is not the Earth's: hundreds of µT that move with every step.
They are never redundant with one another, so they outnumber the clean samples — on a tyrex walk started
20 s in (Nexus 5, phoning), 35–77 of 350–400 samples are the Earth's field.  A least-squares fit over the
whole buffer (even with the Huber weights of :mod:`pdr_mag.calibration.gravity`) is dragged far off and
refused, and nothing is calibrated for the whole walk.

The disturbance has structure the fit can use: it is spatial, so the samples it touches come in runs of
consecutive times, and a run of clean samples obeys the gravity-aided model of
:mod:`pdr_mag.calibration.gravity` with the reference strength ``F`` and dip ``I`` — the field model's, or
the calibration's.  The search (random sample consensus, Fischler & Bolles 1981, with hypotheses that use the
runs):

1. hypotheses ``b_k``: every window of ``consensus_window`` consecutive samples in time (half-overlapping)
   fitted by the gravity-aided fit (strength and dip equations, F and F sin I with their priors) — a
   window that turns (yaw) fixes ``b`` alone; and ``consensus_pairs`` pairs of samples solved exactly
   (:func:`pair_hypotheses`), half of them neighbours in time — clean gaps between disturbances too short
   to turn in still give pairs;
2. a sample is an inlier of ``b`` when its calibrated field ``y_i = M(m_i − b)`` has the reference strength
   and dip: ``| |y_i| − F | ≤ consensus_strength_frac · F`` and ``|dip_i − I| ≤ consensus_dip_deg``
   (``dip_i = asin(−y_i·u_i / |y_i|)``) — two conditions a disturbed field meets by chance only, where
   the clean samples of every time meet both;
3. the hypothesis of the lowest truncated cost (:func:`score`: MSAC, Torr & Zisserman 2000) is refitted on its
   inliers and the inliers found again about the refit, twice; the result is the fit of the last inliers
   (:func:`pdr_mag.calibration.refit.candidates`); fewer than ``consensus_min_inliers`` inliers at any step:
   no result.

The result is an ordinary gravity-aided calibration (``method="gravity"``; its covariance from the inliers
alone, scaled for their errors' correlation in time, :func:`pdr_mag.calibration.refit.with_correlated_errors`)
judged by the same rules as every refit; ``extra["consensus"]`` holds the inlier count and share.  It needs
the references (no F, no I: a window cannot fix the offset along the up axis) and is tried only when the
plain fit of the whole buffer is refused.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numba import njit

from pdr_mag.calibration.gravity import fit_model, fit_offset
from pdr_mag.calibration.model import MagCalibration
from pdr_mag.calibration.online_settings import OnlineSettings


def inliers(y: np.ndarray, u: np.ndarray, c: np.ndarray, strength: float, dip_deg: float,
            s: OnlineSettings) -> np.ndarray:
    """Samples whose field ``y − c`` (shaped samples ``y = M m`` (N, 3), unit up vectors ``u``, centre
    ``c = M b``) has the reference strength and dip within the consensus tolerances (step 2 of the module
    docstring): both misfits (:func:`_misfit`) within 1.  Returns (N,) bool."""
    out = np.empty(len(y), dtype=np.bool_)
    _inliers(*_args(y, u, strength, dip_deg, s), np.asarray(c, dtype=float), out)
    return out


def score(y: np.ndarray, u: np.ndarray, hyp: np.ndarray, strength: float, dip_deg: float,
          s: OnlineSettings) -> np.ndarray:
    """The truncated cost of each hypothesis ``hyp`` (P, 3) over the samples ``y``, ``u`` (N, 3), lower
    is better: ``Σ c_i`` with ``c_i = misfit_s² + misfit_d²`` (:func:`_misfit`; at most 2) for an inlier
    (both misfits within 1) and 2 for an outlier — an inlier costs less the better it fits, so of two
    hypotheses with as many inliers the one that fits them better wins (MSAC rather than a count).
    Returns (P,)."""
    out = np.empty(len(hyp))
    _costs(*_args(y, u, strength, dip_deg, s), np.ascontiguousarray(hyp, dtype=float), out)
    return out


def _args(y, u, strength, dip_deg, s: OnlineSettings) -> tuple:
    """The compiled loops' common arguments: samples, up vectors, F, I (rad) and the two tolerances."""
    tol_s = s.consensus_strength_frac * strength
    return (np.ascontiguousarray(y, dtype=float), np.ascontiguousarray(u, dtype=float), float(strength),
            np.radians(dip_deg), tol_s, np.radians(s.consensus_dip_deg))  # fmt: skip


@njit(cache=True, error_model="numpy")
def _misfit(y, u, i, c, strength, dip, tol_s, tol_d):
    """Sample ``i``'s strength and dip misfits about centre ``c`` in units of the tolerances:
    ``(|y_i − c| − F) / tol_s`` and ``(dip_i − I) / tol_d``, ``dip_i = asin(−(y_i − c)·u_i / |y_i − c|)``
    (rad); ``(inf, inf)`` for a sample at the centre."""
    x0, x1, x2 = y[i, 0] - c[0], y[i, 1] - c[1], y[i, 2] - c[2]
    n = np.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
    if not n > 0.0:
        return np.inf, np.inf
    sd = -(x0 * u[i, 0] + x1 * u[i, 1] + x2 * u[i, 2]) / n
    return (n - strength) / tol_s, (np.arcsin(min(max(sd, -1.0), 1.0)) - dip) / tol_d


@njit(cache=True, error_model="numpy")
def _inliers(y, u, strength, dip, tol_s, tol_d, c, out):
    """:func:`inliers`' loop."""
    for i in range(len(y)):
        ms, md = _misfit(y, u, i, c, strength, dip, tol_s, tol_d)
        out[i] = abs(ms) <= 1.0 and abs(md) <= 1.0


@njit(cache=True, error_model="numpy")
def _costs(y, u, strength, dip, tol_s, tol_d, hyp, out):
    """:func:`score`'s loop (P hypotheses × N samples)."""
    for p in range(len(hyp)):
        total = 0.0
        for i in range(len(y)):
            ms, md = _misfit(y, u, i, hyp[p], strength, dip, tol_s, tol_d)
            total += ms * ms + md * md if abs(ms) <= 1.0 and abs(md) <= 1.0 else 2.0
        out[p] = total


def pair_hypotheses(y: np.ndarray, u: np.ndarray, order: np.ndarray, strength: float, f_sin_dip: float,
                    s: OnlineSettings) -> np.ndarray:
    """Offsets ``c`` from random pairs of samples (``order``: the samples' indices in time order; a fixed
    seed: the same buffer gives the same pairs).

    With F and ``F sin I`` given, each sample gives two equations linear in ``(c, k = |c|²)`` ([Liu2018]
    eq. 7's form and the dip equation of :mod:`pdr_mag.calibration.gravity`)::

        2 y_i·c − k = |y_i|² − F²        u_i·c = y_i·u_i + F sin I

    so two samples fix ``c`` (4 equations, 4 unknowns; ``k`` is not tied to ``c`` here, the refit on the
    inliers ties it).  Pairs whose 4×4 system is near-singular (the same direction twice) are dropped.
    Returns ``(P, 3)``.
    """
    n = len(y)
    p = int(s.consensus_pairs)
    if n < 2 or p <= 0:
        return np.empty((0, 3))
    rng = np.random.default_rng(n)
    # half the pairs anywhere in the buffer, half a sample and one of the next eight in time (a disturbance
    # comes in runs, so neighbours are clean together far more often than two samples drawn at random)
    i = rng.integers(0, n, p)
    j = (i + rng.integers(1, n, p)) % n  # j ≠ i
    near = np.arange(p) % 2 == 1
    pos = rng.integers(0, n - 1, int(near.sum()))
    i[near] = order[pos]
    j[near] = order[np.minimum(pos + rng.integers(1, 9, len(pos)), n - 1)]
    rows = []
    rhs = []
    with np.errstate(divide="ignore", invalid="ignore"):  # a zero sample gives a non-finite row: dropped
        for a in (i, j):
            norm = np.linalg.norm(2.0 * y[a], axis=1, keepdims=True)  # rows scaled to unit size
            rows += [np.hstack([2.0 * y[a], -np.ones((p, 1))]) / norm, np.hstack([u[a], np.zeros((p, 1))])]
            rhs += [(np.einsum("ij,ij->i", y[a], y[a]) - strength**2) / norm[:, 0],
                    np.einsum("ij,ij->i", y[a], u[a]) + f_sin_dip]  # fmt: skip
    a_mat = np.stack(rows, axis=1)
    b_vec = np.stack(rhs, axis=1)
    finite = np.all(np.isfinite(a_mat), axis=(1, 2)) & np.all(np.isfinite(b_vec), axis=1)
    ok = np.zeros(p, dtype=bool)
    ok[finite] = np.abs(np.linalg.det(a_mat[finite])) > 1e-6
    if not np.any(ok):
        return np.empty((0, 3))
    sol = np.linalg.solve(a_mat[ok], b_vec[ok][..., None])[..., 0]
    return sol[np.all(np.isfinite(sol), axis=1), :3]


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

    Samples with a zero or non-finite vector take no part (and are no inliers).  Returns ``(mask, best)``:
    the inliers of the final offset (a boolean mask over the samples) and the
    number of inliers the best hypothesis had; None when the references are not finite, the buffer is
    shorter than a window, no hypothesis can be formed, a refit fails or fewer than
    ``consensus_min_inliers`` inliers are left.
    """
    s = settings
    if not (np.isfinite(strength) and strength > 0 and np.isfinite(sin_dip)):
        return None
    norm_u = np.linalg.norm(u, axis=1)
    usable = np.isfinite(norm_u) & (norm_u > 0) & np.all(np.isfinite(m), axis=1)  # no zero or NaN vectors
    if not np.all(usable):
        found = consensus_offset(m[usable], u[usable], times[usable], shape, strength, sin_dip, s)
        if found is None:
            return None
        mask = np.zeros(len(m), dtype=bool)
        mask[usable] = found[0]
        return mask, found[1]
    k = int(s.consensus_window)
    if len(m) < max(k, s.consensus_min_inliers):
        return None
    mm = shape.matrix if shape is not None else np.eye(3)
    y = m @ mm.T
    uu = u / norm_u[:, None]
    model = fit_model(strength, sin_dip, s.sigma_strength_uT, s.sigma_tilt_deg, s.prior_strength_std_uT,
                      s.prior_dip_std_deg)  # fmt: skip
    dip_deg = float(np.degrees(np.arcsin(np.clip(sin_dip, -1.0, 1.0))))
    order = np.argsort(times, kind="stable")
    hyp = []
    for a in range(0, len(m) - k + 1, max(k // 2, 1)):
        w = order[a : a + k]
        try:
            fit = fit_offset(y[w], uu[w], model)
        except ValueError:  # a window whose normal equations are singular: no hypothesis
            continue
        if fit.ok and np.all(np.isfinite(fit.offset)):
            hyp.append(fit.offset)
    pairs = pair_hypotheses(y, uu, order, strength, strength * sin_dip, s)
    hyp = np.vstack([np.reshape(hyp, (-1, 3)), pairs])
    if not len(hyp):
        return None
    best_c = hyp[int(np.argmin(score(y, uu, hyp, strength, dip_deg, s)))]
    mask = inliers(y, uu, best_c, strength, dip_deg, s)
    best_n = int(np.count_nonzero(mask))
    if best_n < s.consensus_min_inliers:
        return None
    for _ in range(2):  # refit on the inliers, and find them again about the refit
        try:
            fit = fit_offset(y[mask], uu[mask], model)
        except ValueError:
            return None
        if not fit.ok:
            return None
        mask = inliers(y, uu, fit.offset, strength, dip_deg, s)
        if np.count_nonzero(mask) < s.consensus_min_inliers:
            return None
    return mask, best_n


def with_consensus(cal: MagCalibration, mask: np.ndarray, best: int) -> MagCalibration:
    """``cal`` (the fit of the inliers) marked as a consensus fit: inlier count and share of the buffer."""
    n = int(np.count_nonzero(mask))
    found = {"inliers": n, "share": round(n / len(mask), 4), "best_hypothesis": best}
    extra = {**cal.extra, "consensus": found}
    return replace(cal, extra=extra)
