"""MCAP output: inputs and outputs of a replay as JSON messages that Foxglove plots and replays.

Layout (the contract between this sink and the MCAP reader in ``replay/formats``)
---------------------------------------------------------------------------------
Every message is JSON (``message_encoding="json"``) with a JSON schema (``schema encoding="jsonschema"``).
Times: each message carries the recording's own time ``t`` (float seconds, written so that it reads back
bit-exactly) and is logged at the integer-nanosecond
``log_time = publish_time = round(t·1e9) + time_offset_ns``.

=================================  ============================  =============================================
topic                              schema                        message
=================================  ============================  =============================================
``/imu/accel`` (input)             ``pdr_mag.Vector3Stamped``    ``{"t", "x", "y", "z"}``, m/s², device frame
``/imu/gyro`` (input)              ``pdr_mag.Vector3Stamped``    ``{"t", "x", "y", "z"}``, rad/s, device frame
``/mag/raw`` (input)               ``pdr_mag.Vector3Stamped``    ``{"t", "x", "y", "z"}``, raw µT, device
``/mag/calibrated``                ``pdr_mag.Vector3Stamped``    calibrated field at the mag epochs, µT
``/pdr/orientation``               ``foxglove.PoseInFrame``      device → world, frame ``enu``, position 0
``/pdr/heading``                   ``pdr_mag.Heading``           ``t, heading_deg, heading_std_deg, mag_used,
                                                                 interference, cal_state``
``/pdr/diag``                      ``pdr_mag.Diagnostics``       ``t`` + the ``DIAG_KEYS`` present + detector
                                                                 bands ``strength_lower_uT/…_upper_uT``,
                                                                 ``dip_lower_deg/…_upper_deg``; NaN → ``null``
``/pdr/calibration``               ``pdr_mag.MagCalibration``    ``{"t", **MagCalibration.to_dict()}``
``/pdr/events``                    ``foxglove.Log``              one per Event; ``message`` = kind + details
``/reference/<name>/orientation``  ``foxglove.PoseInFrame``      ``reference(name, …)``: ``truth``, ``os``
``/reference/<name>/heading``      ``pdr_mag.HeadingReference``  ``{"t", "heading_deg"}`` of that orientation
=================================  ============================  =============================================

The three input topics carry exactly what the pipeline read (the reader's cleaned, contract-unit streams), so
reading them back gives bit-identical arrays, and replaying the MCAP reproduces the outputs exactly.
A reader needs only ``t``, ``x``, ``y``, ``z`` of those three topics (and may ignore ``log_time``).

Metadata records:

* ``recording`` — the ``meta`` given to :meth:`McapSink.open`, every value JSON-encoded (strings too), so
  ``{k: json.loads(v)}`` gives back the original ``meta`` (the replay adds ``source``, ``format``,
  ``north``, ``t0``, ``field`` to the recording's own keys);
* ``calibration`` — one per :meth:`McapSink.calibration`: ``t`` and ``json`` (the ``calibrate --json``
  object);
* ``pdr_mag`` — at close: ``format_version``, ``time_offset_ns``, ``clamped_log_times``,
  ``message_counts`` (JSON, per topic).

Negative times
--------------
MCAP times are unsigned.  ``time_offset_ns`` is 0 unless the recording has negative times; then it is the
smallest whole number of seconds that makes the earliest time non-negative, the earliest time being
``meta["t0"]`` when the caller gives it, else the first time the sink sees.  A time that is still negative
after the offset (possible only without ``meta["t0"]``) is logged at 0 and counted in ``clamped_log_times``;
its ``t`` field is unaffected.  The offset is also in every channel's metadata.

Streaming: messages go into chunks of ``chunk_size`` uncompressed bytes (zstd or lz4), built with numpy
around mcap's own record classes and written by an I/O thread (:class:`_ChunkWriter`); at most 8192 rows
are formatted at once and at most 4 chunks are held, so memory stays bounded whatever the recording length
(``benchmarks/sinks.py``: the same peak for 10 and 60 minutes).

Messages are formatted per batch: numbers become JSON tokens in one call (orjson's shortest round-trip
representation when orjson is installed, else ``%.17g``; both read back bit-exactly, NaN/inf as ``null``)
and are put into a byte template with one ``%`` call — no per-message ``json.dumps``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from pdr_mag.estimates import DIAG_KEYS

FORMAT_VERSION = 1

#: Topics of the three input streams, by the ``kind`` of :meth:`McapSink.inputs`.
INPUT_TOPICS = {"accel": "/imu/accel", "gyro": "/imu/gyro", "mag": "/mag/raw"}
INPUT_UNITS = {"accel": "m/s^2", "gyro": "rad/s", "mag": "uT"}

_TIME = {
    "type": "object",
    "title": "time",
    "properties": {
        "sec": {"type": "integer", "minimum": 0},
        "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999},
    },
}
_NUM = {"type": "number"}
_NUM_OR_NULL = {"type": ["number", "null"]}

SCHEMAS: dict[str, dict] = {
    "pdr_mag.Vector3Stamped": {
        "title": "pdr_mag.Vector3Stamped",
        "description": "A 3-vector at time t (recording clock, s), device frame",
        "type": "object",
        "properties": {"t": _NUM, "x": _NUM, "y": _NUM, "z": _NUM},
        "required": ["t", "x", "y", "z"],
    },
    "foxglove.PoseInFrame": {
        "title": "foxglove.PoseInFrame",
        "description": "A timestamped pose for an object or reference frame in 3D space",
        "type": "object",
        "properties": {
            "timestamp": _TIME,
            "frame_id": {"type": "string"},
            "pose": {
                "title": "foxglove.Pose",
                "type": "object",
                "properties": {
                    "position": {
                        "title": "foxglove.Vector3",
                        "type": "object",
                        "properties": {"x": _NUM, "y": _NUM, "z": _NUM},
                    },
                    "orientation": {
                        "title": "foxglove.Quaternion",
                        "type": "object",
                        "properties": {"x": _NUM, "y": _NUM, "z": _NUM, "w": _NUM},
                    },
                },
            },
        },
    },
    "foxglove.Log": {
        "title": "foxglove.Log",
        "description": "A log message",
        "type": "object",
        "properties": {
            "timestamp": _TIME,
            "level": {
                "title": "foxglove.LogLevel",
                "type": "integer",
                "oneOf": [
                    {"title": name, "const": i}
                    for i, name in enumerate(("UNKNOWN", "DEBUG", "INFO", "WARNING", "ERROR", "FATAL"))
                ],
            },
            "message": {"type": "string"},
            "name": {"type": "string"},
            "file": {"type": "string"},
            "line": {"type": "integer", "minimum": 0},
        },
    },
    "pdr_mag.Heading": {
        "title": "pdr_mag.Heading",
        "description": "Heading output of the pipeline (INTERFACE.md replay --out-csv columns)",
        "type": "object",
        "properties": {
            "t": _NUM,
            "heading_deg": _NUM_OR_NULL,
            "heading_std_deg": _NUM_OR_NULL,
            "mag_used": {"type": "boolean"},
            "interference": {"type": "boolean"},
            "cal_state": {"type": "string"},
        },
        "required": ["t", "heading_deg", "heading_std_deg", "mag_used", "interference", "cal_state"],
    },
    "pdr_mag.HeadingReference": {
        "title": "pdr_mag.HeadingReference",
        "description": "Heading of a reference orientation (truth, the phone's own), deg from north",
        "type": "object",
        "properties": {"t": _NUM, "heading_deg": _NUM_OR_NULL},
        "required": ["t", "heading_deg"],
    },
    "pdr_mag.Diagnostics": {
        "title": "pdr_mag.Diagnostics",
        "description": "Diagnostic columns of the pipeline; null where not available",
        "type": "object",
        "properties": {
            "t": _NUM,
            **{k: {**_NUM_OR_NULL, "description": v} for k, v in DIAG_KEYS.items()},
            "strength_lower_uT": {**_NUM_OR_NULL, "description": "field_ref_uT - strength_tol_uT"},
            "strength_upper_uT": {**_NUM_OR_NULL, "description": "field_ref_uT + strength_tol_uT"},
            "dip_lower_deg": {**_NUM_OR_NULL, "description": "dip_ref_deg - dip_tol_deg"},
            "dip_upper_deg": {**_NUM_OR_NULL, "description": "dip_ref_deg + dip_tol_deg"},
        },
        "required": ["t"],
    },
    "pdr_mag.MagCalibration": {
        "title": "pdr_mag.MagCalibration",
        "description": "A magnetometer calibration (calibrate --json object of INTERFACE.md) at time t",
        "type": "object",
        "properties": {
            "t": _NUM,
            "format_version": {"type": "integer"},
            "method": {"type": "string"},
            "offset_uT": {"type": "array", "items": _NUM},
            "soft_iron": {"type": "array", "items": {"type": "array", "items": _NUM}},
            "field_uT": _NUM_OR_NULL,
            "residual_rms_uT": _NUM_OR_NULL,
            "offset_std_uT": {"type": "array", "items": _NUM_OR_NULL},
            "n_samples": {"type": "integer"},
            "coverage": _NUM_OR_NULL,
            "accepted": {"type": "boolean"},
            "reasons": {"type": "array", "items": {"type": "string"}},
        },
        "required": ["t", "offset_uT", "soft_iron"],
    },
}

#: Event kinds logged as warnings in ``/pdr/events`` (all others are INFO).
WARNING_EVENTS = ("interference_start", "calibration_rejected", "recalibration_requested")
_LOG_INFO, _LOG_WARNING = 2, 3

_COMPRESSION = ("zstd", "lz4", "none")
#: Longest run of rows formatted at once (longer calls are sliced: bounded transient memory).
_MAX_ROWS = 8192

try:  # orjson (Rust, shortest round-trip float repr) formats numbers ~5× faster than ``%`` — optional
    import orjson as _orjson
except ImportError:  # pragma: no cover - the fallback is exercised by a test that hides orjson
    _orjson = None


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
        Format and write in a separate process (``multiprocessing`` "spawn"): the caller only pickles
        the arrays into a pipe, so on a machine with a free core the replay hardly waits for the sink.
        The pipe blocks when the writer falls behind, so memory stays bounded.  Errors in the writer are
        raised by :meth:`close`.  As with any "spawn" process, a calling *script* needs the usual
        ``if __name__ == "__main__":`` guard.
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
        self._proc: _WriterProcess | None = None
        self._writer = None
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
            self._proc = _WriterProcess(self.path, self.compression, self.chunk_size)
            self._proc.send("open", (dict(meta or {}),))
            return
        self._schemas, self._channels, self.counts = {}, {}, {}
        self._t0_hint, self._offset_ns, self._clamped = None, None, 0
        self._writer = _ChunkWriter(self.path, self.chunk_size, self.compression)
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
        q = np.asarray(batch.q_wd, dtype=float).reshape(n, 4)
        self._pose("/pdr/orientation", ns, q)

        fmt = b'{"t":%s,"heading_deg":%s,"heading_std_deg":%s,"mag_used":%s,"interference":%s,"cal_state":%s}'
        cols = [
            _fmt_col(t),
            _fmt_col(batch.heading_deg),
            _fmt_col(batch.heading_std_deg),
            _bool_col(batch.mag_used),
            _bool_col(batch.interference),
            _str_col(batch.cal_state),
        ]
        self._write("/pdr/heading", "pdr_mag.Heading", ns, fmt, cols)

        diag = {k: np.asarray(v, dtype=float) for k, v in batch.diag.items() if k in DIAG_KEYS}
        if diag:
            nan = np.full(n, np.nan)
            if "field_ref_uT" in diag and "strength_tol_uT" in diag:
                diag["strength_lower_uT"] = diag["field_ref_uT"] - diag["strength_tol_uT"]
                diag["strength_upper_uT"] = diag["field_ref_uT"] + diag["strength_tol_uT"]
            if "dip_ref_deg" in diag and "dip_tol_deg" in diag:
                diag["dip_lower_deg"] = diag["dip_ref_deg"] - diag["dip_tol_deg"]
                diag["dip_upper_deg"] = diag["dip_ref_deg"] + diag["dip_tol_deg"]
            keys = list(diag)
            fmt = ("{" + ",".join(['"t":%s'] + [f'"{k}":%s' for k in keys]) + "}").encode()
            cols = [_fmt_col(t)] + [_fmt_col(diag.get(k, nan)) for k in keys]
            self._write("/pdr/diag", "pdr_mag.Diagnostics", ns, fmt, cols)

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
        fmt = b'{"t":%s,"heading_deg":%s}'
        cols = [_fmt_col(t), _fmt_col(heading_deg_from_quat(q))]
        self._write(f"/reference/{name}/heading", "pdr_mag.HeadingReference", ns, fmt, cols)

    def event(self, ev) -> None:
        if self._forward("event", ev):
            return
        d = ev.to_dict()
        ns = int(self._log_times(np.array([float(ev.t)]))[0])
        details = {k: v for k, v in d.items() if k not in ("t", "kind")}
        text = ev.kind + (" " + json.dumps(_jsonable(details), sort_keys=True) if details else "")
        msg = {
            "timestamp": {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000},
            "level": _LOG_WARNING if ev.kind in WARNING_EVENTS else _LOG_INFO,
            "message": text,
            "name": "pdr_mag",
            "file": "",
            "line": 0,
        }
        self._write("/pdr/events", "foxglove.Log", [ns], b"%s", [_one(json.dumps(msg).encode())])

    def calibration(self, t: float, cal) -> None:
        if self._forward("calibration", float(t), cal):
            return
        d_cal = _jsonable(cal.to_dict())
        d = {"t": float(t), **d_cal}
        ns = int(self._log_times(np.array([float(t)]))[0])
        text = json.dumps(d)
        self._write("/pdr/calibration", "pdr_mag.MagCalibration", [ns], b"%s", [_one(text.encode())])
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
        tok = _tokens(np.column_stack([t, xyz]))
        self._write(topic, "pdr_mag.Vector3Stamped", ns, b'{"t":%s,"x":%s,"y":%s,"z":%s}', tok, channel_meta)

    def _pose(self, topic: str, ns: np.ndarray, q: np.ndarray) -> None:
        fmt = (
            b'{"timestamp":{"sec":%s,"nsec":%s},"frame_id":"enu","pose":{"position":{"x":0,"y":0,"z":0},'
            b'"orientation":{"x":%s,"y":%s,"z":%s,"w":%s}}}'
        )
        cols = [
            _tokens(ns // 1_000_000_000),
            _tokens(ns % 1_000_000_000),
            _fmt_col(q[:, 1]),
            _fmt_col(q[:, 2]),
            _fmt_col(q[:, 3]),
            _fmt_col(q[:, 0]),
        ]
        self._write(topic, "foxglove.PoseInFrame", ns, fmt, cols, {"frame_id": "enu"})

    def _channel(self, topic: str, schema: str, channel_meta: dict | None) -> int:
        cid = self._channels.get(topic)
        if cid is None:
            sid = self._schemas.get(schema)
            if sid is None:
                data = json.dumps(SCHEMAS[schema]).encode()
                sid = self._writer.register_schema(name=schema, encoding="jsonschema", data=data)
                self._schemas[schema] = sid
            md = {**(channel_meta or {}), "time_offset_ns": str(self.time_offset_ns)}
            cid = self._writer.register_channel(topic, "json", sid, md)
            self._channels[topic] = cid
        return cid

    def _write(self, topic: str, schema: str, ns, template: bytes, cols, channel_meta=None) -> None:
        """Messages ``template % row`` for each row of the token columns ``cols`` (a list of n-long object
        arrays of ``bytes``, or an (n, k) object array), logged at ``ns``."""
        if self._writer is None:
            raise RuntimeError("McapSink: open() must be called before writing (and not after close())")
        cid = self._channel(topic, schema, channel_meta)
        ns = np.asarray(ns, dtype=np.int64)
        blob, sizes = _records(cid, ns, template, cols)
        self._writer.add_records(ns, blob, sizes)
        self.counts[topic] = self.counts.get(topic, 0) + len(ns)


# ---------------------------------------------------------------------- background writer process
class _WriterProcess:
    """A child process running an in-process :class:`McapSink`, fed ``(method, args)`` through a pipe."""

    def __init__(self, path: Path, compression: str, chunk_size: int):
        import multiprocessing as mp

        ctx = mp.get_context("spawn")  # not fork: the caller may have threads (rerun, the I/O thread)
        recv_end, self._conn = ctx.Pipe(duplex=False)
        self._result, result_end = ctx.Pipe(duplex=False)
        self._proc = ctx.Process(
            target=_writer_main,
            args=(recv_end, result_end, str(path), compression, chunk_size),
            name="pdr_mag-mcap-sink",
            daemon=True,
        )
        self._proc.start()
        recv_end.close()
        result_end.close()

    def send(self, name: str, args: tuple) -> None:
        try:
            self._conn.send((name, args))
        except (BrokenPipeError, ConnectionResetError, EOFError) as exc:
            raise RuntimeError(f"McapSink writer process ended early ({self._error_or(exc)})") from None

    def _error_or(self, exc) -> str:
        if self._result.poll(1.0):
            return str(self._result.recv().get("error"))
        return f"{type(exc).__name__}; exit code {self._proc.exitcode}"

    def finish(self) -> dict:
        try:
            self._conn.send(("close", ()))
        except (BrokenPipeError, ConnectionResetError):
            pass
        self._conn.close()
        result = {"error": f"no answer from the writer process (exit code {self._proc.exitcode})"}
        try:
            result = self._result.recv()
        except EOFError:
            pass
        self._proc.join(timeout=60)
        return result


def _writer_main(conn, result, path: str, compression: str, chunk_size: int) -> None:
    """The writer process: apply the calls in order; after an error keep draining (no deadlock)."""
    sink = McapSink(path, compression=compression, chunk_size=chunk_size)
    error = None
    while True:
        try:
            name, args = conn.recv()
        except EOFError:  # the caller went away without close(): still finish the file
            name, args = "close", ()
        if error is None:
            try:
                getattr(sink, name)(*args)
            except BaseException as exc:  # noqa: BLE001 - reported to the caller
                error = f"{type(exc).__name__}: {exc}"
        if name == "close":
            break
    if error is not None and sink._writer is not None:
        try:
            sink.close()
        except BaseException:  # noqa: BLE001, S110 - the first error is the one to report
            pass
    result.send(
        {"counts": sink.counts, "time_offset_ns": sink._offset_ns, "clamped": sink._clamped, "error": error}
    )


# ---------------------------------------------------------------------- formatting helpers
def _tokens(values: np.ndarray) -> np.ndarray:
    """JSON number tokens (bytes) of an int or float array, same shape; NaN/inf → ``null``.

    Floats get a representation that reads back bit-exactly (shortest round-trip with orjson, else 17
    significant digits).
    """
    a = np.asarray(values)
    flat = np.ascontiguousarray(a.reshape(-1))
    if flat.dtype.kind not in "iu":
        flat = flat.astype(np.float64, copy=False)
    out = np.empty(len(flat), dtype=object)
    if len(flat) == 0:
        return out.reshape(a.shape)
    if _orjson is not None:
        text = _orjson.dumps(flat, option=_orjson.OPT_SERIALIZE_NUMPY)[1:-1]
    elif flat.dtype.kind in "iu":
        text = (b"%d," * len(flat)) % tuple(flat.tolist())
    else:
        text = (b"%.17g," * len(flat)) % tuple(flat.tolist())
        if not np.isfinite(flat).all():
            text = text.replace(b"-inf", b"null").replace(b"inf", b"null").replace(b"nan", b"null")
    toks = text.split(b",")
    out[:] = toks[: len(flat)]
    return out.reshape(a.shape)


def _slice_batch(batch, sl: slice):
    from dataclasses import fields, replace

    cols = {f.name: getattr(batch, f.name)[sl] for f in fields(batch) if f.name != "diag"}
    return replace(batch, **cols, diag={k: v[sl] for k, v in batch.diag.items()})


def _fmt_col(values) -> np.ndarray:
    return _tokens(np.asarray(values, dtype=float).ravel())


def _bool_col(values) -> np.ndarray:
    return np.where(np.asarray(values, dtype=bool).ravel(), b"true", b"false").astype(object)


def _str_col(values) -> np.ndarray:
    v = np.asarray(values).astype(str).ravel()
    uniq, inv = np.unique(v, return_inverse=True)
    enc = np.array([json.dumps(str(u)).encode() for u in uniq], dtype=object)
    return enc[inv.ravel()]


def _one(value: bytes) -> np.ndarray:
    out = np.empty(1, dtype=object)
    out[0] = value
    return out


def _records(cid: int, ns: np.ndarray, template: bytes, cols) -> tuple[bytes, np.ndarray]:
    """MCAP message records (header + ``template % row``) of all rows, in one ``%`` call, and their sizes.

    The body lengths are known before formatting (template length + token lengths), so each record's
    31-byte header is formatted in with the body: no splitting and re-joining of message bytes.
    """
    n = len(ns)
    if isinstance(cols, np.ndarray):
        body = cols.reshape(n, -1)
    else:
        body = np.empty((n, len(cols)), dtype=object)
        for j, c in enumerate(cols):
            body[:, j] = c
    k = body.shape[1]
    flat = body.ravel().tolist()
    fixed = len(template) - 2 * k  # every field is one "%s"
    body_len = np.fromiter(map(len, flat), dtype=np.int64, count=n * k).reshape(n, k).sum(axis=1) + fixed
    hdr = np.empty(n, dtype=_MSG_HEADER)
    hdr["op"] = _OP_MESSAGE
    hdr["len"] = body_len + (_MSG_HEADER.itemsize - 9)
    hdr["ch"] = cid
    hdr["seq"] = 0
    hdr["log"] = ns
    hdr["pub"] = ns
    hb = hdr.tobytes()
    w = _MSG_HEADER.itemsize
    rows = np.empty((n, k + 1), dtype=object)
    rows[:, 0] = [hb[i : i + w] for i in range(0, n * w, w)]
    rows[:, 1:] = body
    blob = ((b"%s" + template) * n) % tuple(rows.ravel().tolist())
    return blob, body_len + w


def _jsonable(obj):
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    if obj is None or isinstance(obj, (int, str)):
        return obj
    return str(obj)


def _str_dict(d: dict) -> dict[str, str]:
    """MCAP metadata values are strings: every value JSON-encoded (strings too, so types survive)."""
    return {str(k): json.dumps(_jsonable(v)) for k, v in d.items()}


# ---------------------------------------------------------------------- the chunk writer
_MAGIC = b"\x89MCAP0\r\n"
_OP_MESSAGE = 0x05
_OP_MESSAGE_INDEX = 0x07
_OP_CHUNK = 0x06
#: Message record header: opcode, record length, channel id, sequence, log time, publish time (31 bytes).
_MSG_HEADER = np.dtype(
    [("op", "u1"), ("len", "<u8"), ("ch", "<u2"), ("seq", "<u4"), ("log", "<u8"), ("pub", "<u8")]
)


class _ChunkWriter:
    """A streaming MCAP writer that takes messages in batches and builds chunks with numpy.

    The records around the messages (header, schema, channel, chunk, chunk index, metadata, statistics,
    summary, footer) are mcap's own record classes; only the message and message-index records inside
    and after each chunk are assembled here, vectorised, because mcap's per-message ``add_message`` costs
    about 4 µs a message (a one-hour 200 Hz replay writes several million).  The file has the same
    structure as mcap's ``Writer`` output (chunked, message indexes, chunk indexes, statistics, summary
    offsets, CRCs of chunks and summary) and is validated by mcap's reader in the tests.

    Compression, CRCs and file writes run on one background thread (zstd/lz4/zlib release the GIL), fed
    through a queue of at most ``_QUEUE`` finished chunks, so memory stays bounded to a few chunks.  All
    file access happens on that thread, in submission order; an error there is raised by the next call.
    """

    _QUEUE = 3

    def __init__(self, path: Path, chunk_size: int, compression: str):
        import queue
        import threading

        from mcap.data_stream import RecordBuilder
        from mcap.records import Header

        self._rb = RecordBuilder()  # used on the I/O thread only
        self._stream = open(path, "wb")  # noqa: SIM115 - closed in finish()
        self._chunk_size = chunk_size
        self._compression = compression
        self._schemas: list = []
        self._channels: list = []
        self._chunk_indexes: list = []
        self._metadata_indexes: list = []
        self._counts: dict[int, int] = {}
        self._n_messages = 0
        self._t_start: int | None = None
        self._t_end = 0
        self._metadata_count = 0
        # the chunk being filled: list of (channel id, ns (n,), records bytes, record lengths (n,))
        self._pending: list[tuple[int, np.ndarray, bytes, np.ndarray]] = []
        self._pending_bytes = 0
        self._zstd = None
        self._error: BaseException | None = None
        self._jobs: queue.Queue = queue.Queue(maxsize=self._QUEUE)
        self._thread = threading.Thread(target=self._work, name="pdr_mag-mcap-writer", daemon=True)
        self._thread.start()

        def start():
            self._stream.write(_MAGIC)
            Header(profile="", library="pdr_mag (mcap-python records)").write(self._rb)
            self._flush()

        self._submit(start)

    # ------------------------------------------------------------------ the I/O thread
    def _work(self) -> None:
        while True:
            job = self._jobs.get()
            if job is None:
                return
            if self._error is None:
                try:
                    job()
                except BaseException as exc:  # noqa: BLE001 - handed to the caller's thread
                    self._error = exc

    def _submit(self, job) -> None:
        if self._error is not None:
            raise RuntimeError(f"MCAP writer failed: {self._error}") from self._error
        self._jobs.put(job)

    def _flush(self) -> None:
        self._stream.write(self._rb.end())

    # ------------------------------------------------------------------ records
    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        from mcap.records import Schema

        schema = Schema(id=len(self._schemas) + 1, name=name, encoding=encoding, data=data)
        self._schemas.append(schema)

        def job():
            schema.write(self._rb)
            self._flush()

        self._submit(job)
        return schema.id

    def register_channel(self, topic: str, message_encoding: str, schema_id: int, metadata: dict) -> int:
        from mcap.records import Channel

        channel = Channel(
            id=len(self._channels) + 1,
            topic=topic,
            message_encoding=message_encoding,
            schema_id=schema_id,
            metadata=dict(metadata),
        )
        self._channels.append(channel)
        self._counts[channel.id] = 0

        def job():
            channel.write(self._rb)
            self._flush()

        self._submit(job)
        return channel.id

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        from mcap.records import Metadata, MetadataIndex

        record = Metadata(name=name, metadata=dict(data))
        self._metadata_count += 1

        def job():
            offset = self._stream.tell()
            record.write(self._rb)
            self._metadata_indexes.append(MetadataIndex(offset=offset, length=self._rb.count, name=name))
            self._flush()

        self._submit(job)

    def add_records(self, ns: np.ndarray, blob: bytes, sizes: np.ndarray) -> None:
        """Queue finished message records (``blob``: n records back to back, ``sizes`` their lengths,
        ``ns`` their log times) and write every chunk that fills up."""
        n = len(sizes)
        if n == 0:
            return
        if len(ns) != n or int(np.sum(sizes)) != len(blob):
            raise ValueError(f"add_records: {n} sizes, {len(ns)} log times, {len(blob)} bytes do not match")
        cid = int.from_bytes(blob[9:11], "little")
        ends = np.cumsum(sizes)
        start, base = 0, 0
        while start < n:
            room = self._chunk_size - self._pending_bytes
            stop = start + max(1, int(np.searchsorted(ends[start:] - base, room, side="right")))
            end = int(ends[stop - 1])
            self._pending.append((cid, ns[start:stop], blob[base:end], sizes[start:stop]))
            self._pending_bytes += end - base
            self._counts[cid] += stop - start
            start, base = stop, end
            if self._pending_bytes >= self._chunk_size:
                self._finalize_chunk()

    def _finalize_chunk(self) -> None:
        """Join the pending records into one chunk (here) and hand it to the I/O thread."""
        if not self._pending:
            return
        pieces, indexes = [], {}
        offset = 0
        t_lo, t_hi = None, 0
        for cid, ns, piece, sizes in self._pending:
            starts = offset + np.concatenate([[0], np.cumsum(sizes[:-1])])
            pieces.append(piece)
            indexes.setdefault(cid, []).append(np.column_stack([ns, starts]).astype("<u8"))
            offset += len(piece)
            lo, hi = int(ns.min()), int(ns.max())
            t_lo = lo if t_lo is None else min(t_lo, lo)
            t_hi = max(t_hi, hi)
        data = b"".join(pieces)
        index_bodies = {}
        for cid in sorted(indexes):
            entries = np.concatenate(indexes[cid])
            index_bodies[cid] = entries[np.lexsort((entries[:, 1], entries[:, 0]))].tobytes()
        self._n_messages += sum(len(p[1]) for p in self._pending)
        self._t_start = t_lo if self._t_start is None else min(self._t_start, t_lo)
        self._t_end = max(self._t_end, t_hi)
        self._pending, self._pending_bytes = [], 0
        self._submit(lambda: self._write_chunk(data, index_bodies, t_lo, t_hi))

    def _write_chunk(self, data: bytes, index_bodies: dict[int, bytes], t_lo: int, t_hi: int) -> None:
        """On the I/O thread: compress, write the chunk record and its message-index records."""
        import struct
        import zlib

        from mcap.records import ChunkIndex

        if self._compression == "zstd":
            if self._zstd is None:
                import zstandard

                self._zstd = zstandard.ZstdCompressor(level=1)
            compressed, compression = self._zstd.compress(data), "zstd"
        elif self._compression == "lz4":
            import lz4.frame

            compressed, compression = lz4.frame.compress(data), "lz4"
        else:
            compressed, compression = data, ""
        # the Chunk record (mcap.records.Chunk's layout), written without copying the data into a builder
        comp = compression.encode()
        head = struct.pack(
            f"<QQQI I{len(comp)}sQ", t_lo, t_hi, len(data), zlib.crc32(data), len(comp), comp, len(compressed)
        )
        chunk_start = self._stream.tell()
        self._stream.write(struct.pack("<BQ", _OP_CHUNK, len(head) + len(compressed)) + head)
        self._stream.write(compressed)
        chunk_length = 9 + len(head) + len(compressed)
        index_start = self._stream.tell()
        offsets, parts, pos = {}, [], 0
        for cid, body in index_bodies.items():
            rec = (
                bytes([_OP_MESSAGE_INDEX])
                + (6 + len(body)).to_bytes(8, "little")
                + cid.to_bytes(2, "little")
                + len(body).to_bytes(4, "little")
                + body
            )
            offsets[cid] = index_start + pos
            parts.append(rec)
            pos += len(rec)
        self._stream.write(b"".join(parts))
        self._chunk_indexes.append(
            ChunkIndex(
                message_start_time=t_lo,
                message_end_time=t_hi,
                chunk_start_offset=chunk_start,
                chunk_length=chunk_length,
                message_index_offsets=offsets,
                message_index_length=pos,
                compression=compression,
                compressed_size=len(compressed),
                uncompressed_size=len(data),
            )
        )

    def finish(self) -> None:
        """Write the last chunk, the summary and the footer; stop the I/O thread; close the file."""
        self._finalize_chunk()
        self._submit(self._write_summary)
        self._jobs.put(None)
        self._thread.join()
        self._stream.close()
        if self._error is not None:
            raise RuntimeError(f"MCAP writer failed: {self._error}") from self._error

    def _write_summary(self) -> None:
        import struct
        import zlib

        from mcap.data_stream import RecordBuilder
        from mcap.opcode import Opcode
        from mcap.records import DataEnd, Footer, Statistics, SummaryOffset

        DataEnd(data_section_crc=0).write(self._rb)
        self._flush()
        summary_start = self._stream.tell()
        sb = RecordBuilder()
        groups = []

        def group(opcode, records):
            begin = sb.count
            for r in records:
                r.write(sb)
            if sb.count > begin:
                groups.append(SummaryOffset(opcode, summary_start + begin, sb.count - begin))

        group(Opcode.SCHEMA, self._schemas)
        group(Opcode.CHANNEL, self._channels)
        stats = Statistics(
            message_count=self._n_messages,
            schema_count=len(self._schemas),
            channel_count=len(self._channels),
            attachment_count=0,
            metadata_count=self._metadata_count,
            chunk_count=len(self._chunk_indexes),
            message_start_time=self._t_start or 0,
            message_end_time=self._t_end,
            channel_message_counts=dict(self._counts),
        )
        group(Opcode.STATISTICS, [stats])
        group(Opcode.CHUNK_INDEX, self._chunk_indexes)
        group(Opcode.METADATA_INDEX, self._metadata_indexes)
        summary_offset_start = summary_start + sb.count
        for g in groups:
            g.write(sb)
        summary = sb.end()
        crc = zlib.crc32(summary)
        crc = zlib.crc32(struct.pack("<BQQQ", Opcode.FOOTER, 20, summary_start, summary_offset_start), crc)
        self._stream.write(summary)
        Footer(summary_start=summary_start, summary_offset_start=summary_offset_start, summary_crc=crc).write(
            self._rb
        )
        self._flush()
        self._stream.write(_MAGIC)
