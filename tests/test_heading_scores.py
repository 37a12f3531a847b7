"""``replay.heading_scores``: the heading against the walked direction (checked against the shared tool's own
printout on the shopping-mall traces) and against the phone's own attitude, which the readers carry as
``references["os"]`` (checked against the shared peers file and the converted tyrex ``os.csv``)."""

from __future__ import annotations

import csv
import math
import re
import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pdr_mag.conventions import heading_deg_from_quat, quat_multiply, quat_slerp, quat_to_rotation
from pdr_mag.estimates import EstimateBatch
from pdr_mag.field import earth_field_from_meta
from replay.cli import main
from replay.formats import open_recording, read_recording
from replay.heading_scores import (
    BIN_DEG,
    MAX_REF_GAP_S,
    MISSED_DEG,
    HeadingScores,
    Histogram,
    ReferenceErrors,
    heading_error_deg,
    pooled,
    score_segments,
    walked_segments,
    waypoints_from_fixes,
)
from tests.conftest import ROOT, absent, dataset

TOOL = ROOT.parent / "shared" / "tools" / "walked-direction"
PEERS = ROOT.parent / "shared" / "benchmarks" / "walked_peers.csv"
IPIN = ROOT / "tests" / "fixtures" / "ipin_small.txt"


def _traces(per_floor: int) -> list:
    """The first ``per_floor`` mall traces of each floor (sorted names)."""
    floors = sorted(dataset("ms-indoor-location-2020", "site1").iterdir())
    out = []
    for fl in floors:
        if (fl / "path_data_files").is_dir():
            out += sorted((fl / "path_data_files").glob("*.txt"))[:per_floor]
    return out


# ------------------------------------------------------------------------------------ walked direction
def test_segments_keep_pairs_4_m_and_3_s_apart_and_score_their_middle_half():
    wp = [(0.0, 0.0, 0.0), (10.0, 0.0, 10.0),   # 10 m north in 10 s: kept, bearing 0
          (12.0, 0.0, 20.0),                    # 10 m in 2 s: too quick
          (20.0, 3.0, 20.0),                    # 3 m: too short
          (28.0, 3.0 - 8.0, 20.0 - 8.0)]        # south-west in 8 s: bearing 225
    segs = walked_segments(wp)
    assert segs == [(2.5, 7.5, 0.0), (22.0, 26.0, pytest.approx(225.0))]
    assert walked_segments(wp[:1]) == [] and walked_segments([]) == []


def test_the_error_is_the_circular_mean_over_the_window_wrapped_and_missed_windows_score_180():
    segs = [(2.5, 7.5, 0.0), (22.0, 26.0, 225.0), (40.0, 41.0, 90.0)]
    t = np.arange(0.01, 30.0, 0.02)  # 250 rows in the first window, none on its edges
    # about north the heading swings between 355° and 7° (circular mean 1°; the plain mean would be 181°),
    # then it walks 240° (15° right of the bearing); no row lies in the last window but two
    heading = np.where(t < 15, np.where(np.arange(len(t)) % 2 == 0, 355.0, 7.0), 240.0)
    std = np.where(t < 15, 4.0, 6.0)
    t = np.r_[t, 40.2, 40.4]
    heading, std = np.r_[heading, 90.0, 90.0], np.r_[std, 1.0, 1.0]
    res = score_segments(t, heading, std, segs)
    assert res[0] == (pytest.approx(1.0, abs=1e-9), 4.0)
    assert res[1] == (pytest.approx(15.0, abs=1e-9), 6.0)
    assert res[2][0] == MISSED_DEG and math.isnan(res[2][1])
    # any chunking gives the same sums: the replay scores slice by slice
    from replay.heading_scores import SegmentScorer

    sc = SegmentScorer(segs)
    for i in range(0, len(t), 97):
        sc.add(t[i:i + 97], heading[i:i + 97], std[i:i + 97])
    np.testing.assert_allclose(np.array(sc.results()), np.array(res), atol=1e-9)
    assert math.isnan(score_segments(t, heading, None, segs)[0][1])


def test_pooled_figures():
    res = [(1.0, 4.0), (-15.0, 6.0), (180.0, math.nan), (-50.0, 10.0), (30.0, 30.0)]
    p = pooled(res)
    assert p == {"n_segments": 5, "median_deg": 30.0, "mean_deg": pytest.approx(55.2), "p95_deg": 180.0,
                 "n_over_20": 3, "n_over_45": 2, "within_2sigma_share": 0.5, "n_over_45_sigma_le_20": 1}
    assert pooled([])["median_deg"] is None and pooled([(180.0, math.nan)])["within_2sigma_share"] is None


