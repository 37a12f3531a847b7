"""FusionCore: synthetic walks with known truth (the simulator), bias estimation, chunking, state, north,
magnetometer rejection, and the real tyrex walks with motion-capture truth (mode a)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pdr_mag._records import settings_record
from pdr_mag.estimates import EstimateBatch
from pdr_mag.field import EarthField
from pdr_mag.fusion import FusionCore
from pdr_mag.fusion.settings import AccelSettings, FusionSettings, GyroSettings, MagSettings
from pdr_mag.sim import simulate

DEG = np.pi / 180.0


# ------------------------------------------------------------------------------------------ helpers
def merge(res, mag=None):
    """Merged (kind, t, xyz) of a SimResult; ``mag`` replaces the magnetometer values."""
    (ta, a), (tg, g), (tm, m) = res.accel, res.gyro, res.mag
    m = m if mag is None else mag
    kind = np.concatenate([np.zeros(len(ta)), np.ones(len(tg)), np.full(len(tm), 2)]).astype(np.int8)
    t = np.concatenate([ta, tg, tm])
    xyz = np.concatenate([a, g, m])
    o = np.argsort(t, kind="stable")
    return kind[o], t[o], xyz[o]


def turned_about_up(res, angle):
    """A SimResult's magnetometer with its field turned about the world's up by ``angle`` (rad, one per
    magnetometer sample; strength and dip kept, so the detectors pass it): the turned field (N × 3, device
    frame) and the true attitudes at the magnetometer's times (a scipy ``Rotation``, device → world), with
    which a caller adds a world-frame disturbance."""
    from scipy.spatial.transform import Rotation

    from pdr_mag.conventions import quat_slerp

    tm, m = res.mag
    tt, qt = res.truth
    rt = Rotation.from_quat(quat_slerp(tt, qt, np.clip(tm, tt[0], tt[-1]))[:, [1, 2, 3, 0]])
    z = np.zeros_like(angle)
    turn = Rotation.from_rotvec(np.column_stack([z, z, angle]))
    return (rt.inv() * turn * rt).apply(m), rt


def twist_error_deg(batch, truth):
    """Signed heading error (twist about up of q_est q_true⁻¹, as the tyrex scorer), truth at output times."""
    tt, qt = truth
    qt = qt * np.where(qt[:, :1] < 0, -1.0, 1.0)
    from scipy.spatial.transform import Rotation, Slerp

    sl = Slerp(tt, Rotation.from_quat(qt[:, [1, 2, 3, 0]]))
    ok = (batch.t >= tt[0]) & (batch.t <= tt[-1])
    rt = sl(batch.t[ok])
    re = Rotation.from_quat(batch.q_wd[ok][:, [1, 2, 3, 0]])
    e = (re * rt.inv()).as_quat()  # x y z w
    h = np.degrees(2 * np.arctan2(e[:, 2], e[:, 3]))
    return batch.t[ok], (h + 180.0) % 360.0 - 180.0, batch.heading_std_deg[ok]


@pytest.fixture(scope="module")
def walk():
    # calibrated magnetometer (no hard / soft iron), raw gyro offsets like a real phone: 4 °/s on z
    return simulate(
        "walk", seed=11, effects={"hard_iron": None, "soft_iron": None, "gyro_bias": (0.02, -0.03, 0.07)}
    )


@pytest.fixture(scope="module")
def walk_run(walk):
    core = FusionCore(field=walk.field)
    return core, core.process(*merge(walk))


# ------------------------------------------------------------------------------------------ accuracy
def _big_offset_walk(seed, phone=None):
    return simulate(
        "walk",
        seed=seed,
        effects={"hard_iron": None, "soft_iron": None, "gyro_bias": (0.02, -0.03, 0.07)},
        phone=phone,
    )


def test_walk_heading_error_within_the_magnetometer_noise(walk, walk_run):
    """One magnetometer sample gives the heading to σ₁ = σ_m / B_h (≈ 1.1°).  The filtered heading also
    carries the tilt error of a walking hand through the dip (× tan I ≈ 2): a tilt error of ~0.5–1° over tens
    of seconds (the mean horizontal acceleration left in the averaged specific force) gives 1–2° of heading
    on single walks.  Bound: mean over three walks < 2 σ₁, each < 3 σ₁."""
    b_h = walk.field.strength * np.cos(np.radians(walk.field.inclination_deg))
    sigma_one = np.degrees(walk.model.effects["noise"][0] / b_h)
    means = []
    for seed, res in ((11, walk), (12, None), (13, None)):
        if res is None:
            res = _big_offset_walk(seed)
            b = FusionCore(field=res.field).process(*merge(res))
        else:
            b = walk_run[1]
        t, err, std = twist_error_deg(b, res.truth)
        late = t > t[0] + 20.0  # after the bias has converged
        means.append(np.mean(np.abs(err[late])))
        assert means[-1] < 3.0 * sigma_one
        # and its reported uncertainty covers the error (|e| < 2σ nearly always)
        assert np.mean(np.abs(err[late]) < 2.0 * std[late]) > 0.95
        assert np.all(np.abs(err[late]) < 4.0 * std[late])
    assert np.mean(means) < 2.0 * sigma_one


@pytest.mark.parametrize("scenario", ["walk", "mixed"])
def test_simulated_walk_with_ideal_calibration(scenario):
    """The scenario's default phone (hard / soft iron, gyro offset (0.6, −0.8, 0.5) °/s, 0.4 µT noise, gaps
    and drops; ``mixed``: a figure-8 then a walk through a 30-µT steel area), 60 s, magnetometer calibrated
    with the phone's exact calibration — what is left is the fusion's own error.

    Derivation of the bounds.  Tilt: the accelerometer is averaged over ``acc_tau_s`` in the world frame;
    what is left of a walker's horizontal acceleration in that average (speed changes of ±0.1–0.2 m/s over a
    step, turns) is ≈ 0.1–0.3 m/s², i.e. 0.5–1.5° on single windows, less after the filter's averaging:
    mean tilt error < 1.5°.  Heading: a perfect-tilt compass has σ₁ = σ_m / B_h ≈ 1.1° per sample; the
    heading-only magnetometer update adds the tilt error about north × tan I (≈ 2 at I = 63.5°), so the mean
    |heading error| < σ₁ + tan I · (the measured mean tilt error) per walk, and < 2 σ₁ over the seeds."""
    from pdr_mag.sim.sensor_model import SensorModel

    heads, tilts = [], []
    for seed in (1, 2, 3):
        res = simulate(scenario, seed=seed, duration_s=60.0)
        eff = {k: v for k, v in res.model.effects.items() if k in ("hard_iron", "soft_iron")}
        cal = SensorModel(effects=eff).ideal_calibration(0.0)
        b = FusionCore(field=res.field).process(*merge(res, mag=cal.apply(res.mag[1])))
        t, err, std = twist_error_deg(b, res.truth)
        from scipy.spatial.transform import Rotation, Slerp

        tt, qt = res.truth
        rt = Slerp(tt, Rotation.from_quat(qt[:, [1, 2, 3, 0]]))(t)
        ok = (b.t >= tt[0]) & (b.t <= tt[-1])
        re = Rotation.from_quat(b.q_wd[ok][:, [1, 2, 3, 0]])
        up_e, up_t = re.inv().apply([0, 0, 1.0]), rt.inv().apply([0, 0, 1.0])
        tilt = np.degrees(np.arccos(np.clip(np.sum(up_e * up_t, axis=1), -1.0, 1.0)))
        s = t > 5.0
        b_h = res.field.strength * np.cos(np.radians(res.field.inclination_deg))
        sigma_one = np.degrees(res.model.effects["noise"][0] / b_h)
        tan_i = np.tan(np.radians(res.field.inclination_deg))
        heads.append(np.mean(np.abs(err[s])))
        tilts.append(np.mean(tilt[s]))
        assert tilts[-1] < 1.5
        assert heads[-1] < sigma_one + tan_i * tilts[-1]
        assert np.mean(np.abs(err[s]) < 2.0 * std[s]) > 0.95  # the reported std covers the error
    assert np.mean(heads) < 2.0 * sigma_one


def test_raw_gyro_offset_is_estimated(walk, walk_run):
    core, _ = walk_run
    true_bias = np.array([0.02, -0.03, 0.07])
    # walking with turns makes all three axes observable; 0.2 °/s is 1/20 of the offset
    assert np.all(np.abs(core.bias - true_bias) < 0.2 * DEG)


def test_still_device_zero_rate_update():
    res = simulate(
        "still",
        seed=2,
        duration_s=30.0,
        effects={"hard_iron": None, "soft_iron": None, "gyro_bias": (0.09, -0.05, 0.07)},
    )
    core = FusionCore(field=res.field)
    core.process(*merge(res))
    # zero-rate updates average the gyro noise (σ 0.0015 rad/s per sample) over ~25 s
    assert np.all(np.abs(core.bias - np.array([0.09, -0.05, 0.07])) < 0.02 * DEG)


def test_output_rate_and_columns(walk, walk_run):
    _, b = walk_run
    dt = np.diff(b.t)
    rate = FusionSettings().output_rate_hz
    assert np.median(dt) == pytest.approx(1.0 / rate, rel=0.15)
    assert b.q_wd.shape == (len(b), 4)
    np.testing.assert_allclose(np.linalg.norm(b.q_wd, axis=1), 1.0, atol=1e-9)
    assert np.all((b.heading_deg >= 0) & (b.heading_deg < 360))
    assert set(b.diag) >= {"gyro_heading_deg", "field_strength_uT", "interference_score", "gyro_bias_z"}
    assert np.all(b.cal_state == "none")


# ------------------------------------------------------------------------------------------ streaming
def test_chunking_gives_identical_results(walk):
    kind, t, xyz = merge(walk)
    whole = FusionCore(field=walk.field).process(kind, t, xyz)
    rng = np.random.default_rng(0)
    cuts = np.sort(rng.choice(np.arange(1, len(t)), size=40, replace=False))
    core = FusionCore(field=walk.field)
    parts = [
        core.process(kind[a:b], t[a:b], xyz[a:b])
        for a, b in zip(np.r_[0, cuts], np.r_[cuts, len(t)], strict=True)
    ]
    chunked = EstimateBatch.concat(parts)
    assert np.array_equal(whole.t, chunked.t)
    assert np.array_equal(whole.q_wd, chunked.q_wd)
    assert np.array_equal(whole.heading_std_deg, chunked.heading_std_deg)
    assert np.array_equal(whole.mag_used, chunked.mag_used)
    assert np.array_equal(whole.interference, chunked.interference)


def _same_batches(a, b):
    for name in ("t", "q_wd", "heading_deg", "heading_std_deg", "mag_used", "interference"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert set(a.diag) == set(b.diag)
    for name in a.diag:
        assert np.array_equal(a.diag[name], b.diag[name], equal_nan=True), name


def test_state_round_trip_through_json(walk):
    """Resuming from a JSON state gives the rows of an uninterrupted run, bit for bit (every column and
    diagnostic); any float survives the JSON, infinities included; a broken state names its field."""
    kind, t, xyz = merge(walk)
    whole = FusionCore(field=walk.field)
    whole.set_reference_strength(47.5)
    whole = whole.process(kind, t, xyz)
    half = len(t) // 2
    first = FusionCore(field=walk.field)
    first.set_reference_strength(47.5)
    a = first.process(kind[:half], t[:half], xyz[:half])
    saved = json.loads(json.dumps(first.get_state()))
    assert saved["state"]["init"] == 2 and saved["reference_strength_uT"] == 47.5
    second = FusionCore(field=walk.field)
    second.set_state(saved)
    assert second.get_state() == saved
    b = second.process(kind[half:], t[half:], xyz[half:])
    _same_batches(whole, EstimateBatch.concat([a, b]))

    probe = FusionCore(field=walk.field)
    probe._st["det"]["since"] = np.inf
    js = json.loads(json.dumps(probe.get_state()))
    assert js["state"]["det"]["since"] == "inf"
    second.set_state(js)
    assert second.get_state() == js
    with pytest.raises(ValueError, match="version"):
        second.set_state({"version": 999})
    broken = json.loads(json.dumps(saved))
    del broken["state"]["det"]["strength"]["loc"]
    with pytest.raises(ValueError, match=r"det\.strength\.loc"):
        second.set_state(broken)
    broken = json.loads(json.dumps(saved))
    broken["state"]["P"] = broken["state"]["P"][:3]
    with pytest.raises(ValueError, match=r"P: expected shape \(10, 10\)"):
        second.set_state(broken)


def test_the_kernel_writes_every_output_column(walk):
    """Every column of :mod:`pdr_mag.fusion.rows` is written for every row the kernel reports (a sentinel
    put there before the run is gone), and the rows' diagnostics are exactly DIAG_NAMES."""
    from pdr_mag.fusion import Span, kernel
    from pdr_mag.fusion.rows import DIAG_NAMES, FLAG_COLUMNS, FLOAT_COLUMNS, columns, new_rows
    from pdr_mag.fusion.state import STATE

    kind, t, xyz = merge(walk)
    core = FusionCore(field=walk.field)
    out = new_rows(len(t))
    out.floats[:] = -12345.0
    out.q[:] = -12345.0
    out.flags[:] = True
    span = Span(kind, t, xyz, np.ones(len(t), dtype=np.bool_), len(t))
    k = kernel.run_cut(span, core._st, core._p, np.empty(0, dtype=np.intp), np.empty(0, STATE), out)
    assert k > 100
    col = columns(out, k)
    for name in (*FLOAT_COLUMNS, "q"):
        assert not np.any(col[name] == -12345.0), name
    for name in FLAG_COLUMNS:
        assert not np.all(col[name]), name  # some rows without a correction or a flag
    assert set(core.process(kind, t, xyz).diag) == set(DIAG_NAMES)


