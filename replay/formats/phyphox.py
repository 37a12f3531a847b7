"""phyphox CSV export (RWTH Aachen's phone-physics app): a folder or its ``.zip``.

Each sensor of the experiment is one CSV file (``Accelerometer.csv``, ``Gyroscope.csv``,
``Magnetometer.csv``, or ``Raw Data.csv`` for a one-sensor experiment) with a quoted header row, the
first column ``"Time (s)"`` (seconds since the experiment started: one clock for all files) and then, e.g.::

    "Time (s)","Magnetic field x (µT)","Magnetic field y (µT)","Magnetic field z (µT)","Absolute field (µT)"
    "Time (s)","Gyroscope x (rad/s)","Gyroscope y (rad/s)","Gyroscope z (rad/s)","Absolute (rad/s)"
    "Time (s)","Acceleration x (m/s^2)","Acceleration y (m/s^2)","Acceleration z (m/s^2)","Absolute …"

Files are recognised by their column names, not their file names (``Magnetic Field`` or ``Magnetic field``,
``µT`` or ``uT``); ``Linear Acceleration`` (gravity removed) is not used as the accelerometer. phyphox
exports comma-separated with decimal points by default; the tab-separated and the semicolon/decimal-comma
variants are read too. phyphox reports the same axes and units on Android and iOS (its iOS app multiplies
Core Motion's accelerations in g by −9.81, which gives Android's sign), i.e. the contract's: nothing is
converted. ``meta/device.csv`` (``property,value``) gives the device name when present. A row with more
cells than the header or with a cell that is not a number is dropped and counted
(``<stream>:extra_fields``, ``<stream>:non_numeric``).

What the phone states about itself (:mod:`replay.formats._phone`): phyphox's sensors are the OS-calibrated
ones — Android's ``TYPE_MAGNETIC_FIELD`` and ``TYPE_GYROSCOPE``, iOS's Core Motion device-motion field and
rotation rate — so ``mag_os_calibrated`` and ``gyro_os_calibrated`` are True. (An experiment may ask for the
raw magnetometer, ``calibrated="false"``; the export does not say so, and such a file is read as calibrated
too.) No estimate of the OS and no device id are exported (``device.csv`` leaves out phyphox's ``uniqueID``).
``meta/time.csv`` (``event, experiment time, system time, system time text``) gives ``date``: the UTC date
of the first ``START``'s ``system time`` (Unix s), else the date its text states (``2026-02-02
20:10:00.000 UTC+05:30``; another form: ``date_unreadable``).
"""

from __future__ import annotations

import functools
import re
from collections import Counter
from pathlib import Path

from replay.errors import InputError
from replay.formats._common import (
    Bundle,
    ShortRows,
    StreamBuilder,
    StreamSpec,
    chunks_of,
    every,
    iter_csv,
    row_values,
)
from replay.formats._phone import put_date, utc_date
from replay.recording import Recording
from replay.source import Feed, RecordingSource

NAME = "phyphox"

_PATTERNS = {
    "mag": re.compile(r"^magnetic field ([xyz]) \((?:µt|μt|ut)\)$"),
    "gyro": re.compile(r"^gyroscope ([xyz]) \(rad/s\)$"),
    "accel": re.compile(r"^acceleration ([xyz]) \(m/s(?:\^2|²)\)$"),
}
_UNITS = {"mag": "µT", "gyro": "rad/s", "accel": "m/s²"}


def _first_line(b: Bundle, name: str) -> str:
    with b.open(name) as fh:
        return fh.readline().lstrip("\ufeff").strip()


def _dialect(header: str) -> tuple[str, bool]:
    """(delimiter, decimal comma?) of a phyphox CSV from its header line."""
    if "\t" in header:
        return "\t", False
    if ";" in header and "," not in header.replace("(µT)", ""):
        return ";", True
    return ",", False


def _classify(cells: list[str]) -> tuple[str, list[int]] | None:
    """Stream key and column indices (t, x, y, z) of a header row, or None."""
    names = [c.strip().lower() for c in cells]
    if not names or names[0] != "time (s)":
        return None
    for key, pat in _PATTERNS.items():
        idx = {}
        for i, n in enumerate(names):
            m = pat.match(n)
            if m:
                idx[m.group(1)] = i
        if len(idx) == 3:
            return key, [0, idx["x"], idx["y"], idx["z"]]
    return None


def _csv_members(b: Bundle) -> list[str]:
    return sorted(n for n in b.names() if n.lower().endswith(".csv") and not n.lower().startswith("meta/"))


def detect(path: Path) -> bool:
    if not (path.is_dir() or Bundle.is_zip(path)):
        return False
    try:
        b = Bundle(path)
    except InputError:
        return False
    try:
        for name in _csv_members(b)[:20]:
            header = _first_line(b, name)
            delim, _ = _dialect(header)
            cells = [c.strip().strip('"') for c in header.split(delim)]
            hit = _classify(cells)
            if hit is not None and hit[0] == "mag":
                return True
        return False
    finally:
        b.close()


