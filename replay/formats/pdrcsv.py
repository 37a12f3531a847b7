"""The contract's own layout: a directory with mag.csv (+ accel.csv, gyro.csv, meta.json, truth.csv).

Odd rows inside a good file (a NaN value, a duplicate timestamp, more fields than the header, a field that
is not a number) are dropped and counted in ``Recording.dropped``; accelerometer/gyroscope samples clipped
at the sensor's range are kept and counted as ``<stream>:saturated``
(:func:`replay.formats._common.flag_saturation`); a file that cannot be right (missing, bad header, a row
with fewer fields than the header, time going backwards, an empty stream, values in the wrong unit) raises
:class:`InputError` naming the file and line.

``meta.json`` becomes ``Recording.meta`` as it is: besides the contract's keys it may state what the phone
knows about itself (INTERFACE.md: ``mag_os_bias_uT``, ``mag_os_bias_changes``, ``gyro_os_bias_rad_s``,
``gyro_os_bias_changes``, ``mag_os_calibrated``, ``gyro_os_calibrated``, ``device_id``, …), passed on
as they are (nothing is added, so :func:`write` and :func:`read` give the same meta back). Without
``mag_os_calibrated`` the magnetometer is the contract's ``mag.csv``: raw; ``gyro.csv`` may be either
("uncalibrated is fine"), so without ``gyro_os_calibrated`` that is not known.
"""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import numpy as np

from replay.errors import InputError
from replay.formats._common import (
    StreamBuilder,
    StreamSpec,
    chunks_of,
    iter_table,
    open_text,
    read_table,
    read_text,
)
from replay.recording import Recording
from replay.source import Feed, RecordingSource

NAME = "pdr-csv"
VECTOR_HEADER = ["t", "x", "y", "z"]
TRUTH_HEADER = ["t", "qw", "qx", "qy", "qz"]

def detect(path: Path) -> bool:
    return path.is_dir() and (path / "mag.csv").is_file()


def _header(fh, path: Path, header: list[str]) -> int:
    """Check the header row (``header`` first; more columns may follow); returns its number of fields, the
    most a row may have."""
    first = fh.readline()
    got = [c.strip() for c in first.strip().split(",")]
    if got[: len(header)] != header:
        shown = first.strip()
        if "\ufffd" in shown or any(ord(c) < 32 and c != "\t" for c in shown):
            raise InputError(path, f"bad header: not text (a binary file?), expected {','.join(header)!r}", 1)
        shown = shown if len(shown) <= 60 else shown[:60] + "…"
        raise InputError(path, f"bad header {shown!r}, expected {','.join(header)!r}", line=1)
    return len(got)


def _read_builder(path: Path, header: list[str], key: str, dropped: Counter) -> StreamBuilder:
    """Parse one whole file (header row, then ``t`` and values) into a cleaning :class:`StreamBuilder`."""
    b = StreamBuilder(path, key, dropped, width=len(header) - 1)
    with open_text(path) as fh:
        most = _header(fh, path, header)
        read_table(fh, path, [(b, list(range(1, len(header))))], len(header), first_line=2, delimiter=",",
                   most=most)
    return b


def vector_feed(path: Path, key: str, dropped: Counter) -> Feed:
    """One ``t,x,y,z`` file, parsed a chunk at a time."""

    def chunks():
        b = StreamBuilder(path, key, dropped)
        with open_text(path) as fh:
            most = _header(fh, path, VECTOR_HEADER)
            steps = iter_table(fh, path, [(b, [1, 2, 3])], 4, 2, ",", most=most)
            yield from chunks_of(fh, {key: b}, steps)

    return Feed((key,), chunks, path.stat().st_size)


def open_source(path) -> RecordingSource:
    """Open a pdr-csv directory: metadata and truth now, the streams as they are read."""
    p = Path(path)
    if not (p / "mag.csv").is_file():
        raise InputError(p / "mag.csv", "missing (a pdr-csv recording needs mag.csv)")
    dropped: Counter = Counter()
    keys = [k for k in ("mag", "accel", "gyro") if (p / f"{k}.csv").is_file()]
    specs = {k: StreamSpec(p / f"{k}.csv", k) for k in keys}
    feeds = [vector_feed(p / f"{k}.csv", k, dropped) for k in keys]
    meta: dict = {}
    if (p / "meta.json").is_file():
        try:
            meta = json.loads(read_text(p / "meta.json"))
        except json.JSONDecodeError as exc:
            raise InputError(p / "meta.json", f"not valid JSON ({exc.msg})", exc.lineno) from None
        if not isinstance(meta, dict):
            raise InputError(p / "meta.json", "expected a JSON object")
    truth = None
    if (p / "truth.csv").is_file():
        b = _read_builder(p / "truth.csv", TRUTH_HEADER, "truth", dropped)
        if len(b) == 0:
            raise InputError(p / "truth.csv", "truth: empty stream (no valid samples)")
        truth = b.arrays()
    references = {}
    if (p / "os.csv").is_file():  # the phone's own fused attitude, same columns as truth.csv
        b = _read_builder(p / "os.csv", TRUTH_HEADER, "os", dropped)
        if len(b):
            references["os"] = b.arrays()
    return RecordingSource(
        specs, feeds, meta=meta, truth=truth, references=references, source=str(p), format=NAME,
        dropped=dropped,
    )


def read(path) -> Recording:
    """Read a pdr-csv directory into a :class:`Recording`."""
    return open_source(path).collect()


def _write_csv(path: Path, header: list[str], t: np.ndarray, values: np.ndarray, fmt: str) -> None:
    data = np.column_stack([t, values])
    with path.open("w", encoding="utf-8", newline="\n") as fh:
        fh.write(",".join(header) + "\n")
        np.savetxt(fh, data, fmt=["%.6f"] + [fmt] * values.shape[1], delimiter=",")


def write(rec: Recording, path, value_fmt: str = "%.6f") -> None:
    """Write a recording as a pdr-csv directory (deterministic text: same input, same bytes)."""
    p = Path(path)
    p.mkdir(parents=True, exist_ok=True)
    _write_csv(p / "mag.csv", VECTOR_HEADER, rec.mag.t, rec.mag.xyz, value_fmt)
    if rec.accel is not None:
        _write_csv(p / "accel.csv", VECTOR_HEADER, rec.accel.t, rec.accel.xyz, value_fmt)
    if rec.gyro is not None:
        _write_csv(p / "gyro.csv", VECTOR_HEADER, rec.gyro.t, rec.gyro.xyz, "%.8f")
    if rec.truth is not None:
        _write_csv(p / "truth.csv", TRUTH_HEADER, rec.truth[0], rec.truth[1], "%.9f")
    if "os" in rec.references:
        _write_csv(p / "os.csv", TRUTH_HEADER, rec.references["os"][0], rec.references["os"][1], "%.9f")
    if rec.meta:
        (p / "meta.json").write_text(json.dumps(rec.meta, indent=1, sort_keys=True) + "\n")
