"""``pdr-mag batch replay`` on a local Dask cluster against a serial loop of ``pdr-mag replay`` (issue 12).

The recordings: the 42 walks and the calibration recordings of ``../shared/datasets/tyrex-pdrcsv`` (real
phones, 100–200 Hz), simulated recordings (``pdr-mag simulate``: walk, swing, pocket, mixed, figure8 in
turn, ``--sim-duration`` s each) to reach ``--n-total``, and ``--hours`` synthetic one-hour walks (the
200/100 Hz walk of ``benchmarks/sinks.py`` as pdr-csv, 73 MB each). Simulated and hour recordings are made
once into ``--cache``.

In one run:

* **one process** — the single command's code (:func:`replay.commands.replay.run`) in a loop in this
  process: the serial work without a process start per recording;
* **batch** — ``pdr-mag batch replay TYREX SIM HOUR --out DIR --workers W --force`` as one process, with one
  worker (the engine's cost against the loop in one process) and with W (the parallel speed-up); its wall
  time, the fleet table's per-recording times (``elapsed_s``, measured in the workers) and the peak
  resident memory of each worker process (sampled every 0.2 s);
* **serial** — ``pdr-mag replay REC --out-csv … --json …`` for each recording, one process after the other,
  as a shell loop does; its wall time;
* **the machine** — its idle CPU, and how much more a pure-Python loop gets done in ``W`` processes than in
  one (the parallel capacity left by the other jobs of a shared machine);
* **Dask overhead** — a local cluster of W workers started and stopped empty, and 2000 no-op tasks through
  it (the per-task cost of the engine);
* the outputs of the four runs compared (``heading.csv`` byte for byte).

The speed-up is serial wall / batch wall (target ≥ 0.8 × W), against both serial loops (the shell loop
also pays a process start, the imports and the kernels' loading per recording). The per-task overhead of
the batch is ``(W · batch wall − Σ elapsed_s) / n``: what a recording costs beyond its own work (cluster
start, imports in each worker, scheduling, idle workers at the end). A paper projection for 100 000
one-hour recordings on N workers uses the measured cost per hour of recording and the bytes read and
written per hour.

    python benchmarks/batch.py                       # 300 recordings, 2 one-hour walks, W = core count
    python benchmarks/batch.py --write               # ... and update benchmarks/RESULTS.md
    python benchmarks/batch.py --n-total 100 --hours 0   # a quick look
"""

from __future__ import annotations

import argparse
import csv
import datetime
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from _common import ROOT, TYREX, write_section

BIN = Path(sys.executable).parent
SCENARIOS = ("walk", "swing", "pocket", "mixed", "figure8")
SECTION = "## Batch (issue 12)"


# -------------------------------------------------------------------------------------------- recordings
def simulated(n: int, duration: float, cache: Path) -> Path:
    """``n`` simulated recordings in ``cache/sim-<duration>s/`` (made once)."""
    from replay.cli import main

    folder = cache / f"sim-{duration:g}s"
    for i in range(n):
        out = folder / f"{SCENARIOS[i % len(SCENARIOS)]}-{i:04d}"
        if not (out / "meta.json").exists():
            rc = main(["simulate", "--scenario", SCENARIOS[i % len(SCENARIOS)], "--seed", str(i),
                       "--duration", f"{duration:g}", "--out", str(out)])
            assert rc == 0
    return folder


def hour_walks(n: int, cache: Path) -> Path:
    """``n`` one-hour walks (pdr-csv) in ``cache/hour/`` (made once; the same walk, n copies)."""
    folder = cache / "hour"
    first = folder / "hour-00"
    if n and not (first / "mag.csv").exists():
        from sinks import make_recording

        from replay.formats import pdrcsv

        rec = make_recording(60.0)
        rec.truth = None
        pdrcsv.write(rec, first)
    for i in range(1, n):
        if not (folder / f"hour-{i:02d}" / "mag.csv").exists():
            shutil.copytree(first, folder / f"hour-{i:02d}", dirs_exist_ok=True)
    return folder


def listing(inputs: list[Path]) -> list[tuple[Path, str]]:
    """``(recording, output key)`` as ``pdr-mag batch`` finds them."""
    from replay.batch import find_recordings

    return [(Path(it.path), it.key) for it in find_recordings([str(p) for p in inputs])]


def _size(path: Path) -> int:
    if not path.is_dir():
        return path.stat().st_size
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


