"""Prior knowledge of a device: the phone's own estimates from the metadata, their ageing in a device store,
and the choice between them (pdr_mag.calibration.prior, pdr_mag.calibration.store)."""

import json
import math

import numpy as np
import pytest

from pdr_mag.calibration.model import MagCalibration
from pdr_mag.calibration.prior import DAY_S, DevicePrior, PriorSettings, aged, choose, phone_prior
from pdr_mag.calibration.store import DeviceStore

META = {"device": "OPPO PBCM10"}


def _stored_cal(std=0.5):
    return MagCalibration.from_arrays([-57.0, -91.0, -302.0], field_uT=43.0, method="gravity",
                                      offset_std_uT=(std, std, std))  # fmt: skip


def test_phone_prior_from_the_os_bias_and_drift():
    s = PriorSettings()
    meta = {"mag_os_bias_uT": [-61.0, -17.7, -346.3], "gyro_os_bias_rad_s": [0.0018, 0.0022, 0.0009]}
    p = phone_prior(meta)
    assert p.source == "phone"
    assert p.calibration.offset == (-61.0, -17.7, -346.3)
    np.testing.assert_allclose(np.diag(p.calibration.offset_covariance), [s.phone_offset_std_uT**2] * 3)
    assert p.gyro_bias == (0.0018, 0.0022, 0.0009)
    assert p.gyro_bias_std == s.phone_gyro_bias_std


def test_phone_prior_of_os_calibrated_streams_is_a_zero_bias_with_its_sigma():
    p = phone_prior({"mag_os_calibrated": True, "gyro_os_calibrated": True})
    assert p.calibration.offset == (0.0, 0.0, 0.0)
    assert max(p.calibration.offset_std_uT) == PriorSettings().phone_offset_std_uT
    assert p.gyro_bias == (0.0, 0.0, 0.0)


def test_no_phone_prior_when_the_recording_states_nothing_or_it_is_switched_off():
    assert phone_prior({"mag_os_calibrated": False}) is None
    assert phone_prior({"mag_os_bias_uT": [1, 2, 3]}, PriorSettings(use_phone=False)) is None


def test_a_malformed_os_bias_names_its_key():
    with pytest.raises(ValueError, match="mag_os_bias_uT"):
        phone_prior({"mag_os_bias_uT": [1.0, "x", 3.0]})
    with pytest.raises(ValueError, match="gyro_os_bias_rad_s"):
        phone_prior({"gyro_os_bias_rad_s": [1.0, 2.0]})


def test_ageing_grows_the_offset_variance_by_the_drift_rate_and_adds_a_power_up_to_the_gyro():
    s = PriorSettings()
    p = DevicePrior(calibration=_stored_cal(0.5), gyro_bias=(0.01, 0.0, 0.07), gyro_bias_std=0.001,
                    source="store")
    a = aged(p, 2 * DAY_S, s)
    np.testing.assert_allclose(np.diag(a.calibration.offset_covariance),
                               0.25 + 2 * s.offset_drift_uT_per_sqrt_day**2, rtol=1e-12)  # fmt: skip
    assert a.calibration.offset == p.calibration.offset  # the estimate itself does not move
    assert a.gyro_bias_std == pytest.approx(math.hypot(0.001, s.gyro_turn_on_std), rel=1e-12)
    assert a.age_s == 2 * DAY_S


def test_a_zero_estimate_states_none():
    """Android's bias columns of exactly zero: an OS without an estimate — no prior from them (the raw field
    is not the Earth's); a stream the OS calibrated is still a zero offset."""
    assert phone_prior({"mag_os_bias_uT": [0.0, 0.0, 0.0], "gyro_os_bias_rad_s": [0.0, 0.0, 0.0]}) is None
    p = phone_prior({"mag_os_bias_uT": [0.0, 0.0, 0.0], "gyro_os_bias_rad_s": [0.001, 0.0, 0.0]})
    assert p.calibration is None and p.gyro_bias == (0.001, 0.0, 0.0)
    p = phone_prior({"mag_os_bias_uT": [0.0, 0.0, 0.0], "mag_os_calibrated": True})
    assert p.calibration.offset == (0.0, 0.0, 0.0)


def test_choose_takes_the_surer_part_from_each_source():
    phone = phone_prior({"mag_os_bias_uT": [0.5, -0.5, 0.0], "gyro_os_bias_rad_s": [0.001, 0.0, 0.0]})
    fresh = aged(DevicePrior(calibration=_stored_cal(0.5), source="store"), 600.0)  # 10 min old: ≈ 1.1 µT
    old = aged(DevicePrior(calibration=_stored_cal(0.5), source="store"), 3 * DAY_S)  # ≈ 23 µT
    c = choose(phone, fresh)
    assert c.calibration is fresh.calibration and c.gyro_bias == phone.gyro_bias
    assert c.source == "phone+store"
    assert choose(phone, old).calibration is phone.calibration
    assert choose(None, None) is None


