"""Compiled per-sample loop of :class:`pdr_mag.calibration.online.OnlineCalibrator` (numba, ``cache=True``).

For every magnetometer sample, :func:`scan` runs, in this order:

1. at a block's first sample, the block-start copies: the calibration parameters :data:`CAL` and the
   diversity buffer against which the block's samples are admitted;
2. the rotation-episode tracker: the gyro rate at each sample smoothed over time,
   ``ema += (1 − exp(−Δt / episode_tau_s)) (rate − ema)``; an episode (figure-8) starts above
   ``episode_rate`` and ends below half of it;
3. the ring of recent samples (at most ``stale_rate_hz``) for the stale-calibration test;
4. admission to the diversity buffer (:mod:`pdr_mag.calibration.diversity`): the sample must be consistent
   with the block-start calibration (:func:`consistent`) and not redundant;
5. the schedule: a refit every ``refit_period_s`` (:func:`refit_due`), a stale test every ``stale_check_s``
   (:func:`stale_step`).  Only the work the Python side must do (a fit, the stale test's fits) returns from
   :func:`scan`; a due refit with too few new samples and a stale test whose cheap first part
   (:func:`stale_precheck`) settles it are taken here;
6. at a block's last sample, the buffer's coverage (recomputed only when the buffer or its centre changed:
   it is read at every block end, the buffer changes less often).  About a calibration's offset it is kept
   as counts per direction (:func:`pdr_mag.calibration.diversity.count_directions`), updated by the samples
   that enter and leave the buffer and counted afresh only when the offset or the whole buffer changed;
   about the buffer's mean (no calibration yet), which moves with every sample, it is computed anew.

The calibrator's state lives in records with named fields: :data:`STATE` (what the loop carries from sample
to sample), :data:`CAL` (the calibration in force as the loop reads it, set by the Python side at every
change) and :data:`PARAMS` (settings).  Each is a one-element structured array, read and written by field
name on both sides.
"""

from __future__ import annotations

import sys
from typing import NamedTuple

import numpy as np
from numba import njit

from pdr_mag import _jit_cache
from pdr_mag._records import settings_dtype
from pdr_mag.calibration import diversity
from pdr_mag.calibration.diversity import (
    N_DIRS,
    BlockStart,
    Near,
    buffer_coverage,
    count_directions,
    offer,
    put,
    redundant,
)
from pdr_mag.calibration.online_settings import OnlineSettings
from pdr_mag.fusion import ew

STATE = np.dtype(
    [
        ("rate_ema", np.float64),  # smoothed gyro rate, rad/s
        ("rate_t", np.float64),  # time of the sample it last took in, s
        ("episode", np.bool_),  # a rotation-rich episode is on
        ("episode_seen", np.bool_),  # one was on since the last recalibration request
        ("episode_t1", np.float64),  # when the latest episode ended, s (NaN: on, or none yet)
        ("ring_next", np.int64),  # samples written to the ring so far (the next goes to ring_next % len)
        ("ring_last_t", np.float64),  # time of the latest sample written to it
        ("n_buf", np.int64),  # samples in the diversity buffer
        ("coverage", np.float64),  # the buffer's coverage about the calibration's offset
        ("coverage_stale", np.bool_),  # the buffer or the offset changed since it was computed
        ("next_refit_t", np.float64),  # a refit is due from this time
        ("fit_new", np.float64),  # samples taken into the buffer since the last fit (inf: fit anyway)
        ("fit_n", np.int64),  # buffer size at the last fit
        ("fit_scale", np.float64),  # back-off factor of the new samples the next fit needs
        ("next_stale_t", np.float64),  # a stale test is due from this time
        ("has_candidate", np.bool_),  # a stale test found an offset shift, awaiting confirmation
        ("candidate_t", np.float64),  # when it was found (none pending: when the last one was dropped here)
        ("candidate_shift", np.float64, (3,)),  # the shift δ of the calibrated field, µT
        ("in_block", np.bool_),  # a block is open (its block-start copies are taken)
        ("cal_changed", np.bool_),  # the calibration, or the shift suspected of it, changed in the open block
        ("n_buf0", np.int64),  # samples in the block-start copy of the buffer
        ("n_old0", np.int64),  # block-start samples that may be older than refresh_s within the block
        ("hint", np.int64),  # block-start sample last found close (where the redundancy search starts)
        ("cover_ok", np.bool_),  # cover holds the buffer's direction counts about the offset in force
        ("cover", np.int64, (N_DIRS,)),  # … buffer samples within 30° of each direction (count_directions)
    ]
)

