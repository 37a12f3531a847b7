"""IPIN indoor-positioning competition logfiles (the GetSensorData app's format, LOPSI / CAR-CSIC).

A text file: ``%`` lines are comments (the header documents the layout and names the phone), data lines are
``;``-separated records whose first field is the type; the fields after it:

* ``ACCE``: AppTimestamp (s), SensorTimestamp (s), Acc_X, Acc_Y, Acc_Z (m/s²), Accuracy;
* ``GYRO``: AppTimestamp, SensorTimestamp, Gyr_X, Gyr_Y, Gyr_Z (rad/s), Accuracy;
* ``MAGN``: AppTimestamp, SensorTimestamp, Mag_X, Mag_Y, Mag_Z (µT), Accuracy;
* ``POSI``: Timestamp (s), Counter, Latitude (deg), Longitude (deg), FloorID, BuildingID — ground truth;
* ``AHRS``: AppTimestamp, SensorTimestamp, PitchX, RollY, YawZ (deg), then the x, y, z of Android's
  ``TYPE_ROTATION_VECTOR`` (magnetic north; the header calls them ``Quat(2)…Quat(4)`` or
  ``RotVecX()…RotVecZ()``), Accuracy — the phone's own fusion.

Other records (``PRES``, ``WIFI``, ``GNSS``, ``BLE4``, …) are skipped. Android sensors in Android's
frame and units: nothing is converted. An ``ACCE``, ``GYRO``, ``MAGN`` or ``POSI`` record with more fields
than its type has (the six above) or with a field that is not a number (the floor and building of a ``POSI``
may be text) is dropped and counted (``<stream>:extra_fields``, ``<stream>:non_numeric``; ``position:…``);
one with fewer is a truncated file when it is the log's last line, else dropped and counted as well
(``<stream>:short_row``: :class:`~replay.formats._common.ShortRows`).

Time. ``AppTimestamp`` is the app's clock (seconds since logging started), common to all records but
stamped on delivery, so jittered; ``SensorTimestamp`` is the sensor's own, precise timestamp on its own
origin. The sensor timestamps are moved onto the app clock by the smallest ``AppTimestamp -
SensorTimestamp`` (the delivery latency's floor), so the streams share the app clock (and the ``POSI`` fixes)
while keeping the sensors' precise spacing and their relative timing: one shift for all streams when their
sensor clocks agree (within 0.5 s, the usual case on Android), else one shift per stream. The shifts need
the whole file: a first pass finds them (and the fixes and the header), the second streams the samples.
``POSI`` fixes go to ``meta["positions"]`` as ``[t, latitude_deg, longitude_deg, floor, building]``; the
first one also sets ``latitude_deg``/``longitude_deg``. The ``AHRS`` rotation vectors become
``references["os"]`` (:mod:`replay.formats._attitude`; the angles are not read: the app's versions differ in
their yaw's sign), on the app clock by the streams' shift when their sensor clock is the same (within
0.5 s), else by their own; an ``AHRS`` record is garbled like the others (more than its nine fields:
``os:extra_fields``; a field that is not a number: ``os:non_numeric``), and one with a value that is NaN or
missing (too short) is counted as ``os:nan`` — the series is a reference, not a sensor stream, never an
error. The ``% Model:`` and ``% Manufacturer:`` header lines give ``meta["device"]``.

What the phone states about itself (:mod:`replay.formats._phone`): ``MAGN`` and ``GYRO`` are Android's
``TYPE_MAGNETIC_FIELD`` and ``TYPE_GYROSCOPE``, the streams the OS has already calibrated
(``mag_os_calibrated`` and ``gyro_os_calibrated`` True); the OS's estimates are not in the file (no bias
or drift columns), nor is a device id. ``% Date of creation: …`` (Java's ``Date.toString()``, e.g.
``Thu Sep 12 10:22:32 GMT+02:00 2019``, or an ISO-like date) gives ``meta["date"]``, the calendar date as
written; a date in another form is kept as text under ``date_unreadable``. With the ``POSI`` fixes' place,
the date lets the pipeline use the field model (and true north).
"""

from __future__ import annotations

import math
from collections import Counter
from pathlib import Path

from replay.errors import InputError
from replay.formats._attitude import in_output_north, rotation_vector_quat
from replay.formats._common import (
    ShortRows,
    StreamBuilder,
    StreamSpec,
    chunks_of,
    every,
    head_bytes,
    open_text,
    row_values,
)
from replay.formats._common import is_float as _is_number
from replay.formats._phone import put_date
from replay.recording import Recording
from replay.source import Feed, RecordingSource

NAME = "ipin"
_TYPES = {"ACCE": "accel", "GYRO": "gyro", "MAGN": "mag"}
_UNITS = {"accel": "m/s²", "gyro": "rad/s", "mag": "µT"}
_SAME_CLOCK_S = 0.5  # per-stream shifts closer than this: the sensors share one clock
_FIELDS = 6  # fields after the type of every record read here but AHRS
_AHRS_FIELDS = 9  # AppTimestamp, SensorTimestamp, the three angles, the rotation vector's x, y, z, Accuracy


def detect(path: Path) -> bool:
    if not path.is_file():
        return False
    head = head_bytes(path, 16384)
    if b"\x00" in head:
        return False
    lines = head.splitlines()
    data = [ln for ln in lines if ln and not ln.startswith(b"%")]
    if any(ln.startswith((b"ACCE;", b"MAGN;", b"GYRO;")) for ln in data[:200]):
        return True
    return any(b"'MAGN;AppTimestamp" in ln for ln in lines if ln.startswith(b"%"))


