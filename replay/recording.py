"""The in-memory form of a recording that every reader produces (units and frames of INTERFACE.md)."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

import numpy as np


@dataclass
class Stream:
    """One sensor stream: strictly increasing times ``t`` (s, N) and values ``xyz`` (N, 3)."""

    t: np.ndarray
    xyz: np.ndarray

    def __len__(self) -> int:
        return len(self.t)

    @property
    def duration(self) -> float:
        return float(self.t[-1] - self.t[0]) if len(self.t) > 1 else 0.0

    @property
    def rate_hz(self) -> float:
        return (len(self.t) - 1) / self.duration if self.duration > 0 else float("nan")


@dataclass
class Recording:
    """A phone recording in the contract's units and device frame.

    Attributes
    ----------
    mag : Stream
        Raw magnetometer, µT.
    accel, gyro : Stream or None
        Accelerometer (m/s², specific force) and gyroscope (rad/s).
    meta : dict
        ``device``, ``latitude_deg``, ``longitude_deg``, ``altitude_m``, ``date`` — all optional; what the
        file states about the phone's own calibration and the device (``mag_os_bias_uT``,
        ``mag_os_calibrated``, ``device_id``, …: INTERFACE.md, "Recording ``meta``"); format-specific keys.
    truth : (t (N,), q_wxyz (N, 4)) or None
        True orientation, device → ENU true north; for evaluation only.
    references : dict
        Other orientation series to compare with, by name (``"os"``: the phone's own fused attitude, w-first
        device → ENU), as ``(t (N,), q_wxyz (N, 4))``; never read by the pipeline's filter — ``replay`` gives
        the phone's heading to the rows whose heading pdr_mag does not know
        (:func:`pdr_mag.pipeline.fill_unknown_heading`), the rest is evaluation.
    temperature : (t (N,), °C (N,)) or None
        Sensor temperature when the device logs it (e.g. the breadboard IMU's MPU6050).
    source : str
        Where it came from (path) and ``format``: the reader's name.
    dropped : Counter
        Odd samples the reader skipped, by ``"stream:reason"``.
    """

    mag: Stream
    accel: Stream | None = None
    gyro: Stream | None = None
    meta: dict = field(default_factory=dict)
    truth: tuple[np.ndarray, np.ndarray] | None = None
    temperature: tuple[np.ndarray, np.ndarray] | None = None
    references: dict = field(default_factory=dict)
    source: str = ""
    format: str = ""
    dropped: Counter = field(default_factory=Counter)

    @property
    def t0(self) -> float:
        return float(min(s.t[0] for s in (self.mag, self.accel, self.gyro) if s is not None and len(s)))

    @property
    def t1(self) -> float:
        return float(max(s.t[-1] for s in (self.mag, self.accel, self.gyro) if s is not None and len(s)))