CAL = np.dtype(
    [
        ("check", np.bool_),  # test samples against it (calibrated, not recalibrating, F known)
        ("matrix", np.float64, (3, 3)),  # M = mag_to_imu · soft_iron of M (m − b)
        ("offset", np.float64, (3,)),  # b
        ("strength", np.float64),  # reference F, µT (NaN unknown)
        ("strength_tol", np.float64),  # admission: | |M (m − b)| − F | ≤ add_tol_frac · F
        ("dip_check", np.bool_),  # a reference dip is known
        ("dip_deg", np.float64),  # reference dip, deg
        ("dip_tol_deg", np.float64),  # admission: |dip − reference| < add_dip_tol_deg
        ("sep2", np.float64),  # the buffer's neighbourhood², µT² (online.separation)
        ("has_offset", np.bool_),  # a calibration is in force (coverage centre: its offset)
        ("stale_on", np.bool_),  # stale tests run (calibrated, not recalibrating)
        ("stale_ok", np.bool_),  # … and can: F and the dip are known
        ("stale_tol", np.float64),  # a sample deviates when | |M (m − b)| − F | > this, µT
        ("refit_period", np.float64),  # s between refits (half the setting while uncalibrated)
    ]
)

#: the settings as the loop reads them (:class:`~pdr_mag.calibration.online_settings.OnlineSettings`)
PARAMS = settings_dtype(OnlineSettings)


class Blocks(NamedTuple):
    """Magnetometer samples as :func:`scan` takes them, block by block: times ``t`` (N,) s, raw field ``mag``
    (N, 3) µT, device-frame up ``up`` (N, 3) and north ``north`` (N, 3: the filter's world y axis, NaN
    unknown), gyro ``rate`` (N,) rad/s, and ``block_end`` (N,) bool marking each block's last sample."""

    t: np.ndarray
    mag: np.ndarray
    up: np.ndarray
    north: np.ndarray
    rate: np.ndarray
    block_end: np.ndarray


class Loop(NamedTuple):
    """The calibrator's compiled records and buffers: one-element arrays of :data:`STATE`, :data:`CAL` (in
    force) and :data:`CAL` (at the open block's start), :data:`PARAMS`; the diversity buffer, its copy at
    the block's start, the indices of its samples that may grow old within the block, and the ring of recent
    samples (:mod:`pdr_mag.calibration.diversity` records)."""

    state: np.ndarray
    cal: np.ndarray
    cal0: np.ndarray
    params: np.ndarray
    buf: np.ndarray
    buf0: np.ndarray
    old0: np.ndarray
    ring: np.ndarray


class Found(NamedTuple):
    """What :func:`scan` writes: the buffer's ``coverage`` (N,) at each block end (NaN elsewhere), and its
    rotation-episode events: the sample index ``ev_index`` and kind ``ev_kind`` of each."""

    coverage: np.ndarray
    ev_index: np.ndarray
    ev_kind: np.ndarray


# what scan returns for
DONE = 0  # every sample taken in
REFIT = 1  # a refit is due at the returned sample: the Python side fits, then runs stale_step
STALE_TEST = 2  # the stale test's fits are due at the returned sample
BLOCK_END = 3  # the returned sample ended a block in which the calibration (or its suspected shift) changed

# episode events
EPISODE_START = 1
EPISODE_END = 2

