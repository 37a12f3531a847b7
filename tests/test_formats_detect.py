"""Format detection: every known layout is recognised by exactly one reader; bad input ends the commands with
exit code 2 and one line naming the file."""

from __future__ import annotations

import importlib
import shutil
from pathlib import Path

import numpy as np
import pytest

from replay.cli import main
from replay.formats import READERS, detect, formats, read_recording
from tests.conftest import dataset

FIX = Path(__file__).parent / "fixtures"
FIXTURES = {
    "sensorlogger_android": "sensor-logger",
    "sensorlogger_ios": "sensor-logger",
    "phyphox": "phyphox",
    "msindoor_small.txt": "ms-indoor",
    "ipin_small.txt": "ipin",
}
REAL = {
    ("tyrex-pdrcsv", "calib_mag_Nexus5_d1"): "pdr-csv",
    ("tyrex-attitude", "android", "calib_mag_Nexus5_d1"): "tyrex",
    ("tyrex-attitude", "ios", "calib_mag_iPhone5_d3"): "tyrex",
    (
        "ms-indoor-location-2020",
        "site1",
        "B1",
        "path_data_files",
        "5dda257f9191710006b572b5.txt",
    ): "ms-indoor",
    ("broad", "data_mat", "36_disturbed_attached_magnet_5cm.mat"): "broad",
    ("sunsided-marg", "set-2", "rotate-ccw-around-z-pointing-up"): "sunsided-marg",
    ("xio-fusion", "sensor_data.csv"): "xio-csv",
}


def _hits(path: Path) -> list[str]:
    return [
        m.NAME for m in (importlib.import_module(f"replay.formats.{n}") for n in READERS) if m.detect(path)
    ]


def test_all_readers_present():
    assert formats() == [
        "pdr-csv",
        "tyrex",
        "sunsided-marg",
        "sensor-logger",
        "phyphox",
        "ms-indoor",
        "ipin",
        "broad",
        "xio-csv",
        "pdr-mcap",
        "ros2-mcap",
    ]


@pytest.mark.parametrize("name,fmt", sorted(FIXTURES.items()))
def test_fixture_detected_once(name, fmt):
    assert _hits(FIX / name) == [fmt]


@pytest.mark.parametrize("parts,fmt", sorted(REAL.items()))
def test_real_detected_once(parts, fmt):
    assert _hits(dataset(*parts)) == [fmt]


def test_not_recordings(tmp_path):
    (tmp_path / "notes.txt").write_text("hello\n")
    assert detect(tmp_path / "notes.txt") is None and detect(tmp_path) is None
    with pytest.raises(Exception, match="not a recording in a known format"):
        read_recording(tmp_path / "notes.txt")


def test_mocap_files_beside_tyrex_trials_are_not_recordings():
    q = dataset("tyrex-attitude", "qualisys", "Thibaud_Nexus5_NoDist_Texting.mat")
    assert detect(q) is None


def _one_line_exit_2(capsys, argv, must_name):
    rc = main(argv)
    err = capsys.readouterr().err.strip()
    assert rc == 2, err
    assert err.count("\n") == 0 and err.startswith("pdr-mag: ") and must_name in err
    assert "Traceback" not in err
    return err


@pytest.mark.parametrize(
    "name,file,old,new,where",
    [
        ("sensorlogger_android", "Gyroscope.csv", "0.010000000,", "-0.010000000,", "Gyroscope.csv:3"),
        # a row cut short (new ends with "|"): the file ends with it — inside a file it is dropped
        ("phyphox", "Magnetometer.csv", "4.000000000E-03,5.010257830E+00,", "4.000000000E-03|",
         "Magnetometer.csv:2"),
        ("msindoor_small.txt", None, "72.0\t-85.0\t-340.0\t50.0\t-90.0\t-300.0\t3", "72.0\t-85.0|",
         "msindoor_small.txt:25"),
        ("ipin_small.txt", None, "MAGN;0.226;5123.022000", "MAGN;0.226;5122.022000", "ipin_small.txt:21"),
    ],
)
def test_cli_exit_2_on_malformed(tmp_path, capsys, name, file, old, new, where):
    src = FIX / name
    if src.is_dir():
        dst = Path(shutil.copytree(src, tmp_path / name))
        f = dst / file
    else:
        dst = f = tmp_path / name
        shutil.copy(src, dst)
    text = f.read_text(encoding="utf-8").replace(old, new, 1)
    if new.endswith("|"):
        text = text[: text.index(new) + len(new) - 1] + "\n"
    f.write_text(text, encoding="utf-8")
    _one_line_exit_2(capsys, ["calibrate", str(dst)], where)


