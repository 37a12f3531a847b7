"""The breadboard MARG recordings (MPU6050 + HMC5883L, sunsided/sensor-fusion "set-2").

A recording is a folder with two CSV files (header row first), times in seconds of the logging host:

==================  ===================================================================================
``mpu6050.csv``     ``t_s, acc_x_g, acc_y_g, acc_z_g, gyro_x_dps, gyro_y_dps, gyro_z_dps, temp_C``
``hmc5883l.csv``    ``t_s, mag_x_gauss, mag_y_gauss, mag_z_gauss``
==================  ===================================================================================

(decoded from the upstream MATLAB v7.3 buffers ``original_mat/*.mat``; those are HDF5 files, which need
``h5py`` — a folder with only them is reported as such).

Units: accel in g, gyro in deg/s, mag in gauss (1 G = 100 µT).

Axes. The board's axes are x forward, y left, z up (``A``). In ``A``:

* the accelerometer reads the gravity vector (≈ −1 g on z lying level), so specific force ``f_A = -g a``;
* the magnetometer reads the field in the same axes: ``m_A = 100 m`` (level, x to the north, it reads
  ≈ (0.2, −0.1, −0.3) G: north and down);
* the gyroscope's x **and** y signs are flipped: ``ω_A = (-g_x, -g_y, g_z)``. This was measured, not taken
  from the upstream notes (which mention only x): on every rotation recording, the kinematic relation
  ``df/dt = -ω × f`` of the accelerometer and ``dm/dt = -ω × (m - b)`` of the magnetometer hold best with
  exactly these signs (relative residual of the magnetometer's relation 0.14–0.21 on five recordings,
  next best sign choice 0.28–0.91); the scripted turns about z and x then come out counter-clockwise.

The device frame of the contract (x right, y top, z out of the screen) is the board laid flat with its
forward axis as the "top": ``x_d = -y_A``, ``y_d = x_A``, ``z_d = z_A``, so the heading is the direction of
the board's forward axis.

Saturation: the MPU6050 ran at ±2 g and ±250 deg/s; samples with an axis at the range limit are counted as
``accel:saturated`` / ``gyro:saturated`` (22 gyro samples in ``full-sphere``). Timestamps are host arrival
times and come in bursts (median 2 ms, gaps of 42 ms); they are kept as they are.

A breadboard, not a phone: the chips' raw readings (``meta["mag_os_calibrated"]`` and
``["gyro_os_calibrated"]`` False), with no estimate of an OS, no date and no device id in the files.
"""

from __future__ import annotations

import functools
from collections import Counter
from pathlib import Path

import numpy as np

from pdr_mag.conventions import GRAVITY
from replay.errors import InputError
from replay.formats._common import StreamBuilder, StreamSpec, chunks_of, iter_table, open_text, read_table
from replay.recording import Recording
from replay.source import Feed, RecordingSource

NAME = "sunsided-marg"
UT_PER_GAUSS = 100.0
DEG = np.pi / 180.0

MPU_HEADER = ["t_s", "acc_x_g", "acc_y_g", "acc_z_g", "gyro_x_dps", "gyro_y_dps", "gyro_z_dps"]
HMC_HEADER = ["t_s", "mag_x_gauss", "mag_y_gauss", "mag_z_gauss"]

#: board axes A (x forward, y left, z up) → device frame (x right, y top = forward, z up)
A_TO_DEVICE = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
#: raw gyro axes → A: x and y flipped (measured; see the module docstring)
GYRO_TO_A = np.diag([-1.0, -1.0, 1.0])

ACCEL_LIMIT_G = 1.999  # ±2 g range, 16-bit: the largest code is 1.99994 g
GYRO_LIMIT_DPS = 250.0  # ±250 deg/s range: the largest codes are 250.13 deg/s


def detect(path: Path) -> bool:
    if not path.is_dir():
        return False
    if (path / "hmc5883l.csv").is_file():
        return True
    return (path / "original_mat" / "hmc5883l_compass.mat").is_file()


