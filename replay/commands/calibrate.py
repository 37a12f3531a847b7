"""``pdr-mag calibrate REC [--method auto|sphere|ellipsoid|als|ml] [--latitude DEG --longitude DEG
[--altitude M]] [--date YYYY-MM-DD] [--json FILE]``: batch calibration.

Reads the recording (any format a reader recognises), fits :func:`pdr_mag.calibration.calibrate` on the
raw magnetometer, uses the accelerometer's quasi-static instants (if any) for the magnetometer → IMU
alignment and the WMM field of ``meta.json`` (position + date, or the options'
:mod:`replay.commands._place`) for the radius check, prints a short summary and writes the ``calibrate
--json`` object of INTERFACE.md (also the ``replay --calibration`` file).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import click
import numpy as np

from pdr_mag.calibration import calibrate
from pdr_mag.calibration.alignment import quasi_static_accel
from pdr_mag.calibration.model import MagCalibration
from pdr_mag.field import earth_field_from_meta
from replay.commands._output import writable_file
from replay.commands._place import apply_place, place_of, place_options
from replay.errors import InputError
from replay.formats import read_recording
from replay.recording import Recording

#: the estimators `--method` accepts (also `pdr-mag batch calibrate`)
METHODS = ("auto", "sphere", "ellipsoid", "als", "ml", "radial", "lm9", "twostep")


@click.command()
@click.argument("rec", type=click.Path(path_type=Path))
@click.option("--method", type=click.Choice(METHODS), default="auto", show_default=True,
              help="Estimator: auto (geometric ML, model by BIC), sphere, ellipsoid, als, ml; "
                   "also radial (seed 000), lm9 (seed 001), twostep.")
@place_options
@click.option("--json", "json_path", type=click.Path(path_type=Path, dir_okay=False),
              help="Write the calibration (INTERFACE.md calibrate --json) to FILE.")
def command(rec: Path, method: str, latitude, longitude, altitude, date, json_path: Path | None) -> int:
    """Calibrate the magnetometer of recording REC (hard and soft iron, quality, acceptance)."""
    place, day = place_of(latitude, longitude, altitude, date)
    if json_path is not None:
        writable_file(json_path)
    fit = run(rec, method, place=place, date=day)
    if json_path is not None:
        write(fit.calibration, json_path)
    click.echo(summary(fit.calibration, rec, fit.field))
    return 0


@dataclass(frozen=True)
class CalibrateResult:
    """What ``pdr-mag calibrate`` finds for one recording."""

    #: The fit, with ``extra`` holding ``source``, the WMM field and the reader's dropped samples.
    calibration: MagCalibration
    #: The WMM field at the recording's position and date, or None.
    field: object
    #: The recording as read (its metadata and streams, for a caller's report).
    recording: Recording


def run(rec: Path, method: str = "auto", source: str | None = None, place: tuple | None = None,
        date: str | None = None) -> CalibrateResult:
    """What ``pdr-mag calibrate`` does with one recording (``source``: the name ``extra.source`` gives it,
    when it is read under another path; ``place``, ``date``: the options', :func:`.place_of`);
    :class:`InputError` on bad input."""
    recording = read_recording(rec)
    apply_place(recording.meta, rec, place, date)
    mag_file = rec / "mag.csv" if rec.is_dir() else rec
    mag = np.asarray(recording.mag.xyz, dtype=float)
    if mag.ndim != 2 or mag.shape[1] != 3 or len(mag) < 4:
        raise InputError(mag_file, f"need at least 4 magnetometer samples, got {len(mag)}")
    try:
        field = earth_field_from_meta(recording.meta or {})
    except (ValueError, TypeError) as exc:
        raise InputError(rec / "meta.json" if rec.is_dir() else rec, f"bad position/date: {exc}") from None
    accel = None
    acc = recording.accel
    if acc is not None and len(acc) >= 3:
        accel = quasi_static_accel(acc.t, acc.xyz, recording.mag.t)
        if not np.any(np.isfinite(accel[:, 0])):
            accel = np.full_like(mag, np.nan)  # no quasi-static instants: alignment reported as not estimated
    try:
        cal = calibrate(mag, method=method, accel=accel, field=field)
    except ValueError as exc:
        raise InputError(mag_file, f"calibration failed: {exc}") from None
    extra = dict(cal.extra)
    extra["source"] = str(rec) if source is None else source
    if field is not None:
        extra["wmm"] = {"strength_uT": field.strength, "inclination_deg": field.inclination_deg,
                        "declination_deg": field.declination_deg, "model": field.model}
    if recording.dropped:
        extra["dropped_samples"] = dict(recording.dropped)
    return CalibrateResult(replace(cal, extra=extra), field, recording)


def write(cal: MagCalibration, json_path: Path) -> None:
    """Write the ``calibrate --json`` file."""
    try:
        cal.to_json(json_path)
    except OSError as exc:
        raise InputError(json_path, f"cannot write ({exc.strerror})") from None


def summary(cal, rec, field) -> str:
    """A few human-readable lines about a calibration."""
    ex = cal.extra
    model = ex.get("model")
    head = f"calibrate {rec}: method {cal.method}" + (f" (model {model})" if model else "")
    head += f", {cal.n_samples} samples, coverage {cal.coverage:.0%}"
    off = ", ".join(f"{v:.2f}" for v in cal.offset)
    std = ", ".join(f"{v:.2f}" for v in cal.offset_std_uT)
    lines = [head, f"  offset     [{off}] µT  (1-σ [{std}])"]
    fl = f"  field      {cal.field_uT:.2f} µT"
    if field is not None:
        fl += f"  (WMM {field.strength:.2f} µT, {cal.field_uT / field.strength - 1:+.1%})"
    fl += f"   residual RMS {cal.residual_rms_uT:.2f} µT"
    lines.append(fl)
    ev = np.linalg.eigvalsh(cal.soft_iron_array)
    lines.append("  soft iron  eigenvalues " + " ".join(f"{v:.3f}" for v in ev))
    fig = ex.get("heading")
    if isinstance(fig, dict) and fig.get("std_deg") is not None:
        lines.append(f"  heading    ±{fig['std_deg']:.2f}° (1-σ, worst heading and pose) left by the "
                     f"calibration")
    if "alignment" in ex:
        al = ex["alignment"]
        if al is None:
            lines.append("  alignment  not estimated (too few quasi-static accelerometer samples)")
        else:
            if al["significant"]:
                lines.append(f"  alignment  {al['angle_deg']:.2f}° ± {al['angle_std_deg']:.2f}° from "
                             f"{al['n_used']} static samples: applied (mag_to_imu)")
            elif "poses" in al.get("reason", "") or "dip" in al.get("reason", ""):
                lines.append(f"  alignment  not estimable from {al['n_used']} static samples: "
                             f"{al['reason']}; identity kept")
            else:
                lines.append(f"  alignment  {al['angle_deg']:.2f}° ± {al['angle_std_deg']:.2f}° from "
                             f"{al['n_used']} static samples: {al.get('reason', '')}, identity kept")
    if cal.accepted:
        lines.append("  ACCEPTED")
    else:
        lines.append("  REJECTED: " + "; ".join(cal.reasons))
    return "\n".join(lines)
