"""replay options: a refused calibration file is used but never silently; --viewer streams to rerun live;
the place and day of a recording that does not state them."""

from __future__ import annotations

from pdr_mag.calibration.model import MagCalibration
from replay.cli import main
from tests.test_cli_replay import rec_dir  # noqa: F401  (module-scoped fixture)
from tests.test_online import B_TRUE, F


def test_refused_calibration_file_warns_on_stderr(rec_dir, tmp_path, capsys):  # noqa: F811
    cal = tmp_path / "cal.json"
    MagCalibration.from_arrays(
        B_TRUE, None, field_uT=F, method="sphere", accepted=False, reasons=["coverage 0.12 < 0.40"]
    ).to_json(cal)
    assert main(["replay", str(rec_dir), "--calibration", str(cal), "-q"]) == 0
    err = capsys.readouterr().err
    assert "not accepted" in err and "coverage 0.12" in err and "cal.json" in err


def test_viewer_flag_streams_to_a_live_rerun_viewer(rec_dir, tmp_path, monkeypatch):  # noqa: F811
    """``--viewer`` builds the rerun sink with ``spawn=True`` (the viewer itself is faked here)."""
    import pdr_mag.sinks.rerun as rr_sink

    made = []

    class FakeSink:
        def __init__(self, path=None, *, spawn=False):
            made.append((path, spawn))

        def __getattr__(self, name):
            return lambda *a, **k: None

    monkeypatch.setattr(rr_sink, "RerunSink", FakeSink)
    assert main(["replay", str(rec_dir), "--viewer", "-q"]) == 0
    assert made == [(None, True)]


# --latitude / --longitude / --altitude / --date: where and when, for a recording that does not say (a
# backend knows its building)
def _copy_without(rec_dir, dest, *keys):  # noqa: F811
    """A copy of the pdr-csv recording ``rec_dir`` whose meta.json lacks ``keys``."""
    import json
    import shutil

    shutil.copytree(rec_dir, dest)
    meta = json.loads((dest / "meta.json").read_text())
    (dest / "meta.json").write_text(json.dumps({k: v for k, v in meta.items() if k not in keys}))
    return dest


def test_place_gives_what_meta_json_would(rec_dir, tmp_path):  # noqa: F811
    """``--latitude --longitude --altitude`` on a copy without a position replays exactly as the recording
    whose meta.json has that position (same process: the same bytes); without them, magnetic north."""
    import json

    from tests.test_pipeline import META

    bare = _copy_without(rec_dir, tmp_path / "bare", "latitude_deg", "longitude_deg", "altitude_m")
    place = ["--latitude", str(META["latitude_deg"]), "--longitude", str(META["longitude_deg"]),
             "--altitude", str(META["altitude_m"])]
    runs = {
        "meta": [str(rec_dir)],
        "option": [str(bare), *place],
        "none": [str(bare)],
    }
    for name, args in runs.items():
        out = ["--out-csv", str(tmp_path / f"{name}.csv"), "--json", str(tmp_path / f"{name}.json")]
        assert main(["replay", *args, *out, "-q"]) == 0
    assert (tmp_path / "option.csv").read_bytes() == (tmp_path / "meta.csv").read_bytes()
    north = {name: json.loads((tmp_path / f"{name}.json").read_text())["north"] for name in runs}
    assert north == {"meta": "true", "option": "true", "none": "magnetic"}


def test_the_summary_says_how_to_give_a_missing_place(rec_dir, tmp_path, capsys):  # noqa: F811
    bare = _copy_without(rec_dir, tmp_path / "bare", "latitude_deg", "longitude_deg", "altitude_m")
    for args, hint in (([str(bare)], True), ([str(rec_dir)], False)):
        capsys.readouterr()
        assert main(["replay", *args]) == 0
        north = [line for line in capsys.readouterr().out.splitlines() if line.startswith("north")]
        assert len(north) == 1 and ("--latitude" in north[0]) == hint, north


def test_place_calibrates_a_phone_held_flat_that_nothing_else_could(tmp_path):
    """A texting walk (the phone held flat, turning only about up) without a position: the online fit has the
    field's strength and dip to find as well as the offset, and the vertical offset stays open; given the
    place, the field model fixes them and the heading is right within seconds."""
    import json

    walk = tmp_path / "walk"
    assert main(["simulate", "--scenario", "walk", "--seed", "3", "--out", str(walk)]) == 0
    meta = json.loads((walk / "meta.json").read_text())
    place = ["--latitude", str(meta["latitude_deg"]), "--longitude", str(meta["longitude_deg"])]
    (walk / "meta.json").write_text(json.dumps({"date": meta["date"]}))
    assert main(["replay", str(walk), *place, "--json", str(tmp_path / "s.json"), "-q"]) == 0
    s = json.loads((tmp_path / "s.json").read_text())
    assert s["north"] == "true"
    err = s["heading_error"]["truth"]
    assert err["median_deg"] < 5.0, err
    assert err["share_over_45"] < 0.2, err  # the seconds before the first calibration


def test_place_without_a_date_and_bad_places_are_input_errors(rec_dir, tmp_path, capsys):  # noqa: F811
    bare = _copy_without(rec_dir, tmp_path / "nodate", "latitude_deg", "longitude_deg", "altitude_m", "date")
    place = ["--latitude", "45.19", "--longitude", "5.73"]
    capsys.readouterr()
    assert main(["replay", str(bare), *place, "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(bare) in err[0] and "--date" in err[0], err
    assert main(["replay", str(bare), *place, "--date", "2016-05-31", "-q"]) == 0
    bad = (["--latitude", "95", "--longitude", "8"], ["--latitude", "47"], ["--longitude", "8"],
           ["--altitude", "300"], ["--latitude", "a", "--longitude", "8"], ["--date", "2016-02-30"])
    for args in bad:
        capsys.readouterr()
        assert main(["replay", str(rec_dir), *args, "-q"]) == 2, args
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("pdr-mag: "), (args, err)


def test_calibrate_takes_the_place_for_its_radius_check(rec_dir, tmp_path):  # noqa: F811
    """``calibrate --latitude --longitude --altitude`` on a copy without a position: the same calibration file
    as the recording whose meta.json states it, with its WMM field; without them, no WMM field."""
    import json

    from tests.test_pipeline import META

    bare = _copy_without(rec_dir, tmp_path / "bare", "latitude_deg", "longitude_deg", "altitude_m")
    place = ["--latitude", str(META["latitude_deg"]), "--longitude", str(META["longitude_deg"]),
             "--altitude", str(META["altitude_m"])]
    assert main(["calibrate", str(rec_dir), "--json", str(tmp_path / "meta.json")]) == 0
    assert main(["calibrate", str(bare), *place, "--json", str(tmp_path / "option.json")]) == 0
    assert main(["calibrate", str(bare), "--json", str(tmp_path / "none.json")]) == 0
    cals = {name: json.loads((tmp_path / f"{name}.json").read_text()) for name in ("meta", "option", "none")}
    for c in cals.values():
        c["extra"].pop("source")
    assert cals["option"] == cals["meta"] and "wmm" in cals["meta"]["extra"]
    assert "wmm" not in cals["none"]["extra"]
