"""pdr_mag's own MCAP layout — what ``pdr-mag replay --mcap`` writes (:mod:`pdr_mag.sinks.mcap`).

The layout is defined once, in the sink's module docstring; this reader needs only part of it:

=================================  ============================  =============================================
topic                              schema                        message (JSON, ``message_encoding="json"``)
=================================  ============================  =============================================
``/mag/raw``                       ``pdr_mag.Vector3Stamped``    ``{"t", "x", "y", "z"}``, raw µT, device
``/imu/accel``                     ``pdr_mag.Vector3Stamped``    m/s², specific force, device frame
``/imu/gyro``                      ``pdr_mag.Vector3Stamped``    rad/s, device frame
``/reference/truth/orientation``   ``foxglove.PoseInFrame``      device → ENU (optional) → ``Recording.truth``
``/reference/truth/heading``       ``pdr_mag.HeadingReference``  its exact ``t`` (same order as the poses)
=================================  ============================  =============================================

``t`` (float seconds, the recording's clock, written with 17 significant digits) is the sample time, so the
streams read back bit-identical to what was written; a message without ``t`` falls back to its
``log_time`` minus the channel's ``time_offset_ns``. ``null`` values (NaN written by the sink) are dropped
as ``<stream>:nan``. The metadata record ``recording`` becomes ``Recording.meta`` (values JSON-decoded
where they are JSON, else kept as strings). ``/mag/raw`` is required; the other topics are optional.
Messages are decoded one at a time as the file is read (mcap's reader decompresses one chunk at a time).
"""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import numpy as np

from replay.errors import InputError
from replay.formats import _mcap
from replay.formats._common import StreamBuilder, finish
from replay.recording import Recording

NAME = "pdr-mcap"
TOPICS = {"/mag/raw": "mag", "/imu/accel": "accel", "/imu/gyro": "gyro"}
TRUTH_TOPIC = "/reference/truth/orientation"
TRUTH_T_TOPIC = "/reference/truth/heading"  # same messages' exact "t", in the same order
_UNITS = {"mag": "µT", "accel": "m/s²", "gyro": "rad/s"}


def detect(path: Path) -> bool:
    if not _mcap.is_mcap(path):
        return False
    channels, _ = _mcap.scan(path)
    return any(c.topic == "/mag/raw" and c.message_encoding == "json" for c in channels)


def _meta(path: Path) -> dict:
    from mcap.exceptions import McapError
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
        except (McapError, EOFError, OSError) as exc:
            raise InputError(path, _mcap.damaged(exc)) from None
    return meta


def _num(v) -> float:
    return float("nan") if v is None else float(v)


def read(path) -> Recording:
    """Read a pdr_mag MCAP file into a :class:`Recording`."""
    p = Path(path)
    channels, error = _mcap.scan(p)
    if error is not None:
        raise InputError(p, error)
    by_topic = {c.topic: c for c in channels}
    if "/mag/raw" not in by_topic:
        raise InputError(p, "no /mag/raw channel (a stream missing)")
    offsets = {c.id: int(c.metadata.get("time_offset_ns", "0") or 0) for c in channels}
    dropped: Counter = Counter()
    builders = {key: StreamBuilder(p, key, dropped) for t, key in TOPICS.items() if t in by_topic}
    truth_t: list[float] = []
    truth_exact_t: list[float] = []
    truth_q: list[list[float]] = []
    topics = [t for t in (*TOPICS, TRUTH_TOPIC, TRUTH_T_TOPIC) if t in by_topic]
    for n, (channel, message) in enumerate(_mcap.iter_messages(p, topics), start=1):
        try:
            d = json.loads(message.data)
            if channel.topic == TRUTH_TOPIC:
                ts = d.get("timestamp") or {}
                ns = int(ts["sec"]) * 1_000_000_000 + int(ts["nsec"]) if ts else message.log_time
                o = d["pose"]["orientation"]
                truth_t.append((ns - offsets.get(channel.id, 0)) * 1e-9)
                truth_q.append([_num(o[k]) for k in "wxyz"])
                continue
            if channel.topic == TRUTH_T_TOPIC:
                truth_exact_t.append(_num(d["t"]))
                continue
            t = d["t"] if "t" in d else (message.log_time - offsets.get(channel.id, 0)) * 1e-9
            vals = [_num(d["x"]), _num(d["y"]), _num(d["z"])]
            t = _num(t)
        except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError, ValueError) as exc:
            raise InputError(
                p,
                f"{channel.topic}: message {n} (log_time {message.log_time}) is not a valid "
                f"{{t, x, y, z}} JSON object ({type(exc).__name__}: {exc})",
            ) from None
        builders[TOPICS[channel.topic]].add(None, t, vals)
    streams = {k: finish(b, unit_hint=_UNITS[k]) for k, b in builders.items()}
    truth = None
    if truth_q:
        # the pose's timestamp is the log time, which the sink may clamp at 0: prefer the heading's exact t
        t_truth = truth_exact_t if len(truth_exact_t) == len(truth_q) else truth_t
        b = StreamBuilder(p, "truth", dropped, width=4)
        b.add_block(np.asarray(t_truth), np.asarray(truth_q))
        if len(b):
            truth = b.arrays()
    return Recording(
        mag=streams["mag"],
        accel=streams.get("accel"),
        gyro=streams.get("gyro"),
        meta=_meta(p),
        truth=truth,
        source=str(p),
        format=NAME,
        dropped=dropped,
    )