def test_cli_exit_2_on_truncated_mcap(tmp_path, capsys):
    from tests.test_formats_mcap import _rec, _write

    f = _write(_rec(2000), tmp_path / "t.mcap")
    f.write_bytes(f.read_bytes()[:5000])
    err = _one_line_exit_2(capsys, ["calibrate", str(f)], "t.mcap")
    assert "truncated or damaged MCAP" in err


def test_cli_calibrates_a_raw_tyrex_recording(tmp_path, capsys):
    d = dataset("tyrex-attitude", "android", "calib_mag_Nexus5_d1")
    rc = main(["calibrate", str(d), "--method", "sphere", "--json", str(tmp_path / "c.json")])
    assert rc == 0, capsys.readouterr().err
    import json

    cal = json.loads((tmp_path / "c.json").read_text())
    # SOURCE.md: d1 sphere centre ≈ (58.3, −73.6, 412.3) µT, to one decimal: the same least-squares sphere
    # agrees to that rounding (measured within 0.03 µT)
    np.testing.assert_allclose(cal["offset_uT"], [58.3, -73.6, 412.3], atol=0.051)


def _bad_tyrex(tmp_path):
    from tests.test_formats_tyrex import _android

    return _android(tmp_path, "0.0 30 0 -30\n0.02 30\n"), "magnetometer.txt:2"


def _bad_sunsided(tmp_path):
    from tests.test_formats_sunsided import _fixture

    return _fixture(tmp_path, hmc_rows=["0.0,0.2,-0.1,-0.3", "0.1,0.2"]), "hmc5883l.csv:3"


def _bad_broad(tmp_path):
    from tests.test_formats_broad import _mat

    f = _mat(tmp_path)
    f.write_bytes(f.read_bytes()[:300])
    return f, "trial.mat"


def _bad_xio(tmp_path):
    from tests.test_formats_xio import HEADER, _write

    return _write(tmp_path, ["0,0,0,0,0,0,1,20,0,-40", "0.01,0,0,0"], HEADER), "imu.csv:3"


def _bad_ros2(tmp_path):
    from tests.test_formats_ros2 import write_bag

    f = write_bag(tmp_path / "bag.mcap", n=400)
    f.write_bytes(f.read_bytes()[:20000])
    return f, "bag.mcap"


@pytest.mark.parametrize("make", [_bad_tyrex, _bad_sunsided, _bad_broad, _bad_xio, _bad_ros2])
def test_cli_exit_2_other_readers(tmp_path, capsys, make):
    path, where = make(tmp_path)
    _one_line_exit_2(capsys, ["calibrate", str(path)], where)


def _with_bom(src: Path, dst: Path) -> Path:
    """A copy of ``src`` (a file, or a directory whose .csv/.txt files are all rewritten) whose text files
    start with the UTF-8 byte-order mark a spreadsheet or a Windows tool writes."""
    if src.is_dir():
        shutil.copytree(src, dst)
        files = [f for f in dst.iterdir() if f.suffix in (".csv", ".txt", ".json", ".properties")]
    else:
        shutil.copy(src, dst)
        files = [dst]
    for f in files:
        f.write_bytes(b"\xef\xbb\xbf" + f.read_bytes())
    return dst


@pytest.mark.parametrize("name", ["walk", "msindoor_small.txt", "ipin_small.txt", "phyphox", "xio", "tyrex"])
def test_a_byte_order_mark_is_skipped(tmp_path, name):
    """A recording whose text files (the metadata too: meta.json, record.properties) start with a byte-order
    mark reads exactly as without it (pdr-csv, ms-indoor, IPIN, phyphox, x-io, tyrex): the same format,
    streams, metadata and odd-sample counts."""
    if name == "walk":
        src = Path(__file__).resolve().parents[1] / "recordings" / "walk"
    elif name == "tyrex":
        from tests.test_formats_garbled import _tyrex

        src = _tyrex(tmp_path / "tyrex_android", "android")
    elif name == "xio":
        src = tmp_path / "sensor_data.csv"
        from tests.test_formats_xio import HEADER

        rows = [f"{0.01 * i:.2f},0,0,0.1,0,0,1,{20 + i % 7},5,-40" for i in range(50)]
        src.write_text(HEADER + "\n" + "\n".join(rows) + "\n")
    else:
        src = FIX / name
    bom = _with_bom(src, tmp_path / f"bom_{src.name}")
    plain, marked = read_recording(src), read_recording(bom)
    assert detect(bom) == detect(src)
    for key in ("mag", "accel", "gyro"):
        a, b = getattr(plain, key), getattr(marked, key)
        np.testing.assert_array_equal(a.t, b.t)
        np.testing.assert_array_equal(a.xyz, b.xyz)
    assert marked.dropped == plain.dropped
    assert marked.meta == plain.meta
