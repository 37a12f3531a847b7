"""``pdr-mag simulate`` end to end: listing, round trip through the pdr-csv reader, determinism, bad input,
and the demo recordings reproduced from the commands documented in recordings/README.md."""

from __future__ import annotations

import json
import math
import re
import shlex
from pathlib import Path

import numpy as np
import pytest

from pdr_mag.sim import SCENARIOS, simulate
from pdr_mag.sim.sensor_model import EFFECTS
from replay.cli import main
from replay.formats import pdrcsv

ROOT = Path(__file__).resolve().parent.parent
FILES = ("mag.csv", "accel.csv", "gyro.csv", "truth.csv", "truth_position.csv", "meta.json")


def test_list_shows_scenarios_and_effects_with_units(capsys):
    assert main(["simulate", "--list"]) == 0
    out = capsys.readouterr().out
    for name in SCENARIOS:
        assert re.search(rf"^\s+{name}\s", out, re.M)
    for e in EFFECTS.values():
        assert re.search(rf"^\s+{e.name}\s+{re.escape(e.unit)}\s", out, re.M)


def test_list_columns_line_up_and_help_is_plain_text(capsys):
    """Every row of a ``--list`` table has its columns at the same place (durations right-aligned, the
    other cells left-aligned); ``--help`` is text for a terminal, without reStructuredText markup."""
    assert main(["simulate", "--list"]) == 0
    out = capsys.readouterr().out
    # section heading → (a row's pattern, the places that must agree: end of group 1 / start of the others)
    tables = {
        "scenarios:": (r"^  \S+ +(\d+ s)  (\S)", lambda m: (m.end(1), m.start(2))),
        "effects (": (r"^  \S+ +(\S+) +(\S)", lambda m: (m.start(1), m.start(2))),
        "phones (": (r"^  \S+ +(\S)", lambda m: (m.start(1),)),
    }
    rows: dict[str, list[str]] = {h: [] for h in tables}
    head = None
    for line in out.splitlines():
        if not line.startswith(" "):
            head = next((h for h in tables if line.startswith(h)), None)
        elif head is not None:
            rows[head].append(line)
    assert len(rows["scenarios:"]) == len(SCENARIOS) and len(rows["effects ("]) == len(EFFECTS)
    for head, (pattern, places) in tables.items():
        assert rows[head], head
        assert len({places(re.match(pattern, row)) for row in rows[head]}) == 1, rows[head]
    assert main(["simulate", "--help"]) == 0
    text = capsys.readouterr().out
    assert "Write a simulated pdr-csv recording" in text and "`" not in text


def test_round_trip_through_the_reader(tmp_path, capsys):
    out = tmp_path / "rec"
    argv = [
        "simulate",
        "--scenario",
        "walk",
        "--seed",
        "5",
        "--duration",
        "12",
        "--out",
        str(out),
        "--effect",
        "hard_iron=30,-12,80",
        "--effect",
        "time_offset=0.04",
        "--effect",
        "noise=off",
    ]
    assert main(argv) == 0
    rec = pdrcsv.read(out)
    res = simulate(
        "walk",
        seed=5,
        duration_s=12.0,
        effects={"hard_iron": [30, -12, 80], "time_offset": 0.04, "noise": None},
    )
    for stream, (t, v), tol in (
        (rec.mag, res.mag, 5e-5),
        (rec.accel, res.accel, 5e-5),
        (rec.gyro, res.gyro, 5e-9),
    ):
        np.testing.assert_allclose(stream.t, t, atol=5e-7)
        np.testing.assert_allclose(stream.xyz, v, atol=tol)
    np.testing.assert_allclose(rec.truth[1], res.truth[1], atol=5e-9)
    assert sum(rec.dropped.values()) == 0
    sim = rec.meta["simulation"]
    assert sim["effects"]["hard_iron"] == [30.0, -12.0, 80.0]
    assert sim["effects"]["time_offset"] == 0.04
    assert "noise" not in sim["effects"]
    assert {"latitude_deg", "longitude_deg", "date"} <= set(rec.meta)
    pos = np.loadtxt(out / "truth_position.csv", delimiter=",", skiprows=1)
    np.testing.assert_allclose(pos[:, 1:], res.truth_position[1], atol=6e-4)


