"""Sensor Logger (the Android/iOS app by Kelvin Choi) CSV export: a folder or its ``.zip``.

One CSV per sensor, header ``time,seconds_elapsed,z,y,x`` (columns are found by name, in any order);
``time`` is nanoseconds since the Unix epoch, ``seconds_elapsed`` seconds since the recording started (the
common clock used here). ``Metadata.csv`` holds ``device name``, ``platform`` (``android``/``ios``),
``recording time`` (the date in ``meta``) and ``standardisation`` (the app's "Standardise Units & Frames"
switch). Documented units (the app's UNITS.md and
CROSSPLATFORM.md):

=============================  =========================================================================
``MagnetometerUncalibrated``   µT, raw — preferred; else ``Magnetometer`` (µT, OS-calibrated)
``GyroscopeUncalibrated``      rad/s — preferred; else ``Gyroscope`` (rad/s)
``TotalAcceleration``          m/s² with gravity (Android only) — preferred
``AccelerometerUncalibrated``  iOS: **g** (m/s² when standardised); Android: m/s² — next
``Accelerometer`` + ``Gravity``  m/s², user acceleration and gravity apart — summed at common times, last
=============================  =========================================================================

Axes. Both platforms report in the phone's x right, y top, z out of the screen, and rotation rates are
right-handed, so magnetometer and gyroscope need no change. Accelerations differ: iOS's (unless
standardised) are minus Android's in all three axes (gravity points to −z lying flat), so on iOS the
contract's specific force is ``-(Accelerometer + Gravity)``, or ``-9.80665 × AccelerometerUncalibrated``.
Without ``Metadata.csv`` Android conventions are assumed (the unit check still catches g).
``Location.csv``'s first fix gives ``latitude_deg``/``longitude_deg``/``altitude_m`` in ``meta``.

What the phone states about itself (:mod:`replay.formats._phone`): ``mag_os_calibrated`` is False when the
magnetometer read is ``MagnetometerUncalibrated`` (raw), True when it is ``Magnetometer`` (calibrated by
the OS); ``gyro_os_calibrated`` likewise for ``GyroscopeUncalibrated`` / ``Gyroscope``. The app's
uncalibrated files have only ``x, y, z`` (no bias or drift columns); with both magnetometer files the OS's
hard-iron estimate is their difference over the first two seconds, ``mag_os_bias_uT``
(:func:`replay.formats._phone.bias_from_pair`). ``Metadata.csv``'s ``recording time`` (UTC,
``2024-05-29_16-26-40``) gives ``date`` (a value in another form: ``date_unreadable``) and its ``device id``
gives ``device_id``.
"""

from __future__ import annotations

import zlib
from collections import Counter
from pathlib import Path
from zipfile import BadZipFile

import numpy as np

from pdr_mag.conventions import GRAVITY
from replay.errors import InputError
from replay.formats._common import Block, Bundle, StreamBuilder, StreamSpec, chunks_of, iter_csv, iter_table
from replay.formats._phone import PAIR_WINDOW_S, bias_from_pair, put_date
from replay.recording import Recording
from replay.source import Feed, RecordingSource

NAME = "sensor-logger"
_MAG_FILES = ("MagnetometerUncalibrated.csv", "Magnetometer.csv")


def _header_ok(b: Bundle, name: str) -> bool:
    with b.open(name) as fh:
        first = fh.readline().lstrip("\ufeff").strip().lower()
    cols = [c.strip() for c in first.split(",")]
    return ("seconds_elapsed" in cols or "time" in cols) and {"x", "y", "z"} <= set(cols)


def detect(path: Path) -> bool:
    if not (path.is_dir() or Bundle.is_zip(path)):
        return False
    try:
        b = Bundle(path)
    except InputError:
        return False
    try:
        md = b.find("Metadata.csv")
        if md is not None:
            with b.open(md) as fh:
                first = fh.readline().lower()
            if "device name" in first and "platform" in first:
                return True
        for f in _MAG_FILES:
            name = b.find(f)
            if name is not None:
                return _header_ok(b, name)
        return False
    finally:
        b.close()


def _metadata(b: Bundle) -> dict:
    name = b.find("Metadata.csv")
    if name is None:
        return {}
    with b.open(name) as fh:
        rows = [cells for _, cells in iter_csv(fh, b.where(name))]
    if len(rows) < 2:
        raise InputError(b.where(name), "expected a header row and one row of values")
    return {k.strip(): v.strip() for k, v in zip(rows[0], rows[1], strict=False)}


