"""Compiled per-sample loop of :class:`pdr_mag.calibration.online.OnlineCalibrator` (numba, ``cache=True``).

What the calibrator does for every magnetometer sample between two decisions (refit, stale test) lives
here: the rotation-episode tracker, the decimated ring of recent samples, the buffer-admission test
(consistency with the calibration of the block start, redundancy against the buffer of the block start)
and the diversity buffer itself (refresh, eviction of the most redundant sample), plus the direction
coverage of the buffer at every block end.  :func:`scan` returns to Python whenever a refit or a stale test
is due, so those (rare, vectorised) decisions stay in ``online.py``.

Scalar state lives in one float64 vector ``ks`` (the ``K_*`` indices), so the Python object reads and
writes it by name and it round-trips through JSON with the rest of the calibrator's state.
The block-start parameters of the admission test are in ``bp`` (the ``B_*`` indices): the calibration
matrix ``M`` and offset ``b`` of ``M (m − b)``, the reference strength and dip, and the separation
thresholds.
"""

from __future__ import annotations

import numpy as np
from numba import njit

# ---- scalar state ks
K_RATE_EMA = 0
K_EPISODE = 1
K_EPISODE_SEEN = 2
K_LAST_REC_T = 3
K_REC_I = 4
K_NBUF = 5
K_NEXT_REFIT_T = 6
K_NEXT_STALE_T = 7
K_VERSION = 8  # incremented at every change of the buffer
K_COV_VERSION = 9  # buffer version of the cached coverage (-1: stale)
K_COV = 10
K_STALE_ON = 11  # a stale test may run (calibrated, not recalibrating)
K_IN_BLOCK = 12  # 1 while a block is open (its start parameters and buffer copy are set)
K_NBUF0 = 13  # buffer size at the block start
K_NOLD0 = 14  # block-start buffer samples that may be older than refresh_s within the block (in ``old0``)
K_HINT = 15  # index of the last buffer sample found close (where the redundancy scan starts)
K_FIT_NEW = 16  # samples taken into the buffer since the last refit (inf: a refit is due whatever the count)
K_FIT_SCALE = 17  # back-off factor of the samples the next refit needs (OnlineSettings.refit_backoff)
K_FIT_N = 18  # buffer size at the last refit
N_KS = 19

# ---- block-start parameters bp
B_CHECK = 0  # 1: test strength (and dip) against the calibration; 0: every sample is consistent
B_M = 1  # 9 values, row-major
B_OFF = 10  # 3 values
B_F = 13
B_TOL_F = 14  # add_tol_frac · F
B_DIP_CHECK = 15
B_DIP_DEG = 16
B_DIP_TOL = 17
B_SEP2 = 18  # (min_sep_frac · F)² of the redundancy test
B_COS_UP = 19
N_BP = 20

# ---- constant settings cp
C_REFRESH_S = 0
C_REC_DT = 1
C_EP_RATE = 2
C_SIZE = 3
C_COS_COV = 4
N_CP = 5

# ---- return codes of scan
# ---- dp: what scan needs to take a due refit / stale test that would change nothing without returning
D_PERIOD = 0  # the refit period now (OnlineSettings.refit_period_s, halved while uncalibrated)
D_MIN_SAMPLES = 1
D_MIN_NEW = 2  # refit_min_new
D_NEW_FRAC = 3  # refit_new_frac
D_STALE_DT = 4  # stale_check_s
D_STALE_OK = 5  # 1: a field reference and its dip are known (else the stale test returns at once)
D_CAND_NONE = 6  # 1: no stale candidate pending (a "no deviation" verdict then changes nothing)
D_WINDOW = 7  # stale_window_s
D_F = 8  # the reference strength
D_TOL = 9  # the stale test's strength tolerance
D_MIN_FRAC = 10  # stale_min_frac
N_DP = 11

DONE = 0
DECIDE = 1  # a refit or a stale test is due at the returned index (after the sample was taken in)
BLOCK_END = 2  # stopped at a block end (the caller asked for it)

EV_EPISODE_START = 1
EV_EPISODE_END = 2