# ------------------------------------------------------------------------------------------------- runs
class RssSampler(threading.Thread):
    """Peak resident memory of each descendant process of ``pid`` (sampled every 0.2 s), MB."""

    def __init__(self, pid: int):
        super().__init__(daemon=True)
        self.pid, self.peak, self.stop = pid, {}, threading.Event()

    def run(self):
        import psutil

        try:
            root = psutil.Process(self.pid)
        except psutil.NoSuchProcess:
            return
        while not self.stop.is_set():
            try:
                for p in root.children(recursive=True):
                    try:
                        if "spawn_main" not in " ".join(p.cmdline()):  # worker processes only
                            continue
                        self.peak[p.pid] = max(self.peak.get(p.pid, 0.0), p.memory_info().rss / 2**20)
                    except psutil.Error:
                        continue
            except psutil.Error:
                return
            time.sleep(0.2)


def idle_share(seconds: float = 5.0) -> float:
    """Share of the machine's CPU time left idle over ``seconds`` (/proc/stat): the spare capacity the
    batch can use on a shared machine."""
    def snap():
        with open("/proc/stat") as fh:
            v = [int(x) for x in fh.readline().split()[1:]]
        return sum(v), v[3] + v[4]

    t1, i1 = snap()
    time.sleep(seconds)
    t2, i2 = snap()
    return (i2 - i1) / max(t2 - t1, 1)


def run_batch(inputs: list[Path], out: Path, workers: int) -> dict:
    cmd = [str(BIN / "pdr-mag"), "batch", "replay", *map(str, inputs), "--out", str(out), "--workers",
           str(workers), "--force", "--no-progress", "--top", "0"]
    load0 = os.getloadavg()
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    sampler = RssSampler(proc.pid)
    sampler.start()
    stdout, stderr = proc.communicate()
    wall = time.perf_counter() - t0
    sampler.stop.set()
    with (out / "summary.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    return {"wall": wall, "rc": proc.returncode, "stdout": stdout, "stderr": stderr, "rows": rows,
            "worker_peak_mb": sorted(sampler.peak.values()), "load": (load0, os.getloadavg())}


def run_serial(recs: list[tuple[Path, str]], out: Path) -> dict:
    load0 = os.getloadavg()
    t0 = time.perf_counter()
    for rec, key in recs:
        o = out / key
        subprocess.run([str(BIN / "pdr-mag"), "replay", str(rec), "--out-csv", str(o / "heading.csv"),
                        "--json", str(o / "replay.json"), "-q"], check=True, capture_output=True)
    return {"wall": time.perf_counter() - t0, "load": (load0, os.getloadavg())}


def run_inprocess(recs: list[tuple[Path, str]], out: Path) -> dict:
    """The single command's code (:func:`replay.commands.replay.run`) in a loop in this process: the
    work of the serial loop without a process start per recording (the first recording is replayed once
    untimed, so imports and compiled kernels are loaded before the clock starts)."""
    from replay.commands.replay import run

    warm = out / "_warm"
    run(recs[0][0], None, out_csv=warm / "h.csv", json_path=warm / "s.json", progress=False)
    load0 = os.getloadavg()
    t0 = time.perf_counter()
    for rec, key in recs:
        o = out / key
        run(rec, None, out_csv=o / "heading.csv", json_path=o / "replay.json", progress=False)
    return {"wall": time.perf_counter() - t0, "load": (load0, os.getloadavg())}


def _burn(n: int) -> float:
    """A pure-Python loop: the seconds it took."""
    t = time.perf_counter()
    s = 0
    for i in range(n):
        s += i * i
    return time.perf_counter() - t


def machine_scaling(workers: int, n: int = 5_000_000, rounds: int = 4) -> float:
    """How many times more pure-Python work ``workers`` processes do than one in the same time, now: the
    parallel capacity the machine offers (≈ ``workers`` when the cores are free).  ``rounds × workers``
    equal tasks, so every process has the same share."""
    import multiprocessing

    ctx = multiprocessing.get_context("spawn")
    tasks = rounds * workers
    out = []
    for w in (1, workers):
        with ctx.Pool(w) as pool:
            pool.map(_burn, [1000] * w)  # started
            t = time.perf_counter()
            pool.map(_burn, [n] * tasks)
            out.append(time.perf_counter() - t)
    return out[0] / out[1]


def _noop(i):
    return i


