"""The contract's own layout: a directory with mag.csv (+ accel.csv, gyro.csv, meta.json, truth.csv).

Odd rows inside a good file (a NaN value, a duplicate timestamp) are dropped and counted in
``Recording.dropped``; accelerometer/gyroscope samples clipped at the sensor's range are kept and counted
as ``<stream>:saturated`` (:func:`replay.formats._common.flag_saturation`); a file that cannot be right
(missing, bad header, text in a number column, time going backwards, an empty stream, values in the wrong
unit) raises :class:`InputError` naming the file and line.
"""

from __future__ import annotations

import json
import math
from collections import Counter
from pathlib import Path

import numpy as np

from replay.errors import InputError
from replay.recording import Recording, Stream

NAME = "pdr-csv"
VECTOR_HEADER = ["t", "x", "y", "z"]
TRUTH_HEADER = ["t", "qw", "qx", "qy", "qz"]

# Plausible medians of the vector norm per stream, in the contract's units; outside → wrong unit.
_UNIT_RANGES = {
    "mag": (5.0, 2000.0, "µT"),
    "accel": (3.0, 30.0, "m/s²"),
    "gyro": (0.0, 20.0, "rad/s"),
}


def detect(path: Path) -> bool:
    return path.is_dir() and (path / "mag.csv").is_file()


def _parse_csv(path: Path, header: list[str], dropped: Counter, key: str) -> np.ndarray:
    """Rows of floats (N, len(header)); NaN rows and duplicate times dropped and counted."""
    try:
        fh = path.open("r", encoding="utf-8", newline="")
    except OSError as exc:
        raise InputError(path, f"cannot open ({exc.strerror})") from exc
    ncol = len(header)
    rows: list[list[float]] = []
    with fh:
        first = fh.readline()
        got = [c.strip() for c in first.strip().split(",")]
        if got[:ncol] != header:
            raise InputError(path, f"bad header {first.strip()!r}, expected {','.join(header)!r}", line=1)
        last_t = -math.inf
        for lineno, line in enumerate(fh, start=2):
            s = line.strip()
            if not s:
                continue
            parts = s.split(",")
            if len(parts) < ncol:
                raise InputError(path, f"expected {ncol} columns, got {len(parts)} (truncated file?)", lineno)
            try:
                vals = [float(v) for v in parts[:ncol]]
            except ValueError:
                bad = next(v for v in parts[:ncol] if not _is_float(v))
                raise InputError(path, f"not a number: {bad.strip()!r}", lineno) from None
            if not all(math.isfinite(v) for v in vals):
                dropped[f"{key}:nan"] += 1
                continue
            t = vals[0]
            if t == last_t:
                dropped[f"{key}:duplicate_t"] += 1
                continue
            if t < last_t:
                raise InputError(path, f"time goes backwards ({t!r} after {last_t!r})", lineno)
            last_t = t
            rows.append(vals)
    if not rows:
        raise InputError(path, "empty stream (no valid samples)")
    return np.asarray(rows, dtype=float)


def _is_float(v: str) -> bool:
    try:
        float(v)
        return True
    except ValueError:
        return False


def _check_units(path: Path, key: str, xyz: np.ndarray) -> None:
    lo, hi, unit = _UNIT_RANGES[key]
    med = float(np.median(np.linalg.norm(xyz, axis=1)))
    if not (lo <= med <= hi):
        raise InputError(
            path, f"median |{key}| is {med:.4g}, outside the plausible {lo:g}–{hi:g} {unit} (wrong unit?)"
        )


def read_stream(path: Path, key: str, dropped: Counter) -> Stream:
    arr = _parse_csv(path, VECTOR_HEADER, dropped, key)
    if len(arr) < 2:
        raise InputError(path, "fewer than 2 valid samples")
    _check_units(path, key, arr[:, 1:4])
    from replay.formats._common import flag_saturation

    flag_saturation(key, arr[:, 1:4], dropped)  # counted as "<key>:saturated", samples kept
    return Stream(t=arr[:, 0].copy(), xyz=arr[:, 1:4].copy())


def read(path) -> Recording:
    """Read a pdr-csv directory into a :class:`Recording`."""
    p = Path(path)
    if not (p / "mag.csv").is_file():
        raise InputError(p / "mag.csv", "missing (a pdr-csv recording needs mag.csv)")
    dropped: Counter = Counter()
    mag = read_stream(p / "mag.csv", "mag", dropped)
    accel = read_stream(p / "accel.csv", "accel", dropped) if (p / "accel.csv").is_file() else None
    gyro = read_stream(p / "gyro.csv", "gyro", dropped) if (p / "gyro.csv").is_file() else None
    meta: dict = {}
    if (p / "meta.json").is_file():
        try:
            meta = json.loads((p / "meta.json").read_text())
        except json.JSONDecodeError as exc:
            raise InputError(p / "meta.json", f"not valid JSON ({exc.msg})", exc.lineno) from None
        if not isinstance(meta, dict):
            raise InputError(p / "meta.json", "expected a JSON object")
    truth = None
    if (p / "truth.csv").is_file():
        arr = _parse_csv(p / "truth.csv", TRUTH_HEADER, dropped, "truth")
        truth = (arr[:, 0].copy(), arr[:, 1:5].copy())
    return Recording(
        mag=mag, accel=accel, gyro=gyro, meta=meta, truth=truth, source=str(p), format=NAME, dropped=dropped
    )


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
    if rec.meta:
        (p / "meta.json").write_text(json.dumps(rec.meta, indent=1, sort_keys=True) + "\n")