@njit(cache=True, error_model="numpy")
def _consistent(m, u, bp):
    if bp[B_CHECK] == 0.0:
        return True
    x0 = m[0] - bp[B_OFF]
    x1 = m[1] - bp[B_OFF + 1]
    x2 = m[2] - bp[B_OFF + 2]
    c0 = bp[B_M] * x0 + bp[B_M + 1] * x1 + bp[B_M + 2] * x2
    c1 = bp[B_M + 3] * x0 + bp[B_M + 4] * x1 + bp[B_M + 5] * x2
    c2 = bp[B_M + 6] * x0 + bp[B_M + 7] * x1 + bp[B_M + 8] * x2
    nm = np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
    f = bp[B_F]
    if not abs(nm - f) <= bp[B_TOL_F]:
        return False
    if bp[B_DIP_CHECK] != 0.0:
        un = np.sqrt(u[0] * u[0] + u[1] * u[1] + u[2] * u[2])
        s = -(c0 * u[0] + c1 * u[1] + c2 * u[2]) / max(nm * un, 1e-9)
        s = min(max(s, -1.0), 1.0)
        if not abs(np.degrees(np.arcsin(s)) - bp[B_DIP_DEG]) < bp[B_DIP_TOL]:
            return False
    return True


@njit(cache=True, error_model="numpy")
def _close(j, m, u, buf0, sep2, cos_up):
    d0 = buf0[j, 1] - m[0]
    d1 = buf0[j, 2] - m[1]
    d2 = buf0[j, 3] - m[2]
    if not d0 * d0 + d1 * d1 + d2 * d2 < sep2:
        return False
    return buf0[j, 4] * u[0] + buf0[j, 5] * u[1] + buf0[j, 6] * u[2] > cos_up


@njit(cache=True, error_model="numpy")
def _redundant(t, m, u, buf0, old0, ks, bp, refresh_s):
    """Close (raw µT and gravity direction) to a sample of the block-start buffer, and none of the close
    ones old enough to refresh (older than ``refresh_s``).

    The samples that may be that old within the block are listed in ``old0`` (``K_NOLD0`` of them, see
    :func:`scan`): those are checked first, then any close sample will do — from ``K_HINT``, where the last
    one was found.
    """
    n = int(ks[K_NBUF0])
    if n == 0:
        return False
    sep2 = bp[B_SEP2]
    cos_up = bp[B_COS_UP]
    for k in range(int(ks[K_NOLD0])):
        j = old0[k]
        if not t - buf0[j, 0] <= refresh_s and _close(j, m, u, buf0, sep2, cos_up):
            return False
    start = int(ks[K_HINT])
    if start >= n:
        start = 0
    for k in range(n):
        j = start + k
        if j >= n:
            j -= n
        if _close(j, m, u, buf0, sep2, cos_up):
            ks[K_HINT] = j
            return True
    return False


@njit(cache=True, error_model="numpy")
def _put(buf, j, t, m, u):
    buf[j, 0] = t
    buf[j, 1] = m[0]
    buf[j, 2] = m[1]
    buf[j, 3] = m[2]
    buf[j, 4] = u[0]
    buf[j, 5] = u[1]
    buf[j, 6] = u[2]


@njit(cache=True, error_model="numpy")
def add(t, m, u, buf, ks, sep2, cos_up, refresh_s, size):
    """Offer one sample to the diversity buffer (see ``OnlineCalibrator`` in ``online.py``)."""
    n = int(ks[K_NBUF])
    if n:
        j = -1
        tj = np.inf
        for k in range(n):
            d0 = buf[k, 1] - m[0]
            d1 = buf[k, 2] - m[1]
            d2 = buf[k, 3] - m[2]
            if d0 * d0 + d1 * d1 + d2 * d2 < sep2:
                if buf[k, 4] * u[0] + buf[k, 5] * u[1] + buf[k, 6] * u[2] > cos_up:
                    if buf[k, 0] < tj:
                        tj = buf[k, 0]
                        j = k
        if j >= 0:
            if t - tj > refresh_s:
                _put(buf, j, t, m, u)
                ks[K_VERSION] += 1.0
                ks[K_FIT_NEW] += 1.0
            return
    if n < size:
        _put(buf, n, t, m, u)
        ks[K_NBUF] = n + 1
        ks[K_VERSION] += 1.0
        ks[K_FIT_NEW] += 1.0
        return
    # full: evict the sample closest to another one
    best = np.inf
    jb = 0
    for a in range(n):
        ma = np.inf
        for b in range(n):
            if b != a:
                d0 = buf[a, 1] - buf[b, 1]
                d1 = buf[a, 2] - buf[b, 2]
                d2 = buf[a, 3] - buf[b, 3]
                d = d0 * d0 + d1 * d1 + d2 * d2
                if d < ma:
                    ma = d
        if ma < best:
            best = ma
            jb = a
    _put(buf, jb, t, m, u)
    ks[K_VERSION] += 1.0
    ks[K_FIT_NEW] += 1.0


