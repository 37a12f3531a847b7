"""McapSink: write synthetic inputs and estimates, read them back with mcap's own reader.

CDR messages are decoded with mcap-ros2-support's decoder (what a ROS 2 tool would see), JSON messages with
``json``.  ``fixtures/pdrmcap_v2_handwritten.mcap`` holds the messages of :func:`_fixed_calls` as written by
a CDR encoder independent of mcap-ros2-support (numpy structured arrays, format version 2): the sink must
write the same bytes, and the reader must read that file.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import NonSeekingReader, make_reader
from mcap_ros2.decoder import DecoderFactory

from pdr_mag.calibration.model import MagCalibration
from pdr_mag.conventions import heading_deg_from_quat
from pdr_mag.estimates import DIAG_KEYS, EstimateBatch, Event
from pdr_mag.sinks._mcap_schemas import DIAG_FIELDS
from pdr_mag.sinks.mcap import INPUT_TOPICS, SCHEMAS, McapSink

ROOT = Path(__file__).resolve().parent.parent
FIXTURE = ROOT / "tests" / "fixtures" / "pdrmcap_v2_handwritten.mcap"


def _unit_quats(rng, n):
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1)[:, None]
    return q * np.where(q[:, :1] < 0, -1.0, 1.0)


def _batch(rng, t):
    n = len(t)
    diag = {k: rng.normal(40.0, 5.0, n) for k in DIAG_KEYS}
    diag["dip_deg"][::5] = np.nan
    return EstimateBatch(
        t=t,
        q_wd=_unit_quats(rng, n),
        heading_deg=rng.uniform(0, 360, n),
        heading_std_deg=rng.uniform(0.5, 5, n),
        mag_used=rng.random(n) < 0.5,
        interference=rng.random(n) < 0.2,
        cal_state=np.array(["none", "offset", "ellipsoid"])[rng.integers(0, 3, n)],
        diag=diag,
    )


@pytest.fixture
def written(tmp_path):
    """A file written in several chunks of each kind, with irregular, non-round times."""
    rng = np.random.default_rng(5)
    path = tmp_path / "out.mcap"
    sink = McapSink(path, chunk_size=64 * 1024)  # small chunks: many chunks even for a short test
    inputs = {k: ([], []) for k in INPUT_TOPICS}
    batches = []
    sink.open({"device": "synthetic", "north": "magnetic", "field_uT": 48.5, "latitude_deg": 52.1})
    t_start = 1234.5678901
    for c in range(6):
        for kind, rate in (("accel", 200.0), ("gyro", 200.0), ("mag", 50.0)):
            n = int(rate * 2)
            t = t_start + 2.0 * c + np.sort(rng.uniform(0, 2.0, n))
            xyz = rng.normal(0, 30, (n, 3)) * rng.choice([1e-7, 1.0, 1e5], (n, 1))
            sink.inputs(kind, t, xyz)
            inputs[kind][0].append(t)
            inputs[kind][1].append(xyz)
            if kind == "mag":
                sink.mag_calibrated(t, xyz - 1.0)
        tb = t_start + 2.0 * c + np.arange(400) / 200.0
        b = _batch(rng, tb)
        for axis in "xyz":  # the filter's offset error: an internal column of the pipeline's rows
            b.diag[f"mag_offset_error_{axis}"] = rng.normal(0.0, 2.0, len(tb))
        sink.estimates(b)
        batches.append(b)
    tr = t_start + np.arange(2400) / 200.0
    q_truth = _unit_quats(rng, len(tr))
    sink.reference("truth", tr, q_truth)
    sink.event(Event(t_start + 3.0, "interference_start", {"score": np.float64(1.7), "axis": "strength"}))
    sink.event(Event(t_start + 4.0, "interference_end"))
    cal = MagCalibration.from_arrays([10.0, -5.0, 3.0], np.diag([1.1, 0.9, 1.0]), field_uT=48.2, method="ml")
    sink.calibration(t_start + 1.5, cal)
    sink.close()
    return {
        "path": path,
        "inputs": {k: (np.concatenate(v[0]), np.concatenate(v[1])) for k, v in inputs.items()},
        "batch": EstimateBatch.concat(batches),
        "truth": (tr, q_truth),
        "cal": cal,
        "sink": sink,
    }


def _plain(obj):
    """A decoded ROS 2 message (mcap_ros2's dynamic classes) as nested dicts."""
    if hasattr(obj, "__slots__") and hasattr(obj, "_type"):
        return {k: _plain(getattr(obj, k)) for k in obj.__slots__}
    return obj


def _messages(path, topic):
    """``(log_time, publish_time, message as dict)``: CDR through mcap_ros2's decoder, JSON through json."""
    out = []
    with open(path, "rb") as f:
        r = make_reader(f, validate_crcs=True, decoder_factories=[DecoderFactory()])
        summary = r.get_summary()
        encodings = {c.topic: c.message_encoding for c in summary.channels.values()}
        if encodings.get(topic) == "cdr":
            for _, _, m, d in r.iter_decoded_messages(topics=[topic]):
                out.append((m.log_time, m.publish_time, _plain(d)))
            return out
        for _, _, m in r.iter_messages(topics=[topic]):
            out.append((m.log_time, m.publish_time, json.loads(m.data)))
    return out


def test_topics_schemas_and_counts(written):
    with open(written["path"], "rb") as f:
        r = make_reader(f, validate_crcs=True)
        summary = r.get_summary()
    topics = {c.topic: c for c in summary.channels.values()}
    expected = {
        "/imu/accel": "vector3",
        "/imu/gyro": "vector3",
        "/mag/raw": "vector3",
        "/mag/calibrated": "vector3",
        "/pdr/orientation": "pose",
        "/pdr/heading": "heading",
        "/pdr/diag": "diag",
        "/pdr/offset_error": "vector3",
        "/pdr/calibration": "calibration",
        "/pdr/events": "log",
        "/reference/truth/orientation": "pose",
        "/reference/truth/heading": "heading_ref",
    }
    assert set(topics) == set(expected)
    for topic, key in expected.items():
        ch = topics[topic]
        schema = summary.schemas[ch.schema_id]
        spec = SCHEMAS[key]
        assert (schema.name, schema.encoding, schema.data) == (spec.name, spec.encoding, spec.text.encode())
        assert ch.message_encoding == spec.message_encoding
        # what Foxglove decodes natively, without a ROS install
        assert (schema.encoding, ch.message_encoding) in (("ros2msg", "cdr"), ("jsonschema", "json"))
    high_rate = [t for t in expected if not t.startswith(("/pdr/events", "/pdr/calibration"))]
    assert all(topics[t].message_encoding == "cdr" for t in high_rate)
    assert summary.schemas[topics["/pdr/orientation"].schema_id].name == "foxglove_msgs/msg/PoseInFrame"
    counts = {
        topics_by_id.topic: n
        for topics_by_id, n in (
            (summary.channels[i], n) for i, n in summary.statistics.channel_message_counts.items()
        )
    }
    n_est = len(written["batch"])
    assert counts["/imu/accel"] == len(written["inputs"]["accel"][0])
    assert counts["/mag/raw"] == counts["/mag/calibrated"] == len(written["inputs"]["mag"][0])
    assert counts["/pdr/orientation"] == counts["/pdr/heading"] == counts["/pdr/diag"] == n_est
    assert counts["/pdr/offset_error"] == n_est
    assert counts["/pdr/events"] == 2 and counts["/pdr/calibration"] == 1
    assert summary.statistics.message_count == sum(counts.values())
    assert summary.statistics.chunk_count > 10  # streamed in many bounded chunks
    # all messages readable when streaming the file front to back (no summary used)
    with open(written["path"], "rb") as f:
        n_stream = sum(1 for _ in NonSeekingReader(f, validate_crcs=True).iter_messages())
    assert n_stream == summary.statistics.message_count


def test_inputs_read_back_bit_exact_with_ns_log_times(written):
    for kind, topic in INPUT_TOPICS.items():
        t, xyz = written["inputs"][kind]
        msgs = sorted(_messages(written["path"], topic), key=lambda m: m[2]["t"])
        t_back = np.array([m[2]["t"] for m in msgs])
        xyz_back = np.array([[m[2]["x"], m[2]["y"], m[2]["z"]] for m in msgs])
        order = np.argsort(t, kind="stable")
        np.testing.assert_array_equal(t_back, t[order])  # bit-exact, not approximately
        np.testing.assert_array_equal(xyz_back, xyz[order])
        log_times = np.array([m[0] for m in msgs])
        np.testing.assert_array_equal(log_times, np.round(t[order] * 1e9).astype(np.int64))
        assert all(m[0] == m[1] for m in msgs)


def test_outputs_values(written):
    """Outputs decoded by mcap_ros2 equal what was written, bit for bit (CDR float64)."""
    b = written["batch"]
    heading = _messages(written["path"], "/pdr/heading")
    assert [m[2]["t"] for m in heading] == b.t.tolist()
    np.testing.assert_array_equal([m[2]["heading_deg"] for m in heading], b.heading_deg)
    np.testing.assert_array_equal([m[2]["heading_std_deg"] for m in heading], b.heading_std_deg)
    assert [m[2]["mag_used"] for m in heading] == b.mag_used.tolist()
    assert [m[2]["interference"] for m in heading] == b.interference.tolist()
    assert [m[2]["cal_state"] for m in heading] == b.cal_state.tolist()  # variable-length CDR strings

    pose = _messages(written["path"], "/pdr/orientation")
    q = np.array([[p["pose"]["orientation"][k] for k in "wxyz"] for _, _, p in pose])
    np.testing.assert_array_equal(q, b.q_wd)
    for log_time, _, p in pose:
        assert p["frame_id"] == "enu" and p["pose"]["position"] == {"x": 0.0, "y": 0.0, "z": 0.0}
        assert p["timestamp"]["sec"] * 1_000_000_000 + p["timestamp"]["nanosec"] == log_time

    diag = _messages(written["path"], "/pdr/diag")
    assert set(diag[0][2]) == {"t", *DIAG_FIELDS.values()}
    for key, field in DIAG_FIELDS.items():
        if key in DIAG_KEYS:
            np.testing.assert_array_equal([m[2][field] for m in diag], b.diag[key])  # NaN stays NaN
    upper = np.array([m[2]["strength_upper_ut"] for m in diag])
    np.testing.assert_array_equal(upper, b.diag["field_ref_uT"] + b.diag["strength_tol_uT"])
    lower = np.array([m[2]["dip_lower_deg"] for m in diag])
    np.testing.assert_array_equal(lower, b.diag["dip_ref_deg"] - b.diag["dip_tol_deg"])
    offset = _messages(written["path"], "/pdr/offset_error")  # the filter's offset error, µT
    np.testing.assert_array_equal([m[2]["t"] for m in offset], b.t)
    for axis in "xyz":
        np.testing.assert_array_equal([m[2][axis] for m in offset], b.diag[f"mag_offset_error_{axis}"])

    tr, q_truth = written["truth"]
    ref = _messages(written["path"], "/reference/truth/heading")
    np.testing.assert_array_equal([m[2]["t"] for m in ref], tr)
    np.testing.assert_array_equal([m[2]["heading_deg"] for m in ref], heading_deg_from_quat(q_truth))
    pose = _messages(written["path"], "/reference/truth/orientation")
    np.testing.assert_array_equal(
        [[p["pose"]["orientation"][k] for k in "wxyz"] for _, _, p in pose], q_truth
    )


def test_cdr_vector3_layout(written):
    """The documented 36-byte layout: CDR_LE header, then float64 t, x, y, z (readers rely on it)."""
    t, xyz = written["inputs"]["gyro"]
    with open(written["path"], "rb") as f:
        data = [
            m.data for _, _, m in make_reader(f).iter_messages(topics=["/imu/gyro"], log_time_order=False)
        ]
    assert {len(d) for d in data} == {36} and {d[:4] for d in data} == {b"\x00\x01\x00\x00"}
    rows = np.frombuffer(b"".join(d[4:] for d in data), dtype="<f8").reshape(-1, 4)
    np.testing.assert_array_equal(rows[:, 0], t)
    np.testing.assert_array_equal(rows[:, 1:], xyz)


def test_long_and_unusual_cal_state_strings(tmp_path):
    rng = np.random.default_rng(8)
    b = _batch(rng, np.arange(50) / 50.0)
    b.cal_state = np.array(["", "x", "recalibrating_after_interference", "ellipsoid", "none"] * 10)
    p = tmp_path / "s.mcap"
    with McapSink(p) as sink:
        sink.open({})
        sink.estimates(b)
    got = _messages(p, "/pdr/heading")
    assert [m[2]["cal_state"] for m in got] == b.cal_state.tolist()
    np.testing.assert_array_equal([m[2]["heading_deg"] for m in got], b.heading_deg)


def test_events_calibration_and_metadata(written):
    events = _messages(written["path"], "/pdr/events")
    assert [e[2]["level"] for e in events] == [3, 2]  # WARNING, INFO
    assert events[0][2]["message"].startswith("interference_start")
    assert '"score": 1.7' in events[0][2]["message"]
    assert events[0][2]["name"] == "pdr_mag"
    cal_msgs = _messages(written["path"], "/pdr/calibration")
    assert len(cal_msgs) == 1
    back = MagCalibration.from_dict({k: v for k, v in cal_msgs[0][2].items() if k != "t"})
    assert back.to_dict() == written["cal"].to_dict()

    with open(written["path"], "rb") as f:
        meta = {}
        for m in make_reader(f).iter_metadata():
            meta.setdefault(m.name, []).append(dict(m.metadata))
    assert set(meta) == {"recording", "calibration", "pdr_mag"}
    rec = meta["recording"][0]
    assert {k: json.loads(v) for k, v in rec.items()} == {
        "device": "synthetic",
        "north": "magnetic",
        "field_uT": 48.5,
        "latitude_deg": 52.1,
    }
    assert json.loads(meta["calibration"][0]["json"]) == written["cal"].to_dict()
    info = meta["pdr_mag"][0]
    assert info["time_offset_ns"] == "0" and info["clamped_log_times"] == "0"
    assert json.loads(info["message_counts"]) == written["sink"].counts
    assert json.loads(info["rate_limit_hz"]) is None


def test_negative_times_offset_and_clamp(tmp_path):
    p = tmp_path / "neg.mcap"
    sink = McapSink(p, compression="lz4")
    sink.open({"t0": -2.5})
    sink.inputs("mag", np.array([-2.5, -1.0, 0.25]), np.zeros((3, 3)))
    sink.close()
    msgs = _messages(p, "/mag/raw")
    assert [m[0] for m in msgs] == [500_000_000, 2_000_000_000, 3_250_000_000]  # offset 3 s
    assert [m[2]["t"] for m in msgs] == [-2.5, -1.0, 0.25]

    # without meta t0, the first time seen decides; anything earlier still is clamped to 0 and counted
    p2 = tmp_path / "neg2.mcap"
    sink = McapSink(p2, compression="none")
    sink.open({})
    sink.inputs("gyro", np.array([-0.4, 0.0]), np.ones((2, 3)))
    sink.inputs("accel", np.array([-7.0, -0.2]), np.ones((2, 3)))
    sink.close()
    assert sink.time_offset_ns == 1_000_000_000
    assert [m[0] for m in _messages(p2, "/imu/accel")] == [0, 800_000_000]
    with open(p2, "rb") as f:
        info = [dict(m.metadata) for m in make_reader(f).iter_metadata() if m.name == "pdr_mag"][0]
    assert info["clamped_log_times"] == "1" and info["time_offset_ns"] == "1000000000"


def test_bad_arguments(tmp_path):
    with pytest.raises(ValueError, match="compression"):
        McapSink(tmp_path / "x.mcap", compression="gzip")
    sink = McapSink(tmp_path / "y.mcap")
    with pytest.raises(RuntimeError, match="open"):
        sink.inputs("mag", np.zeros(1), np.zeros((1, 3)))
    sink.open({})
    with pytest.raises(ValueError, match="kind"):
        sink.inputs("baro", np.zeros(1), np.zeros((1, 3)))
    sink.close()
    for bad in (0.0, -5.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="rate_hz"):
            McapSink(tmp_path / "z.mcap", rate_hz=bad)


# ---------------------------------------------------------------- the same bytes as an independent encoder
_N = 400  # samples at 200 Hz: 2 s
_EXACT_QUATS = np.array(
    [
        [1.0, 0.0, 0.0, 0.0],
        [0.6, 0.8, 0.0, 0.0],
        [0.8, 0.0, 0.0, 0.6],
        [0.5, 0.5, 0.5, 0.5],
        [0.0, 0.6, 0.0, 0.8],
    ]
)


def _fixed_calls(sink) -> None:
    """A fixed sequence of sink calls on every topic, negative times included.

    Values use exact arithmetic only (no libm), so every machine gives the same bits; the reference heading
    (``atan2``) is the one value that may differ in its last bit.
    """
    k = np.arange(_N)
    kf = k.astype(float)
    t = -0.5 + kf / 200.0
    states = np.array(["none", "offset", "ellipsoid"])
    sink.open({"device": "fixture", "t0": -0.5, "north": "true", "latitude_deg": 45.25})
    for s in (slice(0, 160), slice(160, 320), slice(320, _N)):  # several calls per topic
        ts, ks = t[s], kf[s]
        sink.inputs("accel", ts, np.column_stack([ks / 64, -ks / 128, 9.75 + ks / 1024]))
        sink.inputs("gyro", ts, np.column_stack([ks / 4096, 0.125 - ks / 8192, ks * ks / 2**20]))
        sink.inputs(
            "mag", ts[::2], np.column_stack([20.5 + ks[::2] / 16, -5.0 + ks[::2] / 32, -40.0 * ks[::2] / 512])
        )
        sink.mag_calibrated(ts[::2], np.column_stack([ks[::2] / 16, ks[::2] / 32, -ks[::2] / 20]))
        e = k[s][::4]
        diag = {key: e * (j + 1) / 8.0 for j, key in enumerate(DIAG_KEYS) if key != "coverage"}
        diag["dip_deg"] = np.where(e % 12 == 0, np.nan, diag["dip_deg"])
        sink.estimates(
            EstimateBatch(
                t=t[e],
                q_wd=_EXACT_QUATS[e % 5],
                heading_deg=e * 0.5,
                heading_std_deg=1.0 + e / 256,
                mag_used=e % 3 == 0,
                interference=e % 7 == 0,
                cal_state=states[e % 3],
                diag=diag,
            )
        )
    sink.reference("truth", t[::8], _EXACT_QUATS[k[::8] % 5])
    sink.event(Event(0.25, "interference_start", {"score": 1.75, "axis": "strength"}))
    sink.event(Event(1.5, "interference_end"))
    sink.calibration(
        -0.25, MagCalibration.from_arrays([10.0, -5.0, 3.0], np.diag([1.25, 0.75, 1.0]), field_uT=48.0)
    )
    sink.close()


def _content(path):
    """Messages ``(topic, log_time, data)`` in file order and metadata records of an MCAP file."""
    with open(path, "rb") as f:
        r = make_reader(f, validate_crcs=True)
        msgs = [(c.topic, m.log_time, m.data) for _, c, m in r.iter_messages(log_time_order=False)]
    with open(path, "rb") as f:
        meta = [(m.name, dict(m.metadata)) for m in make_reader(f).iter_metadata()]
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    channels = {
        c.topic: (summary.schemas[c.schema_id].name, c.message_encoding, c.metadata)
        for c in summary.channels.values()
    }
    return msgs, meta, channels


def test_same_messages_as_the_independent_cdr_encoder(tmp_path):
    """The sink writes, message for message, the bytes of the numpy CDR encoder of the fixture."""
    p = tmp_path / "new.mcap"
    _fixed_calls(McapSink(p, chunk_size=16 * 1024))
    new_msgs, new_meta, new_channels = _content(p)
    old_msgs, old_meta, old_channels = _content(FIXTURE)
    assert new_channels == old_channels
    by_topic = {}
    for topic, log_time, data in old_msgs:
        by_topic.setdefault(topic, []).append((log_time, data))
    n_compared = 0
    for topic, expected in by_topic.items():
        got = [(lt, d) for tp, lt, d in new_msgs if tp == topic]
        assert [g[0] for g in got] == [e[0] for e in expected], topic
        if topic.endswith("/heading") and topic.startswith("/reference/"):  # atan2: to the last bit or so
            a = np.frombuffer(b"".join(d[4:] for _, d in got), "<f8")
            b = np.frombuffer(b"".join(d[4:] for _, d in expected), "<f8")
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)
        else:
            assert [g[1] for g in got] == [e[1] for e in expected], topic
        n_compared += len(got)
    assert n_compared == len(new_msgs) > 1500
    old_info, new_info = dict(old_meta).pop("pdr_mag"), dict(new_meta).pop("pdr_mag")
    assert [m for m in new_meta if m[0] != "pdr_mag"] == [m for m in old_meta if m[0] != "pdr_mag"]
    assert json.loads(new_info.pop("rate_limit_hz")) is None
    assert new_info == old_info and old_info["time_offset_ns"] == "1000000000"


