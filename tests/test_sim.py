"""The simulator: physically consistent truth, each effect's own signature, determinism, phone realities."""

from __future__ import annotations

import numpy as np
import pytest

from pdr_mag.conventions import GRAVITY
from pdr_mag.sim import SCENARIOS, simulate
from pdr_mag.sim.sensor_model import (
    EFFECTS,
    Motion,
    PhoneSpec,
    SensorModel,
    correct_mag,
    integrate_gyro,
    normalise_effect,
    predict_mag,
    quat_multiply,
    quat_rotate,
)

WALKING = ("walk", "swing", "pocket")


def _integrate_gyro(t, omega, q0):
    """q_{k+1} = q_k ⊗ exp(½ ω̄ Δt), ω̄ = (ω_k + ω_{k+1})/2 (trapezoid rate, one rotation per step)."""
    wm = 0.5 * (omega[1:] + omega[:-1])
    ang = np.linalg.norm(wm, axis=1) * np.diff(t)
    axis = wm / np.maximum(np.linalg.norm(wm, axis=1, keepdims=True), 1e-300)
    dq = np.column_stack([np.cos(0.5 * ang), axis * np.sin(0.5 * ang)[:, None]])
    out = np.empty((len(t), 4))
    out[0] = q0
    q = q0
    for k in range(len(dq)):
        q = quat_multiply(q, dq[k])
        out[k + 1] = q
    return out


def _angle_deg(q1, q2):
    """Angle between orientations from the vector part of q1⁻¹ ⊗ q2 (precise for small angles)."""
    d = quat_multiply(q1 * [1.0, -1.0, -1.0, -1.0], q2)
    return np.degrees(2.0 * np.arcsin(np.clip(np.linalg.norm(d[..., 1:], axis=-1), 0.0, 1.0)))


def test_scenarios_of_the_contract_exist():
    assert {"figure8", "walk", "swing", "pocket", "still", "mixed"} <= set(SCENARIOS)
    with pytest.raises(ValueError, match="scenario"):
        simulate("moonwalk")
    with pytest.raises(ValueError, match="effect"):
        simulate("still", effects={"wobble": 1})
    assert simulate("still", seed=0, duration_s=12.5).duration_s == 12.5


@pytest.mark.parametrize("scenario", ["figure8", "walk", "swing", "pocket", "mixed"])
def test_integrating_the_gyro_reproduces_the_truth(scenario):
    res = simulate(
        scenario,
        seed=3,
        duration_s=40.0,
        effects={"gyro_bias": None},
        phone=PhoneSpec.ideal(gyro_rate_hz=200.0),
    )
    t, omega = res.gyro
    traj = res.trajectory
    q_true = traj.orientation(t)
    q_int = integrate_gyro(t, omega, q_true[0])
    if scenario == "figure8":  # the library's prefix scan equals the plain sequential loop
        assert _angle_deg(q_int, _integrate_gyro(t, omega, q_true[0])).max() < 1e-9
    err = np.radians(_angle_deg(q_int, q_true))
    # bound of the scheme: per step Δt³/12 (|ω̈| + |ω × ω̇|) (trapezoid error + second Magnus term), summed
    dt = np.diff(t)
    wd = np.gradient(omega, t, axis=0)
    wdd = np.gradient(wd, t, axis=0)
    local = dt**3 / 12.0 * (np.linalg.norm(wdd[1:], axis=1) + np.linalg.norm(np.cross(omega, wd)[1:], axis=1))
    bound = 2.0 * np.concatenate([[0.0], np.cumsum(local)]) + 1e-9
    assert np.all(err <= bound), f"max error {err.max():.3g} rad vs bound {bound[-1]:.3g} rad"
    assert res.gyro[1].shape == (len(t), 3)


@pytest.mark.parametrize("scenario", ["figure8", "walk", "swing", "pocket", "still"])
def test_accelerometer_is_gravity_plus_linear_acceleration(scenario):
    res = simulate(scenario, seed=4, duration_s=30.0, phone=PhoneSpec.ideal())
    traj = res.trajectory
    t, f_d = res.accel
    f_w = quat_rotate(traj.orientation(t), f_d)
    np.testing.assert_allclose(f_w - [0.0, 0.0, GRAVITY], traj.accel_w(t), atol=1e-9)
    # and the linear acceleration is the second derivative of the position (central difference, step h):
    # error ≤ h²/12 · max|p⁗| = h²/12 · max|ä|
    h = 0.01
    ts = t[200:-200:7]
    p2 = (traj.position(ts + h) - 2 * traj.position(ts) + traj.position(ts - h)) / h**2
    a = traj.accel_w(ts)
    add = (traj.accel_w(ts + h) - 2 * a + traj.accel_w(ts - h)) / h**2
    bound = 2.0 * h**2 / 12.0 * np.abs(add).max() + 1e-6
    assert np.abs(p2 - a).max() <= bound