# outcome of stale_precheck / stale_step
STALE_NONE = 0  # not due, or too few recent samples
STALE_CLEAR = 1  # the strength does not deviate
# STALE_TEST (2): deviating, the fits are to run


@njit(cache=True, error_model="numpy")
def scan(blocks, i, resumed, loop, found):
    """Take the samples ``i, i+1, …`` of ``blocks`` (:class:`Blocks`) in (steps 1–6 of the module docstring)
    with the calibrator's records ``loop`` (:class:`Loop`); return ``(code, index, n_events)``.

    At a block's last sample ``found.coverage`` gets the buffer's coverage (a block of skipped samples only
    has none).  Samples with a NaN time, field or up vector are skipped; a NaN rate counts as 0.
    ``resumed``: sample ``i`` was taken in and returned (``REFIT``/``STALE_TEST``) by the previous call; only
    its block end is left.  Episode events go to ``found.ev_index``/``found.ev_kind`` (``n_events`` of them).
    """
    t, mag, up, north, rate, block_end = blocks
    st = loop.state[0]
    c = loop.cal[0]
    cal0 = loop.cal0
    p = loop.params[0]
    buf, buf0, old0, ring = loop.buf, loop.buf0, loop.old0, loop.ring
    n_ev = 0
    while i < len(t):
        ti = t[i]
        m = mag[i]
        u = up[i]
        if resumed:
            resumed = False
        elif _finite(ti, m, u):
            if not st.in_block:
                _start_block(blocks, i, loop)
            rate_i = rate[i] if np.isfinite(rate[i]) else 0.0
            n_ev = _track_episode(i, ti, rate_i, st, p, found, n_ev)
            if ti - st.ring_last_t >= p.ring_dt:
                put(ring, st.ring_next % len(ring), ti, m, u, north[i])
                st.ring_next += 1
                st.ring_last_t = ti
            if consistent(m, u, cal0[0]):
                start = BlockStart(buf0, st.n_buf0, old0, st.n_old0)
                j = redundant(ti, m, u, start, st.hint, Near(cal0[0].sep2, p.cos_up, p.refresh_s))
                if j >= 0:
                    st.hint = j
                else:
                    near = Near(c.sep2, p.cos_up, p.refresh_s)
                    slot = offer(ti, m, u, buf, st.n_buf, p.buffer_size, near)
                    if slot >= 0:
                        _keep(st, c, buf, slot, ti, m, u, north[i])
                        st.fit_new += 1.0
                        st.coverage_stale = True
            if ti >= st.next_refit_t and refit_due(ti, st, c, p):
                return REFIT, i, n_ev
            if stale_step(ti, st, c, p, ring) == STALE_TEST:
                return STALE_TEST, i, n_ev
        if block_end[i] and st.in_block:
            st.in_block = False
            found.coverage[i] = current_coverage(st, c, buf)
            if st.cal_changed:
                return BLOCK_END, i, n_ev
        i += 1
    return DONE, i, n_ev


@njit(cache=True, error_model="numpy")
def _finite(t, m, u):
    """A sample with a finite time, field and up vector (others are skipped)."""
    return (
        np.isfinite(t)
        and np.isfinite(m[0])
        and np.isfinite(m[1])
        and np.isfinite(m[2])
        and np.isfinite(u[0])
        and np.isfinite(u[1])
        and np.isfinite(u[2])
    )


@njit(cache=True, error_model="numpy")
def _start_block(blocks, i, loop):
    """Step 1, at sample ``i``: copy the calibration and the buffer; list the buffer samples that can be
    older than ``refresh_s`` before the block's last time (unknown — the block goes on after these samples,
    or its last time is NaN —: +inf)."""
    t, block_end = blocks.t, blocks.block_end
    st = loop.state[0]
    p = loop.params[0]
    buf, buf0, old0 = loop.buf, loop.buf0, loop.old0
    loop.cal0[0] = loop.cal[0]
    n = st.n_buf
    for k in range(n):
        buf0[k] = buf[k]
    st.n_buf0 = n
    t_last = np.inf
    for k in range(i, len(t)):
        if block_end[k]:
            if np.isfinite(t[k]):
                t_last = t[k]
            break
    n_old = 0
    for k in range(n):
        if t_last - buf[k].t > p.refresh_s:
            old0[n_old] = k
            n_old += 1
    st.n_old0 = n_old
    st.in_block = True
    st.cal_changed = False


