"""The pipeline's input side: each stream's pending samples, and their merge in time order.

A push appends to its stream's :class:`PendingStream`; a poll takes every stream's samples before a time
and merges them (:func:`take_merged`, compiled in :mod:`pdr_mag.pipeline._kernel`), ties in the order of
:data:`pdr_mag.fusion.kinds.KINDS` (accelerometer, gyroscope, magnetometer).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from pdr_mag.pipeline import _kernel as PK


class Pending(NamedTuple):
    """A stream's pending rows as the compiled merge reads them: rows ``[lo, hi)`` of its buffers."""

    t: np.ndarray
    xyz: np.ndarray
    lo: int
    hi: int


class PendingStream:
    """Pending samples of one input stream, in time order: rows ``[lo, hi)`` of a buffer that grows
    (doubling) when a push does not fit after moving the pending rows to its start."""

    __slots__ = ("t", "xyz", "lo", "hi", "last_t", "last_xyz", "repeats")

    def __init__(self):
        self.t = np.empty(0)
        self.xyz = np.empty((0, 3))
        self.lo = 0
        self.hi = 0
        self.last_t = -np.inf  # the latest sample pushed
        self.last_xyz = np.full(3, np.nan)  # its value
        self.repeats = 0  # how many samples in a row repeated it exactly

    @property
    def n(self) -> int:
        return self.hi - self.lo

    def append(self, t: np.ndarray, xyz: np.ndarray) -> None:
        k = len(t)
        if self.hi + k > len(self.t):
            n = self.hi - self.lo
            if n + k > len(self.t):
                cap = max(2 * len(self.t), n + k, 256)
                bt, bx = np.empty(cap), np.empty((cap, 3))
            else:
                bt, bx = self.t, self.xyz
            bt[:n] = self.t[self.lo : self.hi]
            bx[:n] = self.xyz[self.lo : self.hi]
            self.t, self.xyz, self.lo, self.hi = bt, bx, 0, n
        self.t[self.hi : self.hi + k] = t
        self.xyz[self.hi : self.hi + k] = xyz
        self.hi += k
        self.last_t = float(t[-1])

    def stale(self, xyz: np.ndarray) -> np.ndarray:
        """Which of these new values (N, 3), in order, are a stalled sensor's sample delivered again: the
        same value on all three axes for the third time or more in a row.  A quantised sensor at rest
        repeats a value now and then (the tyrex phones: single repeats, never two in a row); a logger that
        writes the latest value on its own clock repeats a stalled one many times (the mall traces' gyroscope
        and magnetometer: runs of up to 80 samples, 1.6 s, while the phone turns).  Updates the run."""
        out = np.empty(len(xyz), dtype=np.bool_)
        xyz = np.ascontiguousarray(xyz, dtype=float)
        self.repeats = int(PK.repeated(xyz, self.last_xyz, self.repeats, out))
        self.last_xyz = xyz[-1].astype(float)
        return out

    def pending(self) -> tuple[np.ndarray, np.ndarray]:
        """A copy of the pending samples ``(t, xyz)``."""
        return self.t[self.lo : self.hi].copy(), self.xyz[self.lo : self.hi].copy()

    def rows(self) -> Pending:
        return Pending(self.t, self.xyz, self.lo, self.hi)


def take_merged(streams: dict, t_end: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each stream's pending samples before ``t_end`` (``streams``: name → :class:`PendingStream`, in kind
    order), merged in time order, ties in kind order: ``(kind, t, xyz)``; they leave the streams."""
    a, g, m = streams.values()
    kind, t, xyz, (a.lo, g.lo, m.lo) = PK.take_merged((a.rows(), g.rows(), m.rows()), t_end)
    return kind, t, xyz