@njit(cache=True, error_model="numpy")
def coverage(m, n, centre, dirs, cos_lim):
    """Share of the directions ``dirs`` with a sample direction of ``m[:n] − centre`` within the angle whose
    cosine is ``cos_lim``."""
    if n == 0:
        return 0.0
    nd = dirs.shape[0]
    hit = np.zeros(nd, dtype=np.bool_)
    for k in range(n):
        x0 = m[k, 0] - centre[0]
        x1 = m[k, 1] - centre[1]
        x2 = m[k, 2] - centre[2]
        nn = max(np.sqrt(x0 * x0 + x1 * x1 + x2 * x2), 1e-12)
        x0 /= nn
        x1 /= nn
        x2 /= nn
        for d in range(nd):
            if not hit[d] and x0 * dirs[d, 0] + x1 * dirs[d, 1] + x2 * dirs[d, 2] > cos_lim:
                hit[d] = True
    c = 0
    for d in range(nd):
        if hit[d]:
            c += 1
    return c / nd


@njit(cache=True, error_model="numpy")
def cached_coverage(buf, ks, centre, dirs, cos_lim):
    """:func:`coverage` of the buffer, recomputed only when it changed since the last call (the caller sets
    ``ks[K_COV_VERSION] = -1`` when ``centre`` changes)."""
    if ks[K_COV_VERSION] != ks[K_VERSION]:
        n = int(ks[K_NBUF])
        c = np.empty(3)
        if centre[0] != 0.0:
            c[:] = centre[1:4]
        else:
            c[:] = 0.0
            for k in range(n):
                c[0] += buf[k, 1]
                c[1] += buf[k, 2]
                c[2] += buf[k, 3]
            c /= max(n, 1)
        ks[K_COV] = coverage(buf[:, 1:4], n, c, dirs, cos_lim)
        ks[K_COV_VERSION] = ks[K_VERSION]
    return ks[K_COV]