@njit(cache=True, error_model="numpy")
def _track_episode(i, ti, rate, st, p, found, n_ev):
    """Step 2; a start or an end makes the next refit fit, an end makes it due now (an event in ``found``,
    the ``n_ev``-th)."""
    ev_index, ev_kind = found.ev_index, found.ev_kind
    if np.isfinite(st.rate_t):  # (the first sample: no time since, the average stays at rest)
        st.rate_ema += ew.ew_alpha(ti - st.rate_t, p.episode_tau_s) * (rate - st.rate_ema)
    st.rate_t = ti
    if not st.episode and st.rate_ema > p.episode_rate:
        st.episode = True
        st.episode_seen = True
        st.episode_t1 = np.nan
        st.fit_new = np.inf
        ev_index[n_ev] = i
        ev_kind[n_ev] = EPISODE_START
        return n_ev + 1
    if st.episode and st.rate_ema < 0.5 * p.episode_rate:
        st.episode = False
        st.episode_t1 = ti
        st.next_refit_t = ti
        st.fit_new = np.inf
        ev_index[n_ev] = i
        ev_kind[n_ev] = EPISODE_END
        return n_ev + 1
    return n_ev


@njit(cache=True, error_model="numpy")
def _calibrated(m, c):
    """``M (m − b)`` of the calibration record ``c``."""
    x0 = m[0] - c.offset[0]
    x1 = m[1] - c.offset[1]
    x2 = m[2] - c.offset[2]
    a = c.matrix
    return (
        a[0, 0] * x0 + a[0, 1] * x1 + a[0, 2] * x2,
        a[1, 0] * x0 + a[1, 1] * x1 + a[1, 2] * x2,
        a[2, 0] * x0 + a[2, 1] * x1 + a[2, 2] * x2,
    )


@njit(cache=True, error_model="numpy")
def deviates(c0, c1, c2, u, strength, tol, dip_check, dip_deg, dip_tol):
    """Whether a calibrated field ``(c0, c1, c2)`` deviates from the reference: its strength more than ``tol``
    from F, or (with a reference dip) its dip ``asin(−c·u / |c||u|)``, against the up vector ``u``, more than
    ``dip_tol`` degrees from the reference — with the admission bands, a sample the buffer refuses
    (:func:`consistent`); with the stale test's, one it counts (a device-fixed shift moves both, in
    proportions that depend on the pose: one may stay within its band while the other does not)."""
    nm = np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
    if abs(nm - strength) > tol:
        return True
    if not dip_check:
        return False
    un = np.sqrt(u[0] * u[0] + u[1] * u[1] + u[2] * u[2])
    s = min(max(-(c0 * u[0] + c1 * u[1] + c2 * u[2]) / max(nm * un, 1e-9), -1.0), 1.0)
    return abs(np.degrees(np.arcsin(s)) - dip_deg) > dip_tol


@njit(cache=True, error_model="numpy")
def deviating(mag_cal, up, strength, tol, dip_check, dip_deg, dip_tol):
    """:func:`deviates` of each calibrated field of ``mag_cal`` (N × 3) with its up vector (N × 3)."""
    out = np.empty(mag_cal.shape[0], dtype=np.bool_)
    for k in range(mag_cal.shape[0]):
        c0, c1, c2 = mag_cal[k, 0], mag_cal[k, 1], mag_cal[k, 2]
        out[k] = deviates(c0, c1, c2, up[k], strength, tol, dip_check, dip_deg, dip_tol)
    return out


