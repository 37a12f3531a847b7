"""Compiled helpers of :class:`pdr_mag.pipeline.HeadingPipeline` (numba, ``cache=True``).

* :func:`in_order`, :func:`repeated` and :func:`take_merged`: a push's checks (time order, a stalled
  sensor's repeated values), and the three input streams' pending samples before a time taken and merged
  in time order;
* :func:`filter_input`: the merged samples as the fusion core takes them, and where each block starts;
  :func:`rows_coverage`;
* :func:`mag_context`: what the online calibrator is given with each magnetometer sample of the merged
  stream — the up vector of the filter's latest output row at or before it (the third row of ``rot_wd``
  from the row's quaternion), or, where the filter has none yet, the direction of the latest accelerometer
  sample; and the norm of the latest gyroscope sample; :func:`carry_over` keeps what the next chunk's
  first samples need of this one.

Loops, because a poll of a second or two is too short for a sequence of numpy calls to pay off.
"""

from __future__ import annotations

import sys

import numpy as np
from numba import njit

from pdr_mag import _jit_cache
from pdr_mag.fusion import kinds
from pdr_mag.fusion.kinds import ACCEL, GYRO, MAG

#: A magnetometer sample with its context: time, raw field (µT), the device-frame up and north axes of the
#: filter's attitude (north NaN where the up vector comes from the accelerometer) and gyro rate (rad/s).
MAG_ROW = np.dtype(
    [
        ("t", np.float64),
        ("m", np.float64, (3,)),
        ("up", np.float64, (3,)),
        ("north", np.float64, (3,)),
        ("rate", np.float64),
    ]
)

#: What the context needs from before a chunk: the latest output row's quaternion (w-first), the latest
#: accelerometer and gyroscope samples (NaN: none yet).
CARRY = np.dtype([("q", np.float64, (4,)), ("accel", np.float64, (3,)), ("gyro", np.float64, (3,))])


@njit(cache=True, error_model="numpy")
def repeated(xyz, last_xyz, repeats, out):
    """``out[k]``: whether ``xyz[k]`` is the same value on all three axes as the sample before it (the
    first's: ``last_xyz``) for the third time or more in a row, ``repeats`` being how many in a row repeated
    ``last_xyz`` so far (:meth:`pdr_mag.pipeline.streams.PendingStream.stale`).  Returns the run at the
    end."""
    px, py, pz = last_xyz[0], last_xyz[1], last_xyz[2]
    for k in range(len(xyz)):
        x, y, z = xyz[k, 0], xyz[k, 1], xyz[k, 2]
        repeats = repeats + 1 if (x == px and y == py and z == pz) else 0
        out[k] = repeats >= 2
        px, py, pz = x, y, z
    return repeats


@njit(cache=True, error_model="numpy")
def in_order(t, xyz, after):
    """Whether the times are finite and strictly increasing from above ``after`` and every value is finite
    (a push's common case: nothing to drop)."""
    prev = after
    for i in range(len(t)):
        if not (t[i] > prev and np.isfinite(t[i])):
            return False
        if not (np.isfinite(xyz[i, 0]) and np.isfinite(xyz[i, 1]) and np.isfinite(xyz[i, 2])):
            return False
        prev = t[i]
    return True


@njit(cache=True, error_model="numpy")
def longest_interval(t, after):
    """The longest interval, s, between consecutive times of ``t`` (increasing, at least one) and from
    ``after`` to ``t[0]`` (``after`` −inf: that one left out): what a push's gap check needs first."""
    longest = t[0] - after if np.isfinite(after) else 0.0
    for i in range(1, len(t)):
        d = t[i] - t[i - 1]
        if d > longest:
            longest = d
    return longest


@njit(cache=True, error_model="numpy")
def take_merged(streams, t_end):
    """The pending rows of the three streams (``streams``: their :class:`~pdr_mag.pipeline.streams.Pending`
    records, accelerometer, gyroscope, magnetometer) that are before ``t_end``, merged: ``(kind, t, xyz)``
    and each stream's new ``lo``."""
    a, g, m = streams
    ka = a.lo + np.searchsorted(a.t[a.lo : a.hi], t_end)
    kg = g.lo + np.searchsorted(g.t[g.lo : g.hi], t_end)
    km = m.lo + np.searchsorted(m.t[m.lo : m.hi], t_end)
    kind, t, xyz = _merge(a.t[a.lo : ka], a.xyz[a.lo : ka], g.t[g.lo : kg], g.xyz[g.lo : kg], m.t[m.lo : km],
                          m.xyz[m.lo : km])  # fmt: skip
    return kind, t, xyz, (ka, kg, km)


@njit(cache=True, error_model="numpy")
def _merge(t0, x0, t1, x1, t2, x2):
    """Three time-ordered streams merged into ``(kind, t, xyz)``, ``kind`` the stream (``ACCEL``, ``GYRO``,
    ``MAG``); on equal times in that order."""
    n0 = len(t0)
    n1 = len(t1)
    n2 = len(t2)
    kind = np.empty(n0 + n1 + n2, dtype=np.int8)
    t = np.empty(n0 + n1 + n2)
    xyz = np.empty((n0 + n1 + n2, 3))
    i0 = i1 = i2 = 0
    for k in range(len(t)):
        if i0 < n0 and (i1 == n1 or t0[i0] <= t1[i1]) and (i2 == n2 or t0[i0] <= t2[i2]):
            kind[k] = ACCEL
            t[k] = t0[i0]
            xyz[k] = x0[i0]
            i0 += 1
        elif i1 < n1 and (i2 == n2 or t1[i1] <= t2[i2]):
            kind[k] = GYRO
            t[k] = t1[i1]
            xyz[k] = x1[i1]
            i1 += 1
        else:
            kind[k] = MAG
            t[k] = t2[i2]
            xyz[k] = x2[i2]
            i2 += 1
    return kind, t, xyz


