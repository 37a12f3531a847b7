"""The tyrex benchmark layouts (Android Senslogs, iOS): real trials against their pdr-csv conversions, and
malformed input."""

from __future__ import annotations

import numpy as np
import pytest

from pdr_mag.conventions import quat_to_rot
from replay.errors import InputError
from replay.formats import detect, pdrcsv, read_recording, tyrex
from tests.conftest import dataset


def _same(a, b):
    assert len(a) == len(b)
    np.testing.assert_allclose(a.t, b.t, atol=1e-6)  # pdr-csv keeps 6 decimals of time
    np.testing.assert_allclose(a.xyz, b.xyz, rtol=1e-7, atol=1e-7)


@pytest.mark.parametrize(
    "platform,trial",
    [
        ("android", "Thibaud_Nexus5_Dist_FrontPocket"),
        ("ios", "Thibaud_iPhone5_NoDist_Texting"),
        ("android", "calib_mag_Nexus5_d2"),
        ("ios", "calib_mag_iPhone5_d3"),
    ],
)
def test_raw_trial_matches_converted(platform, trial):
    raw = dataset("tyrex-attitude", platform, trial)
    ref = pdrcsv.read(dataset("tyrex-pdrcsv", trial))
    assert detect(raw) == "tyrex"
    rec = read_recording(raw)
    assert rec.format == f"tyrex-{platform}"
    for k in ("mag", "accel", "gyro"):
        _same(getattr(rec, k), getattr(ref, k))
    if ref.truth is not None:
        assert rec.truth is not None and rec.meta["truth_north"] == "true"
        np.testing.assert_allclose(rec.truth[0], ref.truth[0], atol=1e-6)
        dots = np.abs(np.sum(rec.truth[1] * ref.truth[1], axis=1))
        assert np.all(dots > 1 - 1e-8)
        # axes and sign against the mocap: the specific force rotated into ENU points up (+g on z)
        tq, q = rec.truth
        i = np.clip(np.searchsorted(tq, rec.accel.t), 0, len(tq) - 1)
        near = np.abs(tq[i] - rec.accel.t) < 0.02
        up = np.einsum("nij,nj->ni", quat_to_rot(q[i[near]]), rec.accel.xyz[near])
        np.testing.assert_allclose(np.median(up, axis=0), [0, 0, 9.8], atol=0.3)


def test_glitches_and_nan_frames_counted():
    rec = tyrex.read(dataset("tyrex-attitude", "android", "Thibaud_Nexus5_Dist_FrontPocket"))
    assert rec.dropped["truth:nan"] == 498
    assert rec.dropped["truth:glitch"] == 634
    assert len(rec.truth[0]) == 7200 - 498 - 634
    assert rec.meta["date"] == "2016-06-02" and rec.meta["device"] == "LGE Nexus 5"


def _android(tmp_path, mag="0.0 30 0 -30 0 0 0\n0.02 30 1 -30 0 0 0\n0.04 31 1 -30 0 0 0\n"):
    d = tmp_path / "rec"
    d.mkdir()
    (d / "record.properties").write_text("[Device]\nModel = Phone\n\n[Time]\nStartTime = 1464686052\n")
    (d / "magnetometer.txt").write_text(mag)
    (d / "accelerometer.txt").write_text("0.0 0 0 9.8\n0.01 0 0 9.81\n0.02 0 0 9.8\n")
    (d / "gyroscope.txt").write_text("0.0 0 0 0.01 0 0 0\n0.01 0 0 0.01 0 0 0\n")
    return d


def test_fixture_android_nan_and_duplicate(tmp_path):
    d = _android(tmp_path, "0.0 30 0 -30\n0.02 nan 1 -30\n0.02 30 1 -30\n0.02 30 1 -30\n0.04 31 1 -30\n")
    rec = read_recording(d)
    assert len(rec.mag) == 3 and rec.dropped["mag:nan"] == 1 and rec.dropped["mag:duplicate_t"] == 1
    assert rec.truth is None and "latitude_deg" not in rec.meta


