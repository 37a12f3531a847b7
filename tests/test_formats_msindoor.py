"""Indoor Location Competition 2.0 path logs: the real traces and a small synthetic fixture."""

from __future__ import annotations

import json
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
    assert rec.meta["mag_os_bias_changes"] == [] and rec.meta["gyro_os_bias_changes"] == []
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
    assert rec.meta["mag_os_bias_uT"] == [50.0, -90.0, -300.0] and rec.meta["mag_os_bias_changes"] == []
    assert rec.meta["gyro_os_bias_rad_s"] == [0.001, 0.001, 0.001] and rec.meta["gyro_os_calibrated"] is False
    assert "latitude_deg" not in rec.meta  # no floor map beside the fixture


def test_real_trace_whose_os_bias_changes():
    """The one trace of the 40 where the OS replaces its hard-iron estimate, 17.4 s in."""
    f = dataset("ms-indoor-location-2020", "site1", "F1", "path_data_files", "5dd9fd619191710006b570f0.txt")
    rec = read_recording(f)
    assert rec.meta["mag_os_bias_uT"] == [-57.131958, -91.18652, -301.94855]
    # the first sample carrying the new value: unix ms 1574566557422, startTime 1574566540013
    assert rec.meta["mag_os_bias_changes"] == [[17.409, -59.109497, -89.86511, -304.66156]]
    assert rec.mag.t[np.searchsorted(rec.mag.t, 17.409)] == 17.409  # a magnetometer sample's time
    assert rec.meta["gyro_os_bias_rad_s"] == [-0.0015563965, -0.00062561035, -0.0001373291]
    assert rec.meta["gyro_os_bias_changes"] == []
    assert not any(k.endswith("os_bias:nan") for k in rec.dropped)


def test_fixture_bias_changes_and_odd_cells(tmp_path):
    """The bias in force at the first kept sample, each change at the first sample carrying it; a cell
    that is NaN is an odd sample, counted; a line with text in a bias cell is garbled, dropped whole, and
    says nothing; the drift likewise."""
    lines = FIXTURE.read_text().splitlines()
    uncal = [i for i, ln in enumerate(lines) if "\tTYPE_MAGNETIC_FIELD_UNCALIBRATED\t" in ln]
    gyro = [i for i, ln in enumerate(lines) if "\tTYPE_GYROSCOPE_UNCALIBRATED\t" in ln]
    # uncal[1] is the NaN sample (dropped): its bias cells say nothing
    lines[uncal[1]] = lines[uncal[1]].replace("50.0\t-90.0\t-300.0", "49.0\t-90.0\t-300.0")
    lines[uncal[2]] = lines[uncal[2]].replace("50.0\t-90.0\t-300.0", "50.5\t-90.0\t-300.0")  # 0.06 s
    lines[uncal[3]] = lines[uncal[3]].replace("50.0\t-90.0", "NaN\t-90.0")  # 0.08 s: odd
    lines[gyro[3]] = lines[gyro[3]].replace("0.001\t0.001\t0.001", "0.002\t0.001\t0.001")  # 0.08 s
    garbled = "1574562661070\tTYPE_MAGNETIC_FIELD_UNCALIBRATED\t71.5\t-85.0\t-340.0\tbias?\t-80.0\t-300.0\t3"
    lines.insert(uncal[2] + 1, garbled)  # 0.07 s
    f = tmp_path / "trace.txt"
    f.write_text("\n".join(lines) + "\n")
    rec = read_recording(f)
    assert rec.meta["mag_os_bias_uT"] == [50.0, -90.0, -300.0]
    assert rec.meta["mag_os_bias_changes"] == [[0.06, 50.5, -90.0, -300.0]]
    assert rec.meta["gyro_os_bias_changes"] == [[0.08, 0.002, 0.001, 0.001]]
    assert rec.dropped["mag_os_bias:nan"] == 1 and "gyro_os_bias:nan" not in rec.dropped
    assert rec.dropped["mag:non_numeric"] == 1
    np.testing.assert_allclose(rec.mag.xyz[:, 0], [70.0, 71.0, 72.0])  # the samples themselves unchanged


def test_calibrated_streams_only(tmp_path):
    """Without the uncalibrated types the OS-calibrated streams are read: flagged, and no estimate."""
    lines = [ln for ln in FIXTURE.read_text().splitlines() if "_UNCALIBRATED\t" not in ln]
    f = tmp_path / "cal.txt"
    f.write_text("\n".join(lines) + "\n")
    rec = read_recording(f)
    assert rec.meta["mag_os_calibrated"] is True and rec.meta["gyro_os_calibrated"] is True
    assert not any(k.startswith(("mag_os_bias", "gyro_os_bias")) for k in rec.meta)
    np.testing.assert_allclose(rec.mag.xyz[0], [20.0, 5.0, -40.0])


