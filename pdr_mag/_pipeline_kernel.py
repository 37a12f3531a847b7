"""Compiled per-poll bookkeeping of :class:`pdr_mag.pipeline.HeadingPipeline` (numba, ``cache=True``).

Nothing here is a model: these are the merge of the three input streams into one time-ordered stream and
the magnetometer context the online calibrator is given (the filter's up vector and the gyro rate at each
magnetometer sample), written as loops because a poll of one or two seconds of data is too small for numpy
calls to pay off (their fixed cost, not the arithmetic, dominated).  The arithmetic is that of the numpy
expressions it replaces, in the same order, so the results are the same to the last bit.
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: ``ctx`` columns of :func:`mag_context`: time, raw field (3), up vector (3), gyro rate.
N_CTX = 8


@njit(cache=True, error_model="numpy")
def merge3(t0, x0, t1, x1, t2, x2, block_s):
    """Merge three time-ordered streams into ``(kind, t, xyz, blk)``; ties in stream order (0 < 1 < 2),
    ``blk = floor(t / block_s)`` — a stable sort of the concatenation by time."""
    n0 = len(t0)
    n1 = len(t1)
    n2 = len(t2)
    n = n0 + n1 + n2
    kind = np.empty(n, dtype=np.int8)
    t = np.empty(n)
    xyz = np.empty((n, 3))
    blk = np.empty(n)
    i0 = i1 = i2 = 0
    for k in range(n):
        # the smallest head; on ties the lower stream index
        s = -1
        best = np.inf
        if i0 < n0:
            s = 0
            best = t0[i0]
        if i1 < n1 and (s < 0 or t1[i1] < best):
            s = 1
            best = t1[i1]
        if i2 < n2 and (s < 0 or t2[i2] < best):
            s = 2
            best = t2[i2]
        kind[k] = s
        t[k] = best
        if s == 0:
            xyz[k, 0] = x0[i0, 0]
            xyz[k, 1] = x0[i0, 1]
            xyz[k, 2] = x0[i0, 2]
            i0 += 1
        elif s == 1:
            xyz[k, 0] = x1[i1, 0]
            xyz[k, 1] = x1[i1, 1]
            xyz[k, 2] = x1[i1, 2]
            i1 += 1
        else:
            xyz[k, 0] = x2[i2, 0]
            xyz[k, 1] = x2[i2, 1]
            xyz[k, 2] = x2[i2, 2]
            i2 += 1
        blk[k] = np.floor(best / block_s)
    return kind, t, xyz, blk


@njit(cache=True, error_model="numpy")
def _up_into(out, k, q, j):
    """Device-frame up vector (third row of rot_wd) of the w-first quaternion ``q[j]`` to ``out[k, 4:7]``."""
    w = q[j, 0]
    x = q[j, 1]
    y = q[j, 2]
    z = q[j, 3]
    out[k, 4] = 2 * (x * z - w * y)
    out[k, 5] = 2 * (y * z + w * x)
    out[k, 6] = 1 - 2 * (x * x + y * y)


@njit(cache=True, error_model="numpy")
def _norm3(a, b, c):
    return np.sqrt(a * a + b * b + c * c)


@njit(cache=True, error_model="numpy")
def mag_context(kind, t, xyz, row_t, row_q, up, up_acc, rate):
    """Rows ``(t, raw, up, rate)`` for the magnetometer samples (``kind == 2``) of a merged stream.

    ``up``: the filter's up vector of the latest output row (``row_t``, ``row_q``) at or before the sample
    (``up`` given: the one before these rows); where that is not finite, the direction of the latest
    accelerometer sample at or before it (``up_acc`` before the first); ``rate``: the norm of the latest
    gyro sample at or before it (``rate[0]`` before the first).
    """
    n = len(t)
    n_mag = 0
    for i in range(n):
        if kind[i] == 2:
            n_mag += 1
    out = np.empty((n_mag, N_CTX))
    k = 0
    r = 0  # output rows with time ≤ the current sample
    a = -1  # latest accelerometer / gyro sample so far (the merge puts ties before the magnetometer)
    g = -1
    n_rows = len(row_t)
    for i in range(n):
        if kind[i] == 0:
            a = i
        elif kind[i] == 1:
            g = i
        else:
            ti = t[i]
            while r < n_rows and row_t[r] <= ti:
                r += 1
            out[k, 0] = ti
            out[k, 1] = xyz[i, 0]
            out[k, 2] = xyz[i, 1]
            out[k, 3] = xyz[i, 2]
            if r > 0:
                _up_into(out, k, row_q, r - 1)
            else:
                out[k, 4] = up[0]
                out[k, 5] = up[1]
                out[k, 6] = up[2]
            if not np.isfinite(out[k, 4]):
                if a >= 0:
                    nn = max(_norm3(xyz[a, 0], xyz[a, 1], xyz[a, 2]), 1e-9)
                    out[k, 4] = xyz[a, 0] / nn
                    out[k, 5] = xyz[a, 1] / nn
                    out[k, 6] = xyz[a, 2] / nn
                else:
                    out[k, 4] = up_acc[0]
                    out[k, 5] = up_acc[1]
                    out[k, 6] = up_acc[2]
            out[k, 7] = _norm3(xyz[g, 0], xyz[g, 1], xyz[g, 2]) if g >= 0 else rate[0]
            k += 1
    return out


@njit(cache=True, error_model="numpy")
def carry_context(kind, xyz, end, row_q, n_rows, up, up_acc, rate):
    """Update ``up``, ``up_acc`` and ``rate`` (in place) with what :func:`mag_context` needs from the first
    ``end`` samples and ``n_rows`` output rows before the next call."""
    if n_rows:
        w = row_q[n_rows - 1, 0]
        x = row_q[n_rows - 1, 1]
        y = row_q[n_rows - 1, 2]
        z = row_q[n_rows - 1, 3]
        up[0] = 2 * (x * z - w * y)
        up[1] = 2 * (y * z + w * x)
        up[2] = 1 - 2 * (x * x + y * y)
    a = -1
    g = -1
    for i in range(end - 1, -1, -1):
        if a < 0 and kind[i] == 0:
            a = i
        if g < 0 and kind[i] == 1:
            g = i
        if a >= 0 and g >= 0:
            break
    if a >= 0:
        nn = max(_norm3(xyz[a, 0], xyz[a, 1], xyz[a, 2]), 1e-9)
        up_acc[0] = xyz[a, 0] / nn
        up_acc[1] = xyz[a, 1] / nn
        up_acc[2] = xyz[a, 2] / nn
    if g >= 0:
        rate[0] = _norm3(xyz[g, 0], xyz[g, 1], xyz[g, 2])


@njit(cache=True, error_model="numpy")
def in_order(t, xyz, after):
    """True when the times are strictly increasing from above ``after`` and every time and value is finite
    (the common case of a push: nothing to drop)."""
    prev = after
    for i in range(len(t)):
        ti = t[i]
        if not (ti > prev and np.isfinite(ti)):
            return False
        if not (np.isfinite(xyz[i, 0]) and np.isfinite(xyz[i, 1]) and np.isfinite(xyz[i, 2])):
            return False
        prev = ti
    return True


@njit(cache=True, error_model="numpy")
def span_pieces(blk, kind, span):
    """The span starting at sample 0: its end ``e`` (the first sample of block ``blk[0] + span``) and its
    block-pieces ``[lo, hi)``, with the number of magnetometer samples before each ``lo`` and ``hi``."""
    n = len(blk)
    stop = blk[0] + span
    e = n
    n_p = 1
    for i in range(1, n):
        if blk[i] >= stop:
            e = i
            break
        if blk[i] != blk[i - 1]:
            n_p += 1
    lo = np.empty(n_p, dtype=np.intp)
    hi = np.empty(n_p, dtype=np.intp)
    mag_lo = np.empty(n_p, dtype=np.intp)
    mag_hi = np.empty(n_p, dtype=np.intp)
    j = 0
    m = 0
    lo[0] = 0
    mag_lo[0] = 0
    for i in range(e):
        if i > 0 and blk[i] != blk[i - 1]:
            hi[j] = i
            mag_hi[j] = m
            j += 1
            lo[j] = i
            mag_lo[j] = m
        if kind[i] == 2:
            m += 1
    hi[j] = e
    mag_hi[j] = m
    return e, lo, hi, mag_lo, mag_hi


@njit(cache=True, error_model="numpy")
def close_layout(n_pre, mag_lo, mag_hi):
    """Rows handed to the calibrator when every piece but the last is closed: the ``n_pre`` rows of the open
    block, then the span's magnetometer samples up to the last piece.  Returns ``(n_rows, last, has, ends,
    piece_of_row)``: each closed piece's last row and whether it has one (the first piece also owns the
    open block's rows), the block-end flags of the rows, and the piece each row closes with."""
    n_c = len(mag_hi) - 1
    n_rows = n_pre + mag_hi[n_c - 1]
    last = np.empty(n_c, dtype=np.intp)
    has = np.empty(n_c, dtype=np.bool_)
    ends = np.zeros(n_rows, dtype=np.bool_)
    for j in range(n_c):
        last[j] = n_pre + mag_hi[j] - 1
        has[j] = mag_hi[j] > mag_lo[j]
    has[0] = last[0] >= 0
    n_has = 0
    for j in range(n_c):
        if has[j]:
            ends[last[j]] = True
            n_has += 1
    hp = np.empty(n_has, dtype=np.intp)
    k = 0
    for j in range(n_c):
        if has[j]:
            hp[k] = j
            k += 1
    piece_of_row = np.empty(n_rows, dtype=np.intp)
    k = 0
    for r in range(n_rows):
        while k < n_has - 1 and last[hp[k]] < r:
            k += 1
        piece_of_row[r] = hp[k]
    return n_rows, last, has, ends, piece_of_row