@njit(cache=True, error_model="numpy")
def scan(
    t,
    mag,
    up,
    rate,
    blk_end,
    i,
    ks,
    bp,
    cp,
    buf,
    buf0,
    old0,
    rec,
    sep2_add,
    centre,
    dirs,
    cov_out,
    stop_at_block_end,
    ev_i,
    ev_k,
    dp,
):
    """Take samples ``i, i+1, …`` in; return ``(code, index, n_events)``.

    ``blk_end[i]`` is True for the last sample of a block; there ``cov_out[i]`` gets the buffer's
    coverage about ``centre`` (``centre[0]`` = 1: ``centre[1:4]``, else the buffer mean), recomputed only
    when the buffer changed (``K_COV_VERSION``).  ``DECIDE``: a refit or stale test is due at ``index``
    (the sample itself has been taken in).  ``BLOCK_END``: ``stop_at_block_end`` and ``index`` closed a
    block.  ``DONE``: every sample taken in.  Episode events go to ``ev_i`` / ``ev_k``.  A due refit that
    too few new samples would skip and a due stale test whose first part ends it without a change are
    taken here (:func:`_quiet_decide`, ``dp``), not returned.
    """
    n = len(t)
    refresh_s = cp[C_REFRESH_S]
    rec_dt = cp[C_REC_DT]
    ep_rate = cp[C_EP_RATE]
    size = int(cp[C_SIZE])
    nrec = rec.shape[0]
    n_ev = 0
    while i < n:
        ti = t[i]
        m = mag[i]
        u = up[i]
        if ks[K_IN_BLOCK] == 0.0:
            nb = int(ks[K_NBUF])
            buf0[:nb] = buf[:nb]
            ks[K_NBUF0] = nb
            # the block's last time (unknown: +inf when the block goes on after these samples) bounds which
            # block-start samples can be older than refresh_s at any sample of the block
            t_last = np.inf
            for k in range(i, n):
                if blk_end[k]:
                    t_last = t[k]
                    break
            n_old = 0
            for k in range(nb):
                if t_last - buf[k, 0] > refresh_s:
                    old0[n_old] = k
                    n_old += 1
            ks[K_NOLD0] = n_old
            ks[K_IN_BLOCK] = 1.0
        # rotation-rich episode (smoothed gyro rate)
        ks[K_RATE_EMA] += 0.02 * (rate[i] - ks[K_RATE_EMA])
        if ks[K_EPISODE] == 0.0 and ks[K_RATE_EMA] > ep_rate:
            ks[K_EPISODE] = 1.0
            ks[K_EPISODE_SEEN] = 1.0
            ks[K_FIT_NEW] = np.inf
            ev_i[n_ev] = i
            ev_k[n_ev] = EV_EPISODE_START
            n_ev += 1
        elif ks[K_EPISODE] != 0.0 and ks[K_RATE_EMA] < 0.5 * ep_rate:
            ks[K_EPISODE] = 0.0
            ev_i[n_ev] = i
            ev_k[n_ev] = EV_EPISODE_END
            n_ev += 1
            ks[K_NEXT_REFIT_T] = ti
            ks[K_FIT_NEW] = np.inf
        # decimated ring of recent samples
        if ti - ks[K_LAST_REC_T] >= rec_dt:
            r = int(ks[K_REC_I]) % nrec
            _put(rec, r, ti, m, u)
            ks[K_REC_I] += 1.0
            ks[K_LAST_REC_T] = ti
        if _consistent(m, u, bp) and not _redundant(ti, m, u, buf0, old0, ks, bp, refresh_s):
            add(ti, m, u, buf, ks, sep2_add, bp[B_COS_UP], refresh_s, size)
        if blk_end[i]:
            ks[K_IN_BLOCK] = 0.0
            cov_out[i] = cached_coverage(buf, ks, centre, dirs, cp[C_COS_COV])
        if ti >= ks[K_NEXT_REFIT_T] or (ks[K_STALE_ON] != 0.0 and ti >= ks[K_NEXT_STALE_T]):
            # (while the calibration changed in this block, bp is the block start's: the caller decides)
            if stop_at_block_end or not _quiet_decide(ti, ks, bp, rec, dp):
                return DECIDE, i, n_ev
        if blk_end[i] and stop_at_block_end:
            return BLOCK_END, i, n_ev
        i += 1
    return DONE, i, n_ev


@njit(cache=True, error_model="numpy")
def _quiet_decide(ti, ks, bp, rec, dp):
    """What ``OnlineCalibrator``'s refit and stale test would do at ``ti`` when neither can change anything:
    the refit skipped (fewer than ``min_samples``, or too few new samples while calibrated), the stale test
    ended by its first part (:func:`stale_precheck`: too few samples, or no deviation with no candidate
    pending).  Then their times (and the refit's back-off reset) are advanced as they would be and True is
    returned; else nothing is touched and False returned (the caller runs them)."""
    due_refit = ti >= ks[K_NEXT_REFIT_T]
    due_stale = ks[K_STALE_ON] != 0.0 and ti >= ks[K_NEXT_STALE_T]
    scale = ks[K_FIT_SCALE]
    if due_refit:
        n = int(ks[K_NBUF])
        if n >= dp[D_MIN_SAMPLES]:
            if ks[K_FIT_NEW] == np.inf or n > ks[K_FIT_N]:
                scale = 1.0
            need = min(max(dp[D_MIN_NEW], dp[D_NEW_FRAC] * n) * scale, n)
            if not (ks[K_STALE_ON] != 0.0 and ks[K_FIT_NEW] < need):
                return False  # a refit
    if due_stale and dp[D_STALE_OK] != 0.0:
        pre = stale_precheck(rec, ti, dp[D_WINDOW], bp, dp[D_F], dp[D_TOL], dp[D_MIN_FRAC])
        if pre == STALE_TEST or (pre == STALE_CLEAR and dp[D_CAND_NONE] == 0.0):
            return False
    if due_refit:
        ks[K_NEXT_REFIT_T] = ti + dp[D_PERIOD]
        ks[K_FIT_SCALE] = scale
    if due_stale:
        ks[K_NEXT_STALE_T] = ti + dp[D_STALE_DT]
    return True


