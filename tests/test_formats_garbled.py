"""A garbled row is an odd sample in every reader: a text row with more fields than the header (or the
format) defines, with a field anywhere in it that is not a number, or with fewer fields than the format needs
but more rows after it (a write cut short and resumed; as a file's last row it is a truncated file, an
error), is dropped whole and counted under ``<stream>:extra_fields`` / ``<stream>:non_numeric`` /
``<stream>:short_row``; the rows around it read as before.

Each reader family reads a small recording twice, clean and with garbled rows inserted: the streams (and the
truth, waypoints, positions) are equal, and the only difference is the garbled rows' counts.
"""

from __future__ import annotations

import json
import shutil
import warnings
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from replay.cli import main
from replay.errors import InputError
from replay.formats import _common, read_recording
from tests.test_formats_mcap import _raw_mcap
from tests.test_formats_sunsided import _fixture as _sunsided
from tests.test_formats_xio import HEADER as XIO_HEADER

ROOT = Path(__file__).resolve().parents[1]
FIX = Path(__file__).parent / "fixtures"
#: The row of the issue: t, x, y, z, then two fields that are no part of a pdr-csv mag.csv row.
ISSUE_ROW = "10.944458,45.03479,-58.094788,12.3,4x5,abc"


def _insert(path: Path, after: dict[str, str]) -> None:
    """Insert the new lines after the first line starting with each key."""
    lines = path.read_text(encoding="utf-8").splitlines()
    for key, new in after.items():
        i = next(i for i, ln in enumerate(lines) if ln.startswith(key))
        lines[i + 1 : i + 1] = new.split("\n")
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


def _assert_only_the_garbled_rows_differ(clean, garbled, counts: dict[str, int]) -> None:
    for key in ("mag", "accel", "gyro"):
        a, b = getattr(clean, key), getattr(garbled, key)
        assert (a is None) == (b is None), key
        if a is not None:
            np.testing.assert_array_equal(a.t, b.t, err_msg=key)
            np.testing.assert_array_equal(a.xyz, b.xyz, err_msg=key)
    if clean.truth is not None:
        np.testing.assert_array_equal(clean.truth[0], garbled.truth[0])
        np.testing.assert_array_equal(clean.truth[1], garbled.truth[1])
    assert clean.meta == garbled.meta
    assert garbled.dropped == Counter(clean.dropped) + Counter(counts)


def _pdrcsv(d: Path) -> Path:
    d.mkdir()
    t = np.arange(0.0, 2.0, 0.02)
    rows = {
        "mag.csv": np.column_stack([t, 20 + np.sin(t), 5 + np.cos(t), -40 + 0 * t]),
        "accel.csv": np.column_stack([t, 0 * t, 0.1 + 0 * t, 9.8 + 0 * t]),
        "gyro.csv": np.column_stack([t, 0.01 + 0 * t, 0 * t, 0.02 * np.sin(t)]),
    }
    for name, arr in rows.items():
        np.savetxt(d / name, arr, fmt="%.6f", delimiter=",", header="t,x,y,z", comments="")
    q = np.column_stack([t, np.ones_like(t), 0 * t, 0 * t, 0 * t])
    np.savetxt(d / "truth.csv", q, fmt="%.6f", delimiter=",", header="t,qw,qx,qy,qz", comments="")
    return d


def test_pdrcsv(tmp_path):
    clean, bad = _pdrcsv(tmp_path / "clean"), tmp_path / "bad"
    shutil.copytree(clean, bad)
    _insert(bad / "mag.csv", {"0.100000,": "0.110000,45.03479,-58.094788,12.3,4x5,abc\n0.115000,20,5,-4O"})
    _insert(bad / "gyro.csv", {"0.200000,": "O.21,0.01,0,0"})  # the time is not a number
    _insert(bad / "truth.csv", {"0.300000,": "0.31,1,0,0,0,0"})
    _insert(bad / "accel.csv", {"0.400000,": "0.41,0.0\n0.42"})  # two rows cut short, and more after them
    _assert_only_the_garbled_rows_differ(
        read_recording(clean), read_recording(bad),
        {"mag:extra_fields": 1, "mag:non_numeric": 1, "gyro:non_numeric": 1, "truth:extra_fields": 1,
         "accel:short_row": 2},
    )


