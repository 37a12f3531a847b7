"""The magnetometer's latency against the IMU: what ``replay --mag-time-offset auto`` finds and wins.

Every tyrex walk (``../shared/datasets/tyrex-pdrcsv``): the latency :func:`replay.run.estimate_latency`
finds over the walk's first 60 s (determined or not, applied or not: :func:`pdr_mag.calibration.latency.
applies`), and the shared scorer's mean |heading error| of ``replay`` in mode a (the day's calibration) and
mode b (none) as it runs by default and with the latency applied; per phone. Then the simulated swinging
hand of ``tests/test_latency.py`` with its magnetometer 0, 40, 80 and 120 ms late: the estimate and the
mean and p90 |heading error| against the truth after the first calibration, without and with ``auto``.
The BROAD trials (``../shared/datasets/broad``, a lab IMU with optical truth): the latency and the median
and p90 error without and with it. And the mall traces of ``../shared/datasets/ms-indoor-location-2020``: the
latencies found (their walked direction is ``walked.py``'s: none is applied, see the table).

Usage::

    python benchmarks/latency.py [--walks PATTERN] [--jobs N] [--write-results] [--commit HASH]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from collections import defaultdict
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import load_scorer, write_section  # noqa: E402
from heading import DATA, Truth, day_files, discover_walks  # noqa: E402

SECTION = "## The magnetometer's latency (`replay --mag-time-offset auto`)"
MALL = DATA.parent / "ms-indoor-location-2020"
BROAD = DATA.parent / "broad" / "data_mat"
SIM_LAGS_S = (0.0, 0.04, 0.08, 0.12)
#: The simulated walk is scored from here on (its first calibration comes within the first 20 s), s.
SIM_FROM_S = 20.0


def run_walk(job: tuple[str, str]) -> dict:
    """One tyrex walk: the latency found, and the scorer's mean in both modes without and with it."""
    from pdr_mag.calibration.latency import applies
    from pdr_mag.estimates import EstimateBatch
    from pdr_mag.pipeline import PipelineSettings
    from replay.formats import read_recording
    from replay.run import MemorySink, estimate_latency, load_calibration, replay

    walk, cal_json = job
    d = DATA / walk
    truth = Truth(load_scorer(), d)
    lat = estimate_latency(d)
    out = {"walk": walk, "latency": lat, "applied": applies(lat)}
    for mode in "ab":
        for tag in ("default", "auto"):
            if tag == "auto" and not out["applied"]:
                out[(mode, tag)] = out[(mode, "default")]
                continue
            settings = PipelineSettings(mag_time_offset_s=lat.seconds if tag == "auto" else 0.0)
            sink = MemorySink()
            cal = load_calibration(cal_json) if mode == "a" else None
            replay(read_recording(d), calibration=cal, sinks=[sink], progress=False, settings=settings)
            b = EstimateBatch.concat(sink.batches)
            out[(mode, tag)] = truth.figures(b.t, b.q_wd)["heading_err_mean"]
    return out


def run_sim(lag: float) -> dict:
    """The simulated swinging hand, its magnetometer ``lag`` s late: the estimate; the mean and p90 error."""
    from scipy.spatial.transform import Rotation

    from pdr_mag.calibration.latency import applies
    from pdr_mag.estimates import EstimateBatch
    from pdr_mag.pipeline import PipelineSettings
    from pdr_mag.sim import simulate
    from replay.recording import Recording, Stream
    from replay.run import MemorySink, estimate_latency, replay

    res = simulate("swing", seed=7, duration_s=120.0, effects={"time_offset": lag or None})
    rec = Recording(**{k: Stream(*getattr(res, k)) for k in ("mag", "accel", "gyro")}, meta=dict(res.meta))
    lat = estimate_latency(rec)
    t_ref, q_ref = res.truth
    keep = t_ref >= SIM_FROM_S
    t_ref, q_ref = t_ref[keep], q_ref[keep]
    err = {}
    for tag, off in (("default", 0.0), ("auto", lat.seconds if applies(lat) else 0.0)):
        sink = MemorySink()
        replay(rec, sinks=[sink], progress=False, settings=PipelineSettings(mag_time_offset_s=off))
        b = EstimateBatch.concat(sink.batches)
        q = np.array([np.interp(t_ref, b.t, b.q_wd[:, i]) for i in range(4)]).T
        rot = Rotation.from_quat(q[:, [1, 2, 3, 0]]) * Rotation.from_quat(q_ref[:, [1, 2, 3, 0]]).inv()
        d = rot.as_quat()
        e = np.degrees(np.abs(np.angle(np.exp(2j * np.arctan2(d[:, 2], d[:, 3])))))  # the twist about Up
        err[tag] = f"{np.mean(e):.2f} / {np.percentile(e, 90):.2f}"
    return {"lag": lag, "latency": lat, "applied": applies(lat), **err}


