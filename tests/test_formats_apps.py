"""Phone-app exports: Sensor Logger (Android, iOS) and phyphox — fixtures written from the documented column
layouts, as folders and as zips, and malformed variants."""

from __future__ import annotations

import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest

from replay.errors import InputError
from replay.formats import detect, read_recording

FIX = Path(__file__).parent / "fixtures"


def _copy(tmp_path, name):
    return Path(shutil.copytree(FIX / name, tmp_path / name))


def _zip(src: Path, dst: Path) -> Path:
    with zipfile.ZipFile(dst, "w", zipfile.ZIP_DEFLATED) as z:
        for f in sorted(src.rglob("*")):
            if f.is_file():
                z.write(f, f"export/{f.relative_to(src).as_posix()}")
    return dst


# --- Sensor Logger ---


def test_sensorlogger_android():
    rec = read_recording(FIX / "sensorlogger_android")
    assert rec.format == "sensor-logger" and rec.meta["platform"] == "android"
    assert rec.meta["mag_os_calibrated"] is False  # the uncalibrated file preferred
    np.testing.assert_allclose(rec.mag.xyz.mean(axis=0), [30, -50, 260], atol=0.5)
    np.testing.assert_allclose(rec.accel.xyz.mean(axis=0), [0, 0, 9.81], atol=0.05)  # TotalAcceleration
    assert rec.meta["accel_source"] == "TotalAcceleration"
    assert rec.meta["date"] == "2024-05-29" and rec.meta["latitude_deg"] == 45.1878
    np.testing.assert_allclose(rec.mag.t[:2], [0.005, 0.025])


def test_sensorlogger_ios_signs(tmp_path):
    rec = read_recording(FIX / "sensorlogger_ios")
    # iOS: gravity −z lying flat → the contract's specific force +9.81 on z
    np.testing.assert_allclose(rec.accel.xyz.mean(axis=0), [0, 0, 9.81], atol=0.05)
    assert rec.meta["accel_source"] == "Accelerometer+Gravity" and rec.meta["mag_os_calibrated"] is True
    assert len(rec.accel) == 40 and len(rec.gyro) == 38
    # the uncalibrated accelerometer in g (iOS sign) is preferred and scaled
    d = _copy(tmp_path, "sensorlogger_ios")
    rows = ["time,seconds_elapsed,z,y,x"] + [
        f"{1717000000000000000 + i * 10**7},{i * 0.01:.2f},-1.0,0.0,0.0" for i in range(5)
    ]
    (d / "AccelerometerUncalibrated.csv").write_text("\n".join(rows) + "\n")
    rec = read_recording(d)
    assert rec.meta["accel_source"] == "AccelerometerUncalibrated"
    np.testing.assert_allclose(rec.accel.xyz, np.tile([0, 0, 9.80665], (5, 1)))
    # standardised: Android conventions
    md = (d / "Metadata.csv").read_text().replace(",false,", ",true,")
    (d / "Metadata.csv").write_text(md)
    with pytest.raises(InputError, match="wrong unit"):  # −1 "m/s²" cannot be right
        read_recording(d)


def test_sensorlogger_zip(tmp_path):
    z = _zip(FIX / "sensorlogger_android", tmp_path / "rec.zip")
    assert detect(z) == "sensor-logger"
    a, b = read_recording(z), read_recording(FIX / "sensorlogger_android")
    np.testing.assert_array_equal(a.mag.xyz, b.mag.xyz)
    np.testing.assert_array_equal(a.accel.t, b.accel.t)


def test_sensorlogger_truncated_zip(tmp_path):
    z = _zip(FIX / "sensorlogger_android", tmp_path / "rec.zip")
    data = z.read_bytes()
    z.write_bytes(data[: int(len(data) * 0.6)])
    with pytest.raises(InputError, match="rec.zip"):
        read_recording(z)


