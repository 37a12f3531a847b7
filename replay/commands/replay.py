"""``pdr-mag replay REC [--calibration FILE] [--device-store DIR] [--ignore-phone-calibration]
[--mag-time-offset S|auto] [--latitude DEG --longitude DEG [--altitude M]] [--date YYYY-MM-DD]
[--out-csv FILE] [--mcap FILE [--mcap-rate HZ]] [--rrd FILE] [--json FILE]``.

``--latitude``/``--longitude`` (``--altitude``) and ``--date`` say where and when the recording was made
when it does not (:mod:`replay.commands._place`).  With them the field model gives the reference field and
the declination (true north); without a place the online calibration must find the field's strength and dip
as well as the offset, which a phone held flat cannot reveal (benchmarks/NOTES.md: the 42 tyrex walks in
mode b 5.3° with the place, 19.1° without)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import click

from pdr_mag.calibration.latency import applies
from pdr_mag.calibration.prior import PriorSettings
from pdr_mag.calibration.store import DeviceStore
from pdr_mag.pipeline import PipelineSettings
from pdr_mag.pipeline.settings import MAX_MAG_TIME_OFFSET_S
from replay.commands._output import writable_file
from replay.commands._place import apply_place, place_of, place_options
from replay.compiling import announced
from replay.console import summary_table
from replay.errors import InputError
from replay.formats import open_recording
from replay.run import (
    LATENCY_SPAN_S,
    CsvSink,
    estimate_latency,
    load_calibration,
    make_sink,
    replay,
)


class LatencyParam(click.ParamType):
    """``--mag-time-offset``: seconds within ±``MAX_MAG_TIME_OFFSET_S``, or ``auto``."""

    name = "latency"

    def convert(self, value, param, ctx):
        if isinstance(value, float) or value == "auto":
            return value
        try:
            x = float(value)
        except ValueError:
            self.fail(f"{value!r} is neither a number of seconds nor 'auto'", param, ctx)
        if not abs(x) <= MAX_MAG_TIME_OFFSET_S:
            self.fail(f"{value} s is beyond ±{MAX_MAG_TIME_OFFSET_S} s (a clock problem, not a latency)",
                      param, ctx)
        return x


@click.command()
@click.argument("rec", type=click.Path(path_type=Path))
@click.option("--calibration", type=click.Path(path_type=Path), help="calibrate --json file of the device.")
@click.option(
    "--device-store",
    type=click.Path(path_type=Path, file_okay=False),
    metavar="DIR",
    help="A store of the devices' calibrations: start from this device's entry (aged; a prior the data may "
    "replace) and leave what the run learnt there.",
)
@click.option(
    "--ignore-phone-calibration",
    is_flag=True,
    help="Do not start from the phone's own hard-iron and gyro estimates that the recording carries.",
)
@click.option(
    "--mag-time-offset",
    type=LatencyParam(),
    default="0",
    metavar="S|auto",
    help="The magnetometer's latency against the IMU, s: a sample stamped t was measured at t − S "
    "(diagnose's time_offset); auto: estimated from the recording's first 60 s, used when determined and "
    "positive. Default 0.",
)
@place_options
@click.option("--out-csv", type=click.Path(path_type=Path), help="Estimates, one row per output epoch.")
@click.option(
    "--mcap", type=click.Path(path_type=Path), help="MCAP file with inputs, outputs and references."
)
@click.option(
    "--mcap-rate",
    type=click.FloatRange(min=0, min_open=True),
    metavar="HZ",
    help="At most HZ messages a second on each high-rate MCAP topic (default: every message). "
    "Writes faster; the file is then for viewing, not for replaying.",
)
@click.option("--rrd", type=click.Path(path_type=Path), help="rerun recording (.rrd).")
@click.option("--viewer", is_flag=True, help="Also stream to a live rerun viewer (started for you).")
@click.option("--json", "json_path", type=click.Path(path_type=Path), help="Run summary as JSON.")
@click.option(
    "--progress/--no-progress", default=None, help="Progress bar (default: long recordings on a tty)."
)
@click.option("--quiet", "-q", is_flag=True, help="No summary table.")
def command(rec, calibration, device_store, ignore_phone_calibration, mag_time_offset, latitude, longitude,
            altitude, date, out_csv, mcap, mcap_rate, rrd, viewer, json_path, progress, quiet):
    """Replay recording REC through the heading pipeline (online calibration unless --calibration)."""
    cal = load_calibration(calibration) if calibration is not None else None
    if cal is not None and not cal.accepted:
        why = "; ".join(cal.reasons) or "no reason given"
        msg = f"pdr-mag: warning: {calibration}: this calibration was not accepted ({why}); using it"
        click.echo(msg, err=True)
    if mcap_rate is not None and mcap is None:
        raise click.UsageError("--mcap-rate needs --mcap FILE")
    place, day = place_of(latitude, longitude, altitude, date)
    with announced():
        summary = run(rec, cal, out_csv=out_csv, json_path=json_path, mcap=mcap, mcap_rate=mcap_rate,
                      rrd=rrd, viewer=viewer, progress=progress, device_store=device_store,
                      use_phone=not ignore_phone_calibration, place=place, date=day,
                      mag_time_offset=mag_time_offset)
    if not quiet:
        click.echo(summary_table(summary))
    return 0


def run(rec, cal=None, *, out_csv=None, json_path=None, mcap=None, mcap_rate=None, rrd=None, viewer=False,
        progress=None, sinks=(), source=None, device_store=None, use_phone=True, place=None,
        date=None, mag_time_offset=0.0) -> dict:
    """What ``pdr-mag replay`` does with one recording: replay it into the requested files.

    Parameters
    ----------
    rec : path or RecordingSource
        The recording.
    cal : MagCalibration or None
        The device calibration (None: online calibration only).
    out_csv, json_path, mcap, rrd : path or None
        The ``--out-csv``, ``--json``, ``--mcap`` and ``--rrd`` files (checked writable before the work, their
        folders created).
    mcap_rate : float or None
        ``--mcap-rate``: the MCAP sink's rate limit of the high-rate topics, Hz.
    viewer : bool
        Also stream to a live rerun viewer.
    progress : bool or None
        As :func:`replay.run.replay`.
    sinks : sequence of Sink
        More sinks fed with the same run (``pdr-mag batch``'s fleet-table metrics).
    source : str, optional
        The name the outputs give the recording (``source``), when ``rec`` is opened under another path.
    device_store : path or None
        ``--device-store``: the folder of the device calibration store.
    use_phone : bool
        False: ``--ignore-phone-calibration``.
    place : tuple or None
        ``--latitude``, ``--longitude`` (degrees) and ``--altitude`` (metres, or None).
    date : str or None
        ``--date``: ``"YYYY-MM-DD"``.
    mag_time_offset : float or "auto"
        ``--mag-time-offset``: the magnetometer's latency against the IMU, s
        (:attr:`~pdr_mag.pipeline.PipelineSettings.mag_time_offset_s`); ``"auto"``: the one
        :func:`replay.run.estimate_latency` finds, when :func:`~pdr_mag.calibration.latency.applies` (the
        summary's ``mag_latency``).

    Returns
    -------
    dict
        The run summary (the ``replay --json`` object).
    """
    for p in (out_csv, json_path, mcap, rrd):
        if p is not None:
            writable_file(p)
    files = []
    if mcap is not None:
        files.append(make_sink("mcap", mcap, rate_hz=mcap_rate))
    if rrd is not None or viewer:
        files.append(make_sink("rrd", rrd, spawn=viewer))
    if out_csv is not None:
        files.append(CsvSink(out_csv))
    latency = None
    if mag_time_offset == "auto":
        latency = estimate_latency(rec)
        mag_time_offset = latency.seconds if applies(latency) else 0.0
    if source is not None or place is not None or date is not None:
        rec = open_recording(rec)
        if source is not None:
            rec.source = source
        apply_place(rec.meta, rec.source, place, date)
    store = None
    if device_store is not None:
        try:
            store = DeviceStore(device_store)
        except ValueError as exc:
            raise InputError(device_store, str(exc).split(": ", 1)[-1]) from None
    settings = None
    if not use_phone or mag_time_offset:
        prior = PriorSettings(use_phone=use_phone)
        settings = PipelineSettings(prior=prior, mag_time_offset_s=mag_time_offset)
    summary = replay(rec, calibration=cal, sinks=[*files, *sinks], progress=progress, settings=settings,
                     device_store=store)
    summary["mag_latency"] = None if latency is None else {**latency.to_dict(), "span_s": LATENCY_SPAN_S,
                                                           "applied": applies(latency)}
    if json_path is not None:
        try:
            json_path.write_text(json.dumps(_clean(summary), indent=1, allow_nan=False) + "\n")
        except OSError as exc:
            raise InputError(json_path, f"cannot write ({exc.strerror})") from None
    return summary


def _clean(obj):
    """JSON-safe copy: NaN/inf → null, numpy scalars → Python numbers."""
    if isinstance(obj, dict):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    if isinstance(obj, (bool, str)) or obj is None:
        return obj
    if isinstance(obj, int) and not isinstance(obj, bool):
        return obj
    try:
        v = float(obj)
    except (TypeError, ValueError):
        return str(obj)
    return v if math.isfinite(v) else None
