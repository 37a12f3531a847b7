"""``pdr-mag batch {replay,calibrate,diagnose} INPUT... --out DIR``: many recordings at once, on Dask.

INPUT: recordings, folders (searched recursively for recordings) and manifests (``*.manifest``: one
recording a line, optionally with its calibration file) — :mod:`replay.batch.inputs`. Each recording's
files go to its own folder under DIR, mirroring the input tree, the same files the single command
writes; ``DIR/summary.csv`` (and ``summary.parquet`` with pyarrow) is the fleet table, one row per
recording (:mod:`replay.batch.table`). A recording that fails is an ``error`` row and the others go on;
the exit code is 2 when any failed. A second run skips recordings whose outputs are complete (``--force``
redoes them). ``--latitude DEG --longitude DEG [--altitude M] [--date YYYY-MM-DD]`` (``replay``,
``calibrate``): the place and day of every recording, as the single commands' options (a building's
recordings, whose logger writes none).

By default the recordings run on a local Dask cluster of ``--workers`` processes started and stopped here;
``--scheduler tcp://HOST:8786`` sends them to an existing cluster (its workers need pdr_mag installed and
the recordings and DIR on paths they share). The local cluster has no dashboard unless ``--dashboard``
(which prints its address on stderr).
"""

from __future__ import annotations

import time
from pathlib import Path

import click

from replay.batch import execute, headline, plan, write_table
from replay.batch.engine import Interrupted
from replay.commands._place import place_of, place_options
from replay.commands.calibrate import METHODS
from replay.commands.diagnose import need_matplotlib
from replay.commands.replay import LatencyParam
from replay.errors import InputError
from replay.run import load_calibration


def _common(f):
    """The options every batch subcommand has."""
    options = [
        click.argument("inputs", nargs=-1, required=True, type=click.Path(path_type=Path)),
        click.option("--out", "out_dir", required=True, type=click.Path(path_type=Path, file_okay=False),
                     help="Output folder: one folder per recording, and summary.csv."),
        click.option("--workers", type=click.IntRange(min=1), default=None,
                     help="Worker processes of the local cluster (default: the core count)."),
        click.option("--scheduler", metavar="ADDRESS",
                     help="Run on the Dask cluster at ADDRESS (tcp://HOST:8786) instead of a local one."),
        click.option("--force", is_flag=True, help="Redo recordings whose outputs are complete."),
        click.option("--progress/--no-progress", default=None,
                     help="Progress bar over recordings (default: on a terminal)."),
        click.option("--top", type=click.IntRange(min=0), default=10, show_default=True,
                     help="Rows of the fleet table printed at the end (worst first)."),
        click.option("--dashboard", is_flag=True,
                     help="Start the local cluster's Dask dashboard and print its address (port 8787 if "
                          "free); with --scheduler, print that cluster's."),
    ]
    for opt in reversed(options):
        f = opt(f)
    return f


@click.group()
def command() -> None:
    """Run replay, calibrate or diagnose over many recordings on Dask; write a fleet table."""


@command.command("replay")
@_common
@click.option("--calibration", type=click.Path(path_type=Path),
              help="calibrate --json file for every recording a manifest gives none.")
@click.option("--mcap", is_flag=True, help="Also write replay.mcap per recording.")
@click.option("--rrd", is_flag=True, help="Also write replay.rrd (rerun) per recording.")
@click.option("--mag-time-offset", type=LatencyParam(), default="0", metavar="S|auto",
              help="The magnetometer's latency against the IMU, s, or auto: estimated per recording "
              "(pdr-mag replay's option).")
@place_options
def replay_cmd(inputs, out_dir, workers, scheduler, force, progress, top, dashboard, calibration, mcap, rrd,
               mag_time_offset, latitude, longitude, altitude, date):
    """Replay every recording: heading.csv and replay.json per recording (pdr-mag replay's files)."""
    place, day = place_of(latitude, longitude, altitude, date)
    opts = {"mcap": mcap, "rrd": rrd, "place": place, "date": day, "mag_time_offset": mag_time_offset}
    return _run("replay", inputs, out_dir, opts, calibration, workers, scheduler, force, progress, top,
                dashboard)


@command.command("calibrate")
@_common
@click.option("--method", type=click.Choice(METHODS),
              default="auto", show_default=True, help="Estimator (as pdr-mag calibrate).")
@place_options
def calibrate_cmd(inputs, out_dir, workers, scheduler, force, progress, top, dashboard, method, latitude,
                  longitude, altitude, date):
    """Calibrate every recording: calibration.json per recording (pdr-mag calibrate --json)."""
    place, day = place_of(latitude, longitude, altitude, date)
    opts = {"method": method, "place": place, "date": day}
    return _run("calibrate", inputs, out_dir, opts, None, workers, scheduler, force, progress, top, dashboard)


@command.command("diagnose")
@_common
@click.option("--report", is_flag=True, help="Also write report/ (report.md with plots) per recording.")
@click.option("--use-truth", is_flag=True, help="Predict along truth.csv (as pdr-mag diagnose).")
def diagnose_cmd(inputs, out_dir, workers, scheduler, force, progress, top, dashboard, report, use_truth):
    """Diagnose every recording: diagnose.json per recording (pdr-mag diagnose --json)."""
    if report:
        need_matplotlib()
    return _run("diagnose", inputs, out_dir, {"report": report, "use_truth": use_truth}, None, workers,
                scheduler, force, progress, top, dashboard)


def _say_dashboard(address: str) -> None:
    click.echo(f"dashboard: {address}", err=True)


def need_bokeh() -> None:
    """A click error when ``--dashboard`` cannot be served (bokeh missing: Dask's dashboard draws with it)."""
    try:
        import bokeh  # noqa: F401
    except ImportError:
        raise click.ClickException(
            "--dashboard needs bokeh, which is not installed (pip install 'pdr_mag[dashboard]')"
        ) from None


def _run(command_name, inputs, out_dir, options, calibration, workers, scheduler, force, progress,
         top, dashboard=False) -> int:
    if scheduler is not None and workers is not None:
        raise click.UsageError("--workers sets the local cluster; with --scheduler the cluster has its own")
    if dashboard and scheduler is None:
        need_bokeh()
    if calibration is not None:
        load_calibration(calibration)  # a bad file stops the batch here, not once per recording
    t_start = time.perf_counter()
    p = plan(command_name, inputs, out_dir, options=options, calibration=calibration, force=force)
    if not p.rows:
        raise InputError(" ".join(str(i) for i in inputs), "no recording found")
    try:
        rows = p.table(execute(p.tasks, workers=workers, scheduler=scheduler, progress=progress,
                               desc=f"batch {command_name}", dashboard=_say_dashboard if dashboard else None))
    except Interrupted as exc:
        raise click.ClickException(
            f"interrupted after {exc.n_done} of {exc.n_tasks} recordings had reported back; the same command "
            f"does the rest (complete outputs are skipped)"
        ) from None
    written = write_table(rows, p.out_dir)
    n_err = sum(r["status"] == "error" for r in rows)
    where = " + ".join(str(out_dir / w.name) for w in written)
    resumed = f" ({p.n_resumed} already done)" if p.n_resumed else ""
    plural = "s" if len(rows) != 1 else ""
    click.echo(f"batch {command_name}: {len(rows)} recording{plural}, {len(rows) - n_err} ok{resumed}, "
               f"{n_err} error → {where}  [{time.perf_counter() - t_start:.1f} s]")
    if top:
        click.echo("worst first:\n" + headline(rows, command_name, top))
    return 2 if n_err else 0