@pytest.mark.parametrize(
    "file,edit,problem,line",
    [
        (
            "MagnetometerUncalibrated.csv",
            lambda s: s.replace("time,seconds_elapsed,z,y,x", "a,b,c"),
            "bad header",
            1,
        ),
        ("Gyroscope.csv", lambda s: s.rsplit("\n", 2)[0] + "\n1,2\n", "truncated", 41),
        (
            "TotalAcceleration.csv",
            lambda s: s.replace("0.020000000", "0.001000000"),
            "time goes backwards",
            4,
        ),
    ],
)
def test_sensorlogger_malformed(tmp_path, file, edit, problem, line):
    d = _copy(tmp_path, "sensorlogger_android")
    (d / file).write_text(edit((d / file).read_text()))
    with pytest.raises(InputError) as ei:
        read_recording(d)
    assert problem in ei.value.problem and ei.value.line == line and file in ei.value.path


def test_sensorlogger_nan_duplicate_counted(tmp_path):
    d = _copy(tmp_path, "sensorlogger_android")
    lines = (d / "Gyroscope.csv").read_text().splitlines()
    lines[3] = lines[3].rsplit(",", 1)[0] + ",NaN"
    lines.insert(5, lines[4])
    (d / "Gyroscope.csv").write_text("\n".join(lines) + "\n")
    rec = read_recording(d)
    assert rec.dropped == {"gyro:nan": 1, "gyro:duplicate_t": 1} and len(rec.gyro) == 39


def test_sensorlogger_no_magnetometer(tmp_path):
    d = _copy(tmp_path, "sensorlogger_android")
    (d / "Magnetometer.csv").unlink()
    (d / "MagnetometerUncalibrated.csv").unlink()
    assert detect(d) == "sensor-logger"  # by its Metadata.csv
    with pytest.raises(InputError, match="no Magnetometer"):
        read_recording(d)


# --- phyphox ---


def test_phyphox_folder_and_zip(tmp_path):
    d = FIX / "phyphox"
    assert detect(d) == "phyphox"
    rec = read_recording(d)
    assert rec.meta["device"] == "Acme Test 5" and rec.dropped == {}
    assert (len(rec.mag), len(rec.accel), len(rec.gyro)) == (20, 40, 40)  # Linear Acceleration not used
    np.testing.assert_allclose(rec.accel.xyz.mean(axis=0), [0.1, 0.2, 9.8], atol=0.02)
    z = _zip(d, tmp_path / "phyphox.zip")
    assert detect(z) == "phyphox"
    np.testing.assert_array_equal(read_recording(z).mag.xyz, rec.mag.xyz)


def test_phyphox_decimal_comma_and_raw_data(tmp_path):
    d = tmp_path / "p"
    d.mkdir()
    rows = [
        '"Time (s)";"Magnetic Field x (µT)";"Magnetic Field y (µT)";"Magnetic Field z (µT)";"Absolute (µT)"'
    ]
    rows += [f"{i * 0.02:.3f};1,5;20,25;-40,0;45,0".replace(".", ",") for i in range(5)]
    (d / "Raw Data.csv").write_text("\n".join(rows) + "\n", encoding="utf-8")
    rec = read_recording(d)
    np.testing.assert_allclose(rec.mag.xyz[0], [1.5, 20.25, -40.0])
    np.testing.assert_allclose(rec.mag.t, [0, 0.02, 0.04, 0.06, 0.08])
    assert rec.accel is None and rec.gyro is None


@pytest.mark.parametrize(
    "edit,problem,line",
    [
        (lambda s: s.rstrip("\n").rsplit(",", 3)[0] + "\n", "truncated", 21),
        (lambda s: s.replace("4.000000000E-03", "9.000000000E-02", 1), "time goes backwards", 3),
    ],
)
def test_phyphox_malformed(tmp_path, edit, problem, line):
    d = _copy(tmp_path, "phyphox")
    f = d / "Magnetometer.csv"
    f.write_text(edit(f.read_text(encoding="utf-8")), encoding="utf-8")
    with pytest.raises(InputError) as ei:
        read_recording(d)
    assert problem in ei.value.problem and ei.value.line == line and "Magnetometer.csv" in ei.value.path


def test_phyphox_gauss_is_wrong_unit(tmp_path):
    d = tmp_path / "p"
    d.mkdir()
    rows = ['"Time (s)","Magnetic field x (µT)","Magnetic field y (µT)","Magnetic field z (µT)"']
    rows += [f"{i * 0.02},50000,0,0" for i in range(5)]
    (d / "Magnetometer.csv").write_text("\n".join(rows) + "\n", encoding="utf-8")
    with pytest.raises(InputError, match="outside the plausible"):
        read_recording(d)


