"""Replay throughput of the whole HeadingPipeline against imufusion's AHRS (issue 4, "Speed").

Recording: a tyrex walk (default ``Thibaud_Nexus5_NoDist_Texting``), both timed in the same run on the
same recording, best of ``--repeats`` (interleaved), the numba kernels loaded before the first timing:

``pipeline``
    ``HeadingPipeline(meta=rec.meta).run(streams)`` — mode (b), no calibration given: merge, blocks,
    fusion, online calibration (diversity buffer, refits, stale test), events; every estimate returned.
``pipeline_sliced``
    the same pushed in 2-s slices of stream time with a poll after each (as a phone app might deliver).
``replay``
    ``replay.run.replay(rec)`` — what ``pdr-mag replay REC`` runs once the recording is read: the merge of
    the recording's streams into slices of :data:`replay.run.SLICE_S` (30 s), the pipeline polled after
    each, events and the run summary; no sink.
``imufusion``
    ``imufusion.Ahrs`` exactly as ``benchmarks/heading.py`` runs it: the accelerometer interpolated and
    the latest magnetometer sample (calibrated with the day's calibration) on the gyroscope's grid, one
    ``update`` per gyro sample; the timing includes that resampling, as ours includes the merge.

Throughput is counted as accelerometer + gyroscope + magnetometer samples of the recording per second of
wall time, the same count for both; ratio = imufusion time / pipeline time (≥ 1: the pipeline is faster).

Synthetic hour (``--hour``): ``benchmarks/memory_pipeline.py``'s texting walk, accelerometer and gyroscope at
200 Hz and magnetometer at 100 Hz, generated one second at a time and pushed/polled one second at a time
(as a phone app would); only the pipeline calls are timed; the resident set size is sampled every 10
minutes.  The same hour is then fed to imufusion (per gyro sample, magnetometer held), and, kept in memory
as a recording (no truth: the episode finder's error detector is idle), to ``replay.run.replay``.

Usage::

    python benchmarks/pipeline_speed.py [--trial NAME | --all] [--repeats 7] [--hour] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import heading as hb  # noqa: E402  (benchmarks/heading.py: the imufusion runner and the day's calibration)
from _common import imufusion_ahrs, rss_mb  # noqa: E402


def _streams(rec) -> dict:
    return {
        "accel": (rec.accel.t, rec.accel.xyz),
        "gyro": (rec.gyro.t, rec.gyro.xyz),
        "mag": (rec.mag.t, rec.mag.xyz),
    }


def _pipeline(rec, streams):
    from pdr_mag.pipeline import HeadingPipeline

    return HeadingPipeline(meta=rec.meta).run(streams)


def _pipeline_sliced(rec, streams, slice_s: float = 2.0):
    from pdr_mag.pipeline import HeadingPipeline

    pipe = HeadingPipeline(meta=rec.meta)
    idx = dict.fromkeys(streams, 0)
    n = 0
    for edge in np.arange(rec.t0 + slice_s, rec.t1 + slice_s, slice_s):
        for k, (t, x) in streams.items():
            j = int(np.searchsorted(t, edge))
            if j > idx[k]:
                pipe.push_arrays(k, t[idx[k] : j], x[idx[k] : j])
                idx[k] = j
        n += len(pipe.poll())
    return n + len(pipe.flush())


def recording(trial: str, repeats: int) -> dict:
    from replay.formats import read_recording

    d = hb.DATA / trial
    rec = read_recording(d)
    streams = _streams(rec)
    n = sum(len(t) for t, _ in streams.values())
    info = json.loads((d / "trial.json").read_text())
    from pdr_mag.field import earth_field_from_meta

    cal = hb.day_calibration(info["calib"], earth_field_from_meta(rec.meta))
    mag_cal = cal.apply(rec.mag.xyz)

    def imu():
        hb.run_imufusion(*hb.on_gyro_grid(rec, mag_cal))

    from replay.run import replay

    runs = {
        "pipeline": lambda: _pipeline(rec, streams),
        "pipeline_sliced": lambda: _pipeline_sliced(rec, streams),
        "replay": lambda: replay(rec, progress=False),
    }
    runs["imufusion"] = imu
    for f in runs.values():  # load the kernels (numba cache) and warm up
        f()
    best = dict.fromkeys(runs, np.inf)
    for _ in range(repeats):
        for name, f in runs.items():
            t0 = time.perf_counter()
            f()
            best[name] = min(best[name], time.perf_counter() - t0)
    out = {"trial": trial, "samples": n, "duration_s": float(rec.t1 - rec.t0), "repeats": repeats}
    for name, b in best.items():
        out[f"{name}_s"] = b
        out[f"{name}_per_s"] = n / b
    out["ratio"] = best["imufusion"] / best["pipeline"]
    out["ratio_sliced"] = best["imufusion"] / best["pipeline_sliced"]
    out["ratio_replay"] = best["imufusion"] / best["replay"]
    return out


def hour(minutes: float = 60.0) -> dict:
    import memory_pipeline as mp  # benchmarks/memory_pipeline.py: the synthetic walk, one second at a time

    from pdr_mag.pipeline import HeadingPipeline

    seconds = int(minutes * 60)
    rng = np.random.default_rng(0)
    pipe = HeadingPipeline(meta=mp.META)
    field_w = np.asarray(pipe.field.field_w)
    samples = n_out = 0
    t_pipe = 0.0
    rss = []
    for k in range(seconds):
        data = mp._second(k, field_w, rng)
        t0 = time.perf_counter()
        for name, (t, x) in data.items():
            pipe.push_arrays(name, t, x)
        n_out += len(pipe.poll())
        pipe.pop_events()
        t_pipe += time.perf_counter() - t0
        samples += sum(len(t) for t, _ in data.values())
        if k % 600 == 0 or k == seconds - 1:
            rss.append((round(k / 60.0, 1), round(rss_mb(), 1)))
    t0 = time.perf_counter()
    n_out += len(pipe.flush())
    t_pipe += time.perf_counter() - t0
    # the same hour through imufusion (per gyro sample, magnetometer held), one second at a time
    rng = np.random.default_rng(0)
    ahrs = imufusion_ahrs(200.0)
    t_imu = 0.0
    parts = {name: ([], []) for name in ("accel", "gyro", "mag")}
    for k in range(seconds):
        data = mp._second(k, field_w, rng)
        for name, (t, x) in data.items():
            parts[name][0].append(t)
            parts[name][1].append(x)
        t0 = time.perf_counter()
        tg, gyr = data["gyro"]
        ta, acc = data["accel"]
        tm, mag = data["mag"]
        acc = np.column_stack([np.interp(tg, ta, acc[:, i]) for i in range(3)]) / 9.80665
        mag = mag[np.clip(np.searchsorted(tm, tg, side="right") - 1, 0, len(tm) - 1)]
        gd = np.degrees(gyr)
        q = np.empty((len(tg), 4))
        for i in range(len(tg)):
            ahrs.update(gd[i], acc[i], mag[i])
            q[i] = ahrs.get_quaternion()
        t_imu += time.perf_counter() - t0
    from replay.recording import Recording, Stream
    from replay.run import replay

    rec = Recording(
        meta=mp.META, **{name: Stream(np.concatenate(t), np.concatenate(x)) for name, (t, x) in parts.items()}
    )
    del parts
    t0 = time.perf_counter()
    replay(rec, progress=False)
    t_replay = time.perf_counter() - t0
    return {
        "minutes": minutes,
        "samples": samples,
        "outputs": n_out,
        "pipeline_s": t_pipe,
        "pipeline_per_s": samples / t_pipe,
        "imufusion_s": t_imu,
        "imufusion_per_s": samples / t_imu,
        "ratio": t_imu / t_pipe,
        "replay_s": t_replay,
        "replay_per_s": samples / t_replay,
        "ratio_replay": t_imu / t_replay,
        "rss_mb": rss,
        "rss_growth_after_10min_mb": rss[-1][1] - rss[1][1] if len(rss) > 2 else None,
        "final_cal_state": pipe.cal_state,
        "offset_error_uT": None
        if pipe.calibration is None
        else float(np.linalg.norm(pipe.calibration.offset_array - mp.B)),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trial", default="Thibaud_Nexus5_NoDist_Texting")
    ap.add_argument("--all", action="store_true", help="every tyrex walk of heading.py")
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--hour", action="store_true", help="also the synthetic one-hour stream")
    ap.add_argument("--minutes", type=float, default=60.0, help="length of the synthetic stream")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    res = {"recordings": []}
    for trial in hb.TRIALS if args.all else (args.trial,):
        r = recording(trial, args.repeats)
        res["recordings"].append(r)
        print(
            f"{trial:34s} {r['samples']:7d} samples  pipeline {r['pipeline_s'] * 1e3:6.1f} ms "
            f"({r['pipeline_per_s'] / 1e6:.2f} M/s; 2-s slices {r['pipeline_sliced_s'] * 1e3:6.1f} ms)  "
            f"imufusion {r['imufusion_s'] * 1e3:6.1f} ms ({r['imufusion_per_s'] / 1e6:.2f} M/s)  "
            f"ratio {r['ratio']:.2f} (sliced {r['ratio_sliced']:.2f}, replay {r['ratio_replay']:.2f})",
            file=sys.stderr,
        )
    if args.hour:
        h = hour(args.minutes)
        res["hour"] = h
        print(
            f"synthetic {h['minutes']:g} min: {h['samples']} samples, pipeline {h['pipeline_s']:.2f} s "
            f"({h['pipeline_per_s'] / 1e6:.2f} M/s), replay {h['replay_s']:.2f} s, imufusion "
            f"{h['imufusion_s']:.2f} s, ratio {h['ratio']:.2f} (replay {h['ratio_replay']:.2f}); "
            f"RSS {h['rss_mb']}",
            file=sys.stderr,
        )
    print(json.dumps(res, indent=1))
    if args.json:
        args.json.write_text(json.dumps(res, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