def _vector_chunks(p: Path, name: str, key: str, dropped: Counter):
    """A ``time,seconds_elapsed,z,y,x`` file (columns by name), parsed a chunk at a time (a Feed's chunks)."""
    b = Bundle(p)
    where = b.where(name)
    builder = StreamBuilder(where, key, dropped)
    try:
        with b.open(name) as fh:
            first = fh.readline()
            header = [c.strip().lstrip("\ufeff") for c in first.strip().split(",")]
            cols = {c.lower(): i for i, c in enumerate(header)}
            tcol = cols.get("seconds_elapsed", cols.get("time"))
            if tcol is None or not {"x", "y", "z"} <= set(cols):
                raise InputError(
                    where, f"bad header {first.strip()!r}, expected time,seconds_elapsed,z,y,x", 1
                )
            t_scale = 1.0 if "seconds_elapsed" in cols else 1e-9
            idx = [cols["x"], cols["y"], cols["z"]]
            ncol = max([tcol, *idx]) + 1
            steps = iter_table(fh, where, [(builder, idx)], ncol, first_line=2, delimiter=",", tcol=tcol,
                               t_scale=t_scale, most=len(header))
            yield from chunks_of(fh, {key: builder}, steps)
    except (BadZipFile, EOFError, zlib.error) as exc:
        raise InputError(where, f"truncated or damaged archive member ({exc})") from None
    finally:
        b.close()


def _head(p: Path, name: str, seconds: float, start: float = -np.inf) -> Block:
    """A vector file's first ``seconds`` from time ``start`` on (times, (n, 3)); its odd rows are left to the
    stream's own pass, which counts them."""
    ts, xs = [], []
    for _, blocks in _vector_chunks(p, name, "mag", Counter()):
        t, x = blocks.get("mag", (np.empty(0), np.empty((0, 3))))
        on = t >= start
        if not on.any():
            continue
        ts.append(t[on])
        xs.append(x[on])
        if ts[-1][-1] > ts[0][0] + seconds:
            break
    if not ts:
        return np.empty(0), np.empty((0, 3))
    t, x = np.concatenate(ts), np.concatenate(xs)
    keep = t <= t[0] + seconds
    return t[keep], x[keep]


def _vector_feed(p: Path, b: Bundle, name: str, key: str, dropped: Counter) -> Feed:
    return Feed((key,), lambda: _vector_chunks(p, name, key, dropped), b.size(name))


def _location(b: Bundle, meta: dict) -> None:
    name = b.find("Location.csv")
    if name is None:
        return
    with b.open(name) as fh:
        rows = iter_csv(fh, b.where(name))
        try:
            _, header = next(rows)
        except StopIteration:
            return
        cols = {c.strip().lower(): i for i, c in enumerate(header)}
        if not {"latitude", "longitude"} <= set(cols):
            return
        for _, cells in rows:
            try:
                lat, lon = float(cells[cols["latitude"]]), float(cells[cols["longitude"]])
            except (ValueError, IndexError):
                continue
            meta["latitude_deg"], meta["longitude_deg"] = lat, lon
            if "altitude" in cols:
                try:
                    meta["altitude_m"] = float(cells[cols["altitude"]])
                except (ValueError, IndexError):
                    pass
            return


def _sum_at_common_times(p: Path, user: str, grav: str, dropped: Counter):
    """User acceleration + gravity at their common times (a Feed's chunks), the two files read in step.

    A user sample is matched once both files have been read up to its time (or have ended); unmatched
    ones are counted as ``accel:no_gravity_sample`` — the same as intersecting the whole streams.
    """
    parts = {
        "accel": _vector_chunks(p, user, "accel", dropped),
        "gravity": _vector_chunks(p, grav, "gravity", Counter()),
    }
    buf = {k: (np.empty(0), np.empty((0, 3))) for k in parts}
    seen = dict.fromkeys(parts, -np.inf)
    pos = dict.fromkeys(parts, 0)
    while parts:
        k = min(parts, key=lambda k: seen[k])  # the file that is behind
        try:
            pos[k], chunk = next(parts[k])
        except StopIteration:
            del parts[k]
        else:
            if k in chunk:
                t, v = chunk[k]
                buf[k] = (np.concatenate([buf[k][0], t]), np.concatenate([buf[k][1], v]))
                seen[k] = float(t[-1])
        limit = min((seen[k] for k in parts), default=np.inf)
        (ta, va), (tg, vg) = buf["accel"], buf["gravity"]
        na, ng = int(np.searchsorted(ta, limit, "right")), int(np.searchsorted(tg, limit, "right"))
        common, ia, ig = np.intersect1d(ta[:na], tg[:ng], assume_unique=True, return_indices=True)
        if na - len(common):
            dropped["accel:no_gravity_sample"] += na - len(common)
        buf = {"accel": (ta[na:], va[na:]), "gravity": (tg[ng:], vg[ng:])}
        yield sum(pos.values()), ({"accel": (common, va[ia] + vg[ig])} if len(common) else {})