def test_pdrcsv_short_row_at_a_chunk_end(tmp_path, monkeypatch):
    """A row cut short as the last of a chunk (the next chunk tells whether the file goes on) is dropped
    when rows follow; as the file's last row it ends the read with an error naming it."""
    monkeypatch.setattr(_common, "CHUNK", 7)
    clean, bad = _pdrcsv(tmp_path / "clean"), tmp_path / "bad"
    shutil.copytree(clean, bad)
    lines = (bad / "mag.csv").read_text().splitlines()
    lines.insert(7, "0.121,20")  # line 8: the header and six rows before it, the 7th line of a chunk of 7
    (bad / "mag.csv").write_text("\n".join(lines) + "\n")
    _assert_only_the_garbled_rows_differ(read_recording(clean), read_recording(bad), {"mag:short_row": 1})
    (bad / "mag.csv").write_text("\n".join(lines[:8]) + "\n")
    with pytest.raises(InputError) as ei:
        read_recording(bad)
    assert ei.value.line == 8 and "truncated file" in ei.value.problem


def test_the_issue_row_in_a_replay_is_dropped_and_named(tmp_path, capsys):
    """The issue's row in the embedded walk's mag.csv: the run is the clean run's, row for row, and its
    summary names the row it dropped (besides what the clean run drops too: the pipeline's repeated
    samples)."""
    clean, bad = tmp_path / "clean", tmp_path / "bad"
    shutil.copytree(ROOT / "recordings" / "walk", clean)
    shutil.copytree(clean, bad)
    lines = (bad / "mag.csv").read_text().splitlines()
    i = next(i for i, ln in enumerate(lines) if ln.startswith("10.9"))
    lines.insert(i + 1, ISSUE_ROW)
    (bad / "mag.csv").write_text("\n".join(lines) + "\n")
    out = {}
    for d in (clean, bad):
        assert main(["replay", str(d), "--out-csv", str(d / "h.csv"), "--json", str(d / "s.json")]) == 0
        out[d] = next(ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("dropped samples"))
    assert (clean / "h.csv").read_bytes() == (bad / "h.csv").read_bytes()
    dropped = {d: json.loads((d / "s.json").read_text())["dropped_samples"] for d in (clean, bad)}
    assert "mag:extra_fields" not in dropped[clean]
    assert dropped[bad] == {**dropped[clean], "mag:extra_fields": 1}
    assert out[bad].split(None, 2)[2] == ", ".join(f"{k} {v}" for k, v in dropped[bad].items())
    assert "mag:extra_fields 1" in out[bad] and "mag:extra_fields" not in out[clean]


def _tyrex(d: Path, platform: str) -> Path:
    d.mkdir()
    t = np.arange(0.0, 1.0, 0.02)
    extra = 3 if platform == "android" else 0  # Android's gyro and mag rows carry a drift/bias x, y, z
    cols = {"magnetometer.txt": [30.0, 5.0, -30.0], "accelerometer.txt": [0.0, 0.0, 9.8],
            "gyroscope.txt": [0.01, 0.0, 0.02]}
    if platform == "android":
        (d / "record.properties").write_text("[Device]\nModel = Phone\n\n[Time]\nStartTime = 1464686052\n")
    else:
        (d / "description.txt").write_text("[Time]\nBootTime = 100\n")
        cols["accelerometer.txt"] = [0.0, 0.0, -1.0]
    for name, v in cols.items():
        n_more = extra if name != "accelerometer.txt" else 0
        rows = np.column_stack([t + 100, np.tile(v, (len(t), 1)), np.zeros((len(t), n_more))])
        np.savetxt(d / name, rows, fmt="%.4f")
    return d


@pytest.mark.parametrize("platform", ["android", "ios"])
def test_tyrex(tmp_path, platform):
    clean, bad = _tyrex(tmp_path / "clean", platform), tmp_path / "bad"
    shutil.copytree(clean, bad)
    if platform == "android":  # 7 fields a magnetometer.txt row: an eighth is garbage, so is text in the bias
        _insert(bad / "magnetometer.txt", {"100.1000 ": "100.1100 30 5 -30 0 0 0 1\n100.1200 30 5 -30 0 x 0"})
    else:
        _insert(bad / "magnetometer.txt", {"100.1000 ": "100.1100 30 5 -30 0\n100.1200 30 5 -3o"})
    _insert(bad / "accelerometer.txt", {"100.2000 ": "100.2100 0 0 9.8 1"})
    _assert_only_the_garbled_rows_differ(
        read_recording(clean), read_recording(bad),
        {"mag:extra_fields": 1, "mag:non_numeric": 1, "accel:extra_fields": 1},
    )


