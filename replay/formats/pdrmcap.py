"""pdr_mag's own MCAP layout — what ``pdr-mag replay --mcap`` writes (:mod:`pdr_mag.sinks.mcap`).

The layout is defined once, in the sink's module docstring; this reader needs only part of it:

=================================  ===================================  =====================================
topic                              schema (format version 2, current)   message
=================================  ===================================  =====================================
``/mag/raw``                       ``pdr_mag/msg/Vector3Stamped`` CDR   ``float64 t, x, y, z``, raw µT, device
``/imu/accel``                     ``pdr_mag/msg/Vector3Stamped`` CDR   m/s², specific force, device frame
``/imu/gyro``                      ``pdr_mag/msg/Vector3Stamped`` CDR   rad/s, device frame
``/reference/truth/orientation``   ``foxglove_msgs/msg/PoseInFrame``    device → ENU (optional) → ``truth``
``/reference/truth/heading``       ``pdr_mag/msg/HeadingReference``     its exact ``t`` (same order as poses)
=================================  ===================================  =====================================

Files written before the CDR layout (format version 1, still in users' hands) are read too: the same topics
as JSON (``message_encoding="json"``): ``pdr_mag.Vector3Stamped`` ``{"t", "x", "y", "z"}`` (17 significant
digits), ``foxglove.PoseInFrame`` and ``pdr_mag.HeadingReference`` ``{"t", "heading_deg"}``; there a message
without ``t`` falls back to its ``log_time`` minus the channel's ``time_offset_ns``, and ``null`` is NaN.
Each topic is decoded by its own channel's encoding, so either layout (or a mix) reads.  A file written
with a rate limit (``rate_limit_hz`` in the ``pdr_mag`` metadata record) reads the same way, with its
decimated streams.

``t`` is the sample time as float64, so the streams read back bit-identical to what was written.  NaN
values are dropped as ``<stream>:nan``, a JSON sample with a value that is not a number (nor ``null``) as
``<stream>:non_numeric``.  The metadata record ``recording`` becomes ``Recording.meta``
(values JSON-decoded where they are JSON, else kept as strings).  ``/mag/raw`` is required; the other
topics are optional.  The file is read twice, front to back (mcap's reader decompresses one chunk at a
time): first the truth topics (loaded whole, for evaluation), then the sensor topics, streamed; CDR messages
are decoded in blocks with numpy.

The ``recording`` metadata holds the meta of the recording the MCAP was written from, so what that file
stated about the phone (``mag_os_bias_uT`` and its ``…_changes``, ``gyro_os_bias_rad_s``,
``mag_os_calibrated``, ``gyro_os_calibrated``, ``date``, ``device_id``, …: INTERFACE.md) comes back as it
was (JSON numbers: the same floats); nothing is added.
"""

from __future__ import annotations

import json
import struct
from collections import Counter
from pathlib import Path

import numpy as np

from replay.errors import InputError
from replay.formats import _common, _mcap
from replay.formats._common import NON_NUMERIC, StreamBuilder, StreamSpec, chunks_of
from replay.recording import Recording
from replay.source import Feed, RecordingSource

NAME = "pdr-mcap"
TOPICS = {"/mag/raw": "mag", "/imu/accel": "accel", "/imu/gyro": "gyro"}
TRUTH_TOPIC = "/reference/truth/orientation"
TRUTH_T_TOPIC = "/reference/truth/heading"  # same messages' exact "t", in the same order
_UNITS = {"mag": "µT", "accel": "m/s²", "gyro": "rad/s"}
VECTOR3_CDR = "pdr_mag/msg/Vector3Stamped"
#: CDR message sizes: encapsulation header (4 bytes) + float64 fields
_V3_SIZE, _REF_SIZE = 4 + 32, 4 + 16
_CDR_LE, _CDR_BE = b"\x00\x01\x00\x00", b"\x00\x00\x00\x00"


def detect(path: Path) -> bool:
    if not _mcap.is_mcap(path):
        return False
    channels, _ = _mcap.scan(path)
    return any(
        c.topic == "/mag/raw"
        and (c.message_encoding == "json" or (c.message_encoding == "cdr" and c.schema_name == VECTOR3_CDR))
        for c in channels
    )