def _open_csv(path: Path, header: list[str], optional: tuple = ()) -> tuple[object, int, int]:
    """Open the table and check its header; ``optional`` columns after ``header`` are read when the header
    has them. Returns the open file (after the header), how many of the optional columns are present and
    the header's number of fields (the most a row may have)."""
    fh = open_text(path)
    first = fh.readline()
    got = [c.strip() for c in first.strip().split(",")]
    if got[: len(header)] != header:
        fh.close()
        raise InputError(path, f"bad header {first.strip()!r}, expected {','.join(header)!r}…", 1)
    extra = got[len(header) :]
    n_opt = 0
    while n_opt < min(len(optional), len(extra)) and extra[n_opt] == optional[n_opt]:
        n_opt += 1
    return fh, n_opt, len(got)


def _feed(path: Path, header: list[str], targets: dict[str, tuple[float | None, list[int]]], dropped) -> Feed:
    """One CSV file of the pair, parsed a chunk at a time: ``targets`` = ``{key: (range limit, columns)}``."""

    def chunks():
        builders = {k: StreamBuilder(path, k, dropped, limit=lim) for k, (lim, _) in targets.items()}
        fh, _, most = _open_csv(path, header)
        with fh:
            cols = [(builders[k], ix) for k, (_, ix) in targets.items()]
            yield from chunks_of(fh, builders, iter_table(fh, path, cols, len(header), 2, ",", most=most))

    return Feed(tuple(targets), chunks, path.stat().st_size)


def _temperature(mpu: Path):
    """The MPU6050's temperature column (evaluation only), read whole when asked for, or None."""
    fh, has_temp, most = _open_csv(mpu, MPU_HEADER, optional=("temp_C",))
    with fh:
        if not has_temp:
            return None
        b = StreamBuilder(mpu, "temperature", Counter(), width=1)  # rows counted by the accel/gyro stream
        read_table(fh, mpu, [(b, [7])], len(MPU_HEADER) + 1, first_line=2, delimiter=",", most=most)
    t, v = b.arrays()
    return (t, v[:, 0].copy()) if len(t) else None


def read(path) -> Recording:
    """Read a set-2 recording folder (the CSV pair) into a :class:`Recording` in the contract's frame."""
    return open_source(path).collect()


def open_source(path) -> RecordingSource:
    """Open a set-2 recording folder (the CSV pair): the streams are read as they are consumed."""
    p = Path(path)
    mpu, hmc = p / "mpu6050.csv", p / "hmc5883l.csv"
    if not hmc.is_file():
        raise InputError(
            hmc,
            "missing (only MATLAB v7.3/HDF5 buffers in original_mat/: decode them to CSV, or install h5py)",
        )
    dropped: Counter = Counter()
    specs = {"mag": StreamSpec(hmc, "mag", scale=UT_PER_GAUSS, axes=A_TO_DEVICE, unit_hint="gauss × 100")}
    feeds = [_feed(hmc, HMC_HEADER, {"mag": (None, [1, 2, 3])}, dropped)]
    temperature = None
    if mpu.is_file():
        targets = {"accel": (ACCEL_LIMIT_G, [1, 2, 3]), "gyro": (GYRO_LIMIT_DPS, [4, 5, 6])}
        feeds.append(_feed(mpu, MPU_HEADER, targets, dropped))
        specs["accel"] = StreamSpec(
            mpu, "accel", scale=-GRAVITY, axes=A_TO_DEVICE, unit_hint="g, gravity sign", limit_known=True
        )
        specs["gyro"] = StreamSpec(
            mpu, "gyro", scale=DEG, axes=A_TO_DEVICE @ GYRO_TO_A, unit_hint="deg/s", limit_known=True
        )
        temperature = functools.partial(_temperature, mpu)
    meta = {
        "device": "MPU6050 + HMC5883L breadboard",
        "axes": "device x = -board y, y = board x (forward), z = z",
        "mag_os_calibrated": False,
        "gyro_os_calibrated": False,
    }
    return RecordingSource(
        specs, feeds, meta=meta, temperature=temperature, source=str(p), format=NAME, dropped=dropped
    )
