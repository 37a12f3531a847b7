"""A filter started in the middle of a walk (a backend restarted): the first accelerometer sample of a
phone in a pocket or a swinging hand can point tens of degrees from up with ``|a|`` far from — or, worse,
close to — g, and a heading taken through that tilt is off by ``tan I`` times as much.  The first tilt's
variance counts the rotation rate, the heading waits for a tilt in the linear range before it is updated,
and the correction that follows a run of rejections does not teach the gyro bias
(:mod:`pdr_mag.fusion.accel`, :mod:`pdr_mag.fusion.mag`)."""

from __future__ import annotations

import numpy as np
from test_attitude import merge, twist_error_deg

from pdr_mag.fusion import FusionCore
from pdr_mag.sim import simulate

#: a phone's gyro offset, rad/s (0.6, −0.9, 0.5 °/s)
GYRO_BIAS = (0.01, -0.015, 0.008)


def _started_late(scenario: str, seed: int, starts_s) -> list[float]:
    """Mean |heading error| from 10 s after each start ``starts_s`` into one simulated walk (calibrated
    magnetometer, the true field given), deg."""
    w = simulate(scenario, seed=seed, effects={"hard_iron": None, "soft_iron": None, "gyro_bias": GYRO_BIAS})
    kind, t, xyz = merge(w, mag=w.mag[1])
    out = []
    for start in starts_s:
        keep = t >= t[0] + start
        b = FusionCore(field=w.field).process(kind[keep], t[keep], xyz[keep])
        tr, err, _ = twist_error_deg(b, w.truth)
        out.append(float(np.mean(np.abs(err[tr > tr[0] + 10.0]))))
    return out


def test_a_start_in_motion_converges():
    """72 starts 20.00–20.41 s into pocket, swinging-hand and running-pocket walks (seeds 1–6), mid-stride:
    measured mean 3.0°, worst 17.8° (run_pocket seed 1).  Without the rate in the first tilt's variance and
    with the bias taught by the correction that ends a run of rejections: mean 4.6°, worst 91.8° (a heading
    fixed 90° off through a tilt 40° off, its correction then taught as a 15 °/s gyro bias).  Bounds: mean
    4° (a third above the measured mean, below the other rule's), none above 30° (a start the heading
    recovers from, against one it does not)."""
    errors = [
        e
        for scenario in ("pocket", "swing", "run_pocket")
        for seed in range(1, 7)
        for e in _started_late(scenario, seed, (20.0, 20.13, 20.27, 20.41))
    ]
    assert len(errors) == 72
    assert np.mean(errors) < 4.0
    assert max(errors) < 30.0
