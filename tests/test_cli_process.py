"""The ``pdr-mag`` console script started as a process: bad input ends with exit code 2 and exactly one
line on stderr naming the file (and line), never a traceback; odd samples in a good file are dropped,
counted in the JSON summary, and the command succeeds.

Every command (simulate, calibrate, replay, diagnose) runs as the installed entry point, and once through
``python -m pdr_mag``.  The recordings are tiny: a 5 s ``pdr-mag simulate`` figure-8, edited by the tests.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
#: The console script installed beside this interpreter (``pip install -e .`` puts it there).
SCRIPT = shutil.which("pdr-mag", path=str(Path(sys.executable).parent)) or shutil.which("pdr-mag")


def _processes_run_this_checkout(cwd: Path) -> None:
    """Fail unless ``pdr-mag`` and ``python -m pdr_mag``, started from ``cwd`` as the tests start them, run
    the code of this checkout (not another install's)."""
    if SCRIPT is None:
        pytest.fail("the pdr-mag console script is not installed (pip install -e .)")
    pythons = {"python -m pdr_mag": sys.executable}
    first = Path(SCRIPT).read_text(errors="replace").splitlines()[0]
    if first.startswith("#!") and "python" in first:  # else a launcher: its interpreter is not named
        pythons[SCRIPT] = first[2:].strip()
    code = "import replay, pathlib; print(pathlib.Path(replay.__file__).resolve().parent.parent)"
    for what, python in pythons.items():
        out = subprocess.run([python, "-c", code], capture_output=True, text=True, cwd=cwd)
        where = out.stdout.strip()
        assert where == str(ROOT), f"{what} runs the checkout at {where or out.stderr[-300:]}, not {ROOT}"


def pdr_mag(*args, cwd: Path, module: bool = False) -> subprocess.CompletedProcess:
    """Run ``pdr-mag ARGS`` (or ``python -m pdr_mag ARGS``) as a process, capturing stdout and stderr."""
    cmd = [sys.executable, "-m", "pdr_mag"] if module else [SCRIPT]
    env = {**os.environ, "PYTHONUTF8": "1"}  # the messages' units (µT, m/s²) whatever the locale
    return subprocess.run(cmd + [str(a) for a in args], capture_output=True, encoding="utf-8", cwd=cwd,
                          env=env, timeout=300)


def assert_one_line_exit_2(res: subprocess.CompletedProcess, path, *needles: str, line: int | None = None):
    """Exit code 2, nothing on stdout, exactly one line on stderr: ``pdr-mag: PATH[:LINE]: problem``."""
    assert res.returncode == 2, (res.returncode, res.stderr[-2000:])
    assert "Traceback" not in res.stderr, res.stderr[-2000:]
    lines = res.stderr.splitlines()
    assert len(lines) == 1, res.stderr
    where = f"{path}:{line}: " if line is not None else f"{path}: "
    assert lines[0].startswith(f"pdr-mag: {where}"), lines[0]
    problem = lines[0][len(f"pdr-mag: {where}"):]
    for needle in needles:
        assert needle in problem, lines[0]
    assert res.stdout == ""


def _edit_vectors(path: Path, fn) -> None:
    """Rewrite a ``t,x,y,z`` file with ``xyz = fn(xyz)``."""
    d = np.loadtxt(path, delimiter=",", skiprows=1)
    d[:, 1:] = fn(d[:, 1:])
    np.savetxt(path, d, delimiter=",", header="t,x,y,z", comments="", fmt="%.6f")


def _edit_lines(path: Path, edits: dict[int, str]) -> None:
    """Replace lines of a text file (1-based line numbers, the header is line 1)."""
    lines = path.read_text().splitlines()
    for n, text in edits.items():
        lines[n - 1] = text
    path.write_text("\n".join(lines) + "\n")


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    """A folder with ``rec`` (a 5 s figure-8 written by ``pdr-mag simulate`` as a process) and ``afile``
    (a plain file: a path under it cannot be written, for root too)."""
    d = tmp_path_factory.mktemp("proc")
    _processes_run_this_checkout(d)
    res = pdr_mag("simulate", "--scenario", "figure8", "--seed", "3", "--duration", "5", "--out", d / "rec",
                  cwd=d)
    assert res.returncode == 0, res.stderr
    assert res.stderr == "" and "figure8 seed 3" in res.stdout
    for name in ("mag.csv", "accel.csv", "gyro.csv", "truth.csv", "meta.json"):
        assert (d / "rec" / name).is_file()
    (d / "afile").write_text("not a folder\n")
    return d


def _copy(work: Path, name: str) -> Path:
    dst = work / name
    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(work / "rec", dst)
    return dst


# --- unknown format -------------------------------------------------------------------------------

@pytest.mark.parametrize("command", ["calibrate", "replay", "diagnose"])
def test_unknown_format(work, command):
    unk = work / "unknown"
    unk.mkdir(exist_ok=True)
    (unk / "notes.txt").write_text("no sensor data here\n")
    assert_one_line_exit_2(pdr_mag(command, unk, cwd=work), unk, "not a recording in a known format")


def test_unknown_file_format_through_python_dash_m(work):
    f = work / "notes.bin"
    f.write_bytes(b"\x00\x01 not a recording")
    assert_one_line_exit_2(pdr_mag("diagnose", f, cwd=work, module=True), f, "known format")


def test_missing_recording(work):
    gone = work / "no-such-recording"
    assert_one_line_exit_2(pdr_mag("replay", gone, cwd=work), gone, "no such file or directory")


# --- unwritable outputs: a path under a plain file fails for every user, root included ------------

@pytest.mark.parametrize(
    "args",
    [
        ("simulate", "--scenario", "still", "--duration", "2", "--out", "{bad}"),
        ("calibrate", "{rec}", "--json", "{bad}"),
        ("replay", "{rec}", "--json", "{bad}"),
        ("replay", "{rec}", "--out-csv", "{bad}"),
        ("replay", "{rec}", "--mcap", "{bad}"),
        ("replay", "{rec}", "--rrd", "{bad}"),
        ("diagnose", "{rec}", "--json", "{bad}"),
        ("diagnose", "{rec}", "--report", "{bad}"),
    ],
    ids=["simulate-out", "calibrate-json", "replay-json", "replay-out-csv", "replay-mcap", "replay-rrd",
         "diagnose-json", "diagnose-report"],
)
def test_unwritable_output(work, args):
    bad = work / "afile" / "out.x"
    argv = [a.format(rec=work / "rec", bad=bad) for a in args]
    assert_one_line_exit_2(pdr_mag(*argv, cwd=work), bad, "cannot write")
    assert (work / "afile").is_file()


def test_output_path_that_is_a_folder(work):
    folder = work / "a-folder"
    folder.mkdir(exist_ok=True)
    res = pdr_mag("replay", work / "rec", "--out-csv", folder, cwd=work)
    assert_one_line_exit_2(res, folder, "directory")


# --- wrong units, bad header, bad rows ------------------------------------------------------------

def test_accel_in_g_is_wrong_units(work):
    rec = _copy(work, "accel_g")
    _edit_vectors(rec / "accel.csv", lambda a: a / 9.80665)
    assert_one_line_exit_2(pdr_mag("replay", rec, cwd=work), rec / "accel.csv", "m/s²", "wrong unit")


def test_mag_in_nanotesla_is_wrong_units(work):
    rec = _copy(work, "mag_nT")
    _edit_vectors(rec / "mag.csv", lambda m: m * 1000.0)
    assert_one_line_exit_2(pdr_mag("calibrate", rec, cwd=work), rec / "mag.csv", "µT", "wrong unit")


def test_mag_in_gauss_is_wrong_units(work):
    rec = _copy(work, "mag_G")
    _edit_vectors(rec / "mag.csv", lambda m: m / 100.0)
    assert_one_line_exit_2(pdr_mag("diagnose", rec, cwd=work), rec / "mag.csv", "µT", "wrong unit")


def test_time_in_milliseconds_is_wrong_units(work):
    """Time in ms: the magnetometer's 20-ms interval read as 20 s (a replay would integrate the gyroscope
    over hours)."""
    rec = _copy(work, "time_ms")
    for name in ("mag", "accel", "gyro"):
        d = np.loadtxt(rec / f"{name}.csv", delimiter=",", skiprows=1)
        d[:, 0] *= 1000.0
        np.savetxt(rec / f"{name}.csv", d, delimiter=",", header="t,x,y,z", comments="", fmt="%.6f")
    res = pdr_mag("replay", rec, cwd=work)
    assert_one_line_exit_2(res, rec / "mag.csv", "interval between samples", "time not in seconds")


def test_streams_of_two_clocks_are_an_input_error(work):
    """A magnetometer stamped by another clock (10⁵ s later: the time since boot against the epoch's) never
    meets the IMU: exit 2 naming the recording, not a replay of a heading that never had a field."""
    rec = _copy(work, "two_clocks")
    d = np.loadtxt(rec / "mag.csv", delimiter=",", skiprows=1)
    d[:, 0] += 1.0e5
    np.savetxt(rec / "mag.csv", d, delimiter=",", header="t,x,y,z", comments="", fmt="%.6f")
    assert_one_line_exit_2(pdr_mag("replay", rec, cwd=work), rec, "start", "apart", "not one clock")


def test_bad_header(work):
    rec = _copy(work, "header")
    _edit_lines(rec / "mag.csv", {1: "time,mx,my,mz"})
    assert_one_line_exit_2(pdr_mag("replay", rec, cwd=work), rec / "mag.csv", "bad header", line=1)


def test_binary_file_is_a_bad_header_in_one_line(work):
    rec = _copy(work, "bytes")
    (rec / "mag.csv").write_bytes(bytes(range(256)) * 4)
    assert_one_line_exit_2(pdr_mag("calibrate", rec, cwd=work), rec / "mag.csv", "bad header: not text",
                           line=1)


def test_text_in_a_number_column_is_an_odd_sample_named_in_the_output(work):
    """A garbled row inside a good file is dropped and counted: exit 0, the row named in the JSON."""
    rec = _copy(work, "text_cell")
    t = (rec / "accel.csv").read_text().splitlines()[11].split(",")[0]
    _edit_lines(rec / "accel.csv", {12: f"{t},1.0,abc,9.8"})
    res = pdr_mag("calibrate", rec, "--json", work / "text_cell.json", cwd=work)
    assert res.returncode == 0 and res.stderr == "", res.stderr
    extra = json.loads((work / "text_cell.json").read_text())["extra"]
    assert extra["dropped_samples"] == {"accel:non_numeric": 1}


def test_time_going_backwards_names_the_line(work):
    rec = _copy(work, "backwards")
    rows = (rec / "gyro.csv").read_text().splitlines()
    _edit_lines(rec / "gyro.csv", {30: "0.000001," + rows[29].split(",", 1)[1]})
    assert_one_line_exit_2(pdr_mag("diagnose", rec, cwd=work), rec / "gyro.csv", "time goes backwards",
                           line=30)


def test_truncated_last_row_names_the_line(work):
    rec = _copy(work, "truncated")
    text = (rec / "mag.csv").read_text()
    (rec / "mag.csv").write_text(text[: text.rindex(",")] + "\n")
    n_lines = len(text.splitlines())
    assert_one_line_exit_2(pdr_mag("replay", rec, cwd=work), rec / "mag.csv", "truncated", line=n_lines)


def test_simulate_unknown_effect_is_one_line(work):
    res = pdr_mag("simulate", "--scenario", "still", "--effect", "nope=1", "--out", work / "x", cwd=work)
    assert res.returncode == 2 and res.stdout == "" and "Traceback" not in res.stderr
    assert len(res.stderr.splitlines()) == 1 and "nope" in res.stderr
    assert not (work / "x").exists()


# --- odd samples in a good file: dropped, counted in the JSON, exit 0 -----------------------------

#: What the edits below put into the files, as the JSON summaries count it.
ODD = {"mag:nan": 3, "mag:duplicate_t": 2, "gyro:nan": 1, "accel:duplicate_t": 1}


@pytest.fixture(scope="module")
def odd_rec(work) -> Path:
    """The figure-8 with NaN/inf rows and repeated timestamps (a duplicate time is dropped, not an error)."""
    rec = _copy(work, "odd")
    for name in ("mag.csv", "gyro.csv", "accel.csv"):
        d = np.loadtxt(rec / name, delimiter=",", skiprows=1)
        assert np.all(np.isfinite(d)) and np.all(np.diff(d[:, 0]) > 0)  # the clean file has none of either
    mag = (rec / "mag.csv").read_text().splitlines()
    t = [row.split(",")[0] for row in mag]
    _edit_lines(rec / "mag.csv", {
        5: f"{t[4]},nan,1.0,2.0",
        40: f"{t[39]},1.0,NaN,2.0",
        41: f"{t[40]},1.0,2.0,inf",
        60: mag[58],                                # line 59 again: same time, same values
        80: f"{t[78]},10.0,20.0,30.0",              # line 79's time, other values
    })
    gyro_t = (rec / "gyro.csv").read_text().splitlines()[99].split(",")[0]
    _edit_lines(rec / "gyro.csv", {100: f"{gyro_t},nan,0.0,0.0"})
    accel = (rec / "accel.csv").read_text().splitlines()
    _edit_lines(rec / "accel.csv", {200: accel[198]})
    return rec


def _odd_counts(dropped: dict) -> dict:
    return {k: v for k, v in dropped.items() if k.endswith((":nan", ":duplicate_t"))}


def test_odd_samples_replay(work, odd_rec):
    out = work / "odd_replay.json"
    res = pdr_mag("replay", odd_rec, "--json", out, "-q", cwd=work)
    assert res.returncode == 0 and res.stderr == "", res.stderr[-2000:]
    d = json.loads(out.read_text())
    assert _odd_counts(d["dropped_samples"]) == ODD
    assert d["n_outputs"] > 0


def test_odd_samples_calibrate(work, odd_rec):
    out = work / "odd_calibrate.json"
    res = pdr_mag("calibrate", odd_rec, "--json", out, cwd=work)
    assert res.returncode == 0 and res.stderr == "", res.stderr[-2000:]
    d = json.loads(out.read_text())
    assert _odd_counts(d["extra"]["dropped_samples"]) == ODD
    n_mag = len((odd_rec / "mag.csv").read_text().splitlines()) - 1
    assert d["n_samples"] == n_mag - ODD["mag:nan"] - ODD["mag:duplicate_t"]


def test_odd_samples_diagnose(work, odd_rec):
    out = work / "odd_diagnose.json"
    res = pdr_mag("diagnose", odd_rec, "--json", out, cwd=work)
    assert res.returncode == 0 and res.stderr == "", res.stderr[-2000:]
    d = json.loads(out.read_text())
    assert _odd_counts(d["dropped_samples"]) == ODD
    assert d["missing_effects"] is not None and d["final"]["gap"] <= d["baseline"]["gap"]


def test_a_broken_device_store_entry_is_named_in_one_line(work):
    """A store file that cannot be read (cut short while written, say) is an error naming it — never a
    traceback, never silently replaced (INTERFACE.md)."""
    rec = _copy(work, "store_rec")
    store = work / "store"
    assert pdr_mag("replay", rec, "--device-store", store, cwd=work).returncode == 0
    (entry,) = list(store.glob("*.json"))
    text = entry.read_text()
    entry.write_text(text[: len(text) // 2])
    assert_one_line_exit_2(pdr_mag("replay", rec, "--device-store", store, cwd=work), entry, "device store",
                           "cannot read")
    assert entry.read_text() == text[: len(text) // 2]  # left as it was


@pytest.mark.parametrize("option", ["--out-csv", "--mcap", "--rrd", "--json"])
def test_a_full_disk_names_the_output_in_one_line(work, option):
    """Writing an output fails (``/dev/full``: no space left): exit 2 and one line naming the file, from
    every writer — Python's file objects and the rerun SDK name no file themselves."""
    if not Path("/dev/full").exists():
        pytest.skip("no /dev/full on this system (a Linux device that is always full)")
    res = pdr_mag("replay", work / "rec", option, "/dev/full", cwd=work)
    assert_one_line_exit_2(res, "/dev/full", "cannot write")
