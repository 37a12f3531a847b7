"""RerunSink: write synthetic inputs and estimates to .rrd, read them back with rerun's own RrdReader."""

from __future__ import annotations

import numpy as np
import pytest
from rerun.chunk import RrdReader

from pdr_mag.calibration.model import MagCalibration
from pdr_mag.conventions import heading_deg_from_quat
from pdr_mag.episodes import Episode
from pdr_mag.estimates import DIAG_KEYS, EstimateBatch, Event
from pdr_mag.sinks.rerun import RerunSink


def _unit_quats(rng, n):
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1)[:, None]


def _read(path):
    """Entity → {column name → concatenated values}, time as int ns; from the recording store."""
    out: dict[str, dict[str, list]] = {}
    for chunk in RrdReader(path).stream().to_chunks():
        rb = chunk.to_record_batch()
        d = out.setdefault(chunk.entity_path, {})
        for name in rb.schema.names:
            if "RowId" in name:
                continue
            col = rb.column(name)
            if name == "time":
                values = col.cast("int64").to_pylist()
            else:
                values = col.to_pylist()
            d.setdefault(name, []).extend(values)
    return out


def read_blueprint(path):
    """The default blueprint of an .rrd: {view origin: {"class", "name", "x" (ns), "y", "legend"}}, the
    containers' shares, and the per-entity visible time ranges of the 3-D view."""
    reader = RrdReader(path)
    (store,) = reader.blueprints()
    views: dict[str, dict] = {}
    extra: dict[str, dict] = {}
    for chunk in reader.stream(store=store).to_chunks():
        rb = chunk.to_record_batch()
        path_parts = chunk.entity_path.strip("/").split("/")
        if path_parts[0] != "view":
            continue
        d = views.setdefault(path_parts[1], {})
        cols = {n: rb.column(n).to_pylist()[-1] for n in rb.schema.names if ":" in n}
        if "ViewBlueprint:space_origin" in cols:
            d["origin"] = cols["ViewBlueprint:space_origin"][0]
            d["class"] = cols["ViewBlueprint:class_identifier"][0]
            d["name"] = cols["ViewBlueprint:display_name"][0]
        if "TimeAxis:view_range" in cols:
            r = cols["TimeAxis:view_range"][0]
            d["x"] = (r["start"], r["end"])
        if "ScalarAxis:range" in cols:
            d["y"] = tuple(cols["ScalarAxis:range"][0])
        if "PlotLegend:visible" in cols:
            d["legend"] = cols["PlotLegend:visible"][0]
        if "VisibleTimeRanges:ranges" in cols:
            extra.setdefault(path_parts[1], {})["/".join(path_parts[4:-1])] = cols["VisibleTimeRanges:ranges"]
    out = {}
    for key, d in views.items():
        if "origin" in d:
            d["overrides"] = extra.get(key, {})
            out[d["origin"]] = d
    return out


def _series(data, entity, component="Scalars:scalars"):
    """(t_ns, values) of a temporal entity, sorted by time."""
    d = data[entity]
    t = np.array(d["time"], dtype=np.int64)
    v = [x[0] if isinstance(x, list) and len(x) == 1 else x for x in d[component]]
    order = np.argsort(t, kind="stable")
    return t[order], [v[i] for i in order]