@pytest.mark.parametrize(
    "mag,problem,line",
    [
        ("0.0 30 0 -30\n0.02 30 0 -30\n0.01 30 0 -30\n", "time goes backwards", 3),
        ("0.0 30 0 -30\n0.02 30 0 -30\n0.04 30\n", "truncated", 3),
        ("0.0 30000 0 -30000\n0.02 30000 0 -30000\n", "wrong unit", None),
        ("", "empty stream", None),
    ],
)
def test_malformed(tmp_path, mag, problem, line):
    d = _android(tmp_path, mag)
    with pytest.raises(InputError) as ei:
        read_recording(d)
    assert problem in ei.value.problem
    assert ei.value.line == line
    assert "magnetometer.txt" in str(ei.value)


def test_stream_missing(tmp_path):
    d = _android(tmp_path)
    (d / "gyroscope.txt").unlink()
    with pytest.raises(InputError, match=r"gyroscope\.txt: missing"):
        read_recording(d)


def test_ios_bad_boot_time(tmp_path):
    d = tmp_path / "ios"
    d.mkdir()
    (d / "description.txt").write_text("[Time]\nBootTime = soon\n")
    (d / "magnetometer.txt").write_text("1 30 0 -30\n2 30 0 -30\n")
    with pytest.raises(InputError, match="BootTime is not a number"):
        read_recording(d)


@pytest.mark.parametrize(
    "platform,trial",
    [("ios", "Thibaud_iPhone5_NoDist_Texting"), ("android", "Thibaud_Nexus5_NoDist_Swinging")],
)
def test_magnetometer_axes_against_mocap(platform, trial):
    """Hard-iron-corrected field rotated into ENU by the mocap points north (WMM: E 0.6, N 22.8 µT)."""
    rec = read_recording(dataset("tyrex-attitude", platform, trial))
    m = rec.mag.xyz
    a = np.column_stack([2 * m, np.ones(len(m))])
    centre = np.linalg.lstsq(a, (m**2).sum(axis=1), rcond=None)[0][:3]
    tq, q = rec.truth
    i = np.clip(np.searchsorted(tq, rec.mag.t), 0, len(tq) - 1)
    near = np.abs(tq[i] - rec.mag.t) < 0.02
    field_w = np.median(np.einsum("nij,nj->ni", quat_to_rot(q[i[near]]), (m - centre)[near]), axis=0)
    assert abs(field_w[0]) < 4.0 and 17.0 < field_w[1] < 28.0


def test_os_estimates_of_a_real_nexus5_walk():
    """Senslogs' bias/drift columns: what the OS stated when the walk started, and that it never changed."""
    rec = tyrex.read(dataset("tyrex-attitude", "android", "Thibaud_Nexus5_Dist_Texting"))
    assert rec.meta["mag_os_bias_uT"] == [57.95996, -35.742188, 419.90356]
    assert rec.meta["gyro_os_bias_rad_s"] == [0.013793947, -0.0052337646, 0.070999146]
    assert rec.meta["mag_os_bias_changes"] == [] and rec.meta["gyro_os_bias_changes"] == []
    assert rec.meta["mag_os_calibrated"] is False and rec.meta["gyro_os_calibrated"] is False
    assert rec.meta["device_id"] == "03bd36a425202217"
    # the raw field minus the OS's estimate is the Earth's (about 47 µT in Grenoble) where the walk is clean
    cal = np.linalg.norm(rec.mag.xyz - rec.meta["mag_os_bias_uT"], axis=1)
    assert 40 < np.percentile(cal, 10) < np.median(cal) < 60


