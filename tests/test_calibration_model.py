import numpy as np
import pytest

from pdr_mag.calibration import MagCalibration, fit_sphere


def _sphere_samples(rng, n, radius, offset, sigma):
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    return radius * u + offset + rng.normal(scale=sigma, size=(n, 3))


def test_fit_sphere_recovers_offset_within_its_own_uncertainty():
    rng = np.random.default_rng(3)
    offset = np.array([58.0, -74.0, 412.0])
    errs = []
    for _ in range(200):
        cal = fit_sphere(_sphere_samples(rng, 400, 47.0, offset, 0.5))
        errs.append((cal.offset_array - offset) / np.asarray(cal.offset_std_uT))
    z = np.asarray(errs)
    # normalised errors: unit variance if the reported std is honest (χ² bounds for 600 draws)
    assert 0.8 < np.mean(z**2) < 1.25
    assert abs(cal.field_uT - 47.0) < 0.2


def test_json_round_trip_and_apply(tmp_path):
    a = np.array([[1.1, 0.02, 0.0], [0.02, 0.95, 0.01], [0.0, 0.01, 1.0]])
    cal = MagCalibration.from_arrays([1.0, 2.0, 3.0], a, field_uT=47.0, method="ml", n_samples=10,
                                     offset_std_uT=[0.1, 0.1, 0.2], coverage=0.8)
    path = tmp_path / "cal.json"
    cal.to_json(path)
    back = MagCalibration.from_json(path)
    assert back.to_dict() == cal.to_dict()
    m = np.array([[11.0, 2.0, 3.0], [1.0, 2.0, 13.0]])
    np.testing.assert_allclose(back.apply(m), (m - [1, 2, 3]) @ a.T)
    d = cal.to_dict()
    for key in ("format_version", "method", "offset_uT", "soft_iron", "field_uT", "residual_rms_uT",
                "offset_std_uT", "n_samples", "coverage", "accepted", "reasons"):
        assert key in d


def test_bad_calibration_objects_raise_naming_the_key():
    with pytest.raises(ValueError, match="offset"):
        MagCalibration.from_arrays([1.0, 2.0], None)
    with pytest.raises(ValueError, match="format_version"):
        MagCalibration.from_dict(
            {"format_version": 7, "offset_uT": [0, 0, 0], "soft_iron": np.eye(3).tolist()}
        )
    with pytest.raises(ValueError, match="soft_iron"):
        MagCalibration.from_dict({"format_version": 1, "offset_uT": [0, 0, 0]})
    # values no calibration can have: each named, never a numpy error later
    good = {"format_version": 1, "offset_uT": [0, 0, 0], "soft_iron": np.eye(3).tolist(), "field_uT": 48.0}
    for key, value, needle in (
        ("soft_iron", [[0, 0, 0], [0, 1, 0], [0, 0, 1]], "soft_iron: expected a positive-definite"),
        ("soft_iron", [[-1, 0, 0], [0, 1, 0], [0, 0, 1]], "soft_iron: expected a positive-definite"),
        ("soft_iron", [[float("nan"), 0, 0], [0, 1, 0], [0, 0, 1]], "soft_iron: .*NaN or infinite"),
        ("field_uT", -5.0, "field_uT: expected a positive"),
        ("offset_std_uT", [-1.0, 0.5, 0.5], "offset_std_uT"),
    ):
        with pytest.raises(ValueError, match=needle):
            MagCalibration.from_dict({**good, key: value})
    assert MagCalibration.from_dict({**good, "offset_std_uT": [None, 0.5, 0.5]}).field_uT == 48.0
    with pytest.raises(ValueError, match="samples"):
        fit_sphere(np.ones((3, 3)))
    with pytest.raises(ValueError, match="3-D"):
        fit_sphere(np.ones((10, 3)))
