"""Peak memory of ``pdr-mag replay`` on long recordings read from files (issue 5: readers stream).

The synthetic walk of :mod:`sinks` (accelerometer and gyroscope at 200 Hz, magnetometer at 100 Hz; no truth
file — truth is evaluation-only and loaded whole) is written once per length in two layouts: the Android
(tyrex Senslogs) folder (``accelerometer.txt``, ``gyroscope.txt``, ``magnetometer.txt``, space-separated,
drift/bias columns included) and pdr-csv. Then ``pdr-mag replay REC`` runs, each run in its own process,
without sinks, with ``--mcap`` and with ``--rrd``, from the code of one or more checkouts (``--repo``, e.g.
``/work/main`` for before and this checkout for after). Reported per run: the process's peak resident
memory (``VmHWM``), the resident memory after the imports and before the replay, and the difference —
what the replay itself held at its peak. Running 10 and 60 minutes shows whether memory grows with length.

    python benchmarks/replay_memory.py                                  # this checkout, 10 and 60 min
    python benchmarks/replay_memory.py --repo /work/main --repo .       # before and after
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _common import ROOT

SINKS = {"none": [], "mcap": ["--mcap", "{out}/o.mcap"], "rrd": ["--rrd", "{out}/o.rrd"]}


def write_recordings(minutes: float, folder: Path) -> dict[str, Path]:
    """The walk of ``sinks.make_recording`` as an Android (tyrex) folder and a pdr-csv folder."""
    from sinks import make_recording

    from replay.formats import pdrcsv

    rec = make_recording(minutes)
    rec.truth = None
    pdr = folder / f"pdrcsv-{minutes:g}"
    pdrcsv.write(rec, pdr)
    android = folder / f"android-{minutes:g}"
    android.mkdir(parents=True, exist_ok=True)
    (android / "record.properties").write_text(
        "[Device]\nModel = Benchmark\nManufacturer = Synthetic\n[Time]\nStartTime = 1781481600.0\n"
    )
    for name, s, extra in (
        ("accelerometer.txt", rec.accel, 0),
        ("gyroscope.txt", rec.gyro, 3),
        ("magnetometer.txt", rec.mag, 3),
    ):
        data = np.column_stack([s.t, s.xyz, np.zeros((len(s.t), extra))])
        np.savetxt(android / name, data, fmt=["%.6f"] + ["%.6f"] * (3 + extra), delimiter=" ")
    return {"android": android, "pdr-csv": pdr}


def _peak_mb() -> float:
    """Peak resident memory of this process, MB: ``VmHWM`` (Linux; it starts afresh at exec), else
    ``ru_maxrss`` (which on Linux keeps the parent's resident memory at the fork, hence not first)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def run_one(repo: str, rec: str, sink: str, out: str) -> dict:
    """One replay in this process, with ``repo``'s code; peak and start resident memory, MB."""
    import psutil

    sys.path.insert(0, repo)
    import pdr_mag.pipeline  # noqa: F401 — imported before the start figure, as the replay needs it
    from replay.cli import main

    start = psutil.Process().memory_info().rss / 2**20
    args = ["replay", rec, "-q", "--no-progress"] + [a.format(out=out) for a in SINKS[sink]]
    t0 = time.perf_counter()
    code = main(args)
    wall = time.perf_counter() - t0
    peak = _peak_mb()
    import replay

    return {"code": code, "start_MB": start, "peak_MB": peak, "wall_s": wall, "code_from": replay.__file__}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, nargs="*", default=[10.0, 60.0])
    ap.add_argument("--repo", action="append", help="checkout whose code replays (repeatable)")
    ap.add_argument("--sinks", nargs="*", choices=list(SINKS), default=list(SINKS))
    ap.add_argument("--one", nargs=4, metavar=("REPO", "REC", "SINK", "OUT"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.one:
        print(json.dumps(run_one(*args.one)))
        return 0
    repos = [str(Path(r).resolve()) for r in (args.repo or [str(ROOT)])]
    rows = []
    with tempfile.TemporaryDirectory(prefix="pdr_replay_mem_") as tmp:
        for minutes in args.minutes:
            recs = write_recordings(minutes, Path(tmp))
            for layout, rec in recs.items():
                size = sum(f.stat().st_size for f in rec.iterdir()) / 2**20
                for sink in args.sinks:
                    for repo in repos:
                        cmd = [sys.executable, __file__, "--one", repo, str(rec), sink, tmp]
                        res = subprocess.run(cmd, capture_output=True, text=True, check=False)
                        if res.returncode != 0:
                            print(res.stderr, file=sys.stderr)
                            return 1
                        r = json.loads(res.stdout.strip().splitlines()[-1])
                        row = {"minutes": minutes, "layout": layout, "input_MB": size, "sink": sink}
                        rows.append({**row, "repo": repo, **r})
                        print(
                            f"{minutes:>4g} min {layout:<8} {sink:<5} {Path(repo).name:<12} exit {r['code']} "
                            f"peak {r['peak_MB']:6.0f} MB (start {r['start_MB']:4.0f}, "
                            f"+{r['peak_MB'] - r['start_MB']:4.0f}) wall {r['wall_s']:5.1f} s",
                            file=sys.stderr,
                            flush=True,
                        )
    print("| length (input) | layout | sinks | code | peak RSS | RSS before replay | peak − before | wall |")
    print("| --- | --- | --- | --- | ---: | ---: | ---: | ---: |")
    for r in rows:
        print(
            f"| {r['minutes']:g} min ({r['input_MB']:.0f} MB) | {r['layout']} | {r['sink']} | "
            f"{Path(r['repo']).name} | {r['peak_MB']:.0f} MB | {r['start_MB']:.0f} MB | "
            f"{r['peak_MB'] - r['start_MB']:.0f} MB | {r['wall_s']:.1f} s |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