def test_position_fixes_become_metres_east_and_north():
    # at 45° N one degree of latitude is 111 132 m and one of longitude 78 847 m (WGS-84)
    wp = waypoints_from_fixes([[0.0, 45.0, 7.0, 1.0], [10.0, 45.001, 7.0], [20.0, 45.001, 7.001]])
    np.testing.assert_allclose(np.array(wp), [[0.0, 0.0, 0.0], [10.0, 0.0, 111.132], [20.0, 78.847, 111.132]],
                               atol=0.002)
    assert [round(s[2], 6) for s in walked_segments(wp)] == [0.0, 90.0]


def test_the_mall_traces_score_as_the_shared_tool_prints_them(tmp_path, capsys):
    """``pdr-mag replay`` of 8 mall traces (4 per floor) into ``<trace id>.csv``: the tool run on that
    folder (over a tree holding those 8 traces only) prints the pooled figures of the replay summaries'
    own segments — median and mean to its 2 decimals, the counts and the share within 2σ exactly."""
    if not TOOL.is_file():
        absent(f"shared tool {TOOL} not found (../shared is not beside this checkout)")
    data, res_dir = tmp_path / "data", tmp_path / "res"
    results, consoles = [], []
    for trace in _traces(4):
        floor = trace.parent.parent.name
        (data / "site1" / floor / "path_data_files").mkdir(parents=True, exist_ok=True)
        (data / "site1" / floor / "path_data_files" / trace.name).symlink_to(trace)
        js = tmp_path / f"{trace.stem}.json"
        assert main(["replay", str(trace), "--out-csv", str(res_dir / f"{trace.stem}.csv"), "--json",
                     str(js)]) == 0
        consoles.append(capsys.readouterr().out)
        import json

        w = json.loads(js.read_text())["walked_direction"]
        assert w["from"] == "waypoints" and w["north"] == "true"
        results += [(s["error_deg"], math.nan if s["sigma_deg"] is None else s["sigma_deg"])
                    for s in w["segments"]]
    out = subprocess.run([sys.executable, str(TOOL), str(res_dir), "--data", str(data), "--peers",
                          str(tmp_path / "no-peers.csv")], capture_output=True, text=True, check=True).stdout
    tool = dict(re.findall(r"(\w+)=([-\d.]+)", out.strip().splitlines()[-1]))
    ours = pooled(results)
    assert ours["n_segments"] == int(tool["pdr_mag_n"]) >= 20
    assert ours["median_deg"] == pytest.approx(float(tool["pdr_mag_median"]), abs=0.0051)
    assert ours["mean_deg"] == pytest.approx(float(tool["pdr_mag_mean"]), abs=0.0051)
    assert (ours["n_over_20"], ours["n_over_45"]) == (int(tool["pdr_mag_n20"]), int(tool["pdr_mag_n45"]))
    assert 100 * ours["within_2sigma_share"] == pytest.approx(float(tool["pdr_mag_within2"]), abs=0.0051)
    assert ours["n_over_45_sigma_le_20"] == int(tool["pdr_mag_kept45"])
    # the console says it too
    assert all("heading vs walked" in c and "heading vs phone's own" in c for c in consoles)


# ------------------------------------------------------------------------------ the phone's own heading
def test_the_mall_phones_own_heading_matches_the_peers_file():
    """The phone's fusion of the mall traces (``TYPE_ROTATION_VECTOR`` + WMM declination, as the reader
    gives it) scored on the walked segments: the shared peers file's ``os_err`` on every segment of 8 traces,
    but for a constant 0.070° (that file took its declination from another WMM input; the spread, ±0.005°,
    is its 2-decimal rounding)."""
    if not PEERS.is_file():
        absent(f"shared peers file {PEERS} not found (../shared is not beside this checkout)")
    peers = {(r["trace"], int(r["segment"])): r for r in csv.DictReader(PEERS.open())}
    diff = []
    for trace in _traces(4):
        src = open_recording(trace)
        t, q = src.references["os"]
        segs = walked_segments(src.meta["waypoints"])
        assert len(segs) == sum(1 for k in peers if k[0] == trace.stem)
        for i, ((lo, hi, bearing), (err, _)) in enumerate(
                zip(segs, score_segments(t, heading_deg_from_quat(q), None, segs), strict=True)):
            p = peers[(trace.stem, i)]
            assert (lo, hi, bearing) == pytest.approx(
                (float(p["t_lo"]), float(p["t_hi"]), float(p["bearing_deg"])), abs=0.0051)
            diff.append(err - float(p["os_err"]))
    assert len(diff) >= 20
    assert np.ptp(diff) <= 0.011 and abs(np.mean(diff) + 0.070) <= 0.006


