"""One recording's work in a batch: a picklable :class:`Task` and :func:`run_task`, which a Dask worker (or
any caller) runs and which returns the recording's fleet-table row.

The work is the single command's own code (:func:`replay.commands.replay.run`,
:func:`replay.commands.calibrate.run`, :func:`replay.commands.diagnose.run`), so the files are those the
single command writes for the same recording, byte for byte:

========== ============================================================================================
command    files in the recording's output folder
========== ============================================================================================
replay     ``heading.csv`` (``--out-csv``), ``replay.json`` (``--json``); ``replay.mcap``, ``replay.rrd``
           on request
calibrate  ``calibration.json`` (``--json``)
diagnose   ``diagnose.json`` (``--json``); ``report/`` (``--report``) on request
========== ============================================================================================

plus :data:`ROW_FILE`, the recording's fleet-table row and the command and options that made it.

Atomic outputs
--------------
The files are written into a hidden staging folder beside the output folder, which is renamed into place
when everything is written (a rename within one file system is atomic): an output folder is complete or
absent, never half-written. A worker killed mid-recording leaves only its staging folder, which the next
attempt at that recording removes. A recording that fails leaves no output folder (an earlier run's is
removed: the folder always reflects the latest attempt).
"""

from __future__ import annotations

import json
import os
import shutil
import time
import uuid
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

from replay.batch.metrics import FleetMetrics
from replay.batch.table import EVENT_COLUMNS, empty_row, error_row
from replay.commands import calibrate, diagnose
from replay.commands import replay as replay_command
from replay.errors import InputError
from replay.run import load_calibration

#: The file in each output folder holding its fleet-table row and how it was made.
ROW_FILE = "batch.json"

#: Commands and their options with defaults (the single command's option names, as flags for files).
OPTIONS = {
    "replay": {"mcap": False, "rrd": False, "place": None, "date": None, "mag_time_offset": 0.0},
    "calibrate": {"method": "auto", "place": None, "date": None},
    "diagnose": {"report": False, "use_truth": False},
}


@dataclass(frozen=True)
class Task:
    """One recording to process: everything a worker needs, with absolute paths.

    Attributes
    ----------
    command : str
        ``replay``, ``calibrate`` or ``diagnose``.
    label, path, key : str
        As :class:`replay.batch.inputs.Item`: the recording's name in outputs, its absolute path, its
        output folder under ``out_dir``.
    out_dir : str
        The batch's output folder, absolute.
    options : dict
        The command's options (:data:`OPTIONS`).
    calibration, calibration_path : str or None
        ``replay``: the calibration file, as named and absolute.
    """

    command: str
    label: str
    path: str
    key: str
    out_dir: str
    options: dict = field(default_factory=dict)
    calibration: str | None = None
    calibration_path: str | None = None

    @property
    def output(self) -> Path:
        return Path(self.out_dir) / self.key

    def files(self) -> list[str]:
        """The files (relative to the output folder) the task writes, :data:`ROW_FILE` last."""
        o = self.options
        if self.command == "replay":
            names = ["heading.csv", "replay.json"]
            names += ["replay.mcap"] * bool(o.get("mcap")) + ["replay.rrd"] * bool(o.get("rrd"))
        elif self.command == "calibrate":
            names = ["calibration.json"]
        else:
            names = ["diagnose.json"] + ["report/report.md"] * bool(o.get("report"))
        return [*names, ROW_FILE]

    def made_by(self) -> dict:
        """What decides the outputs: a complete folder made by another command, other options, another
        calibration file or for another recording is redone."""
        return {"command": self.command, "recording": self.label,
                "options": dict(sorted(self.options.items())), "calibration": self.calibration}