# ---- return codes of gravity_fit
FIT_OK = 0
FIT_DEGENERATE = 1
FIT_BAD_INPUT = 2

_HUBER = 2.5


@njit(cache=True, error_model="numpy")
def _huber(r):
    a = abs(r)
    return 1.0 if a <= _HUBER else _HUBER / max(a, 1e-12)


@njit(cache=True, error_model="numpy")
def gravity_fit(m, up, f_guess, strength, s_ref, free, sigma_s, sig2, iterations, prior, sig_f, sig_s):
    """The numbers of :func:`pdr_mag.calibration.online.gravity_aided_offset` (see its docstring and the
    module docstring of ``online.py``): raw samples ``m`` (N, 3), up vectors ``up`` (N, 3).

    Returns ``(code, b, f, s, cov, estimated, rms, dip_rms)`` with ``b`` the offset and ``cov`` the
    (npar, npar) covariance; ``code`` ``FIT_BAD_INPUT`` for NaN, infinite or zero vectors,
    ``FIT_DEGENERATE`` when the linear initial value is rank-deficient.  Raises ``np.linalg.LinAlgError``
    on singular normal equations.
    """
    n = m.shape[0]
    b = np.zeros(3)
    cov = np.zeros((5, 5))
    u = np.empty((n, 3))
    centre = np.zeros(3)
    for i in range(n):
        un = np.sqrt(up[i, 0] * up[i, 0] + up[i, 1] * up[i, 1] + up[i, 2] * up[i, 2])
        if not (np.isfinite(un) and un > 0 and np.isfinite(m[i, 0] + m[i, 1] + m[i, 2])):
            return FIT_BAD_INPUT, b, 0.0, 0.0, cov, free, 0.0, 0.0
        for c in range(3):
            u[i, c] = up[i, c] / un
            centre[c] += m[i, c]
    centre /= n
    mc = np.empty((n, 3))  # centred for conditioning
    for i in range(n):
        for c in range(3):
            mc[i, c] = m[i, c] - centre[c]
    # ---- linear initial value
    p = 5 if free else 4
    a = np.zeros((2 * n, p))
    y = np.empty(2 * n)
    k2 = 2.0 * f_guess
    for i in range(n):
        mm = mc[i, 0] * mc[i, 0] + mc[i, 1] * mc[i, 1] + mc[i, 2] * mc[i, 2]
        mu = mc[i, 0] * u[i, 0] + mc[i, 1] * u[i, 1] + mc[i, 2] * u[i, 2]
        for c in range(3):
            a[i, c] = 2.0 * mc[i, c] / k2 / sigma_s
            a[n + i, c] = u[i, c] / sig2
        if free:
            # unknowns (b, c, s): 2 m·b + c = |m|², u·b − s = m·u   (c = F² − |b|², s = F sin I)
            a[i, 3] = 1.0 / k2 / sigma_s
            a[n + i, 4] = -1.0 / sig2
            y[i] = mm / k2 / sigma_s
            y[n + i] = mu / sig2
        else:
            # unknowns (b, k): 2 m·b − k = |m|² − F²,  u·b = m·u + s
            a[i, 3] = -1.0 / k2 / sigma_s
            y[i] = (mm - strength * strength) / k2 / sigma_s
            y[n + i] = (mu + s_ref) / sig2
    rcond = np.finfo(np.float64).eps * max(2 * n, p)
    sol, _, rank, sv = np.linalg.lstsq(a, y, rcond)
    if rank < p or sv[-1] < 1e-9 * sv[0]:
        return FIT_DEGENERATE, b, 0.0, 0.0, cov, free, 0.0, 0.0
    b[:] = sol[:3]
    if free:
        s = sol[4]
        f = np.sqrt(max(sol[3] + b[0] * b[0] + b[1] * b[1] + b[2] * b[2], 1e-6))
    else:
        f = strength
        s = s_ref
    # ---- Gauss–Newton with Huber weights (optionally F, s free with a prior around the given values)
    f0 = f
    s0 = s
    est = free or prior
    npar = 5 if est else 3
    h = np.zeros((npar, npar))
    g = np.zeros(npar)
    ss = 1.0 / sigma_s
    sd = 1.0 / sig2
    for _ in range(iterations):
        # normal equations, symmetric, accumulated in scalars: strength row a = (−d/|d|, −1, 0)/σ_s,
        # dip row c = (−u, 0, 1)/σ_dip
        h00 = h01 = h02 = h11 = h12 = h22 = 0.0
        h03 = h13 = h23 = h33 = h04 = h14 = h24 = h44 = 0.0
        g0 = g1 = g2 = g3 = g4 = 0.0
        for i in range(n):
            d0 = mc[i, 0] - b[0]
            d1 = mc[i, 1] - b[1]
            d2 = mc[i, 2] - b[2]
            nd = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
            r = (nd - f) * ss
            w = _huber(r)
            a0 = -d0 / nd * ss
            a1 = -d1 / nd * ss
            a2 = -d2 / nd * ss
            wa0 = w * a0
            wa1 = w * a1
            wa2 = w * a2
            h00 += wa0 * a0
            h01 += wa0 * a1
            h02 += wa0 * a2
            h11 += wa1 * a1
            h12 += wa1 * a2
            h22 += wa2 * a2
            g0 += wa0 * r
            g1 += wa1 * r
            g2 += wa2 * r
            h03 -= wa0 * ss
            h13 -= wa1 * ss
            h23 -= wa2 * ss
            h33 += w * ss * ss
            g3 -= w * ss * r
            r = (d0 * u[i, 0] + d1 * u[i, 1] + d2 * u[i, 2] + s) * sd
            w = _huber(r)
            c0 = -u[i, 0] * sd
            c1 = -u[i, 1] * sd
            c2 = -u[i, 2] * sd
            wc0 = w * c0
            wc1 = w * c1
            wc2 = w * c2
            h00 += wc0 * c0
            h01 += wc0 * c1
            h02 += wc0 * c2
            h11 += wc1 * c1
            h12 += wc1 * c2
            h22 += wc2 * c2
            g0 += wc0 * r
            g1 += wc1 * r
            g2 += wc2 * r
            h04 += wc0 * sd
            h14 += wc1 * sd
            h24 += wc2 * sd
            h44 += w * sd * sd
            g4 += w * sd * r
        h[0, 0] = h00
        h[0, 1] = h[1, 0] = h01
        h[0, 2] = h[2, 0] = h02
        h[1, 1] = h11
        h[1, 2] = h[2, 1] = h12
        h[2, 2] = h22
        g[0] = g0
        g[1] = g1
        g[2] = g2
        if est:
            h[0, 3] = h[3, 0] = h03
            h[1, 3] = h[3, 1] = h13
            h[2, 3] = h[3, 2] = h23
            h[3, 3] = h33
            h[0, 4] = h[4, 0] = h04
            h[1, 4] = h[4, 1] = h14
            h[2, 4] = h[4, 2] = h24
            h[4, 4] = h44
            h[3, 4] = h[4, 3] = 0.0
            g[3] = g3
            g[4] = g4
        if prior:
            h[3, 3] += 1.0 / (sig_f * sig_f)
            g[3] += (f - f0) / sig_f / sig_f
            h[4, 4] += 1.0 / (sig_s * sig_s)
            g[4] += (s - s0) / sig_s / sig_s
        step = np.linalg.solve(h, -g)
        b += step[:3]
        if est:
            f += step[3]
            s += step[4]
        if np.max(np.abs(step)) < 1e-6:
            break
    chi = 0.0
    sw1 = 0.0
    swe1 = 0.0
    se2 = 0.0
    for i in range(n):
        d0 = mc[i, 0] - b[0]
        d1 = mc[i, 1] - b[1]
        d2 = mc[i, 2] - b[2]
        e1 = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2) - f
        e2 = d0 * u[i, 0] + d1 * u[i, 1] + d2 * u[i, 2] + s
        r1 = e1 / sigma_s
        r2 = e2 / sig2
        w1 = _huber(r1)
        w2 = _huber(r2)
        chi += w1 * r1 * r1 + w2 * r2 * r2
        sw1 += w1
        swe1 += w1 * e1 * e1
        se2 += e2 * e2
    chi2 = chi / max(2 * n - npar, 1)
    ci = np.linalg.inv(h) * max(chi2, 1.0)
    cov[:npar, :npar] = ci
    rms = np.sqrt(swe1 / max(sw1, 1e-12))
    return FIT_OK, b + centre, f, s, cov, est, rms, np.sqrt(se2 / n)