def test_still_phone_measures_gravity_and_bias_only():
    res = simulate("still", seed=5, duration_s=20.0)
    np.testing.assert_allclose(res.accel[1].mean(axis=0), [0, 0, GRAVITY], atol=0.01)
    np.testing.assert_allclose(res.gyro[1].mean(axis=0), res.model.value("gyro_bias"), atol=0.0005)


def test_inverting_the_model_on_the_magnetometer_gives_the_wmm_field():
    res = simulate("figure8", seed=6, duration_s=60.0)  # default phone: noise 0.4 µT, 0.15 µT steps
    model, field_w = res.model, res.field.field_w_array
    t, raw = res.mag
    q = res.trajectory.orientation(model.measurement_time(t))
    # residual in magnetometer axes before the soft-iron correction is noise + quantisation only
    noiseless = predict_mag(model.without("noise"), t, res.trajectory, res.field)
    r = raw - noiseless
    sd = np.sqrt(model.value("noise") ** 2 + res.phone.mag_step**2 / 12.0)
    n = len(t)
    np.testing.assert_allclose(r.std(axis=0) / sd, 1.0, atol=5 / np.sqrt(2 * n))
    assert np.all(np.abs(r.mean(axis=0)) < 5 * sd / np.sqrt(n))
    # rotated into the world frame, the corrected field is the WMM vector
    h_w = quat_rotate(q, correct_mag(model, t, raw))
    np.testing.assert_allclose(h_w.mean(axis=0), field_w, atol=5 * 0.6 / np.sqrt(n) * 3)
    assert res.field.strength == pytest.approx(48.38, abs=0.05)  # Zürich 2026 (WMM-2025)


def test_time_offset_shows_as_lag_against_the_gyro_predicted_field():
    offset = 0.04
    res = simulate("figure8", seed=7, duration_s=40.0, effects={"time_offset": offset})
    model = res.model
    t_g, omega = res.gyro
    q_gyro = integrate_gyro(t_g, omega - model.value("gyro_bias"), res.trajectory.orientation(t_g[:1])[0])
    gyro_motion = Motion(t_g, q_gyro)
    t, raw = res.mag
    keep = (t > 1.0) & (t < 39.0)
    no_offset = model.without("time_offset")
    lags = np.arange(-0.1, 0.1001, 0.002)
    gap = [
        np.sqrt(np.mean((raw[keep] - predict_mag(no_offset, t[keep] - lag, gyro_motion, res.field)) ** 2))
        for lag in lags
    ]
    best = lags[int(np.argmin(gap))]
    assert best == pytest.approx(offset, abs=0.004)
    assert min(gap) < 0.6 < gap[int(np.argmin(np.abs(lags)))]


def _pair(effect, value, scenario="walk", **kw):
    """The same seed without and with one effect, on an ideal phone and without other effects."""
    common = dict(seed=8, duration_s=30.0, defaults=False, phone=PhoneSpec.ideal())
    common.update(kw)
    return simulate(scenario, **common), simulate(scenario, effects={effect: value}, **common)