@njit(cache=True, error_model="numpy")
def filter_input(kind, xyz, blk, offset, calibrated):
    """``(data, allowed, n_gyro, starts)``: the merged samples with the offset ``b`` taken off the
    magnetometer's (NaN without a calibration), the flags allowing its use, the number of gyroscope
    samples, and the index of each block's first sample (``blk``: each sample's block)."""
    n = len(kind)
    data = np.empty((n, 3))
    allowed = np.empty(n, dtype=np.bool_)
    starts = np.empty(n, dtype=np.intp)
    n_gyro = 0
    n_blocks = 0
    for i in range(n):
        if i == 0 or blk[i] != blk[i - 1]:
            starts[n_blocks] = i
            n_blocks += 1
        allowed[i] = calibrated
        n_gyro += kind[i] == GYRO
        for c in range(3):
            if kind[i] != MAG:
                data[i, c] = xyz[i, c]
            elif calibrated:
                data[i, c] = xyz[i, c] - offset[c]
            else:
                data[i, c] = np.nan
    return data, allowed, n_gyro, starts[:n_blocks]


@njit(cache=True, error_model="numpy")
def rows_coverage(row_t, block_s, closed_blk, closed_cov, before):
    """Each output row's buffer coverage: the one after the last of the closed blocks ``closed_blk``
    (increasing) before the row's own block, ``before`` where there is none."""
    out = np.empty(len(row_t))
    k = 0
    c = before
    for r in range(len(row_t)):
        b = np.floor(row_t[r] / block_s)
        while k < len(closed_blk) and closed_blk[k] < b:
            c = closed_cov[k]
            k += 1
        out[r] = c
    return out


@njit(cache=True, error_model="numpy")
def _norm(v):
    return np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])


@njit(cache=True, error_model="numpy")
def _direction(v, out):
    nn = max(_norm(v), 1e-9)
    out[0] = v[0] / nn
    out[1] = v[1] / nn
    out[2] = v[2] / nn


@njit(cache=True, error_model="numpy")
def _axes(q, up, north):
    """Device-frame up and north (world z and y) axes of the w-first quaternion ``q``: the third and second
    rows of ``rot_wd``."""
    w = q[0]
    x = q[1]
    y = q[2]
    z = q[3]
    up[0] = 2 * (x * z - w * y)
    up[1] = 2 * (y * z + w * x)
    up[2] = 1 - 2 * (x * x + y * y)
    north[0] = 2 * (x * y + w * z)
    north[1] = 1 - 2 * (x * x + z * z)
    north[2] = 2 * (y * z - w * x)


@njit(cache=True, error_model="numpy")
def mag_context(kind, t, xyz, row_t, row_q, carry, before, block_s):
    """:data:`MAG_ROW` records: ``before``'s, then those of the magnetometer samples (``kind == MAG``) of a
    merged chunk, given its filter output rows (``row_t``, ``row_q``) and the :data:`CARRY` record from
    before the chunk; and each record's block, ``floor(t / block_s)``."""
    n_mag = 0
    for i in range(len(t)):
        if kind[i] == MAG:
            n_mag += 1
    out = np.empty(len(before) + n_mag, dtype=MAG_ROW)
    for k in range(len(before)):
        out[k] = before[k]
    c = carry[0]
    k = len(before)
    r = 0  # output rows with time ≤ the current sample
    a = -1  # latest accelerometer / gyroscope sample so far (the merge puts ties before the magnetometer)
    g = -1
    for i in range(len(t)):
        if kind[i] == ACCEL:
            a = i
        elif kind[i] == GYRO:
            g = i
        else:
            row = out[k]
            row.t = t[i]
            row.m[:] = xyz[i]
            while r < len(row_t) and row_t[r] <= t[i]:
                r += 1
            if r > 0:
                _axes(row_q[r - 1], row.up, row.north)
            else:
                _axes(c.q, row.up, row.north)
            if not np.isfinite(row.up[0]):
                if a >= 0:
                    _direction(xyz[a], row.up)
                else:
                    _direction(c.accel, row.up)
            row.rate = _norm(xyz[g]) if g >= 0 else _norm(c.gyro)
            k += 1
    blk = np.empty(len(out))
    for k in range(len(out)):
        blk[k] = np.floor(out[k].t / block_s)
    return out, blk


@njit(cache=True, error_model="numpy")
def carry_over(kind, xyz, row_q, carry):
    """Update the :data:`CARRY` record with the last output row and the last accelerometer and gyroscope
    samples of a chunk."""
    c = carry[0]
    if len(row_q):
        c.q[:] = row_q[len(row_q) - 1]
    a = -1
    g = -1
    for i in range(len(kind) - 1, -1, -1):
        if a < 0 and kind[i] == ACCEL:
            a = i
        if g < 0 and kind[i] == GYRO:
            g = i
        if a >= 0 and g >= 0:
            break
    if a >= 0:
        c.accel[:] = xyz[a]
    if g >= 0:
        c.gyro[:] = xyz[g]


# numba freezes the kind codes into the cached kernels: empty the caches when they change
_jit_cache.refresh_if_changed((sys.modules[__name__], kinds), "pipeline")
