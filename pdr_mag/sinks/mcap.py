"""MCAP output: inputs and outputs of a replay, in encodings Foxglove decodes natively.

Layout (the contract between this sink and the MCAP reader ``replay/formats/pdrmcap.py``), format version 2
-----------------------------------------------------------------------------------------------------------
High-rate topics are CDR (``message_encoding="cdr"``) with ``ros2msg`` schemas (the definitions are in
:mod:`pdr_mag.sinks._mcap_schemas`); events and calibrations are JSON with JSON schemas.
Times: a message carries the recording's own time ``t`` (float64, exactly as read) and is logged at the
integer-nanosecond ``log_time = publish_time = round(t·1e9) + time_offset_ns``.

=================================  =================================  =======================================
topic                              schema                             message
=================================  =================================  =======================================
``/imu/accel`` (input)             ``pdr_mag/msg/Vector3Stamped``     ``float64 t, x, y, z``; m/s², device
``/imu/gyro`` (input)              ``pdr_mag/msg/Vector3Stamped``     rad/s, device frame
``/mag/raw`` (input)               ``pdr_mag/msg/Vector3Stamped``     raw µT, device frame
``/mag/calibrated``                ``pdr_mag/msg/Vector3Stamped``     calibrated field at the mag epochs, µT
``/pdr/orientation``               ``foxglove_msgs/msg/PoseInFrame``  device → world, frame ``enu``,
                                                                      position 0, timestamp = log time
``/pdr/heading``                   ``pdr_mag/msg/Heading``            ``t, heading_deg, heading_std_deg,
                                                                      mag_used, interference, cal_state``
``/pdr/diag``                      ``pdr_mag/msg/Diagnostics``        ``t`` + every ``DIAG_KEYS`` column and
                                                                      the detector bands
                                                                      ``strength_lower_uT/…_upper_uT``,
                                                                      ``dip_lower_deg/…_upper_deg``, field
                                                                      names lower-cased (ROS 2 rule); NaN
                                                                      where not available
``/pdr/offset_error``              ``pdr_mag/msg/Vector3Stamped``     the calibration's offset error the
                                                                      filter found, µT, device frame (the
                                                                      rows' ``mag_offset_error_*``)
``/pdr/calibration``               ``pdr_mag.MagCalibration`` (JSON)  ``{"t", **MagCalibration.to_dict()}``
``/pdr/events``                    ``foxglove.Log`` (JSON)            one per Event; ``message`` = kind +
                                                                      details
``/reference/<name>/orientation``  ``foxglove_msgs/msg/PoseInFrame``  ``reference(name, …)``: ``truth``,
                                                                      ``os``
``/reference/<name>/heading``      ``pdr_mag/msg/HeadingReference``   ``float64 t, heading_deg``
=================================  =================================  =======================================

The three input topics carry exactly what the pipeline read (the reader's cleaned, contract-unit streams):
``t``, ``x``, ``y``, ``z`` are the float64 bits, so reading them back gives bit-identical arrays and replaying
the MCAP reproduces the outputs exactly.  A CDR message of those topics is 36 bytes: ``00 01 00 00``
(CDR, little endian) then the four little-endian float64 ``t, x, y, z``; the reader decodes them in blocks
relying on that.  Channel metadata: ``time_offset_ns`` on every channel, ``unit`` and ``role`` on the
vector topics, ``frame_id`` on the poses.  ``/mag/calibrated`` is the field the filter takes: the calibration
in force applied, less the offset error the filter has found
(:meth:`pdr_mag.pipeline.HeadingPipeline.pop_mag_calibrated`).

Metadata records:

* ``recording`` — the ``meta`` given to :meth:`McapSink.open`, every value JSON-encoded (strings too), so
  ``{k: json.loads(v)}`` gives back the original ``meta`` (the replay adds ``source``, ``format``,
  ``north``, ``t0``, ``field`` to the recording's own keys);
* ``calibration`` — one per :meth:`McapSink.calibration`: ``t`` and ``json`` (the ``calibrate --json``
  object);
* ``pdr_mag`` — at close: ``format_version``, ``time_offset_ns``, ``clamped_log_times``,
  ``message_counts`` (JSON, per topic), ``rate_limit_hz`` (JSON: ``null`` when every message was written).

Format version 1 wrote every topic as JSON (``pdr_mag.Vector3Stamped`` ``{"t","x","y","z"}``
etc.); the reader still reads it.

Negative times
--------------
MCAP times are unsigned.  ``time_offset_ns`` is 0 unless the recording has negative times; then it is the
smallest whole number of seconds that makes the earliest time non-negative, the earliest time being
``meta["t0"]`` when the caller gives it, else the first time the sink sees.  A time that is still negative
after the offset (possible only without ``meta["t0"]``) is logged at 0 and counted in ``clamped_log_times``;
its ``t`` field is unaffected.

Rate limit
----------
With ``rate_hz`` set, each high-rate topic keeps the first message whose ``t`` falls into each interval
``[k, k + 1) / rate_hz`` (``k`` an integer), so at most ``rate_hz`` messages a second; the estimate topics
share their rows, as do a reference's two topics.  Events and calibrations are always written.  Such a file
is for viewing: its inputs are decimated, so replaying it is not the original replay.

Writing
-------
:class:`mcap.writer.Writer` writes the file in chunks of ``chunk_size`` uncompressed bytes (compressed, with
message indexes) and a summary section (schemas, channels, chunk indexes, statistics) that lets readers
seek.  Memory holds one open chunk plus an index entry per chunk written, whatever the recording length.
Each CDR message is a dict encoded by ``mcap-ros2-support`` and added by the writer, both in Python: about
10 µs a message, and an hour of a phone recording at 200 Hz is about 3 million messages (the cost is
measured by ``benchmarks/sinks.py``; ``rate_hz`` bounds it).  Long calls are handled :data:`MAX_ROWS` rows
at a time, so transient memory stays bounded too.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

import mcap_ros2
import numpy as np
from mcap.writer import LIBRARY_IDENTIFIER, CompressionType, Writer
from mcap_ros2._dynamic import serialize_dynamic  # the encoder behind mcap_ros2.writer.Writer

from pdr_mag._json import jsonable
from pdr_mag.conventions import heading_deg_from_quat
from pdr_mag.estimates import DIAG_KEYS, diag_vectors
from pdr_mag.fusion.rows import OFFSET_ERROR_COLUMNS
from pdr_mag.sinks import WARNING_EVENTS
from pdr_mag.sinks._mcap_schemas import BAND_COLUMNS, DIAG_FIELDS, POSE_FRAME, SCHEMAS, Schema

FORMAT_VERSION = 2

#: Topics of the three input streams, by the ``kind`` of :meth:`McapSink.inputs`.
INPUT_TOPICS = {"accel": "/imu/accel", "gyro": "/imu/gyro", "mag": "/mag/raw"}
INPUT_UNITS = {"accel": "m/s^2", "gyro": "rad/s", "mag": "uT"}

#: foxglove.Log levels of ``/pdr/events``: the kinds in WARNING_EVENTS are warnings.
_LOG_INFO, _LOG_WARNING = 2, 3

_COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
#: Longest run of rows turned into messages at once (longer calls are sliced: bounded transient memory).
MAX_ROWS = 8192
_LIBRARY = f"pdr_mag; {LIBRARY_IDENTIFIER}; mcap-ros2-support/{mcap_ros2.__version__}"
_ORIGIN = {"x": 0.0, "y": 0.0, "z": 0.0}


class McapSink:
    """Write a replay's inputs and outputs to an MCAP file (see the module docstring for the layout).

    Parameters
    ----------
    path : str or Path
        The ``.mcap`` file to write (created/overwritten at :meth:`open`).
    compression : {"zstd", "lz4", "none"}
        Chunk compression.
    chunk_size : int
        Uncompressed bytes per chunk (bounds the memory the writer holds).
    rate_hz : float, optional
        At most this many messages a second on each high-rate topic (module docstring, "Rate limit").
        None (the default) writes every message: the file holds the complete inputs and replays exactly.
    """

    def __init__(
        self, path, *, compression: str = "zstd", chunk_size: int = 1 << 20, rate_hz: float | None = None
    ):
        if compression not in _COMPRESSION:
            raise ValueError(f"compression: expected one of {tuple(_COMPRESSION)}, got {compression!r}")
        if int(chunk_size) <= 0:
            raise ValueError(f"chunk_size: expected a positive number of bytes, got {chunk_size!r}")
        if rate_hz is not None and not (math.isfinite(rate_hz) and rate_hz > 0):
            raise ValueError(
                f"rate_hz: expected a positive number of messages a second or None, got {rate_hz!r}"
            )
        self.path = Path(path)
        self.compression = compression
        self.chunk_size = int(chunk_size)
        self.rate_hz = None if rate_hz is None else float(rate_hz)
        self._fh = None
        self._writer: Writer | None = None
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._encoders: dict[str, Callable[[dict], bytes]] = {}
        self._last_bin: dict[str, int] = {}
        self._t0_hint: float | None = None
        self._offset_ns: int | None = None
        self._clamped = 0
        self.counts: dict[str, int] = {}

    # ------------------------------------------------------------------ Sink protocol
    def open(self, meta: dict) -> None:
        if self._writer is not None:
            raise RuntimeError("McapSink: open() called twice without close()")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._schemas, self._channels, self._last_bin, self.counts = {}, {}, {}, {}
        self._t0_hint, self._offset_ns, self._clamped = None, None, 0
        meta = dict(meta or {})
        t0 = meta.get("t0")
        if isinstance(t0, (int, float)) and math.isfinite(t0):
            self._t0_hint = float(t0)
        self._fh = self.path.open("wb")
        self._writer = Writer(
            self._fh, chunk_size=self.chunk_size, compression=_COMPRESSION[self.compression]
        )
        self._writer.start(profile="", library=_LIBRARY)
        self._writer.add_metadata("recording", _str_dict(meta))

    def inputs(self, kind: str, t: np.ndarray, xyz: np.ndarray) -> None:
        if kind not in INPUT_TOPICS:
            raise ValueError(f"kind: expected one of {tuple(INPUT_TOPICS)}, got {kind!r}")
        self._vector3(INPUT_TOPICS[kind], t, xyz, {"unit": INPUT_UNITS[kind], "role": "input"})

    def mag_calibrated(self, t: np.ndarray, xyz: np.ndarray) -> None:
        self._vector3("/mag/calibrated", t, xyz, {"unit": "uT", "role": "output"})

    def estimates(self, batch) -> None:
        self._check_open()
        n = len(batch)
        if n == 0:
            return
        t = np.asarray(batch.t, dtype=float)
        q = np.asarray(batch.q_wd, dtype=float).reshape(n, 4)
        columns = (
            np.asarray(batch.heading_deg, dtype=float),
            np.asarray(batch.heading_std_deg, dtype=float),
            np.asarray(batch.mag_used, dtype=bool),
            np.asarray(batch.interference, dtype=bool),
            np.asarray(batch.cal_state).astype(str).ravel(),
        )
        diag = {k: np.asarray(v, dtype=float) for k, v in batch.diag.items() if k in DIAG_KEYS}
        offset = diag_vectors(batch, OFFSET_ERROR_COLUMNS)
        if offset is not None:  # the rows of a filter with the offset states
            self._vector3("/pdr/offset_error", t, offset, {"unit": "uT", "role": "output"})
        for rows, ns in self._kept("/pdr/orientation", t):
            t_rows = t[rows]
            self._pose("/pdr/orientation", ns, q[rows])
            heading = (
                {
                    "t": a,
                    "heading_deg": h,
                    "heading_std_deg": s,
                    "mag_used": m,
                    "interference": i,
                    "cal_state": c,
                }
                for a, h, s, m, i, c in zip(
                    t_rows.tolist(), *(col[rows].tolist() for col in columns), strict=True
                )
            )
            self._write("/pdr/heading", "heading", ns, heading)
            if diag:
                self._write(
                    "/pdr/diag", "diag", ns, _diag_messages(t_rows, {k: v[rows] for k, v in diag.items()})
                )

    def reference(self, name: str, t: np.ndarray, q_wd: np.ndarray) -> None:
        self._check_open()
        t = np.asarray(t, dtype=float)
        q = np.asarray(q_wd, dtype=float).reshape(len(t), 4)
        for rows, ns in self._kept(f"/reference/{name}/orientation", t):
            self._pose(f"/reference/{name}/orientation", ns, q[rows])
            heading = heading_deg_from_quat(q[rows]).tolist()
            msgs = ({"t": a, "heading_deg": h} for a, h in zip(t[rows].tolist(), heading, strict=True))
            self._write(f"/reference/{name}/heading", "heading_ref", ns, msgs)

    def event(self, ev) -> None:
        self._check_open()
        d = ev.to_dict()
        ns = self._log_times(np.array([float(ev.t)]))
        details = {k: v for k, v in d.items() if k not in ("t", "kind")}
        sec, nsec = divmod(int(ns[0]), 1_000_000_000)
        msg = {
            "timestamp": {"sec": sec, "nsec": nsec},
            "level": _LOG_WARNING if ev.kind in WARNING_EVENTS else _LOG_INFO,
            "message": ev.kind + (" " + json.dumps(jsonable(details), sort_keys=True) if details else ""),
            "name": "pdr_mag",
            "file": "",
            "line": 0,
        }
        self._write("/pdr/events", "log", ns, [msg])

    def calibration(self, t: float, cal) -> None:
        self._check_open()
        d_cal = jsonable(cal.to_dict())
        ns = self._log_times(np.array([float(t)]))
        self._write("/pdr/calibration", "calibration", ns, [{"t": float(t), **d_cal}])
        self._writer.add_metadata("calibration", {"t": repr(float(t)), "json": json.dumps(d_cal)})

    def close(self) -> None:
        if self._writer is None:
            return
        writer, fh = self._writer, self._fh
        self._writer = self._fh = None
        try:
            writer.add_metadata(
                "pdr_mag",
                {
                    "format_version": str(FORMAT_VERSION),
                    "time_offset_ns": str(self.time_offset_ns),
                    "clamped_log_times": str(self._clamped),
                    "message_counts": json.dumps(self.counts, sort_keys=True),
                    "rate_limit_hz": json.dumps(self.rate_hz),
                },
            )
            writer.finish()
        finally:
            fh.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    @property
    def time_offset_ns(self) -> int:
        return self._offset_ns or 0

    # ------------------------------------------------------------------ times and rows
    def _check_open(self) -> None:
        if self._writer is None:
            raise RuntimeError("McapSink: open() must be called before writing (and not after close())")

    def _fix_offset(self, t: np.ndarray) -> None:
        """Choose ``time_offset_ns`` at the first times seen (see the module docstring on negative t)."""
        if self._offset_ns is None:
            first = float(np.min(t)) if self._t0_hint is None else min(self._t0_hint, float(np.min(t)))
            self._offset_ns = 0 if first >= 0 else int(math.ceil(-first)) * 1_000_000_000

    def _log_times(self, t: np.ndarray) -> np.ndarray:
        """Integer-ns log times ``round(t·1e9) + offset``; still negative → 0, counted."""
        self._fix_offset(t)
        ns = np.round(t * 1e9).astype(np.int64) + self._offset_ns
        neg = ns < 0
        if neg.any():
            self._clamped += int(neg.sum())
            ns[neg] = 0
        return ns

    def _kept(self, key: str, t: np.ndarray) -> Iterator[tuple[slice | np.ndarray, np.ndarray]]:
        """``(rows, log times)`` of the rows of ``t`` to write, at most :data:`MAX_ROWS` at a time.

        ``key`` names the rate limiter's state: the first row of each ``1/rate_hz`` interval of ``t`` is kept
        unless the previous row (of this call, or the last of the previous call with this key) is in it.
        """
        n = len(t)
        if n == 0:
            return
        self._fix_offset(t)  # from every row, kept or not
        if self.rate_hz is None:
            for i in range(0, n, MAX_ROWS):
                rows = slice(i, i + MAX_ROWS)
                yield rows, self._log_times(t[rows])
            return
        bins = np.floor(t * self.rate_hz).astype(np.int64)
        prev = np.empty_like(bins)
        prev[0] = self._last_bin.get(key, bins[0] - 1)
        prev[1:] = bins[:-1]
        self._last_bin[key] = int(bins[-1])
        kept = np.flatnonzero(bins != prev)
        for i in range(0, len(kept), MAX_ROWS):
            rows = kept[i : i + MAX_ROWS]
            yield rows, self._log_times(t[rows])

    # ------------------------------------------------------------------ messages
    def _vector3(self, topic: str, t, xyz, channel_meta: dict) -> None:
        self._check_open()
        t = np.asarray(t, dtype=float)
        xyz = np.asarray(xyz, dtype=float).reshape(len(t), 3)
        for rows, ns in self._kept(topic, t):
            x, y, z = xyz[rows].T.tolist()
            msgs = (
                {"t": a, "x": b, "y": c, "z": d} for a, b, c, d in zip(t[rows].tolist(), x, y, z, strict=True)
            )
            self._write(topic, "vector3", ns, msgs, channel_meta)

    def _pose(self, topic: str, ns: np.ndarray, q: np.ndarray) -> None:
        sec, nsec = np.divmod(ns, 1_000_000_000)
        w, x, y, z = q.T.tolist()
        msgs = (
            {
                "timestamp": {"sec": s, "nanosec": n},
                "frame_id": POSE_FRAME,
                "pose": {"position": _ORIGIN, "orientation": {"x": qx, "y": qy, "z": qz, "w": qw}},
            }
            for s, n, qw, qx, qy, qz in zip(sec.tolist(), nsec.tolist(), w, x, y, z, strict=True)
        )
        self._write(topic, "pose", ns, msgs, {"frame_id": POSE_FRAME})

    def _write(
        self,
        topic: str,
        schema: str,
        ns: np.ndarray,
        messages: Iterable[dict],
        channel_meta: dict | None = None,
    ) -> None:
        """Encode ``messages`` (one per log time in ``ns``) and add them to ``topic``'s channel."""
        cid = self._channel(topic, schema, channel_meta)
        encode, add = self._encoders[schema], self._writer.add_message
        for log_time, msg in zip(ns.tolist(), messages, strict=True):
            add(cid, log_time, encode(msg), log_time)
        self.counts[topic] = self.counts.get(topic, 0) + len(ns)

    def _channel(self, topic: str, schema: str, channel_meta: dict | None) -> int:
        cid = self._channels.get(topic)
        if cid is None:
            spec = SCHEMAS[schema]
            if schema not in self._schemas:
                self._schemas[schema] = self._writer.register_schema(
                    spec.name, spec.encoding, spec.text.encode()
                )
                self._encoders[schema] = _encoder(spec)
            md = {**(channel_meta or {}), "time_offset_ns": str(self.time_offset_ns)}
            cid = self._writer.register_channel(topic, spec.message_encoding, self._schemas[schema], md)
            self._channels[topic] = cid
        return cid