def dask_overhead(workers: int, n_tasks: int = 2000) -> dict:
    """Start + stop of an empty local cluster, and the per-task cost of no-op tasks through it."""
    from replay.batch import dask_client

    t0 = time.perf_counter()
    with dask_client(workers) as client:
        t_up = time.perf_counter() - t0
        client.gather(client.map(_noop, range(50), pure=False))  # warm
        t1 = time.perf_counter()
        client.gather(client.map(_noop, range(n_tasks), pure=False))
        per_task = (time.perf_counter() - t1) / n_tasks
        t2 = time.perf_counter()
    return {"start_s": t_up, "stop_s": time.perf_counter() - t2, "per_task_ms": per_task * 1e3}


# ------------------------------------------------------------------------------------------------ report
def projection(cost_s_per_hour: float, in_mb_per_hour: float, out_mb_per_hour: float,
               overhead_s: float, n_rec: int = 100_000) -> list[tuple]:
    """Wall time of ``n_rec`` one-hour recordings on N workers: compute (cost + per-task overhead) / N,
    and the storage throughput it needs."""
    rows = []
    for n in (2, 16, 64, 256, 1024):
        wall_s = n_rec * (cost_s_per_hour + overhead_s) / n
        mb_s = n * (in_mb_per_hour + out_mb_per_hour) / (cost_s_per_hour + overhead_s)
        rows.append((n, wall_s / 3600.0, mb_s))
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n-total", type=int, default=300, help="recordings in all (tyrex + simulated + hours)")
    ap.add_argument("--sim-duration", type=float, default=60.0, help="length of a simulated recording, s")
    ap.add_argument("--hours", type=int, default=2, help="one-hour synthetic walks among them")
    ap.add_argument("--workers", type=int, default=None, help="local cluster size (default: core count)")
    ap.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "pdr-mag-bench-batch")
    ap.add_argument("--write", action="store_true", help="update benchmarks/RESULTS.md")
    ap.add_argument("--commit", default="", help="commit to name in the section")
    a = ap.parse_args()
    from replay.batch import default_workers

    workers = a.workers or default_workers()
    tyrex = sorted(p for p in TYREX.iterdir() if p.is_dir())
    n_walks = sum(not p.name.startswith("calib") for p in tyrex)
    n_sim = max(0, a.n_total - len(tyrex) - a.hours)
    inputs = [TYREX, simulated(n_sim, a.sim_duration, a.cache)]
    if a.hours:
        inputs.append(hour_walks(a.hours, a.cache))
    recs = listing(inputs)
    print(f"{len(recs)} recordings: {n_walks} tyrex walks, {len(tyrex) - n_walks} tyrex calibration, "
          f"{n_sim} simulated × {a.sim_duration:g} s, {a.hours} × 1 h; {workers} workers", flush=True)
    work = Path(tempfile.mkdtemp(prefix="pdr-mag-batch-"))
    idle = idle_share()
    print(f"idle CPU before the runs: {idle:.1%} of {os.cpu_count()} cores", flush=True)
    try:
        scale = machine_scaling(workers)
        print(f"machine: {workers} processes of a pure-Python loop do {scale:.2f}× the work of one",
              flush=True)
        ovh = dask_overhead(workers)
        print(f"dask: local cluster up {ovh['start_s']:.2f} s, down {ovh['stop_s']:.2f} s, "
              f"{ovh['per_task_ms']:.2f} ms a no-op task", flush=True)
        # the two shorter runs back to back (the load of a shared machine drifts), the long loop last
        m = run_inprocess(recs, work / "inprocess")
        print(f"in one process: {m['wall']:.1f} s (load {m['load'][0][0]:.1f} → {m['load'][1][0]:.1f})",
              flush=True)
        b1 = run_batch(inputs, work / "batch1", 1)
        assert b1["rc"] == 0, b1["stderr"][-2000:]
        print(f"batch, 1 worker: {b1['wall']:.1f} s (load {b1['load'][0][0]:.1f} → {b1['load'][1][0]:.1f})",
              flush=True)
        b = run_batch(inputs, work / "batch", workers)
        assert b["rc"] == 0, b["stderr"][-2000:]
        print(f"batch: {b['wall']:.1f} s (load {b['load'][0][0]:.1f} → {b['load'][1][0]:.1f})", flush=True)
        s = run_serial(recs, work / "serial")
        print(f"serial: {s['wall']:.1f} s (load {s['load'][0][0]:.1f} → {s['load'][1][0]:.1f})", flush=True)
        same = sum((work / "serial" / k / "heading.csv").read_bytes()
                   == (work / "batch" / k / "heading.csv").read_bytes()
                   == (work / "inprocess" / k / "heading.csv").read_bytes()
                   == (work / "batch1" / k / "heading.csv").read_bytes() for _, k in recs)
        rows = b["rows"]
        elapsed = sum(float(r["elapsed_s"]) for r in rows)
        # the cost of an hour from the 1-worker batch: a worker with a core of its own, as on a cluster node
        hour_rows = [r for r in b1["rows"] if "/hour/" in r["recording"]]
        tyrex_rows = [r for r in b1["rows"] if str(TYREX) in r["recording"]]
        per_hour = hour_rows or tyrex_rows
        cost_h = 3600 * sum(float(r["elapsed_s"]) for r in per_hour) / sum(
            float(r["duration_s"]) for r in per_hour)
        dur = sum(float(r["duration_s"]) for r in rows)
        if hour_rows:
            keys = [k for p, k in recs if "/hour/" in str(p)]
            in_h = sum(_size(p) for p, k in recs if "/hour/" in str(p)) / len(keys) / 2**20
            out_h = sum(_size(work / "batch" / k) for k in keys) / len(keys) / 2**20
        else:
            in_b = sum(_size(Path(p)) for p, _ in recs)
            out_b = sum(_size(work / "batch" / k) for _, k in recs)
            in_h, out_h = in_b / dur * 3600 / 2**20, out_b / dur * 3600 / 2**20
    finally:
        shutil.rmtree(work, ignore_errors=True)
    n = len(rows)
    speedup, speedup_m = s["wall"] / b["wall"], m["wall"] / b["wall"]
    overhead = (workers * b["wall"] - elapsed) / n
    proj = projection(cost_h, in_h, out_h, overhead)
    loads = [run["load"][k][0] for run in (m, b1, b, s) for k in (0, 1)]  # 1-min load before / after each
    load = (f"idle CPU {idle:.0%} before the runs, {workers} processes of a pure-Python loop did "
            f"{scale:.2f}× the work of one; load {min(loads):.1f}–{max(loads):.1f}")
    lines = [
        SECTION,
        "",
        f"`python benchmarks/batch.py{'' if a.n_total == 300 else f' --n-total {a.n_total}'}"
        f"{'' if a.hours == 2 else f' --hours {a.hours}'}` — {n} recordings ({n_walks} tyrex walks, "
        f"{len(tyrex) - n_walks} tyrex calibrations, {n_sim} simulated × {a.sim_duration:g} s, {a.hours} "
        f"synthetic hours; {dur / 3600:.1f} h of data), `pdr-mag batch replay` on a local cluster of "
        f"{workers} workers, in one run ({load}), {datetime.date.today()}"
        + (f", {a.commit}" if a.commit else "") + ".",
        "",
        f"| | wall | speed-up of `--workers {workers}` (target ≥ {0.8 * workers:.1f} against the first) |",
        "| --- | ---: | ---: |",
        f"| serial loop of `pdr-mag replay` (a shell loop) | {s['wall']:.1f} s | **{speedup:.2f}** |",
        f"| the same code looped in one process | {m['wall']:.1f} s | {speedup_m:.2f} |",
        f"| `pdr-mag batch replay --workers 1` | {b1['wall']:.1f} s | {b1['wall'] / b['wall']:.2f} |",
        f"| `pdr-mag batch replay --workers {workers}` | {b['wall']:.1f} s | |",
        "",
        f"Per-task overhead (W · wall − Σ elapsed) / n **{overhead * 1e3:.0f} ms** (local cluster up "
        f"{ovh['start_s']:.1f} s, down {ovh['stop_s']:.1f} s, a no-op task {ovh['per_task_ms']:.2f} ms); "
        f"`heading.csv` byte-identical between the four runs for {same} of {n} recordings; worker peak "
        f"memory {', '.join(f'{mb:.0f}' for mb in b['worker_peak_mb'])} MB. Projection for 100 000 one-hour "
        f"recordings ({cost_h:.1f} s of worker time per hour of data, {overhead * 1e3:.0f} ms a recording, "
        f"{in_h:.0f} MB read and {out_h:.0f} MB written per hour): "
        + " / ".join(str(nw) for nw, _, _ in proj[:4]) + " workers take "
        + " / ".join(f"{h:.1f}" for _, h, _ in proj[:4]) + " h and need "
        + " / ".join(f"{mb:.0f}" for _, _, mb in proj[:4]) + " MB/s of storage throughput.",
    ]
    text = "\n".join(lines) + "\n"
    print(text)
    if a.write:
        write_section(SECTION, text)


if __name__ == "__main__":
    if str(ROOT / "benchmarks") not in sys.path:
        sys.path.insert(0, str(ROOT / "benchmarks"))
    main()
