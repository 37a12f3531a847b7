"""One row rule for every text reader (``replay.formats._common.row_values``): a garbled row — more fields
than the format defines, or a field that is not a number — is dropped whole and counted under the stream's
``extra_fields`` / ``non_numeric``, the same in every reader, the phone's own attitude (``os``) included.
"""

from __future__ import annotations

import shutil
from collections import Counter
from pathlib import Path

import numpy as np

from replay.formats import _common, open_recording, read_recording
from replay.formats._common import row_values
from tests.test_formats_garbled import _pdrcsv, _tyrex, _xio

FIX = Path(__file__).parent / "fixtures"
#: The phone-attitude rows each reader below gets besides its good ones: text in a cell, one field more
#: than the record has, a NaN value.
OS_ODD = {"os:non_numeric": 1, "os:extra_fields": 1, "os:nan": 1}


# --------------------------------------------------------------------------- the phone's own attitude
def _append(path: Path, rows: list[str]) -> Path:
    path.write_text(path.read_text(encoding="utf-8").rstrip("\n") + "\n" + "\n".join(rows) + "\n")
    return path


def _msindoor(d: Path, odd: bool) -> Path:
    d.mkdir()
    f = d / "log.txt"
    shutil.copy(FIX / "msindoor_small.txt", f)
    rows = [f"15745626610{30 + k}\tTYPE_ROTATION_VECTOR\t0.0\t0.0\t0.1\t3" for k in range(5)]
    if odd:  # x, y, z and the accuracy after the type
        rows += ["1574562661040\tTYPE_ROTATION_VECTOR\t0.0\tO.0\t0.1\t3",
                 "1574562661041\tTYPE_ROTATION_VECTOR\t0.0\t0.0\t0.1\t3\t7",
                 "1574562661042\tTYPE_ROTATION_VECTOR\t0.0\tNaN\t0.1\t3"]
    return _append(f, rows)


def _ipin(d: Path, odd: bool) -> Path:
    d.mkdir()
    f = d / "log.txt"
    shutil.copy(FIX / "ipin_small.txt", f)
    rows = [f"AHRS;{0.40 + 0.01 * k:.2f};{5123.2 + 0.01 * k:.2f};0;0;0;0.0;0.0;0.1;3" for k in range(5)]
    if odd:  # app and sensor time, three angles, the rotation vector's x, y, z, the accuracy
        rows += ["AHRS;0.45;5123.25;0;0;0;0.0;x;0.1;3", "AHRS;0.46;5123.26;0;0;0;0.0;0.0;0.1;3;7",
                 "AHRS;0.47;5123.27;0;0;0;0.0;nan;0.1;3"]
    return _append(f, rows)


def _tyrex_android(d: Path, odd: bool) -> Path:
    _tyrex(d, "android")
    rows = [f"{100.0 + 0.02 * k:.2f} 0.0 0.0 0.1 0.99 0" for k in range(5)]
    if odd:  # t, qx, qy, qz, qw, the heading accuracy
        rows += ["100.11 0.0 x 0.1 0.99 0", "100.12 0.0 0.0 0.1 0.99 0 7", "100.13 0.0 nan 0.1 0.99 0"]
    (d / "rotation-vector.txt").write_text("\n".join(rows) + "\n")
    return d


def test_the_phone_attitudes_odd_rows_have_the_same_names_in_every_reader(tmp_path):
    """ms-indoor's ``TYPE_ROTATION_VECTOR``, ipin's ``AHRS`` and tyrex's ``rotation-vector.txt``: text in a
    cell is ``os:non_numeric``, a field too many ``os:extra_fields`` (both rows dropped whole), a NaN
    ``os:nan``; the good rows read as without them."""
    for make in (_msindoor, _ipin, _tyrex_android):
        src = {}
        for odd in (False, True):
            src[odd] = open_recording(make(tmp_path / f"{make.__name__}-{odd}", odd))
        (t0, q0), (t1, q1) = src[False].references["os"], src[True].references["os"]
        assert len(t0) >= 5, make.__name__  # the good rows (and the fixture's own)
        np.testing.assert_array_equal(t0, t1)
        np.testing.assert_array_equal(q0, q1)
        assert src[True].dropped == Counter(src[False].dropped) + Counter(OS_ODD), make.__name__


# ------------------------------------------------------------------------------------ the rule itself
def test_row_values_reads_a_good_row_and_counts_a_garbled_one_under_each_stream():
    dropped = Counter()
    assert row_values(["0.1", " 2", "3e1"], 4, dropped, "mag") == [0.1, 2.0, 30.0]
    assert row_values(["0.1", "2", "3", "4", "5"], 4, dropped, "mag", "accel") is None
    assert row_values(["0.1", "2", "x"], 4, dropped, "mag") is None
    assert row_values(["0.1", "2", "x", "4", "5"], 4, dropped, "mag") is None  # both: extra_fields
    assert row_values(["nan", "inf", "3"], 4, dropped, "mag") is not None  # numbers: the builder's to judge
    assert dropped == {"mag:extra_fields": 2, "accel:extra_fields": 1, "mag:non_numeric": 1}