@njit(cache=True, error_model="numpy")
def piece_coverage(cov, last, has, c0):
    """Coverage in effect in each piece: ``c0`` in the first, then the coverage after the close of the
    previous piece with rows (``cov`` at its last row), carried over pieces without rows or a finite value."""
    n_p = len(last) + 1
    out = np.empty(n_p)
    out[0] = c0
    for j in range(1, n_p):
        v = cov[last[j - 1]] if has[j - 1] else np.nan
        out[j] = v if np.isfinite(v) else out[j - 1]
    return out


@njit(cache=True, error_model="numpy")
def minus_offset(kind, xyz, off):
    """``xyz`` with ``off`` subtracted from the magnetometer rows (``kind == 2``): the calibration
    ``A (m − b)`` when ``A`` is the identity (an offset-only calibration)."""
    out = xyz.copy()
    for i in range(len(kind)):
        if kind[i] == 2:
            out[i, 0] = xyz[i, 0] - off[0]
            out[i, 1] = xyz[i, 1] - off[1]
            out[i, 2] = xyz[i, 2] - off[2]
    return out


@njit(cache=True, error_model="numpy")
def _first_at_or_after(t, lo, hi, t_end):
    """``lo + searchsorted(t[lo:hi], t_end, side="left")`` (increasing times)."""
    a = lo
    b = hi
    while a < b:
        mid = (a + b) // 2
        if t[mid] < t_end:
            a = mid + 1
        else:
            b = mid
    return a


