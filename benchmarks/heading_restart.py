"""Heading when the filter starts late: every tyrex walk replayed from S seconds in (a backend restarted).

The walks of ``../shared/datasets/tyrex-pdrcsv`` all start with the walker standing still in an undisturbed
spot. A PDR backend restarts its filter wherever its user is: running, swinging the phone, next to steel. Here
each walk is replayed with the first S seconds of every stream dropped (S = 0, 5, 10, 20, 30 s by default), in
mode a (the day's calibration file, as a backend keeps it across restarts) and mode b (no calibration), and
scored by the shared scorer as ``heading.py`` scores (``score_arrays``: mean |heading error| against motion
capture, frames across an estimate gap > 1 s dropped) with its window's start moved: from the scorer's own
start (5 s after the motion capture's ``t0``) for S = 0, so that row is ``heading.py``'s; for S > 0 from 5 s
after the restart (the recording's first sample + S + 5 s) when that is later, to the scorer's end (120 s).
The σ columns are over the same frames (``heading.Truth.frames`` with the same window).

Per start and mode: mean / median over walks of the mean |heading error|, walks above 20° / 45°, the pooled
share of frames within 2σ of ``heading_std_deg``, walks with more than 10 % of their frames beyond 3σ, and
the frames more than 45° wrong while σ ≤ 20° (a user discarding rows with σ > 20° keeps these).

Usage::

    python benchmarks/heading_restart.py [--starts 0 5 20] [--walks PATTERN] [--jobs N] [--write-results]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import load_scorer, write_section  # noqa: E402
from heading import BEYOND_3SIGMA_MAX, DATA, FAIL, KEEP_STD, WRONG, Truth, day_files, discover_walks  # noqa: E402

SECTION = "## Heading after a late start (issue 10)"


def run_walk(job: tuple[str, str, tuple[float, ...]]) -> list[dict]:
    """Both modes at every start on one walk: the scorer's mean, and the per-frame errors and σ."""
    from pdr_mag.estimates import EstimateBatch
    from replay.formats import read_recording
    from replay.recording import Stream
    from replay.run import MemorySink, load_calibration, replay

    walk, cal_json, starts = job
    score = load_scorer()
    d = DATA / walk
    truth = Truth(score, d)
    full = read_recording(d)
    cal = load_calibration(cal_json)
    out = []
    for start in starts:
        rec = read_recording(d) if start > 0 else full
        t_start = full.t0 + start
        for name in ("mag", "accel", "gyro"):
            s = getattr(rec, name)
            keep = s.t >= t_start
            setattr(rec, name, Stream(s.t[keep], s.xyz[keep]))
        lo = score.WINDOW[0] if start == 0 else max(score.WINDOW[0], t_start + 5.0 - truth.t0)
        window = (lo, score.WINDOW[1])
        for mode, c in (("a", cal), ("b", None)):
            sink = MemorySink()
            replay(rec, calibration=c, sinks=[sink], progress=False)
            b = EstimateBatch.concat(sink.batches)
            mean = truth.figures(b.t, b.q_wd, window=window)["heading_err_mean"]
            tf, head = truth.frames(b.t, b.q_wd, window=window)
            sd = np.interp(tf, b.t, b.heading_std_deg)
            out.append(
                {"walk": walk, "start": start, "mode": mode, "mean": mean, "err": np.abs(head), "std": sd}
            )
    return out


def summarise(rows: list[dict]) -> dict:
    means = np.array([r["mean"] for r in rows])
    err = np.concatenate([r["err"] for r in rows])
    sd = np.concatenate([r["std"] for r in rows])
    return {
        "n": len(rows),
        "mean": float(np.mean(means)),
        "median": float(np.median(means)),
        "over": [int(np.sum(means > f)) for f in FAIL],
        "within_2sigma": float(np.mean(err <= 2.0 * sd)),
        "beyond_3sigma_walks": int(sum(np.mean(r["err"] > 3.0 * r["std"]) > BEYOND_3SIGMA_MAX for r in rows)),
        "wrong_kept": int(np.sum((err > WRONG) & (sd <= KEEP_STD))),
    }


def table(results: list[dict], starts) -> list[str]:
    lines = [
        "| start | mode | mean / median | walks > 20° / > 45° | within 2σ | walks > 10 % beyond 3σ |"
        " frames > 45° off at σ ≤ 20° |",
        "| ---: | --- | --- | --- | ---: | ---: | ---: |",
    ]
    for start in starts:
        for mode in ("a", "b"):
            s = summarise([r for r in results if r["start"] == start and r["mode"] == mode])
            lines.append(
                f"| {start:g} s | {mode} | {s['mean']:.1f} / {s['median']:.1f}"
                f" | {s['over'][0]} / {s['over'][1]} | {100 * s['within_2sigma']:.0f} %"
                f" | {s['beyond_3sigma_walks']} | {s['wrong_kept']} |"
            )
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--starts", type=float, nargs="+", default=[0.0, 5.0, 10.0, 20.0, 30.0])
    ap.add_argument("--walks", default=None, help="comma-separated globs on the walk names")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--write-results", action="store_true")
    a = ap.parse_args(argv)
    walks = discover_walks(a.walks)
    if not walks:
        print(f"no walks found in {DATA}", file=sys.stderr)
        return 2
    t_wall = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp, ProcessPoolExecutor(a.jobs) as ex:
        made = day_files(walks, ex, tmp)
        jobs = [(w, made[w][0], tuple(a.starts)) for w in walks]
        results = [r for rows in ex.map(run_walk, jobs) for r in rows]
    wall = time.perf_counter() - t_wall
    lines = table(results, a.starts)
    print("\n".join(lines))
    print(f"wall time {wall:.0f} s on {a.jobs} processes")
    if a.write_results:
        head = (
            f"`python benchmarks/heading_restart.py --write-results` ({len(walks)} walks, {wall:.0f} s wall"
            f" on {a.jobs} processes): each walk replayed from S s in, scored by the shared scorer from"
            " S + 5 s (S = 0: heading.py's figures; see the script)."
        )
        write_section(SECTION, "\n".join([SECTION, "", head, "", *lines]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
