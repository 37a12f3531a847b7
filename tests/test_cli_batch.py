"""``pdr-mag batch`` end to end on Dask, the console script as a process: a local cluster, then a real
``dask scheduler`` + ``dask worker`` started here as separate processes (``--scheduler``).

One folder of short simulated recordings with a malformed file (claimed by the IPIN reader) and an
unreadable folder (claimed by the pdr-csv reader), plus an explicit input no reader recognises.
"""

from __future__ import annotations

import importlib.util
import json
import math
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

from replay.batch import read_csv
from replay.cli import main

BIN = Path(sys.executable).parent
PDR_MAG = str(BIN / "pdr-mag")
GOOD = {"in/calib/figure8": ("figure8", 3), "in/walk": ("walk", 4), "in/sub/swing": ("swing", 5)}
BAD = {
    "in/bad": "in/bad/mag.csv:1: bad header 't,x,y', expected 't,x,y,z'",
    "in/broken.txt": "in/broken.txt:1: ACCE: expected 5 values after the type, got 3 (truncated?)",
    "junk.bin": "junk.bin: not a recording in a known format",
}
TIMING = ("elapsed_s", "samples_per_s", "compile_s")  # run-time figures: the only fields two runs differ in


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """The batch's working folder: in/ (3 recordings of 20 s, a malformed file, a bad folder), junk.bin."""
    base = tmp_path_factory.mktemp("batch")
    for label, (scenario, seed) in GOOD.items():
        assert main(["simulate", "--scenario", scenario, "--seed", str(seed), "--duration", "20",
                     "--out", str(base / label)]) == 0
    (base / "in" / "bad").mkdir()
    (base / "in" / "bad" / "mag.csv").write_text("t,x,y\n1,2\n")
    (base / "in" / "broken.txt").write_text("ACCE;1;2;x\n")
    (base / "in" / "notes").mkdir()
    (base / "in" / "notes" / "README.md").write_text("no recording here\n")
    (base / "junk.bin").write_bytes(b"\x00junk\x01")
    return base


def _batch(site, *args, timeout=240):
    return subprocess.run([PDR_MAG, "batch", *args], cwd=site, capture_output=True, text=True,
                          timeout=timeout)


@contextmanager
def _dashboard_port_taken():
    """Port 8787 (Dask's dashboard) in use while the block runs: held here, unless another process has it."""
    s = socket.socket()
    try:
        s.bind(("", 8787))
        s.listen(1)
    except OSError:
        pass  # taken already
    try:
        yield
    finally:
        s.close()


@pytest.fixture(scope="module")
def local(site):
    """``pdr-mag batch replay in junk.bin --out out-local`` on the local cluster of 2 processes, while another
    dashboard holds port 8787."""
    with _dashboard_port_taken():
        proc = _batch(site, "replay", "in", "junk.bin", "--out", "out-local", "--workers", "2",
                      "--no-progress")
    return proc, site / "out-local"


def _batch_here(site, monkeypatch, capsys, *args) -> tuple[int, str]:
    """``pdr-mag batch ARGS`` in this process (from ``site``): exit code and stdout."""
    monkeypatch.chdir(site)
    capsys.readouterr()
    rc = main(["batch", *args, "--no-progress"])
    return rc, capsys.readouterr().out


def _strip(rows):
    return [{k: v for k, v in r.items() if k != "elapsed_s"} for r in rows]


def test_local_batch_table_complete_errors_named_exit_2(local):
    proc, out = local
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr + proc.stdout
    rows = read_csv(out / "summary.csv")
    assert [r["recording"] for r in rows] == [
        "in/bad", "in/broken.txt", "in/calib/figure8", "in/sub/swing", "in/walk", "junk.bin"]
    by = {r["recording"]: r for r in rows}
    for label, msg in BAD.items():
        assert by[label]["status"] == "error"
        assert by[label]["error"].startswith(msg)
        assert by[label]["output"] is None
    for label in GOOD:
        r = by[label]
        assert r["status"] == "ok" and r["error"] is None
        assert r["output"] == label and r["format"] == "pdr-csv"
        assert r["duration_s"] == pytest.approx(20.0, abs=0.2)
        assert r["n_outputs"] > 900 and r["n_samples"] > 4500
        # the table's σ quantiles (0.01° bins) against the nearest-rank quantiles of the written rows
        sd = np.sort(np.loadtxt(out / label / "heading.csv", delimiter=",", skiprows=1, usecols=6))
        for q, col in ((0.5, "heading_std_median_deg"), (0.95, "heading_std_p95_deg")):
            assert r[col] == pytest.approx(sd[math.ceil(q * len(sd)) - 1], abs=0.011)
        # simulated recordings carry truth.csv (the table's figures are replay.json's), no phone attitude
        # and no waypoints
        err = json.loads((out / label / "replay.json").read_text())["heading_error"]
        assert set(err) == {"truth"} and err["truth"]["n_epochs"] > 900
        for col, key in (("median", "median_deg"), ("p90", "p90_deg"), ("p95", "p95_deg")):
            assert r[f"heading_err_truth_{col}_deg"] == err["truth"][key] is not None
        assert r["heading_err_truth_over45_share"] == err["truth"]["share_over_45"]
        assert r["heading_err_os_median_deg"] is None and r["walked_segments"] is None
        assert r["elapsed_s"] > 0
        files = sorted(p.name for p in (out / label).iterdir())
        assert files == ["batch.json", "heading.csv", "replay.json"]
    lines = proc.stdout.splitlines()
    assert lines[0].startswith("batch replay: 6 recordings, 3 ok, 3 error → out-local/summary.csv")
    assert lines[1] == "worst first:"
    assert [ln.split()[0] for ln in lines[3:9]] == ["error"] * 3 + ["ok"] * 3
    hidden = [p for p in out.rglob(".*")]
    assert hidden == []  # no staging folder left behind


