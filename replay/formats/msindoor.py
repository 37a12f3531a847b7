"""The Indoor Location Competition 2.0 path logs (Microsoft / XYZ10 shopping-mall traces).

One tab-separated text file per walk. ``#`` lines are the header (``startTime:<unix ms>``, site and floor,
``Brand``/``Model``, one line per sensor with ``type:<android type>`` and ``maximumRange``, ``endTime``).
Data lines are ``<unix ms> <TAB> TYPE_… <TAB> values…``:

======================================  ===================================================
``TYPE_ACCELEROMETER``                  x, y, z (m/s², Android frame), accuracy
``TYPE_ACCELEROMETER_UNCALIBRATED``     x, y, z (m/s², no factory bias compensation), bias x, y, z, accuracy
``TYPE_GYROSCOPE``                      x, y, z (rad/s), accuracy
``TYPE_GYROSCOPE_UNCALIBRATED``         x, y, z (rad/s), drift x, y, z, accuracy
``TYPE_MAGNETIC_FIELD``                 x, y, z (µT, calibrated by the OS), accuracy
``TYPE_MAGNETIC_FIELD_UNCALIBRATED``    x, y, z (µT, raw), bias x, y, z, accuracy
``TYPE_WAYPOINT``                       x, y (metres on the floor map: x east, y north)
``TYPE_ROTATION_VECTOR``                x, y, z (the phone's own fusion, magnetic north), accuracy
======================================  ===================================================

Android's frame and units are the contract's, so nothing is converted. The raw streams are preferred: the
magnetometer from ``TYPE_MAGNETIC_FIELD_UNCALIBRATED`` and the gyroscope from ``TYPE_GYROSCOPE_UNCALIBRATED``;
the calibrated types are used only when the raw ones are absent (then ``meta["mag_os_calibrated"]`` /
``meta["gyro_os_calibrated"]`` is True, else False). The accelerometer is the other way round:
``TYPE_ACCELEROMETER`` (the tilt wants the factory's bias compensation, and no estimate of it is learnt here),
``TYPE_ACCELEROMETER_UNCALIBRATED`` only when a trace has no calibrated one.

What the phone states about its own calibration (:mod:`replay.formats._phone`): the OS's hard-iron estimate
(the bias columns of ``TYPE_MAGNETIC_FIELD_UNCALIBRATED``) in force at the first magnetometer sample that
states one (bias columns of exactly zero state none), ``mag_os_bias_uT``, and its later changes,
``mag_os_bias_changes`` (one trace of the dataset's 40 changes it, once); the same for the gyroscope's drift
columns, ``gyro_os_bias_rad_s`` / ``gyro_os_bias_changes``; a bias cell that is NaN or infinite, or missing,
is counted as ``mag_os_bias:nan`` / ``gyro_os_bias:nan`` (text in a cell makes the line garbled, below). The
header states no device id. Times are seconds since the header's ``startTime`` (``meta["start_time_unix"]``;
without that header line, the first data line's time when it is a Unix time in ms, which gives the date as
well). The surveyor's waypoints go to ``meta["waypoints"]`` as ``[t, x_m, y_m]`` (truth for position and
segment headings, true north).

Samples at the sensor's ``maximumRange`` from the header are counted as ``<stream>:saturated``. A line of a
type read here with more values than the type has (4 with the accuracy, 7 for the uncalibrated types, 2 for a
waypoint) or with a field that is not a number is dropped and counted (``<stream>:extra_fields``,
``<stream>:non_numeric``; ``waypoint:…``); one with fewer than the x, y, z (x, y) it needs (or a line of one
column) is a truncated file when it is the log's last line, else dropped and counted as well
(``<stream>:short_row``, a line of one column in every stream read:
:class:`~replay.formats._common.ShortRows`).

The phone's own fusion (``TYPE_ROTATION_VECTOR``) becomes ``references["os"]``
(:mod:`replay.formats._attitude`: in the pipeline's north, i.e. turned by the WMM declination when the map
gives the position); its lines are garbled like the others (more than x, y, z and the accuracy:
``os:extra_fields``; a field not a number: ``os:non_numeric``), and one with a value NaN or missing is counted
as ``os:nan``. Other line types (Wi-Fi, beacons, …) are skipped.

Choosing the streams needs the whole file (and the header's ``endTime``, the waypoints and the OS's estimates
are spread over it): a first pass reads it without keeping samples (but the waypoints, the rotation vectors
and the estimates' changes), the second streams the chosen types. When the floor's ``geojson_map.json`` is
beside ``path_data_files/`` (the dataset's layout), the centre of its WGS84 bounding box gives
``latitude_deg``/``longitude_deg`` (so the field model, and true north, are known) and ``map_bbox_deg`` =
[lat_min, lon_min, lat_max, lon_max] (the waypoints' origin is its south-west corner).
"""

