"""Output sinks.  Every call into ``mcap`` and ``rerun`` lives in this package (imported lazily).

A sink receives, in time order and in chunks, what the replay drives through the pipeline:

``open(meta)``
    once, with the recording's metadata (``source``, ``format``, ``device``, ``north``, the WMM field, …).
``inputs(kind, t, xyz)``
    raw input chunks: ``kind`` in ``{"accel", "gyro", "mag"}`` (contract units, device frame).
``mag_calibrated(t, xyz)``
    the calibrated field at the magnetometer epochs (µT, device frame).
``estimates(batch)``
    a :class:`pdr_mag.estimates.EstimateBatch`.
``reference(name, t, q_wd)``
    an orientation series to compare with (``"truth"`` from truth.csv, ``"os"`` the phone's own).
``event(ev)`` / ``calibration(t, cal)``
    :class:`pdr_mag.estimates.Event` and each new :class:`pdr_mag.calibration.MagCalibration`.
``close()``
    flush and finish the file.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

#: Event kinds the sinks log as warnings (all others are info).
WARNING_EVENTS = ("interference_start", "calibration_rejected", "recalibration_requested", "drift_episode")


class Sink(Protocol):
    def open(self, meta: dict) -> None: ...

    def inputs(self, kind: str, t: np.ndarray, xyz: np.ndarray) -> None: ...

    def mag_calibrated(self, t: np.ndarray, xyz: np.ndarray) -> None: ...

    def estimates(self, batch) -> None: ...

    def reference(self, name: str, t: np.ndarray, q_wd: np.ndarray) -> None: ...

    def event(self, ev) -> None: ...

    def calibration(self, t: float, cal) -> None: ...

    def close(self) -> None: ...