@pytest.fixture
def written(tmp_path):
    rng = np.random.default_rng(11)
    path = tmp_path / "out.rrd"
    sink = RerunSink(path, chunk_rows=700, cloud_rate_hz=10.0)  # small chunks: several sends per entity
    sink.open({"source": "/data/rec_walk", "device": "synthetic", "north": "magnetic"})
    n_per, k = 1000, 4
    t_all = -3.25 + np.arange(n_per * k) / 200.0  # starts negative: rerun's duration timeline allows it
    q = _unit_quats(rng, len(t_all))
    cal_state = np.where(t_all < 5.0, "none", "offset")
    interference = (t_all > 2.0) & (t_all < 4.0)
    diag = {key: rng.normal(45.0, 3.0, len(t_all)) for key in DIAG_KEYS}
    diag["field_strength_uT"][::9] = np.nan
    for axis in "xyz":  # the filter's offset error: an internal column the pipeline's rows carry
        diag[f"mag_offset_error_{axis}"] = rng.normal(0.0, 2.0, len(t_all))
    batch = EstimateBatch(
        t=t_all,
        q_wd=q,
        heading_deg=rng.uniform(0, 360, len(t_all)),
        heading_std_deg=rng.uniform(1, 3, len(t_all)),
        mag_used=~interference,
        interference=interference,
        cal_state=cal_state,
        diag=diag,
    )
    mag_raw = rng.normal(0, 40, (len(t_all) // 2, 3))
    q_truth = _unit_quats(rng, len(t_all))
    sink.reference("truth", t_all[: 2 * n_per], q_truth[: 2 * n_per])  # before the estimates, in 2 calls
    sink.reference("truth", t_all[2 * n_per :], q_truth[2 * n_per :])
    for c in range(k):
        sl = slice(c * n_per, (c + 1) * n_per)
        ts = t_all[sl]
        sink.inputs("accel", ts, rng.normal(size=(n_per, 3)))
        sink.inputs("gyro", ts, rng.normal(size=(n_per, 3)))
        msl = slice(c * n_per // 2, (c + 1) * n_per // 2)
        sink.inputs("mag", ts[::2], mag_raw[msl])
        sink.mag_calibrated(ts[::2], mag_raw[msl] - 5.0)
        sink.estimates(
            EstimateBatch(
                t=ts,
                q_wd=q[sl],
                heading_deg=batch.heading_deg[sl],
                heading_std_deg=batch.heading_std_deg[sl],
                mag_used=batch.mag_used[sl],
                interference=batch.interference[sl],
                cal_state=batch.cal_state[sl],
                diag={key: v[sl] for key, v in diag.items()},
            )
        )
    sink.reference("os", t_all[::4], q_truth[::4])
    sink.event(Event(2.0, "interference_start", {"score": 1.4}))
    sink.event(Event(4.0, "interference_end"))
    soft = np.array([[1.2, 0.1, 0.0], [0.1, 0.9, 0.0], [0.0, 0.0, 1.0]])
    cal = MagCalibration.from_arrays([10.0, -4.0, 2.0], soft, field_uT=47.0, method="ellipsoid", coverage=0.8)
    sink.calibration(5.0, cal)
    sink.close()
    return {"path": path, "batch": batch, "q_truth": q_truth, "cal": cal, "mag_raw": mag_raw, "sink": sink}


def test_series_read_back_equal(written):
    data = _read(written["path"])
    b = written["batch"]
    t_ns = np.round(b.t * 1e9).astype(np.int64)
    t_back, heading = _series(data, "/heading/ours")
    np.testing.assert_array_equal(t_back, t_ns)
    np.testing.assert_array_equal(heading, b.heading_deg)  # float64 columns: exact
    t_back, gyro = _series(data, "/heading/gyro_only")
    np.testing.assert_array_equal(gyro, b.diag["gyro_heading_deg"])
    _, truth = _series(data, "/heading/truth")
    np.testing.assert_allclose(truth, heading_deg_from_quat(written["q_truth"]), rtol=1e-12)
    assert len(_series(data, "/heading/os")[0]) == len(b.t[::4])

    # heading error against the truth (same epochs here, so the interpolation is exact)
    h_truth = heading_deg_from_quat(written["q_truth"])
    t_back, err = _series(data, "/heading_error/ours")
    np.testing.assert_array_equal(t_back, t_ns)
    expected = np.mod(b.heading_deg - h_truth + 180.0, 360.0) - 180.0
    np.testing.assert_allclose(np.mod(np.array(err) - expected + 180.0, 360.0) - 180.0, 0.0, atol=1e-9)
    assert np.all(np.abs(err) <= 180.0)
    _, err_gyro = _series(data, "/heading_error/gyro_only")
    assert len(err_gyro) == len(b.t)
    _, err_os = _series(data, "/heading_error/os")
    np.testing.assert_allclose(err_os, 0.0, atol=1e-9)  # the "os" series is the truth itself here

    # NaN rows are left out of the plots; the rest is there
    ok = np.isfinite(b.diag["field_strength_uT"])
    t_back, strength = _series(data, "/field/strength")
    np.testing.assert_array_equal(t_back, t_ns[ok])
    np.testing.assert_array_equal(strength, b.diag["field_strength_uT"][ok])
    _, upper = _series(data, "/field/upper")
    np.testing.assert_allclose(upper, b.diag["field_ref_uT"] + b.diag["strength_tol_uT"])
    _, lower = _series(data, "/dip/lower")
    np.testing.assert_allclose(lower, b.diag["dip_ref_deg"] - b.diag["dip_tol_deg"])
    for entity in (
        "/dip/measured",
        "/dip/reference",
        "/coverage/online",
        "/detector/score",
        "/heading_std/ours",
    ):
        assert len(_series(data, entity)[0]) == len(b.t), entity
    for kind in ("accel", "gyro"):
        for axis in "xyz":
            assert len(data[f"/inputs/{kind}/{axis}"]["time"]) == len(b.t)
    for axis in "xyz":  # the filter's estimates, in °/s and µT
        _, bias = _series(data, f"/estimates/gyro_bias/{axis}")
        np.testing.assert_allclose(bias, np.degrees(b.diag[f"gyro_bias_{axis}"]), rtol=1e-12)
        _, offset = _series(data, f"/estimates/offset_error/{axis}")
        np.testing.assert_array_equal(offset, b.diag[f"mag_offset_error_{axis}"])
    assert written["sink"].rows_sent["heading/ours"] == len(b.t)


def test_state_lanes_only_on_change(written):
    data = _read(written["path"])
    t_cal, cal_states = _series(data, "/state/mag_calibration", "StateChange:state")
    assert cal_states == ["none", "offset"]
    assert t_cal[1] == 5_000_000_000
    _, interf = _series(data, "/state/interference", "StateChange:state")
    assert interf == ["clean", "interference", "clean"]


def test_cloud_fit_and_events(written):
    data = _read(written["path"])
    t_raw, pts = _series(data, "/mag/raw", "Points3D:positions")
    # decimated to 10 Hz over 20 s of 100 Hz magnetometer samples
    assert 195 <= len(pts) <= 201
    raw = written["mag_raw"]
    # every cloud point is one of the raw samples (float32 positions)
    first = np.array(pts[0], dtype=float)
    assert np.any(np.all(np.abs(raw - first) < 1e-4 * (1 + np.abs(first)), axis=1))
    assert len(_series(data, "/mag/calibrated", "Points3D:positions")[1]) == len(pts)

    cal = written["cal"]
    _, centers = _series(data, "/mag/fit/ellipsoid", "Ellipsoids3D:centers")
    np.testing.assert_allclose(centers[0], cal.offset, rtol=1e-6)
    _, half = _series(data, "/mag/fit/ellipsoid", "Ellipsoids3D:half_sizes")
    lam = np.linalg.eigvalsh(np.asarray(cal.soft_iron))
    np.testing.assert_allclose(sorted(half[0]), sorted(cal.field_uT / lam), rtol=1e-5)
    _, sphere = _series(data, "/mag/fit/sphere", "Ellipsoids3D:half_sizes")
    np.testing.assert_allclose(sphere[0], [47.0] * 3, rtol=1e-6)

    t_ev, texts = _series(data, "/events", "TextLog:text")
    _, levels = _series(data, "/events", "TextLog:level")
    assert texts[0].startswith("interference_start") and levels[0] == "WARN"
    assert texts[1] == "interference_end" and levels[1] == "INFO"
    assert texts[2].startswith("calibration: ellipsoid accepted")
    assert list(t_ev) == [2_000_000_000, 4_000_000_000, 5_000_000_000]


def test_blueprint_fitted_to_the_data(written):
    views = read_blueprint(written["path"])
    kinds = {o: v["class"] for o, v in views.items()}
    for origin in ("/heading", "/heading_error", "/field", "/dip", "/detector", "/mag_use", "/coverage"):
        assert kinds[origin] == "TimeSeries", origin
    for sensor in ("accel", "gyro", "mag"):  # one plot per sensor
        assert kinds[f"/inputs/{sensor}"] == "TimeSeries"
    for group in ("gyro_bias", "offset_error"):
        assert kinds[f"/estimates/{group}"] == "TimeSeries"
    assert kinds["/state"] == "StateTimeline" and kinds["/mag"] == "3D" and kinds["/events"] == "TextLog"
    # every time axis spans the whole recording (absolute, not round the cursor)
    b = written["batch"]
    lo, hi = b.t[0] * 1e9, b.t[-1] * 1e9
    for origin, v in views.items():
        if v["class"] in ("TimeSeries", "StateTimeline"):
            x0, x1 = v["x"]
            assert x0 < lo < hi < x1 and (x1 - x0) < 1.1 * (hi - lo), origin
        if v["class"] == "TimeSeries":
            assert v["legend"] is False, origin  # the titles name the series: nothing covers the curves
    # error plot: symmetric, fitted to the error (uniform random headings here: up to 180°) and 2σ
    y0, y1 = views["/heading_error"]["y"]
    assert y0 == -y1 and y1 == pytest.approx(180.0)
    assert views["/heading"]["y"] == (0.0, 360.0)
    # field and dip: the detector's bands widened to twice their tolerance
    d = b.diag
    f0, f1 = views["/field"]["y"]
    assert f0 == pytest.approx(np.min(d["field_ref_uT"] - 2 * d["strength_tol_uT"]))
    assert f1 == pytest.approx(np.max(d["field_ref_uT"] + 2 * d["strength_tol_uT"]))
    # the 3-D view accumulates the clouds up to the cursor, and shows the fits at the cursor only
    ov = views["/mag"]["overrides"]
    assert set(ov) == {"mag/raw", "mag/calibrated"}


def test_drift_episode_rotation_and_one_line_per_calibration(tmp_path):
    path = tmp_path / "ep.rrd"
    sink = RerunSink(path)
    sink.open({"source": "x", "mag_interval_s": 0.2})
    t = np.arange(0, 30, 0.02)
    n = len(t)
    used = (np.arange(n) % 10 == 0) & ~((t >= 10) & (t < 20))
    flag = (t >= 12) & (t < 18)
    sink.reference("truth", t, np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)))
    sink.estimates(
        EstimateBatch(
            t=t,
            q_wd=np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)),
            heading_deg=np.where((t > 11) & (t < 19), 15.0, 1.0),
            heading_std_deg=np.full(n, 3.0),
            mag_used=used,
            interference=flag,
            cal_state=np.full(n, "offset"),
        )
    )
    cal = MagCalibration.from_arrays([1.0, 2.0, 3.0], None, field_uT=48.0, method="sphere", coverage=0.5)
    sink.event(Event(5.0, "calibration_accepted", {"method": "sphere"}))
    sink.calibration(5.0, cal)
    sink.event(Event(1.0, "rotation_episode_start"))
    sink.event(Event(4.0, "rotation_episode_end"))
    ep = Episode("error", 11.0, 19.0, 10.0, 14.0, 15.0, peak_error_deg=14.0, peak_std_deg=3.0, t_flag=12.0)
    gap = Episode("no_reference", 9.8, 20.0, 10.0, 10.2, 20.0, peak_error_deg=14.0, peak_std_deg=3.0)
    sink.event(ep.to_event())
    sink.event(gap.to_event())
    gap_data = {"stream": "gyro", "t_to": 28.5, "duration_s": 3.5, "where": "inside"}
    sink.event(Event(25.0, "stream_gap", gap_data))
    sink.close()
    data = _read(path)
    t_text, texts = _series(data, "/events", "TextLog:text")
    assert sum("sphere" in x for x in texts) == 1  # the event and the calibration: one line
    gap_line = [(tt, x) for tt, x in zip(t_text, texts, strict=True) if x.startswith("stream gap")]
    assert gap_line == [(25e9, "stream gap: no gyro sample for 3.5 s, until its next sample")]
    texts = [x for x in texts if not x.startswith("stream gap")]
    assert texts[0].startswith("rotation_episode_start") and texts[-1].startswith("drift episode: error")
    t_drift, drift = _series(data, "/state/drift", "StateChange:state")
    assert drift == ["no_reference", "error", "no_reference", ""]  # the worst open kind at each time
    np.testing.assert_array_equal(t_drift, np.array([9.8, 11.0, 19.0, 20.0]) * 1e9)
    _, rot = _series(data, "/state/rotation", "StateChange:state")
    assert rot == ["rotating", ""]
    # magnetometer: 5 corrections per second × 0.2 s = all of each second, none from 10 to 20 s
    t_share, share = _series(data, "/mag_use/share")
    np.testing.assert_allclose(np.array(share)[(t_share > 0) & (t_share < 9e9)], 1.0)
    np.testing.assert_allclose(np.array(share)[(t_share > 10e9) & (t_share < 20e9)], 0.0)
    _, lane = _series(data, "/state/magnetometer", "StateChange:state")
    assert lane == ["used", "not used", "used"]
    # the strips in the error plot: the flag's stretch at the bottom, the episodes at the top
    t_strip, strip = _series(data, "/heading_error/strip_interference")
    np.testing.assert_allclose(np.array(t_strip)[np.isfinite(strip)], [12e9, 18e9])
    t_strip, strip = _series(data, "/heading_error/strip_drift_error")
    np.testing.assert_allclose(np.array(t_strip)[np.isfinite(strip)], [11e9, 19e9])
    half = read_blueprint(path)["/heading_error"]["y"][1]
    assert np.nanmax(strip) < half  # inside the plot


def test_bad_arguments(tmp_path):
    with pytest.raises(ValueError, match="path"):
        RerunSink()
    with pytest.raises(ValueError, match="chunk_rows"):
        RerunSink(tmp_path / "a.rrd", chunk_rows=0)
    sink = RerunSink(tmp_path / "b.rrd")
    with pytest.raises(RuntimeError, match="open"):
        sink.inputs("gyro", np.zeros(1), np.zeros((1, 3)))


def test_live_viewer_gets_the_blueprint(monkeypatch):
    """spawn=True starts the viewer with the drift blueprint (the viewer itself is faked: no display here)."""
    import rerun as rr
    import rerun.blueprint as rrb

    seen = {}
    monkeypatch.setattr(rr.RecordingStream, "spawn", lambda self, **kw: seen.update(kw))
    sink = RerunSink(spawn=True)
    sink.open({"source": "live"})
    sink.inputs("gyro", np.arange(10.0) / 100.0, np.zeros((10, 3)))
    sink.close()
    assert isinstance(seen["default_blueprint"], rrb.Blueprint)
    assert sink.rows_sent["inputs/gyro/x"] == 10
