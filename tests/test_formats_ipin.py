"""IPIN / GetSensorData logfiles: a synthetic fixture in the documented layout, and malformed variants."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from replay.errors import InputError
from replay.formats import detect, read_recording

FIXTURE = Path(__file__).parent / "fixtures" / "ipin_small.txt"


def test_fixture():
    assert detect(FIXTURE) == "ipin"
    rec = read_recording(FIXTURE)
    assert rec.meta["device"] == "Acme P2"
    assert (len(rec.mag), len(rec.accel), len(rec.gyro)) == (15, 30, 30)
    assert rec.meta["positions"][1] == [0.45, 40.3135, -3.4836, 0.0, 0.0]
    # one sensor clock: shifted as one, so the magnetometer keeps its 2 ms lead over the accelerometer
    np.testing.assert_allclose(rec.mag.t[0] - rec.accel.t[0], 0.002, atol=1e-9)
    np.testing.assert_allclose(np.diff(rec.accel.t), 0.01, atol=1e-9)
    # on the app clock: the first accelerometer sample was delivered at 0.203 s or later
    assert 0.2 <= rec.accel.t[0] <= 0.2 + 0.0035
    np.testing.assert_allclose(rec.accel.xyz.mean(axis=0), [0.1, 0.2, 9.8], atol=0.02)


def _edit(tmp_path, old, new):
    f = tmp_path / "log.txt"
    f.write_text(FIXTURE.read_text().replace(old, new, 1))
    return f


def test_nan_and_duplicate(tmp_path):
    text = FIXTURE.read_text().splitlines()
    magn = [i for i, ln in enumerate(text) if ln.startswith("MAGN;")]
    text[magn[2]] = ";".join(text[magn[2]].split(";")[:3] + ["NaN", "1", "2", "3"])
    text.insert(magn[4] + 1, text[magn[4]])
    f = tmp_path / "log.txt"
    f.write_text("\n".join(text) + "\n")
    rec = read_recording(f)
    assert rec.dropped == {"mag:nan": 1, "mag:duplicate_t": 1} and len(rec.mag) == 14


@pytest.mark.parametrize(
    "old,new,problem,line",
    [
        ("MAGN;0.226;5123.022000", "MAGN;0.226;5122.022000", "time goes backwards", 21),
        ("MAGN;0.226;5123.022000;12.1229;25.2490;-38.4929;3", "MAGN;0.226;5123.022000;12.1", "truncated", 21),
    ],
)
def test_malformed(tmp_path, old, new, problem, line):
    f = _edit(tmp_path, old, new)
    if problem == "truncated":  # the row cut short ends the file (inside it, it is dropped: below)
        f.write_text("".join(f.read_text().splitlines(keepends=True)[:line]))
    with pytest.raises(InputError) as ei:
        read_recording(f)
    assert problem in ei.value.problem and ei.value.line == line and str(f) in str(ei.value)


def test_no_magnetometer(tmp_path):
    f = tmp_path / "log.txt"
    f.write_text(
        "\n".join(ln for ln in FIXTURE.read_text().splitlines() if not ln.startswith("MAGN;")) + "\n"
    )
    assert detect(f) == "ipin"  # by its header
    with pytest.raises(InputError, match="no MAGN records"):
        read_recording(f)


def test_field_in_nanotesla_is_wrong_unit(tmp_path):
    lines = [
        ";".join(p[:3] + [str(float(v) * 1000) for v in p[3:6]] + p[6:]) if p[0] == "MAGN" else ";".join(p)
        for p in (ln.split(";") for ln in FIXTURE.read_text().splitlines())
    ]
    f = tmp_path / "log.txt"
    f.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match=r"median \|mag\| is .* outside the plausible"):
        read_recording(f)


def _with_header_line(tmp_path, line):
    anchor = "% Phone used for this logfile:"
    text = FIXTURE.read_text().replace(anchor, f"{line}\n{anchor}")
    f = tmp_path / "log.txt"
    f.write_text(text)
    return f


def test_os_calibrated_streams_and_no_date():
    rec = read_recording(FIXTURE)
    assert rec.meta["mag_os_calibrated"] is True and rec.meta["gyro_os_calibrated"] is True
    assert "date" not in rec.meta and "date_unreadable" not in rec.meta
    assert not any(k.startswith(("mag_os_bias", "gyro_os_bias", "device_id")) for k in rec.meta)


@pytest.mark.parametrize(
    "stated,day",
    [
        ("Thu Sep 12 10:22:32 GMT+02:00 2019", "2019-09-12"),  # what the app writes: Date.toString()
        ("Tue Jun 04 09:15:00 CEST 2019", "2019-06-04"),
        ("2019-09-12 10:22:32", "2019-09-12"),
        ("2019/09/12", "2019-09-12"),
    ],
)
def test_date_of_creation(tmp_path, stated, day):
    rec = read_recording(_with_header_line(tmp_path, f"% Date of creation: {stated}"))
    assert rec.meta["date"] == day and "date_unreadable" not in rec.meta
    # with the POSI fixes' place, the field model is known: the pipeline can give true north
    from pdr_mag.field import earth_field_from_meta

    field = earth_field_from_meta(rec.meta)
    assert field is not None and 35 < field.strength < 50  # Madrid, about 45 µT
    assert (len(rec.mag), len(rec.accel)) == (15, 30)  # the samples are as before


def test_date_of_creation_unreadable(tmp_path):
    rec = read_recording(_with_header_line(tmp_path, "% Date of creation: 12.09.2019 10h22"))
    assert "date" not in rec.meta and rec.meta["date_unreadable"] == "12.09.2019 10h22"
    assert (len(rec.mag), len(rec.accel)) == (15, 30)
