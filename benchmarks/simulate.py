"""Simulation speed (issue 3): samples per second of ``pdr_mag.sim.simulate`` for a one-hour walk.

Counted samples are accelerometer + gyroscope + magnetometer (truth and positions come on top).  Reported:
the best and median of ``--repeat`` runs for the one-hour texting walk at the default phone rates
(100/100/50 Hz) and at 200/200/100 Hz, a one-hour ``chain`` (with a steel layout: dipole fields on every
magnetometer sample), and, once, the whole ``pdr-mag simulate`` command for the one-hour walk including
writing the CSV files (text formatting dominates there).

    python benchmarks/simulate.py               # ~30 s
    python benchmarks/simulate.py --repeat 5 --json results.json
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from pdr_mag.sim import simulate  # noqa: E402
from pdr_mag.sim.sensor_model import PhoneSpec  # noqa: E402


def _time_sim(repeat: int, **kw) -> dict:
    """Wall and CPU time (process_time: robust when other jobs share the cores) of ``repeat`` runs."""
    walls, cpus, n = [], [], 0
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        res = simulate(**kw)
        walls.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
        n = res.n_samples
    wall, cpu = min(walls), min(cpus)
    return {
        "samples": n,
        "best_wall_s": round(wall, 3),
        "best_cpu_s": round(cpu, 3),
        "median_wall_s": round(float(np.median(walls)), 3),
        "samples_per_s_wall": round(n / wall),
        "samples_per_s_cpu": round(n / cpu),
    }


def _time_cli() -> dict:
    from replay.cli import main

    with tempfile.TemporaryDirectory() as d:
        t0 = time.perf_counter()
        rc = main(
            [
                "simulate",
                "--scenario",
                "walk",
                "--seed",
                "1",
                "--duration",
                "3600",
                "--out",
                str(Path(d) / "w"),
            ]
        )
        dt = time.perf_counter() - t0
        size = sum(f.stat().st_size for f in (Path(d) / "w").iterdir())
    return {"rc": rc, "wall_s": round(dt, 2), "bytes": size}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    runs = {
        "walk 1 h, 100/100/50 Hz": dict(scenario="walk", seed=1, duration_s=3600.0),
        "walk 1 h, 200/200/100 Hz": dict(
            scenario="walk",
            seed=1,
            duration_s=3600.0,
            phone=PhoneSpec(accel_rate_hz=200, gyro_rate_hz=200, mag_rate_hz=100),
        ),
        "chain 1 h (steel dipoles), 100/100/50 Hz": dict(scenario="chain", seed=1, duration_s=3600.0),
    }
    out = {
        "machine": f"{platform.processor() or platform.machine()}, python {platform.python_version()}",
        "numpy": np.__version__,
        "runs": {},
    }
    simulate("walk", seed=0, duration_s=10.0)  # warm-up (imports, WMM coefficients)
    for name, kw in runs.items():
        out["runs"][name] = r = _time_sim(args.repeat, **kw)
        print(
            f"{name:<42} {r['samples']:>9} samples  wall {r['best_wall_s']:.2f} s "
            f"({r['samples_per_s_wall'] / 1e6:.2f} M/s)  cpu {r['best_cpu_s']:.2f} s "
            f"({r['samples_per_s_cpu'] / 1e6:.2f} M/s)"
        )
    out["cli_walk_1h"] = c = _time_cli()
    print(
        f"{'pdr-mag simulate walk 1 h (with CSV writing)':<42} {c['wall_s']:.1f} s, {c['bytes'] / 1e6:.0f} MB"
    )
    if args.json:
        args.json.write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