def test_each_effect_leaves_its_own_signature():
    base, on = _pair("hard_iron", [30.0, -12.0, 80.0])
    np.testing.assert_allclose(
        on.mag[1] - base.mag[1], np.tile([30.0, -12.0, 80.0], (len(base.mag[0]), 1)), atol=1e-9
    )

    base, on = _pair("bias_drift", [6.0, 0.0, -3.0])
    np.testing.assert_allclose(
        on.mag[1] - base.mag[1], np.outer(base.mag[0] / 60.0, [6.0, 0.0, -3.0]), atol=1e-9
    )

    s = normalise_effect("soft_iron", [1.1, 0.9, 1.0, 0.05, 0.0, -0.02])
    base, on = _pair("soft_iron", s)
    np.testing.assert_allclose(on.mag[1] @ s.T, base.mag[1], atol=1e-9)

    base, on = _pair("mag_imu_misalignment", [2.0, -3.0, 1.0])
    r = on.model.mag_to_imu
    np.testing.assert_allclose(on.mag[1] @ r.T, base.mag[1], atol=1e-9)

    base, on = _pair("gyro_bias", [0.01, -0.02, 0.005])
    np.testing.assert_allclose(
        on.gyro[1] - base.gyro[1], np.tile([0.01, -0.02, 0.005], (len(base.gyro[0]), 1)), atol=1e-12
    )
    np.testing.assert_array_equal(on.mag[1], base.mag[1])
    np.testing.assert_array_equal(on.accel[1], base.accel[1])

    base, on = _pair("noise", 0.5)
    d = on.mag[1] - base.mag[1]
    np.testing.assert_allclose(d.std(axis=0), 0.5, rtol=5 / np.sqrt(2 * len(d)))

    base, on = _pair("time_offset", 0.05)
    # same true measurement instants, stamped 50 ms later; the values at a given instant are unchanged
    n = len(on.mag[0])
    np.testing.assert_allclose(on.mag[0], base.mag[0][:n] + 0.05, atol=1e-12)
    np.testing.assert_allclose(on.mag[1], base.mag[1][:n], atol=1e-9)


def test_local_anomaly_stays_in_the_steel_area():
    base, on = _pair("local_anomaly", 30.0, scenario="mixed", duration_s=90.0)
    sim = on.meta["simulation"]
    (steel,) = sim["steel_windows"]
    t = base.mag[0]
    d = np.linalg.norm(correct_mag(on.model, t, on.mag[1]) - base.mag[1], axis=1)
    assert d.max() == pytest.approx(30.0, rel=0.05)
    assert d[(t > steel["t0"]) & (t < steel["t1"])].max() > 15.0
    assert d[t < 20.0].max() < 1.0  # the calibration part is far from the steel
    # outside the reported anomaly windows the anomaly is below the threshold (10 Hz grid: ±0.1 s slack)
    inside = np.zeros(len(t), bool)
    for w in sim["anomaly_windows"]:
        inside |= (t >= w["t0"] - 0.1) & (t <= w["t1"] + 0.1)
    assert d[~inside].max() <= 1.0
    assert max(w["peak_uT"] for w in sim["anomaly_windows"]) == pytest.approx(30.0, rel=0.05)
    # the field seen is the dipoles' field at the phone's position
    dip = on.model.value("local_anomaly")
    ref = np.linalg.norm(dip.field_w(on.trajectory.position(t)), axis=1)
    np.testing.assert_allclose(d, ref, atol=1e-9)


def test_same_seed_same_numbers_and_effects_do_not_move_the_rest():
    a = simulate("mixed", seed=11, duration_s=40.0)
    b = simulate("mixed", seed=11, duration_s=40.0)
    for k in ("accel", "gyro", "mag", "truth", "truth_position"):
        for x, y in zip(getattr(a, k), getattr(b, k), strict=True):
            np.testing.assert_array_equal(x, y)
    c = simulate("mixed", seed=12, duration_s=40.0)
    assert not np.array_equal(a.truth[1], c.truth[1])
    d = simulate("mixed", seed=11, duration_s=40.0, effects={"noise": None, "bias_drift": 1.0})
    np.testing.assert_array_equal(a.accel[1], d.accel[1])
    np.testing.assert_array_equal(a.mag[0], d.mag[0])
    np.testing.assert_array_equal(a.truth[1], d.truth[1])


def test_phone_realities_rates_jitter_drops_quantisation():
    res = simulate("walk", seed=13, duration_s=600.0)
    ph = res.phone
    for (t, v), rate, step in (
        (res.accel, ph.accel_rate_hz, ph.accel_step),
        (res.gyro, ph.gyro_rate_hz, ph.gyro_step),
        (res.mag, ph.mag_rate_hz, ph.mag_step),
    ):
        dt = np.diff(t)
        assert np.all(dt > 0)
        assert np.median(dt) == pytest.approx(1.0 / rate, rel=0.01)
        assert dt.std() > 0.0  # jittered
        assert np.sum(dt > 1.5 / rate) > 10  # dropped samples and gaps
        np.testing.assert_allclose(v / step, np.round(v / step), atol=1e-6)
    rates = [len(s[0]) / res.duration_s for s in (res.accel, res.gyro)]
    assert rates[0] != rates[1]  # independent clocks


