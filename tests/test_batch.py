"""``replay.batch`` in-process: finding recordings, the fleet metrics, the table, one task's atomic outputs
and resume bookkeeping (no Dask here: the end-to-end runs on Dask are in ``test_cli_batch.py``)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

import numpy as np
import pytest

from pdr_mag.estimates import EstimateBatch
from replay.batch import (
    COLUMNS,
    Task,
    completed_row,
    find_recordings,
    headline,
    read_csv,
    run_task,
    write_table,
)
from replay.batch.metrics import FleetMetrics
from replay.batch.table import csv_text, error_row, worst_first
from replay.cli import main
from tests.conftest import ROOT

DEMO = ROOT / "recordings"


@pytest.fixture()
def tree(tmp_path):
    """in/{a (recording), notes/ (nothing), deep/x/b (recording), bad (claimed, unreadable), junk.txt}."""
    base = tmp_path / "in"
    shutil.copytree(DEMO / "figure8", base / "a")
    shutil.copytree(DEMO / "figure8", base / "deep" / "x" / "b")
    (base / "notes").mkdir()
    (base / "notes" / "readme.md").write_text("not a recording\n")
    (base / "bad").mkdir()
    (base / "bad" / "mag.csv").write_text("t,x,y\n1,2\n")
    (base / ".hidden").mkdir()
    shutil.copytree(DEMO / "figure8", base / ".hidden" / "c")
    return tmp_path


def test_folder_search_order_keys_and_passed_over(tree, monkeypatch):
    monkeypatch.chdir(tree)
    items = find_recordings(["in"])
    assert [(i.label, i.key, i.error) for i in items] == [
        ("in/a", "in/a", None),
        ("in/bad", "in/bad", None),  # claimed by the pdr-csv reader: it fails when read, as a task
        ("in/deep/x/b", "in/deep/x/b", None),
    ]
    assert all(i.path.startswith(str(tree)) for i in items)


def test_explicit_unrecognised_missing_and_duplicates(tree, monkeypatch):
    monkeypatch.chdir(tree)
    (tree / "junk.bin").write_bytes(b"\x00\x01junk")
    items = find_recordings(["in/a", "junk.bin", "nothing", "in"])
    by = {i.label: i for i in items}
    assert by["junk.bin"].error.startswith("junk.bin: not a recording in a known format")
    assert by["nothing"].error == "nothing: no such file or directory"
    # in/a named first keeps its own output folder; the folder search does not repeat it
    assert [i.label for i in items if i.error is None] == ["in/a", "in/bad", "in/deep/x/b"]
    assert by["in/a"].key == "a"


def test_manifest_with_calibrations_and_errors(tree, monkeypatch):
    monkeypatch.chdir(tree)
    lists = tree / "lists"
    lists.mkdir()
    (lists / "week.manifest").write_text(
        "# recordings of the week\n"
        "../in/a   ../cal/n5.json\n"
        "\n"
        '"../in/deep/x/b"  # no calibration\n'
        "../in/a ../cal/other.json\n"  # the same recording again: once
        "a b c\n"
        "'unclosed\n"
    )
    items = find_recordings(["lists/week.manifest"])
    assert [(i.label, i.key, i.calibration) for i in items if i.error is None] == [
        ("in/a", "a", "cal/n5.json"),  # outside the manifest's folder: by name
        ("in/deep/x/b", "b", None),
    ]
    errors = [i.error for i in items if i.error]
    assert errors[0].startswith("lists/week.manifest:6: expected RECORDING [CALIBRATION], got 3 fields")
    assert errors[1].startswith("lists/week.manifest:7:")


def test_two_recordings_for_one_output_folder(tree, monkeypatch):
    monkeypatch.chdir(tree)
    shutil.copytree(DEMO / "figure8", tree / "other" / "a")
    items = find_recordings(["in/a", "other/a"])
    assert items[0].error is None
    assert items[1].error == "other/a: its output folder a is already that of in/a"


def _batch(t, q, std, interf, mag_used):
    n = len(t)
    return EstimateBatch(t=t, q_wd=q, heading_deg=np.zeros(n), heading_std_deg=std, mag_used=mag_used,
                         interference=interf, cal_state=np.array(["offset"] * n, dtype=object))


def test_fleet_metrics_counts_and_sigma_quantiles():
    m = FleetMetrics()
    t = np.arange(0.0, 12.0, 0.01)
    q = np.tile([1.0, 0, 0, 0], (len(t), 1))
    flags = t > 11
    std = np.where(t < 3, 20.0, 3.0)  # a quarter of the rows at 20°
    for i in range(0, len(t), 250):
        sl = slice(i, i + 250)
        m.estimates(_batch(t[sl], q[sl], std[sl], flags[sl], ~flags[sl]))
    assert m.n_rows == len(t)
    assert m.share(m.n_interference) == pytest.approx(np.mean(flags))
    assert m.share(m.n_mag_used) == pytest.approx(1 - np.mean(flags))
    assert m.heading_std.quantile(0.5) == 3.0 and m.heading_std.quantile(0.95) == 20.0


def test_table_csv_round_trip_and_parquet(tmp_path):
    ok = {name: None for name, _, _ in COLUMNS}
    ok.update(recording="r/a", output="r/a", status="ok", duration_s=12.5, n_samples=100, cal_accepted=True,
              heading_std_p95_deg=4.25, heading_err_truth_p95_deg=7.0, interference_share=0.125)
    rows = [ok, error_row("r/b", "r/b/mag.csv:1: bad\nheader")]
    paths = write_table(rows, tmp_path)
    back = read_csv(paths[0])
    assert back[0] == ok
    assert back[1]["error"] == "r/b/mag.csv:1: bad header" and back[1]["status"] == "error"
    assert csv_text(back) == paths[0].read_text()
    import pyarrow.parquet as pq  # the test extra installs pyarrow (optional for users: the parquet extra)

    assert [p.name for p in paths] == ["summary.csv", "summary.parquet"]
    t = pq.read_table(paths[1])
    assert t.column_names == [name for name, _, _ in COLUMNS]
    assert t.to_pylist() == back


def test_worst_first_and_headline():
    def row(rec, **kw):
        r = {name: None for name, _, _ in COLUMNS}
        r.update(recording=rec, status="ok", **kw)
        return r

    rows = [row("calm", heading_std_p95_deg=5.0), row("truth-good", heading_err_truth_p95_deg=3.0),
            error_row("broken", "broken: no such file or directory"),
            row("truth-bad", heading_err_truth_p95_deg=30.0), row("wild", heading_std_p95_deg=90.0),
            # truth of another kind ranks by its error among the others: the walked direction before the
            # phone's own heading, which counts only without either
            row("mall-bad", heading_err_walked_p95_deg=60.0, heading_err_os_p95_deg=1.0,
                heading_std_p95_deg=2.0),
            row("mall-good", heading_err_walked_p95_deg=4.0, heading_err_os_p95_deg=99.0),
            row("phone-only", heading_err_os_p95_deg=10.0, heading_std_p95_deg=95.0)]
    assert [r["recording"] for r in worst_first(rows, "replay")] == [
        "broken", "mall-bad", "truth-bad", "phone-only", "mall-good", "truth-good", "wild", "calm"]
    text = headline(rows, "replay", top=3).splitlines()
    assert text[1].startswith("error") and "broken: no such file or directory" in text[1]
    assert text[2].endswith("mall-bad") and "60.00" in text[2]
    assert text[3].endswith("truth-bad") and "30.00" in text[3]
    assert len(text) == 4


def test_run_task_atomic_outputs_and_resume_bookkeeping(tmp_path):
    out = tmp_path / "out"
    rec = DEMO / "figure8"
    task = Task("calibrate", "figure8", str(rec), "figure8", str(out), {"method": "auto"})
    # an earlier attempt killed mid-write left its staging folder: not complete, removed by the next attempt
    stale = out / ".figure8.part-0123456789ab"
    stale.mkdir(parents=True)
    (stale / "calibration.json").write_text("{")
    row = run_task(task)
    assert row["status"] == "ok" and row["cal_accepted"] is True
    assert not stale.exists()
    assert sorted(p.name for p in out.iterdir()) == ["figure8"]
    assert sorted(p.name for p in (out / "figure8").iterdir()) == ["batch.json", "calibration.json"]
    stored = completed_row(task)
    assert stored == json.loads(json.dumps(row))
    # other options: not the same outputs
    other = Task("calibrate", "figure8", str(rec), "figure8", str(out), {"method": "sphere"})
    assert completed_row(other) is None
    # a file missing: incomplete
    (out / "figure8" / "calibration.json").unlink()
    assert completed_row(task) is None


def test_run_task_failure_is_a_row_and_removes_the_old_output(tmp_path):
    out = tmp_path / "out"
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "mag.csv").write_text("t,x,y\n")
    (out / "bad").mkdir(parents=True)
    (out / "bad" / "heading.csv").write_text("old\n")
    row = run_task(Task("replay", "data/bad", str(bad), "bad", str(out), {"mcap": False, "rrd": False}))
    assert row["status"] == "error"
    assert row["error"] == "data/bad/mag.csv:1: bad header 't,x,y', expected 't,x,y,z'"
    assert list(out.iterdir()) == []


def test_batch_without_recordings_is_one_line(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    assert main(["batch", "replay", str(tmp_path / "empty"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"pdr-mag: {tmp_path / 'empty'}: no recording found"]


def test_batch_bad_calibration_file_is_one_line(tmp_path, capsys):
    (tmp_path / "cal.json").write_text("{}")
    rc = main(["batch", "replay", str(DEMO / "walk"), "--out", str(tmp_path / "o"), "--calibration",
               str(tmp_path / "cal.json")])
    assert rc == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"pdr-mag: {tmp_path / 'cal.json'}: ")


def test_the_library_never_imports_the_engine():
    code = ("import sys, pdr_mag, pdr_mag.pipeline, pdr_mag.modelcheck, replay.run, replay.cli; "
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('dask', 'distributed')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_the_output_folder_inside_an_input_folder_is_not_searched(tree, monkeypatch):
    monkeypatch.chdir(tree)
    shutil.copytree(DEMO / "figure8", tree / "in" / "results" / "in" / "a")  # a recording-like output
    labels = [i.label for i in find_recordings(["in"], skip=["in/results"])]
    assert labels == ["in/a", "in/bad", "in/deep/x/b"]


def test_replay_task_with_a_calibration_file(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["calibrate", str(DEMO / "figure8"), "--json", "cal.json"]) == 0
    task = Task("replay", "walk", str(DEMO / "walk"), "walk", str(tmp_path / "out"),
                {"mcap": False, "rrd": False}, "cal.json", str(tmp_path / "cal.json"))
    row = run_task(task)
    assert row["status"] == "ok" and row["calibration_file"] == "cal.json"
    summary = json.loads((tmp_path / "out" / "walk" / "replay.json").read_text())
    assert summary["calibration_given"] is True and summary["source"] == "walk"
    assert row["cal_method"] == summary["calibrations"][-1]["method"]
    assert row["cal_offset_x_uT"] == summary["calibrations"][-1]["offset_uT"][0]
    assert row["n_outputs"] == summary["n_outputs"] and row["cal_state"] == summary["cal_state"]
    kinds = [e["kind"] for e in summary["events"]]
    assert row["n_events"] == len(kinds)
    assert row["events_calibration_accepted"] == kinds.count("calibration_accepted")
    # a calibration file that is not there: an error row naming it as given
    bad = Task("replay", "walk", str(DEMO / "walk"), "walk2", str(tmp_path / "out"),
               {"mcap": False, "rrd": False}, "nope.json", str(tmp_path / "nope.json"))
    assert run_task(bad)["error"] == "nope.json: no such calibration file"