def _meta(path: Path) -> dict:
    from mcap.reader import make_reader

    meta: dict = {}
    with path.open("rb") as fh:
        try:
            for rec in make_reader(fh).iter_metadata():
                if rec.name != "recording":
                    continue
                for k, v in rec.metadata.items():
                    try:
                        meta[k] = json.loads(v)
                    except (json.JSONDecodeError, TypeError):
                        meta[k] = v
        except _mcap.read_errors() as exc:
            raise InputError(path, _mcap.damaged(exc)) from None
    return meta


def _num(v) -> float:
    return float("nan") if v is None else float(v)


def _json_numbers(values) -> list[float] | None:
    """JSON values as floats (``null``: NaN), or None when one is not a JSON number (a string, a bool, …)."""
    if all(v is None or (isinstance(v, (int, float)) and not isinstance(v, bool)) for v in values):
        return [_num(v) for v in values]
    return None


def _floats(path: Path, topic: str, payloads: list[bytes], size: int) -> np.ndarray:
    """The float64 fields of fixed-size CDR messages (``size`` bytes each), one row a message."""
    blob = b"".join(payloads)
    if len(blob) != size * len(payloads) or any(len(p) != size for p in payloads):
        bad = next(i for i, p in enumerate(payloads) if len(p) != size)
        raise InputError(path, f"{topic}: a CDR message of {len(payloads[bad])} bytes, expected {size}")
    u8 = np.frombuffer(blob, dtype=np.uint8).reshape(len(payloads), size)
    head = u8[:, :4]
    le = np.all(head == np.frombuffer(_CDR_LE, np.uint8), axis=1)
    be = np.all(head == np.frombuffer(_CDR_BE, np.uint8), axis=1)
    if not np.all(le | be):
        raise InputError(
            path, f"{topic}: a message that is not CDR (encapsulation {bytes(head[~(le | be)][0])!r})"
        )
    body = np.ascontiguousarray(u8[:, 4:])
    out = body.view("<f8").copy()
    if be.any():
        out[be] = body[be].view(">f8")
    return out


def _pose_cdr(data: bytes) -> tuple[int, list[float]]:
    """Timestamp (ns) and orientation (w, x, y, z) of a foxglove_msgs/msg/PoseInFrame CDR message."""
    if data[:4] not in (_CDR_LE, _CDR_BE):
        raise ValueError(f"not CDR (encapsulation {data[:4]!r})")
    e = "<" if data[:4] == _CDR_LE else ">"
    sec, nsec, n_frame = struct.unpack_from(e + "iII", data, 4)
    pos = 16 + n_frame
    pos += -(pos - 4) % 8  # float64 alignment, counted after the encapsulation header
    x, y, z, w = struct.unpack_from(e + "4d", data, pos + 24)
    return sec * 1_000_000_000 + nsec, [w, x, y, z]