def test_uncalibrated_accelerometer_when_no_calibrated_one(tmp_path):
    """A trace that logged only ``TYPE_ACCELEROMETER_UNCALIBRATED`` is read with it (its bias columns are
    not applied); with both, the calibrated one is read."""
    lines = FIXTURE.read_text().splitlines()
    uncal = [ln.replace("\tTYPE_ACCELEROMETER\t", "\tTYPE_ACCELEROMETER_UNCALIBRATED\t").replace(
        "0.1\t0.2\t", "0.3\t0.4\t").replace("\t3", "\t0.01\t0.02\t0.03\t3") for ln in lines
        if "\tTYPE_ACCELEROMETER\t" in ln]
    only = [ln for ln in lines if "\tTYPE_ACCELEROMETER\t" not in ln] + uncal
    only.sort(key=lambda ln: ln.split("\t")[0] if not ln.startswith("#") else "")
    f = tmp_path / "uncal.txt"
    f.write_text("\n".join(only) + "\n")
    rec = read_recording(f)
    np.testing.assert_allclose(rec.accel.xyz[0], [0.3, 0.4, 9.8])
    both = tmp_path / "both.txt"
    both.write_text("\n".join(lines + uncal) + "\n")
    np.testing.assert_allclose(read_recording(both).accel.xyz[0], [0.1, 0.2, 9.8])


def test_no_start_time_header_the_first_line_dates_the_trace(tmp_path):
    """Without ``#\tstartTime``, the first data line's Unix time (ms) is the start and gives the date (so the
    field model and true north are known where the place is); a time that is no Unix time gives neither."""
    lines = [ln for ln in FIXTURE.read_text().splitlines() if "startTime" not in ln]
    f = tmp_path / "nostart.txt"
    f.write_text("\n".join(lines) + "\n")
    rec = read_recording(f)
    assert rec.meta["start_time_unix"] == 1574562661.0 and rec.meta["date"] == "2019-11-24"
    np.testing.assert_allclose(rec.mag.t, [0.02, 0.06, 0.08])
    f.write_text("\n".join(ln.replace("15745626610", "10") for ln in lines) + "\n")
    rec = read_recording(f)
    assert "date" not in rec.meta and "start_time_unix" not in rec.meta


def test_a_zero_bias_is_no_estimate(tmp_path):
    """A phone whose uncalibrated magnetometer states a zero bias has no hard-iron estimate: the raw stream is
    read, and no ``mag_os_bias_uT`` (so ``replay`` starts without a prior, not from an offset of zero)."""
    f = _write(tmp_path, "50.0\t-90.0\t-300.0", "50.0\t-90.0\t-300.0")
    f.write_text(f.read_text().replace("50.0\t-90.0\t-300.0", "0\t0\t0"))
    rec = read_recording(f)
    assert rec.meta["mag_os_calibrated"] is False and "mag_os_bias_uT" not in rec.meta
    assert "mag_os_bias_changes" not in rec.meta and not any(k.startswith("mag_os_bias") for k in rec.dropped)
    np.testing.assert_allclose(rec.mag.xyz[:, 0], [70.0, 71.0, 72.0])


def _floor(tmp_path, coords) -> Path:
    """The fixture at ``<floor>/path_data_files/`` with a ``geojson_map.json`` of one polygon beside it."""
    floor = tmp_path / "site" / "F1"
    (floor / "path_data_files").mkdir(parents=True)
    geo = {"type": "FeatureCollection",
           "features": [{"type": "Feature", "geometry": {"type": "Polygon", "coordinates": [coords]}}]}
    (floor / "geojson_map.json").write_text(json.dumps(geo))
    f = floor / "path_data_files" / "trace.txt"
    f.write_text(FIXTURE.read_text())
    return f


def test_the_floor_map_gives_the_place_only_in_degrees(tmp_path):
    """A map in longitude and latitude gives the place (its box's centre); one drawn in metres (a box of
    tens of units) gives none, though its numbers lie within ±90 / ±180."""
    f = _floor(tmp_path / "deg", [[120.13, 30.30], [120.1325, 30.30], [120.1325, 30.304], [120.13, 30.304]])
    meta = read_recording(f).meta
    assert meta["latitude_deg"] == pytest.approx(30.302) and meta["longitude_deg"] == pytest.approx(120.13125)
    f = _floor(tmp_path / "m", [[0.0, 0.0], [80.0, 0.0], [80.0, 60.0], [0.0, 60.0]])
    assert "latitude_deg" not in read_recording(f).meta


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
    if problem == "truncated":  # the row cut short ends the file (inside it, it is dropped: below)
        f.write_text("".join(f.read_text().splitlines(keepends=True)[:line]))
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