def test_store_round_trip_keys_and_age(tmp_path):
    store = DeviceStore(tmp_path / "devices")
    assert store.load(META, 1000.0) is None
    prior = DevicePrior(calibration=_stored_cal(0.5), gyro_bias=(0.002, -0.001, 0.0), gyro_bias_std=4e-4)
    path = store.save(META, prior, t_unix=1000.0)
    assert path.name == "OPPO_PBCM10.json" and json.loads(path.read_text())["device"] == "OPPO PBCM10"
    back = store.load(META, 1000.0 + 3600.0)
    assert back.source == "store" and back.age_s == 3600.0
    assert back.calibration.offset == prior.calibration.offset
    s = store.settings
    np.testing.assert_allclose(np.diag(back.calibration.offset_covariance),
                               0.25 + s.offset_drift_uT_per_sqrt_day**2 / 24, rtol=1e-9)  # fmt: skip
    # another device, or the same model with another id, has no entry
    assert store.load({"device": "Pixel 7"}, 1000.0) is None
    assert store.load({**META, "device_id": "a1"}, 1000.0) is None
    # a recording that names no device is not stored
    assert store.save({}, prior, 1000.0) is None


def test_store_keeps_the_part_a_new_save_lacks(tmp_path):
    store = DeviceStore(tmp_path)
    first = DevicePrior(calibration=_stored_cal(0.5), gyro_bias=(0.01, 0.0, 0.0), gyro_bias_std=1e-3)
    store.save(META, first, t_unix=0.0)
    store.save(META, DevicePrior(calibration=None, gyro_bias=(0.02, 0.0, 0.0), gyro_bias_std=1e-3), 60.0)
    back = store.load(META, 60.0)
    assert back.calibration is not None and back.calibration.offset == (-57.0, -91.0, -302.0)
    # two sessions of the same gyro, equally sure, 0.57 °/s apart (within their power-ups' σ): their mean
    assert back.gyro_bias == pytest.approx((0.015, 0.0, 0.0), abs=1e-12)
    stored = back.gyro_bias_std
    # saves that bring only a calibration keep the gyro part as it was stored: one power-up's σ at the load,
    # not one more per save
    for t in (120.0, 180.0, 240.0):
        store.save(META, DevicePrior(calibration=_stored_cal(0.5), gyro_bias=None), t)
    again = store.load(META, 240.0)
    assert again.gyro_bias == back.gyro_bias and again.gyro_bias_std == pytest.approx(stored, rel=1e-12)


def test_the_stored_gyro_bias_is_the_devices_mean_over_its_sessions(tmp_path):
    """Sessions of one gyro: each powers up at ``b_dev + ε`` (ε of the power-up σ) and its filter ends with
    that offset ± 0.3 °/s.  The store keeps their information-weighted mean: after 30 sessions it is within
    3 σ of ``b_dev`` (σ = √((0.3² + τ²) / 30) °/s per axis) — nearer than one session's estimate can be
    sure of — and the next load's σ has shrunk to little more than one power-up's.  A session whose bias
    the mean cannot explain (another gyro under the key) starts the estimate afresh."""
    store = DeviceStore(tmp_path)
    tau = store.settings.gyro_turn_on_std
    sd = math.radians(0.3)
    b_dev = np.radians([0.4, -0.2, 0.1])
    rng = np.random.default_rng(3)
    for k in range(30):
        b_k = b_dev + rng.normal(0.0, tau, 3) + rng.normal(0.0, sd, 3)
        store.save(META, DevicePrior(gyro_bias=tuple(b_k), gyro_bias_std=sd), 60.0 * k)
    back = store.load(META, 1800.0)
    sigma_mean = math.sqrt((sd**2 + tau**2) / 30)
    assert np.all(np.abs(np.array(back.gyro_bias) - b_dev) < 3 * sigma_mean)
    assert back.gyro_bias_std == pytest.approx(math.hypot(sigma_mean, tau), rel=1e-9)
    # another gyro, 3 °/s off on one axis: its own bias, at one session's σ
    other = tuple(b_dev + np.radians([3.0, 0.0, 0.0]))
    store.save(META, DevicePrior(gyro_bias=other, gyro_bias_std=sd), 1900.0)
    again = store.load(META, 1900.0)
    assert again.gyro_bias == other
    assert again.gyro_bias_std == pytest.approx(math.sqrt(sd**2 + 2 * tau**2), rel=1e-9)
    # an entry that states its bias exactly (σ 0, written by hand) is kept by a session that agrees with it
    entry = json.loads(store.path(META).read_text())
    entry["gyro_bias_std_rad_s"] = 0.0
    store.path(META).write_text(json.dumps(entry))
    store.save(META, DevicePrior(gyro_bias=tuple(np.add(other, 0.001)), gyro_bias_std=sd), 2000.0)
    kept = store.load(META, 2000.0)
    assert kept.gyro_bias == pytest.approx(other, abs=1e-15)
    assert kept.gyro_bias_std == pytest.approx(tau, rel=1e-12)
    with pytest.raises(ValueError, match="finite"):
        store.save(META, DevicePrior(gyro_bias=(0.0, 0.0, 0.0), gyro_bias_std=float("nan")), 2100.0)


