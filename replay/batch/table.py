"""The fleet table: one row per recording (``DIR/summary.csv``, and ``summary.parquet`` with pyarrow).

:data:`COLUMNS` is the contract (INTERFACE.md): the same columns for the three commands, in this order; a
column that does not apply to the command, or that the recording cannot give (no truth, no phone
attitude, an error), is empty (null in Parquet). Units are in the names (``_s``, ``_uT``, ``_deg``);
shares are in [0, 1]. A ``DIR`` holds one batch: ``summary.csv`` is replaced by each run.
"""

from __future__ import annotations

import csv
import io
import math
import os
from pathlib import Path

#: ``(name, type, meaning)``; type is the Parquet type: ``str``, ``int``, ``float`` or ``bool``.
COLUMNS = (
    ("recording", "str", "the recording's path, as given or as found under a given folder"),
    ("output", "str", "its output folder under DIR (empty when it has none)"),
    ("status", "str", "ok or error"),
    ("error", "str", "the one-line message (FILE[:LINE]: problem) when status is error"),
    ("format", "str", "the reader's format name"),
    ("device", "str", "device name from the recording's metadata"),
    ("duration_s", "float", "replay: span of the output epochs; calibrate/diagnose: of the samples, s"),
    ("n_samples", "int", "accelerometer + gyroscope + magnetometer samples used"),
    ("dropped_samples", "int", "odd samples dropped by the reader or the pipeline, all streams"),
    ("dropped_by_reason", "str", "the same by stream:reason, e.g. 'mag:nan 3; gyro:duplicate_t 1'"),
    ("calibration_file", "str", "replay: the calibration file given (empty: online calibration only)"),
    ("cal_method", "str", "final calibration: method (replay: the last one in effect)"),
    ("cal_offset_x_uT", "float", "final calibration: hard-iron offset x, µT"),
    ("cal_offset_y_uT", "float", "final calibration: hard-iron offset y, µT"),
    ("cal_offset_z_uT", "float", "final calibration: hard-iron offset z, µT"),
    ("cal_offset_std_x_uT", "float", "final calibration: 1-σ of the offset x, µT"),
    ("cal_offset_std_y_uT", "float", "final calibration: 1-σ of the offset y, µT"),
    ("cal_offset_std_z_uT", "float", "final calibration: 1-σ of the offset z, µT"),
    ("cal_field_uT", "float", "final calibration: fitted field strength, µT"),
    ("cal_residual_rms_uT", "float", "final calibration: fit residual RMS, µT"),
    ("cal_coverage", "float", "final calibration: orientation coverage of its samples, [0, 1]"),
    ("cal_accepted", "bool", "final calibration: accepted"),
    ("cal_state", "str", "replay: cal_state of the last output row"),
    ("n_outputs", "int", "replay: output rows (epochs)"),
    ("interference_share", "float", "replay: share of output rows flagged as interference"),
    ("mag_used_share", "float", "replay: share of output rows the magnetometer corrected"),
    ("heading_std_median_deg", "float", "replay: median of heading_std_deg over the rows, deg (±0.005)"),
    ("heading_std_p95_deg", "float", "replay: 95th percentile of heading_std_deg, deg (±0.005)"),
    ("n_events", "int", "replay: events of every kind"),
    ("events_interference", "int", "replay: interference_start events"),
    ("events_calibration_accepted", "int", "replay: calibration_accepted events"),
    ("events_calibration_rejected", "int", "replay: calibration_rejected events"),
    ("events_recalibration_requested", "int", "replay: recalibration_requested events"),
    ("events_recalibrated", "int", "replay: recalibrated events"),
    ("heading_err_truth_median_deg", "float",
     "replay: median |heading error| against truth at the output epochs, deg (±0.005)"),
    ("heading_err_truth_p95_deg", "float", "replay: 95th percentile of the same, deg (±0.005)"),
    ("heading_err_os_median_deg", "float",
     "replay: median |heading error| against the phone's own attitude, deg (±0.005)"),
    ("heading_err_os_p95_deg", "float", "replay: 95th percentile of the same, deg (±0.005)"),
    ("heading_err_truth_p90_deg", "float", "replay: 90th percentile of |heading error| against truth, deg "
                                           "(±0.005)"),
    ("heading_err_truth_over45_share", "float", "replay: share of those epochs with |heading error| > 45°"),
    ("heading_err_os_p90_deg", "float",
     "replay: 90th percentile of |heading error| against the phone's own attitude, deg (±0.005)"),
    ("heading_err_os_over45_share", "float", "replay: share of those epochs with |heading error| > 45°"),
    ("walked_segments", "int", "replay, with waypoints or position fixes: segments scored against the "
                               "walked direction"),
    ("heading_err_walked_median_deg", "float", "replay: median |heading error| against the walked "
                                               "direction over the segments, deg"),
    ("heading_err_walked_mean_deg", "float", "replay: mean of the same, deg"),
    ("heading_err_walked_p95_deg", "float", "replay: 95th percentile (nearest rank) of the same, deg"),
    ("walked_over45", "int", "replay: segments more than 45° off the walked direction"),
    ("walked_within_2sigma_share", "float", "replay: share of the segments with a σ whose |error| ≤ 2σ"),
    ("walked_over45_sigma_le20", "int", "replay: segments more than 45° off with σ ≤ 20° (wrong, confident)"),
    ("diag_orientation", "str", "diagnose: where the orientation came from (gyro+accel or truth)"),
    ("diag_missing_effects", "str", "diagnose: the missing effects named, in order, joined by '+'"),
    ("diag_baseline_gap_uT", "float", "diagnose: gap of the baseline model (hard_iron + noise), µT"),
    ("diag_final_gap_uT", "float", "diagnose: gap of the final model, µT"),
    ("elapsed_s", "float", "wall time the recording took on its worker (reading, processing, writing; a "
                           "worker's first recording also loads the compiled kernels), s"),
)

