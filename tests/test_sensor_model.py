"""The forward sensor model: effect registry, parsing, each formula, its inverse, noise statistics."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pdr_mag.conventions import GRAVITY, quat_to_rot, rotation_to_quat
from pdr_mag.sim.sensor_model import (
    EFFECT_SIZES,
    EFFECTS,
    DipoleField,
    Motion,
    PhoneSpec,
    SensorModel,
    correct_mag,
    digitise,
    integrate_gyro,
    mag_from_orientation,
    measure_mag,
    normalise_effect,
    pack_effect,
    parse_effect_value,
    predict_accel,
    predict_gyro,
    predict_mag,
    quat_rotate,
    quat_slerp,
    unpack_effect,
)

FIELD_W = np.array([1.36, 21.54, -43.30])
INTERFACE_EFFECTS = (
    "hard_iron soft_iron time_offset mag_imu_misalignment bias_drift local_anomaly gyro_bias noise".split()
)
UNITS = {
    "hard_iron": "µT",
    "time_offset": "s",
    "mag_imu_misalignment": "deg",
    "bias_drift": "µT/min",
    "local_anomaly": "µT",
    "gyro_bias": "rad/s",
    "noise": "µT",
}


def _random_motion(rng, n=400, duration=20.0):
    t = np.linspace(0.0, duration, n)
    # a smooth tumbling motion: rotation vector growing with time
    rv = np.column_stack([0.5 * np.sin(0.3 * t), 0.8 * np.sin(0.21 * t + 1), 0.4 * t])
    q = rotation_to_quat(Rotation.from_rotvec(rv))
    return Motion(t, q, position_w=np.column_stack([0.5 * t, np.zeros(n), np.full(n, 1.2)]))


def _full_model():
    return SensorModel(
        {
            "hard_iron": [30.0, -12.0, 80.0],
            "soft_iron": [1.1, 0.95, 1.02, 0.03, -0.02, 0.01],
            "mag_imu_misalignment": [2.0, -1.0, 3.0],
            "bias_drift": [0.5, -0.2, 0.1],
        },
        t_ref=1.0,
    )


def test_registry_names_and_units_are_the_contract():
    assert tuple(EFFECTS) == tuple(INTERFACE_EFFECTS)
    for name, unit in UNITS.items():
        assert EFFECTS[name].unit == unit
    assert all(e.description and e.cli for e in EFFECTS.values())


@pytest.mark.parametrize(
    ("name", "value", "expected"),
    [
        ("hard_iron", 5.0, [5.0, 5.0, 5.0]),
        ("hard_iron", [1, 2, 3], [1, 2, 3]),
        ("noise", 0.4, [0.4, 0.4, 0.4]),
        ("soft_iron", 1.1, np.diag([1.1] * 3)),
        ("soft_iron", [1.0, 2.0, 3.0], np.diag([1.0, 2.0, 3.0])),
        ("soft_iron", [1, 2, 3, 0.1, 0.2, 0.3], [[1, 0.1, 0.2], [0.1, 2, 0.3], [0.2, 0.3, 3]]),
        ("time_offset", 0.04, 0.04),
        ("mag_imu_misalignment", np.sqrt(3.0), [1.0, 1.0, 1.0]),
    ],
)
def test_normalise_shorthands(name, value, expected):
    got = normalise_effect(name, value)
    np.testing.assert_allclose(got, expected)
    assert not got.flags.writeable


@pytest.mark.parametrize(
    ("name", "value"),
    [
        ("hard_iron", [1, 2]),
        ("hard_iron", [np.nan, 0, 0]),
        ("noise", -0.1),
        ("soft_iron", [1, 2]),
        ("soft_iron", [[1, 0.5, 0], [0, 1, 0], [0, 0, 1]]),
        ("soft_iron", [1, 1, -1]),
        ("time_offset", [1, 2]),
        ("local_anomaly", 30.0),
        ("wobble", 1.0),
    ],
)
def test_bad_values_raise_naming_the_effect(name, value):
    with pytest.raises(ValueError, match=name):
        normalise_effect(name, value)
    if name != "wobble":
        with pytest.raises(ValueError, match=name):
            SensorModel({name: value})


def test_parse_effect_value():
    assert parse_effect_value("noise", "off") is None
    np.testing.assert_allclose(parse_effect_value("hard_iron", "30,-12,80"), [30, -12, 80])
    assert parse_effect_value("time_offset", " 0.04 ") == 0.04
    assert parse_effect_value("local_anomaly", "25") == 25.0
    for name, text in [("noise", "abc"), ("hard_iron", "1,2"), ("local_anomaly", "-3"), ("nope", "1")]:
        with pytest.raises(ValueError):
            parse_effect_value(name, text)


def test_model_switching_and_json_round_trip():
    m = _full_model().with_effects(noise=0.3, time_offset=0.02)
    assert m.active == (
        "hard_iron",
        "soft_iron",
        "time_offset",
        "mag_imu_misalignment",
        "bias_drift",
        "noise",
    )
    assert "noise" not in m.without("noise").active
    assert m.only("hard_iron").active == ("hard_iron",)
    assert m.with_effects(noise=None) == m.without("noise")
    np.testing.assert_array_equal(m.without("soft_iron").value("soft_iron"), np.eye(3))
    assert SensorModel.from_json(m.to_json(), t_ref=m.t_ref) == m
    assert hash(SensorModel.from_json(m.to_json(), t_ref=m.t_ref)) == hash(m)
    odd = SensorModel({"hard_iron": [0.1 + 0.2, 1 / 3, np.pi]})
    assert SensorModel.from_json(odd.to_json()) == odd  # exact: JSON floats round-trip
    dip = DipoleField([[0, 0, 0]], [[0, 0, 5.0]], 5.0)
    m2 = SensorModel({"local_anomaly": dip})
    back = SensorModel.from_json(m2.to_json())
    np.testing.assert_allclose(back.value("local_anomaly").moments_w, dip.moments_w)


def test_neutral_model_is_the_rotated_field():
    rng = np.random.default_rng(0)
    mot = _random_motion(rng)
    m = predict_mag(SensorModel(), mot.t, mot, FIELD_W)
    expected = np.einsum("nji,j->ni", quat_to_rot(mot.q_wd), FIELD_W)  # R^T f
    np.testing.assert_allclose(m, expected, atol=1e-12)


def test_correct_mag_inverts_the_static_effects_exactly():
    rng = np.random.default_rng(1)
    mot = _random_motion(rng)
    model = _full_model()
    raw = predict_mag(model, mot.t, mot, FIELD_W)
    h_d = correct_mag(model, mot.t, raw)
    np.testing.assert_allclose(h_d, quat_rotate(mot.q_wd, FIELD_W, inverse=True), atol=1e-10)
    # the calibration object of the same phone does the same thing
    for k in (0, 100, 399):
        cal = model.ideal_calibration(mot.t[k])
        np.testing.assert_allclose(cal.apply(raw[k]), h_d[k], atol=1e-10)


def test_soft_iron_is_the_calibration_correction_matrix():
    s = normalise_effect("soft_iron", [1.2, 0.9, 1.0, 0.05, 0.0, 0.0])
    model = SensorModel({"soft_iron": s})
    raw = mag_from_orientation(model, np.zeros(1), np.array([[1.0, 0, 0, 0]]), FIELD_W)
    np.testing.assert_allclose(s @ raw[0], FIELD_W, atol=1e-12)  # S · m_raw = field (identity pose)


def test_hard_iron_and_bias_drift():
    model = SensorModel({"hard_iron": [10, 20, 30], "bias_drift": [6, 0, -3]}, t_ref=5.0)
    np.testing.assert_allclose(
        model.offset(np.array([5.0, 65.0, 125.0])), [[10, 20, 30], [16, 20, 27], [22, 20, 24]]
    )


def test_time_offset_means_late_stamps():
    rng = np.random.default_rng(2)
    mot = _random_motion(rng)
    t = np.linspace(2.0, 18.0, 300)
    late = predict_mag(SensorModel({"time_offset": 0.05}), t, mot, FIELD_W)
    np.testing.assert_allclose(late, predict_mag(SensorModel(), t - 0.05, mot, FIELD_W), atol=1e-12)


def test_misalignment_is_a_rotation_of_the_given_angle():
    model = SensorModel({"mag_imu_misalignment": 3.0})
    r = model.mag_to_imu
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-14)
    assert np.degrees(np.arccos((np.trace(r) - 1) / 2)) == pytest.approx(3.0)
    np.testing.assert_allclose(r @ np.ones(3), np.ones(3), atol=1e-12)  # about (1,1,1)


def test_dipole_field_on_axis_and_required_positions():
    dip = DipoleField([[0.0, 0.0, 0.0]], [[0.0, 0.0, 8.0]])
    b = dip.field_w(np.array([[0.0, 0.0, 2.0], [2.0, 0.0, 0.0]]))
    np.testing.assert_allclose(b, [[0, 0, 2 * 8 / 8], [0, 0, -8 / 8]], atol=1e-12)  # 2m/r³ and −m/r³
    model = SensorModel({"local_anomaly": dip})
    with pytest.raises(ValueError, match="position_w"):
        mag_from_orientation(model, np.zeros(1), np.array([[1.0, 0, 0, 0]]), FIELD_W)
    rng = np.random.default_rng(3)
    mot = _random_motion(rng)
    diff = predict_mag(model, mot.t, mot, FIELD_W) - predict_mag(SensorModel(), mot.t, mot, FIELD_W)
    np.testing.assert_allclose(
        diff, quat_rotate(mot.q_wd, dip.field_w(mot.position_w), inverse=True), atol=1e-12
    )


def test_slerp_keys_and_midpoint():
    q = rotation_to_quat(Rotation.from_rotvec([[0, 0, 0], [0, 0, 1.0], [0, 0, 3.0]]))
    tk = np.array([0.0, 1.0, 2.0])
    np.testing.assert_allclose(np.abs(np.sum(quat_slerp(tk, q, tk) * q, axis=1)), 1.0, atol=1e-12)
    mid = quat_slerp(tk, q, np.array([0.5, 1.5, -1.0, 9.0]))
    ang = Rotation.from_quat(mid[:, [1, 2, 3, 0]]).as_rotvec()[:, 2]
    np.testing.assert_allclose(ang, [0.5, 2.0, 0.0, 3.0], atol=1e-12)


def test_measure_mag_noise_is_white_with_sigma():
    rng = np.random.default_rng(4)
    mot = _random_motion(rng, n=2000)
    sigma = np.array([0.3, 0.5, 0.4])
    model = SensorModel({"noise": sigma})
    t = np.linspace(0.0, 20.0, 20000)
    res = measure_mag(model, t, mot, FIELD_W, rng, PhoneSpec.ideal()) - predict_mag(model, t, mot, FIELD_W)
    n = len(t)
    # std estimate of a Gaussian: relative σ ≈ 1/sqrt(2n); allow 5 of them
    np.testing.assert_allclose(res.std(axis=0) / sigma, 1.0, atol=5 / np.sqrt(2 * n))
    lag1 = np.mean(res[1:] * res[:-1], axis=0) / res.var(axis=0)
    assert np.all(np.abs(lag1) < 5 / np.sqrt(n))


def test_digitise_saturates_then_rounds():
    v = np.array([-100.0, -0.26, 0.0749, 0.076, 100.0])
    np.testing.assert_allclose(digitise(v, 10.0, 0.15), [-10.05, -0.3, 0.0, 0.15, 10.05])
    np.testing.assert_array_equal(digitise(v, np.inf, 0.0), v)


def test_inertial_forward_models():
    q = rotation_to_quat(Rotation.from_euler("x", 90, degrees=True))[None]
    # phone rotated top-up (y along world z): gravity reaction appears on +y
    np.testing.assert_allclose(predict_accel(q, np.zeros((1, 3))), [[0, GRAVITY, 0]], atol=1e-12)
    model = SensorModel({"gyro_bias": [0.01, -0.02, 0.03]})
    np.testing.assert_allclose(predict_gyro(model, np.zeros((2, 3))), [[0.01, -0.02, 0.03]] * 2)


def test_motion_validates_input():
    with pytest.raises(ValueError, match="t"):
        Motion(np.array([0.0, 0.0]), np.tile([1.0, 0, 0, 0], (2, 1)))
    with pytest.raises(ValueError, match="q_wd"):
        Motion(np.array([0.0, 1.0]), np.ones((2, 3)))


def test_pack_unpack_round_trip_for_fitting():
    values = {
        "hard_iron": [1, 2, 3],
        "soft_iron": [1.1, 0.9, 1.0, 0.02, -0.01, 0.03],
        "time_offset": 0.04,
        "mag_imu_misalignment": [1, -2, 0.5],
        "bias_drift": 0.3,
        "gyro_bias": [0.01, 0, -0.01],
        "noise": 0.4,
    }
    assert set(values) == set(EFFECT_SIZES)
    for name, v in values.items():
        p = pack_effect(name, v)
        assert p.shape == (EFFECT_SIZES[name],)
        np.testing.assert_allclose(unpack_effect(name, p), normalise_effect(name, v))
    with pytest.raises(ValueError, match="local_anomaly"):
        pack_effect("local_anomaly", DipoleField([[0, 0, 0]], [[1, 0, 0]]))
    with pytest.raises(ValueError, match="hard_iron"):
        unpack_effect("hard_iron", [1, 2])


def test_integrate_gyro_constant_rate_is_exact():
    t = np.cumsum(np.random.default_rng(5).uniform(0.004, 0.006, 2001)) - 0.005
    w = np.array([0.3, -0.2, 0.5])
    q = integrate_gyro(t, np.tile(w, (len(t), 1)), [1.0, 0, 0, 0])
    expected = rotation_to_quat(Rotation.from_rotvec(np.outer(t - t[0], w)))
    np.testing.assert_allclose(np.abs(np.sum(q * expected, axis=1)), 1.0, atol=1e-12)


def test_known_answer_seed_000_lumped_model_is_representable():
    """Seed 000 (eqs. 2–4): H_m = S·H_i + b with S = C_k C_n C_s, b = C_k C_n b_h + b_o, and its simulation
    settings.  Any such S (det > 0) is soft_iron⁻¹ · mag_to_imuᵀ (left polar decomposition S = P·U), so the
    model reproduces the seed's sensor exactly."""
    from scipy.linalg import polar

    al, be, ga = np.radians([1.2, 87.6, 87.0])
    c_n = np.array(
        [
            [np.sqrt(1 - np.cos(be) ** 2 - np.cos(ga) ** 2), np.cos(be), np.cos(ga)],
            [0.0, np.cos(al), np.sin(al)],
            [0.0, 0.0, 1.0],
        ]
    )
    c_k = np.diag([1.0, 0.9, 1.2])
    c_s = np.array([[1.23, 0.23, 0.32], [0.23, 1.45, 0.45], [0.32, 0.45, 1.56]])
    b_h, b_o = np.array([7.0, 7.5, 8.0]), np.array([9.0, 8.5, 7.5])  # the seed's 700…900 (×0.01 → µT)
    s = c_k @ c_n @ c_s
    b = c_k @ c_n @ b_h + b_o
    u, p = polar(s, side="left")  # s = p @ u
    model = SensorModel(
        {
            "hard_iron": b,
            "soft_iron": np.linalg.inv(p),
            "mag_imu_misalignment": np.degrees(Rotation.from_matrix(u.T).as_rotvec()),
        }
    )
    f = 48.152
    dec, inc = np.radians([-4.57, 44.57])
    field_w = f * np.array([np.cos(inc) * np.sin(dec), np.cos(inc) * np.cos(dec), -np.sin(inc)])
    rng = np.random.default_rng(9)
    mot = _random_motion(rng)
    h_i = quat_rotate(mot.q_wd, field_w, inverse=True)
    np.testing.assert_allclose(predict_mag(model, mot.t, mot, field_w), h_i @ s.T + b, atol=1e-9)