@njit(cache=True, error_model="numpy")
def consistent(m, u, c):
    """Whether a sample agrees with the calibration ``c`` (always, when ``c.check`` is off): strength within
    ``strength_tol`` of F, dip ``asin(−M(m − b)·u / |M(m − b)|)`` within ``dip_tol_deg`` of the reference."""
    if not c.check:
        return True
    c0, c1, c2 = _calibrated(m, c)
    return not deviates(c0, c1, c2, u, c.strength, c.strength_tol, c.dip_check, c.dip_deg, c.dip_tol_deg)


@njit(cache=True, error_model="numpy")
def _keep(st, c, buf, j, t, m, u, n):
    """Put the sample in slot ``j`` of the buffer (``n_buf``: appended), the direction counts about the
    offset following the sample that leaves and the one that enters while they are valid."""
    if st.cover_ok and c.has_offset:
        if j < st.n_buf:
            count_directions(buf[j].m, c.offset, st.cover, -1)
        count_directions(m, c.offset, st.cover, 1)
    put(buf, j, t, m, u, n)
    st.n_buf = max(st.n_buf, j + 1)


@njit(cache=True, error_model="numpy")
def current_coverage(st, c, buf):
    """The buffer's coverage about the calibration's offset (the buffer mean without one)."""
    if st.coverage_stale:
        if c.has_offset:
            if not st.cover_ok:
                st.cover[:] = 0
                for k in range(st.n_buf):
                    count_directions(buf[k].m, c.offset, st.cover, 1)
                st.cover_ok = True
            hit = 0
            for d in range(N_DIRS):
                if st.cover[d] > 0:
                    hit += 1
            st.coverage = hit / N_DIRS
        else:
            st.coverage = buffer_coverage(buf, st.n_buf, False, c.offset)
        st.coverage_stale = False
    return st.coverage


@njit(cache=True, error_model="numpy")
def refit_due(ti, st, c, p):
    """The refit schedule at a due time ``ti``: the next one a period later; True when this one fits.

    It fits when the buffer holds ``min_samples`` and — while calibrated and not recalibrating — took in at
    least ``max(refit_min_new, refit_new_frac · n) · scale`` new samples (at most n) since the last fit.
    ``scale`` grows by ``refit_backoff`` at every fit and starts over at 1 when the buffer grew or an event
    (a change of calibration, an episode's start or end, a cleared buffer: ``fit_new = inf``) happened.
    """
    st.next_refit_t = ti + c.refit_period
    n = st.n_buf
    if n < p.min_samples:
        return False
    if st.fit_new == np.inf or n > st.fit_n:
        st.fit_scale = 1.0
    need = min(max(p.refit_min_new, p.refit_new_frac * n) * st.fit_scale, n)
    if c.stale_on and st.fit_new < need:
        return False
    st.fit_new = 0.0
    st.fit_n = n
    st.fit_scale *= p.refit_backoff
    return True


@njit(cache=True, error_model="numpy")
def stale_step(ti, st, c, p, ring):
    """The stale test's schedule at ``ti`` and its cheap first part: ``STALE_TEST`` when its fits are to run.

    Due every ``stale_check_s`` while ``c.stale_on``; a window whose strength does not deviate
    (:func:`stale_precheck`) drops a pending candidate (the calibration's uncertainty in the filter changes
    with it: the block ends there)."""
    if not (c.stale_on and ti >= st.next_stale_t):
        return STALE_NONE
    st.next_stale_t = ti + p.stale_check_s
    if not c.stale_ok:
        return STALE_NONE
    verdict = stale_precheck(ring, ti, c, p)
    if verdict == STALE_CLEAR and st.has_candidate:
        st.has_candidate = False
        st.candidate_t = ti
        st.cal_changed = True
    return verdict


#: The stale test's dip band over the buffer's admission band (``add_dip_tol_deg``): twice it, as the
#: consensus fit counts a walking phone's tilt (known to a few degrees).
STALE_DIP_FACTOR = 2.0


