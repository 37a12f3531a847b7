"""Indoor Location Competition 2.0 path logs: the real traces and a small synthetic fixture."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from replay.errors import InputError
from replay.formats import detect, msindoor, read_recording
from tests.conftest import dataset

FIXTURE = Path(__file__).parent / "fixtures" / "msindoor_small.txt"


def test_real_trace():
    f = dataset("ms-indoor-location-2020", "site1", "F1", "path_data_files", "5dd9ef979191710006b57086.txt")
    assert detect(f) == "ms-indoor"
    rec = read_recording(f)
    assert rec.meta["device"] == "OPPO PBCM10" and rec.meta["date"] == "2019-11-24"
    assert len(rec.meta["waypoints"]) == 17 and rec.meta["mag_os_calibrated"] is False
    # the mall (SOURCE.md: bounding box about 30.292–30.294 N, 120.073–120.077 E) from the floor's geojson
    assert 30.29 < rec.meta["latitude_deg"] < 30.30 and 120.07 < rec.meta["longitude_deg"] < 120.08
    for s in (rec.mag, rec.accel, rec.gyro):
        assert len(s) == 5755 and abs(s.rate_hz - 50.0) < 1.0
    assert abs(rec.mag.duration - 114.3) < 0.5
    # the raw field minus the OS's hard-iron estimate is the Earth's field (SOURCE.md: p50 41.8 µT)
    cal = rec.mag.xyz - np.asarray(rec.meta["mag_os_bias_uT"])
    assert 38 < np.median(np.linalg.norm(cal, axis=1)) < 46
    # held flat in front of the body: gravity mostly on +z
    assert np.median(rec.accel.xyz[:, 2]) > 8.0


def test_fixture():
    rec = msindoor.read(FIXTURE)
    assert rec.meta["device"] == "Acme P1" and rec.meta["mag_os_calibrated"] is False
    np.testing.assert_allclose(rec.mag.t, [0.02, 0.06, 0.08])
    np.testing.assert_allclose(rec.mag.xyz[:, 0], [70.0, 71.0, 72.0])
    np.testing.assert_allclose(rec.gyro.xyz[0], [0.011, 0.021, 0.031])  # the uncalibrated gyro preferred
    assert rec.dropped == {"mag:nan": 1, "accel:duplicate_t": 1, "accel:saturated": 1}
    assert rec.meta["waypoints"] == [[0.0, 10.0, 20.0], [0.07, 11.0, 20.5]]
    assert rec.meta["mag_os_bias_uT"] == [50.0, -90.0, -300.0]
    assert "latitude_deg" not in rec.meta  # no floor map beside the fixture


def _write(tmp_path, replace_from, replace_to):
    text = FIXTURE.read_text().replace(replace_from, replace_to, 1)
    f = tmp_path / "trace.txt"
    f.write_text(text)
    return f


@pytest.mark.parametrize(
    "old,new,problem,line",
    [
        (
            "1574562661080\tTYPE_MAGNETIC_FIELD_UNCALIBRATED",
            "1574562661050\tTYPE_MAGNETIC_FIELD_UNCALIBRATED",
            "time goes backwards",
            25,
        ),
        (
            "0.1\t0.2\t9.8\t3\n1574562661080\tTYPE_GYROSCOPE_UNCAL",
            "0.1\n1574562661080\tTYPE_GYROSCOPE_UNCAL",
            "truncated",
            26,
        ),
    ],
)
def test_malformed(tmp_path, old, new, problem, line):
    f = _write(tmp_path, old, new)
    with pytest.raises(InputError) as ei:
        read_recording(f)
    assert problem in ei.value.problem and ei.value.line == line and "trace.txt" in str(ei.value)


def test_no_magnetometer_and_wrong_unit(tmp_path):
    lines = [ln for ln in FIXTURE.read_text().splitlines() if "MAGNETIC" not in ln]
    f = tmp_path / "nomag.txt"
    f.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match="no magnetometer"):
        read_recording(f)
    f = _write(tmp_path, "TYPE_ACCELEROMETER\t0.1\t0.2\t9.8", "TYPE_ACCELEROMETER\t0.1\t0.2\t9.8")
    text = f.read_text().replace("\t-85.0\t-340.0", "\t-85000.0\t-340000.0")
    f.write_text(text)
    with pytest.raises(InputError, match="wrong unit"):
        read_recording(f)