from __future__ import annotations

import json
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
    read_text,
    row_values,
)
from replay.formats._phone import OsEstimate, utc_date
from replay.recording import Recording
from replay.source import Feed, RecordingSource

NAME = "ms-indoor"

# data type → (stream, rank: lower is preferred), Android sensor type number of its header line
_TYPES = {
    "TYPE_MAGNETIC_FIELD_UNCALIBRATED": ("mag", 0, 14),
    "TYPE_MAGNETIC_FIELD": ("mag", 1, 2),
    "TYPE_ACCELEROMETER": ("accel", 0, 1),
    "TYPE_ACCELEROMETER_UNCALIBRATED": ("accel", 1, 35),
    "TYPE_GYROSCOPE_UNCALIBRATED": ("gyro", 0, 16),
    "TYPE_GYROSCOPE": ("gyro", 1, 4),
}
# values after the type a line may have: x, y, z, accuracy (+ the bias or drift x, y, z); x, y of a waypoint
_MOST = {kind: 7 if kind.endswith("_UNCALIBRATED") else 4 for kind in _TYPES} | {
    "TYPE_WAYPOINT": 2,
    "TYPE_ROTATION_VECTOR": 4,
}


#: Unix times in ms from 2000 to 2100: a data line's time that is one states the trace's date.
_UNIX_MS = (946_684_800_000.0, 4_102_444_800_000.0)


def _is_unix_ms(t_ms: float) -> bool:
    return _UNIX_MS[0] <= t_ms < _UNIX_MS[1]


def detect(path: Path) -> bool:
    if not path.is_file():
        return False
    head = head_bytes(path, 4096)
    return head.startswith(b"#\tstartTime:") or (
        b"\tTYPE_ACCELEROMETER\t" in head and not head.startswith(b"\x89")
    )


def _header(line: str, meta: dict, ranges: dict) -> None:
    fields = {}
    for cell in line.lstrip("#").strip().split("\t"):
        k, sep, v = cell.partition(":")
        if sep:
            fields[k.strip()] = v.strip()
    if "startTime" in fields:
        meta["start_time_unix"] = float(fields["startTime"]) / 1000.0
    if "Model" in fields:
        meta["device"] = f"{fields.get('Brand', '')} {fields['Model']}".strip()
    if "FloorName" in fields:
        meta["site"] = f"{fields.get('SiteName', '')} {fields['FloorName']}".strip()
    if "type" in fields and "maximumRange" in fields:
        try:
            ranges[int(fields["type"])] = float(fields["maximumRange"])
        except ValueError:
            pass


#: A floor map's bounding box spans at most this many degrees (11 km): wider, its coordinates are no
#: longitude and latitude (a map drawn in metres) and it gives no place.
MAP_SPAN_DEG = 0.1


