"""x-io CSV (units in the header, sample-and-hold magnetometer): the real Fusion example and fixtures."""

from __future__ import annotations

import numpy as np
import pytest

from replay.errors import InputError
from replay.formats import detect, read_recording
from tests.conftest import dataset

HEADER = (
    "Time (s),Gyroscope X (deg/s),Gyroscope Y (deg/s),Gyroscope Z (deg/s),Accelerometer X (g),"
    "Accelerometer Y (g),Accelerometer Z (g),Magnetometer X (uT),Magnetometer Y (uT),Magnetometer Z (uT)"
)


def test_real_file():
    f = dataset("xio-fusion", "sensor_data.csv")
    assert detect(f) == "xio-csv"
    rec = read_recording(f)
    assert len(rec.accel) == 13514 and abs(rec.accel.rate_hz - 100) < 2
    assert 18 < rec.mag.rate_hz < 22  # SOURCE.md: new values every ~50 ms, repeats left out
    assert rec.dropped["mag:held_repeat"] == 13514 - len(rec.mag)
    assert 42 < np.median(np.linalg.norm(rec.mag.xyz, axis=1)) < 45  # calibrated, |m| ≈ 43.6 µT
    np.testing.assert_allclose(np.median(rec.accel.xyz[:500], axis=0), [0, 0, 9.8], atol=0.3)
    assert np.degrees(np.abs(rec.gyro.xyz).max()) == pytest.approx(365, abs=5)  # peak 365 deg/s


def _write(tmp_path, rows, header=HEADER):
    f = tmp_path / "imu.csv"
    f.write_text(header + "\n" + "\n".join(rows) + "\n")
    return f


def test_fixture_units(tmp_path):
    rows = [f"{i * 0.01},0,0,57.29577951308232,0,0,1,20,0,-40" for i in range(3)]
    rows += ["0.03,0,0,57.29577951308232,0,0,1,21,0,-40"]
    rec = read_recording(_write(tmp_path, rows))
    np.testing.assert_allclose(rec.gyro.xyz[0], [0, 0, 1.0])
    np.testing.assert_allclose(rec.accel.xyz[0], [0, 0, 9.80665])
    np.testing.assert_allclose(rec.mag.t, [0.0, 0.03])
    assert rec.dropped == {"mag:held_repeat": 2}


@pytest.mark.parametrize(
    "rows,header,problem,line",
    [
        (["0,0,0,0,0,0,1,20,0,-40", "0.01,0,0,0"], HEADER, "truncated", 3),
        (
            ["0,0,0,0,0,0,1,20,0,-40", "0.01,0,0,0,0,0,1,21,0,-40"],
            HEADER.replace("(uT)", "(mT)"),
            "unknown unit",
            1,
        ),
        (
            ["0,0,0,0,0,0,1,20,0,-40", "0.01,0,0,0,0,0,1,21,0,-40"],
            HEADER.replace("(uT)", "(nT)"),
            "wrong unit",
            None,
        ),
    ],
)
def test_malformed(tmp_path, rows, header, problem, line):
    with pytest.raises(InputError) as ei:
        read_recording(_write(tmp_path, rows, header))
    assert problem in ei.value.problem and ei.value.line == line and "imu.csv" in ei.value.path
