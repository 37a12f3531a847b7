"""One row rule for every text reader (``replay.formats._common.row_values``): a garbled row — more fields
than the format defines, or a field that is not a number — is dropped whole and counted under the stream's
``extra_fields`` / ``non_numeric``, the same in every reader, the phone's own attitude (``os``) included.
"""

from __future__ import annotations

import shutil
from collections import Counter
from pathlib import Path

import numpy as np

from replay.formats import open_recording
from replay.formats._common import row_values
from tests.test_formats_garbled import _tyrex

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
    mag = {"dropped": dropped, "keys": ("mag",)}
    assert row_values(["0.1", " 2", "3e1"], 4, **mag) == [0.1, 2.0, 30.0]
    assert row_values(["0.1", "2", "3", "4", "5"], 4, dropped=dropped, keys=("mag", "accel")) is None
    assert row_values(["0.1", "2", "x"], 4, **mag) is None
    assert row_values(["0.1", "2", "x", "4", "5"], 4, **mag) is None  # both: extra_fields
    assert row_values(["nan", "inf", "3"], 4, **mag) is not None  # numbers: the builder's to judge
    assert dropped == {"mag:extra_fields": 2, "accel:extra_fields": 1, "mag:non_numeric": 1}


def test_row_values_numeric_leaves_the_later_fields_to_the_caller_and_no_keys_count_nothing():
    dropped = Counter()
    pos = {"dropped": dropped, "keys": ("position",), "numeric": 4}
    assert row_values(["1", "2", "3", "4", "F1", "B"], 6, **pos) == [1, 2, 3, 4]
    assert row_values(["1", "2", "x", "4", "F1", "B"], 6, **pos) is None
    assert row_values(["1", "2", "3", "4", "F1", "B", "7"], 6, **pos) is None
    assert dropped == {"position:non_numeric": 1, "position:extra_fields": 1}
    assert row_values(["1", "x"], 4) is None and row_values(["1", "2", "3"], 2) is None