def test_reads_the_files_of_the_independent_cdr_encoder():
    """A format-version-2 file written by the numpy encoder reads as what :func:`_fixed_calls` gave it."""
    from replay.formats import read_recording

    got = read_recording(FIXTURE)
    assert got.format == "pdr-mcap"
    t = -0.5 + np.arange(_N) / 200.0
    kf = np.arange(float(_N))
    np.testing.assert_array_equal(got.accel.t, t)
    np.testing.assert_array_equal(got.accel.xyz, np.column_stack([kf / 64, -kf / 128, 9.75 + kf / 1024]))
    np.testing.assert_array_equal(got.mag.t, t[::2])
    np.testing.assert_array_equal(got.truth[0], t[::8])
    np.testing.assert_array_equal(got.truth[1], _EXACT_QUATS[np.arange(0, _N, 8) % 5])
    assert got.meta["device"] == "fixture" and got.meta["latitude_deg"] == 45.25 and got.dropped == {}


# ---------------------------------------------------------------------- rate limit
def test_rate_limit_keeps_the_first_message_of_each_interval(tmp_path):
    p = tmp_path / "r.mcap"
    _fixed_calls(McapSink(p, rate_hz=4.0))
    msgs, meta, _ = _content(p)
    t = -0.5 + np.arange(_N) / 200.0  # sample k at 200 Hz over 2 s; the 0.25-s intervals start at k = 50 j

    def first_per_interval(step):  # a topic with a sample every `step` k: the first one at or after 50 j
        return t[np.ceil(50 * np.arange(8) / step).astype(int) * step]

    expected = {
        "/imu/accel": t[::50],
        "/imu/gyro": t[::50],
        "/mag/raw": t[::50],
        "/mag/calibrated": t[::50],
        "/pdr/orientation": first_per_interval(4),
        "/pdr/heading": first_per_interval(4),
        "/pdr/diag": first_per_interval(4),
        "/reference/truth/orientation": first_per_interval(8),
        "/reference/truth/heading": first_per_interval(8),
    }
    by_topic = {}
    for topic, log_time, _data in msgs:
        by_topic.setdefault(topic, []).append(log_time)
    for topic, t_kept in expected.items():
        assert by_topic[topic] == (np.round(t_kept * 1e9).astype(np.int64) + 1_000_000_000).tolist(), topic
    assert len(by_topic["/pdr/events"]) == 2 and len(by_topic["/pdr/calibration"]) == 1  # never limited
    info = dict(meta)["pdr_mag"]
    assert json.loads(info["rate_limit_hz"]) == 4.0
    assert json.loads(info["message_counts"])["/imu/accel"] == 8

    from replay.formats import read_recording

    got = read_recording(p)  # still a readable recording, at the lower rate
    np.testing.assert_array_equal(got.accel.t, t[::50])


