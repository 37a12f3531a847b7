"""The contract's units, checked: is a stream plausibly in µT, m/s² or rad/s, its time in seconds, and are
the streams stamped by one clock?

A stream in another unit is not noisy data but a different quantity: the accelerometer in g (iOS CoreMotion's
unit) has no gravity of 9.8 to tilt by, a magnetometer in gauss or nT no field of the Earth's strength, a
gyroscope in °/s turns the attitude 57 times too fast, and times in nanoseconds (Android's
``SensorEvent.timestamp``) make every sample interval millions of seconds of motion.  The pipeline then runs
and reports an unknown heading (σ 180°) with nothing said.  The readers (``replay/formats``) and
:class:`pdr_mag.pipeline.HeadingPipeline` apply the same rules to a stream's first samples and say which unit
the numbers look like.

The rules look at medians, which no single odd sample moves: the median vector norm within
:data:`UNIT_RANGES` and the median interval between samples within :data:`SAMPLE_INTERVAL_S`.  They catch a
wrong unit, not a miscalibrated sensor: a magnetometer with a large hard iron reads several hundred µT, a
gyroscope in °/s held still reads below 20 and passes.
"""

from __future__ import annotations

import numpy as np

from pdr_mag.conventions import GRAVITY, NT_PER_UT, UT_PER_GAUSS, UT_PER_TESLA

#: Plausible median vector norm of each stream's samples (low, high, unit).  Magnetometer: the Earth's
#: 22–67 µT plus a phone's hard iron (up to ~600 µT seen) and a magnet's passing field; accelerometer:
#: gravity with a walker's or runner's accelerations; gyroscope: anything up to a spinning phone.
UNIT_RANGES = {
    "mag": (5.0, 2000.0, "µT"),
    "accel": (3.0, 30.0, "m/s²"),
    "gyro": (0.0, 20.0, "rad/s"),
}

#: Plausible median interval between a sensor stream's samples, s: 100 kHz to 1/1.5 Hz.  Phones log 5–500 Hz,
#: IMUs up to a few kHz; a file whose time is in milliseconds (at up to 660 Hz), microseconds or nanoseconds
#: falls above, and a replay of it would treat each sample interval as seconds of motion.
SAMPLE_INTERVAL_S = (1.0e-5, 1.5)

#: Units a stream is often delivered in by mistake, with the factor into the contract's unit: the first whose
#: conversion lands the median inside :data:`UNIT_RANGES` is named in the message.
_OTHER_UNITS = {
    "mag": (("gauss", UT_PER_GAUSS), ("nT", 1.0 / NT_PER_UT), ("mT", 1000.0), ("T", UT_PER_TESLA)),
    "accel": (("g", GRAVITY),),
    "gyro": (("°/s", np.pi / 180.0),),
}
_OTHER_TIME_UNITS = (("ms", 1e-3), ("µs", 1e-6), ("ns", 1e-9))

#: Streams whose first samples lie further apart than this (s) were not stamped by one clock (a logger mixing
#: the time since boot with the time since the epoch): an input error, not a recording.
MAX_START_SPREAD_S = 600.0

#: An accelerometer's per-axis median over its first samples is mostly gravity (its direction holds while the
#: phone is carried); below this share of the median norm the samples have no common direction: gravity was
#: taken out (Android's ``TYPE_LINEAR_ACCELERATION``, iOS's ``userAcceleration``).
_GRAVITY_SHARE = 0.5


def _median(x: np.ndarray) -> float:
    """``np.median`` of a finite 1-D array, by a partial sort (a few µs instead of ~20 on 50 values)."""
    n = len(x)
    k = n // 2
    if n % 2:
        return float(np.partition(x, k)[k])
    p = np.partition(x, (k - 1, k))
    return float(0.5 * (p[k - 1] + p[k]))


