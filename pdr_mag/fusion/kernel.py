"""The run loop of the fusion filter: samples in, output rows out (numba, ``cache=True``).

:func:`run` dispatches a merged, time-ordered chunk sample by sample to :func:`~pdr_mag.fusion.accel.
accel_step`, :func:`~pdr_mag.fusion.gyro.gyro_step` and :func:`~pdr_mag.fusion.mag.mag_step`, all of which
read and write one record of :data:`~pdr_mag.fusion.state.STATE`; everything carried from one sample to the
next is in that record, so a chunked run equals a single run.

Output rows: one per gyroscope sample once the tilt is known, decimated to a grid of ``out_dt_s`` anchored
at the first such sample (a row at the first gyroscope sample at or after each grid time; ``out_dt_s = 0``
gives every sample).  A row holds the attitude, ``heading_std_deg = degrees(√max((P + U)[δθ_z, δθ_z],
g Σ_b gᵀ))`` (:func:`calibration_floor`), whether
the magnetometer corrected the heading and whether the interference flag was up since the previous row,
and the diagnostics (:data:`~pdr_mag.fusion.rows.DIAG_NAMES`).
"""

from __future__ import annotations

import sys

import numpy as np
from numba import njit

from pdr_mag import _jit_cache
from pdr_mag.fusion import accel, detectors, eskf, gyro, kinds, mag, rows, state
from pdr_mag.fusion.accel import accel_step
from pdr_mag.fusion.eskf import heading_var_u
from pdr_mag.fusion.gyro import PREDICT_WORK, gyro_step
from pdr_mag.fusion.kinds import ACCEL, GYRO, MAG
from pdr_mag.fusion.mag import mag_step, offset_heading_var
from pdr_mag.fusion.quat import heading_deg
from pdr_mag.fusion.rows import COL, FLAG
from pdr_mag.fusion.state import TH_Z


@njit(cache=True, error_model="numpy")
def run(kind, t, xyz, allowed, st, p, out, k0):
    """Process a chunk (``kind``: :mod:`pdr_mag.fusion.kinds`) with the state record ``st``, writing rows
    into ``out`` (:class:`~pdr_mag.fusion.rows.Rows`) from row ``k0`` on; returns the number of rows
    written."""
    R = np.empty((3, 3))
    work = np.empty(1, dtype=PREDICT_WORK)  # gyro_step's scratch
    n_out = k0
    for i in range(len(t)):
        k = kind[i]
        x, y, z = xyz[i, 0], xyz[i, 1], xyz[i, 2]
        ti = t[i]
        if k == ACCEL:
            if np.isfinite(x) and np.isfinite(y) and np.isfinite(z):
                accel_step(st, R, x, y, z, ti, p)
        elif k == MAG:
            mag_step(st, R, x, y, z, ti, allowed[i], p)
        elif k == GYRO:
            if not (np.isfinite(x) and np.isfinite(y) and np.isfinite(z)):
                continue
            gyro_step(st, R, work, x, y, z, ti, p)
            if st.init == 0:
                continue
            nxt = st.t_next_out
            if np.isfinite(nxt) and ti < nxt:
                continue
            if p.out_dt_s > 0:
                if not np.isfinite(nxt):
                    nxt = ti
                while nxt <= ti:
                    nxt += p.out_dt_s
                st.t_next_out = nxt
            _write_row(st, ti, out, n_out, p)
            n_out += 1
    return n_out - k0


@njit(cache=True, error_model="numpy")
def calibration_floor(f, n, suspect_cov):
    """The least heading variance the calibration in force allows at row ``n`` of the float columns ``f``
    (:class:`~pdr_mag.fusion.rows.Rows`), rad²: ``g ΔΔᵀ gᵀ`` with g the heading gradient at the latest usable
    sample (``cal_g``) and Δ an offset shift the stale test suspects and has yet to confirm (``suspect_cov``
    = ``ΔΔᵀ``), plus the row's ``var_cal``; 0 before the first heading.  The row holds ``var_cal`` and g
    (:data:`~pdr_mag.fusion.rows.VAR_PARTS`, written by :func:`_write_row`).  The suspected shift is in the
    std only, not in the filter's weights: most candidates are a building's field that the test then drops
    (on the shared recordings about one in ten is confirmed), and until then the heading is what the
    calibration in force makes it.  ``var_cal`` is 0 with the offset states (``mag.offset_states``: the
    filter carries the calibration's offset error in ``P``); without them it is ``g Σ_b gᵀ``, ``Σ_b`` the
    offset covariance in force — the filter then carries that error in c, whose Gauss–Markov model lets it
    average out over a few ``mag.error_tau_s`` or quarter turns, and the floor restores what does not."""
    g = (f[COL.cal_gx, n], f[COL.cal_gy, n], f[COL.cal_gz, n])
    return f[COL.var_cal, n] + offset_heading_var(g, suspect_cov)


@njit(cache=True, error_model="numpy")
def _write_std(f, n, suspect_cov):
    """Row ``n``'s ``heading_std_deg`` from its variance parts and the suspected shift's ``suspect_cov``."""
    var = min(max(f[COL.var_filter, n], calibration_floor(f, n, suspect_cov)), np.pi**2)
    f[COL.heading_std_deg, n] = np.degrees(np.sqrt(max(var, 0.0)))