@njit(cache=True, error_model="numpy")
def step_start_index(mag_cal, up, strength, tol, dip_check, dip_deg, dip_tol, min_frac, min_n):
    """:func:`pdr_mag.calibration.stale.step_start`'s search (−1: none): the share of samples that
    :func:`deviates` after ``j`` less the share before it, largest over ``min_n ≤ j ≤ n − min_n``
    among the ``j`` with the share after at least ``min_frac`` and before below half of it."""
    n = mag_cal.shape[0]
    if n < 2 * min_n:
        return -1
    d = deviating(mag_cal, up, strength, tol, dip_check, dip_deg, dip_tol)
    cum = np.zeros(n + 1)  # deviating samples before each index
    for k in range(n):
        cum[k + 1] = cum[k] + d[k]
    best, best_gain = -1, -np.inf
    for j in range(min_n, n - min_n + 1):
        before = cum[j] / j
        after = (cum[n] - cum[j]) / (n - j)
        if after >= min_frac and before < 0.5 * min_frac and after - before > best_gain:
            best, best_gain = j, after - before
    return best


@njit(cache=True, error_model="numpy")
def stale_precheck(ring, ti, c, p):
    """The ring's samples newer than ``ti − stale_window_s`` (at least 40, spanning 0.6 of the window):
    ``STALE_TEST`` when the share deviating (:func:`deviates`: from F by more than ``c.stale_tol``, or
    from the reference dip by more than :data:`STALE_DIP_FACTOR` × ``dip_tol_deg``) reaches ``stale_min_frac``
    in the window's last third and half of that overall; ``STALE_CLEAR`` otherwise; ``STALE_NONE`` when the
    samples are too few."""
    window = p.stale_window_s
    n = 0
    n_last = 0
    dev = 0
    dev_last = 0
    t_min = np.inf
    t_max = -np.inf
    for k in range(len(ring)):
        tk = ring[k].t
        if not (np.isfinite(tk) and tk > ti - window):
            continue
        n += 1
        t_min = min(t_min, tk)
        t_max = max(t_max, tk)
        c0, c1, c2 = _calibrated(ring[k].m, c)
        d = deviates(c0, c1, c2, ring[k].u, c.strength, c.stale_tol, c.dip_check, c.dip_deg,
                     STALE_DIP_FACTOR * c.dip_tol_deg)
        dev += d
        if tk > ti - window / 3:
            n_last += 1
            dev_last += d
    if n < 40 or t_max - t_min < 0.6 * window:
        return STALE_NONE
    frac_last = dev_last / n_last if n_last else np.nan
    if frac_last < p.stale_min_frac or dev / n < 0.5 * p.stale_min_frac:
        return STALE_CLEAR
    return STALE_TEST


@njit(cache=True, error_model="numpy")
def recent(ring, ring_next, t_min):
    """The ring's samples after ``t_min``, oldest first (it is written cyclically, the next at ``ring_next %
    len(ring)``: the oldest)."""
    n = len(ring)
    start = ring_next % n
    keep = np.zeros(n, dtype=np.bool_)
    for k in range(n):
        tk = ring[(start + k) % n].t
        keep[k] = np.isfinite(tk) and tk > t_min
    out = np.empty(np.count_nonzero(keep), dtype=ring.dtype)
    j = 0
    for k in range(n):
        if keep[k]:
            out[j] = ring[(start + k) % n]
            j += 1
    return out


@njit(cache=True, error_model="numpy")
def stale_now(ti, loop):
    """:func:`stale_step` on the calibrator's records (the Python side's entry, after a refit)."""
    return stale_step(ti, loop.state[0], loop.cal[0], loop.params[0], loop.ring)


@njit(cache=True, error_model="numpy")
def coverage_now(loop):
    """:func:`current_coverage` on the calibrator's records (the Python side's entry)."""
    return current_coverage(loop.state[0], loop.cal[0], loop.buf)


# numba's cache checks a kernel against its own file only: empty the caches when diversity.py or ew.py changed
_jit_cache.refresh_if_changed((sys.modules[__name__], diversity, ew), "online")