# ---------------------------------------------------------------------- replay round trip
def test_replaying_the_mcap_reproduces_the_outputs(tmp_path):
    """``replay rec --mcap a.mcap --out-csv 1.csv`` then ``replay a.mcap --out-csv 2.csv``: identical CSV."""
    from replay import run
    from replay.formats import read_recording

    rec = ROOT / "recordings" / "mixed"
    a, csv1, csv2 = tmp_path / "a.mcap", tmp_path / "1.csv", tmp_path / "2.csv"
    run.replay(rec, sinks=[McapSink(a), run.CsvSink(csv1)], progress=False)
    again = read_recording(a)  # replay/formats/pdrmcap.py
    assert again.format == "pdr-mcap"
    run.replay(again, sinks=[run.CsvSink(csv2)], progress=False)
    first, second = csv1.read_bytes(), csv2.read_bytes()
    assert first.count(b"\n") > 1000
    assert first == second


def test_cli_replay_of_the_written_mcap_gives_the_same_csv(tmp_path):
    """``pdr-mag replay REC --mcap a.mcap --out-csv 1.csv``; ``pdr-mag replay a.mcap --out-csv 2.csv``."""
    from replay import cli

    rec = ROOT / "recordings" / "mixed"
    a, csv1, csv2 = tmp_path / "a.mcap", tmp_path / "1.csv", tmp_path / "2.csv"
    assert cli.main(["replay", str(rec), "--mcap", str(a), "--out-csv", str(csv1), "-q"]) == 0
    assert cli.main(["replay", str(a), "--out-csv", str(csv2), "-q"]) == 0
    first = csv1.read_bytes()
    assert first.count(b"\n") > 1000
    assert first == csv2.read_bytes()