def test_saturation_at_the_range():
    res = simulate("figure8", seed=14, duration_s=30.0, phone=PhoneSpec(gyro_range=1.0))
    g = res.gyro[1]
    assert np.abs(g).max() == pytest.approx(1.0, abs=res.phone.gyro_step)
    assert np.mean(np.abs(g) >= 1.0 - res.phone.gyro_step) > 0.01


@pytest.mark.parametrize("scenario", WALKING)
def test_walking_has_steps_at_1_6_to_2_hz(scenario):
    res = simulate(scenario, seed=15, duration_s=60.0, phone=PhoneSpec.ideal())
    t = np.arange(5.0, 55.0, 0.01)
    a = res.trajectory.accel_w(t)
    spec = np.abs(np.fft.rfft(a[:, 2] - a[:, 2].mean()))
    f = np.fft.rfftfreq(len(t), 0.01)
    f_step = f[int(np.argmax(spec))]
    assert 1.55 <= f_step <= 2.05
    assert 1.0 < a[:, 2].std() < 9.0  # vertical acceleration of a few m/s² (the swinging hand: more)
    speed = np.linalg.norm(np.diff(res.trajectory.walker_position(t), axis=0), axis=1).sum() / 50.0
    assert 0.9 < speed < 1.6


def test_figure8_covers_the_orientation_sphere():
    res = simulate("figure8", seed=16)
    t, raw = res.mag
    h = correct_mag(res.model, t, raw)
    u = h / np.linalg.norm(h, axis=1, keepdims=True)
    # 40 near-uniform cells (Fibonacci sphere): share of cells the field direction visits
    k = np.arange(40) + 0.5
    z = 1 - 2 * k / 40
    phi = np.pi * (1 + 5**0.5) * k
    cells = np.column_stack([np.sqrt(1 - z**2) * np.cos(phi), np.sqrt(1 - z**2) * np.sin(phi), z])
    visited = np.unique(np.argmax(u @ cells.T, axis=1))
    assert len(visited) / 40 > 0.85


def test_sim_model_is_a_sensor_model_with_known_effects():
    res = simulate("chain", seed=17, duration_s=60.0)
    assert isinstance(res.model, SensorModel)
    assert set(res.model.active) <= set(EFFECTS)
    assert [s["mode"] for s in res.meta["simulation"]["segments"]] == [
        "figure8",
        "texting",
        "figure8",
        "texting",
    ]
    assert res.meta["simulation"]["north"] == "true"


@pytest.mark.parametrize(("scenario", "peak"), [("walk", 20.0), ("still", 12.0), ("figure8", 15.0)])
def test_local_anomaly_in_any_scenario_reaches_its_peak(scenario, peak):
    res = simulate(
        scenario, seed=18, duration_s=45.0, effects={"local_anomaly": peak}, phone=PhoneSpec.ideal()
    )
    dip = res.model.value("local_anomaly")
    t = np.arange(0.0, 45.0, 0.05)
    b = np.linalg.norm(dip.field_w(res.trajectory.position(t)), axis=1)
    assert b.max() == pytest.approx(peak, rel=1e-9)
    assert res.meta["simulation"]["anomaly_windows"]
    if scenario == "walk":  # laid out along the middle third of the walk
        assert b[t < 8.0].max() < 1.0


# ------------------------------------------------------------------------------------------ hard cases
@pytest.mark.parametrize(("scenario", "seed"), [("run", 21), ("run_pocket", 22)])
def test_running_clips_a_2g_accelerometer_where_the_specific_force_exceeds_it(scenario, seed):
    """The iPhone 4S accelerometer saturates at ±2 g: a sample is clipped exactly where the true specific
    force (gravity + the trajectory's acceleration, noise-free) is beyond the range on an axis — except
    within a few noise σ of the limit — and running does that often (tyrex: 23–27 % of the samples of
    running in hand have an axis at the limit)."""
    res = simulate(scenario, seed=seed, duration_s=40.0, phone="iphone4s")
    ph = res.phone
    t, a = res.accel
    q = res.trajectory.orientation(t)
    f = quat_rotate(q, res.trajectory.accel_w(t) + [0.0, 0.0, GRAVITY], inverse=True)
    assert np.abs(a).max() <= ph.accel_range + 0.5 * ph.accel_step  # clipped, then rounded to the step
    clipped = np.abs(a) >= ph.accel_range - 0.5 * ph.accel_step
    beyond = np.abs(f) > ph.accel_range
    near = np.abs(np.abs(f) - ph.accel_range) < 5.0 * ph.accel_noise + ph.accel_step
    assert np.all((clipped == beyond) | near)
    share = np.mean(np.any(clipped, axis=1)[t > 5.0])
    assert share == pytest.approx(np.mean(np.any(beyond, axis=1)[t > 5.0]), abs=np.mean(np.any(near, axis=1)))
    assert 0.10 < share < 0.50
    assert np.abs(res.gyro[1]).max() < ph.gyro_range  # the gyroscope's ±2000 °/s is not reached