def test_every_setting_reaches_the_kernel():
    """Each setting of each FusionSettings group fills one field of the group's nested PARAMS record
    (``*_deg`` in rad, the rate as a period) and each PARAMS field comes from one setting."""
    from dataclasses import fields, is_dataclass

    from pdr_mag.fusion.state import PARAMS

    def kernel_names(cls, dtype):
        names = set()
        for f in fields(cls):
            name = f.metadata["kernel"][0] if "kernel" in f.metadata else f.name
            kind = getattr(cls(), f.name)
            if is_dataclass(kind):
                kernel_names(type(kind), dtype[name])
            names.add(name)
        assert names == set(dtype.names), cls.__name__

    kernel_names(FusionSettings, PARAMS)
    s = FusionSettings(mag=MagSettings(noise_deg=3.0), gyro=GyroSettings(max_dt=0.7), output_rate_hz=20.0)
    p = settings_record(s)[0]
    assert p["mag"]["noise_rad"] == np.radians(3.0) and p["out_dt_s"] == 1.0 / 20.0
    assert p["gyro"]["max_dt"] == 0.7 and p["accel"]["gravity"] == 9.80665


# ------------------------------------------------------------------------------------------ north
def test_declination_gives_true_north(walk):
    kind, t, xyz = merge(walk)
    true_n = FusionCore(field=walk.field).process(kind, t, xyz)
    mag_core = FusionCore(field=None)
    mag_core.set_reference_strength(walk.field.strength)
    assert mag_core.north == "magnetic"
    mag_n = mag_core.process(kind, t, xyz)
    d = (true_n.heading_deg - mag_n.heading_deg + 180.0) % 360.0 - 180.0
    late = true_n.t > true_n.t[0] + 20.0
    # magnetic north lies D east of true north: a true heading is D larger than a magnetic one
    assert np.median(d[late]) == pytest.approx(walk.field.declination_deg, abs=0.3)