@njit(cache=True, error_model="numpy")
def contiguous_rows(t, mag, up, rate):
    """``(ok, t, mag, up, rate)``: contiguous copies, ``ok`` when every time, field and up value is finite,
    non-finite rates set to 0 (the rows :func:`scan` takes)."""
    n = len(t)
    ok = True
    tc = np.empty(n)
    mc = np.empty((n, 3))
    uc = np.empty((n, 3))
    rc = np.empty(n)
    for i in range(n):
        tc[i] = t[i]
        ok = ok and np.isfinite(t[i])
        for c in range(3):
            mc[i, c] = mag[i, c]
            uc[i, c] = up[i, c]
            ok = ok and np.isfinite(mag[i, c]) and np.isfinite(up[i, c])
        rc[i] = rate[i] if np.isfinite(rate[i]) else 0.0
    return ok, tc, mc, uc, rc


@njit(cache=True, error_model="numpy")
def recent(rec, rec_i, t_min):
    """Rows of the ring ``rec`` (written cyclically, the next at ``rec_i % len(rec)``: the oldest first)
    with a finite time after ``t_min``, in time order."""
    nrec = rec.shape[0]
    start = int(rec_i) % nrec
    n = 0
    for k in range(nrec):
        tk = rec[(start + k) % nrec, 0]
        if np.isfinite(tk) and tk > t_min:
            n += 1
    out = np.empty((n, rec.shape[1]))
    j = 0
    for k in range(nrec):
        i = (start + k) % nrec
        tk = rec[i, 0]
        if np.isfinite(tk) and tk > t_min:
            out[j] = rec[i]
            j += 1
    return out


