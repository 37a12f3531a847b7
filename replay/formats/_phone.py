"""What a recording states about the phone itself: the OS's own calibration, the date, the device's id.

The readers put these into ``Recording.meta`` under the keys of INTERFACE.md ("Recording ``meta``: what the
phone knows about itself"); nothing here is a measurement of ours, only what the file says.

OS offset estimates
-------------------
A logger that records the raw field and the OS-calibrated one side by side states the OS's hard-iron estimate
as their difference (:func:`bias_from_pair`). Android's uncalibrated sensors deliver, with every sample, the
offset the OS currently estimates:
``TYPE_MAGNETIC_FIELD_UNCALIBRATED`` the hard-iron bias ``b`` (µT; raw = OS-calibrated + ``b``),
``TYPE_GYROSCOPE_UNCALIBRATED`` the drift ``d`` (rad/s; raw = OS-calibrated + ``d``). The estimate is
piecewise constant: the OS replaces it now and then (when its own calibration converges, or after a
magnetic disturbance). :class:`OsEstimate` keeps the value in force at the stream's first sample and each
later change ``[t, x, y, z]`` (``t`` the time of the first sample that carries the new value, on the
recording's clock) — a few numbers however long the recording. A value that is NaN, infinite or missing
is an odd sample: counted in the recording's ``dropped`` as ``<key>:nan`` (``key`` = ``mag_os_bias`` or
``gyro_os_bias``), and the estimate in force stays as it was (the readers drop a row with a cell of text
before it gets here, as ``<stream>:non_numeric``). A value of exactly (0, 0, 0) is an OS that states no
estimate (a phone without its own hard-iron calibration reports its raw field with a zero bias; no estimate
of a real offset comes out at zero to the last bit): it says nothing, like a row without the columns — so a
phone that never estimated has no ``mag_os_bias_uT`` (the pipeline starts as with no prior instead of from
an offset of zero: the raw field, hundreds of µT, is not the Earth's), and an OS that drops its estimate
mid-recording leaves the one in force as it was.

Dates
-----
:func:`stated_date` reads the date a header states, in the forms phone apps write: Java's
``Date.toString()`` (``Thu Sep 12 10:22:32 GMT+02:00 2019``, the GetSensorData app's ``Date of
creation``) and ISO-like dates (``2019-09-12 10:22:32``, ``2019/09/12``, ``2019-09-12T10:22:32.5Z``,
``2026-02-02 20:10:00.000 UTC+05:30``). The result is the calendar date as written (the phone's local date:
the field model needs the day, not the hour); anything else is an unreadable date, which the readers keep
as text under ``date_unreadable`` — never an error.
"""

from __future__ import annotations

import datetime as dt
import math
import re
from collections import Counter

import numpy as np

#: meta keys of each estimate: (first value, changes)
META_KEYS = {
    "mag_os_bias": ("mag_os_bias_uT", "mag_os_bias_changes"),
    "gyro_os_bias": ("gyro_os_bias_rad_s", "gyro_os_bias_changes"),
}


class OsEstimate:
    """The OS's offset estimate of one stream as its samples state it: the first value and each change.

    Parameters
    ----------
    key : {"mag_os_bias", "gyro_os_bias"}
        Which estimate (names the meta keys, :data:`META_KEYS`, and the odd-sample count).
    dropped : Counter
        The recording's counter of odd samples (``<key>:nan``).

    Attributes
    ----------
    first : list of float or None
        The value in force at the first sample that states one.
    changes : list of [t, x, y, z]
        Each later change, at the time of the first sample carrying the new value.
    """

    def __init__(self, key: str, dropped: Counter):
        if key not in META_KEYS:
            raise ValueError(f"key: expected one of {tuple(META_KEYS)}, got {key!r}")
        self.key = key
        self.dropped = dropped
        self.first: list[float] | None = None
        self.last: list[float] | None = None
        self.changes: list[list[float]] = []

    def add(self, t: float, values) -> None:
        """One sample's estimate (3 numbers, or the text cells that hold them)."""
        try:
            v = [float(x) for x in values]
        except (TypeError, ValueError):
            v = []
        if len(v) != 3 or not all(math.isfinite(x) for x in v):
            self.dropped[f"{self.key}:nan"] += 1
            return
        if v == [0.0, 0.0, 0.0]:  # no estimate stated (module docstring)
            return
        if self.first is None:
            self.first = v
        elif v != self.last:
            self.changes.append([float(t), *v])
        self.last = v

    def add_block(self, t: np.ndarray, values: np.ndarray) -> None:
        """Many samples' estimates at once (``values`` (N, 3), NaN where a cell was not a number)."""
        t = np.asarray(t, dtype=float)
        v = np.asarray(values, dtype=float).reshape(len(t), 3)
        ok = np.all(np.isfinite(v), axis=1)
        if (~ok).any():
            self.dropped[f"{self.key}:nan"] += int((~ok).sum())
        t, v = t[ok], v[ok]
        stated = np.any(v != 0.0, axis=1)  # (0, 0, 0): no estimate stated (module docstring)
        t, v = t[stated], v[stated]
        if len(t) == 0:
            return
        if self.first is None:
            self.first = v[0].tolist()
            self.last = self.first
        prev = np.vstack([np.asarray(self.last)[None, :], v[:-1]])
        for i in np.flatnonzero(np.any(v != prev, axis=1)):
            self.changes.append([float(t[i]), *v[i].tolist()])
        self.last = v[-1].tolist()

    def to_meta(self, meta: dict) -> None:
        """Put the first value and the changes (an empty list: it never changed) into ``meta``; nothing
        when no sample stated a readable value."""
        if self.first is None:
            return
        first_key, changes_key = META_KEYS[self.key]
        meta[first_key] = list(self.first)
        meta[changes_key] = [list(c) for c in self.changes]