def test_running_has_steps_at_2_5_to_3_hz_and_peaks_beyond_2g():
    res = simulate("run", seed=23, duration_s=60.0, phone=PhoneSpec.ideal())
    t = np.arange(5.0, 55.0, 0.01)
    a = res.trajectory.accel_w(t)
    spec = np.abs(np.fft.rfft(a[:, 2] - a[:, 2].mean()))
    f_step = np.fft.rfftfreq(len(t), 0.01)[int(np.argmax(spec))]
    assert 2.45 <= f_step <= 3.05
    # the vertical specific force of the trunk averages g over a step and peaks at π g / (2 D) = 2.2–2.9 g
    assert np.mean(a[:, 2]) == pytest.approx(0.0, abs=0.1)
    sf = np.linalg.norm(a + [0.0, 0.0, GRAVITY], axis=1)
    assert np.percentile(sf, 99) > 2.2 * GRAVITY
    speed = np.linalg.norm(np.diff(res.trajectory.walker_position(t), axis=0), axis=1).sum() / 50.0
    assert 2.3 < speed < 3.9


@pytest.mark.parametrize("seed", [24, 25])
def test_steel_hides_the_field_for_a_minute_where_it_was_put(seed):
    """``steel``: 30–90 s of 120 s along magnetised shelving — the anomaly at the phone exceeds the Earth's
    horizontal field (the heading reference) nearly all along the window, and is gone 5 s outside it."""
    res = simulate("steel", seed=seed)
    sim = res.meta["simulation"]
    assert [(w["t0"], w["t1"]) for w in sim["steel_windows"]] == [(30.0, 90.0)]
    t = res.mag[0]
    b = np.linalg.norm(res.model.value("local_anomaly").field_w(res.trajectory.position(t)), axis=1)
    b_h = np.hypot(*res.field.field_w[:2])
    inside = (t >= 30.0) & (t <= 90.0)
    assert np.mean(b[inside] > b_h) > 0.75 and np.median(b[inside]) > 1.5 * b_h
    assert np.all(b[(t < 25.0) | (t > 95.0)] < 1.5)
    hidden = t[b > b_h]
    assert 28.0 < hidden.min() < 32.0 and 88.0 < hidden.max() < 92.0
    (w,) = sim["anomaly_windows"]  # one window, where the steel is (the 1-µT edge a few seconds wider)
    assert 24.0 < w["t0"] < 30.0 and 90.0 < w["t1"] < 96.0


def test_named_phone_has_its_hardware_and_its_large_hard_iron():
    """``phone="iphone4s"``: its rates and ±2 g range, and a 593-µT hard iron that the raw field is centred
    on (|raw| ≈ 600 µT for a 48-µT field); an ``effects`` value still overrides the phone's own."""
    res = simulate("figure8", seed=26, duration_s=30.0, phone="iphone4s")
    assert res.phone.accel_range == pytest.approx(2.0 * GRAVITY)
    assert (res.phone.accel_rate_hz, res.phone.gyro_rate_hz, res.phone.mag_rate_hz) == (90.0, 108.0, 38.0)
    b = res.model.value("hard_iron")
    assert np.linalg.norm(b) == pytest.approx(593.1, abs=0.1)
    t, m = res.mag
    h = correct_mag(res.model, t, m)
    np.testing.assert_allclose(np.linalg.norm(h, axis=1), res.field.strength, atol=2.0)  # 0.4 µT noise
    assert np.linalg.norm(m.mean(axis=0) - b) < res.field.strength
    assert res.meta["simulation"]["phone_name"] == "iphone4s"
    other = simulate("figure8", seed=26, duration_s=30.0, phone="iphone4s", effects={"hard_iron": 600.0})
    np.testing.assert_array_equal(other.model.value("hard_iron"), [600.0, 600.0, 600.0])
    with pytest.raises(ValueError, match="phone"):
        simulate("figure8", phone="nokia3310")
