"""The online calibrator's diversity buffer: a bounded set of raw magnetometer samples of varied orientation.

A kept sample is a :data:`SAMPLE` record ``(t, m, u)``: time (s), raw field ``m`` (µT, device frame) and
the unit up vector ``u`` (device frame) at that instant.  Repeated orientations add no information to a
fit but would dominate its least squares; the buffer keeps one sample per neighbourhood instead.  Two
samples are *close* when ``|m_a − m_b| < min_sep_frac · F`` (raw µT) and ``u_a · u_b > cos(min_sep_up_deg)``
(similar gravity direction).

Admission of a new sample (:func:`redundant`, after the calibrator's consistency test) is judged against the
buffer as it was at the start of the sample's block, so that a block's samples are judged alike however
the stream is cut: the sample is *redundant* when a block-start sample is close to it, unless every close
one is older than ``refresh_s`` (then it may be refreshed).  An admitted sample is offered to the buffer as
it is now (:func:`offer` says where it goes, the caller puts it there):

* close to a kept sample: it replaces the oldest close one if that is older than ``refresh_s`` (so the
  buffer follows slow drift), else it is dropped;
* otherwise it is appended while there is room;
* the buffer full: it replaces the kept sample nearest to another one (the most redundant).

:func:`coverage` is the online measure of how much of the sphere the samples cover: the share of 64
near-uniform directions (a golden-angle spiral) with a sample direction, about a centre, within 30°
(:func:`count_directions` keeps it per direction as samples come and go, for a buffer that changes at
almost every block while its centre stays).  The refit triggers (``sphere_coverage``,
``ellipsoid_coverage``) are set on it; the full fit's further gate (``ellipsoid_precheck_frac``) uses the
calibration core's equal-area :func:`pdr_mag.calibration.coverage.coverage`, and the fit is accepted by its
heading bound (:func:`pdr_mag.calibration.coverage.accept`), not by a coverage.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

#: A kept magnetometer sample: time, raw field (µT), and the up and north (world y; NaN unknown) axes of the
#: filter's attitude, device frame.  Packed (80 bytes), so ``buf["m"]`` is an (n, 3) view with the row
#: stride of ten floats.
SAMPLE = np.dtype(
    [("t", np.float64), ("m", np.float64, (3,)), ("u", np.float64, (3,)), ("n", np.float64, (3,))]
)


class Near(NamedTuple):
    """When two samples count as one: ``|m_a − m_b|² < sep2`` (raw µT²) and ``u_a · u_b > cos_up``; and the
    age (s) beyond which a close kept sample may be refreshed."""

    sep2: float
    cos_up: float
    refresh_s: float


class BlockStart(NamedTuple):
    """The buffer as it was at the start of the open block: its samples ``buf[:n]``, and the indices
    ``old[:n_old]`` of those that can grow older than ``refresh_s`` within the block."""

    buf: np.ndarray
    n: int
    old: np.ndarray
    n_old: int


#: The 64 directions of :func:`coverage` (golden-angle spiral) and the cosine of its 30° cap.
N_DIRS = 64
_golden = np.pi * (3.0 - np.sqrt(5.0))
_z = 1.0 - 2.0 * (np.arange(N_DIRS) + 0.5) / N_DIRS
DIRS = np.column_stack(
    [
        np.sqrt(1 - _z**2) * np.cos(_golden * np.arange(N_DIRS)),
        np.sqrt(1 - _z**2) * np.sin(_golden * np.arange(N_DIRS)),
        _z,
    ]
)
COS_CAP = float(np.cos(np.radians(30.0)))


def empty(n: int) -> np.ndarray:
    """``n`` unused :data:`SAMPLE` slots (every value NaN)."""
    buf = np.empty(n, dtype=SAMPLE)
    buf.view(np.float64)[:] = np.nan
    return buf


def direction_coverage(mag_cal: np.ndarray) -> float:
    """:func:`coverage` of calibrated samples (about the origin), in [0, 1]."""
    m = np.ascontiguousarray(mag_cal, dtype=float).reshape(-1, 3)
    return float(coverage(m, len(m), np.zeros(3)))


@njit(cache=True, error_model="numpy")
def coverage(m, n, centre):
    """Share of the :data:`DIRS` with a direction of ``m[:n] − centre`` within 30°."""
    if n == 0:
        return 0.0
    hit = np.zeros(N_DIRS, dtype=np.bool_)
    for k in range(n):
        x0, x1, x2 = _direction(m[k], centre)
        for d in range(N_DIRS):
            if not hit[d] and x0 * DIRS[d, 0] + x1 * DIRS[d, 1] + x2 * DIRS[d, 2] > COS_CAP:
                hit[d] = True
    c = 0
    for d in range(N_DIRS):
        if hit[d]:
            c += 1
    return c / N_DIRS


@njit(cache=True, error_model="numpy")
def _direction(m, centre):
    """The unit direction of ``m − centre`` (a zero vector stays zero)."""
    x0 = m[0] - centre[0]
    x1 = m[1] - centre[1]
    x2 = m[2] - centre[2]
    nn = max(np.sqrt(x0 * x0 + x1 * x1 + x2 * x2), 1e-12)
    return x0 / nn, x1 / nn, x2 / nn


@njit(cache=True, error_model="numpy")
def count_directions(m, centre, counts, delta):
    """Add ``delta`` to ``counts[d]`` for each of the :data:`DIRS` within 30° of the direction of ``m −
    centre``: with ``delta`` ±1 as samples enter and leave, the directions with a positive count are those
    :func:`coverage` finds hit, by the same test."""
    x0, x1, x2 = _direction(m, centre)
    for d in range(N_DIRS):
        if x0 * DIRS[d, 0] + x1 * DIRS[d, 1] + x2 * DIRS[d, 2] > COS_CAP:
            counts[d] += delta


@njit(cache=True, error_model="numpy")
def buffer_coverage(buf, n, has_centre, centre):
    """:func:`coverage` of the first ``n`` kept samples about ``centre`` (``has_centre``), else about their
    mean."""
    c = np.zeros(3)
    if has_centre:
        c[:] = centre
    else:
        for k in range(n):
            c[0] += buf[k].m[0]
            c[1] += buf[k].m[1]
            c[2] += buf[k].m[2]
        c /= max(n, 1)
    m = np.empty((n, 3))
    for k in range(n):
        m[k, 0] = buf[k].m[0]
        m[k, 1] = buf[k].m[1]
        m[k, 2] = buf[k].m[2]
    return coverage(m, n, c)


@njit(cache=True, error_model="numpy")
def _close(a, m, u, near):
    """Whether the kept sample ``a`` is close to ``(m, u)`` (:class:`Near`, the module docstring)."""
    d0 = a.m[0] - m[0]
    d1 = a.m[1] - m[1]
    d2 = a.m[2] - m[2]
    if not d0 * d0 + d1 * d1 + d2 * d2 < near.sep2:
        return False
    return a.u[0] * u[0] + a.u[1] * u[1] + a.u[2] * u[2] > near.cos_up


@njit(cache=True, error_model="numpy")
def redundant(t, m, u, start, hint, near):
    """The index of a block-start sample (:class:`BlockStart` ``start``) close to ``(t, m, u)`` when the
    sample is redundant, else −1 (none close, or a close one older than ``near.refresh_s``).

    ``start.old[:start.n_old]`` lists the block-start samples that can be that old within the block: they
    are checked first; then any close sample will do, searched from ``hint`` (where the previous one was
    found: consecutive samples are usually close to the same one).
    """
    buf0, n0 = start.buf, start.n
    if n0 == 0:
        return -1
    for k in range(start.n_old):
        j = start.old[k]
        if not t - buf0[j].t <= near.refresh_s and _close(buf0[j], m, u, near):
            return -1
    first = hint if hint < n0 else 0
    for k in range(n0):
        j = first + k
        if j >= n0:
            j -= n0
        if _close(buf0[j], m, u, near):
            return j
    return -1


@njit(cache=True, error_model="numpy")
def put(buf, j, t, m, u, n):
    """Write the sample ``(t, m, u, n)`` to slot ``j``."""
    a = buf[j]
    a.t = t
    a.m[0] = m[0]
    a.m[1] = m[1]
    a.m[2] = m[2]
    a.u[0] = u[0]
    a.u[1] = u[1]
    a.u[2] = u[2]
    a.n[0] = n[0]
    a.n[1] = n[1]
    a.n[2] = n[2]


@njit(cache=True, error_model="numpy")
def offer(t, m, u, buf, n, size, near):
    """Where ``(t, m, u)`` offered to the buffer of ``n`` samples (room for ``size``) goes: the slot it is to
    be put in (``n``: appended; below ``n``: it replaces the sample there), or −1 (dropped)."""
    if n:
        j = -1
        tj = np.inf
        for k in range(n):
            if _close(buf[k], m, u, near) and buf[k].t < tj:
                tj = buf[k].t
                j = k
        if j >= 0:
            return j if t - tj > near.refresh_s else -1
    if n < size:
        return n
    return _most_redundant(buf, n)


@njit(cache=True, error_model="numpy")
def _most_redundant(buf, n):
    """The sample nearest (raw µT) to another one."""
    best = np.inf
    jb = 0
    for a in range(n):
        nearest = np.inf
        for b in range(n):
            if b != a:
                d0 = buf[a].m[0] - buf[b].m[0]
                d1 = buf[a].m[1] - buf[b].m[1]
                d2 = buf[a].m[2] - buf[b].m[2]
                d = d0 * d0 + d1 * d1 + d2 * d2
                if d < nearest:
                    nearest = d
        if nearest < best:
            best = nearest
            jb = a
    return jb