#: the OS's hard-iron estimate from a raw and an OS-calibrated field logged side by side is taken over the
#: calibrated field's first this many seconds, s
PAIR_WINDOW_S = 2.0


def bias_from_pair(t_raw, raw, t_cal, cal) -> list[float] | None:
    """The OS's hard-iron estimate at the start of a recording that logs the raw field and the OS-calibrated
    one side by side (iOS Core Motion, Sensor Logger's two magnetometer files): ``b = raw − calibrated``, the
    raw field interpolated to each calibrated sample's time, over the calibrated samples of the first
    :data:`PAIR_WINDOW_S` seconds inside the raw stream; the component-wise median (the two are often sampled
    at different rates — 25 and 95 Hz on the iPhone 5 — and the interpolation errs by tens of µT in a quick
    turn; the median of two seconds' samples does not see it). Only the value in force at the start: the OS
    refines it without saying when, and a refinement is found in the data like any other change (the stale
    test). None with fewer than two raw samples or no calibrated one inside them.  Times in seconds, fields
    (n, 3) in µT, both on one clock."""
    t_raw, raw = np.asarray(t_raw, dtype=float), np.asarray(raw, dtype=float).reshape(-1, 3)
    t_cal, cal = np.asarray(t_cal, dtype=float), np.asarray(cal, dtype=float).reshape(-1, 3)
    if len(t_raw) < 2 or not len(t_cal):
        return None
    inside = (t_cal >= t_raw[0]) & (t_cal <= t_raw[-1])
    t_cal, cal = t_cal[inside], cal[inside]
    if not len(t_cal):
        return None
    first = t_cal <= t_cal[0] + PAIR_WINDOW_S
    t_cal, cal = t_cal[first], cal[first]
    raw_at = np.column_stack([np.interp(t_cal, t_raw, raw[:, k]) for k in range(3)])
    return [round(float(v), 4) for v in np.median(raw_at - cal, axis=0)]


_MONTHS = {m: i for i, m in enumerate(
    ("jan", "feb", "mar", "apr", "may", "jun", "jul", "aug", "sep", "oct", "nov", "dec"), start=1)}
_ZONE = r"(?:Z|UTC|GMT|(?:UTC|GMT)?\s?[+-]\d{1,2}(?::?\d{2})?|[A-Z]{2,5})"
# Java's Date.toString(): "EEE MMM dd HH:mm:ss zzz yyyy" (zzz: "GMT+02:00", "CEST", "UTC", … or none)
_JAVA = re.compile(
    r"^[A-Za-z]{3},?\s+(?P<mon>[A-Za-z]{3})\s+(?P<day>\d{1,2})\s+(?P<hms>\d{1,2}:\d{2}:\d{2})"
    r"(?:\s+(?P<zone>[A-Za-z]{1,5}(?:[+-]\d{1,2}(?::?\d{2})?)?|[+-]\d{2}:?\d{2}))?\s+(?P<year>\d{4})$"
)
# ISO-like: "2019-09-12", "2019/09/12", then optionally " 10:22:32[.fff]" or "T…", then optionally a zone
_ISO = re.compile(
    r"^(?P<year>\d{4})(?P<sep>[-/])(?P<mon>\d{1,2})(?P=sep)(?P<day>\d{1,2})"
    r"(?:[ T_](?P<h>\d{1,2})[:-](?P<m>\d{2})(?:[:-](?P<s>\d{2})(?:\.\d+)?)?(?:\s?" + _ZONE + r")?)?$"
)


def _hms_ok(h, m, s) -> bool:
    return 0 <= int(h) <= 23 and 0 <= int(m) <= 59 and 0 <= int(s or 0) <= 60


def stated_date(text: str) -> str | None:
    """The calendar date ``YYYY-MM-DD`` that ``text`` states (module docstring: the accepted forms), or
    None when it is not one of them (or names a day that does not exist)."""
    s = " ".join(str(text).split())
    m = _JAVA.match(s)
    if m:
        mon = _MONTHS.get(m["mon"].lower())
        h, mi, sec = m["hms"].split(":")
        if mon is None or not _hms_ok(h, mi, sec):
            return None
        year, day = int(m["year"]), int(m["day"])
    else:
        m = _ISO.match(s)
        if not m or (m["h"] is not None and not _hms_ok(m["h"], m["m"], m["s"])):
            return None
        year, mon, day = int(m["year"]), int(m["mon"]), int(m["day"])
    try:
        return dt.date(year, mon, day).isoformat()
    except ValueError:
        return None


def put_date(meta: dict, text: str) -> None:
    """``meta["date"]`` from a stated date, else the text as written under ``meta["date_unreadable"]``."""
    day = stated_date(text)
    if day is not None:
        meta["date"] = day
    elif str(text).strip():
        meta["date_unreadable"] = str(text).strip()


def utc_date(unix_s: float) -> str:
    """The UTC calendar date of a Unix time (s)."""
    return dt.datetime.fromtimestamp(float(unix_s), dt.UTC).date().isoformat()