def test_os_bias_changes_of_a_real_nexus5_walk():
    rec = tyrex.read(dataset("tyrex-attitude", "android", "Thibaud_Nexus5_NoDist_Swinging"))
    changes = rec.meta["mag_os_bias_changes"]
    assert [len(c) for c in changes] == [4, 4]
    assert 0 < changes[0][0] < changes[1][0] < rec.mag.t[-1]
    assert all(c[0] in rec.mag.t for c in changes)  # at magnetometer samples
    assert rec.meta["mag_os_bias_uT"] == [58.569336, -74.22638, 412.05902]


def test_ios_estimate_from_the_calibrated_field():
    """iOS: the hard-iron estimate is raw − Core Motion's calibrated field over the first two seconds — within
    3 µT of the same over the whole walk (the OS's bias holds), and the raw field minus it is the Earth's."""
    d = dataset("tyrex-attitude", "ios", "Thibaud_iPhone5_NoDist_Texting")
    rec = tyrex.read(d)
    assert rec.meta["mag_os_calibrated"] is False and rec.meta["gyro_os_calibrated"] is False
    assert rec.meta["mag_os_bias_changes"] == []
    assert not any(k.startswith(("gyro_os_bias", "device_id")) for k in rec.meta)
    raw, cal = np.loadtxt(d / "magnetometer.txt"), np.loadtxt(d / "magnetometer-calibrated.txt")
    inside = (cal[:, 0] > raw[0, 0]) & (cal[:, 0] < raw[-1, 0])
    raw_at_cal = np.column_stack([np.interp(cal[inside, 0], raw[:, 0], raw[:, k]) for k in (1, 2, 3)])
    whole = np.median(raw_at_cal - cal[inside, 1:4], axis=0)
    np.testing.assert_allclose(rec.meta["mag_os_bias_uT"], whole, atol=3.0)
    f = np.linalg.norm(rec.mag.xyz - rec.meta["mag_os_bias_uT"], axis=1)
    assert 35 < np.percentile(f, 10) < np.median(f) < 55


def _ios(tmp_path, calibrated: str | None):
    d = tmp_path / "ios"
    d.mkdir()
    (d / "description.txt").write_text("[Time]\nBootTime = 100.0\n")
    t = 100.0 + np.arange(0.0, 4.0, 0.04)  # raw at 25 Hz: the Earth's field (20, 0, −40) plus (100, 200, 50)
    (d / "magnetometer.txt").write_text("".join(f"{x:.3f} 120 200 10\n" for x in t))
    (d / "accelerometer.txt").write_text("".join(f"{x:.3f} 0 0 -1\n" for x in t))
    (d / "gyroscope.txt").write_text("".join(f"{x:.3f} 0 0 0\n" for x in t))
    if calibrated is not None:
        (d / "magnetometer-calibrated.txt").write_text(calibrated)
    return d


def test_fixture_ios_estimate(tmp_path):
    """Calibrated rows of accuracy −1 state no calibration; odd rows are skipped and counted by the readers'
    rules (garbled, a value missing, time going back); the first two seconds only; a trial without the
    calibrated file states no estimate."""
    rows = ["100.010 5 5 5 -1\n"]  # uncalibrated: ignored
    rows += [f"{100.02 + 0.01 * i:.3f} 20 0 -40 2\n" for i in range(150)]  # b = (100, 200, 50) for 1.5 s
    rows += ["101.600 20 zero -40 2\n", "101.610 20 0 -40\n", "101.400 0 0 0 2\n"]  # odd
    rows += [f"{101.7 + 0.01 * i:.3f} 20 0 -40 1\n" for i in range(50)]  # still within the first two seconds
    rows += [f"{103.0 + 0.01 * i:.3f} 50 50 50 2\n" for i in range(100)]  # after the window: not used
    rec = tyrex.read(_ios(tmp_path, "".join(rows)))
    np.testing.assert_allclose(rec.meta["mag_os_bias_uT"], [100.0, 200.0, 50.0], atol=1e-9)
    odd = {k: n for k, n in rec.dropped.items() if k.startswith("mag_os_bias:")}
    assert odd == {"mag_os_bias:non_numeric": 1, "mag_os_bias:nan": 1, "mag_os_bias:non_monotonic": 1}
    other = tmp_path / "other"
    other.mkdir()
    rec = tyrex.read(_ios(other, None))
    assert "mag_os_bias_uT" not in rec.meta
    # a calibrated field that starts before the raw one, and uncalibrated for its first second after
    early = tmp_path / "early"
    early.mkdir()
    rows = [f"{98.0 + 0.01 * i:.3f} 0 0 0 2\n" for i in range(190)]  # before the raw field: nothing to pair
    rows += [f"{100.0 + 0.01 * i:.3f} 0 0 0 -1\n" for i in range(100)]
    rows += [f"{101.0 + 0.01 * i:.3f} 20 0 -40 2\n" for i in range(250)]
    rec = tyrex.read(_ios(early, "".join(rows)))
    np.testing.assert_allclose(rec.meta["mag_os_bias_uT"], [100.0, 200.0, 50.0], atol=1e-9)
    only_uncalibrated = tmp_path / "unc"
    only_uncalibrated.mkdir()
    rec = tyrex.read(_ios(only_uncalibrated, "100.5 1 2 3 -1\n100.6 1 2 3 -1\n"))
    assert "mag_os_bias_uT" not in rec.meta