def test_no_dashboard_and_no_warning_text_unless_asked(local, site):
    """With port 8787 taken (another cluster's dashboard), a run without --dashboard says nothing about
    it: its stderr is empty (the errors are rows of the table). --dashboard prints where the dashboard is
    (or, without bokeh, which Dask's dashboard needs, says so in one line)."""
    proc, _ = local
    assert proc.stderr == ""
    with _dashboard_port_taken():
        dash = _batch(site, "replay", "in/walk", "--out", "out-dash", "--workers", "1", "--no-progress",
                      "--dashboard")
    if importlib.util.find_spec("bokeh") is None:
        assert dash.returncode == 2 and dash.stderr == (
            "pdr-mag: --dashboard needs bokeh, which is not installed (pip install 'pdr_mag[dashboard]')\n")
    else:
        assert dash.returncode == 0, dash.stderr
        assert re.fullmatch(r"dashboard: http://[\w.:-]+:(\d+)/status\n", dash.stderr), dash.stderr


def test_batch_replay_identical_to_the_single_command(local, tmp_path, monkeypatch):
    _, out = local
    monkeypatch.chdir(out.parent)
    for label in GOOD:
        csv, js = tmp_path / label / "h.csv", tmp_path / label / "s.json"
        assert main(["replay", label, "--out-csv", str(csv), "--json", str(js), "-q"]) == 0
        assert (out / label / "heading.csv").read_bytes() == csv.read_bytes()
        single, batch = json.loads(js.read_text()), json.loads((out / label / "replay.json").read_text())
        assert {k: v for k, v in single.items() if k not in TIMING} == \
            {k: v for k, v in batch.items() if k not in TIMING}
        assert single["source"] == label


def test_parquet_matches_csv(local):
    import pyarrow.parquet as pq  # the test extra installs pyarrow (optional for users: the parquet extra)

    _, out = local
    assert pq.read_table(out / "summary.parquet").to_pylist() == read_csv(out / "summary.csv")


