"""The magnetometer's latency against the IMU (``pdr_mag/calibration/latency.py``,
``PipelineSettings.mag_time_offset_s``, ``replay --mag-time-offset S|auto``): found on simulated phones whose
magnetometer reports late (the simulator's ``time_offset``), undetermined without turns, and what moving the
stamps back wins."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pdr_mag.calibration.latency import LatencySettings, applies, estimate_mag_latency
from pdr_mag.estimates import EstimateBatch
from pdr_mag.pipeline import HeadingPipeline, PipelineSettings
from pdr_mag.sim import simulate
from replay.cli import main
from replay.formats import pdrcsv
from replay.recording import Recording, Stream
from replay.run import estimate_latency

LAG_S = 0.08


@pytest.fixture(scope="module")
def late():
    """A swinging hand (2 rad/s swings) whose magnetometer reports 80 ms late, and the same phone on time."""
    out = {}
    for name, lag in (("late", LAG_S), ("on_time", None)):
        out[name] = simulate("swing", seed=7, duration_s=50.0, effects={"time_offset": lag})
    return out


def _estimate(res, settings=None):
    (tg, g), (tm, m) = res.gyro, res.mag
    return estimate_mag_latency(tg, g, tm, m, settings)


def test_a_late_magnetometer_is_found_within_a_few_milliseconds(late):
    lat = _estimate(late["late"])
    assert lat.determined and applies(lat)
    assert lat.seconds == pytest.approx(LAG_S, abs=0.005)
    assert lat.std_s < 0.005 and lat.gain > 0.5  # most of the field's turn residual at lag 0 is the latency
    on_time = _estimate(late["on_time"])
    assert abs(on_time.seconds) < 0.005 and not applies(on_time)


def test_a_magnetometer_ahead_of_the_imu_is_found_but_not_applied():
    res = simulate("swing", seed=8, duration_s=40.0, effects={"time_offset": -0.05})
    lat = _estimate(res)
    assert lat.determined and lat.seconds == pytest.approx(-0.05, abs=0.005)
    assert not applies(lat)  # an IMU later than the magnetometer: the output follows the IMU's stamps


def test_a_phone_that_does_not_turn_determines_no_latency():
    res = simulate("still", seed=1, duration_s=30.0, effects={"time_offset": LAG_S})
    lat = _estimate(res)
    assert not lat.determined and lat.n < 4 * 50
    few = np.arange(10.0)
    assert not estimate_mag_latency(few, np.zeros((10, 3)), few, np.ones((10, 3))).determined
    same_t = np.zeros(100)  # no time between samples: nothing to fit, no error
    assert not estimate_mag_latency(same_t, np.zeros((100, 3)), same_t, np.ones((100, 3))).determined


def test_a_latency_beyond_the_search_is_not_reported_as_found(late):
    lat = _estimate(late["late"], LatencySettings(max_lag_s=0.05))
    assert not lat.determined  # the minimum lies at the edge of ±50 ms


def _run(res, offset):
    pipe = HeadingPipeline(PipelineSettings(mag_time_offset_s=offset), meta=dict(res.meta))
    out = pipe.run({"accel": res.accel, "gyro": res.gyro, "mag": res.mag})
    return pipe, out


def _mean_error(res, out: EstimateBatch) -> float:
    from tests.test_cli_replay import _heading_err_deg

    t_ref, q_ref = res.truth
    keep = (t_ref > 15.0) & (t_ref < out.t[-1])  # after the first calibration
    return float(np.mean(_heading_err_deg(out.t, out.q_wd, t_ref[keep], q_ref[keep])))


def test_moving_the_stamps_back_is_the_same_as_a_magnetometer_on_time(late):
    """The setting is the stamps moved back by it, nothing else: the same rows as the shifted stream pushed
    as it is; and on the late phone it takes the heading error back to the on-time phone's."""
    res = late["late"]
    pipe, moved = _run(res, LAG_S)
    tm, m = res.mag
    streams = {"accel": res.accel, "gyro": res.gyro, "mag": (tm - LAG_S, m)}
    by_hand = HeadingPipeline(meta=dict(res.meta)).run(streams)
    np.testing.assert_array_equal(moved.heading_deg, by_hand.heading_deg)
    np.testing.assert_array_equal(moved.heading_std_deg, by_hand.heading_std_deg)
    assert pipe.summary()["mag_time_offset_s"] == LAG_S
    _, as_is = _run(res, 0.0)
    _, on_time = _run(late["on_time"], 0.0)
    e_late, e_moved = _mean_error(res, as_is), _mean_error(res, moved)
    e_on_time = _mean_error(late["on_time"], on_time)
    # the late phone moved back is the on-time phone (the same samples but for its clocks' jitter)
    assert e_moved == pytest.approx(e_on_time, abs=0.05)
    assert e_late > e_on_time + 0.5  # 80 ms of a 2-rad/s swing: 9° of turn in the fields the filter reads