# --- what the phone states about itself ---


def test_sensorlogger_flags_device_id_and_date(tmp_path):
    rec = read_recording(FIX / "sensorlogger_android")
    assert rec.meta["device_id"] == "abc"
    assert rec.meta["mag_os_calibrated"] is False and rec.meta["gyro_os_calibrated"] is True  # Gyroscope.csv
    assert not any(k.startswith("gyro_os_bias") for k in rec.meta)  # not in the export
    # both magnetometer files: the OS's estimate is raw − calibrated (the fixture: a field of (0, 20, −40) µT
    # read raw with an offset of (30, −70, 300) µT)
    np.testing.assert_allclose(rec.meta["mag_os_bias_uT"], [30.0, -70.0, 300.0], atol=1.0)
    assert rec.meta["mag_os_bias_changes"] == []
    early = _copy(tmp_path / "early", "sensorlogger_android")  # the calibrated file starts 3 s sooner
    lines = (early / "Magnetometer.csv").read_text().splitlines()
    before = [f"{1716999997000000000 + 20000000 * i},{-3.0 + 0.02 * i:.9f},0,0,0" for i in range(100)]
    (early / "Magnetometer.csv").write_text("\n".join([lines[0], *before, *lines[1:]]) + "\n")
    rec = read_recording(early)
    np.testing.assert_allclose(rec.meta["mag_os_bias_uT"], [30.0, -70.0, 300.0], atol=1.0)
    d = _copy(tmp_path, "sensorlogger_android")
    (d / "MagnetometerUncalibrated.csv").unlink()
    gyro = (d / "Gyroscope.csv").read_text()
    (d / "GyroscopeUncalibrated.csv").write_text(gyro)
    md = (d / "Metadata.csv").read_text().replace("2024-05-29_16-26-40", "29 May 2024")
    (d / "Metadata.csv").write_text(md)
    rec = read_recording(d)
    assert rec.meta["mag_os_calibrated"] is True and rec.meta["gyro_os_calibrated"] is False
    assert "mag_os_bias_uT" not in rec.meta  # the calibrated field alone states no offset
    assert "date" not in rec.meta and rec.meta["date_unreadable"] == "29 May 2024"


def _phyphox_time(tmp_path, text):
    d = _copy(tmp_path, "phyphox")
    (d / "meta" / "time.csv").write_text(text, encoding="utf-8")
    return read_recording(d)


def test_phyphox_flags_and_start_date(tmp_path):
    rec = read_recording(FIX / "phyphox")  # no meta/time.csv
    assert rec.meta["mag_os_calibrated"] is True and rec.meta["gyro_os_calibrated"] is True
    assert "date" not in rec.meta and "device_id" not in rec.meta
    header = '"event","experiment time","system time","system time text"\n'
    # the START's Unix time gives the UTC date: 1770070000 s is 2026-02-02 22:06:40 UTC (03:36 the next day
    # in India: the text's local date is not the one used)
    rec = _phyphox_time(
        tmp_path / "a",
        header + '"START",0.000000000E0,1770070000.000,"2026-02-03 03:36:40.000 UTC+05:30"\n'
        '"PAUSE",1.000000000E1,1770070010.000,"2026-02-03 03:36:50.000 UTC+05:30"\n',
    )
    assert rec.meta["date"] == "2026-02-02"
    row = '"START";0,000000000E0;1770070000,000;"2026-02-03 03:36:40"\n'  # semicolons and decimal commas
    rec = _phyphox_time(tmp_path / "b", header.replace(",", ";") + row)
    assert rec.meta["date"] == "2026-02-02"
    rec = _phyphox_time(tmp_path / "c", header + '"START",0,n/a,"2026-02-03 03:36:40.000 UTC+05:30"\n')
    assert rec.meta["date"] == "2026-02-03"  # no Unix time: the date its text states
    rec = _phyphox_time(tmp_path / "d", header + '"START",0,,"03.02.2026"\n')
    assert "date" not in rec.meta and rec.meta["date_unreadable"] == "03.02.2026"
