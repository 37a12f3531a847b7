"""MCAP output: inputs and outputs of a replay, in encodings Foxglove decodes natively.

Layout (the contract between this sink and the MCAP reader ``replay/formats/pdrmcap.py``), format version 2
-----------------------------------------------------------------------------------------------------------
High-rate topics are CDR (``message_encoding="cdr"``) with ``ros2msg`` schemas (definitions and byte
layouts in :mod:`pdr_mag.sinks._mcap_schemas`); events and calibrations are JSON with JSON schemas.
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
(CDR, little endian) then the four little-endian float64 ``t, x, y, z``.

Metadata records:

* ``recording`` — the ``meta`` given to :meth:`McapSink.open`, every value JSON-encoded (strings too), so
  ``{k: json.loads(v)}`` gives back the original ``meta`` (the replay adds ``source``, ``format``,
  ``north``, ``t0``, ``field`` to the recording's own keys);
* ``calibration`` — one per :meth:`McapSink.calibration`: ``t`` and ``json`` (the ``calibrate --json``
  object);
* ``pdr_mag`` — at close: ``format_version``, ``time_offset_ns``, ``clamped_log_times``,
  ``message_counts`` (JSON, per topic).

Format version 1 wrote every topic as JSON (``pdr_mag.Vector3Stamped`` ``{"t","x","y","z"}``
etc.); the reader still reads it.

Negative times
--------------
MCAP times are unsigned.  ``time_offset_ns`` is 0 unless the recording has negative times; then it is the
smallest whole number of seconds that makes the earliest time non-negative, the earliest time being
``meta["t0"]`` when the caller gives it, else the first time the sink sees.  A time that is still negative
after the offset (possible only without ``meta["t0"]``) is logged at 0 and counted in ``clamped_log_times``;
its ``t`` field is unaffected.  The offset is also in every channel's metadata.

Speed and memory: a batch of CDR messages is one numpy structured array holding the MCAP record headers and
the payloads (:mod:`pdr_mag.sinks._mcap_chunks`), so a message costs a fraction of a µs; chunks of
``chunk_size`` uncompressed bytes are compressed and written by an I/O thread.  At most 8192 rows are
encoded at once and at most 4 chunks are held, so memory stays bounded whatever the recording length
(``benchmarks/sinks.py``).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from pdr_mag._json import jsonable
from pdr_mag.estimates import DIAG_KEYS
from pdr_mag.sinks import _mcap_schemas as S
from pdr_mag.sinks._mcap_chunks import (
    HEADER_SIZE,
    ChunkWriter,
    new_records,
    one_record,
    record_bytes,
    record_dtype,
)
from pdr_mag.sinks._mcap_process import WriterProcess

FORMAT_VERSION = 2

#: Topics of the three input streams, by the ``kind`` of :meth:`McapSink.inputs`.
INPUT_TOPICS = {"accel": "/imu/accel", "gyro": "/imu/gyro", "mag": "/mag/raw"}
INPUT_UNITS = {"accel": "m/s^2", "gyro": "rad/s", "mag": "uT"}
#: Schemas by short key (name, encodings, definition): see :mod:`pdr_mag.sinks._mcap_schemas`.
SCHEMAS = S.SCHEMAS

#: Event kinds logged as warnings in ``/pdr/events`` (all others are INFO).
WARNING_EVENTS = ("interference_start", "calibration_rejected", "recalibration_requested", "drift_episode")
_LOG_INFO, _LOG_WARNING = 2, 3

_COMPRESSION = ("zstd", "lz4", "none")
#: Longest run of rows encoded at once (longer calls are sliced: bounded transient memory).
_MAX_ROWS = 8192

# record dtypes (MCAP message header + CDR payload) of the fixed-size messages
_VECTOR3 = record_dtype(S.cdr_dtype(S.VECTOR3_FIELDS, HEADER_SIZE))
_POSE = record_dtype(S.cdr_dtype(S.POSE_FIELDS, HEADER_SIZE))
_HEADING_REF = record_dtype(S.cdr_dtype(S.HEADING_REF_FIELDS, HEADER_SIZE))
_DIAG = record_dtype(S.cdr_dtype(S.DIAG_COLUMNS, HEADER_SIZE))


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
    background : bool
        Encode and write in a separate process (``multiprocessing`` "spawn"): the caller only pickles
        the arrays into a pipe.  The pipe blocks when the writer falls behind, so memory stays bounded.
        Errors in the writer are raised by :meth:`close`.  As with any "spawn" process, a calling
        *script* needs the usual ``if __name__ == "__main__":`` guard.  Rarely worth it now that encoding
        is vectorised (spawn start-up ≈ 0.5 s).
    """

    def __init__(
        self, path, *, compression: str = "zstd", chunk_size: int = 1 << 20, background: bool = False
    ):
        if compression not in _COMPRESSION:
            raise ValueError(f"compression: expected one of {_COMPRESSION}, got {compression!r}")
        if int(chunk_size) <= 0:
            raise ValueError(f"chunk_size: expected a positive number of bytes, got {chunk_size!r}")
        self.path = Path(path)
        self.compression = compression
        self.chunk_size = int(chunk_size)
        self.background = bool(background)
        self._proc: WriterProcess | None = None
        self._writer: ChunkWriter | None = None
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._t0_hint: float | None = None
        self._offset_ns: int | None = None
        self._clamped = 0
        self.counts: dict[str, int] = {}

    # ------------------------------------------------------------------ Sink protocol
    def open(self, meta: dict) -> None:
        if self._writer is not None or self._proc is not None:
            raise RuntimeError("McapSink: open() called twice without close()")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if self.background:
            self._proc = WriterProcess(self.path, self.compression, self.chunk_size)
            self._proc.send("open", (dict(meta or {}),))
            return
        self._schemas, self._channels, self.counts = {}, {}, {}
        self._t0_hint, self._offset_ns, self._clamped = None, None, 0
        self._writer = ChunkWriter(self.path, self.chunk_size, self.compression)
        meta = dict(meta or {})
        t0 = meta.get("t0")
        if isinstance(t0, (int, float)) and math.isfinite(t0):
            self._t0_hint = float(t0)
        self._writer.add_metadata("recording", _str_dict(meta))

    def inputs(self, kind: str, t: np.ndarray, xyz: np.ndarray) -> None:
        if kind not in INPUT_TOPICS:
            raise ValueError(f"kind: expected one of {tuple(INPUT_TOPICS)}, got {kind!r}")
        if self._forward("inputs", kind, np.asarray(t, dtype=float), np.asarray(xyz, dtype=float)):
            return
        self._vector3(INPUT_TOPICS[kind], t, xyz, {"unit": INPUT_UNITS[kind], "role": "input"})

    def mag_calibrated(self, t: np.ndarray, xyz: np.ndarray) -> None:
        if self._forward("mag_calibrated", np.asarray(t, dtype=float), np.asarray(xyz, dtype=float)):
            return
        self._vector3("/mag/calibrated", t, xyz, {"unit": "uT", "role": "output"})

    def estimates(self, batch) -> None:
        n = len(batch)
        if n == 0 or self._forward("estimates", batch):
            return
        if n > _MAX_ROWS:  # bounded transient memory whatever the caller hands over
            for i in range(0, n, _MAX_ROWS):
                self.estimates(_slice_batch(batch, slice(i, i + _MAX_ROWS)))
            return
        t = np.asarray(batch.t, dtype=float)
        ns = self._log_times(t)
        self._pose("/pdr/orientation", ns, np.asarray(batch.q_wd, dtype=float).reshape(n, 4))
        self._heading(ns, t, batch)

        cols = {k: np.asarray(v, dtype=float) for k, v in batch.diag.items() if k in DIAG_KEYS}
        if cols:
            if "field_ref_uT" in cols and "strength_tol_uT" in cols:
                cols["strength_lower_uT"] = cols["field_ref_uT"] - cols["strength_tol_uT"]
                cols["strength_upper_uT"] = cols["field_ref_uT"] + cols["strength_tol_uT"]
            if "dip_ref_deg" in cols and "dip_tol_deg" in cols:
                cols["dip_lower_deg"] = cols["dip_ref_deg"] - cols["dip_tol_deg"]
                cols["dip_upper_deg"] = cols["dip_ref_deg"] + cols["dip_tol_deg"]
            rec = new_records(_DIAG, self._channel("/pdr/diag", "diag"), ns)
            rec["t"] = t
            for key, name in S.DIAG_FIELDS.items():
                rec[name] = cols[key] if key in cols else np.nan
            self._add("/pdr/diag", ns, rec)

    def reference(self, name: str, t: np.ndarray, q_wd: np.ndarray) -> None:
        from pdr_mag.conventions import heading_deg_from_quat

        t = np.asarray(t, dtype=float)
        n = len(t)
        if n == 0 or self._forward("reference", name, t, np.asarray(q_wd, dtype=float)):
            return
        q = np.asarray(q_wd, dtype=float).reshape(n, 4)
        if n > _MAX_ROWS:
            for i in range(0, n, _MAX_ROWS):
                self.reference(name, t[i : i + _MAX_ROWS], q[i : i + _MAX_ROWS])
            return
        ns = self._log_times(t)
        self._pose(f"/reference/{name}/orientation", ns, q)
        topic = f"/reference/{name}/heading"
        rec = new_records(_HEADING_REF, self._channel(topic, "heading_ref"), ns)
        rec["t"] = t
        rec["heading_deg"] = heading_deg_from_quat(q)
        self._add(topic, ns, rec)

    def event(self, ev) -> None:
        if self._forward("event", ev):
            return
        d = ev.to_dict()
        ns = int(self._log_times(np.array([float(ev.t)]))[0])
        details = {k: v for k, v in d.items() if k not in ("t", "kind")}
        text = ev.kind + (" " + json.dumps(jsonable(details), sort_keys=True) if details else "")
        msg = {
            "timestamp": {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000},
            "level": _LOG_WARNING if ev.kind in WARNING_EVENTS else _LOG_INFO,
            "message": text,
            "name": "pdr_mag",
            "file": "",
            "line": 0,
        }
        self._add_one("/pdr/events", "log", ns, json.dumps(msg).encode())

    def calibration(self, t: float, cal) -> None:
        if self._forward("calibration", float(t), cal):
            return
        d_cal = jsonable(cal.to_dict())
        ns = int(self._log_times(np.array([float(t)]))[0])
        self._add_one("/pdr/calibration", "calibration", ns, json.dumps({"t": float(t), **d_cal}).encode())
        self._writer.add_metadata("calibration", {"t": repr(float(t)), "json": json.dumps(d_cal)})

    def close(self) -> None:
        if self._proc is not None:
            proc, self._proc = self._proc, None
            result = proc.finish()
            self.counts = result.get("counts", {})
            self._offset_ns = result.get("time_offset_ns")
            self._clamped = result.get("clamped", 0)
            if result.get("error"):
                raise RuntimeError(f"McapSink writer process for {self.path}: {result['error']}")
            return
        if self._writer is None:
            return
        self._writer.add_metadata(
            "pdr_mag",
            {
                "format_version": str(FORMAT_VERSION),
                "time_offset_ns": str(self._offset_ns or 0),
                "clamped_log_times": str(self._clamped),
                "message_counts": json.dumps(self.counts, sort_keys=True),
            },
        )
        self._writer.finish()
        self._writer = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # ------------------------------------------------------------------ helpers
    def _forward(self, name: str, *args) -> bool:
        """In background mode, send the call to the writer process (True); else check we are open."""
        if self._proc is not None:
            self._proc.send(name, args)
            return True
        if self._writer is None:
            raise RuntimeError("McapSink: open() must be called before writing (and not after close())")
        return False

    @property
    def time_offset_ns(self) -> int:
        return self._offset_ns or 0

    def _log_times(self, t: np.ndarray) -> np.ndarray:
        """Integer-ns log times ``round(t·1e9) + offset`` (see the module docstring on negative t)."""
        if self._offset_ns is None:
            first = float(np.min(t)) if self._t0_hint is None else min(self._t0_hint, float(np.min(t)))
            self._offset_ns = 0 if first >= 0 else int(math.ceil(-first)) * 1_000_000_000
        ns = np.round(np.asarray(t, dtype=float) * 1e9).astype(np.int64) + self._offset_ns
        neg = ns < 0
        if neg.any():
            self._clamped += int(neg.sum())
            ns[neg] = 0
        return ns

    def _vector3(self, topic: str, t, xyz, channel_meta: dict) -> None:
        t = np.asarray(t, dtype=float)
        n = len(t)
        if n == 0:
            return
        xyz = np.asarray(xyz, dtype=float).reshape(n, 3)
        if n > _MAX_ROWS:
            for i in range(0, n, _MAX_ROWS):
                self._vector3(topic, t[i : i + _MAX_ROWS], xyz[i : i + _MAX_ROWS], channel_meta)
            return
        ns = self._log_times(t)
        rec = new_records(_VECTOR3, self._channel(topic, "vector3", channel_meta), ns)
        rec["t"] = t
        rec["x"], rec["y"], rec["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
        self._add(topic, ns, rec)

    def _pose(self, topic: str, ns: np.ndarray, q: np.ndarray) -> None:
        rec = new_records(_POSE, self._channel(topic, "pose", {"frame_id": S.POSE_FRAME.decode()}), ns)
        rec["sec"] = ns // 1_000_000_000
        rec["nanosec"] = ns % 1_000_000_000
        rec["frame_len"] = len(S.POSE_FRAME) + 1
        rec["frame_id"] = S.POSE_FRAME
        rec["qw"], rec["qx"], rec["qy"], rec["qz"] = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
        self._add(topic, ns, rec)

    def _heading(self, ns: np.ndarray, t: np.ndarray, batch) -> None:
        """``/pdr/heading``: CDR with a variable-length string (``cal_state``), rows trimmed to their size."""
        states = np.asarray(batch.cal_state).astype(str).ravel()
        uniq, inv = np.unique(states, return_inverse=True)
        enc = [u.encode() for u in uniq]
        width = max(len(e) for e in enc) + 1
        dtype = record_dtype(S.heading_dtype(-(-width // 8) * 8, HEADER_SIZE))
        start = dtype.fields["cal_state"][1]  # offset of the string's bytes in the record
        sizes = start + np.array([len(e) + 1 for e in enc], dtype=np.int64)[inv.ravel()]
        rec = new_records(dtype, self._channel("/pdr/heading", "heading"), ns, sizes)
        rec["t"] = t
        rec["heading_deg"] = batch.heading_deg
        rec["heading_std_deg"] = batch.heading_std_deg
        rec["mag_used"] = batch.mag_used
        rec["interference"] = batch.interference
        rec["cal_len"] = sizes - start
        rec["cal_state"] = np.array(enc, dtype=f"S{width}")[inv.ravel()]
        self._add("/pdr/heading", ns, rec, sizes)

    def _channel(self, topic: str, schema: str, channel_meta: dict | None = None) -> int:
        cid = self._channels.get(topic)
        if cid is None:
            spec = S.SCHEMAS[schema]
            sid = self._schemas.get(schema)
            if sid is None:
                sid = self._writer.register_schema(spec.name, spec.encoding, spec.text.encode())
                self._schemas[schema] = sid
            md = {**(channel_meta or {}), "time_offset_ns": str(self.time_offset_ns)}
            cid = self._writer.register_channel(topic, spec.message_encoding, sid, md)
            self._channels[topic] = cid
        return cid

    def _add(self, topic: str, ns: np.ndarray, rec: np.ndarray, sizes=None) -> None:
        blob, sizes = record_bytes(rec, sizes)
        self._writer.add_records(ns, blob, sizes)
        self.counts[topic] = self.counts.get(topic, 0) + len(ns)

    def _add_one(self, topic: str, schema: str, ns: int, data: bytes) -> None:
        cid = self._channel(topic, schema)
        blob, sizes = one_record(cid, ns, data)
        self._writer.add_records(np.array([ns], dtype=np.int64), blob, sizes)
        self.counts[topic] = self.counts.get(topic, 0) + 1


# ---------------------------------------------------------------------- helpers
def _slice_batch(batch, sl: slice):
    from dataclasses import fields, replace

    cols = {f.name: getattr(batch, f.name)[sl] for f in fields(batch) if f.name != "diag"}
    return replace(batch, **cols, diag={k: v[sl] for k, v in batch.diag.items()})


def _str_dict(d: dict) -> dict[str, str]:
    """MCAP metadata values are strings: every value JSON-encoded (strings too, so types survive)."""
    return {str(k): json.dumps(jsonable(v)) for k, v in d.items()}
