"""``pdr-mag diagnose REC [--json FILE] [--report DIR] [--use-truth]``: simulation vs measured.

Estimates the orientation from the recording's gyroscope and accelerometer (``truth.csv`` only with
``--use-truth``), fits the baseline sensor model (hard_iron + noise), simulates the magnetometer with
:mod:`pdr_mag.sim.sensor_model`, names the missing effects one by one and shows the gap shrink.  Writes the
``diagnose --json`` object of INTERFACE.md (``--json -``: to stdout) and, with ``--report DIR``, a Markdown
report with plots (needs matplotlib: the ``report`` extra).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import click
import numpy as np

from pdr_mag.modelcheck import diagnose
from pdr_mag.modelcheck.report import write_report
from replay.commands._output import writable_dir, writable_file
from replay.errors import InputError
from replay.formats import read_recording
from replay.recording import Recording


def _temperature(recording):
    """A temperature channel ``(t, °C)`` if the reader provides one, else None."""
    for cand in (getattr(recording, "temperature", None), (recording.meta or {}).get("temperature")):
        if cand is None:
            continue
        t = getattr(cand, "t", None)
        v = getattr(cand, "xyz", None)
        if v is None:
            v = getattr(cand, "values", None)
        if t is None and isinstance(cand, (tuple, list)) and len(cand) == 2:
            t, v = cand
        if t is None or v is None:
            continue
        t = np.asarray(t, dtype=float)
        v = np.asarray(v, dtype=float).reshape(len(t), -1)[:, 0]
        if len(t) >= 2 and np.all(np.isfinite(v)):
            return t, v
    return None


@click.command()
@click.argument("rec", type=click.Path(path_type=Path))
@click.option("--json", "json_path", type=click.Path(path_type=Path, dir_okay=False, allow_dash=True),
              help="Write the diagnosis (INTERFACE.md diagnose --json) to FILE ('-': stdout).")
@click.option("--report", "report_dir", type=click.Path(path_type=Path, file_okay=False),
              help="Write report.md with plots into DIR (needs matplotlib).")
@click.option("--use-truth", is_flag=True,
              help="Evaluation mode: predict along truth.csv, not the gyro + accelerometer orientation.")
def command(rec: Path, json_path: Path | None, report_dir: Path | None, use_truth: bool) -> int:
    """Compare the sensor model with recording REC, name the missing effects, refit."""
    if report_dir is not None:
        need_matplotlib()
    if json_path is not None and str(json_path) != "-":
        writable_file(json_path)
    if report_dir is not None:
        writable_dir(report_dir)
    res = run(rec, use_truth=use_truth)
    if json_path is not None:
        if str(json_path) == "-":
            click.echo(json_text(res.result))
        else:
            write_json(res.result, json_path)
    if report_dir is not None:
        write_report_dir(res, report_dir, title=str(rec))
    if str(json_path) != "-":
        click.echo(summary(res.result, rec))
    return 0


@dataclass(frozen=True)
class DiagnoseResult:
    """What ``pdr-mag diagnose`` finds for one recording."""

    #: The :class:`pdr_mag.modelcheck.Diagnosis` (for the report).
    diagnosis: object
    #: Its ``diagnose --json`` object, with ``source``.
    result: dict
    #: The recording as read.
    recording: Recording


def need_matplotlib() -> None:
    """A click error when ``--report`` cannot be written (matplotlib missing)."""
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        raise click.ClickException(
            "--report needs matplotlib, which is not installed (pip install 'pdr_mag[report]')"
        ) from None


def run(rec: Path, use_truth: bool = False, source: str | None = None) -> DiagnoseResult:
    """What ``pdr-mag diagnose`` does with one recording (``source``: the name the result gives it, when it
    is read under another path); :class:`InputError` on bad input."""
    recording = read_recording(rec)
    if use_truth:
        if recording.truth is None:
            raise InputError(rec, "--use-truth: the recording has no truth (truth.csv)")
    else:
        for name in ("gyro", "accel"):
            s = getattr(recording, name)
            if s is None or len(s) < 10:
                raise InputError(rec, f"no {name} stream: diagnose needs gyro and accel for the orientation")
    if len(recording.mag) < 50:
        raise InputError(rec, f"need at least 50 magnetometer samples, got {len(recording.mag)}")
    g, a = recording.gyro, recording.accel
    try:
        diag = diagnose(
            recording.mag.t, recording.mag.xyz,
            None if g is None else g.t, None if g is None else g.xyz,
            None if a is None else a.t, None if a is None else a.xyz,
            truth=recording.truth, use_truth=use_truth, temperature=_temperature(recording),
        )
    except ValueError as exc:
        raise InputError(rec, f"diagnose failed: {exc}") from None
    out = diag.to_dict()
    out["source"] = str(rec) if source is None else source
    out["dropped_samples"] = dict(recording.dropped)
    return DiagnoseResult(diag, out, recording)


def json_text(out: dict) -> str:
    """The ``diagnose --json`` text (without the final newline)."""
    return json.dumps(out, indent=1, ensure_ascii=False)


def write_json(out: dict, json_path: Path) -> None:
    """Write the ``diagnose --json`` file."""
    try:
        json_path.write_text(json_text(out) + "\n", encoding="utf-8")
    except OSError as exc:
        raise InputError(json_path, f"cannot write ({exc.strerror})") from None


def write_report_dir(res: DiagnoseResult, report_dir: Path, title: str) -> None:
    """Write ``report.md`` with plots into ``report_dir`` (needs matplotlib)."""
    try:
        write_report(res.diagnosis, report_dir, title=title)
    except OSError as exc:
        raise InputError(report_dir, f"cannot write the report ({exc.strerror})") from None


def summary(d: dict, rec) -> str:
    """A few human-readable lines."""
    lines = [f"diagnose {rec}: {d['n_samples']} mag samples, {d['duration_s']:.1f} s, orientation "
             f"from {d['orientation']}",
             f"  baseline {'+'.join(d['baseline']['effects'])}: gap {d['baseline']['gap']:.3f} µT"]
    added = d["missing_effects"]
    acc = d.get("gyro_bias_from_accelerometer") or {}
    if acc.get("named"):
        b = np.degrees(np.linalg.norm(acc["rad_per_s"]))
        lines.append(f"  accelerometer: gyro_bias (|b| {b:.2f} °/s where it sees it, T² {acc['t2']} > "
                     f"{acc['threshold']}; in the orientation from the start: the final model's gap along "
                     f"the raw gyro {acc['gap_raw_gyro']:.3f} µT, {acc['gap_with']:.3f} µT with it) — added")
        added = [e for e in added if e != "gyro_bias" or any(
            c["effect"] == "gyro_bias" and c["significant"] for r in d["rounds"] for c in r)]
    for i, rnd in enumerate(d["rounds"]):
        # the round's line names the effect added in it (chosen after the null test, not always the top
        # score); a round that added nothing names its best score
        pick = [c for c in rnd if i < len(added) and c["effect"] == added[i]]
        best = pick[0] if pick else max(
            rnd, key=lambda c: c["score"] if c["score"] is not None else -np.inf, default=None)
        if best is None:
            continue
        mark = "added" if pick else "not significant"
        if not pick and best.get("null") and not best["null"]["passed"]:
            mark = "not significant: it fits no more than on the recording's own null"
        lines.append(f"  round {best['round']}: {'' if pick else 'best '}{best['effect']} (score "
                     f"{best['score']}, gap {best['gap']:.3f} µT) — {mark}")
    lines.append(f"  missing effects: {', '.join(d['missing_effects']) or 'none'}")
    lines.append(f"  final {'+'.join(d['final']['effects'])}: gap {d['final']['gap']:.3f} µT")
    lag = d["final"].get("estimate", {}).get("time_offset")
    if lag is not None:  # the one effect the heading pipeline takes as a setting
        lines.append(f"  the magnetometer's latency {lag['seconds']:.4f} s (± {lag['std']:.4f}): "
                     f"pdr-mag replay --mag-time-offset {lag['seconds']:.3f} applies it")
    lines += identifiability_lines(d.get("identifiability", {}))
    return "\n".join(lines)


def identifiability_lines(ident: dict) -> list[str]:
    """What the motion could reveal, every candidate effect in one of the lines (none left out)."""
    by: dict[str, list[str]] = {}
    for e, v in ident.items():
        by.setdefault(v["status"], []).append(e)
    lines = []
    if by.get("not_significant"):
        lines.append(f"  identifiable, not significant: {', '.join(by['not_significant'])}")
    for status, head in (("not_identifiable", "not identifiable from this motion"),
                         ("partly_identifiable", "partly identifiable (not significant where identifiable)")):
        for e in by.get(status, []):
            v = ident[e]
            reveal = f" — would be revealed by {v['reveal']}" if v["reveal"] else ""
            lines.append(f"  {head}: {e}: {v['reason']}{reveal}")
    for e in by.get("named", []):
        v = ident[e]
        if v["reason"]:
            reveal = f" — would be revealed by {v['reveal']}" if v["reveal"] else ""
            lines.append(f"  named, not identified in every direction: {e}: {v['reason']}{reveal}")
    if by.get("not_tried"):
        lines.append("  not tried: " + "; ".join(f"{e} ({ident[e]['reason']})" for e in by["not_tried"]))
    return lines