# ---- return codes of stale_precheck
STALE_SKIP = 0  # too few recent samples: nothing to do
STALE_CLEAR = 1  # the strength does not deviate: no candidate
STALE_TEST = 2  # deviating: run the fits


@njit(cache=True, error_model="numpy")
def stale_precheck(rec, t, window, bp, f, tol, min_frac):
    """The cheap first part of the stale test on the ring ``rec``: samples newer than ``t − window``, at
    least 40 of them over ``0.6 · window``; share of samples with ``| |M (m − b)| − F | > tol`` overall and
    in the last third of the window (``bp``: ``M`` and ``b`` as in :func:`scan`)."""
    n = 0
    n_last = 0
    dev = 0
    dev_last = 0
    t_min = np.inf
    t_max = -np.inf
    for k in range(rec.shape[0]):
        tk = rec[k, 0]
        if not (np.isfinite(tk) and tk > t - window):
            continue
        n += 1
        t_min = min(t_min, tk)
        t_max = max(t_max, tk)
        x0 = rec[k, 1] - bp[B_OFF]
        x1 = rec[k, 2] - bp[B_OFF + 1]
        x2 = rec[k, 3] - bp[B_OFF + 2]
        c0 = bp[B_M] * x0 + bp[B_M + 1] * x1 + bp[B_M + 2] * x2
        c1 = bp[B_M + 3] * x0 + bp[B_M + 4] * x1 + bp[B_M + 5] * x2
        c2 = bp[B_M + 6] * x0 + bp[B_M + 7] * x1 + bp[B_M + 8] * x2
        d = abs(np.sqrt(c0 * c0 + c1 * c1 + c2 * c2) - f) > tol
        last = tk > t - window / 3
        dev += d
        if last:
            n_last += 1
            dev_last += d
    if n < 40 or t_max - t_min < 0.6 * window:
        return STALE_SKIP
    frac_last = dev_last / n_last if n_last else np.nan
    if frac_last < min_frac or dev / n < 0.5 * min_frac:
        return STALE_CLEAR
    return STALE_TEST
