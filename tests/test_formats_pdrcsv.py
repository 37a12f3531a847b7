"""The contract's own reader: good files, odd rows (dropped and counted), bad files (InputError → exit 2)."""

import json

import numpy as np
import pytest

from replay.cli import main
from replay.errors import InputError
from replay.formats import pdrcsv, read_recording
from replay.recording import Recording, Stream
from tests.conftest import dataset


def _rec(n=50):
    t = np.arange(n) * 0.02
    mag = np.column_stack([20 + np.sin(t), 5 + np.cos(t), -40 + 0 * t])
    acc = np.tile([0.1, 0.2, 9.8], (n, 1))
    gyr = np.tile([0.01, -0.02, 0.03], (n, 1))
    return Recording(mag=Stream(t, mag), accel=Stream(t, acc), gyro=Stream(t, gyr),
                     meta={"device": "sim", "date": "2020-01-01"})


def test_write_read_round_trip(tmp_path):
    rec = _rec()
    pdrcsv.write(rec, tmp_path / "r")
    back = read_recording(tmp_path / "r")
    assert back.format == "pdr-csv" and back.meta == rec.meta
    np.testing.assert_allclose(back.mag.xyz, rec.mag.xyz, atol=1e-6)
    np.testing.assert_allclose(back.gyro.xyz, rec.gyro.xyz, atol=1e-8)
    assert not back.dropped


def test_phone_orientation_round_trips_as_a_reference(tmp_path):
    rec = _rec()
    q = np.tile([0.5, 0.5, -0.5, 0.5], (len(rec.mag.t), 1))
    rec.references["os"] = (rec.mag.t, q)
    pdrcsv.write(rec, tmp_path / "r")
    back = read_recording(tmp_path / "r")
    np.testing.assert_allclose(back.references["os"][1], q, atol=1e-9)
    assert back.truth is None


def test_odd_rows_are_dropped_and_counted(tmp_path):
    pdrcsv.write(_rec(), tmp_path / "r")
    lines = (tmp_path / "r" / "mag.csv").read_text().splitlines()
    lines.insert(5, lines[4])  # duplicate timestamp
    lines[10] = lines[10].split(",")[0] + ",nan,1,2"
    (tmp_path / "r" / "mag.csv").write_text("\n".join(lines) + "\n")
    back = read_recording(tmp_path / "r")
    assert back.dropped["mag:duplicate_t"] == 1 and back.dropped["mag:nan"] == 1
    assert len(back.mag) == 49  # 50 rows, one made NaN; the duplicate is not kept
    assert np.all(np.diff(back.mag.t) > 0)


@pytest.mark.parametrize(
    "mutate, match",
    [
        (lambda ls: ["time,x,y,z"] + ls[1:], "bad header"),
        (lambda ls: ls[:5] + [ls[2]] + ls[6:], "backwards"),
        (lambda ls: ls[:1], "empty stream"),
        (lambda ls: ls[:-1] + ["0.99,1.0"], "truncated"),
        (lambda ls: [ls[0]] + [",".join([r.split(",")[0]] + [str(float(v) * 1000) for v in r.split(",")[1:]])
                               for r in ls[1:]], "wrong unit"),
    ],
)
def test_bad_files_raise_naming_file_and_line(tmp_path, mutate, match):
    pdrcsv.write(_rec(), tmp_path / "r")
    f = tmp_path / "r" / "mag.csv"
    f.write_text("\n".join(mutate(f.read_text().splitlines())) + "\n")
    with pytest.raises(InputError, match=match) as err:
        read_recording(tmp_path / "r")
    assert str(f) in str(err.value)


def test_missing_and_bad_meta(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        read_recording(tmp_path / "nope")
    pdrcsv.write(_rec(), tmp_path / "r")
    (tmp_path / "r" / "meta.json").write_text("{oops")
    with pytest.raises(InputError, match="meta.json"):
        read_recording(tmp_path / "r")
    (tmp_path / "r" / "meta.json").write_text(json.dumps([1, 2]))
    with pytest.raises(InputError, match="JSON object"):
        read_recording(tmp_path / "r")


def test_cli_bad_input_is_exit_2_one_line(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    code = main(["calibrate", str(tmp_path / "empty")])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert len(err.splitlines()) == 1 and "Traceback" not in err


def test_real_tyrex_recording_reads_in_contract_units():
    rec = read_recording(dataset("tyrex-pdrcsv", "Thibaud_Nexus5_NoDist_Texting"))
    g = np.median(np.linalg.norm(rec.accel.xyz, axis=1))
    assert 9.0 < g < 10.6
    assert 150 < rec.accel.rate_hz < 250 and 40 < rec.mag.rate_hz < 60
    assert rec.truth is not None and rec.truth[1].shape[1] == 4