def completed_row(task: Task) -> dict | None:
    """The row stored in a complete output folder made the same way, else None (the task must run)."""
    out = task.output
    try:
        stored = json.loads((out / ROW_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(stored, dict) or stored.get("made_by") != task.made_by():
        return None
    if not all((out / name).is_file() for name in task.files()):
        return None
    row = stored.get("row")
    return row if isinstance(row, dict) else None


# ------------------------------------------------------------------------------------------------- running
def run_task(task: Task) -> dict:
    """Process one recording and return its fleet-table row; never raises for the recording's own problems
    (bad input, or any failure inside the work: ``status`` error, the one-line message in ``error``)."""
    t_start = time.perf_counter()
    out = task.output
    stage = out.with_name(f".{out.name}.part-{uuid.uuid4().hex[:12]}")
    try:
        _remove_stale(out)
        stage.mkdir(parents=True)
        row = _RUNNERS[task.command](task, stage)
        row["status"] = "ok"
        row["elapsed_s"] = time.perf_counter() - t_start
        text = json.dumps({"made_by": task.made_by(), "row": row}, indent=1, allow_nan=False)
        (stage / ROW_FILE).write_text(text + "\n", encoding="utf-8")
        _publish(stage, out)
        return row
    except Exception as exc:  # noqa: BLE001 — one recording's failure is a row, never the batch's end
        msg = str(exc) if isinstance(exc, InputError) else f"{type(exc).__name__}: {exc}"
        for path, name in ((str(stage), str(out)), (task.path, task.label),
                           (task.calibration_path, task.calibration)):
            if path and name:
                msg = msg.replace(path, name)
        if not isinstance(exc, InputError) and not msg.startswith(task.label):
            msg = f"{task.label}: {msg}"
        try:
            _discard(out)
        except OSError:
            pass
        return error_row(task.label, msg, elapsed_s=time.perf_counter() - t_start)
    finally:
        if stage.exists():
            shutil.rmtree(stage, ignore_errors=True)


def _remove_stale(out: Path) -> None:
    """Remove staging folders that earlier attempts at this output left (a killed worker's)."""
    parent = out.parent
    if not parent.is_dir():
        return
    for p in parent.glob(f".{out.name}.part-*"):
        shutil.rmtree(p, ignore_errors=True)
    for p in parent.glob(f".{out.name}.old-*"):
        shutil.rmtree(p, ignore_errors=True)


def _discard(out: Path) -> None:
    """Remove an output folder (renamed aside first, so it disappears at once)."""
    if out.exists():
        old = out.with_name(f".{out.name}.old-{uuid.uuid4().hex[:12]}")
        os.rename(out, old)
        shutil.rmtree(old, ignore_errors=True)


def _publish(stage: Path, out: Path) -> None:
    """Put the staging folder in the output folder's place (an earlier output folder goes first)."""
    _discard(out)
    os.rename(stage, out)


# -------------------------------------------------------------------------------------- per command
def _common(row: dict, rec) -> None:
    """Format, device, duration, samples and dropped samples of a recording read whole."""
    streams = [s for s in (rec.mag, rec.accel, rec.gyro) if s is not None]
    row["format"] = rec.format or None
    row["device"] = (rec.meta or {}).get("device")
    row["duration_s"] = rec.t1 - rec.t0 if any(len(s) for s in streams) else 0.0
    row["n_samples"] = sum(len(s) for s in streams)
    _dropped(row, rec.dropped)


def _dropped(row: dict, dropped) -> None:
    row["dropped_samples"] = int(sum(dropped.values()))
    row["dropped_by_reason"] = "; ".join(f"{k} {v}" for k, v in sorted(dropped.items())) or None


def _calibration(row: dict, cal: dict) -> None:
    """The ``cal_*`` columns from a calibration's dict (``MagCalibration.to_dict``)."""
    row["cal_method"] = cal.get("method")
    for axis, v in zip("xyz", cal.get("offset_uT") or (None,) * 3, strict=True):
        row[f"cal_offset_{axis}_uT"] = v
    for axis, v in zip("xyz", cal.get("offset_std_uT") or (None,) * 3, strict=True):
        row[f"cal_offset_std_{axis}_uT"] = v
    row["cal_field_uT"] = cal.get("field_uT")
    row["cal_residual_rms_uT"] = cal.get("residual_rms_uT")
    row["cal_coverage"] = cal.get("coverage")
    row["cal_accepted"] = cal.get("accepted")


def _where(options: dict) -> dict:
    """The ``place`` and ``date`` keywords of the single commands' ``run`` from a task's options."""
    place = options.get("place")
    return {"place": None if place is None else tuple(place), "date": options.get("date")}


def _run_replay(task: Task, stage: Path) -> dict:
    cal = load_calibration(task.calibration_path) if task.calibration_path else None
    metrics = FleetMetrics()
    o = task.options
    summary = replay_command.run(
        Path(task.path), cal, out_csv=stage / "heading.csv", json_path=stage / "replay.json",
        mcap=stage / "replay.mcap" if o.get("mcap") else None,
        rrd=stage / "replay.rrd" if o.get("rrd") else None,
        progress=False, sinks=[metrics], source=task.label, mag_time_offset=o.get("mag_time_offset", 0.0),
        **_where(o),
    )
    row = empty_row(task.label, task.key)
    row["format"] = summary.get("format") or None
    row["device"] = metrics.meta.get("device")
    row["duration_s"] = summary["duration_s"]
    row["n_samples"] = int(sum(summary["n_samples"].values()))
    _dropped(row, summary["dropped_samples"])
    row["calibration_file"] = task.calibration
    if summary["calibrations"]:
        _calibration(row, summary["calibrations"][-1])
    row["cal_state"] = summary.get("cal_state")
    row["n_outputs"] = summary["n_outputs"]
    row["interference_share"] = metrics.share(metrics.n_interference)
    row["mag_used_share"] = metrics.share(metrics.n_mag_used)
    row["heading_std_median_deg"], row["heading_std_p95_deg"] = metrics.heading_std.quantiles(0.5, 0.95)
    row["n_events"] = len(summary["events"])
    kinds = Counter(e["kind"] for e in summary["events"])
    for kind, col in EVENT_COLUMNS.items():
        row[col] = kinds.get(kind, 0)
    for name, e in summary["heading_error"].items():
        for col, key in (("median", "median_deg"), ("p90", "p90_deg"), ("p95", "p95_deg")):
            row[f"heading_err_{name}_{col}_deg"] = e[key]
        row[f"heading_err_{name}_over45_share"] = e["share_over_45"]
    w = summary["walked_direction"]
    if w is not None:
        row["walked_segments"] = w["n_segments"]
        for col in ("median", "mean", "p95"):
            row[f"heading_err_walked_{col}_deg"] = w[f"{col}_deg"]
        row["walked_over45"] = w["n_over_45"]
        row["walked_within_2sigma_share"] = w["within_2sigma_share"]
        row["walked_over45_sigma_le20"] = w["n_over_45_sigma_le_20"]
    return row


def _run_calibrate(task: Task, stage: Path) -> dict:
    o = task.options
    res = calibrate.run(Path(task.path), o.get("method", "auto"), source=task.label, **_where(o))
    calibrate.write(res.calibration, stage / "calibration.json")
    row = empty_row(task.label, task.key)
    _common(row, res.recording)
    _calibration(row, res.calibration.to_dict())
    return row


def _run_diagnose(task: Task, stage: Path) -> dict:
    res = diagnose.run(Path(task.path), use_truth=bool(task.options.get("use_truth")), source=task.label)
    diagnose.write_json(res.result, stage / "diagnose.json")
    if task.options.get("report"):
        diagnose.write_report_dir(res, stage / "report", title=task.label)
    row = empty_row(task.label, task.key)
    _common(row, res.recording)
    d = res.result
    row["diag_orientation"] = d.get("orientation")
    row["diag_missing_effects"] = "+".join(d.get("missing_effects") or []) or None
    row["diag_baseline_gap_uT"] = d["baseline"]["gap"]
    row["diag_final_gap_uT"] = d["final"]["gap"]
    return row


_RUNNERS = {"replay": _run_replay, "calibrate": _run_calibrate, "diagnose": _run_diagnose}