def test_a_latency_the_pipeline_cannot_take_is_refused():
    with pytest.raises(ValueError, match="mag_time_offset_s"):
        PipelineSettings(mag_time_offset_s=1.5)
    with pytest.raises(ValueError, match="mag_time_offset_s"):
        PipelineSettings(mag_time_offset_s=float("nan"))
    assert PipelineSettings(mag_time_offset_s=-0.02).mag_time_offset_s == -0.02


def test_the_estimate_before_a_run_reads_the_first_60_s():
    res = simulate("swing", seed=9, duration_s=90.0, effects={"time_offset": 0.03})
    rec = Recording(**{k: Stream(*getattr(res, k)) for k in ("mag", "accel", "gyro")}, meta=dict(res.meta))
    t0 = min(res.accel[0][0], res.gyro[0][0], res.mag[0][0])
    (tg, g), (tm, m) = res.gyro, res.mag
    first = estimate_mag_latency(tg[tg < t0 + 60], g[tg < t0 + 60], tm[tm < t0 + 60], m[tm < t0 + 60])
    assert estimate_latency(rec) == first and first.determined
    assert estimate_latency(rec, span_s=200.0) == estimate_mag_latency(tg, g, tm, m)


def test_replay_auto_estimates_applies_and_reports_it(late, tmp_path, capsys):
    res = late["late"]
    rec = Recording(**{k: Stream(*getattr(res, k)) for k in ("mag", "accel", "gyro")}, meta=dict(res.meta),
                    truth=res.truth)
    lat = estimate_latency(rec)
    assert lat.seconds == pytest.approx(LAG_S, abs=0.005)
    p = tmp_path / "late"
    pdrcsv.write(rec, p)
    errors = {}
    for opt in ("0", "auto", "0.08"):
        out = tmp_path / f"s{opt}.json"
        assert main(["replay", str(p), "--mag-time-offset", opt, "--json", str(out), "--no-progress"]) == 0
        summary = json.loads(out.read_text())
        errors[opt] = summary["heading_error"]["truth"]["median_deg"]
        text = capsys.readouterr().out
        if opt == "auto":
            assert summary["mag_latency"]["applied"] and summary["mag_latency"]["span_s"] == 60.0
            assert summary["mag_time_offset_s"] == pytest.approx(summary["mag_latency"]["seconds"], abs=1e-5)
            assert "estimated from the first 60 s and applied" in text
        elif opt == "0":
            assert summary["mag_latency"] is None and summary["mag_time_offset_s"] == 0.0
            assert "mag latency" not in text
        else:
            assert "80.0 ms given" in text
    assert errors["auto"] == pytest.approx(errors["0.08"], abs=0.1)
    assert errors["0.08"] < errors["0"] - 0.5


@pytest.mark.parametrize("bad", ["x", "2", "nan"])
def test_a_bad_latency_option_is_a_usage_error(bad, tmp_path, capsys):
    d = simulate("still", seed=1, duration_s=5.0)
    rec = Recording(mag=Stream(*d.mag), accel=Stream(*d.accel), gyro=Stream(*d.gyro), meta=dict(d.meta))
    pdrcsv.write(rec, tmp_path / "r")
    assert main(["replay", str(tmp_path / "r"), "--mag-time-offset", bad]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--mag-time-offset" in err[0]


def test_batch_replay_takes_the_latency_option_per_recording(late, tmp_path):
    """``pdr-mag batch replay --mag-time-offset auto``: each recording's own latency, as ``replay``'s."""
    for name, res in late.items():
        streams = {k: Stream(*getattr(res, k)) for k in ("mag", "accel", "gyro")}
        pdrcsv.write(Recording(**streams, meta=dict(res.meta)), tmp_path / "in" / name)
    out = tmp_path / "out"
    assert main(["batch", "replay", str(tmp_path / "in"), "--out", str(out), "--workers", "1",
                 "--mag-time-offset", "auto", "--no-progress"]) == 0
    got = {name: json.loads((out / "in" / name / "replay.json").read_text()) for name in late}
    assert got["late"]["mag_latency"]["applied"]
    assert got["late"]["mag_time_offset_s"] == pytest.approx(LAG_S, abs=0.005)
    assert not got["on_time"]["mag_latency"]["applied"] and got["on_time"]["mag_time_offset_s"] == 0.0