def test_a_broken_store_file_is_reported_by_name(tmp_path):
    store = DeviceStore(tmp_path)
    (tmp_path / "OPPO_PBCM10.json").write_text("{not json")
    with pytest.raises(ValueError, match="OPPO_PBCM10.json: device store: cannot read"):
        store.load(META, 0.0)
    (tmp_path / "OPPO_PBCM10.json").write_text(json.dumps({"format_version": 7}))
    with pytest.raises(ValueError, match="format_version"):
        store.load(META, 0.0)


def test_two_devices_whose_keys_read_the_same_as_file_names_keep_their_own_entries(tmp_path):
    store = DeviceStore(tmp_path)
    a, b = {"device": "Galaxy S9"}, {"device": "Galaxy/S9"}
    pa = store.save(a, DevicePrior(calibration=_stored_cal(0.5), gyro_bias=None), 0.0)
    cal_b = MagCalibration.from_arrays([10.0, 20.0, 30.0], field_uT=43.0, method="gravity",
                                       offset_std_uT=(0.5, 0.5, 0.5))  # fmt: skip
    pb = store.save(b, DevicePrior(calibration=cal_b, gyro_bias=None), 0.0)
    assert pa != pb and pa.name == "Galaxy_S9.json" and pb.name.startswith("Galaxy_S9-")
    assert store.load(a, 0.0).calibration.offset == (-57.0, -91.0, -302.0)
    assert store.load(b, 0.0).calibration.offset == (10.0, 20.0, 30.0)
    # saving each again writes its own file
    store.save(b, DevicePrior(calibration=cal_b, gyro_bias=None), 10.0)
    assert store.path(a) == pa and store.path(b) == pb
    assert store.load(a, 10.0).calibration.offset == (-57.0, -91.0, -302.0)
    # the plain file gone (removed by hand): the second device still finds its own, and saves there
    pa.unlink()
    assert store.load(b, 10.0).calibration.offset == (10.0, 20.0, 30.0)
    assert store.save(b, DevicePrior(calibration=cal_b, gyro_bias=None), 20.0) == pb and not pa.exists()


def test_a_prior_without_its_sigma_gives_way_to_a_first_fit():
    """A store's or the phone's estimate saved without its σ knows nothing sure: provisional for the
    refits (a first fit may replace it), where a calibration the user gave without σ is as sure as given."""
    from pdr_mag.calibration.online_settings import OnlineSettings
    from pdr_mag.calibration.refit import provisional

    nan = (float("nan"),) * 3
    prior = MagCalibration.from_arrays([1.0, 2.0, 3.0], offset_std_uT=nan, extra={"prior": "store"})
    given = MagCalibration.from_arrays([1.0, 2.0, 3.0], offset_std_uT=nan)
    assert provisional(prior, OnlineSettings(), vague_prior=True)
    assert not provisional(given, OnlineSettings(), vague_prior=True)


def test_a_store_file_without_its_key_is_reported_not_overwritten(tmp_path):
    store = DeviceStore(tmp_path)
    path = store.save(META, DevicePrior(calibration=_stored_cal(0.5), gyro_bias=None), 0.0)
    d = json.loads(path.read_text())
    del d["key"]
    path.write_text(json.dumps(d))
    with pytest.raises(ValueError, match="OPPO_PBCM10.json: device store: no device key"):
        store.load(META, 0.0)
    with pytest.raises(ValueError, match="no device key"):
        store.save(META, DevicePrior(calibration=None, gyro_bias=None), 1.0)
    assert json.loads(path.read_text())["calibration"] is not None  # what was there is kept


def test_a_save_and_a_load_read_the_file_once(tmp_path, monkeypatch):
    from pathlib import Path

    store = DeviceStore(tmp_path)
    store.save(META, DevicePrior(calibration=_stored_cal(0.5), gyro_bias=None), 0.0)
    reads = []
    real = Path.read_text
    monkeypatch.setattr(Path, "read_text", lambda self, *a, **k: reads.append(self) or real(self, *a, **k))
    store.save(META, DevicePrior(calibration=_stored_cal(0.5), gyro_bias=None), 1.0)
    assert len(reads) == 1
    store.load(META, 2.0)
    assert len(reads) == 2
    path, prior = store.find(META, 3.0)  # what replay --device-store asks: the file and its prior, one read
    assert len(reads) == 3 and path == store.path(META) and prior.calibration is not None


