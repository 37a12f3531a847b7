"""Breadboard MARG (sunsided set-2): units and axes checked by physics on the real recordings; fixtures."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import uniform_filter1d

from replay.errors import InputError
from replay.formats import detect, read_recording, sunsided
from tests.conftest import dataset


def _kinematic_residual(rec, dt=0.01):
    """Relative residual of dm/dt = -ω × (m - b), b fitted, in the device frame (gyro bias left in)."""
    t = np.arange(rec.gyro.t[0] + 1, rec.gyro.t[-1] - 1, dt)

    def res(s):
        return uniform_filter1d(
            np.column_stack([np.interp(t, s.t, s.xyz[:, i]) for i in range(3)]), 25, axis=0
        )

    w, m = res(rec.gyro), res(rec.mag)
    d = np.gradient(m, dt, axis=0)
    pred = -np.cross(w, m)
    skew = np.zeros((len(w), 3, 3))
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -w[:, 2], w[:, 1], -w[:, 0]
    skew[:, 1, 0], skew[:, 2, 0], skew[:, 2, 1] = w[:, 2], -w[:, 1], w[:, 0]
    b = np.linalg.lstsq(skew.reshape(-1, 3), (d - pred).ravel(), rcond=None)[0]
    return np.sqrt(np.mean((d - pred - skew @ b) ** 2) / np.mean(d**2))


def test_full_sphere_units_axes_saturation():
    d = dataset("sunsided-marg", "set-2", "full-sphere")
    assert detect(d) == "sunsided-marg"
    rec = read_recording(d)
    assert len(rec.mag) == 8190 and len(rec.accel) == 10528
    assert rec.dropped["gyro:saturated"] == 22  # SOURCE.md: 22 samples at ±250 deg/s
    # sphere radius 0.537 G → ≈ 54 µT
    assert 50 < np.median(np.linalg.norm(rec.mag.xyz, axis=1)) < 58
    assert _kinematic_residual(rec) < 0.3


@pytest.mark.parametrize(
    "name,axis",
    [("unmoved-with-z-pointing-front-and-x-up", 1), ("unmoved-with-z-pointing-front-and-y-down", 0)],
)
def test_static_poses(name, axis):
    rec = read_recording(dataset("sunsided-marg", "set-2", name))
    f = np.median(rec.accel.xyz, axis=0)
    assert f[axis] > 9.5  # board x up → device y up; board y down → device x (= −board y) up


def test_turn_about_up_is_counter_clockwise():
    rec = read_recording(dataset("sunsided-marg", "set-2", "rotate-ccw-around-z-pointing-up"))
    turn = np.degrees(np.trapezoid(rec.gyro.xyz[:, 2], rec.gyro.t))
    assert 700 < turn < 780  # two CCW turns (+ gyro bias); level, north-ish: field north and down
    assert np.median(rec.accel.xyz[:, 2]) > 9.5


def _fixture(tmp_path, mpu_rows=None, hmc_rows=None):
    d = tmp_path / "rec"
    d.mkdir()
    mpu = mpu_rows or [
        "0.00,0.0,0.0,-1.0,1.0,2.0,3.0,25.0",
        "0.01,0.0,0.0,-1.0,1.0,2.0,250.13,25.0",
        "0.01,0.0,0.0,-1.0,1.0,2.0,3.0,25.0",
        "0.02,0.5,0.0,-1.0,nan,2.0,3.0,25.0",
        "0.03,0.0,0.0,-1.0,1.0,2.0,3.0,25.0",
    ]
    hmc = hmc_rows or ["0.005,0.2,-0.1,-0.3", "0.018,0.2,-0.1,-0.3", "0.031,0.21,-0.1,-0.3"]
    (d / "mpu6050.csv").write_text(",".join(sunsided.MPU_HEADER) + ",temp_C\n" + "\n".join(mpu) + "\n")
    (d / "hmc5883l.csv").write_text(",".join(sunsided.HMC_HEADER) + "\n" + "\n".join(hmc) + "\n")
    return d


def test_fixture_conversion(tmp_path):
    rec = read_recording(_fixture(tmp_path))
    np.testing.assert_allclose(rec.mag.xyz[0], [10.0, 20.0, -30.0])  # (−y, x, z) × 100
    np.testing.assert_allclose(rec.accel.xyz[0], [0.0, 0.0, 9.80665])
    np.testing.assert_allclose(rec.gyro.xyz[0], np.radians([2.0, -1.0, 3.0]))  # (g_y, −g_x, g_z)
    assert rec.dropped == {"gyro:saturated": 1, "accel:duplicate_t": 1, "gyro:duplicate_t": 1, "gyro:nan": 1}
    assert len(rec.accel) == 4 and len(rec.gyro) == 3


@pytest.mark.parametrize(
    "hmc,problem,line",
    [
        (["0.0,0.2,-0.1,-0.3", "0.1,0.2,-0.1,-0.3", "0.05,0.2,-0.1,-0.3"], "time goes backwards", 4),
        (["0.0,0.2,-0.1,-0.3", "0.1,0.2"], "truncated", 3),
        (["0.0,20,-10,-30", "0.1,20,-10,-30"], "wrong unit", None),
    ],
)
def test_malformed(tmp_path, hmc, problem, line):
    with pytest.raises(InputError) as ei:
        read_recording(_fixture(tmp_path, hmc_rows=hmc))
    assert problem in ei.value.problem and ei.value.line == line and "hmc5883l.csv" in ei.value.path


def test_bad_header_and_mat_only(tmp_path):
    d = _fixture(tmp_path)
    (d / "hmc5883l.csv").write_text("t,x,y,z\n0,1,2,3\n")
    with pytest.raises(InputError, match="bad header"):
        read_recording(d)
    e = tmp_path / "matonly" / "original_mat"
    e.mkdir(parents=True)
    (e / "hmc5883l_compass.mat").write_bytes(b"MATLAB 7.3 MAT-file")
    with pytest.raises(InputError, match="h5py"):
        read_recording(e.parent)


def test_breadboard_temperature_channel_is_exposed():
    rec = read_recording(dataset("sunsided-marg", "set-2", "full-sphere"))
    t, temp = rec.temperature
    assert len(t) == len(temp) == len(rec.accel)
    assert np.all(np.diff(t) > 0)
    assert 0.0 < np.median(temp) < 60.0  # °C of a breadboard on a desk
