"""x-io Technologies CSV (the x-io Fusion example ``sensor_data.csv``, x-IMU3 exports): units in the header.

One CSV file, header row first, e.g.::

    Time (s),Gyroscope X (deg/s),…,Accelerometer X (g),…,Magnetometer X (uT),Magnetometer Y (uT),…

Columns are found by name (``Gyroscope``/``Accelerometer``/``Magnetometer`` + ``X``/``Y``/``Z``) and converted
from the unit in brackets: deg/s or rad/s; g or m/s^2; uT/µT, nT or G/gauss. The accelerometer reads +1 g on
z lying flat (specific force) and the IMU's own axes are taken as the device frame (it is not a phone).

The magnetometer is sample-and-hold: it updates at ~20 Hz while rows come at 100 Hz, repeating the last
value. A row whose magnetometer value equals the previous one exactly is not a new measurement: it is left
out of the magnetometer stream and counted as ``mag:held_repeat``. A row with more cells than the header or
with a cell that is not a number is dropped from every stream and counted (``<stream>:extra_fields``,
``<stream>:non_numeric``).

A lab IMU, not a phone: its streams are taken as raw (``meta["mag_os_calibrated"]`` and
``["gyro_os_calibrated"]`` False), with no estimate of an OS, no date and no device id in the file.
"""

from __future__ import annotations

import re
from collections import Counter
from pathlib import Path

import numpy as np

from pdr_mag.conventions import GRAVITY
from replay.errors import InputError
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
from replay.recording import Recording
from replay.source import Feed, RecordingSource

NAME = "xio-csv"
_COL = re.compile(r"^(gyroscope|accelerometer|magnetometer) ([xyz]) \((.+)\)$")
_KEY = {"gyroscope": "gyro", "accelerometer": "accel", "magnetometer": "mag"}
_SCALE = {
    "gyro": {"deg/s": np.pi / 180.0, "dps": np.pi / 180.0, "rad/s": 1.0},
    "accel": {"g": GRAVITY, "m/s^2": 1.0, "m/s²": 1.0},
    "mag": {"ut": 1.0, "µt": 1.0, "nt": 1e-3, "g": 100.0, "gauss": 100.0, "a.u.": 1.0},
}


def detect(path: Path) -> bool:
    if not (path.is_file() and path.suffix.lower() == ".csv"):
        return False
    first = head_bytes(path, 4096).split(b"\n", 1)[0].decode("utf-8", "replace").strip().lower()
    return first.startswith("time (s),") and "magnetometer x (" in first


def _header(p: Path, fh) -> tuple[dict[str, list[int]], dict[str, str], int]:
    """Columns of x, y, z by stream, units by stream, and the column count, from the header row."""
    header = [c.strip() for c in fh.readline().strip().split(",")]
    if not header or header[0].lower() != "time (s)":
        raise InputError(p, f"bad header {','.join(header)!r}, expected 'Time (s),…'", 1)
    cols: dict[str, dict[str, int]] = {}
    units: dict[str, str] = {}
    for i, name in enumerate(header):
        m = _COL.match(name.lower())
        if m:
            key = _KEY[m.group(1)]
            cols.setdefault(key, {})[m.group(2)] = i
            units[key] = m.group(3)
    if "mag" not in cols or len(cols["mag"]) != 3:
        raise InputError(p, "no Magnetometer X/Y/Z columns (a stream missing)", 1)
    for key, unit in units.items():
        if unit not in _SCALE[key]:
            raise InputError(p, f"unknown unit {unit!r} for {key} (known: {', '.join(_SCALE[key])})", 1)
    return {k: [c[a] for a in "xyz"] for k, c in cols.items() if len(c) == 3}, units, len(header)


def _rows(p: Path, fh, idx: dict, ncol: int, builders: dict, dropped: Counter):
    """Parse the rows line by line (yielding after each) into the builders; held magnetometer repeats out."""
    last_mag = None
    short = ShortRows(p, dropped)
    for lineno, line in enumerate(fh, start=2):
        yield
        s = line.strip()
        if not s:
            continue
        parts = s.split(",")
        if len(parts) < ncol:
            why = f"expected {ncol} columns, got {len(parts)} (truncated file?)"
            short.found(lineno, why, tuple(builders))  # garbled: in every stream
            continue
        short.follows()
        vals = row_values(parts, ncol, dropped=dropped, keys=tuple(builders))  # garbled: in every stream
        if vals is None:
            continue
        t = vals[0]
        for key, ix in idx.items():
            v = [vals[i] for i in ix]
            if key == "mag":
                if v == last_mag:
                    dropped["mag:held_repeat"] += 1
                    continue
                last_mag = v
            builders[key].add(lineno, t, v)
    short.end()


def read(path) -> Recording:
    """Read an x-io CSV into a :class:`Recording`."""
    return open_source(path).collect()


def open_source(path) -> RecordingSource:
    """Open an x-io CSV: the header now, the rows as they are read (one pass for all streams)."""
    p = Path(path)
    with open_text(p) as fh:
        idx, units, _ = _header(p, fh)
    dropped: Counter = Counter()

    def chunks():
        with open_text(p) as fh:
            _, _, ncol = _header(p, fh)
            builders = {k: StreamBuilder(p, k, dropped) for k in idx}
            yield from chunks_of(fh, builders, every(_rows(p, fh, idx, ncol, builders, dropped)))

    specs = {k: StreamSpec(p, k, scale=_SCALE[k][units[k]], unit_hint=units[k]) for k in idx}
    return RecordingSource(
        specs,
        [Feed(tuple(idx), chunks, p.stat().st_size)],
        meta={"device": "x-io IMU", "units_in_file": units, "mag_os_calibrated": False,
              "gyro_os_calibrated": False},
        source=str(p),
        format=NAME,
        dropped=dropped,
    )
