"""The peers of ``../shared/benchmarks/PEERS.md``, run as that page describes, on a recording's raw streams.

imufusion 1.3.3 (x-io Fusion: gain 0.5, acceleration rejection 10°, magnetic rejection 10°, recovery 5 s),
vqf 2.1.2 (defaults), ahrs 0.4.0 Madgwick (gain 0.041) and Mahony (defaults).  They assume a fixed
sample period (:func:`sample_period`), so they are fed on the gyroscope's time grid from the first instant
all three streams have a sample: the accelerometer interpolated, the latest magnetometer sample held.  The
magnetometer is calibrated with the day's calibration and scaled to the WMM strength; their ENU
(imufusion, vqf, Mahony) or north-west-up (Madgwick: the reference field is ``(b_x, 0, b_z)``)
magnetic-north frame is turned to true north with the WMM declination.

Columns (PEERS.md's names): ``<peer>_cal`` — raw gyroscope; ``<peer>_cal_gcal`` — the day's gyroscope
offset (mean of the static ``calib_gyr_*`` recording) removed first, the peers' best case.
"""

from __future__ import annotations

import numpy as np
from _common import imufusion_ahrs
from scipy.spatial.transform import Rotation

#: The peer columns of PEERS.md, in its order.
PEER_COLUMNS = (
    "imufusion_cal",
    "vqf_cal",
    "madgwick_cal",
    "mahony_cal",
    "imufusion_cal_gcal",
    "vqf_cal_gcal",
    "madgwick_cal_gcal",
)


def on_gyro_grid(rec, mag_cal, period: float | None = None):
    """Accelerometer interpolated and the latest magnetometer sample at the gyroscope's times, from the
    first time all three streams have a sample.  With ``period`` (s): on a regular grid of that period
    instead, the latest gyroscope sample held on it too — what a logger that repeats a stalled gyroscope's
    last value delivers, and what a filter of fixed sample period integrates across a sample left out."""
    start = max(rec.gyro.t[0], rec.accel.t[0], rec.mag.t[0])
    if period is None:
        keep = rec.gyro.t >= start
        tg, gyr = rec.gyro.t[keep], rec.gyro.xyz[keep]
    else:
        tg = np.arange(start, rec.gyro.t[-1], period)
        gyr = rec.gyro.xyz[_latest(rec.gyro.t, tg)]
    acc = np.column_stack([np.interp(tg, rec.accel.t, rec.accel.xyz[:, k]) for k in range(3)])
    return tg, gyr, acc, mag_cal[_latest(rec.mag.t, tg)]


def _latest(t, grid):
    """Index of the latest sample of times ``t`` at or before each grid time (the first before any)."""
    return np.clip(np.searchsorted(t, grid, side="right") - 1, 0, len(t) - 1)


def _to_true(q_wxyz, declination_deg, pre_yaw_deg=0.0):
    """Quaternions of a peer's magnetic-north world frame (rotated by ``pre_yaw_deg`` about up from ENU)
    turned into device → ENU true north, w first."""
    r = Rotation.from_quat(np.asarray(q_wxyz)[:, [1, 2, 3, 0]])
    r = Rotation.from_euler("z", pre_yaw_deg - declination_deg, degrees=True) * r
    return r.as_quat()[:, [3, 0, 1, 2]]


def sample_period(tg) -> float:
    """The grid's period: the mean sample interval without the gaps (intervals over 1.5× the median), which
    the peers' fixed period cannot represent; the mean, not the median, since some phones alternate
    between two intervals (iPhone 5: 10.5 / 10.6 ms)."""
    dt = np.diff(tg)
    return float(np.mean(dt[dt <= 1.5 * np.median(dt)]))


def run_imufusion(tg, gyr, acc, mag):
    ahrs = imufusion_ahrs(1.0 / sample_period(tg))
    gd = np.degrees(gyr)
    ag = acc / 9.80665
    q = np.empty((len(tg), 4))
    for i in range(len(tg)):
        ahrs.update(gd[i], ag[i], mag[i])
        q[i] = ahrs.get_quaternion()
    return q


def run_vqf(tg, gyr, acc, mag):
    from vqf import VQF

    v = VQF(sample_period(tg))
    out = v.updateBatch(np.ascontiguousarray(gyr), np.ascontiguousarray(acc), np.ascontiguousarray(mag))
    return out["quat9D"]


def run_madgwick(tg, gyr, acc, mag):
    from ahrs.filters import Madgwick

    return Madgwick(gyr=gyr, acc=acc, mag=mag, frequency=1.0 / sample_period(tg), gain=0.041).Q


def run_mahony(tg, gyr, acc, mag):
    from ahrs.filters import Mahony

    return Mahony(gyr=gyr, acc=acc, mag=mag, frequency=1.0 / sample_period(tg)).Q


#: peer → (runner, yaw of its world frame's x axis from east, deg)
RUNNERS = {
    "imufusion": (run_imufusion, 0.0),
    "vqf": (run_vqf, 0.0),
    "madgwick": (run_madgwick, 90.0),
    "mahony": (run_mahony, 0.0),
}


def run_peers(rec, mag_cal_wmm, gyro_offset, declination_deg, columns=PEER_COLUMNS):
    """Each peer column's estimate ``(t, q_wd)`` (device → ENU true north) on one recording.

    ``mag_cal_wmm``: the calibrated magnetometer scaled to the WMM strength (N, 3), µT; ``gyro_offset``: the
    day's gyroscope offset, rad/s (used by the ``_gcal`` columns).
    """
    tg, gyr, acc, mag = on_gyro_grid(rec, mag_cal_wmm)
    out = {}
    for col in columns:
        name, _, rest = col.partition("_cal")
        fn, pre_yaw = RUNNERS[name]
        g = gyr - gyro_offset if rest == "_gcal" else gyr
        out[col] = (tg, _to_true(fn(tg, g, acc, mag), declination_deg, pre_yaw))
    return out