def _site_location(path: Path, meta: dict) -> None:
    """Position from the floor's ``geojson_map.json`` (``<floor>/geojson_map.json`` beside
    ``path_data_files/``): the centre of its WGS84 bounding box, whose south-west corner is the map origin
    (none when the box spans more than :data:`MAP_SPAN_DEG`)."""
    geo = path.parent.parent / "geojson_map.json"
    if not geo.is_file():
        return
    try:
        features = json.loads(read_text(geo))["features"]
    except (ValueError, KeyError, TypeError, OSError):
        return  # the map is optional context, not part of the recording
    lons: list[float] = []
    lats: list[float] = []

    def walk(c):
        if isinstance(c, list) and len(c) >= 2 and all(isinstance(v, (int, float)) for v in c[:2]):
            lons.append(float(c[0]))
            lats.append(float(c[1]))
        elif isinstance(c, list):
            for x in c:
                walk(x)

    for f in features if isinstance(features, list) else []:
        walk((f.get("geometry") or {}).get("coordinates"))
    if (lats and -90 <= min(lats) <= max(lats) <= 90 and -180 <= min(lons) <= max(lons) <= 180
            and max(max(lats) - min(lats), max(lons) - min(lons)) <= MAP_SPAN_DEG):
        meta["latitude_deg"] = (min(lats) + max(lats)) / 2
        meta["longitude_deg"] = (min(lons) + max(lons)) / 2
        meta["map_bbox_deg"] = [min(lats), min(lons), max(lats), max(lons)]


def _parse(p: Path, fh, builders: dict, found: dict, kinds):
    """Parse the log line by line (yielding after each line) into ``builders`` (by data type, made here for
    the types in ``kinds``, counting odd samples in ``found["dropped"]``); ``found`` collects the header
    (``meta``, ``ranges``), the ``waypoints``, the first time (``t0_ms``) and, when ``found["os"]`` is a
    builder, the rotation vectors (times in ms); each kept sample's bias/drift columns go to its data type's
    :class:`OsEstimate` in ``found["estimates"]``, if any."""
    meta, ranges = found["meta"], found["ranges"]
    t0_ms: float | None = None
    # a garbled line is counted in its stream when that is read (a type not chosen: not counted)
    counted = {kind: (_TYPES[kind][0],) if kind in kinds else () for kind in _TYPES}
    counted["TYPE_WAYPOINT"] = ("waypoint",)
    read_keys = tuple(_TYPES[kind][0] for kind in kinds)
    short = ShortRows(p, found["dropped"])
    for lineno, line in enumerate(fh, start=1):
        yield
        if short.pending is not None and line.strip():
            short.follows()
        if line.startswith("#"):
            try:
                _header(line, meta, ranges)
            except ValueError:
                raise InputError(p, f"bad header line {line.strip()!r}", lineno) from None
            continue
        parts = line.rstrip("\r\n").split("\t")
        if len(parts) < 2:
            if line.strip():  # its type unknown: counted in every stream read
                short.found(lineno, "expected '<unix ms>\\tTYPE_…\\tvalues', got one column", read_keys)
            continue
        kind = parts[1]
        if kind == "TYPE_ROTATION_VECTOR" and found.get("os") is not None:
            _rotation_vector(found["os"], lineno, parts)
            continue
        if kind not in _TYPES and kind != "TYPE_WAYPOINT":
            continue
        nval = 2 if kind == "TYPE_WAYPOINT" else 3
        if len(parts) < 2 + nval:
            why = f"{kind}: expected {nval} values, got {len(parts) - 2} (truncated?)"
            short.found(lineno, why, counted[kind])
            continue
        cells = [parts[0], *parts[2:]]
        vals = row_values(cells, 1 + _MOST[kind], dropped=found["dropped"], keys=counted[kind])
        if vals is None:
            continue
        if t0_ms is None:
            t0_ms = meta.get("start_time_unix", 0.0) * 1000.0 or vals[0]
            found["t0_ms"] = t0_ms
        t = (vals[0] - t0_ms) / 1000.0
        if kind == "TYPE_WAYPOINT":
            found["waypoints"].append([t, vals[1], vals[2]])
            continue
        if kind not in kinds:
            continue
        b = builders.get(kind)
        if b is None:
            key, _, android_type = _TYPES[kind]
            b = builders[kind] = StreamBuilder(p, key, found["dropped"], limit=ranges.get(android_type))
        est = found["estimates"].get(kind)
        if b.add(lineno, t, vals[1:4]) and est is not None:
            est.add(t, vals[4:7])
    short.end()