# ------------------------------------------------------------------------------------------ rejection
def test_rejected_magnetometer_heading_runs_on_gyro_and_std_grows(walk):
    kind, t, xyz = merge(walk)
    allowed = ~((kind == 2) & (t > 60.0))
    b = FusionCore(field=walk.field).process(kind, t, xyz, allowed)
    after = b.t > 61.0
    assert not b.mag_used[after].any()
    assert b.mag_used[(b.t > 20.0) & (b.t < 60.0)].any()
    std = b.heading_std_deg[after]
    assert np.all(np.diff(std) >= -1e-9) and std[-1] > std[0] + 0.05
    _, err, sd = twist_error_deg(b, walk.truth)
    tt = b.t[(b.t >= walk.truth[0][0]) & (b.t <= walk.truth[0][-1])]
    late = tt > 61.0
    assert np.all(np.abs(err[late]) < 3.0 * sd[late] + 0.5)


def test_nan_magnetometer_rows_are_skipped(walk):
    kind, t, xyz = merge(walk)
    xyz = xyz.copy()
    xyz[kind == 2] = np.nan  # no usable calibration yet
    b = FusionCore(field=walk.field).process(kind, t, xyz)
    assert len(b) > 0 and not b.mag_used.any() and not b.interference.any()
    assert np.all((b.heading_std_deg > 170.0) & (b.heading_std_deg <= 180.0 + 1e-9))  # heading unknown