NAMES = tuple(name for name, _, _ in COLUMNS)
TYPES = {name: kind for name, kind, _ in COLUMNS}

#: Event kinds with a column of their own (``events_<column suffix>``).
EVENT_COLUMNS = {
    "interference_start": "events_interference",
    "calibration_accepted": "events_calibration_accepted",
    "calibration_rejected": "events_calibration_rejected",
    "recalibration_requested": "events_recalibration_requested",
    "recalibrated": "events_recalibrated",
}


def empty_row(recording: str, output: str | None = None) -> dict:
    """A row with every column, empty but ``recording`` and ``output``."""
    row = dict.fromkeys(NAMES)
    row["recording"] = recording
    row["output"] = output
    return row


def error_row(recording: str, message: str, output: str | None = None,
              elapsed_s: float | None = None) -> dict:
    """The row of a recording that failed: ``status`` error and the one-line ``message``."""
    row = empty_row(recording, output)
    row["status"] = "error"
    row["error"] = " ".join(str(message).split())
    row["elapsed_s"] = elapsed_s
    return row


def _cell(value, kind: str) -> str:
    if value is None:
        return ""
    if kind == "bool":
        return "true" if value else "false"
    if kind == "float":
        v = float(value)
        return repr(v) if math.isfinite(v) else ""
    if kind == "int":
        return str(int(value))
    return str(value)


