"""End-to-end: ``pdr-mag diagnose`` on a simulated pdr-csv recording; bad input → exit 2, one line."""

from __future__ import annotations

import json
import sys

import pytest

from pdr_mag.sim import simulate
from replay.cli import main
from replay.formats import pdrcsv
from replay.recording import Recording, Stream


@pytest.fixture(scope="module")
def rec_dir(tmp_path_factory):
    r = simulate("figure8", seed=5, duration_s=25.0, defaults=False,
                 effects={"hard_iron": (22.0, -31.0, 48.0), "noise": 0.4, "time_offset": 0.05})
    out = tmp_path_factory.mktemp("rec") / "fig8"
    rec = Recording(mag=Stream(*r.mag), accel=Stream(*r.accel), gyro=Stream(*r.gyro), meta=r.meta,
                    truth=r.truth, source="test", format=pdrcsv.NAME)
    pdrcsv.write(rec, out)
    return out


def test_diagnose_json_has_the_interface_keys_and_report(rec_dir, tmp_path, capsys):
    """The report needs matplotlib: optional for users (the `report` extra), in the test extra here."""
    out = tmp_path / "d.json"
    rep = tmp_path / "rep"
    assert main(["diagnose", str(rec_dir), "--json", str(out), "--report", str(rep)]) == 0
    d = json.loads(out.read_text())
    for key in ("gap_metric", "baseline", "candidates", "missing_effect", "missing_effects", "final"):
        assert key in d
    assert d["gap_metric"] == "rms of measured minus simulated magnetometer, µT"
    assert d["baseline"]["effects"] == ["hard_iron", "noise"]
    assert {"effect", "gap", "score", "estimate"} <= set(d["candidates"][0])
    assert d["missing_effect"] == "time_offset"
    assert d["missing_effects"][0] == "time_offset"
    assert d["final"]["effects"][:2] == ["hard_iron", "noise"] and "time_offset" in d["final"]["effects"]
    assert d["final"]["gap"] < d["baseline"]["gap"] / 2
    assert abs(d["final"]["estimate"]["time_offset"]["seconds"] - 0.05) < 0.005
    # the added effect beat the recording's own null; the rules that decided are in the JSON
    added = next(c for c in d["candidates"] if c["effect"] == "time_offset")
    assert added["significant"] and added["null"]["passed"]
    assert added["null"]["statistic"] > added["null"]["threshold"] > added["null"]["null_mean"]
    assert d["rules"]["null_replicates"] == added["null"]["replicates"] > 0
    assert "missing effects: time_offset" in capsys.readouterr().out
    report = (rep / "report.md").read_text()
    assert "time_offset" in report
    # every candidate has its verdict in the report's table, as in the JSON
    assert "## What this motion can reveal" in report
    verdicts = d["identifiability"]
    assert all(f"| {e} | {v['status'].replace('_', ' ')} |" in report for e, v in verdicts.items())
    for png in ("residual_vs_time.png", "residual_vs_heading.png", "residual_vs_strength.png",
                "residual_vs_rate.png", "field_strength.png"):
        assert (rep / png).stat().st_size > 1000


def test_diagnose_json_to_stdout_and_use_truth(rec_dir, capsys):
    assert main(["diagnose", str(rec_dir), "--json", "-", "--use-truth"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["orientation"] == "truth"
    assert d["missing_effect"] == "time_offset"


def test_diagnose_report_without_matplotlib_is_exit_2(rec_dir, tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    assert main(["diagnose", str(rec_dir), "--report", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "matplotlib" in err


def test_bad_input_is_exit_2_one_line(tmp_path, capsys):
    assert main(["diagnose", str(tmp_path / "nope")]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1
    d = tmp_path / "magonly"
    d.mkdir()
    (d / "mag.csv").write_text("t,x,y,z\n" + "".join(f"{i * 0.02},1,2,{40 + i % 3}\n" for i in range(100)))
    assert main(["diagnose", str(d)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "gyro" in err
    assert main(["diagnose", str(d), "--use-truth"]) == 2
    assert "truth" in capsys.readouterr().err


def test_the_summary_names_the_effect_added_not_the_top_score():
    """A round whose top-scoring candidate failed the recording's own null and whose second was added: the
    round's line names the one added; the last round, which added nothing, names its best score."""
    from replay.commands.diagnose import summary

    def cand(rnd, effect, score, passed):
        return {"round": rnd, "effect": effect, "score": score, "gap": 1.0, "significant": passed,
                "null": {"passed": passed}}

    d = {"n_samples": 10, "duration_s": 1.0, "orientation": "fusion",
         "baseline": {"effects": ["hard_iron"], "gap": 2.0},
         "final": {"effects": ["hard_iron", "b"], "gap": 1.0},
         "missing_effects": ["b"],
         "rounds": [[cand(1, "a", 9.0, False), cand(1, "b", 5.0, True)], [cand(2, "c", 3.0, False)]]}
    lines = summary(d, "rec").splitlines()
    assert "round 1: b (score 5.0" in lines[2] and lines[2].endswith("— added")
    assert "round 2: best c" in lines[3] and "own null" in lines[3]