def test_a_session_that_agrees_with_the_stored_calibration_refines_it(tmp_path):
    """Two sessions' fits 2 µT apart along x, σ 1 and 2 µT (within χ²₃ 99 %): the store keeps their
    information-weighted mean, −57 + 2 · 1 / (1 + 4) = −56.6 µT, at the later fit's covariance (their errors
    are partly shared); a fit 20 µT away (a changed device), one of another soft-iron shape, or the entry left
    standing as this session's prior replace or keep it as they are."""
    store = DeviceStore(tmp_path)
    store.save(META, DevicePrior(calibration=_stored_cal(1.0)), t_unix=0.0)
    near = MagCalibration.from_arrays([-55.0, -91.0, -302.0], field_uT=43.0, method="gravity",
                                      offset_std_uT=(2.0, 2.0, 2.0))  # fmt: skip
    store.save(META, DevicePrior(calibration=near), t_unix=0.0)
    back = store.load(META, 0.0).calibration
    np.testing.assert_allclose(back.offset, (-56.6, -91.0, -302.0), atol=1e-9)
    np.testing.assert_allclose(back.offset_std_uT, (2.0, 2.0, 2.0), rtol=1e-12)
    far = MagCalibration.from_arrays([-37.0, -91.0, -302.0], field_uT=43.0, method="gravity",
                                     offset_std_uT=(2.0, 2.0, 2.0))  # fmt: skip
    store.save(META, DevicePrior(calibration=far), t_unix=0.0)
    assert store.load(META, 0.0).calibration.offset == far.offset
    shaped = MagCalibration.from_arrays([-36.0, -91.0, -302.0], np.diag([1.05, 0.95, 1.0]), field_uT=43.0,
                                        method="ml", offset_std_uT=(2.0, 2.0, 2.0))  # fmt: skip
    store.save(META, DevicePrior(calibration=shaped), t_unix=0.0)
    assert store.load(META, 0.0).calibration.offset == shaped.offset
    again = store.load(META, 0.0)
    store.save(META, again, t_unix=0.0)  # the entry itself, left standing: nothing new
    assert store.load(META, 0.0).calibration.offset == shaped.offset


def test_a_stored_part_serves_only_the_stream_it_was_learnt_on(tmp_path):
    """A raw magnetometer's offset (hundreds of µT) is not the residual offset of the field the OS has
    already corrected, nor a raw gyro's offset the residual of an OS-calibrated rate: an entry keeps which
    stream each part was learnt on, a recording of the other stream does not start from that part, and its
    own fit replaces the part rather than refining it.  A recording (or an entry) that does not say which
    stream it has is served as before."""
    store = DeviceStore(tmp_path)
    raw = {**META, "mag_os_calibrated": False, "gyro_os_calibrated": False}
    calibrated = {**META, "mag_os_calibrated": True, "gyro_os_calibrated": False}
    learnt = DevicePrior(calibration=_stored_cal(0.5), gyro_bias=(0.01, 0.0, 0.0), gyro_bias_std=1e-3)
    store.save(raw, learnt, 0.0)
    entry = json.loads(store.path(raw).read_text())
    assert entry["mag_stream"] == "raw" and entry["gyro_stream"] == "raw"
    assert store.load(raw, 60.0).calibration.offset == (-57.0, -91.0, -302.0)
    other = store.load(calibrated, 60.0)
    assert other.calibration is None and other.gyro_bias == (0.01, 0.0, 0.0)
    assert store.load({**META, "mag_os_calibrated": True, "gyro_os_calibrated": True}, 60.0) is None
    assert store.load(META, 60.0).calibration is not None  # the recording does not say: served
    # the OS-calibrated session's own fit, 2 µT from zero: it replaces the raw offset (no mean of the two)
    residual = MagCalibration.from_arrays([2.0, 0.0, 0.0], field_uT=43.0, method="gravity",
                                          offset_std_uT=(400.0, 400.0, 400.0))  # fmt: skip
    store.save(calibrated, DevicePrior(calibration=residual), 120.0)
    entry = json.loads(store.path(raw).read_text())
    assert entry["mag_stream"] == "os_calibrated" and entry["gyro_stream"] == "raw"
    assert store.load(calibrated, 180.0).calibration.offset == (2.0, 0.0, 0.0)
    assert store.load(raw, 180.0).calibration is None
    # an entry written without streams serves every recording
    del entry["mag_stream"], entry["gyro_stream"]
    store.path(raw).write_text(json.dumps(entry))
    assert store.load(raw, 180.0).calibration.offset == (2.0, 0.0, 0.0)