@pytest.fixture(scope="module")
def cluster(site, tmp_path_factory):
    """A Dask cluster of separate processes: ``dask scheduler`` and ``dask worker`` (1 process)."""
    tmp = tmp_path_factory.mktemp("dask")
    info = tmp / "scheduler.json"
    procs = [subprocess.Popen([str(BIN / "dask"), "scheduler", "--host", "127.0.0.1", "--port", "0",
                               "--no-dashboard", "--scheduler-file", str(info)],
                              cwd=tmp, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    try:
        t0 = time.monotonic()
        while not info.exists() or not info.read_text().strip():
            assert time.monotonic() - t0 < 60, "dask scheduler did not start"
            time.sleep(0.2)
        address = json.loads(info.read_text())["address"]
        procs.append(subprocess.Popen([str(BIN / "dask"), "worker", address, "--nworkers", "1", "--nthreads",
                                       "1", "--no-nanny", "--no-dashboard", "--local-directory", str(tmp)],
                                      cwd=tmp, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        yield address
    finally:
        for p in reversed(procs):
            p.send_signal(signal.SIGTERM)
        for p in reversed(procs):
            try:
                p.wait(timeout=5)  # an idle Dask process leaves in well under a second
            except subprocess.TimeoutExpired:
                p.kill()


def test_scheduler_gives_the_same_table_as_the_local_cluster(site, local, cluster, monkeypatch, capsys,
                                                             tmp_path):
    rc, _ = _batch_here(site, monkeypatch, capsys, "replay", "in", "junk.bin", "--out", "out-remote",
                        "--scheduler", cluster, "--mcap")
    assert rc == 2
    assert main(["replay", "in/walk", "--mcap", str(tmp_path / "walk.mcap"), "-q"]) == 0
    assert (site / "out-remote" / "in" / "walk" / "replay.mcap").read_bytes() == \
        (tmp_path / "walk.mcap").read_bytes()
    remote, here = read_csv(site / "out-remote" / "summary.csv"), read_csv(local[1] / "summary.csv")
    assert _strip(remote) == _strip(here)
    for label in GOOD:
        for name in ("heading.csv", "replay.json"):
            a = (site / "out-remote" / label / name).read_bytes()
            b = (local[1] / label / name).read_bytes()
            if name == "replay.json":
                a, b = ({k: v for k, v in json.loads(x).items() if k not in TIMING} for x in (a, b))
            assert a == b


def test_resume_skips_complete_outputs_and_force_redoes_them(site, local, cluster, monkeypatch, capsys):
    out = site / "out-resume"
    shutil.copytree(local[1], out)
    shutil.rmtree(out / "in" / "walk")
    stale = out / "in" / ".walk.part-0123456789ab"  # left by a worker killed while writing
    stale.mkdir()
    (stale / "heading.csv").write_text("t,qw\n")
    kept = {label: (out / label / "heading.csv").stat().st_mtime_ns for label in GOOD if label != "in/walk"}
    args = ("replay", "in", "junk.bin", "--out", "out-resume", "--scheduler", cluster)
    rc, text = _batch_here(site, monkeypatch, capsys, *args)
    assert rc == 2
    assert "3 ok (2 already done), 3 error" in text.splitlines()[0]
    for label, mtime in kept.items():
        assert (out / label / "heading.csv").stat().st_mtime_ns == mtime
    assert not stale.exists()
    assert _strip(read_csv(out / "summary.csv")) == _strip(read_csv(local[1] / "summary.csv"))
    rc, text = _batch_here(site, monkeypatch, capsys, *args, "--force")
    assert rc == 2 and "3 ok, 3 error" in text.splitlines()[0]
    for label, mtime in kept.items():
        assert (out / label / "heading.csv").stat().st_mtime_ns != mtime


def test_batch_calibrate_and_diagnose_identical_to_the_single_commands(site, cluster, tmp_path, monkeypatch,
                                                                      capsys):
    good = list(GOOD)
    rc, _ = _batch_here(site, monkeypatch, capsys, "calibrate", *good, "--out", "out-cal", "--scheduler",
                        cluster)
    assert rc == 0
    rc, _ = _batch_here(site, monkeypatch, capsys, "diagnose", "in/walk", "--out", "out-diag", "--scheduler",
                        cluster)
    assert rc == 0
    for label in good:
        single = tmp_path / f"{Path(label).name}.json"
        assert main(["calibrate", label, "--json", str(single)]) == 0
        assert (site / "out-cal" / Path(label).name / "calibration.json").read_bytes() == single.read_bytes()
    rows = read_csv(site / "out-cal" / "summary.csv")
    assert [r["cal_accepted"] for r in rows if r["recording"] == "in/calib/figure8"] == [True]
    single = tmp_path / "diag.json"
    assert main(["diagnose", "in/walk", "--json", str(single)]) == 0
    assert (site / "out-diag" / "walk" / "diagnose.json").read_bytes() == single.read_bytes()
    (row,) = read_csv(site / "out-diag" / "summary.csv")
    d = json.loads(single.read_text())
    assert row["diag_final_gap_uT"] == d["final"]["gap"]
    assert row["diag_missing_effects"] == ("+".join(d["missing_effects"]) or None)


def test_batch_place_and_date_as_the_single_commands(site, local, cluster, monkeypatch, capsys,
                                                          tmp_path):
    """``batch replay`` and ``batch calibrate`` with ``--latitude --longitude --altitude --date`` give every
    recording what the single commands with the same options give one."""
    where = ("--latitude", "-33.87", "--longitude", "151.21", "--altitude", "20", "--date", "2024-03-01")
    rc, _ = _batch_here(site, monkeypatch, capsys, "replay", "in/walk", "--out", "out-place",
                        "--scheduler", cluster, *where)
    assert rc == 0
    assert main(["replay", "in/walk", "--out-csv", str(tmp_path / "h.csv"), *where, "-q"]) == 0
    batch = (site / "out-place" / "walk" / "heading.csv").read_bytes()
    assert batch == (tmp_path / "h.csv").read_bytes()
    assert batch != (local[1] / "in" / "walk" / "heading.csv").read_bytes()  # the place was taken
    rc, _ = _batch_here(site, monkeypatch, capsys, "calibrate", "in/walk", "--out", "out-place-cal",
                        "--scheduler", cluster, *where)
    assert rc == 0
    assert main(["calibrate", "in/walk", "--json", str(tmp_path / "c.json"), *where]) == 0
    single = json.loads((tmp_path / "c.json").read_text())
    batch = json.loads((site / "out-place-cal" / "walk" / "calibration.json").read_text())
    assert batch["extra"].pop("source") == single["extra"].pop("source") == "in/walk"
    assert batch == single and single["extra"]["wmm"]["declination_deg"] > 10.0  # Sydney's, not the site's