def csv_text(rows) -> str:
    """The rows as CSV text (header first; floats in their shortest round-trip form)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(NAMES)
    for row in rows:
        w.writerow([_cell(row.get(name), TYPES[name]) for name in NAMES])
    return buf.getvalue()


def read_csv(path) -> list[dict]:
    """Rows of a ``summary.csv`` back as typed dicts (empty cells → None)."""
    out = []
    with Path(path).open(newline="", encoding="utf-8") as fh:
        for rec in csv.DictReader(fh):
            row = {}
            for name in NAMES:
                text = rec.get(name, "")
                kind = TYPES[name]
                if text == "" and kind != "str":
                    row[name] = None
                elif kind == "float":
                    row[name] = float(text)
                elif kind == "int":
                    row[name] = int(text)
                elif kind == "bool":
                    row[name] = text == "true"
                else:
                    row[name] = text if text != "" else None
            out.append(row)
    return out


def _replace_atomically(path: Path, write) -> None:
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def write_table(rows, out_dir) -> list[Path]:
    """Write ``summary.csv`` (and ``summary.parquet`` when pyarrow is installed) into ``out_dir``, each
    replaced atomically; return the paths written."""
    out_dir = Path(out_dir)
    rows = list(rows)
    written = [out_dir / "summary.csv"]
    _replace_atomically(written[0], lambda p: p.write_text(csv_text(rows), encoding="utf-8"))
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        return written
    types = {"str": pa.string(), "int": pa.int64(), "float": pa.float64(), "bool": pa.bool_()}
    schema = pa.schema([(name, types[kind]) for name, kind, _ in COLUMNS])
    cols = {}
    for name, kind, _ in COLUMNS:
        vals = [row.get(name) for row in rows]
        if kind == "float":
            vals = [None if v is None or not math.isfinite(float(v)) else float(v) for v in vals]
        cols[name] = vals
    table = pa.table(cols, schema=schema)
    written.append(out_dir / "summary.parquet")
    _replace_atomically(written[1], lambda p: pq.write_table(table, p))
    return written


# ------------------------------------------------------------------------------------------------ headline
#: Per command: the columns the headline shows, and how the rows are ranked (worst first).
HEADLINE = {
    "replay": ("heading_err_truth_p95_deg", "heading_err_walked_p95_deg", "heading_err_os_p95_deg",
               "heading_std_p95_deg", "interference_share", "cal_state"),
    "calibrate": ("cal_accepted", "cal_residual_rms_uT", "cal_coverage", "cal_field_uT", "cal_method"),
    "diagnose": ("diag_final_gap_uT", "diag_baseline_gap_uT", "diag_missing_effects"),
}


def _neg(v) -> float:
    """Sort key part: larger values first, empty last."""
    return -float(v) if v is not None and math.isfinite(float(v)) else math.inf


#: replay: the error figures a row is ranked by, the first the recording has (its truth of any kind).
ERROR_RANK = ("heading_err_truth_p95_deg", "heading_err_walked_p95_deg", "heading_err_os_p95_deg")


def _figure(v) -> float | None:
    return float(v) if v is not None and math.isfinite(float(v)) else None


def worst_first(rows, command: str) -> list[dict]:
    """The rows ranked worst first: errors, then — replay — the recordings with a heading error against
    any truth by that error's p95 (against motion capture when they have it, else the walked direction,
    else the phone's own attitude: :data:`ERROR_RANK`), then those without by the heading σ's p95;
    calibrate: rejected calibrations first, then by residual RMS; diagnose: by the final gap."""
    def key(row):
        head = (row.get("status") != "error",)
        if command == "replay":
            err = next((f for f in (_figure(row.get(c)) for c in ERROR_RANK) if f is not None), None)
            rank = (True, 0.0) if err is None else (False, -err)
            return head + rank + (_neg(row.get("heading_std_p95_deg")),)
        if command == "calibrate":
            return head + (row.get("cal_accepted") is not False, _neg(row.get("cal_residual_rms_uT")))
        return head + (_neg(row.get("diag_final_gap_uT")),)

    return sorted(rows, key=key)


def headline(rows, command: str, top: int = 10) -> str:
    """The fleet table's worst ``top`` rows as aligned text (errors with their message)."""
    cols = HEADLINE[command]
    ranked = worst_first(rows, command)[:top]
    if not ranked:
        return ""
    lines = [["status", *cols, "recording"]]
    for row in ranked:
        if row.get("status") == "error":
            lines.append(["error", row.get("error") or "", row["recording"]])
            continue
        cells = ["ok"]
        for c in cols:
            v = row.get(c)
            if v is None:
                cells.append("-")
            elif isinstance(v, bool):
                cells.append("yes" if v else "no")
            elif isinstance(v, float):
                cells.append(f"{v:.3f}" if "share" in c or "coverage" in c else f"{v:.2f}")
            else:
                cells.append(str(v))
        cells.append(row["recording"])
        lines.append(cells)
    width = [max(len(r[i]) for r in lines if len(r) == len(lines[0]) and i < len(r)) for i in
             range(len(lines[0]))]
    out = []
    for r in lines:
        if len(r) == len(lines[0]):
            out.append("  ".join(c.rjust(w) if 0 < i < len(r) - 1 else c.ljust(w)
                                 for i, (c, w) in enumerate(zip(r, width, strict=True))).rstrip())
        else:  # an error: status, message, recording
            msg = r[1] if r[1].startswith(r[2]) else f"{r[2]}: {r[1]}"
            out.append(f"{r[0]:<{width[0]}}  {msg}")
    return "\n".join(out)
