"""Memory check: a one-hour 200 Hz stream through HeadingPipeline in bounded memory (not a timed test).

A synthetic texting-pose walk (yaw turns, tilt sway, walking bounce, hard iron, noise) is generated one
second at a time — accelerometer and gyroscope at 200 Hz, magnetometer at 100 Hz — pushed, polled, and the
estimates dropped (as a PDR backend would consume them).  The resident set size is sampled every five
minutes of stream time; bounded memory means it stops growing after the first minutes.

Usage::

    python benchmarks/memory_pipeline.py [--minutes 60] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import rss_mb  # noqa: E402

META = {"latitude_deg": 45.19, "longitude_deg": 5.73, "altitude_m": 200.0, "date": "2016-05-31"}
B = np.array([58.0, -74.0, 412.0])


def _second(k: int, field_w: np.ndarray, rng) -> dict:
    """One second of sensor data starting at t = k (deterministic yaw profile: a turn every 7 s)."""
    t = k + np.arange(200) / 200.0

    def yaw(tt):
        return 0.9 * np.floor(tt / 7.0) + 0.9 * np.clip((tt % 7.0) - 6.0, 0, 1)

    def rot(tt):
        return Rotation.from_euler(
            "ZXY", np.column_stack([yaw(tt), np.radians(20 + 3 * np.sin(1.9 * tt)), 0.05 * np.sin(5.7 * tt)])
        )

    r = rot(t)
    r2 = rot(t + 1e-3)
    omega = (r.inv() * r2).as_rotvec() / 1e-3 + np.array([0.0, 0.0, 0.07]) + rng.normal(0, 0.003, (200, 3))
    lin = np.column_stack([np.zeros(200), 0.4 * np.sin(11.3 * t), 1.5 * np.sin(11.3 * t)])
    acc = r.inv().apply(np.array([0, 0, 9.81]) + lin) + rng.normal(0, 0.05, (200, 3))
    tm = t[::2] + 0.001
    mag = rot(tm).inv().apply(field_w) + B + rng.normal(0, 0.4, (100, 3))
    return {"accel": (t, acc), "gyro": (t, omega), "mag": (tm, mag)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=60.0)
    ap.add_argument("--json", type=str, default=None)
    args = ap.parse_args(argv)
    from pdr_mag.pipeline import HeadingPipeline

    rng = np.random.default_rng(0)
    pipe = HeadingPipeline(meta=META)
    f = pipe.field
    field_w = np.asarray(f.field_w)
    samples = 0
    n_out = 0
    marks = []
    t_proc = 0.0
    for k in range(int(args.minutes * 60)):
        data = _second(k, field_w, rng)
        t0 = time.perf_counter()
        for name, (t, x) in data.items():
            pipe.push_arrays(name, t, x)
            samples += len(t)
        n_out += len(pipe.poll())
        pipe.pop_events()
        t_proc += time.perf_counter() - t0
        if k % 300 == 0 or k == int(args.minutes * 60) - 1:
            marks.append({"minute": round(k / 60.0, 1), "rss_mb": round(rss_mb(), 1)})
            print(f"{marks[-1]['minute']:5.1f} min  RSS {marks[-1]['rss_mb']:7.1f} MB", file=sys.stderr)
    n_out += len(pipe.flush())
    res = {
        "minutes": args.minutes,
        "samples": samples,
        "outputs": n_out,
        "rss": marks,
        "rss_growth_after_5min_mb": round(marks[-1]["rss_mb"] - marks[1]["rss_mb"], 1)
        if len(marks) > 2
        else None,
        "pipeline_s": round(t_proc, 1),
        "samples_per_s": round(samples / t_proc),
        "final_cal_state": pipe.cal_state,
        "offset_error_uT": None
        if pipe.calibration is None
        else round(float(np.linalg.norm(pipe.calibration.offset_array - B)), 2),
    }
    print(json.dumps(res, indent=1))
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(res, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