def test_settings_validation():
    with pytest.raises(ValueError, match=r"GyroSettings\.noise"):
        GyroSettings(noise=-1.0)
    with pytest.raises(ValueError, match="kind"):
        FusionCore().process(np.zeros(3, np.int8), np.zeros(3), np.zeros((3, 2)))
    with pytest.raises(ValueError, match="strength_uT"):
        FusionCore().set_reference_strength(-3.0)
    assert FusionCore(field=EarthField.from_vector([0.0, 20.0, -40.0])).north == "true"


# ------------------------------------------------------------------------------------------ real walks
# (their accuracy: tests/test_real_walks.py, each walk bounded by the peers on the same walk)


def error_at_truth(batch, tt, qt):
    """Signed heading error at the truth times, the estimate slerp-interpolated (the tyrex metric)."""
    from scipy.spatial.transform import Rotation, Slerp

    q = batch.q_wd
    sl = Slerp(batch.t, Rotation.from_quat(q[:, [1, 2, 3, 0]]))
    ok = (tt >= batch.t[0]) & (tt <= batch.t[-1])
    re = sl(tt[ok])
    rt = Rotation.from_quat(qt[ok][:, [1, 2, 3, 0]])
    e = (re * rt.inv()).as_quat()
    h = np.degrees(2 * np.arctan2(e[:, 2], e[:, 3]))
    return (h + 180.0) % 360.0 - 180.0


@pytest.mark.parametrize("rates", [(100.0, 50.0), (200.0, 100.0), (400.0, 100.0)])
def test_other_phones_sample_rates(rates):
    """The noise model is per second, not per sample: the same walk at other IMU / magnetometer rates."""
    from pdr_mag.sim.sensor_model import PhoneSpec

    imu, mag = rates
    res = _big_offset_walk(11, PhoneSpec(accel_rate_hz=imu, gyro_rate_hz=imu, mag_rate_hz=mag))
    core = FusionCore(field=res.field)
    t, err, std = twist_error_deg(core.process(*merge(res)), res.truth)
    late = t > t[0] + 20.0
    b_h = res.field.strength * np.cos(np.radians(res.field.inclination_deg))
    # single-walk bound of test_walk_heading_error_within_the_magnetometer_noise
    assert np.mean(np.abs(err[late])) < 3.0 * np.degrees(res.model.effects["noise"][0] / b_h)
    assert np.mean(np.abs(err[late]) < 2.0 * std[late]) > 0.95
    assert np.all(np.abs(core.bias - np.array([0.02, -0.03, 0.07])) < 0.2 * DEG)


