"""Speed and memory of the MCAP and rerun sinks on a long replay.

A synthetic phone recording (accelerometer and gyroscope at 200 Hz, magnetometer at 100 Hz, truth at 50 Hz;
a walker turning now and then, phone tilting a little, hard iron, noise, gyro bias; Zürich's WMM field) is
replayed through :func:`replay.run.replay` — the real :class:`pdr_mag.pipeline.HeadingPipeline` — with no
sink, with :class:`~pdr_mag.sinks.mcap.McapSink` (``mcap``: every message; ``mcap@HZ``: ``rate_hz=HZ``),
with :class:`~pdr_mag.sinks.rerun.RerunSink` (``rrd``) and with both (``both``).
Every configuration runs in its own process, so the peak memory of one does not leak into the next.

Reported per run: wall time of the replay (sinks opened, fed and closed inside it); CPU time of all threads;
CPU time of the replay's own thread; the overhead against the same replay without sinks (ratios and seconds
of wall time); the messages written to the MCAP file; and the peak resident memory *during* the replay above
the resident memory just before it (psutil, sampled every 10 ms: counts the Rust side of rerun and the zstd
buffers too, not only Python objects).  Running it for 10 and 60 minutes shows whether memory grows with
the length.

    python benchmarks/sinks.py                     # 10 and 60 min, the default configurations, 2 runs each
    python benchmarks/sinks.py --minutes 60 --configs none mcap mcap@10 --repeat 3
    python benchmarks/sinks.py --one mcap --minutes 60 --out /tmp/x   # a single run (JSON on stdout)
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

CONFIGS = ("none", "mcap", "mcap@10", "rrd", "both")  # the default set; any "mcap@HZ" is accepted
SITE = {
    "device": "synthetic benchmark phone",
    "latitude_deg": 47.3769,
    "longitude_deg": 8.5417,
    "altitude_m": 410.0,
    "date": "2026-06-15",
}


def make_recording(minutes: float, seed: int = 0):
    """A walk with turns: rates 200/200/100 Hz (accel/gyro/mag), jittered clocks, truth at 50 Hz."""
    from scipy.spatial.transform import Rotation

    from pdr_mag.field import earth_field_from_meta
    from replay.recording import Recording, Stream

    rng = np.random.default_rng(seed)
    dur = 60.0 * minutes
    # heading: piecewise-constant turn rate (a turn every ~20 s), plus sway; tilt: small wobble
    tk = np.arange(0.0, dur + 1.0, 0.01)
    turn = np.repeat(
        rng.normal(0.0, 0.35, len(tk) // 2000 + 1) * (rng.random(len(tk) // 2000 + 1) < 0.3), 2000
    )
    yaw = np.cumsum(turn[: len(tk)]) * 0.01 + 0.15 * np.sin(2 * np.pi * 0.9 * tk)
    pitch = np.radians(35.0) + 0.05 * np.sin(2 * np.pi * 1.8 * tk)
    roll = 0.04 * np.sin(2 * np.pi * 0.9 * tk + 0.3)

    def rot(t):
        return Rotation.from_euler(
            "ZXY", np.column_stack([np.interp(t, tk, -yaw), np.interp(t, tk, pitch), np.interp(t, tk, roll)])
        )

    def clock(rate):
        n = int(dur * rate)
        return np.arange(n) / rate + rng.normal(0.0, 0.05 / rate, n) + 0.123

    field = earth_field_from_meta(SITE)
    f_w = field.field_w_array
    ta, tg, tm, tt = clock(200.0), clock(200.0), clock(100.0), np.arange(int(dur * 50)) / 50.0 + 0.123
    ta.sort(), tg.sort(), tm.sort()
    accel = rot(ta).inv().apply([0.0, 0.0, 9.80665]) + rng.normal(0.0, 0.05, (len(ta), 3))
    r_g = rot(tg)
    w = (r_g[:-1].inv() * r_g[1:]).as_rotvec() / np.diff(tg)[:, None]
    gyro = np.vstack([w, w[-1:]]) + [0.01, -0.014, 0.009] + rng.normal(0.0, 0.003, (len(tg), 3))
    mag = rot(tm).inv().apply(f_w) + [22.0, -31.0, 48.0] + rng.normal(0.0, 0.4, (len(tm), 3))
    q = rot(tt).as_quat()[:, [3, 0, 1, 2]]
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    return Recording(
        mag=Stream(tm, mag),
        accel=Stream(ta, accel),
        gyro=Stream(tg, gyro),
        meta=dict(SITE),
        truth=(tt, q),
        source=f"synthetic-{minutes:g}min",
        format="synthetic",
    )


def _cpu_all() -> float:
    """CPU seconds of this process (all threads: rerun's too) + its finished children."""
    import resource

    ch = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + ch.ru_utime + ch.ru_stime


def _peak_rss_sampler(stop: threading.Event, out: list):
    import psutil

    proc = psutil.Process()
    peak = proc.memory_info().rss
    while not stop.wait(0.01):
        peak = max(peak, proc.memory_info().rss)
    out.append(max(peak, proc.memory_info().rss))


def run_one(config: str, minutes: float, out_dir: Path) -> dict:
    """One replay in this process; returns timing, memory and file sizes."""
    import psutil

    from pdr_mag.pipeline import PipelineSettings
    from pdr_mag.sinks.mcap import McapSink
    from pdr_mag.sinks.rerun import RerunSink
    from replay.run import replay

    rec = make_recording(minutes)
    settings = PipelineSettings(keep_mag_calibrated=True)  # identical pipeline work in every configuration
    # warm the compiled kernels on a short slice, so no configuration pays the JIT
    from replay.recording import Recording, Stream

    def head(s, n):
        return Stream(s.t[:n], s.xyz[:n])

    warm = Recording(
        mag=head(rec.mag, 3000),
        accel=head(rec.accel, 6000),
        gyro=head(rec.gyro, 6000),
        meta=rec.meta,
        source="warm-up",
    )
    replay(warm, settings=settings, progress=False)

    sinks = []
    paths = []
    if config == "both" or config.startswith("mcap"):
        rate = float(config.split("@")[1]) if "@" in config else None
        paths.append(out_dir / f"{config}-{minutes:g}.mcap")
        sinks.append(McapSink(paths[-1], rate_hz=rate))
    if config in ("rrd", "both"):
        paths.append(out_dir / f"{config}-{minutes:g}.rrd")
        sinks.append(RerunSink(paths[-1]))
    # import the sink libraries before timing: a constant ~1 s (rerun) that is not per-sample overhead
    t_imp = time.perf_counter()
    import mcap.records  # noqa: F401
    import rerun  # noqa: F401

    import_s = time.perf_counter() - t_imp
    rss0 = psutil.Process().memory_info().rss
    stop, peak = threading.Event(), []
    sampler = threading.Thread(target=_peak_rss_sampler, args=(stop, peak), daemon=True)
    sampler.start()
    t0, c0, m0 = time.perf_counter(), _cpu_all(), time.thread_time()
    summary = replay(rec, settings=settings, sinks=sinks, progress=False)
    elapsed, cpu, main_cpu = time.perf_counter() - t0, _cpu_all() - c0, time.thread_time() - m0
    stop.set()
    sampler.join()
    sizes = {p.suffix[1:]: p.stat().st_size for p in paths}
    messages = sum(sum(s.counts.values()) for s in sinks if isinstance(s, McapSink))
    for p in paths:
        p.unlink()
    return {
        "config": config,
        "minutes": minutes,
        "samples": int(len(rec.accel) + len(rec.gyro) + len(rec.mag)),
        "outputs": int(summary["n_outputs"]),
        "elapsed_s": elapsed,
        "cpu_s": cpu,
        "main_thread_cpu_s": main_cpu,
        "import_s": import_s,
        "rss_before_MB": rss0 / 2**20,
        "peak_above_MB": (peak[0] - rss0) / 2**20,
        "file_MB": {k: v / 2**20 for k, v in sizes.items()},
        "mcap_messages": messages,
    }


def _config(name: str) -> str:
    """A configuration name: one of :data:`CONFIGS` or ``mcap@HZ`` (the MCAP sink with ``rate_hz=HZ``)."""
    if name in CONFIGS:
        return name
    if name.startswith("mcap@"):
        try:
            if float(name[5:]) > 0:
                return name
        except ValueError:
            pass
    raise argparse.ArgumentTypeError(f"expected one of {CONFIGS} or mcap@HZ, got {name!r}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, nargs="*", default=[10.0, 60.0])
    ap.add_argument("--repeat", type=int, default=2, help="runs per configuration (best time, worst memory)")
    ap.add_argument(
        "--configs", nargs="*", type=_config, default=list(CONFIGS), help=f"of {CONFIGS}, mcap@HZ"
    )
    ap.add_argument("--one", type=_config, help="run one configuration in this process, print JSON")
    ap.add_argument("--out", type=Path, default=None, help="folder for the files written (deleted after)")
    args = ap.parse_args(argv)
    if args.one:
        out = args.out or Path(tempfile.mkdtemp(prefix="pdr_sinks_"))
        print(json.dumps(run_one(args.one, args.minutes[0], out)))
        return 0
    runs: dict[tuple, list] = {}
    with tempfile.TemporaryDirectory(prefix="pdr_sinks_") as tmp:
        for minutes in args.minutes:
            for _ in range(args.repeat):
                for config in args.configs:  # interleaved, so a burst of load elsewhere hits all alike
                    cmd = [sys.executable, __file__, "--one", config, "--minutes", str(minutes), "--out", tmp]
                    res = subprocess.run(cmd, capture_output=True, text=True, check=False)
                    if res.returncode != 0:
                        print(res.stderr, file=sys.stderr)
                        return 1
                    r = json.loads(res.stdout.strip().splitlines()[-1])
                    runs.setdefault((minutes, config), []).append(r)
                    print(
                        f"{minutes:>4g} min {config:<5} wall {r['elapsed_s']:6.1f} s cpu {r['cpu_s']:6.1f} s "
                        f"peak +{r['peak_above_MB']:5.0f} MB {r['file_MB']}",
                        file=sys.stderr,
                        flush=True,
                    )
    best = {
        k: {
            **v[0],
            "elapsed_s": min(r["elapsed_s"] for r in v),
            "cpu_s": min(r["cpu_s"] for r in v),
            "main_thread_cpu_s": min(r["main_thread_cpu_s"] for r in v),
            "peak_above_MB": max(r["peak_above_MB"] for r in v),
        }
        for k, v in runs.items()
    }
    print(
        "| length | sinks | wall | overhead vs none | CPU all | CPU replay thread "
        "| ratio wall / CPU all / CPU thread | MCAP messages | peak memory above start (vs none) | files |"
    )
    print("| --- | --- | ---: | ---: | ---: | ---: | --- | ---: | ---: | --- |")
    for (minutes, config), r in best.items():
        base = best.get((minutes, "none"))
        ratio = (
            f"{r['elapsed_s'] / base['elapsed_s']:.2f}× / {r['cpu_s'] / base['cpu_s']:.2f}× / "
            f"{r['main_thread_cpu_s'] / base['main_thread_cpu_s']:.2f}×"
            if base
            else "—"
        )
        extra = f"+{r['elapsed_s'] - base['elapsed_s']:.1f} s" if base else "—"
        peak = f"{r['peak_above_MB']:.0f} MB" + (
            f" (+{r['peak_above_MB'] - base['peak_above_MB']:.0f})" if base else ""
        )
        files = ", ".join(f"{k} {v:.0f} MB" for k, v in r["file_MB"].items()) or "—"
        print(
            f"| {minutes:g} min ({r['samples'] / 1e6:.2f} M samples, {r['outputs']} outputs) | {config} | "
            f"{r['elapsed_s']:.1f} s | {extra} | {r['cpu_s']:.1f} s | {r['main_thread_cpu_s']:.1f} s | "
            f"{ratio} | "
            f"{r['mcap_messages'] / 1e6:.2f} M | {peak} | {files} |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
