"""What the fleet table says about one replay, gathered as the replay streams (a sink beside the files).

:class:`FleetMetrics` receives the same estimates as the CSV, MCAP and rerun sinks (:mod:`pdr_mag.sinks`)
and keeps only counts and a fixed-size histogram, so its memory does not grow with the recording's length.
The heading's errors against the recording's references and the walked direction are the replay summary's
own (``heading_error``, ``walked_direction``: :mod:`replay.heading_scores`), as are the event counts.

Quantiles
---------
:class:`~replay.heading_scores.Histogram` counts ``heading_std_deg`` (capped at 180°) in bins of
:data:`~replay.heading_scores.BIN_DEG` and returns the nearest-rank quantile (the ``⌈q·n⌉``-th smallest
value) to within half a bin.
"""

from __future__ import annotations

import numpy as np

from pdr_mag.sinks import QuietSink
from replay.heading_scores import Histogram

__all__ = ["FleetMetrics"]


class FleetMetrics(QuietSink):
    """A replay sink (:class:`pdr_mag.sinks.Sink`) that keeps what a fleet-table row needs beyond the
    summary: output rows, the share flagged as interference and corrected by the magnetometer, and the
    quantiles of ``heading_std_deg``."""

    def __init__(self):
        self.meta: dict = {}
        self.n_rows = 0
        self.n_interference = 0
        self.n_mag_used = 0
        self.heading_std = Histogram()

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

    def share(self, count: int) -> float | None:
        """``count`` as a share of the output rows (None without rows)."""
        return count / self.n_rows if self.n_rows else None