def _rotation_vector(b: StreamBuilder, lineno: int, parts: list[str]) -> None:
    """One ``TYPE_ROTATION_VECTOR`` line into ``b`` (t in ms, x, y, z): a garbled one is dropped as
    ``os:extra_fields`` / ``os:non_numeric``, one with a value NaN or missing as ``os:nan`` (the series is
    a reference, not a sensor stream: never an error)."""
    most = 1 + _MOST["TYPE_ROTATION_VECTOR"]
    vals = row_values([parts[0], *parts[2:]], most, dropped=b.dropped, keys=(b.key,))
    if vals is not None:
        vals += [math.nan] * (most - len(vals))  # a value missing: counted as os:nan
        b.add(lineno, vals[0], vals[1:4])


def _pass(p: Path, dropped: Counter, kinds, os_builder: StreamBuilder | None = None, estimates=None):
    """One pass over the log: ``(found, builders, chunks)``; the chunks are keyed by data type (the
    rotation vectors go to ``os_builder``, the OS's estimates to ``estimates`` (by data type), when given)."""
    found = {"meta": {}, "ranges": {}, "waypoints": [], "dropped": dropped, "os": os_builder, "t0_ms": None,
             "estimates": estimates or {}}
    builders: dict[str, StreamBuilder] = {}

    def chunks():
        with open_text(p) as fh:
            yield from chunks_of(fh, builders, every(_parse(p, fh, builders, found, kinds)))

    return found, builders, chunks()


def read(path) -> Recording:
    """Read one path log into a :class:`Recording`."""
    return open_source(path).collect()


def open_source(path) -> RecordingSource:
    """Open one path log: a first pass chooses the streams and gathers the metadata, then they stream."""
    p = Path(path)
    os_dropped: Counter = Counter()
    os_builder = StreamBuilder(p, "os", os_dropped)
    estimates = {"TYPE_MAGNETIC_FIELD_UNCALIBRATED": OsEstimate("mag_os_bias", os_dropped),
                 "TYPE_GYROSCOPE_UNCALIBRATED": OsEstimate("gyro_os_bias", os_dropped)}
    # odd samples of the streams: counted by the second pass; of the estimates: by this one
    found, builders, chunks = _pass(p, Counter(), _TYPES, os_builder, estimates)
    n_valid: Counter = Counter()
    for _, chunk in chunks:
        n_valid.update({kind: len(t) for kind, (t, _) in chunk.items()})
    meta = found["meta"]
    chosen: dict[str, str] = {}  # stream → data type
    for kind, (key, rank, _) in sorted(_TYPES.items(), key=lambda kv: kv[1][1]):
        if n_valid[kind] and key not in chosen:
            chosen[key] = kind
            if key in ("mag", "gyro"):
                meta[f"{key}_os_calibrated"] = rank > 0
    if "mag" not in chosen:
        raise InputError(p, "no magnetometer lines (TYPE_MAGNETIC_FIELD[_UNCALIBRATED])")
    for kind, est in estimates.items():
        if kind in chosen.values():  # the raw stream read: its OS estimate is what the file states
            est.to_meta(meta)
    if "start_time_unix" not in meta and found["t0_ms"] is not None and _is_unix_ms(found["t0_ms"]):
        meta["start_time_unix"] = found["t0_ms"] / 1000.0  # the times are since the first line's
    if "start_time_unix" in meta:
        meta["date"] = utc_date(meta["start_time_unix"])
    _site_location(p, meta)
    if found["waypoints"]:
        meta["waypoints"] = sorted(found["waypoints"])
        meta["waypoints_frame"] = "floor map, metres, x east, y north (true)"
    specs = {
        key: StreamSpec(
            p, key, unit_hint=f"{key} in Android units", limit_known=builders[kind].limit is not None
        )
        for key, kind in chosen.items()
    }
    references = {}
    if len(os_builder) and found["t0_ms"] is not None:
        t_ms, xyz = os_builder.arrays()
        q = in_output_north(rotation_vector_quat(xyz), meta)
        references["os"] = ((t_ms - found["t0_ms"]) / 1000.0, q)
    dropped: Counter = Counter(os_dropped)

    def streams():
        for pos, chunk in _pass(p, dropped, set(chosen.values()))[2]:
            yield pos, {_TYPES[kind][0]: block for kind, block in chunk.items()}

    feed = Feed(tuple(chosen), streams, p.stat().st_size)
    return RecordingSource(specs, [feed], meta=meta, source=str(p), format=NAME, dropped=dropped,
                           references=references)
