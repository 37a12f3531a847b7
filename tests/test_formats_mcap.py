"""pdr_mag's own MCAP layout: written by the sink (CDR), read back bit-exactly; the JSON layout v1; damage."""

from __future__ import annotations

import json

import numpy as np
import pytest

from replay.errors import InputError
from replay.formats import detect, read_recording
from replay.recording import Recording, Stream


def _rec(n=400, seed=0):
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.004, 0.006, n)) - 0.3  # negative times too
    tm = t[::4]
    q = rng.standard_normal((len(tm), 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q *= np.sign(q[:, :1])
    return Recording(
        mag=Stream(tm, np.array([20.0, 5.0, -40.0]) + rng.standard_normal((len(tm), 3))),
        accel=Stream(t, np.array([0.0, 0.0, 9.81]) + 0.1 * rng.standard_normal((n, 3))),
        gyro=Stream(t, 0.05 * rng.standard_normal((n, 3))),
        meta={"device": "Sim 1", "latitude_deg": 45.2, "date": "2024-01-02", "n": 3},
        truth=(tm, q),
    )


def _write(rec, path, with_t0=True):
    from pdr_mag.sinks.mcap import McapSink

    sink = McapSink(path, chunk_size=4096)
    meta = dict(rec.meta)
    if with_t0:
        meta["t0"] = rec.t0
    sink.open(meta)
    for k in ("mag", "accel", "gyro"):
        s = getattr(rec, k)
        if s is not None:
            sink.inputs(k, s.t, s.xyz)
    if rec.truth is not None:
        sink.reference("truth", *rec.truth)
    sink.close()
    return path


@pytest.mark.parametrize("with_t0", [True, False])
def test_roundtrip_bit_exact(tmp_path, with_t0):
    rec = _rec()
    f = _write(rec, tmp_path / "r.mcap", with_t0)
    assert detect(f) == "pdr-mcap"
    got = read_recording(f)
    for k in ("mag", "accel", "gyro"):
        np.testing.assert_array_equal(getattr(got, k).t, getattr(rec, k).t)
        np.testing.assert_array_equal(getattr(got, k).xyz, getattr(rec, k).xyz)
    np.testing.assert_array_equal(got.truth[0], rec.truth[0])  # exact t even where log times were clamped
    np.testing.assert_allclose(got.truth[1], rec.truth[1], atol=1e-9)
    assert got.meta["device"] == "Sim 1" and got.meta["latitude_deg"] == 45.2 and got.meta["n"] == 3
    assert got.meta["date"] == "2024-01-02" and got.dropped == {}


def test_mag_only_and_nan_dropped(tmp_path):
    rec = _rec()
    rec.accel = rec.gyro = None
    rec.truth = None
    rec.mag.xyz[5, 1] = np.nan
    got = read_recording(_write(rec, tmp_path / "m.mcap"))
    assert got.accel is None and got.truth is None
    assert len(got.mag) == len(rec.mag) - 1 and got.dropped == {"mag:nan": 1}


def test_truncated(tmp_path):
    f = _write(_rec(2000), tmp_path / "t.mcap")
    data = f.read_bytes()
    f.write_bytes(data[: len(data) * 2 // 3])
    with pytest.raises(InputError, match=r"t\.mcap: truncated or damaged MCAP"):
        read_recording(f)
    f.write_bytes(data[:40])
    with pytest.raises(InputError, match=r"t\.mcap: truncated or damaged MCAP"):
        read_recording(f)


def test_a_corrupt_compressed_chunk_is_a_damaged_file(tmp_path):
    """A chunk whose compressed bytes are damaged (zeroed in the middle of the file): the compression
    library's error becomes the damaged-MCAP InputError, not a traceback."""
    from pathlib import Path

    data = bytearray((Path(__file__).parent / "fixtures" / "pdrmcap_v2_handwritten.mcap").read_bytes())
    a = len(data) // 2
    data[a : a + 64] = bytes(64)
    f = tmp_path / "z.mcap"
    f.write_bytes(bytes(data))
    with pytest.raises(InputError, match=r"z\.mcap: truncated or damaged MCAP \(ZstdError"):
        read_recording(f)


def _raw_mcap(path, topic, payloads):
    from mcap.writer import Writer

    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start()
        sid = w.register_schema("pdr_mag.Vector3Stamped", "jsonschema", b"{}")
        cid = w.register_channel(topic, "json", sid)
        for i, p in enumerate(payloads):
            w.add_message(cid, log_time=i * 10_000_000, data=p, publish_time=i * 10_000_000)
        w.finish()
    return path


def test_no_mag_topic(tmp_path):
    f = _raw_mcap(
        tmp_path / "a.mcap", "/imu/accel", [json.dumps({"t": 0, "x": 0, "y": 0, "z": 9.8}).encode()]
    )
    with pytest.raises(InputError, match=r"without /mag/raw .*topics: /imu/accel"):
        read_recording(f)


@pytest.mark.parametrize(
    "payloads,problem",
    [
        ([b'{"t": 0, "x": 1, "y": 2, "z": -40}', b'{"t": 0.1, "x": 1, "y": "a"'], "not a valid {t, x, y, z}"),
        (
            [b'{"t": 0.1, "x": 1, "y": 2, "z": -40}', b'{"t": 0.0, "x": 1, "y": 2, "z": -40}'],
            "time goes backwards",
        ),
        ([b'{"t": 0.0, "x": 1e5, "y": 0, "z": 0}', b'{"t": 0.1, "x": 1e5, "y": 0, "z": 0}'], "wrong unit"),
    ],
)
def test_malformed_messages(tmp_path, payloads, problem):
    f = _raw_mcap(tmp_path / "b.mcap", "/mag/raw", payloads)
    with pytest.raises(InputError) as ei:
        read_recording(f)
    assert problem in ei.value.problem and "b.mcap" in ei.value.path


def test_time_from_log_time_when_no_t(tmp_path):
    f = _raw_mcap(tmp_path / "c.mcap", "/mag/raw", [b'{"x": 20, "y": 0, "z": -40}'] * 3)
    np.testing.assert_allclose(read_recording(f).mag.t, [0.0, 0.01, 0.02])


# ---------------------------------------------------------------------- format version 1 (all JSON)
def _write_v1(rec, path):
    """A file in the first layout (every topic JSON, 17 significant digits), as users may still have."""
    from mcap.writer import Writer

    def num(v):
        return None if not np.isfinite(v) else float(f"{v:.17g}")

    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start()
        w.add_metadata("recording", {k: json.dumps(v) for k, v in rec.meta.items()})
        sid = w.register_schema("pdr_mag.Vector3Stamped", "jsonschema", b"{}")
        pid = w.register_schema("foxglove.PoseInFrame", "jsonschema", b"{}")
        hid = w.register_schema("pdr_mag.HeadingReference", "jsonschema", b"{}")
        offset = {"time_offset_ns": "1000000000"}
        for kind, topic in (("mag", "/mag/raw"), ("accel", "/imu/accel"), ("gyro", "/imu/gyro")):
            cid = w.register_channel(topic, "json", sid, offset)
            s = getattr(rec, kind)
            for t, (x, y, z) in zip(s.t, s.xyz, strict=True):
                ns = round(t * 1e9) + 1_000_000_000
                d = {"t": num(t), "x": num(x), "y": num(y), "z": num(z)}
                w.add_message(cid, log_time=ns, data=json.dumps(d).encode(), publish_time=ns)
        c_pose = w.register_channel("/reference/truth/orientation", "json", pid, offset)
        c_head = w.register_channel("/reference/truth/heading", "json", hid, offset)
        for t, q in zip(*rec.truth, strict=True):
            ns = round(t * 1e9) + 1_000_000_000
            o = dict(zip("wxyz", map(float, q), strict=True))
            pose = {
                "timestamp": {"sec": ns // 10**9, "nsec": ns % 10**9},
                "frame_id": "enu",
                "pose": {"position": {"x": 0, "y": 0, "z": 0}, "orientation": o},
            }
            w.add_message(c_pose, log_time=ns, data=json.dumps(pose).encode(), publish_time=ns)
            w.add_message(
                c_head,
                log_time=ns,
                data=json.dumps({"t": float(t), "heading_deg": 1.0}).encode(),
                publish_time=ns,
            )
        w.finish()
    return path


def test_reads_the_json_layout_of_format_version_1(tmp_path):
    rec = _rec()
    f = _write_v1(rec, tmp_path / "v1.mcap")
    assert detect(f) == "pdr-mcap"
    got = read_recording(f)
    for k in ("mag", "accel", "gyro"):
        np.testing.assert_array_equal(getattr(got, k).t, getattr(rec, k).t)
        np.testing.assert_array_equal(getattr(got, k).xyz, getattr(rec, k).xyz)
    np.testing.assert_array_equal(got.truth[0], rec.truth[0])
    np.testing.assert_array_equal(got.truth[1], rec.truth[1])
    assert got.meta == rec.meta


def test_both_layouts_give_the_same_recording(tmp_path):
    rec = _rec(seed=3)
    a = read_recording(_write(rec, tmp_path / "v2.mcap"))
    b = read_recording(_write_v1(rec, tmp_path / "v1.mcap"))
    for k in ("mag", "accel", "gyro"):
        np.testing.assert_array_equal(getattr(a, k).t, getattr(b, k).t)
        np.testing.assert_array_equal(getattr(a, k).xyz, getattr(b, k).xyz)
    np.testing.assert_array_equal(a.truth[0], b.truth[0])
    np.testing.assert_array_equal(a.truth[1], b.truth[1])


def _cdr_mcap(path, payloads):
    from mcap.writer import Writer

    from pdr_mag.sinks._mcap_schemas import SCHEMAS

    spec = SCHEMAS["vector3"]
    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start()
        sid = w.register_schema(spec.name, spec.encoding, spec.text.encode())
        cid = w.register_channel("/mag/raw", "cdr", sid)
        for i, p in enumerate(payloads):
            w.add_message(cid, log_time=i * 10_000_000, data=p, publish_time=i * 10_000_000)
        w.finish()
    return path


def test_cdr_big_endian_and_malformed(tmp_path):
    import struct

    le = [b"\x00\x01\x00\x00" + struct.pack("<4d", 0.01 * i, 20.0, 5.0, -40.0) for i in range(5)]
    be = [b"\x00\x00\x00\x00" + struct.pack(">4d", 0.05 + 0.01 * i, 21.0, 5.0, -40.0) for i in range(3)]
    got = read_recording(_cdr_mcap(tmp_path / "ok.mcap", le + be))
    np.testing.assert_array_equal(
        got.mag.t, [0.01 * i for i in range(5)] + [0.05 + 0.01 * i for i in range(3)]
    )
    np.testing.assert_array_equal(got.mag.xyz[:, 0], [20.0] * 5 + [21.0] * 3)

    with pytest.raises(InputError, match=r"/mag/raw: a CDR message of 35 bytes, expected 36"):
        read_recording(_cdr_mcap(tmp_path / "short.mcap", [le[0], le[1][:35]]))
    with pytest.raises(InputError, match=r"/mag/raw: a message that is not CDR"):
        read_recording(_cdr_mcap(tmp_path / "enc.mcap", [le[0], b"\x00\x03" + le[1][2:]]))
    with pytest.raises(InputError, match="time goes backwards"):
        read_recording(_cdr_mcap(tmp_path / "back.mcap", [le[3], le[1]]))