@njit(cache=True, error_model="numpy")
def _write_row(st, ti, out, n, p):
    """Row ``n`` of ``out`` (:class:`~pdr_mag.fusion.rows.Rows`) from the state at gyroscope time ti; resets
    the since-last-row flags."""
    f = out.floats
    f[COL.t, n] = ti
    for c in range(4):
        out.q[n, c] = st.q[c]
    f[COL.var_filter, n] = st.P[TH_Z, TH_Z] + heading_var_u(st)
    floor = st.init >= 2  # no floor before the first heading
    # an offset error the filter does not carry (without the offset states) floors the std
    carried = p.mag.offset_states
    f[COL.var_cal, n] = offset_heading_var(st.cal_g, st.cal_cov) if floor and not carried else 0.0
    f[COL.cal_gx, n] = st.cal_g[0] if floor else 0.0
    f[COL.cal_gy, n] = st.cal_g[1] if floor else 0.0
    f[COL.cal_gz, n] = st.cal_g[2] if floor else 0.0
    _write_std(f, n, st.suspect_cov)
    out.flags[FLAG.mag_used, n] = st.mag_used
    out.flags[FLAG.interference, n] = st.det.flag or st.interference_seen
    st.mag_used = False
    st.interference_seen = False
    f[COL.gyro_heading_deg, n] = heading_deg(st.q_gyro) if st.init >= 2 else np.nan
    detectors.write(st.det, f, n, COL)
    f[COL.interference_score, n] = st.det.score
    f[COL.gyro_bias_x, n] = st.b[0]
    f[COL.gyro_bias_y, n] = st.b[1]
    f[COL.gyro_bias_z, n] = st.b[2]
    f[COL.heading_reset_deg, n] = np.degrees(st.reset_jump) if st.reset_jump != 0.0 else np.nan
    f[COL.mag_offset_error_x, n] = st.offset[0]
    f[COL.mag_offset_error_y, n] = st.offset[1]
    f[COL.mag_offset_error_z, n] = st.offset[2]
    st.reset_jump = 0.0


@njit(cache=True, error_model="numpy")
def run_cut(span, state, params, cuts, snaps, out):
    """:func:`run` over the chunk ``span`` (:class:`pdr_mag.fusion.core.Span`) with a copy of the state put
    in ``snaps[j]`` before sample ``cuts[j]`` (increasing); then each row's quaternion sign made
    non-negative in w and its heading's ``arctan2`` arguments written (``h_y``, ``h_x``).  ``state`` and
    ``params`` are one-element arrays of :data:`~pdr_mag.fusion.state.STATE` and
    :data:`~pdr_mag.fusion.state.PARAMS`; ``out`` the rows (:class:`~pdr_mag.fusion.rows.Rows`).  Returns the
    number of rows (the rows of one :func:`run` call per piece: the same rows, cut or not)."""
    kind, t, xyz, allowed = span.kind, span.t, span.xyz, span.mag_allowed
    st = state[0]
    p = params[0]
    n = len(t)
    k = 0
    a = 0
    for j in range(len(cuts) + 1):
        b = cuts[j] if j < len(cuts) else n
        if b > a or j == len(cuts):
            k += run(kind[a:b], t[a:b], xyz[a:b], allowed[a:b], st, p, out, k)
        if j < len(cuts):
            snaps[j] = st
        a = b
    q = out.q
    for i in range(k):
        s = -1.0 if q[i, 0] < 0 else 1.0
        for c in range(4):
            q[i, c] = q[i, c] * s
        w = q[i, 0]
        x = q[i, 1]
        y = q[i, 2]
        z = q[i, 3]
        out.floats[COL.h_y, i] = 2.0 * (x * y - w * z)
        out.floats[COL.h_x, i] = 1.0 - 2.0 * (x * x + z * z)
    return k


@njit(cache=True, error_model="numpy")
def rewrite_std(state, out, lo, hi):
    """``heading_std_deg`` of the rows ``lo … hi − 1`` of ``out`` anew, with the suspected shift of the
    one-element ``state`` (its ``suspect_cov``), from the variance parts the rows keep."""
    S = state[0].suspect_cov
    for n in range(lo, hi):
        _write_std(out.floats, n, S)


@njit(cache=True, error_model="numpy")
def fix_from_history(state, params, r, var, span, t):
    """:func:`pdr_mag.fusion.mag.history_fix` on the one-element state and params arrays."""
    mag.history_fix(state[0], r, var, span, t, params[0])


@njit(cache=True, error_model="numpy")
def refresh_unmodelled(state, params):
    """c's unmodelled variance ``u_var`` (:func:`pdr_mag.fusion.gyro.unmodelled_var`) anew, after its inputs
    were set outside the loop (:meth:`pdr_mag.fusion.FusionCore.seed_flag_share`)."""
    s = state[0]
    s.u_var = gyro.unmodelled_var(s, params[0])


# numba checks a cached function against its own file only: empty the caches when any of these changed
_jit_cache.refresh_if_changed(
    (sys.modules[__name__], *detectors.SOURCES, kinds, state, rows, eskf, gyro, accel, mag), "fusion"
)
