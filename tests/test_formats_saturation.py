"""Saturation flagging: samples clipped at a sensor's range are kept and counted (pdr-csv and every reader
that does not know the range)."""

from __future__ import annotations

from collections import Counter

import numpy as np

from replay.formats import pdrcsv, read_recording
from replay.formats._common import flag_saturation
from replay.recording import Recording, Stream
from tests.conftest import dataset


def _accel(n=2000, seed=1):
    rng = np.random.default_rng(seed)
    return np.array([0.0, 0.0, 9.81]) + 9.0 * rng.standard_normal((n, 3))


def test_clipped_axis_counted():
    a = _accel()
    limit = 19.6133  # ±2 g
    clipped = np.clip(a, -limit, limit)
    n_expected = int(np.any(np.abs(a) >= limit, axis=1).sum())
    assert n_expected >= 3
    c = Counter()
    assert flag_saturation("accel", clipped, c) == n_expected and c == {"accel:saturated": n_expected}


def test_unclipped_or_small_not_counted():
    c = Counter()
    assert flag_saturation("accel", _accel(), c) == 0  # random floats never repeat the peak
    q = np.round(_accel() / 3.0) * 0.1  # coarse quantisation repeats the peak, but far below any range
    assert flag_saturation("accel", q, c) == 0
    assert flag_saturation("mag", np.full((10, 3), 5000.0), c) == 0  # not for the magnetometer
    assert c == {}


def test_pdrcsv_counts_and_keeps(tmp_path):
    t = np.arange(2000) * 0.01
    a = np.clip(_accel(), -19.6133, 19.6133)
    rec = Recording(mag=Stream(t, np.tile([20.0, 0.0, -40.0], (2000, 1))), accel=Stream(t, a))
    pdrcsv.write(rec, tmp_path / "r")
    got = read_recording(tmp_path / "r")
    assert got.dropped["accel:saturated"] == int(np.any(np.abs(a) >= 19.6133, axis=1).sum())
    assert len(got.accel) == 2000


def test_real_calibration_shaking_hits_2g():
    rec = pdrcsv.read(dataset("tyrex-pdrcsv", "calib_mag_Nexus5_d3"))
    assert rec.dropped["accel:saturated"] == 107  # |a| pinned at 19.45–19.54 m/s² on all three axes
    walk = pdrcsv.read(dataset("tyrex-pdrcsv", "Thibaud_Nexus5_NoDist_Texting"))
    assert "accel:saturated" not in walk.dropped and "gyro:saturated" not in walk.dropped
