"""Every code block of README.md, run or checked: the commands in a scratch folder laid out as a checkout
(``recordings/`` here, ``../shared`` beside it), the library example against the command line's own rows,
the synopsis against the commands' options, the layout against the files.

Commands not run, and why, are :data:`NOT_RUN`; the ``pdr-mag`` and ``dask`` ones among them are still
parsed by their own command-line parsers (options and values valid, nothing executed).
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import re
import shlex
from dataclasses import dataclass
from importlib.metadata import entry_points
from pathlib import Path

import click
import numpy as np
import pytest

from replay.cli import cli, main
from tests.conftest import ROOT, dataset

README = ROOT / "README.md"

#: Commands of the README's shell blocks that the tests do not run (matched by their start), and why.
NOT_RUN = {
    "python3 -m pip install": "installs the package: the suite runs in the environment it set up (CI's "
                              ".ci/run runs exactly these install commands on a clean checkout)",
    "python3 -m pytest": "this test suite itself",
    "pdr-mag batch replay ../shared/datasets/tyrex-pdrcsv week.manifest":
        "week.manifest stands for the reader's own list, and the folder holds 63 recordings (minutes on "
        "2 cores); tests/test_cli_batch.py runs batch on a local cluster",
    "dask scheduler": "starts a Dask scheduler on a head node (tests/test_cli_batch.py's cluster fixture "
                      "starts one on this machine)",
    "dask worker": "starts workers on other machines, connected to tcp://HEAD:8786",
    "pdr-mag batch replay /shared/logs/week-42": "needs the scheduler at tcp://HEAD:8786 and the shared "
                                                 "folders of a cluster",
}

#: The CSV's printed decimals (replay/run.py CsvSink): t 6, q 9, heading and σ 4; half a unit of the last
#: digit is the rounding a value read back carries.
CSV_ATOL = np.array([5e-7, 5e-10, 5e-10, 5e-10, 5e-10, 5e-5, 5e-5]) * 1.0001


@dataclass(frozen=True)
class Block:
    lang: str
    text: str
    line: int


def _blocks() -> list[Block]:
    out, lang, buf, start = [], None, [], 0
    for i, line in enumerate(README.read_text(encoding="utf-8").splitlines(), start=1):
        if line.startswith("```"):
            if lang is None:
                lang, buf, start = line[3:].strip(), [], i
            else:
                out.append(Block(lang, "\n".join(buf) + "\n", start))
                lang = None
        elif lang is not None:
            buf.append(line)
    assert lang is None, "README.md: a code block is not closed"
    return out


BLOCKS = _blocks()


def _commands(block: Block) -> list[str]:
    """The commands of a shell block: continuations joined, comments dropped, ``&&`` chains split."""
    text = block.text.replace("\\\n", " ")
    cmds = []
    for line in text.splitlines():
        line = line.split("#", 1)[0].strip()
        cmds += [c.strip() for c in line.split("&&") if c.strip()]
    return cmds


def _not_run(cmd: str) -> str | None:
    return next((why for start, why in NOT_RUN.items() if cmd.startswith(start)), None)


def _leaf(argv: list[str]) -> tuple[click.Command, list[str]]:
    """The ``pdr-mag`` (sub)command ``argv`` names, and its own arguments."""
    cmd, args = cli, list(argv)
    while isinstance(cmd, click.Group):
        cmd = cmd.get_command(click.Context(cmd), args.pop(0))  # pdr-mag loads a subcommand when asked
    return cmd, args


def _subcommands(group: click.Group) -> dict[str, click.Command]:
    """The subcommands of a group by name (``pdr-mag``'s own are loaded on demand, not in ``.commands``)."""
    ctx = click.Context(group)
    return {name: group.get_command(ctx, name) for name in group.list_commands(ctx)}


def _parse(argv: list[str]) -> dict:
    """Parse a ``pdr-mag`` command line with its own parser (nothing runs): its parameters."""
    cmd, args = _leaf(argv)
    return cmd.make_context(argv[0], args).params


@pytest.fixture()
def checkout(tmp_path, monkeypatch):
    """A scratch folder laid out as a checkout: ``work/recordings`` → this checkout's, ``shared`` beside
    ``work`` → ``../shared``; the working directory is ``work``."""
    work = tmp_path / "work"
    work.mkdir()
    (work / "recordings").symlink_to(ROOT / "recordings")
    if (ROOT.parent / "shared").exists():
        (tmp_path / "shared").symlink_to(ROOT.parent / "shared")
    monkeypatch.chdir(work)
    return work


def _run(cmd: str) -> None:
    argv = shlex.split(cmd)
    assert argv[0] == "pdr-mag", cmd
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(argv[1:]) == 0, cmd


# ------------------------------------------------------------------------------------------------ tests
def test_every_block_is_run_or_checked():
    """A block of a new kind, or a command that is neither run nor listed in NOT_RUN, fails here."""
    langs = [b.lang for b in BLOCKS]
    assert langs.count("python") == 3 and set(langs) == {"bash", "python", ""}, langs
    shell = [c for b in BLOCKS if b.lang == "bash" for c in _commands(b)]
    assert len(shell) == 10
    for cmd in shell:
        why = _not_run(cmd)
        assert why is not None or cmd.startswith("pdr-mag "), f"README command neither run nor listed: {cmd}"
    plain = [b for b in BLOCKS if b.lang == ""]
    assert [b.text.split()[0] for b in plain] == ["pdr-mag", "replay/"]  # the synopsis and the layout
    for start in NOT_RUN:
        assert any(c.startswith(start) for c in shell), f"NOT_RUN names no README command: {start}"


def test_the_commands_not_run_parse():
    dask = {e.name: e for e in entry_points(group="dask_cli")}
    for b in BLOCKS:
        if b.lang != "bash":
            continue
        for cmd in _commands(b):
            if _not_run(cmd) is None:
                continue
            argv = shlex.split(cmd)
            if argv[0] == "pdr-mag":
                assert _parse(argv[1:]), cmd
            elif argv[0] == "dask":
                command = dask[argv[1]].load()
                command.make_context(f"dask {argv[1]}", argv[2:])


def test_command_1_and_the_library_example_give_the_same_rows(checkout):
    """README command 1 (the replay part) in the scratch checkout, then the library example as written: the
    same rows (to the CSV's decimals; the flags and cal_state exactly), the events of the JSON summary, and
    the recording's own place and date (true north, the summary's declination); then the grouped-settings
    example after it."""
    first = BLOCKS[0]
    assert first.lang == "bash"
    replay_cmd = [c for c in _commands(first) if c.startswith("pdr-mag replay")]
    assert replay_cmd == ["pdr-mag replay recordings/mixed --out-csv out/heading.csv --json out/summary.json"]
    _run(replay_cmd[0])
    example = next(b for b in BLOCKS if b.lang == "python")
    ns: dict = {}
    exec(compile(example.text, f"README.md:{example.line}", "exec"), ns)  # noqa: S102 — the README's own code
    rows = ns["rows"]
    with open("out/heading.csv", newline="") as fh:
        cli_rows = list(csv.reader(fh))[1:]
    assert len(rows) == len(cli_rows) > 4000
    num = np.array([[float(v) for v in r[:7]] for r in cli_rows])
    lib = np.column_stack([rows.t, rows.q_wd, rows.heading_deg, rows.heading_std_deg])
    assert np.all(np.abs(lib - num) <= CSV_ATOL), np.max(np.abs(lib - num), axis=0)
    assert [(int(m), int(i), s) for m, i, s in zip(rows.mag_used, rows.interference, rows.cal_state,
                                                   strict=True)] == [(int(r[7]), int(r[8]), r[9])
                                                                     for r in cli_rows]
    summary = json.loads(Path("out/summary.json").read_text())
    events = [e.to_dict() for e in ns["events"] + ns["pipe"].pop_events()]
    assert [(e["t"], e["kind"]) for e in events] == [(e["t"], e["kind"]) for e in summary["events"]]
    pipe = ns["pipe"]
    assert pipe.north == summary["north"] == "true"
    assert pipe.field.declination_deg == pytest.approx(summary["field"]["declination_deg"], abs=1e-9)
    json.dumps(ns["state"])  # JSON-serialisable, as the comment says
    # the device-store example continues it (its rec): the first run finds no entry and leaves one, the
    # second starts from it
    store_block = [b for b in BLOCKS if b.lang == "python"][1]
    exec(compile(store_block.text, f"README.md:{store_block.line}", "exec"), ns)  # noqa: S102
    assert ns["pipe"].prior is None and ns["store"].path(ns["rec"].meta).is_file()
    exec(compile(store_block.text, f"README.md:{store_block.line}", "exec"), ns)  # noqa: S102
    assert ns["pipe"].prior.source == "store" and len(ns["rows"]) == len(cli_rows)
    # the settings example continues this one (its rec): the pipeline it builds has the settings it writes
    # (the defaults are gate 4.0 and tol_deg 15.0) and the recording's place and date
    grouped = [b for b in BLOCKS if b.lang == "python"][2]
    exec(compile(grouped.text, f"README.md:{grouped.line}", "exec"), ns)  # noqa: S102 — the README's own code
    fusion = ns["pipe"].fusion.settings
    assert (fusion.mag.gate, fusion.interference.dip.tol_deg) == (3.0, 10.0)
    assert ns["pipe"].north == "true"


def test_the_real_recording_example_runs(checkout):
    """The example with a real recording: the day's calibration file, then the walk replayed with it into
    the CSV, rerun and MCAP files."""
    dataset("tyrex-pdrcsv", "Thibaud_Nexus5_Dist_Texting")
    cmds = [c for b in BLOCKS if b.lang == "bash" for c in _commands(b)
            if "calib_mag_Nexus5_d2" in c or "Thibaud_Nexus5_Dist_Texting" in c]
    assert len(cmds) == 2 and cmds[0].startswith("pdr-mag calibrate")
    for cmd in cmds:
        _run(cmd)
    cal = json.loads(Path("out/n5d2.json").read_text())
    assert cal["accepted"] is True
    with open("out/h.csv", newline="") as fh:
        rows = list(csv.reader(fh))
    assert len(rows) > 6000 and rows[1][-1] in ("offset", "ellipsoid")  # the file's, from the first row
    assert Path("out/h.rrd").stat().st_size > 100_000 and Path("out/h.mcap").stat().st_size > 100_000


def test_the_synopsis_is_the_command_line():
    """Every option the synopsis writes exists on its command (with the choices it lists), and every option
    of every command is in the synopsis."""
    synopsis = next(b for b in BLOCKS if b.lang == "" and b.text.startswith("pdr-mag"))
    entries: list[list[str]] = []
    for line in synopsis.text.splitlines():
        if line.startswith("pdr-mag "):
            entries.append([line])
        elif line.strip():
            entries[-1].append(line)
    written: dict[str, set[str]] = {}
    for lines in entries:
        text = " ".join(lines)
        words = text.split()
        if words[1] == "batch":
            subs = re.search(r"\{([\w,]+)\}", text).group(1).split(",")
            names = [f"batch {s}" for s in subs]
            # the options of the command: replay --calibration FILE --mcap --rrd; calibrate --method M; …
            common, _, per = text.partition("options of the command:")
            for name in names:
                own = re.search(rf"{name.split()[1]} ([^;\]]*)", per).group(1)
                written.setdefault(name, set()).update(re.findall(r"--[\w-]+|-\w\b", common + " " + own))
        else:
            written.setdefault(words[1], set()).update(re.findall(r"(?<![\w-])(--[\w-]+|-\w)\b", text))
            for opt, choices in re.findall(r"(--[\w-]+) ((?:[\w-]+\|)+[\w-]+)", text):
                param = _option(words[1], opt)
                assert isinstance(param.type, click.Choice), (words[1], opt)
                assert set(choices.split("|")) == set(param.type.choices), (words[1], opt, choices)
    leaves = {}
    for name, cmd in _subcommands(cli).items():
        subs = _subcommands(cmd).items() if isinstance(cmd, click.Group) else [(None, cmd)]
        for sub, c in subs:
            opts = {o for p in c.params for o in p.opts + p.secondary_opts if o.startswith("-")}
            leaves[f"{name} {sub}" if sub else name] = opts - {"-h", "--help"}
    assert set(written) == set(leaves)
    for name, opts in leaves.items():
        assert written[name] == opts, (name, sorted(written[name] ^ opts))


def _option(command: str, opt: str) -> click.Parameter:
    cmd, _ = _leaf(command.split())
    return next(p for p in cmd.params if opt in p.opts)


def test_the_layout_names_files_that_exist():
    """The layout block: every top-level folder, every name at the head of an indented line, and every
    file name in the descriptions exists (a file moved or renamed fails here until the README follows)."""
    layout = next(b for b in BLOCKS if b.lang == "" and b.text.startswith("replay/"))
    top = None
    checked = 0
    for line in layout.text.splitlines():
        indent = len(line) - len(line.lstrip(" "))
        head, _, desc = line.strip().partition("  ")
        if indent == 0:
            top = ROOT / head.split()[0]
            assert top.is_dir(), line
            checked += 1
        elif indent == 2:
            for name in head.split():
                assert (top / name).exists(), f"{top.name}/{name}"
                checked += 1
        else:
            desc = line
        for name in re.findall(r"\b[\w/]+\.(?:py|json|md)\b", desc):
            assert any(top.rglob(Path(name).name)), f"{top.name}: {name}"
            checked += 1
    assert checked >= 25  # 28 names today: a parser that stops finding them fails
