"""MATLAB files of the BROAD robust-orientation benchmark (myon aktos-t IMU with OptiTrack truth).

A MATLAB v5 file (``scipy.io.loadmat``) with, on one common clock of ``sampling_rate`` Hz (285.714):

=================  ==========================================================================
``imu_acc``        N×3, m/s², specific force (+g up)
``imu_gyr``        N×3, rad/s
``imu_mag``        N×3, µT (updates at ~200 Hz, resampled: repeated values are sample-and-hold)
``opt_quat``       N×4, w-first, IMU body → ENU with **magnetic** north (OptiTrack); NaN rows = occlusions
``sampling_rate``  Hz
``info``           text
=================  ==========================================================================

The IMU's own axes are taken as the device frame (it is not a phone; x, y, z of the board). Units are the
contract's already. Times are ``i / sampling_rate``. ``opt_quat`` becomes :attr:`Recording.truth` without its
NaN rows (counted as ``truth:nan``), with ``meta["truth_north"] = "magnetic"`` (the lab's measured field
defines north). Only the needed variables are loaded (``opt_pos`` is skipped). ``scipy.io.loadmat`` cannot
read a variable in parts, so this reader loads the file whole (the one reader that does; the trials are a
few minutes long) and then serves it through the streaming source API like the others.

A lab IMU, not a phone: its streams are raw (``meta["mag_os_calibrated"]`` and ``["gyro_os_calibrated"]``
False), with no estimate of an OS, no date and no device id in the file.
"""

from __future__ import annotations

import functools
from collections import Counter
from pathlib import Path

import numpy as np

from replay.errors import InputError
from replay.formats import _common
from replay.formats._common import StreamBuilder, StreamSpec
from replay.recording import Recording
from replay.source import Feed, RecordingSource

NAME = "broad"
_NEEDED = ("imu_acc", "imu_gyr", "imu_mag")


def detect(path: Path) -> bool:
    if not (path.is_file() and path.suffix.lower() == ".mat"):
        return False
    with path.open("rb") as fh:
        if not fh.read(10).startswith(b"MATLAB 5.0"):
            return False
    from scipy.io import whosmat

    try:
        names = {w[0] for w in whosmat(path)}
    except Exception:  # noqa: BLE001 — a damaged v5 file: let read() report the problem
        return True
    return "imu_mag" in names and ("imu_acc" in names or "imu_gyr" in names)


def _array_chunks(p: Path, key: str, t: np.ndarray, v: np.ndarray, dropped: Counter):
    """Arrays already in memory, cleaned (:meth:`StreamBuilder.add_block`) a chunk at a time."""
    b = StreamBuilder(p, key, dropped)
    step = _common.CHUNK
    for i in range(0, len(t), step):
        b.add_block(t[i : i + step], v[i : i + step])
        yield 0, ({key: b.take()} if len(b) else {})


def read(path) -> Recording:
    """Read a BROAD trial ``.mat`` into a :class:`Recording` (with truth)."""
    return open_source(path).collect()


def open_source(path) -> RecordingSource:
    """Open a BROAD trial ``.mat`` (loaded whole, see the module docstring) as a source."""
    p = Path(path)
    from scipy.io import loadmat

    try:
        m = loadmat(
            p, squeeze_me=True, variable_names=[*_NEEDED, "opt_quat", "sampling_rate", "info", "movement"]
        )
    except Exception as exc:  # noqa: BLE001 — scipy raises many types for a damaged file
        raise InputError(p, f"cannot read as a MATLAB v5 file ({type(exc).__name__}: {exc})") from None
    for k in ("imu_mag", "sampling_rate"):
        if k not in m:
            raise InputError(p, f"variable {k!r} missing")
    try:
        rate = float(m["sampling_rate"])
    except (TypeError, ValueError):
        raise InputError(p, "sampling_rate is not a number") from None
    if not (rate > 0):
        raise InputError(p, f"sampling_rate is {rate}, expected > 0 Hz")
    n = np.asarray(m["imu_mag"]).shape[0]
    t = np.arange(n) / rate
    dropped: Counter = Counter()
    specs, feeds = {}, []
    for var, key in (("imu_mag", "mag"), ("imu_acc", "accel"), ("imu_gyr", "gyro")):
        if var not in m:
            continue
        v = np.asarray(m[var], dtype=float)
        if v.ndim != 2 or v.shape != (n, 3):
            raise InputError(p, f"{var} has shape {v.shape}, expected ({n}, 3)")
        specs[key] = StreamSpec(p, key, unit_hint={"mag": "µT", "accel": "m/s²", "gyro": "rad/s"}[key])
        feeds.append(Feed((key,), functools.partial(_array_chunks, p, key, t, v, dropped)))
    truth = None
    if "opt_quat" in m:
        q = np.asarray(m["opt_quat"], dtype=float)
        if q.shape != (n, 4):
            raise InputError(p, f"opt_quat has shape {q.shape}, expected ({n}, 4)")
        good = np.all(np.isfinite(q), axis=1)
        if (~good).any():
            dropped["truth:nan"] += int((~good).sum())
        q = q[good] / np.linalg.norm(q[good], axis=1, keepdims=True)
        truth = (t[good], q * np.where(q[:, :1] < 0, -1.0, 1.0))
    meta: dict = {"device": "myon aktos-t IMU", "mag_os_calibrated": False, "gyro_os_calibrated": False}
    if truth is not None:
        meta["truth_north"] = "magnetic"
    if "info" in m:
        meta["info"] = str(m["info"]).strip()
    if "movement" in m:
        mv = np.asarray(m["movement"]).astype(bool)
        if mv.shape == (n,) and mv.any():
            idx = np.flatnonzero(mv)
            meta["movement_s"] = [float(t[idx[0]]), float(t[idx[-1]])]
    return RecordingSource(specs, feeds, meta=meta, truth=truth, source=str(p), format=NAME, dropped=dropped)