@njit(cache=True, error_model="numpy")
def take_merge3(t0, x0, lo0, hi0, t1, x1, lo1, hi1, t2, x2, lo2, hi2, t_end, block_s):
    """Take each stream's pending rows ``[lo, hi)`` before ``t_end`` and :func:`merge3` them: returns the
    new ``lo`` of each stream and the merged ``(kind, t, xyz, blk)``."""
    k0 = _first_at_or_after(t0, lo0, hi0, t_end)
    k1 = _first_at_or_after(t1, lo1, hi1, t_end)
    k2 = _first_at_or_after(t2, lo2, hi2, t_end)
    kind, t, xyz, blk = merge3(
        t0[lo0:k0], x0[lo0:k0], t1[lo1:k1], x1[lo1:k1], t2[lo2:k2], x2[lo2:k2], block_s
    )  # fmt: skip
    return k0, k1, k2, kind, t, xyz, blk


@njit(cache=True, error_model="numpy")
def rows_before(row_t, t, hi):
    """Output rows with time ≤ ``t[hi[j] − 1]`` for each piece end ``hi[j]`` (``searchsorted(row_t,
    t[hi − 1], side="right")`` on increasing row times)."""
    out = np.empty(len(hi), dtype=np.intp)
    r = 0
    n = len(row_t)
    for j in range(len(hi)):
        tj = t[hi[j] - 1]
        while r < n and row_t[r] <= tj:
            r += 1
        out[j] = r
    return out