def unit_problem(key: str, xyz: np.ndarray, unit_hint: str = "") -> str | None:
    """What is wrong with the unit of samples ``xyz`` (N, 3) of stream ``key`` (``"mag"``, ``"accel"``,
    ``"gyro"``), or None: their median norm outside :data:`UNIT_RANGES`, with the unit they look like when
    one fits.  ``unit_hint``: the unit the caller read them as, named in the message."""
    lo, hi, unit = UNIT_RANGES[key]
    v = np.asarray(xyz, dtype=float).reshape(-1, 3)
    with np.errstate(over="ignore", invalid="ignore"):  # a corrupt 1e308 among them: its norm is inf
        med = _median(np.sqrt(np.einsum("ij,ij->i", v, v)))
    if lo <= med <= hi:
        return None
    what = f" (read as {unit_hint})" if unit_hint else ""
    with np.errstate(over="ignore", invalid="ignore"):
        common = float(np.linalg.norm(np.median(v, axis=0)))  # the samples' shared vector (gravity)
    if key == "accel" and med > 0 and common < _GRAVITY_SHARE * med:
        guess = " gravity taken out? the accelerometer must measure gravity too"
    else:
        guess = next((f" in {name}, × {k:.6g} gives {med * k:.4g} {unit}" for name, k in _OTHER_UNITS[key]
                      if lo <= med * k <= hi and med > 0), "")
    return (f"median |{key}| is {med:.4g} {unit}{what}, outside the plausible {lo:g}–{hi:g} {unit} "
            f"(wrong unit?{guess})")


def time_unit_problem(key: str, t: np.ndarray) -> str | None:
    """What is wrong with the time unit of a stream's increasing sample times ``t``, or None: the median
    interval outside :data:`SAMPLE_INTERVAL_S` (fewer than 3 times: nothing to judge)."""
    t = np.asarray(t, dtype=float).reshape(-1)
    if len(t) < 3:
        return None
    med = _median(np.diff(t))
    lo, hi = SAMPLE_INTERVAL_S
    if lo <= med <= hi:
        return None
    guess = next((f" in {name}, × {k:g} gives {med * k:.4g} s" for name, k in _OTHER_TIME_UNITS
                  if lo <= med * k <= hi), "")
    return (f"{key}: median interval between samples is {med:.4g} s, outside the plausible {lo:g}–{hi:g} s "
            f"(time not in seconds?{guess})")


def clock_problem(starts: dict) -> str | None:
    """What is wrong with the streams' first sample times ``starts`` ({stream: t, s}), or None: further apart
    than :data:`MAX_START_SPREAD_S` (two clocks)."""
    if len(starts) < 2:
        return None
    spread = max(starts.values()) - min(starts.values())
    if spread <= MAX_START_SPREAD_S:
        return None
    at = ", ".join(f"{k} at {t:.6g} s" for k, t in starts.items())
    return f"the streams start {spread:.4g} s apart ({at}): not one clock?"


class UnitCheck:
    """The unit rules on a pushed stream's first :data:`SAMPLES` samples (:meth:`add`), or on fewer when
    the caller must know before then (:meth:`settle`).  Raises ``ValueError`` naming the stream and the
    unit its numbers look like; after one check it looks no more."""

    #: samples a check looks at: enough for a median no motion moves (a second at 50 Hz)
    SAMPLES = 50
    #: fewest samples :meth:`settle` judges
    MIN_SAMPLES = 3

    def __init__(self, key: str):
        self.key = key
        self.done = False
        self._t: list[np.ndarray] = []
        self._xyz: list[np.ndarray] = []
        self._n = 0

    def add(self, t: np.ndarray, xyz: np.ndarray) -> None:
        """The stream's next samples (cleaned: finite, increasing); checks once :data:`SAMPLES` are in."""
        if self.done or not len(t):
            return
        # copies: a caller may refill its buffers before the check runs
        self._t.append(np.array(t[: self.SAMPLES - self._n], dtype=float))
        self._xyz.append(np.array(xyz[: self.SAMPLES - self._n], dtype=float))
        self._n += len(self._t[-1])
        if self._n >= self.SAMPLES:
            self._check()

    def settle(self) -> None:
        """Check what is held now if that is at least :data:`MIN_SAMPLES` (before the samples are used)."""
        if not self.done and self._n >= self.MIN_SAMPLES:
            self._check()

    def _check(self) -> None:
        t, xyz = np.concatenate(self._t), np.concatenate(self._xyz)
        self.done = True
        self._t, self._xyz = [], []
        problem = time_unit_problem(self.key, t)  # its message names the stream
        if problem is None and (unit := unit_problem(self.key, xyz)) is not None:
            problem = f"{self.key}: {unit}"
        if problem is not None:
            raise ValueError(problem)
