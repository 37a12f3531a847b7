"""BROAD benchmark MATLAB files: a real trial (truth consistency) and synthetic files written with savemat."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.io import savemat

from pdr_mag.conventions import quat_to_rot
from replay.errors import InputError
from replay.formats import broad, detect, read_recording
from tests.conftest import dataset


def test_real_trial_truth_consistent():
    f = dataset("broad", "data_mat", "01_undisturbed_slow_rotation_A.mat")
    assert detect(f) == "broad"
    rec = read_recording(f)
    assert len(rec.mag) == 56940 and abs(rec.mag.rate_hz - 285.714) < 0.01
    assert rec.meta["truth_north"] == "magnetic" and rec.dropped["truth:nan"] == 162
    tq, q = rec.truth
    i = np.searchsorted(rec.mag.t, tq)
    rot = quat_to_rot(q)
    field_w = np.median(np.einsum("nij,nj->ni", rot, rec.mag.xyz[i]), axis=0)
    up_w = np.median(np.einsum("nij,nj->ni", rot, rec.accel.xyz[i]), axis=0)
    # SOURCE.md: (E, N, U) ≈ (−0.6, 14.7, −40.6) µT — magnetic north; specific force +g up
    np.testing.assert_allclose(field_w, [-0.6, 14.7, -40.6], atol=0.5)
    np.testing.assert_allclose(up_w, [0, 0, 9.81], atol=0.15)


def _mat(tmp_path, **over):
    n = 50
    rng = np.random.default_rng(0)
    d = {
        "imu_acc": np.tile([0.0, 0.0, 9.81], (n, 1)) + 0.01 * rng.standard_normal((n, 3)),
        "imu_gyr": 0.01 * rng.standard_normal((n, 3)),
        "imu_mag": np.tile([0.0, 20.0, -40.0], (n, 1)),
        "opt_quat": np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)),
        "sampling_rate": 100.0,
        "info": "synthetic",
    }
    d["imu_mag"][3, 1] = np.nan
    d["opt_quat"][5] = np.nan
    d.update(over)
    f = tmp_path / "trial.mat"
    savemat(f, {k: v for k, v in d.items() if v is not None})
    return f


def test_synthetic(tmp_path):
    rec = read_recording(_mat(tmp_path))
    assert rec.format == "broad" and rec.meta["info"] == "synthetic"
    assert len(rec.mag) == 49 and len(rec.truth[0]) == 49
    assert rec.dropped == {"mag:nan": 1, "truth:nan": 1}
    np.testing.assert_allclose(rec.accel.t[:3], [0.0, 0.01, 0.02])


@pytest.mark.parametrize(
    "over,problem",
    [
        ({"imu_mag": np.tile([0.0, 0.2, -0.4], (50, 1))}, "wrong unit"),  # gauss, not µT
        ({"imu_gyr": np.zeros((10, 3))}, "imu_gyr has shape"),
        ({"sampling_rate": None}, "'sampling_rate' missing"),
        ({"sampling_rate": -1.0}, "expected > 0 Hz"),
    ],
)
def test_malformed(tmp_path, over, problem):
    f = _mat(tmp_path, **over)
    with pytest.raises(InputError, match=problem):
        broad.read(f)


def test_truncated_detected(tmp_path):
    f = _mat(tmp_path)
    f.write_bytes(f.read_bytes()[:300])
    with pytest.raises(InputError, match="trial.mat: a MATLAB file without .* or truncated"):
        read_recording(f)


def test_truncated_file(tmp_path):
    f = _mat(tmp_path)
    data = f.read_bytes()
    f.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match="trial.mat: cannot read"):
        broad.read(f)