def test_row_values_numeric_leaves_the_later_fields_to_the_caller_and_no_keys_count_nothing():
    dropped = Counter()
    assert row_values(["1", "2", "3", "4", "F1", "B"], 6, dropped, "position", numeric=4) == [1, 2, 3, 4]
    assert row_values(["1", "2", "x", "4", "F1", "B"], 6, dropped, "position", numeric=4) is None
    assert row_values(["1", "2", "3", "4", "F1", "B", "7"], 6, dropped, "position", numeric=4) is None
    assert dropped == {"position:non_numeric": 1, "position:extra_fields": 1}
    assert row_values(["1", "x"], 4) is None and row_values(["1", "2", "3"], 2) is None


# ---------------------------------------------------------------- the same garbled rows, every reader
def _mag_rows(path: Path, after: str, rows: list[str]) -> None:
    """Insert ``rows`` after the first line starting with ``after``."""
    lines = path.read_text(encoding="utf-8").splitlines()
    i = next(i for i, ln in enumerate(lines) if ln.startswith(after))
    lines[i + 1 : i + 1] = rows
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


def _garbled_copies(tmp_path: Path) -> dict[str, tuple[Path, Path]]:
    """Per reader, a clean recording and its copy with two garbled magnetometer rows after the first: one
    field more than the format has, and text in a field."""
    out = {}
    clean = _pdrcsv(tmp_path / "pdrcsv")
    bad = shutil.copytree(clean, tmp_path / "pdrcsv-bad")
    _mag_rows(bad / "mag.csv", "0.000000,", ["0.001,20,5,-40,1", "0.002,20,5,-4O"])
    out["pdr-csv"] = clean, bad
    xio = [f"{i * 0.01:.2f},0,0,1,0,0,1,{20 + i},0,-40" for i in range(20)]
    out["xio"] = (_xio(tmp_path / "xio.csv", xio),
                  _xio(tmp_path / "xio-bad.csv", [xio[0], "0.001,0,0,1,0,0,1,20,0,-40,1",
                                                  "0.002,0,0,1,0,0,1,20,O,-40", *xio[1:]]))
    bad = shutil.copytree(FIX / "phyphox", tmp_path / "phyphox-bad")
    _mag_rows(bad / "Magnetometer.csv", "4.000000000E-03,", ["5.0E-03,5,22,-40,46,1", "6.0E-03,5,22,-40,n/a"])
    out["phyphox"] = FIX / "phyphox", bad
    bad = shutil.copy(FIX / "msindoor_small.txt", tmp_path / "msindoor-bad.txt")
    _mag_rows(bad, "1574562661020\tTYPE_MAGNETIC_FIELD_UNCALIBRATED", [
        "1574562661021\tTYPE_MAGNETIC_FIELD_UNCALIBRATED\t70\t-85\t-340\t50\t-90\t-300\t3\t1",
        "1574562661022\tTYPE_MAGNETIC_FIELD_UNCALIBRATED\t70\t-85\t-34O\t50\t-90\t-300\t3",
    ])
    out["ms-indoor"] = FIX / "msindoor_small.txt", bad
    bad = shutil.copy(FIX / "ipin_small.txt", tmp_path / "ipin-bad.txt")
    _mag_rows(bad, "MAGN;0.206;", ["MAGN;0.207;5123.003;11.7;25.2;-37.5;3;1",
                                    "MAGN;0.208;5123.004;11.7;2S.2;-37.5;3"])
    out["ipin"] = FIX / "ipin_small.txt", bad
    clean = _tyrex(tmp_path / "tyrex", "android")
    bad = shutil.copytree(clean, tmp_path / "tyrex-bad")
    _mag_rows(bad / "magnetometer.txt", "100.0000 ", ["100.0010 30 5 -30 0 0 0 1", "100.0020 30 5 -3o 0 0 0"])
    out["tyrex"] = clean, bad
    return out


def test_a_garbled_row_is_dropped_and_counted_the_same_by_every_reader_through_row_values(
    tmp_path, monkeypatch
):
    """The same two garbled magnetometer rows (a field too many, text in a field) in six readers' files:
    every reader drops both whole (its samples are the clean file's) and counts one of each — under the
    names ``row_values`` gives, so renaming the reasons there renames them in every reader."""
    monkeypatch.setattr(_common, "EXTRA_FIELDS", "extra_fields (row_values)")
    monkeypatch.setattr(_common, "NON_NUMERIC", "non_numeric (row_values)")
    counted = {}
    for reader, (clean, bad) in _garbled_copies(tmp_path).items():
        a, b = read_recording(clean), read_recording(bad)
        np.testing.assert_array_equal(a.mag.t, b.mag.t, err_msg=reader)
        np.testing.assert_array_equal(a.mag.xyz, b.mag.xyz, err_msg=reader)
        diff = Counter(b.dropped) - Counter(a.dropped)
        counted[reader] = {k: n for k, n in diff.items() if k.startswith("mag:")}  # x-io: every stream's
    expected = {"mag:extra_fields (row_values)": 1, "mag:non_numeric (row_values)": 1}
    assert counted == dict.fromkeys(counted, expected)
