"""Sensor Logger (the Android/iOS app by Kelvin Choi) CSV export: a folder or its ``.zip``.

One CSV per sensor, header ``time,seconds_elapsed,z,y,x`` (columns are found by name, in any order);
``time`` is nanoseconds since the Unix epoch, ``seconds_elapsed`` seconds since the recording started (the
common clock used here). ``Metadata.csv`` holds ``device name``, ``platform`` (``android``/``ios``) and
``standardisation`` (the app's "Standardise Units & Frames" switch). Documented units (the app's UNITS.md and
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
"""

from __future__ import annotations

import datetime as dt
from collections import Counter
from pathlib import Path

import numpy as np

from replay.errors import InputError
from replay.formats._common import Bundle, StreamBuilder, finish, floats, iter_csv
from replay.recording import Recording

NAME = "sensor-logger"
GRAVITY = 9.80665
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


def _read_vectors(b: Bundle, name: str, key: str, dropped: Counter) -> tuple[StreamBuilder, int | None]:
    """A ``time,seconds_elapsed,z,y,x`` file into a builder; also the first ``time`` (ns) seen."""
    where = b.where(name)
    builder = StreamBuilder(where, key, dropped)
    first_ns = None
    with b.open(name) as fh:
        rows = iter_csv(fh, where)
        try:
            _, header = next(rows)
        except StopIteration:
            raise InputError(where, "empty file (no header)", 1) from None
        cols = {c.strip().lstrip("\ufeff").lower(): i for i, c in enumerate(header)}
        tcol = cols.get("seconds_elapsed", cols.get("time"))
        if tcol is None or not {"x", "y", "z"} <= set(cols):
            raise InputError(
                where, f"bad header {','.join(header)!r}, expected time,seconds_elapsed,z,y,x", 1
            )
        scale_t = 1e-9 if "seconds_elapsed" not in cols else 1.0
        idx = [tcol, cols["x"], cols["y"], cols["z"]]
        need = max(idx) + 1
        for lineno, cells in rows:
            if not cells or all(not c.strip() for c in cells):
                continue
            if len(cells) < need:
                raise InputError(
                    where, f"expected {len(header)} columns, got {len(cells)} (truncated?)", lineno
                )
            vals = floats(where, lineno, [cells[i] for i in idx])
            if first_ns is None and "time" in cols:
                try:
                    first_ns = int(cells[cols["time"]])
                except ValueError:
                    first_ns = None
            builder.add(lineno, vals[0] * scale_t, vals[1:])
    return builder, first_ns


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


def _sum_at_common_times(a: StreamBuilder, g: StreamBuilder, dropped: Counter) -> StreamBuilder:
    ta, va = a.arrays()
    tg, vg = g.arrays()
    common, ia, ig = np.intersect1d(ta, tg, assume_unique=True, return_indices=True)
    if len(ta) - len(common):
        dropped["accel:no_gravity_sample"] += len(ta) - len(common)
    out = StreamBuilder(a.path, "accel", dropped)
    out.add_block(common, va[ia] + vg[ig])
    return out


def read(path) -> Recording:
    """Read a Sensor Logger export (folder or zip) into a :class:`Recording`."""
    p = Path(path)
    b = Bundle(p)
    try:
        return _read(b, p)
    finally:
        b.close()


def _read(b: Bundle, p: Path) -> Recording:
    md = _metadata(b)
    platform = md.get("platform", "").lower() or "unknown"
    standard = md.get("standardisation", "").lower() == "true"
    ios_frame = platform == "ios" and not standard
    meta: dict = {"platform": platform}
    if md.get("device name"):
        meta["device"] = md["device name"]
    dropped: Counter = Counter()

    mag_name = next((n for n in map(b.find, _MAG_FILES) if n is not None), None)
    if mag_name is None:
        raise InputError(p, "no Magnetometer.csv or MagnetometerUncalibrated.csv (a stream missing)")
    meta["mag_os_calibrated"] = not mag_name.endswith("MagnetometerUncalibrated.csv")
    mag_b, first_ns = _read_vectors(b, mag_name, "mag", dropped)
    mag = finish(mag_b, unit_hint="µT")
    if first_ns is not None and first_ns > 1e17:
        meta["date"] = dt.datetime.fromtimestamp(first_ns * 1e-9, dt.UTC).date().isoformat()

    gyro = None
    gyr_name = b.find("GyroscopeUncalibrated.csv") or b.find("Gyroscope.csv")
    if gyr_name is not None:
        gyro = finish(_read_vectors(b, gyr_name, "gyro", dropped)[0], unit_hint="rad/s")

    accel = None
    sign = -1.0 if ios_frame else 1.0
    total, uncal = b.find("TotalAcceleration.csv"), b.find("AccelerometerUncalibrated.csv")
    user, grav = b.find("Accelerometer.csv"), b.find("Gravity.csv")
    if total is not None:
        accel = finish(_read_vectors(b, total, "accel", dropped)[0], scale=sign, unit_hint="m/s²")
        meta["accel_source"] = "TotalAcceleration"
    elif uncal is not None:
        scale = -GRAVITY if ios_frame else 1.0
        accel = finish(_read_vectors(b, uncal, "accel", dropped)[0], scale=scale, unit_hint="iOS g / m/s²")
        meta["accel_source"] = "AccelerometerUncalibrated"
    elif user is not None and grav is not None:
        ub = _read_vectors(b, user, "accel", dropped)[0]
        gb = _read_vectors(b, grav, "gravity", Counter())[0]
        accel = finish(_sum_at_common_times(ub, gb, dropped), scale=sign, unit_hint="m/s²")
        meta["accel_source"] = "Accelerometer+Gravity"
    _location(b, meta)
    return Recording(mag=mag, accel=accel, gyro=gyro, meta=meta, source=str(p), format=NAME, dropped=dropped)
