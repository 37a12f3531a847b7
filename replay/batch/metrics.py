"""What the fleet table says about one replay, gathered as the replay streams (a sink beside the files).

:class:`FleetMetrics` receives the same estimates, events and reference series as the CSV, MCAP and rerun
sinks (:mod:`pdr_mag.sinks`) and keeps only counts and fixed-size histograms, so its memory does not grow
with the recording's length.

Heading error against a reference
---------------------------------
At every output epoch ``t`` inside a reference series (``truth`` from truth.csv, ``os`` the phone's own
attitude) the reference is slerp-interpolated between its two samples around ``t`` (epochs whose two
samples lie more than :data:`MAX_REF_GAP_S` apart are not scored), and the error rotation
``e = q_est ⊗ q_ref⁻¹`` (world frame) gives the heading error as its twist about the world Up axis,

    ε = wrap₍₋₁₈₀,₁₈₀₎( 2 · atan2(e_z, e_w) )  [deg],

the definition of the shared tyrex scorer (``../shared/benchmarks/tyrex/score.py``), which stays defined at
any pitch. The table gives the median and 95th percentile of ``|ε|`` over the scored epochs (the scorer
evaluates at the truth frames of a fixed window; here every output epoch the reference covers counts).

Quantiles
---------
:class:`Histogram` counts values in bins of :data:`BIN_DEG` centred on its multiples over [0°, 180°]
(``heading_std_deg`` is capped at 180°, ``|ε|`` ≤ 180°) and returns the nearest-rank quantile
(the ``⌈q·n⌉``-th smallest value) to within half a bin.
"""

from __future__ import annotations

import math

import numpy as np

from pdr_mag.conventions import quat_multiply, quat_slerp, wrap_deg
from pdr_mag.sinks import QuietSink

#: Histogram bin width, deg: quantiles are given to within half of it.
BIN_DEG = 0.01

#: Largest gap between two reference samples that an output epoch between them is scored across, s.
MAX_REF_GAP_S = 1.0

#: The reference series scored (``Recording.references`` names and ``truth``).
REFERENCES = ("truth", "os")


class Histogram:
    """Counts of angles in [0°, 180°], in bins of :data:`BIN_DEG` centred on its multiples."""

    def __init__(self, top_deg: float = 180.0):
        self.n_bins = int(round(top_deg / BIN_DEG)) + 1
        self.counts = np.zeros(self.n_bins, dtype=np.int64)

    def add(self, values_deg: np.ndarray) -> None:
        """Count the finite values (clipped into the range)."""
        v = np.asarray(values_deg, dtype=float)
        v = v[np.isfinite(v)]
        if len(v):
            idx = np.clip(np.rint(v / BIN_DEG), 0, self.n_bins - 1).astype(np.int64)
            self.counts += np.bincount(idx, minlength=self.n_bins)

    @property
    def n(self) -> int:
        return int(self.counts.sum())

    def quantile(self, q: float) -> float | None:
        """Nearest-rank ``q`` quantile (the ``⌈q·n⌉``-th smallest value) to within ``BIN_DEG / 2``, or None
        without values."""
        n = self.n
        if n == 0:
            return None
        rank = max(1, math.ceil(q * n))
        k = int(np.searchsorted(np.cumsum(self.counts), rank))
        return round(k * BIN_DEG, 2)


def heading_error_deg(q_est: np.ndarray, q_ref: np.ndarray) -> np.ndarray:
    """Signed heading error, deg: the twist about Up of ``e = q_est ⊗ q_ref⁻¹`` (w-first), in [-180, 180)."""
    conj = np.asarray(q_ref, dtype=float) * np.array([1.0, -1.0, -1.0, -1.0])
    e = quat_multiply(q_est, conj)
    return wrap_deg(np.degrees(2.0 * np.arctan2(e[:, 3], e[:, 0])))


class _Reference:
    """One reference series and the histogram of the heading error against it."""

    def __init__(self, t: np.ndarray, q_wd: np.ndarray):
        t = np.asarray(t, dtype=float)
        q = np.asarray(q_wd, dtype=float)
        ok = np.isfinite(t) & np.all(np.isfinite(q), axis=1)
        t, q = t[ok], q[ok]
        order = np.argsort(t, kind="stable")
        self.t, self.q = t[order], q[order]
        self.errors = Histogram()

    def add(self, t: np.ndarray, q_est: np.ndarray) -> None:
        tr = self.t
        if len(tr) < 2:
            return
        inside = (t >= tr[0]) & (t <= tr[-1]) & np.all(np.isfinite(q_est), axis=1)
        if not inside.any():
            return
        ts, qs = t[inside], q_est[inside]
        i = np.clip(np.searchsorted(tr, ts, side="right") - 1, 0, len(tr) - 2)
        near = (tr[i + 1] - tr[i]) <= MAX_REF_GAP_S
        if not near.any():
            return
        q_ref = quat_slerp(tr, self.q, ts[near])
        self.errors.add(np.abs(heading_error_deg(qs[near], q_ref)))


class FleetMetrics(QuietSink):
    """A replay sink (:class:`pdr_mag.sinks.Sink`) that keeps what a fleet-table row needs: output rows,
    the share flagged as interference and corrected by the magnetometer, quantiles of ``heading_std_deg``
    and of the heading error against each reference (the event counts are the replay summary's)."""

    def __init__(self):
        self.meta: dict = {}
        self.n_rows = 0
        self.n_interference = 0
        self.n_mag_used = 0
        self.heading_std = Histogram()
        self.references: dict[str, _Reference] = {}

    def open(self, meta: dict) -> None:
        self.meta = dict(meta)

    def estimates(self, batch) -> None:
        n = len(batch)
        if not n:
            return
        self.n_rows += n
        self.n_interference += int(np.count_nonzero(batch.interference))
        self.n_mag_used += int(np.count_nonzero(batch.mag_used))
        self.heading_std.add(batch.heading_std_deg)
        t = np.asarray(batch.t, dtype=float)
        q = np.asarray(batch.q_wd, dtype=float)
        for ref in self.references.values():
            ref.add(t, q)

    def reference(self, name, t, q_wd) -> None:
        if name in REFERENCES:
            self.references[name] = _Reference(t, q_wd)

    def share(self, count: int) -> float | None:
        """``count`` as a share of the output rows (None without rows)."""
        return count / self.n_rows if self.n_rows else None

    def error_quantile(self, name: str, q: float) -> float | None:
        """Quantile ``q`` of ``|ε|`` against reference ``name``, deg (None without that reference)."""
        ref = self.references.get(name)
        return None if ref is None else ref.errors.quantile(q)