def test_fixture_android_estimates(tmp_path):
    """The estimate of the first kept sample; changes at the samples carrying them; odd cells counted; rows
    the stream drops (NaN, repeated time, garbled: text in a cell, an eighth field) say nothing."""
    mag = (
        "0.00 30 0 -30 1 2 3\n"
        "0.02 nan 1 -30 9 9 9\n"  # dropped sample
        "0.04 30 1 -30 1 2 3\n"
        "0.04 30 1 -30 8 8 8\n"  # repeated time: dropped
        "0.06 31 1 -30 7 7 x\n"  # garbled (text in the estimate): dropped whole
        "0.07 31 1 -30 5 5 5 1\n"  # garbled (an eighth field): dropped whole
        "0.08 31 1 -30 1.5 2 3\n"
        "0.10 31 1 -30 1.5 2\n"  # a column missing: odd
        "0.12 31 1 -30\n"  # no estimate stated
        "0.14 31 1 -30 inf 2 3\n"  # not a finite number: odd
    )
    d = _android(tmp_path, mag)
    (d / "record.properties").write_text(
        "[Device]\nModel = Phone\nManufacturer = Acme\nID = 0123abcd\n\n[Time]\nStartTime = 1464686052\n"
    )
    rec = read_recording(d)
    assert len(rec.mag) == 6 and rec.dropped["mag:nan"] == 1 and rec.dropped["mag:duplicate_t"] == 1
    assert rec.dropped["mag:non_numeric"] == 1 and rec.dropped["mag:extra_fields"] == 1
    assert rec.meta["mag_os_bias_uT"] == [1.0, 2.0, 3.0]
    assert rec.meta["mag_os_bias_changes"] == [[0.08, 1.5, 2.0, 3.0]]
    assert rec.dropped["mag_os_bias:nan"] == 2
    # the fixture's gyroscope states a drift of exactly zero: no estimate (replay.formats._phone)
    assert "gyro_os_bias_rad_s" not in rec.meta and "gyro_os_bias_changes" not in rec.meta
    assert rec.meta["device_id"] == "0123abcd" and rec.meta["device"] == "Acme Phone"


def test_fixture_android_without_estimate_columns(tmp_path):
    d = _android(tmp_path, "0.0 30 0 -30\n0.02 30 1 -30\n0.04 31 1 -30\n")
    (d / "gyroscope.txt").write_text("0.0 0 0 0.01\n0.01 0 0 0.01\n")
    rec = read_recording(d)
    assert not any(k.startswith(("mag_os_bias", "gyro_os_bias")) for k in rec.meta) and rec.dropped == {}
    assert "device_id" not in rec.meta and rec.meta["mag_os_calibrated"] is False
