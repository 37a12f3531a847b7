"""Where a local disturbance may act: windows in time where the residual stands out.

``local_anomaly`` (an external field, world frame) and ``hard_iron_change`` (an offset fixed to the phone,
device frame) are *local*: their knots are free only inside these windows and held at zero at the window
edges, so they cannot soak up what is everywhere (a heading drift, a soft-iron pattern).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from pdr_mag.conventions import quat_slerp
from pdr_mag.modelcheck.fit import FitResult, Problem, _quat_to_matrix


def anomaly_support(problem: Problem, fit: FitResult, knot_s: float = 1.0, min_uT: float = 2.0,
                    n_sigma: float = 4.0, max_share: float = 0.5, smooth_s: float = 1.0,
                    frame: str = "world") -> Problem:
    """Confine ``local_anomaly`` to where the residual of ``fit``, seen in the world frame, stands out.

    ``r_w = R_wd (m − m̂)`` is averaged over ``smooth_s``; samples where ``|r̄_w|`` exceeds
    ``max(min_uT, n_sigma · σ_robust)`` (σ from the median absolute deviation) mark the support,
    widened by one knot on each side.  At most ``max_share`` of the samples are kept (the strongest):
    a field that is everywhere is not local.  Knots every ``knot_s`` inside the windows are free; the
    knots at the window edges are held at zero.

    ``frame="device"``: the same on the residual in device axes, for ``hard_iron_change`` (a body-fixed
    offset stands out in the device frame, an external field in the world frame).
    """
    if frame == "device":
        r_w = fit.residual
    else:
        q = quat_slerp(problem.track.t, problem.track.quat, problem.t)
        r_w = np.einsum("nij,nj->ni", _quat_to_matrix(q), fit.residual)
    c = np.vstack([np.zeros((1, 3)), np.cumsum(r_w, axis=0)])
    lo = np.searchsorted(problem.t, problem.t - 0.5 * smooth_s, side="left")
    hi = np.searchsorted(problem.t, problem.t + 0.5 * smooth_s, side="right")
    mag = np.linalg.norm((c[hi] - c[lo]) / (hi - lo)[:, None], axis=1)
    sigma = 1.4826 * np.median(np.abs(fit.residual - np.median(fit.residual, axis=0)))
    thr = max(min_uT, n_sigma * sigma)
    hot = mag > thr
    if hot.mean() > max_share:
        hot = mag >= np.quantile(mag, 1.0 - max_share)
    t = problem.t
    # widen by one knot spacing each side
    th = t[hot]
    if th.size:
        near = np.searchsorted(th, t)
        d_prev = np.abs(t - th[np.clip(near - 1, 0, th.size - 1)])
        d_next = np.abs(th[np.clip(near, 0, th.size - 1)] - t)
        hot = np.minimum(d_prev, d_next) <= knot_s
    edges = np.flatnonzero(np.diff(np.concatenate([[0], hot.astype(np.int8), [0]])))
    for a, b in zip(edges[1:-1:2], edges[2::2], strict=True):  # fill gaps shorter than 3 knots
        if t[b] - t[a - 1] < 3.0 * knot_s:
            hot[a:b] = True
    edges = np.flatnonzero(np.diff(np.concatenate([[0], hot.astype(np.int8), [0]])))
    knots, free = [], []
    for a, b in zip(edges[::2], edges[1::2], strict=True):
        t0, t1 = t[a], t[b - 1]
        nk = max(2, int(np.ceil((t1 - t0) / knot_s)) + 1)
        kt = np.linspace(t0 - knot_s, t1 + knot_s, nk + 2)
        knots.extend(kt)
        free.extend([False] + [True] * nk + [False])
    if not knots:
        knots, free = [t[0], t[-1]], [False, False]
    knots = np.asarray(knots)
    free = np.asarray(free)
    if frame == "device":
        return replace(problem, offset_knots=knots, offset_knot_free=free)
    return replace(problem, knots=knots, knot_free=free)