# ---------------------------------------------------------------------- helpers
def _encoder(spec: Schema) -> Callable[[dict], bytes]:
    """Message dict → bytes: CDR by mcap-ros2-support from the ``ros2msg`` definition, else JSON."""
    if spec.message_encoding == "cdr":
        return serialize_dynamic(spec.name, spec.text)[spec.name]
    return lambda msg: json.dumps(msg).encode()


def _diag_messages(t: np.ndarray, cols: dict[str, np.ndarray]) -> Iterator[dict]:
    """``pdr_mag/msg/Diagnostics`` dicts: ``t``, the diagnostic columns and the detector bands."""
    for col, (band, sign) in BAND_COLUMNS.items():
        if band.reference in cols and band.tolerance in cols:
            cols[col] = cols[band.reference] + sign * cols[band.tolerance]
    names = ["t", *DIAG_FIELDS.values()]
    table = np.column_stack([t, *(cols.get(key, np.full(len(t), np.nan)) for key in DIAG_FIELDS)])
    return (dict(zip(names, row, strict=True)) for row in table.tolist())


def _str_dict(d: dict) -> dict[str, str]:
    """MCAP metadata values are strings: every value JSON-encoded (strings too, so types survive)."""
    return {str(k): json.dumps(jsonable(v)) for k, v in d.items()}