# ------------------------------------------------------------------------------------------ honesty, guards
def _coverage_cases():
    """(|heading error|, reported std) over t > 5 s of simulated walks with the exact magnetometer
    calibration (the cases of benchmarks/heading_sim.py, 60 s each), and the total scored duration."""
    from pdr_mag.sim.sensor_model import SensorModel

    errs, stds, dur = [], [], 0.0
    for scenario in ("walk", "swing", "pocket"):
        for seed in (1, 2):
            res = simulate(scenario, seed=seed, duration_s=60.0)
            eff = {k: v for k, v in res.model.effects.items() if k in ("hard_iron", "soft_iron")}
            cal = SensorModel(effects=eff).ideal_calibration(0.0)
            b = FusionCore(field=res.field).process(*merge(res, mag=cal.apply(res.mag[1])))
            t, err, std = twist_error_deg(b, res.truth)
            s = t > 5.0
            errs.append(np.abs(err[s]))
            stds.append(std[s])
            dur += float(t[s][-1] - t[s][0])
    return np.concatenate(errs), np.concatenate(stds), dur


def _coverage_band(p: float, duration_s: float) -> float:
    """Three binomial standard deviations of a coverage fraction p measured on ``duration_s`` of output whose
    heading errors are correlated over ``mag_error_tau_s`` (the magnetometer error's correlation time): about
    one independent sample per correlation time."""
    n_eff = duration_s / FusionSettings().mag.error_tau_s
    return 3.0 * np.sqrt(p * (1.0 - p) / n_eff)


def test_heading_std_is_not_overconfident_on_simulated_walks():
    """The truth must lie within 1σ / 2σ of ``heading_std_deg`` at least as often as a Gaussian says (68 % /
    95 %), within the band of :func:`_coverage_band` (≈ 70 independent samples: ±17 % / ±8 %)."""
    err, std, dur = _coverage_cases()
    assert np.mean(err < std) > 0.68 - _coverage_band(0.68, dur)
    assert np.mean(err < 2.0 * std) > 0.95 - _coverage_band(0.95, dur)


@pytest.mark.xfail(
    strict=True,
    reason="known limitation (see RESULTS): on clean simulated fields the std is"
    " conservative (truth within 1σ in ~100 %);"
    " two floors: the magnetometer error state c (σ_c 6°, sized for indoor fields: the heading std here is"
    " 6.4° median, 4.8–9.9° p10–p90, against errors of 1.2° median) and, once c is scaled to the observed"
    " field"
    " (σ_c → 1.4°), the tilt variance (≈ 1.1° per axis) × tan I through the consider-tilt term (std ≈ 2°);"
    " scaling either cost accuracy on the real or simulated walks (benchmarks/RESULTS.md)",
)
def test_heading_std_is_not_too_loose_on_simulated_walks():
    err, std, dur = _coverage_cases()
    assert np.mean(err < std) < 0.68 + _coverage_band(0.68, dur)


def test_unflagged_field_rotation_at_the_start_does_not_become_gyro_bias(walk):
    """The field turns about up by A and back within T, starting 1 s after the first magnetometer sample:
    strength and dip unchanged (only the gyro-consistency check can see it) and slower than its flag
    threshold, so nothing is flagged — the FrontPocket situation of the online mode.  Read entirely as drift,
    the ramp (A over T/2) is a rate 2A/T along up; the bias may take at most half of it (|δb| < A/T) at the
    end of the anomaly, and must converge afterwards as on the undisturbed walk (0.2 °/s, see
    test_raw_gyro_offset_is_estimated).  Measured: |δb| 2.0 / 4.3 °/s for (A, T) = (20°, 4 s) / (30°, 6 s)."""
    tm = walk.mag[0]
    true_bias = np.array([0.02, -0.03, 0.07])
    for amp_deg, dur in ((20.0, 4.0), (30.0, 6.0)):
        t0 = tm[0] + 1.0
        a = np.radians(amp_deg) * np.sin(np.pi * np.clip((tm - t0) / dur, 0.0, 1.0)) ** 2
        kind, t, xyz = merge(walk, mag=turned_about_up(walk, a)[0])
        core = FusionCore(field=walk.field)
        during = t <= t0 + dur
        b = core.process(kind[during], t[during], xyz[during])
        assert not b.interference.any()  # the anomaly is not flagged: the test is about the weighting
        db = np.linalg.norm(core.bias - true_bias)
        assert db < np.radians(amp_deg) / dur
        core.process(kind[~during], t[~during], xyz[~during])
        assert np.all(np.abs(core.bias - true_bias) < 0.2 * DEG)