def test_a_channel_going_back_in_time_reads_in_log_time_order(tmp_path):
    """A caller may hand a channel earlier times later (not the replay): the file reads in log-time order."""
    p = tmp_path / "unsorted.mcap"
    with McapSink(p, chunk_size=1 << 16) as sink:
        sink.open({})
        sink.inputs("mag", 10.0 + np.arange(100) / 100, np.ones((100, 3)))
        sink.inputs("mag", 5.0 + np.arange(100) / 100, np.ones((100, 3)))
        sink.inputs("mag", 10.0 + np.arange(100) / 100, np.ones((100, 3)))  # repeated times: ties
    with open(p, "rb") as f:
        t = [m.log_time for _, _, m in make_reader(f, validate_crcs=True).iter_messages(log_time_order=True)]
    assert t == sorted(t) and len(t) == 300 and t[0] == 5_000_000_000


def test_cli_mcap_rate(tmp_path, capsys):
    """``pdr-mag replay REC --mcap a.mcap --mcap-rate 5``: each high-rate topic ≤ 5 messages a second."""
    from replay import cli

    rec, a = ROOT / "recordings" / "mixed", tmp_path / "a.mcap"
    assert cli.main(["replay", str(rec), "--mcap", str(a), "--mcap-rate", "5", "-q"]) == 0
    msgs, meta, channels = _content(a)
    info = dict(meta)["pdr_mag"]
    assert json.loads(info["rate_limit_hz"]) == 5.0
    counts = json.loads(info["message_counts"])
    for topic, (_, encoding, _) in channels.items():
        if encoding != "cdr":
            continue
        bins = [lt // 200_000_000 for tp, lt, _ in msgs if tp == topic]  # 0.2-s intervals (time offset 0)
        assert len(bins) == len(set(bins)) == counts[topic] > 50, topic
    assert cli.main(["replay", str(rec), "--mcap", str(a), "--mcap-rate", "0", "-q"]) == 2
    assert cli.main(["replay", str(rec), "--mcap-rate", "5", "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "--mcap-rate" in err[0] and "--mcap-rate needs --mcap" in err[1]