@njit(cache=True, error_model="numpy")
def close_rows(pre, ctx, n_ctx):
    """The rows handed to the calibrator (``pre``, then ``ctx[:n_ctx]``) as contiguous columns ``(ok, t,
    raw, up, rate)``, non-finite rates set to 0; ``ok`` when every time, field and up value is finite (else
    the caller hands the rows as they are)."""
    n_pre = pre.shape[0]
    n = n_pre + n_ctx
    tc = np.empty(n)
    mc = np.empty((n, 3))
    uc = np.empty((n, 3))
    rc = np.empty(n)
    ok = True
    for r in range(n):
        src = pre if r < n_pre else ctx
        i = r if r < n_pre else r - n_pre
        tc[r] = src[i, 0]
        ok = ok and np.isfinite(tc[r])
        for c in range(3):
            mc[r, c] = src[i, 1 + c]
            uc[r, c] = src[i, 4 + c]
            ok = ok and np.isfinite(mc[r, c]) and np.isfinite(uc[r, c])
        v = src[i, 7]
        rc[r] = v if np.isfinite(v) else 0.0
    return ok, tc, mc, uc, rc


@njit(cache=True, error_model="numpy")
def rows_coverage(covs, row_hi, n_pieces):
    """Each output row's coverage: ``covs[j]`` for the rows of piece ``j`` (``np.repeat`` of the first
    ``n_pieces`` by their row counts)."""
    out = np.empty(row_hi[n_pieces - 1])
    r = 0
    for j in range(n_pieces):
        while r < row_hi[j]:
            out[r] = covs[j]
            r += 1
    return out


@njit(cache=True, error_model="numpy")
def all_equal(flags, v):
    """Whether every flag equals ``v``."""
    for i in range(len(flags)):
        if flags[i] != v:
            return False
    return True


@njit(cache=True, error_model="numpy")
def append_in_order(bt, bx, hi, t, xyz, after, done_t):
    """A push's common case: when ``t[0] ≥ done_t`` and :func:`in_order`, copy the rows to ``bt[hi:]``,
    ``bx[hi:]`` if they fit (returns 1) or leave that to the caller (2); 0 when they need checking."""
    n = len(t)
    if not (t[0] >= done_t) or not in_order(t, xyz, after):
        return 0
    if hi + n > len(bt):
        return 2
    for i in range(n):
        bt[hi + i] = t[i]
        bx[hi + i, 0] = xyz[i, 0]
        bx[hi + i, 1] = xyz[i, 1]
        bx[hi + i, 2] = xyz[i, 2]
    return 1


@njit(cache=True, error_model="numpy")
def span_start(blk, kind, xyz, span, off, calibrated):
    """:func:`span_pieces` and the span's samples as the filter takes them: with ``calibrated``, the
    magnetometer's less ``off`` (:func:`minus_offset`), else NaN; the ``mag_allowed`` flags; the number of
    gyro samples.  Returns ``(e, lo, hi, mag_lo, mag_hi, data, allowed, n_gyro)``."""
    e, lo, hi, mag_lo, mag_hi = span_pieces(blk, kind, span)
    data = np.empty((e, 3))
    allowed = np.empty(e, dtype=np.bool_)
    n_gyro = 0
    for i in range(e):
        allowed[i] = calibrated
        if kind[i] == 1:
            n_gyro += 1
        if kind[i] == 2:
            if calibrated:
                data[i, 0] = xyz[i, 0] - off[0]
                data[i, 1] = xyz[i, 1] - off[1]
                data[i, 2] = xyz[i, 2] - off[2]
            else:
                data[i, 0] = np.nan
                data[i, 1] = np.nan
                data[i, 2] = np.nan
        else:
            data[i, 0] = xyz[i, 0]
            data[i, 1] = xyz[i, 1]
            data[i, 2] = xyz[i, 2]
    return e, lo, hi, mag_lo, mag_hi, data, allowed, n_gyro


@njit(cache=True, error_model="numpy")
def span_context(kind, t, xyz, hi, row_t, row_q, up, up_acc, rate):
    """:func:`rows_before` and :func:`mag_context` of a span in one call: ``(row_hi, ctx)``."""
    return rows_before(row_t, t, hi), mag_context(kind, t, xyz, row_t, row_q, up, up_acc, rate)


@njit(cache=True, error_model="numpy")
def close_span(pre, ctx, mag_lo, mag_hi):
    """:func:`close_layout` and :func:`close_rows` of a span's closed pieces in one call: ``(n_rows, last,
    has, ends, piece_of_row, ok, t, raw, up, rate)``."""
    n_rows, last, has, ends, piece_of_row = close_layout(pre.shape[0], mag_lo, mag_hi)
    ok, tc, mc, uc, rc = close_rows(pre, ctx, mag_hi[len(mag_hi) - 2])
    return n_rows, last, has, ends, piece_of_row, ok, tc, mc, uc, rc