# ------------------------------------------------------------------------------------------ robustness
def test_tilt_waits_for_the_gyroscope():
    """A phone whose gyroscope starts 1 s after its accelerometer while the device turns (a real iPhone 4S
    running walk: 0.7 s; a tilt set from the first accelerometer sample went stale by ~55° there and the
    first tilt updates taught the bias −30 °/s).  The tilt starts with the gyroscope: on a figure-8 the first
    rows' tilt is within the accelerometer's single-sample error of a turning hand (< 5°); set from the
    first accelerometer sample it is 10–22° off on these seeds."""
    from scipy.spatial.transform import Rotation

    from pdr_mag.conventions import quat_slerp

    for seed in (1, 2, 3):
        res = simulate("figure8", seed=seed, effects={"hard_iron": None, "soft_iron": None}, duration_s=20)
        kind, t, xyz = merge(res)
        keep = ~((kind == 1) & (t < t[0] + 1.0))
        b = FusionCore(field=res.field).process(kind[keep], t[keep], xyz[keep])
        first = slice(0, 5)
        q_est = Rotation.from_quat(b.q_wd[first][:, [1, 2, 3, 0]])
        q_true = Rotation.from_quat(quat_slerp(*res.truth, b.t[first])[:, [1, 2, 3, 0]])
        up_est, up_true = q_est.inv().apply([0.0, 0.0, 1.0]), q_true.inv().apply([0.0, 0.0, 1.0])
        tilt = np.degrees(np.arccos(np.clip(np.sum(up_est * up_true, axis=1), -1.0, 1.0)))
        assert b.t[0] >= t[0] + 1.0
        assert np.all(tilt < 5.0)


@pytest.mark.parametrize("scenario", ["still", "walk", "run"])
def test_a_tilt_started_upside_down_is_reset_not_learnt_as_bias(scenario):
    """The first accelerometer sample is a jolt pointing down (a swinging, clipping arm gave 150° on a real
    Nexus 5 started mid-run): the tilt starts upside down.  A linearised update cannot correct that, and its
    corrections taught the gyro bias 30–56 °/s here.  Far off, the averages correct the tilt only (the bias
    a consider state) and the 3-s average turns the attitude: from 4 to 10 s the tilt is within 10°
    (median), from 6 to 20 s too, and the bias ends within 1 °/s of the truth.  Without the reset the
    linearised updates alone take much longer on a still phone and a running one (> 15° from 4 to 10 s)."""
    from scipy.spatial.transform import Rotation

    from pdr_mag.conventions import quat_slerp

    bias = np.array([0.02, -0.03, 0.07])
    res = simulate(scenario, seed=3, effects={"hard_iron": None, "soft_iron": None, "gyro_bias": tuple(bias)})
    kind, t, xyz = merge(res)
    xyz = xyz.copy()
    acc = np.where(kind == 0)[0]
    first = acc[acc > np.argmax(kind == 1)][0]  # the first accelerometer sample once the gyroscope streams
    xyz[first] = -xyz[first]

    def run(settings):
        core = FusionCore(settings, field=res.field)
        b = core.process(kind, t, xyz)
        q_est = Rotation.from_quat(b.q_wd[:, [1, 2, 3, 0]])
        q_true = Rotation.from_quat(quat_slerp(*res.truth, b.t)[:, [1, 2, 3, 0]])
        up_est, up_true = q_est.inv().apply([0.0, 0.0, 1.0]), q_true.inv().apply([0.0, 0.0, 1.0])
        tilt = np.degrees(np.arccos(np.clip(np.sum(up_est * up_true, axis=1), -1.0, 1.0)))
        dt = b.t - b.t[0]
        early = float(np.median(tilt[(dt > 4.0) & (dt < 10.0)]))
        late = float(np.median(tilt[(dt > 6.0) & (dt < 20.0)]))
        return early, late, np.degrees(np.abs(core._st[0]["b"] - bias)), int(core._st[0]["tilt_resets"])

    early, late, bias_err, resets = run(FusionSettings())
    assert resets >= 1
    assert early < 10.0 and late < 10.0
    assert np.all(bias_err < 1.0)
    if scenario in ("still", "run"):
        early_off, _, _, resets_off = run(FusionSettings(accel=AccelSettings(tilt_reset_k=0.0)))
        assert resets_off == 0 and early_off > 15.0


