"""Output sinks.  Every call into ``mcap`` and ``rerun`` lives in this package (imported lazily).

A sink receives, in time order and in chunks, what the replay drives through the pipeline:

``open(meta)``
    once, with the recording's metadata (``source``, ``format``, ``device``, ``north``, the WMM field, …).
``inputs(kind, t, xyz)``
    raw input chunks: ``kind`` in ``{"accel", "gyro", "mag"}`` (contract units, device frame).
``mag_calibrated(t, xyz)``
    the calibrated field at the magnetometer epochs (µT, device frame): the field the filter takes, the
    calibration in force applied less the offset error the filter has found.
``estimates(batch)``
    a :class:`pdr_mag.estimates.EstimateBatch`.
``reference(name, t, q_wd)``
    an orientation series to compare with (``"truth"`` from truth.csv, ``"os"`` the phone's own).
``event(ev)`` / ``calibration(t, cal)``
    :class:`pdr_mag.estimates.Event` and each new :class:`pdr_mag.calibration.MagCalibration`.
``close()``
    flush and finish the file.

A sink with ``wants_mag_calibrated = False`` does not get the calibrated samples, and the replay may then
run the pipeline without collecting them (a sink without the attribute gets them).  :class:`QuietSink`
ignores every call: a sink that wants only some of them derives from it and overrides those.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

#: Event kinds the sinks log as warnings (all others are info).
WARNING_EVENTS = (
    "interference_start", "calibration_rejected", "calibration_suspected", "recalibration_requested",
    "drift_episode", "stream_gap",
)


class Sink(Protocol):
    def open(self, meta: dict) -> None: ...

    def inputs(self, kind: str, t: np.ndarray, xyz: np.ndarray) -> None: ...

    def mag_calibrated(self, t: np.ndarray, xyz: np.ndarray) -> None: ...

    def estimates(self, batch) -> None: ...

    def reference(self, name: str, t: np.ndarray, q_wd: np.ndarray) -> None: ...

    def event(self, ev) -> None: ...

    def calibration(self, t: float, cal) -> None: ...

    def close(self) -> None: ...


class QuietSink:
    """A sink that ignores every call and does not want the calibrated magnetometer samples; derive from it
    and override what the sink uses."""

    wants_mag_calibrated = False

    def open(self, meta: dict) -> None:
        pass

    def inputs(self, kind: str, t: np.ndarray, xyz: np.ndarray) -> None:
        pass

    def mag_calibrated(self, t: np.ndarray, xyz: np.ndarray) -> None:
        pass

    def estimates(self, batch) -> None:
        pass

    def reference(self, name: str, t: np.ndarray, q_wd: np.ndarray) -> None:
        pass

    def event(self, ev) -> None:
        pass

    def calibration(self, t: float, cal) -> None:
        pass

    def close(self) -> None:
        pass