def run_broad(path: str) -> dict:
    """A BROAD trial (a lab IMU, optical truth): the latency found; median / p90 error without and with it."""
    from pdr_mag.calibration.latency import applies
    from pdr_mag.pipeline import PipelineSettings
    from replay.run import estimate_latency, replay

    lat = estimate_latency(path)
    out = {"trial": Path(path).stem, "latency": lat, "applied": applies(lat)}
    for tag, off in (("default", 0.0), ("auto", lat.seconds if applies(lat) else 0.0)):
        summary = replay(path, progress=False, settings=PipelineSettings(mag_time_offset_s=off))
        e = summary["heading_error"]["truth"]
        out[tag] = f"{e['median_deg']:.2f} / {e['p90_deg']:.2f}"
    return out


def run_trace(path: str) -> tuple[str, object]:
    from replay.run import estimate_latency

    return Path(path).stem, estimate_latency(path)


def _found_table(title: str, first: str, rows: list[tuple[str, dict]]) -> list[str]:
    """A results table: per row, the latency found (σ), whether applied, the errors without and with it."""
    lines = ["", title, "", f"| {first} | found, ms (σ) | applied | default | auto |",
             "| --- | --- | --- | --- | --- |"]
    for name, r in rows:
        lat = r["latency"]
        applied = "yes" if r["applied"] else "no"
        lines.append(f"| {name} | {_ms(lat.seconds)} ({_ms(lat.std_s)}) | {applied} | {r['default']} | "
                     f"{r['auto']} |")
    return lines


def _ms(x) -> str:
    return "—" if x is None or not np.isfinite(x) else f"{1000 * x:.1f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--walks", help="walk name pattern(s), comma-separated")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--write-results", action="store_true")
    ap.add_argument("--commit", default="", help="the commit measured, for the section's preamble")
    a = ap.parse_args()
    walks = discover_walks(a.walks)
    if not walks:
        sys.exit(f"no tyrex walks found in {DATA}")
    traces = sorted(str(p) for p in MALL.glob("*/*/path_data_files/*.txt")) if MALL.is_dir() else []
    with tempfile.TemporaryDirectory() as tmp, ProcessPoolExecutor(a.jobs) as ex:
        made = day_files(walks, ex, tmp)
        rows = list(ex.map(run_walk, [(w, made[w][0]) for w in walks]))
        sims = list(ex.map(run_sim, SIM_LAGS_S))
        mall = list(ex.map(run_trace, traces))
        broad = list(ex.map(run_broad, sorted(str(p) for p in BROAD.glob("*.mat")))) if BROAD.is_dir() else []

    stamp = f", commit {a.commit}" if a.commit else ""
    lines = [SECTION, "", f"`python benchmarks/latency.py --jobs {a.jobs} --write-results` ({len(walks)} "
             f"tyrex walks, {len(traces)} mall traces{stamp}). Latency over the first 60 s "
             "(`replay.run.estimate_latency`); applied when determined (σ < 5 ms, a gain beyond noise) and "
             "positive. Mean |heading error| per walk (shared scorer), the mean over a phone's walks, as "
             "`replay` runs by default and with `--mag-time-offset auto`.", "",
             "| phone | walks | determined (applied) | latency found, ms: median (range) "
             "| mode a default → auto | mode b default → auto |", "| --- | --- | --- | --- | --- | --- |"]
    by = defaultdict(list)
    for r in rows:
        by[r["walk"].split("_")[1]].append(r)
    for phone, rs in [*sorted(by.items()), ("all", rows)]:
        found = [r["latency"].seconds for r in rs if r["latency"].determined]
        rng = f"{_ms(np.median(found))} ({_ms(min(found))} … {_ms(max(found))})" if found else "—"
        m = {k: np.mean([r[k] for r in rs]) for k in (("a", "default"), ("a", "auto"), ("b", "default"),
                                                      ("b", "auto"))}
        lines.append(f"| {phone} | {len(rs)} | {len(found)} ({sum(r['applied'] for r in rs)}) | {rng} | "
                     f"{m['a', 'default']:.3f} → {m['a', 'auto']:.3f} | {m['b', 'default']:.3f} → "
                     f"{m['b', 'auto']:.3f} |")
    sim_title = ("Simulated swinging hand (seed 7, 120 s), its magnetometer late by the simulator's "
                 f"`time_offset`; mean / p90 |heading error| against the truth from {SIM_FROM_S:.0f} s on, "
                 "degrees:")
    lines += _found_table(sim_title, "late by, ms", [(f"{1000 * s['lag']:.0f}", s) for s in sims])
    if broad:
        lines += _found_table("BROAD (a lab IMU, optical truth; `replay` of the trial file, no calibration "
                              "given): median / p90 |heading error|, degrees:", "trial",
                              [(r["trial"], r) for r in broad])
    if mall:
        found = [lat.seconds for _, lat in mall if lat.determined]
        span = f"{_ms(min(found))} … {_ms(max(found))} ms (median {_ms(np.median(found))}), " if found else ""
        applied = sum(lat.determined and lat.seconds > 0 for _, lat in mall)
        lines += ["", f"Mall traces: determined on {len(found)} of {len(mall)}, {span}applied on {applied}."]
    text = "\n".join(lines) + "\n"
    print(text)
    if a.write_results:
        write_section(SECTION, text)


if __name__ == "__main__":
    main()