def test_lost_heading_is_reacquired_with_an_event(walk):
    """For the first 40 s the field is turned by 90° about up — strength and dip unchanged, so nothing can
    tell — and the filter takes that heading.  Then the true field returns: it is clean but fails the gate.
    After ``reacquire_s`` of such rejections the heading is re-acquired (one ``heading_reset``
    of about 90°, within 2 × reacquire_s), and then it is as accurate as the undisturbed walk (< 3°); without
    re-acquisition it is still tens of degrees off at that time."""
    from pdr_mag.fusion import heading_reset_events

    tm = walk.mag[0]
    a = np.where(tm < tm[0] + 40.0, np.radians(90.0), 0.0)
    kind, t, xyz = merge(walk, mag=turned_about_up(walk, a)[0])
    settings = FusionSettings()
    b = FusionCore(settings, field=walk.field).process(kind, t, xyz)
    events = heading_reset_events(b)
    assert len(events) == 1
    ev = events[0]
    assert tm[0] + 40.0 < ev.t < tm[0] + 40.0 + 2 * settings.mag.reacquire_s
    assert abs(abs(ev.data["jump_deg"]) - 90.0) < 10.0
    t_err, err, _ = twist_error_deg(b, walk.truth)
    after = t_err > ev.t + 5.0
    assert np.mean(np.abs(err[after])) < 3.0
    off = FusionCore(FusionSettings(mag=MagSettings(reacquire_s=0.0)), field=walk.field).process(kind, t, xyz)
    assert not heading_reset_events(off)
    _, err_off, _ = twist_error_deg(off, walk.truth)
    assert np.mean(np.abs(err_off[(t_err > ev.t) & (t_err < ev.t + 10.0)])) > 20.0


def test_reacquisition_follows_a_lost_heading_that_drifts():
    """The re-acquisition test on its own (``mag._rejected``, fed the innovations of clean fields that fail
    the gate, 5 Hz): a heading lost by 170° whose gyro bias is also off by 3 °/s gives innovations along a
    line — re-acquired after ``reacquire_s``, onto the line's value then (≈ 170 + 3 · 20 = 230°), though their
    circular spread about their mean (computed: 22.7° at 20 s) is beyond the 15° bound; the same innovations
    with the filter's bias known to 0.3 °/s about up cannot be its drift (a field that turns): no
    re-acquisition; a constant 170° with 3° of noise: re-acquired onto 170°."""
    from pdr_mag._records import settings_record
    from pdr_mag.fusion.mag import _rejected
    from pdr_mag.fusion.state import BIAS, C_ERR, NX, TH_Z, new_state

    settings = FusionSettings()
    p = settings_record(settings)[0]

    def run(slope_deg_s, bias_std_deg_s, seed=4):
        st = new_state()
        rec = st[0]
        rec["init"] = 2
        P = np.diag(np.full(NX, 1e-4))
        P[BIAS + 2, BIAS + 2] = np.radians(bias_std_deg_s) ** 2
        rec["P"] = P
        h = np.zeros(NX)
        h[TH_Z] = h[C_ERR] = 1.0
        noise = np.random.default_rng(seed).normal(0.0, np.radians(3.0), 200)
        for k in range(200):  # 40 s of rejections
            t = 0.2 * k
            r = np.radians(170.0 + slope_deg_s * t) + noise[k]
            r = (r + np.pi) % (2 * np.pi) - np.pi
            _rejected(rec, np.eye(3), h, r, 1e-4, t, p)
            if rec["reset_jump"] != 0.0:
                return t, np.degrees(rec["reset_jump"]) % 360.0
        return None, None

    t, jump = run(3.0, 1.5)
    assert t is not None and abs(t - settings.mag.reacquire_s) < 0.5
    assert abs(jump - (170.0 + 3.0 * t)) < 5.0
    assert run(3.0, 0.3) == (None, None)
    t, jump = run(0.0, 0.3)
    assert t is not None and abs(jump - 170.0) < 3.0


def test_reacquisition_waits_as_long_as_the_fields_behind_the_heading_span():
    """A run of clean fields that agree among themselves (a constant 170° off, 3° of noise, 5 Hz) against a
    heading whose accepted updates span T_s since it was set from the field: re-acquired once the run spans
    T_s, at least two of c's correlation times (10 s: the run's fields then carry errors of their own) and at
    most ``reacquire_s`` (20 s) — a first fix followed by 2 s of updates gives way after 10 s, one resting
    on 14 s of fields after 14 s, one resting on a minute of them (or on nothing known) after 20 s."""
    from pdr_mag._records import settings_record
    from pdr_mag.fusion.mag import _rejected
    from pdr_mag.fusion.state import BIAS, C_ERR, NX, TH_Z, new_state

    settings = FusionSettings()
    p = settings_record(settings)[0]
    tau_c = settings.mag.error_tau_s

    def run(t_set, t_update):
        st = new_state()
        rec = st[0]
        rec["init"] = 2
        rec["t_heading_set"] = t_set
        rec["t_mag_update"] = t_update
        P = np.diag(np.full(NX, 1e-4))
        P[BIAS + 2, BIAS + 2] = np.radians(0.3) ** 2
        rec["P"] = P
        h = np.zeros(NX)
        h[TH_Z] = h[C_ERR] = 1.0
        noise = np.random.default_rng(5).normal(0.0, np.radians(3.0), 200)
        for k in range(200):  # 40 s of rejections from t = 0
            t = 0.2 * k
            _rejected(rec, np.eye(3), h, np.radians(170.0) + noise[k], 1e-4, t, p)
            if rec["reset_jump"] != 0.0:
                return t, np.degrees(rec["reset_jump"]) % 360.0
        return None, None

    for (t_set, t_update), wait in (((-3.0, -1.0), 2.0 * tau_c), ((-15.0, -1.0), 14.0),
                                    ((-61.0, -1.0), settings.mag.reacquire_s),
                                    ((np.nan, np.nan), settings.mag.reacquire_s)):  # fmt: skip
        t, jump = run(t_set, t_update)
        assert t is not None and abs(t - wait) < 0.5, (t_set, t_update, t)
        assert abs(jump - 170.0) < 3.0