def test_sunsided(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    clean, bad = _sunsided(tmp_path / "a"), _sunsided(tmp_path / "b")
    _insert(bad / "mpu6050.csv", {"0.00,": "0.005,0.0,0.0,-1.0,1.0,2.0,3.0,warm"})  # text in temp_C, unread
    _insert(bad / "hmc5883l.csv", {"0.005,": "0.01,0.2,-0.1,-0.3,0.1"})
    _assert_only_the_garbled_rows_differ(
        read_recording(clean), read_recording(bad),
        {"accel:non_numeric": 1, "gyro:non_numeric": 1, "mag:extra_fields": 1},
    )


def test_sensorlogger(tmp_path):
    clean, bad = FIX / "sensorlogger_android", tmp_path / "bad"
    shutil.copytree(clean, bad)
    _insert(bad / "Gyroscope.csv", {
        "1717000000010000000,": "1717000000015000000,0.015000000,0.01,0.001,0.0004,1\n"
                               "17170000000x0000000,0.016000000,0.01,0.001,0.0004",  # text in the unread time
    })
    _assert_only_the_garbled_rows_differ(
        read_recording(clean), read_recording(bad), {"gyro:extra_fields": 1, "gyro:non_numeric": 1}
    )


def test_phyphox(tmp_path):
    clean, bad = FIX / "phyphox", tmp_path / "bad"
    shutil.copytree(clean, bad)
    _insert(bad / "Magnetometer.csv", {
        "4.000000000E-03,": "5.0E-03,5.0,22.4,-40.6,46.6,1\n6.0E-03,5.0,22.4,-40.6,n/a"  # "Absolute": unread
                            "\n7.0E-03,5.0",
    })
    _assert_only_the_garbled_rows_differ(
        read_recording(clean), read_recording(bad),
        {"mag:extra_fields": 1, "mag:non_numeric": 1, "mag:short_row": 1},
    )


def test_msindoor(tmp_path):
    clean, bad = FIX / "msindoor_small.txt", tmp_path / "bad.txt"
    shutil.copy(clean, bad)
    _insert(bad, {
        "1574562661020\tTYPE_MAGNETIC_FIELD_UNCALIBRATED":  # x, y, z, bias x, y, z, accuracy and one more
            "1574562661021\tTYPE_MAGNETIC_FIELD_UNCALIBRATED\t70\t-85\t-340\t50\t-90\t-300\t3\t9",
        "1574562661020\tTYPE_ACCELEROMETER": "1574562661021\tTYPE_ACCELEROMETER\t0.1\t0.2\t9.8\thigh",
        "1574562661000\tTYPE_WAYPOINT": "1574562661001\tTYPE_WAYPOINT\t10.0\t2O.0",
        # the OS-calibrated field is not read (the raw one is there): its garbled lines are not counted
        "1574562661020\tTYPE_MAGNETIC_FIELD\t": "1574562661021\tTYPE_MAGNETIC_FIELD\t2x\t5.0\t-40.0\t3",
        # cut short: a gyroscope row (its stream counts it) and a line of one column (every stream read does)
        "1574562661040\tTYPE_GYROSCOPE_UNCAL": "1574562661041\tTYPE_GYROSCOPE_UNCALIBRATED\t0.01\n1574562661",
    })
    _assert_only_the_garbled_rows_differ(
        read_recording(clean), read_recording(bad),
        {"mag:extra_fields": 1, "accel:non_numeric": 1, "waypoint:non_numeric": 1, "gyro:short_row": 2,
         "mag:short_row": 1, "accel:short_row": 1},
    )


def test_ipin(tmp_path):
    clean, bad = FIX / "ipin_small.txt", tmp_path / "bad.txt"
    shutil.copy(clean, bad)
    _insert(bad, {
        "MAGN;0.206;": "MAGN;0.207;5123.003000;11.7646;25.2246;-37.5096;3;1",
        "ACCE;0.205;": "ACCE;0.2055;5123.005000;0.07351;0.19503;9.80841;III",
        "POSI;0.100;": "POSI;0.101;1;4O.3134;-3.4837;0;0\nPOSI;0.102;1",
        "GYRO;": "GYRO;0.2041;5123.004000;0.01",  # cut short
    })
    _assert_only_the_garbled_rows_differ(
        read_recording(clean), read_recording(bad),
        {"mag:extra_fields": 1, "accel:non_numeric": 1, "position:non_numeric": 1, "position:short_row": 1,
         "gyro:short_row": 1},
    )


def _xio(path: Path, rows: list[str]) -> Path:
    path.write_text(XIO_HEADER + "\n" + "\n".join(rows) + "\n")
    return path


def test_xio(tmp_path):
    rows = [f"{i * 0.01:.2f},0,0,1,0,0,1,{20 + i},0,-40" for i in range(20)]
    garbled = [*rows[:5], "0.045,0,0,1,0,0,1,24.5,0,-40,7", "0.046,0,0,1,O,0,1,24.6,0,-40", "0.047,0,0",
               *rows[5:]]  # fmt: skip
    _assert_only_the_garbled_rows_differ(
        read_recording(_xio(tmp_path / "a.csv", rows)), read_recording(_xio(tmp_path / "b.csv", garbled)),
        {f"{k}:{why}": 1 for k in ("mag", "accel", "gyro") for why in ("extra_fields", "non_numeric",
                                                                        "short_row")},
    )


def test_pdrmcap_json_layout(tmp_path):
    msgs = [{"t": i * 0.02, "x": 20.0 + i, "y": 5.0, "z": -40.0} for i in range(20)]
    odd = [{"t": 0.085, "x": 20.0, "y": "5.0", "z": -40.0}, {"t": 0.086, "x": True, "y": 5, "z": 1}]
    bad = [*msgs[:5], *odd, *msgs[5:]]
    a = _raw_mcap(tmp_path / "a.mcap", "/mag/raw", [json.dumps(m).encode() for m in msgs])
    b = _raw_mcap(tmp_path / "b.mcap", "/mag/raw", [json.dumps(m).encode() for m in bad])
    _assert_only_the_garbled_rows_differ(read_recording(a), read_recording(b), {"mag:non_numeric": 2})


@pytest.mark.parametrize(
    "stream, row",
    [("gyro.csv", "0.0231,1e308,0.0,0.0"), ("mag.csv", "0.0231,3.5e4,1,2"),
     ("accel.csv", "0.0231,-2e4,0,9.8")],
)
def test_a_corrupt_number_is_an_odd_sample(tmp_path, capsys, stream, row):
    """A finite number no sensor of the kind reports (|axis| beyond ``PHYSICAL_LIMITS``: 1e308 rad/s,
    35 000 µT, 2 000 g) inserted between two rows of the embedded walk is dropped and counted as
    ``<stream>:implausible``; the run is the clean run's, row for row, and no numerical warning reaches the
    user (1e308 squared overflowed in the unit check's norm)."""
    key = stream.removesuffix(".csv")
    clean, bad = tmp_path / "clean", tmp_path / "bad"
    shutil.copytree(ROOT / "recordings" / "walk", clean)
    shutil.copytree(clean, bad)
    lines = (bad / stream).read_text().splitlines()
    i = next(i for i, ln in enumerate(lines[1:], start=1) if float(ln.split(",")[0]) > 0.0231)
    lines.insert(i, row)
    (bad / stream).write_text("\n".join(lines) + "\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for d in (clean, bad):
            assert main(["replay", str(d), "--out-csv", str(d / "h.csv"), "--json", str(d / "s.json")]) == 0
    capsys.readouterr()
    assert (clean / "h.csv").read_bytes() == (bad / "h.csv").read_bytes()
    dropped = {d: json.loads((d / "s.json").read_text())["dropped_samples"] for d in (clean, bad)}
    assert dropped[bad] == {**dropped[clean], f"{key}:implausible": 1}


@pytest.mark.parametrize("name", ["truth.csv", "os.csv"])
def test_an_attitude_row_that_is_no_unit_quaternion_is_dropped(tmp_path, capsys, name):
    """An all-zero quaternion row (a logger's placeholder) in the mocap truth or the phone's own attitude is
    no attitude: dropped and counted (``truth:not_unit`` / ``os:not_unit``), the series otherwise the clean
    one; the replay scores against what is left (an all-zero os.csv ended the run with a division by zero in
    the scorer)."""
    key = name.removesuffix(".csv")
    clean, bad = tmp_path / "clean", tmp_path / "bad"
    shutil.copytree(ROOT / "recordings" / "walk", clean)
    if name == "os.csv":  # the truth as the phone's own estimate: a reference series like any other
        shutil.copy(clean / "truth.csv", clean / "os.csv")
    shutil.copytree(clean, bad)
    lines = (bad / name).read_text().splitlines()
    lines.insert(5, f"{(float(lines[4].split(',')[0]) + float(lines[5].split(',')[0])) / 2:.6f},0,0,0,0")
    (bad / name).write_text("\n".join(lines) + "\n")
    plain, odd = read_recording(clean), read_recording(bad)
    series = (lambda r: r.truth) if key == "truth" else (lambda r: r.references["os"])
    for a, b in zip(series(plain), series(odd), strict=True):
        np.testing.assert_array_equal(a, b)
    assert odd.dropped == {**plain.dropped, f"{key}:not_unit": 1}
    assert main(["replay", str(bad), "--json", str(bad / "s.json")]) == 0
    capsys.readouterr()