def test_the_mall_rotation_vector_is_turned_by_the_declination():
    trace = _traces(1)[0]
    src = open_recording(trace)
    t, q = src.references["os"]
    rows = [ln.rstrip("\n").split("\t") for ln in trace.open() if "\tTYPE_ROTATION_VECTOR\t" in ln]
    v = np.array([[float(x) for x in r[2:5]] for r in rows])
    w = np.sqrt(1 - np.sum(v * v, axis=1))
    raw = heading_deg_from_quat(np.column_stack([w, v]))  # Android's azimuth, magnetic north
    decl = earth_field_from_meta(src.meta).declination_deg
    assert len(t) == len(rows) and abs(decl) > 1.0
    np.testing.assert_allclose(np.mod(heading_deg_from_quat(q) - raw - decl + 180, 360) - 180, 0, atol=1e-6)
    start = float(next(ln for ln in trace.open() if "startTime:" in ln).split("startTime:")[1].split()[0])
    np.testing.assert_allclose(t, (np.array([float(r[0]) for r in rows]) - start) / 1000, atol=1e-6)


@pytest.mark.parametrize("platform, walk", [("android", "Thibaud_Nexus5_Dist_Texting"),
                                            ("ios", "Thibaud_iPhone5_NoDist_Texting")])
def test_the_tyrex_phone_attitude_is_the_converted_os_csv(platform, walk):
    """The raw tyrex layouts' ``rotation-vector.txt`` (Android, x y z w) and ``attitude.txt`` (iOS,
    CoreMotion's x-north frame) read as ``os``: the tyrex-pdrcsv ``os.csv`` of the same walk (converted
    independently, true north) to its 6 decimals in time, and within 0.002° in heading (the dates differ:
    the Nexus's StartTime gives 2016-06-02, the benchmark's field 2016-05-31: 0.001° of declination)."""
    raw = open_recording(dataset("tyrex-attitude", platform, walk)).references["os"]
    conv = open_recording(dataset("tyrex-pdrcsv", walk)).references["os"]
    assert len(raw[0]) == len(conv[0]) > 10000
    np.testing.assert_allclose(raw[0], conv[0], atol=5.1e-7)
    assert np.max(np.abs(heading_error_deg(raw[1], conv[1]))) < 0.002


def test_ipin_ahrs_rows_are_the_phones_attitude_on_the_app_clock(tmp_path):
    """``AHRS`` rows: the rotation vector (magnetic north: the fixture has no date, so the output is
    magnetic too) at its sensor time moved by the streams' shift; the angles are not read; a garbled row
    is dropped and counted."""
    text = IPIN.read_text().splitlines()
    text = [ln for ln in text if not ln.startswith("AHRS;")]
    half = np.radians(30.0) / 2  # a phone flat, heading 30°: a turn of −30° about Up
    rows = [f"AHRS;{0.30 + 0.01 * k:.3f};{5123.0 + 0.01 * k:.3f};0.0;0.0;999.0;0.0;0.0;{-np.sin(half):.8f};3"
            for k in range(5)] + ["AHRS;0.36;5123.06;0;0;0;0.1;x;0.2;3"]
    f = tmp_path / "log.txt"
    f.write_text("\n".join(text + rows) + "\n")
    src = open_recording(f)
    t, q = src.references["os"]
    mag = read_recording(f).mag
    np.testing.assert_allclose(heading_deg_from_quat(q), 30.0, atol=1e-6)
    # MAGN;0.206;5123.002 is the streams' smallest delivery latency: the same shift for the attitude
    shift = min(float(ln.split(";")[1]) - float(ln.split(";")[2]) for ln in text
                if ln.startswith(("ACCE;", "GYRO;", "MAGN;")))
    np.testing.assert_allclose(t, 5123.0 + 0.01 * np.arange(5) + shift, atol=1e-9)
    assert mag.t[0] == pytest.approx(5123.002 + shift, abs=1e-9)
    assert src.dropped == {"os:non_numeric": 1}


# ------------------------------------------------------------------------------------------- the sink
def _batch(t, q, heading, std):
    n = len(t)
    return EstimateBatch(t=t, q_wd=q, heading_deg=heading, heading_std_deg=std, mag_used=np.ones(n, bool),
                         interference=np.zeros(n, bool), cal_state=np.array(["offset"] * n, dtype=object))