def _classify_member(b: Bundle, name: str) -> tuple[str, list[int], int] | None:
    """Stream key, column indices (t, x, y, z) and column count of a member's header row, or None."""
    delim, _ = _dialect(_first_line(b, name))
    with b.open(name) as fh:
        try:
            _, header = next(iter_csv(fh, b.where(name), delimiter=delim))
        except StopIteration:
            return None
    hit = _classify([c.lstrip("\ufeff") for c in header])
    return None if hit is None else (*hit, len(header))


def _member_chunks(p: Path, name: str, key: str, idx: list[int], n_header: int, dropped: Counter):
    """The rows of one member, parsed a chunk at a time (a Feed's chunks)."""
    b = Bundle(p)
    where = b.where(name)
    delim, decimal_comma = _dialect(_first_line(b, name))
    builder = StreamBuilder(where, key, dropped)
    need = max(idx) + 1

    def rows(fh):
        lines = iter_csv(fh, where, delimiter=delim)
        next(lines)  # the header
        short = ShortRows(where, dropped)
        for lineno, cells in lines:
            if not cells or all(not c.strip() for c in cells):
                continue
            if len(cells) < need:
                short.found(lineno, f"expected {n_header} columns, got {len(cells)} (truncated?)", (key,))
                continue
            short.follows()
            if decimal_comma:
                cells = [c.replace(",", ".") for c in cells]
            vals = row_values(cells, n_header, dropped=dropped, keys=(key,))
            if vals is None:
                continue
            yield builder.add(lineno, vals[idx[0]], [vals[i] for i in idx[1:]])
        short.end()

    try:
        with b.open(name) as fh:
            yield from chunks_of(fh, {key: builder}, every(rows(fh)))
    finally:
        b.close()


def _device(b: Bundle) -> str | None:
    name = b.find("device.csv")
    if name is None:
        return None
    props = {}
    with b.open(name) as fh:
        for _, cells in iter_csv(fh, b.where(name)):
            if len(cells) >= 2:
                props[cells[0].strip()] = cells[1].strip()
    model = props.get("deviceModel") or props.get("model")
    brand = props.get("deviceBrand") or props.get("deviceManufacturer") or ""
    return f"{brand} {model}".strip() if model else None


def _start_date(b: Bundle, meta: dict) -> None:
    """``date`` from ``meta/time.csv``'s first ``START`` row (module docstring), when the export has one."""
    name = next((n for n in b.names() if n.lower() == "meta/time.csv"), None)
    if name is None:
        return
    delim, decimal_comma = _dialect(_first_line(b, name))
    with b.open(name) as fh:
        rows = iter_csv(fh, b.where(name), delimiter=delim)
        try:
            _, header = next(rows)
        except StopIteration:
            return
        cols = {c.strip().lstrip("\ufeff").lower(): i for i, c in enumerate(header)}

        def cell(cells: list[str], name: str) -> str:
            i = cols.get(name)
            return cells[i].strip() if i is not None and i < len(cells) else ""

        for _, cells in rows:
            if cell(cells, "event") != "START":
                continue
            unix = cell(cells, "system time")
            try:
                meta["date"] = utc_date(float(unix.replace(",", ".") if decimal_comma else unix))
            except (ValueError, OverflowError, OSError):
                put_date(meta, cell(cells, "system time text"))
            return


def read(path) -> Recording:
    """Read a phyphox CSV export (folder or zip) into a :class:`Recording`."""
    return open_source(path).collect()


def open_source(path) -> RecordingSource:
    """Open a phyphox CSV export (folder or zip): each sensor's file is read as it is consumed."""
    p = Path(path)
    b = Bundle(p)
    try:
        dropped: Counter = Counter()
        specs, feeds = {}, []
        for name in _csv_members(b):
            got = _classify_member(b, name)
            if got is None or got[0] in specs:
                continue
            key, idx, n_header = got
            specs[key] = StreamSpec(b.where(name), key, unit_hint=_UNITS[key])
            chunks = functools.partial(_member_chunks, p, name, key, idx, n_header, dropped)
            feeds.append(Feed((key,), chunks, b.size(name)))
        if "mag" not in specs:
            raise InputError(p, "no magnetometer file (columns 'Magnetic field x (µT)' …): a stream missing")
        meta: dict = {"mag_os_calibrated": True, "gyro_os_calibrated": True}
        device = _device(b)
        if device:
            meta["device"] = device
        _start_date(b, meta)
    finally:
        b.close()
    return RecordingSource(specs, feeds, meta=meta, source=str(p), format=NAME, dropped=dropped)