def test_accelerometer_range_is_found_in_the_data():
    """Running with a ±2-g accelerometer piles samples up at the range: the filter finds it (its peak within
    the band of 2 g, many hits) and counts clipped samples in the average; a texting walk, which never comes
    near a range, has no clipped share.  A range given in the settings is used as such."""
    run = simulate("run", seed=1, phone="iphone4s", effects={"hard_iron": None, "soft_iron": None})
    core = FusionCore(field=run.field)
    core.process(*merge(run))
    st = core._st[0]
    g2 = 2.0 * 9.80665
    assert abs(st["acc_peak"] - g2) <= 0.05 * g2 and st["acc_peak_hits"] >= 100
    walk = simulate("walk", seed=1, effects={"hard_iron": None, "soft_iron": None})
    core = FusionCore(field=walk.field)
    core.process(*merge(walk))
    assert core._st[0]["clip_share"] == 0.0 and core._st[0]["acc_peak"] < 1.5 * 9.80665
    given = FusionCore(FusionSettings(accel=AccelSettings(range=0.5 * 9.80665)), field=walk.field)
    given.process(*merge(walk))
    assert given._st[0]["clip_share"] > 0.5  # every sample of a walk is above half a g on some axis


def test_calibration_covariance_makes_the_std_honest():
    """A calibration whose offset is off by (6, −4, 3) µT with σ = 6 µT per axis (a coarse first online fit):
    the heading error it causes varies with the heading (9–10° mean here, B_h ≈ 21 µT).  Given the
    covariance, the std covers it — truth within 2σ in ≥ 95 % of the rows — where without it the filter
    claims ~6° and the truth is within 2σ in only 51–78 % of the rows on these seeds."""
    for seed in (11, 12, 13):
        effects = {"hard_iron": None, "soft_iron": None, "gyro_bias": (0.02, -0.03, 0.07)}
        w = simulate("walk", seed=seed, effects=effects)
        tm, m = w.mag
        core = FusionCore(field=w.field)
        core.set_calibration_covariance(np.diag([36.0, 36.0, 36.0]))
        b = core.process(*merge(w, mag=m + np.array([6.0, -4.0, 3.0])))
        _, err, sd = twist_error_deg(b, w.truth)
        assert np.mean(np.abs(err) <= 2.0 * sd) >= 0.95
    with pytest.raises(ValueError, match="cov_uT2"):
        FusionCore().set_calibration_covariance(np.eye(2))


def test_a_new_calibration_covariance_counts_before_the_next_field():
    """Without the offset states (``mag.offset_states`` False: the offset's error is c's noise, and the std is
    floored by it): a calibration known to 0.1 µT, then an uncertain one (σ 10 µT per axis: a recalibration's
    provisional offset) while no field comes (a flagged stretch): the std's floor takes the new covariance at
    once — 10 µT against the horizontal field turns the heading by up to ``10 / B_h`` rad — where it used to
    wait for the next usable field; and an exact calibration (None) takes the floor away again."""
    w = simulate("walk", seed=11, effects={"hard_iron": None, "soft_iron": None})
    kind, t, xyz = merge(w)
    core = FusionCore(FusionSettings(mag=MagSettings(offset_states=False)), field=w.field)
    core.set_calibration_covariance(np.eye(3) * 0.01)
    first = t < t[0] + 30.0
    before = core.process(kind[first], t[first], xyz[first]).heading_std_deg[-1]
    core.set_calibration_covariance(np.eye(3) * 100.0)
    no_field = ~first & (kind != 2) & (t < t[0] + 31.0)
    after = core.process(kind[no_field], t[no_field], xyz[no_field]).heading_std_deg
    b_h = w.field.strength * np.cos(np.radians(w.field.inclination_deg))
    assert before < 10.0
    # |g| = 1 / B_h, so g Σ gᵀ = 100 / B_h² at any orientation (the measured B_h within 20 % of the model's)
    assert np.all(after >= 0.8 * np.degrees(10.0 / b_h))
    core.set_calibration_covariance(None)
    assert np.all(core.process(kind[no_field], t[no_field] + 1.0, xyz[no_field]).heading_std_deg < 10.0)