def test_histogram_nearest_rank_to_half_a_bin():
    rng = np.random.default_rng(4)
    v = np.concatenate([rng.gamma(2.0, 3.0, 5000), [180.0, np.nan]])
    h = Histogram()
    h.add(v[:2000])
    h.add(v[2000:])
    finite = np.sort(v[np.isfinite(v)])
    assert h.n == len(finite)
    for q in (0.05, 0.5, 0.95, 1.0):
        exact = finite[math.ceil(q * len(finite)) - 1]
        assert abs(h.quantile(q) - exact) <= BIN_DEG / 2 + 1e-9
    assert Histogram().quantile(0.5) is None


def test_heading_error_is_the_twist_about_up():
    rng = np.random.default_rng(5)
    q_ref = rng.normal(size=(200, 4))
    q_ref /= np.linalg.norm(q_ref, axis=1, keepdims=True)
    yaw = rng.uniform(-170, 170, 200)
    # a pure rotation about world Up by yaw applied to the reference: the error is exactly that yaw
    up = np.column_stack([np.cos(np.radians(yaw) / 2), 0 * yaw, 0 * yaw, np.sin(np.radians(yaw) / 2)])
    np.testing.assert_allclose(heading_error_deg(quat_multiply(up, q_ref), q_ref), yaw, atol=1e-9)
    # and it equals the scorer-style computation with scipy for arbitrary pairs
    q_est = rng.normal(size=(200, 4))
    q_est /= np.linalg.norm(q_est, axis=1, keepdims=True)
    e = (quat_to_rotation(q_est) * quat_to_rotation(q_ref).inv()).as_quat()  # x, y, z, w
    ref = np.degrees(np.mod(2 * np.arctan2(e[:, 2], e[:, 3]) + np.pi, 2 * np.pi) - np.pi)
    np.testing.assert_allclose(heading_error_deg(q_est, q_ref), ref, atol=1e-9)


def test_reference_errors_are_the_numpy_twist_of_the_slerped_reference():
    """The compiled scorer against its definition: |heading_error_deg| of the estimate against the reference
    slerped at its time (:func:`pdr_mag.conventions.quat_slerp`), over a turning reference whose samples
    include sign flips (the shorter arc), a gap beyond ``MAX_REF_GAP_S`` (epochs in it not scored),
    estimates outside its span or with a non-finite attitude (not scored) and epochs on its samples (the
    phone's own attitude on the gyroscope's clock) — the same counts in every bin."""
    rng = np.random.default_rng(11)
    tr = np.concatenate([np.arange(0.0, 20.0, 0.02), np.arange(22.0, 40.0, 0.02)])  # a 2-s gap
    rv = np.cumsum(rng.normal(scale=0.05, size=(len(tr), 3)), axis=0)
    q_ref = Rotation.from_rotvec(rv).as_quat()[:, [3, 0, 1, 2]]
    q_ref[::7] *= -1.0  # the same rotations, the other sign
    t = np.sort(np.concatenate([rng.uniform(-2.0, 42.0, 5000), tr[::3]]))
    q_est = Rotation.from_rotvec(rng.normal(scale=1.0, size=(len(t), 3))).as_quat()[:, [3, 0, 1, 2]]
    q_est[::97, 2] = np.nan
    q_est[::89, 0] = np.inf
    ref = ReferenceErrors(tr, q_ref)
    for k in range(0, len(t), 700):  # slice by slice, as the sink feeds it
        ref.add(t[k : k + 700], q_est[k : k + 700])
    inside = (t >= tr[0]) & (t <= tr[-1]) & np.all(np.isfinite(q_est), axis=1)
    i = np.clip(np.searchsorted(tr, t, side="right") - 1, 0, len(tr) - 2)
    inside &= (tr[i + 1] - tr[i]) <= MAX_REF_GAP_S
    err = np.abs(heading_error_deg(q_est[inside], quat_slerp(tr, q_ref, t[inside])))
    want = Histogram()
    want.add(err)
    assert 0 < inside.sum() < len(t)
    np.testing.assert_array_equal(ref.errors.counts, want.counts)
    assert ref.n_over_45 == int(np.count_nonzero(err > 45.0))
    # slices fed latest first (each slice's first row earlier than the one before): the same counts
    back = ReferenceErrors(tr, q_ref)
    for k in reversed(range(0, len(t), 700)):
        back.add(t[k : k + 700], q_est[k : k + 700])
    np.testing.assert_array_equal(back.errors.counts, want.counts)