def read(path) -> Recording:
    """Read a Sensor Logger export (folder or zip) into a :class:`Recording`."""
    return open_source(path).collect()


def open_source(path) -> RecordingSource:
    """Open a Sensor Logger export (folder or zip): metadata now, the streams as they are read."""
    p = Path(path)
    b = Bundle(p)
    try:
        return _open(b, p)
    finally:
        b.close()


def _open(b: Bundle, p: Path) -> RecordingSource:
    md = _metadata(b)
    platform = md.get("platform", "").lower() or "unknown"
    standard = md.get("standardisation", "").lower() == "true"
    ios_frame = platform == "ios" and not standard
    meta: dict = {"platform": platform}
    if md.get("device name"):
        meta["device"] = md["device name"]
    if md.get("device id"):
        meta["device_id"] = md["device id"]
    dropped: Counter = Counter()
    specs, feeds = {}, []

    mag_name = next((n for n in map(b.find, _MAG_FILES) if n is not None), None)
    if mag_name is None:
        raise InputError(p, "no Magnetometer.csv or MagnetometerUncalibrated.csv (a stream missing)")
    meta["mag_os_calibrated"] = not mag_name.endswith("MagnetometerUncalibrated.csv")
    cal_name = b.find("Magnetometer.csv")
    if not meta["mag_os_calibrated"] and cal_name is not None:
        raw_t, raw = _head(p, mag_name, PAIR_WINDOW_S + 1.0)
        if len(raw_t):
            cal_t, cal = _head(p, cal_name, PAIR_WINDOW_S, start=float(raw_t[0]))
            bias = bias_from_pair(raw_t, raw, cal_t, cal)
            if bias is not None:
                meta["mag_os_bias_uT"], meta["mag_os_bias_changes"] = bias, []
    specs["mag"] = StreamSpec(b.where(mag_name), "mag", unit_hint="µT")
    feeds.append(_vector_feed(p, b, mag_name, "mag", dropped))
    if md.get("recording time"):
        put_date(meta, md["recording time"])

    gyr_name = b.find("GyroscopeUncalibrated.csv") or b.find("Gyroscope.csv")
    if gyr_name is not None:
        meta["gyro_os_calibrated"] = not gyr_name.endswith("GyroscopeUncalibrated.csv")
        specs["gyro"] = StreamSpec(b.where(gyr_name), "gyro", unit_hint="rad/s")
        feeds.append(_vector_feed(p, b, gyr_name, "gyro", dropped))

    sign = -1.0 if ios_frame else 1.0
    total, uncal = b.find("TotalAcceleration.csv"), b.find("AccelerometerUncalibrated.csv")
    user, grav = b.find("Accelerometer.csv"), b.find("Gravity.csv")
    if total is not None:
        specs["accel"] = StreamSpec(b.where(total), "accel", scale=sign, unit_hint="m/s²")
        feeds.append(_vector_feed(p, b, total, "accel", dropped))
        meta["accel_source"] = "TotalAcceleration"
    elif uncal is not None:
        scale = -GRAVITY if ios_frame else 1.0
        specs["accel"] = StreamSpec(b.where(uncal), "accel", scale=scale, unit_hint="iOS g / m/s²")
        feeds.append(_vector_feed(p, b, uncal, "accel", dropped))
        meta["accel_source"] = "AccelerometerUncalibrated"
    elif user is not None and grav is not None:
        specs["accel"] = StreamSpec(b.where(user), "accel", scale=sign, unit_hint="m/s²")
        size = b.size(user) + b.size(grav)
        feeds.append(Feed(("accel",), lambda: _sum_at_common_times(p, user, grav, dropped), size))
        meta["accel_source"] = "Accelerometer+Gravity"
    _location(b, meta)
    return RecordingSource(specs, feeds, meta=meta, source=str(p), format=NAME, dropped=dropped)