def test_rates_site_and_plain_field_options(tmp_path, capsys):
    out = tmp_path / "r"
    argv = [
        "simulate",
        "--scenario",
        "still",
        "--duration",
        "10",
        "--imu-rate",
        "200",
        "--mag-rate",
        "25",
        "--field",
        "0,20,-40",
        "--out",
        str(out),
    ]
    assert main(argv) == 0
    rec = pdrcsv.read(out)
    assert rec.accel.rate_hz == pytest.approx(200.0, rel=0.02)
    assert rec.mag.rate_hz == pytest.approx(25.0, rel=0.02)
    assert rec.meta["simulation"]["field_w_uT"] == [0.0, 20.0, -40.0]
    assert "latitude_deg" not in rec.meta  # a site would imply another field
    out2 = tmp_path / "s"
    assert (
        main(
            [
                "simulate",
                "--scenario",
                "still",
                "--duration",
                "5",
                "--latitude",
                "-33.9",
                "--longitude",
                "151.2",
                "--date",
                "2025-03-01",
                "--out",
                str(out2),
            ]
        )
        == 0
    )
    meta = json.loads((out2 / "meta.json").read_text())
    assert (meta["latitude_deg"], meta["longitude_deg"], meta["date"]) == (-33.9, 151.2, "2025-03-01")
    assert meta["simulation"]["inclination_deg"] < 0  # southern hemisphere: field points up


def test_named_phone_option(tmp_path, capsys):
    """``--phone iphone4s``: its rates, its ±2 g range (running clips it; the reader counts the clipped
    samples) and its own hard iron, which ``--effect hard_iron=…`` still overrides."""
    out = tmp_path / "run"
    argv = ["simulate", "--scenario", "run", "--duration", "20", "--phone", "iphone4s", "--out", str(out)]
    assert main(argv) == 0
    assert "phones (--phone NAME" in (main(["simulate", "--list"]), capsys.readouterr().out)[1]
    rec = pdrcsv.read(out)
    sim = rec.meta["simulation"]
    assert sim["phone_name"] == "iphone4s" and sim["phone"]["accel_range"] == pytest.approx(19.6133)
    for stream, rate in ((rec.accel, 90.0), (rec.gyro, 108.0), (rec.mag, 38.0)):
        assert 1.0 / np.median(np.diff(stream.t)) == pytest.approx(rate, rel=0.01)
    assert sim["effects"]["hard_iron"] == [85.0, 205.0, -550.0]
    assert rec.dropped["accel:saturated"] > 0.1 * len(rec.accel)
    out2 = tmp_path / "still"
    argv = ["simulate", "--scenario", "still", "--duration", "5", "--phone", "iphone4s",
            "--effect", "hard_iron=600,0,0", "--out", str(out2)]
    assert main(argv) == 0
    assert pdrcsv.read(out2).meta["simulation"]["effects"]["hard_iron"] == [600.0, 0.0, 0.0]