def test_a_reference_row_that_is_no_attitude_is_left_out():
    """All-zero reference rows (a logger's placeholder) are not scored against: the scorer counts what the
    series without them gives, where their zero norm divided by zero before."""
    tr = np.arange(0.0, 10.0, 0.02)
    q_ref = Rotation.from_rotvec(np.column_stack([0 * tr, 0 * tr, 0.1 * tr])).as_quat()[:, [3, 0, 1, 2]]
    bad = np.zeros(len(tr), dtype=bool)
    bad[[5, 6, 200, 401]] = True
    zeroed = q_ref.copy()
    zeroed[bad] = 0.0
    t = np.arange(0.01, 10.0, 0.05)
    q_est = Rotation.from_rotvec(np.column_stack([0 * t, 0 * t, 0.1 * t + 0.3])).as_quat()[:, [3, 0, 1, 2]]
    got, want = ReferenceErrors(tr, zeroed), ReferenceErrors(tr[~bad], q_ref[~bad])
    got.add(t, q_est)
    want.add(t, q_est)
    assert got.errors.counts.sum() > 0
    np.testing.assert_array_equal(got.errors.counts, want.errors.counts)


def test_the_sink_scores_references_and_the_walked_direction_slice_by_slice():
    s = HeadingScores()
    s.open({"north": "true", "waypoints": [[0.0, 0.0, 0.0], [20.0, 0.0, 30.0], [40.0, 30.0, 30.0]]})
    t_ref = np.arange(0.0, 10.0, 0.04)
    s.reference("truth", t_ref, np.tile([1.0, 0, 0, 0], (len(t_ref), 1)))
    s.reference("peer", t_ref, np.tile([1.0, 0, 0, 0], (len(t_ref), 1)))  # not a scored name
    t = np.arange(0.0, 40.0, 0.01)  # rows after 10 s lie outside the truth: not scored against it
    yaw = np.where(t < 4, 2.0, np.where(t < 7, 10.0, 50.0))  # about Up by 2°, 10°, then 50° (heading −yaw)
    ang = np.radians(yaw)
    q = np.column_stack([np.cos(ang / 2), 0 * t, 0 * t, np.sin(ang / 2)])
    for i in range(0, len(t), 250):
        sl = slice(i, i + 250)
        s.estimates(_batch(t[sl], q[sl], np.mod(-yaw[sl], 360), np.full(len(t[sl]), 3.0)))
    out = s.summary()
    assert set(out["heading_error"]) == {"truth"}
    e = out["heading_error"]["truth"]
    scored = np.abs(yaw[t <= t_ref[-1]])
    assert e["n_epochs"] == len(scored) == 997
    assert e["median_deg"] == pytest.approx(np.sort(scored)[math.ceil(0.5 * len(scored)) - 1], abs=BIN_DEG)
    assert e["p90_deg"] == pytest.approx(50.0, abs=BIN_DEG)
    assert e["share_over_45"] == pytest.approx(np.mean(scored > 45))
    w = out["walked_direction"]
    # segment 1 walks north (the estimate's heading there: 2°, 10° and 50° west of it), segment 2 east
    h1 = np.radians(-yaw[(t >= 5.0) & (t <= 15.0)])
    expect1 = math.degrees(math.atan2(np.sin(h1).sum(), np.cos(h1).sum()))
    assert [g["bearing_deg"] for g in w["segments"]] == [0.0, pytest.approx(90.0)]
    assert w["segments"][0]["error_deg"] == pytest.approx(expect1, abs=1e-9)
    assert w["segments"][1]["error_deg"] == pytest.approx(-140.0, abs=1e-9)
    assert w["n_segments"] == 2 and w["n_over_45"] == 1 and w["n_over_45_sigma_le_20"] == 1
    assert w["from"] == "waypoints" and w["north"] == "true"
    empty = HeadingScores()
    empty.open({})
    assert empty.summary() == {"heading_error": {}, "walked_direction": None}
    fixes = HeadingScores()  # IPIN's POSI fixes: latitude, longitude, floor, building
    fixes.open({"north": "magnetic", "positions": [[0.0, 45.0, 7.0, 0, 0], [20.0, 45.0, 7.001, 0, 0]]})
    fixes.estimates(_batch(t, q, np.full(len(t), 90.0), np.full(len(t), 3.0)))
    w = fixes.summary()["walked_direction"]
    assert w["from"] == "positions" and w["north"] == "magnetic" and w["n_segments"] == 1
    assert w["segments"][0]["bearing_deg"] == pytest.approx(90.0) and w["median_deg"] == pytest.approx(0.0)