def _parse(p: Path, fh, builders: dict, found: dict):
    """Parse the logfile line by line into ``builders`` (yielding after each line, counting garbled records
    in ``found["dropped"]``); ``found`` collects the delivery-latency floors (``offsets``), the
    ``positions``, the header's ``model``/``maker``/``created`` (the ``Date of creation`` text) and, when
    ``found["os"]`` is a builder, the ``AHRS`` rotation vectors (sensor clock) and their floor
    (``os_offset``)."""
    short = ShortRows(p, found["dropped"])
    for lineno, line in enumerate(fh, start=1):
        yield
        if short.pending is not None and line.strip():
            short.follows()
        if line.startswith("%"):
            body = line.lstrip("% ").strip()
            if body.startswith("Model:"):
                found["model"] = body.split(":", 1)[1].strip()
            elif body.startswith("Manufacturer:"):
                found["maker"] = body.split(":", 1)[1].strip()
            elif body.startswith("Date of creation:") and "created" not in found:
                found["created"] = body.split(":", 1)[1].strip()
            continue
        s = line.strip()
        if not s:
            continue
        parts = s.split(";")
        kind = parts[0]
        key = _TYPES.get(kind)
        if key is not None:
            if len(parts) < 6:
                why = f"{kind}: expected 5 values after the type, got {len(parts) - 1} (truncated?)"
                short.found(lineno, why, (key,))
                continue
            vals = row_values(parts[1:], _FIELDS, dropped=found["dropped"], keys=(key,))
            if vals is None:
                continue
            app, sensor, x, y, z = vals[:5]
            if builders[key].add(lineno, sensor, (x, y, z)):
                found["offsets"][key] = min(found["offsets"][key], app - sensor)
        elif kind == "POSI":
            if len(parts) < 5:
                short.found(lineno, f"POSI: expected at least 4 values, got {len(parts) - 1} (truncated?)",
                            ("position",))  # fmt: skip
                continue
            # only the first four fields must be numbers: the floor and the building may be text
            vals = row_values(parts[1:], _FIELDS, dropped=found["dropped"], keys=("position",), numeric=4)
            if vals is None:
                continue
            t, _, lat, lon = vals
            rest = [float(v) if _is_number(v) else v.strip() for v in parts[5:7]]
            found["positions"].append([t, lat, lon, *rest])
        elif kind == "AHRS" and found.get("os") is not None:
            b = found["os"]
            vals = row_values(parts[1:], _AHRS_FIELDS, dropped=b.dropped, keys=(b.key,))
            if vals is None:
                continue
            vals += [math.nan] * (_AHRS_FIELDS - len(vals))  # a value missing: counted as os:nan
            if b.add(lineno, vals[1], vals[5:8]):
                found["os_offset"] = min(found["os_offset"], vals[0] - vals[1])
    short.end()


def _chunks(p: Path, dropped: Counter, found: dict):
    found["dropped"] = dropped
    builders = {k: StreamBuilder(p, k, dropped) for k in _TYPES.values()}
    with open_text(p) as fh:
        yield from chunks_of(fh, builders, every(_parse(p, fh, builders, found)))


def read(path) -> Recording:
    """Read an IPIN/GetSensorData logfile into a :class:`Recording`."""
    return open_source(path).collect()


def open_source(path) -> RecordingSource:
    """Open an IPIN/GetSensorData logfile: a first pass for the clock shifts and fixes, then streamed."""
    p = Path(path)
    os_dropped: Counter = Counter()
    found: dict = {"offsets": dict.fromkeys(_TYPES.values(), math.inf), "positions": [],
                   "os": StreamBuilder(p, "os", os_dropped), "os_offset": math.inf}
    counts: Counter = Counter()
    for _, chunk in _chunks(p, Counter(), found):
        counts.update({k: len(t) for k, (t, _) in chunk.items()})
    if not counts["mag"]:
        raise InputError(p, "no MAGN records (a stream missing)")
    offsets = found["offsets"]
    finite = [o for k, o in offsets.items() if counts[k]]
    if max(finite) - min(finite) < _SAME_CLOCK_S:  # one sensor clock (the usual case): one shift for all
        offsets = dict.fromkeys(offsets, min(finite))
    keys = [k for k in _TYPES.values() if counts[k]]
    specs = {k: StreamSpec(p, k, t_offset=offsets[k], unit_hint=_UNITS[k]) for k in keys}
    dropped: Counter = Counter(os_dropped)
    chunks = lambda: _chunks(p, dropped, {"offsets": dict(offsets), "positions": []})  # noqa: E731
    feed = Feed(tuple(keys), chunks, p.stat().st_size)
    meta: dict = {"mag_os_calibrated": True, "gyro_os_calibrated": True}
    if found.get("model"):
        meta["device"] = f"{found.get('maker', '')} {found['model']}".strip()
    if "created" in found:
        put_date(meta, found["created"])
    positions = found["positions"]
    if positions:
        meta["positions"] = positions
        meta["latitude_deg"], meta["longitude_deg"] = positions[0][1], positions[0][2]
    references = {}
    if len(found["os"]):
        t, xyz = found["os"].arrays()
        shift = found["os_offset"]
        if len(set(offsets.values())) == 1 and abs(shift - min(finite)) < _SAME_CLOCK_S:
            shift = min(finite)  # the streams' one sensor clock
        references["os"] = (t + shift, in_output_north(rotation_vector_quat(xyz), meta))
    return RecordingSource(specs, [feed], meta=meta, source=str(p), format=NAME, dropped=dropped,
                           references=references)