def test_same_seed_byte_identical_files(tmp_path, capsys):
    for d in ("a", "b", "c"):
        seed = "4" if d != "c" else "5"
        assert (
            main(
                [
                    "simulate",
                    "--scenario",
                    "mixed",
                    "--seed",
                    seed,
                    "--duration",
                    "30",
                    "--out",
                    str(tmp_path / d),
                ]
            )
            == 0
        )
    for f in FILES:
        assert (tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes(), f
    assert (tmp_path / "a" / "mag.csv").read_bytes() != (tmp_path / "c" / "mag.csv").read_bytes()


@pytest.mark.parametrize(
    "args",
    [
        ["--scenario", "moonwalk"],
        ["--scenario", "walk", "--effect", "wobble=1"],
        ["--scenario", "walk", "--effect", "noise=abc"],
        ["--scenario", "walk", "--effect", "soft_iron=1,2"],
        ["--scenario", "walk", "--effect", "soft_iron=1,1,-1"],
        ["--scenario", "walk", "--effect", "hard_iron"],
        ["--scenario", "walk", "--duration", "-3"],
        ["--scenario", "walk", "--seed", "x"],
        ["--scenario", "walk", "--date", "2026-13-01"],
        ["--scenario", "walk", "--field", "1,2"],
        ["--scenario", "walk", "--imu-rate", "0"],
        [],
    ],
)
def test_bad_input_exits_2_with_one_line(tmp_path, capsys, args):
    assert main(["simulate", *args, "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("pdr-mag: ") and err.count("\n") == 1
    assert not (tmp_path / "x").exists()


def _documented_commands() -> list[list[str]]:
    text = (ROOT / "recordings" / "README.md").read_text(encoding="utf-8")
    cmds = [shlex.split(c) for c in re.findall(r"`(pdr-mag simulate [^`]+)`", text) if "--out" in c]
    assert cmds, "recordings/README.md documents no commands"
    return cmds


def _assert_json_close(got, ref, where: str) -> None:
    """Same structure and strings; floats to 1e-9 relative (the last digits of a float differ across CPUs)."""
    if isinstance(ref, dict):
        assert isinstance(got, dict) and got.keys() == ref.keys(), where
        for k in ref:
            _assert_json_close(got[k], ref[k], f"{where}.{k}")
    elif isinstance(ref, list):
        assert isinstance(got, list) and len(got) == len(ref), where
        for i, (g, r) in enumerate(zip(got, ref, strict=True)):
            _assert_json_close(g, r, f"{where}[{i}]")
    elif isinstance(ref, float) and not isinstance(ref, bool):
        assert isinstance(got, int | float) and math.isclose(got, ref, rel_tol=1e-9, abs_tol=1e-12), where
    else:
        assert got == ref, where


def _assert_same_recording_file(got: Path, ref: Path) -> None:
    """A regenerated demo file against the committed one, numerically.

    Same-seed determinism is bitwise on one machine (``test_same_seed_is_byte_identical``); across CPUs the
    libm behind sin/exp may differ in the last bit, which can move a printed value by one unit of its last
    decimal. CSVs: same header and shape, values within one unit of the last printed decimal (1e-6 s for
    time, 1e-4 µT / m/s², 1e-8 rad/s, 1e-9 for quaternions, 1e-3 m for positions: atol 1.01e-3 covers all,
    relative 1e-9 otherwise). meta.json: same keys and strings, floats to 1e-9 relative.
    """
    where = f"{ref.parent.name}/{ref.name}"
    if ref.suffix == ".json":
        _assert_json_close(json.loads(got.read_text()), json.loads(ref.read_text()), where)
        return
    g_lines, r_lines = got.read_text().splitlines(), ref.read_text().splitlines()
    assert g_lines[0] == r_lines[0], f"{where}: header differs"
    assert len(g_lines) == len(r_lines), f"{where}: {len(g_lines)} rows against {len(r_lines)}"
    g = np.loadtxt(got, delimiter=",", skiprows=1, ndmin=2)
    r = np.loadtxt(ref, delimiter=",", skiprows=1, ndmin=2)
    last_digit = np.array([10.0 ** -len(c.split(".")[1]) if "." in c else 1.0 for c in r_lines[1].split(",")])
    bad = np.abs(g - r) > 1.01 * last_digit + 1e-9 * np.abs(r)
    assert not bad.any(), f"{where}: {int(bad.sum())} values differ by more than one unit of the last digit"


def test_demo_recordings_are_reproduced_by_their_documented_commands(tmp_path, capsys):
    cmds = _documented_commands()
    outs = [c[c.index("--out") + 1] for c in cmds]
    assert "recordings/mixed" in outs  # the default recording of `pdr-mag replay`
    for cmd, out in zip(cmds, outs, strict=True):
        argv = cmd[1:]
        argv[argv.index("--out") + 1] = str(tmp_path / out)
        assert main(argv) == 0
        size = 0
        for f in FILES:
            ref, got = ROOT / out / f, tmp_path / out / f
            _assert_same_recording_file(got, ref)
            size += ref.stat().st_size
        assert size < 1.25e6
        meta = json.loads((ROOT / out / "meta.json").read_text())
        assert meta["simulation"]["north"] == "true"