def _parse(p: Path, by_topic: dict, keep, offsets: dict, builders: dict, truth: dict, opened: list):
    """Read the messages of the topics in ``keep`` into ``builders`` (sensor topics) and ``truth`` (lists
    ``t``, ``q``, ``exact_t``, ``cdr``: the truth topics); yields after every
    :data:`~replay.formats._common.CHUNK` messages, with the CDR messages read so far decoded (in blocks, with
    numpy). Messages are numbered (in errors) over all the topics read, whichever pass reads them."""
    topics = [t for t in (*TOPICS, TRUTH_TOPIC, TRUTH_T_TOPIC) if t in by_topic]
    pending: dict[str, list[bytes]] = {t: [] for t in TOPICS}  # CDR payloads not yet decoded

    def flush() -> None:
        for topic, payloads in pending.items():
            if payloads:
                rows = _floats(p, topic, payloads, _V3_SIZE)
                pending[topic] = []
                builders[TOPICS[topic]].add_block(rows[:, 0], rows[:, 1:])

    for n, (channel, message) in enumerate(_mcap.iter_messages(p, topics, opened=opened), start=1):
        if n % _common.CHUNK == 0:
            flush()
            yield
        topic, cdr = channel.topic, channel.message_encoding == "cdr"
        if topic not in keep:
            continue
        if cdr and topic in TOPICS:
            pending[topic].append(message.data)
            continue
        if cdr and topic == TRUTH_T_TOPIC:
            truth["cdr"].append(message.data)
            continue
        try:
            if cdr:  # TRUTH_TOPIC
                ns, q = _pose_cdr(message.data)
                truth["t"].append((ns - offsets.get(channel.id, 0)) * 1e-9)
                truth["q"].append(q)
                continue
            d = json.loads(message.data)
            if topic == TRUTH_TOPIC:
                ts = d.get("timestamp") or {}
                ns = int(ts["sec"]) * 1_000_000_000 + int(ts["nsec"]) if ts else message.log_time
                o = d["pose"]["orientation"]
                truth["t"].append((ns - offsets.get(channel.id, 0)) * 1e-9)
                truth["q"].append([_num(o[k]) for k in "wxyz"])
                continue
            if topic == TRUTH_T_TOPIC:
                truth["exact_t"].append(_num(d["t"]))
                continue
            t = d["t"] if "t" in d else (message.log_time - offsets.get(channel.id, 0)) * 1e-9
            raw = [t, d["x"], d["y"], d["z"]]
        except (
            json.JSONDecodeError,
            UnicodeDecodeError,
            KeyError,
            TypeError,
            ValueError,
            struct.error,
        ) as exc:
            what = "PoseInFrame CDR message" if cdr else "{t, x, y, z} JSON object"
            raise InputError(
                p,
                f"{topic}: message {n} (log_time {message.log_time}) is not a valid {what} "
                f"({type(exc).__name__}: {exc})",
            ) from None
        vals = _json_numbers(raw)
        if vals is None:
            builders[TOPICS[topic]].count(NON_NUMERIC)
            continue
        builders[TOPICS[topic]].add(None, vals[0], vals[1:])
    flush()


def _truth(p: Path, by_topic: dict, offsets: dict, dropped: Counter):
    """The truth orientation (first pass over the truth topics), or None."""
    truth: dict = {"t": [], "q": [], "exact_t": [], "cdr": []}
    if TRUTH_TOPIC not in by_topic:
        return None
    for _ in _parse(p, by_topic, (TRUTH_TOPIC, TRUTH_T_TOPIC), offsets, {}, truth, []):
        pass
    if truth["cdr"]:
        truth["exact_t"] = _floats(p, TRUTH_T_TOPIC, truth["cdr"], _REF_SIZE)[:, 0].tolist()
    if not truth["q"]:
        return None
    # the pose's timestamp is the log time, which the sink may clamp at 0: prefer the heading's exact t
    t_truth = truth["exact_t"] if len(truth["exact_t"]) == len(truth["q"]) else truth["t"]
    b = StreamBuilder(p, "truth", dropped, width=4)
    b.add_block(np.asarray(t_truth), np.asarray(truth["q"]))
    return b.arrays() if len(b) else None


def read(path) -> Recording:
    """Read a pdr_mag MCAP file (either layout) into a :class:`Recording`."""
    return open_source(path).collect()


def open_source(path) -> RecordingSource:
    """Open a pdr_mag MCAP file (either layout): metadata and truth now, the sensor topics streamed."""
    p = Path(path)
    channels, error = _mcap.scan(p)
    if error is not None:
        raise InputError(p, error)
    by_topic = {c.topic: c for c in channels}
    if "/mag/raw" not in by_topic:
        raise InputError(p, "no /mag/raw channel (a stream missing)")
    offsets = {c.id: int(c.metadata.get("time_offset_ns", "0") or 0) for c in channels}
    dropped: Counter = Counter()
    truth = _truth(p, by_topic, offsets, dropped)
    keys = tuple(key for t, key in TOPICS.items() if t in by_topic)

    def chunks():
        builders = {key: StreamBuilder(p, key, dropped) for key in keys}
        opened: list = []
        yield from chunks_of(opened, builders, _parse(p, by_topic, TOPICS, offsets, builders, {}, opened))

    specs = {k: StreamSpec(p, k, unit_hint=_UNITS[k]) for k in keys}
    return RecordingSource(
        specs, [Feed(keys, chunks, p.stat().st_size)], meta=_meta(p), truth=truth, source=str(p), format=NAME,
        dropped=dropped,
    )
