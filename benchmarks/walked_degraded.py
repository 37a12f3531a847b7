"""The walked-direction benchmark on streams degraded as other phones and loggers would deliver them.

``benchmarks/walked.py`` scores the mall traces as one phone (50 Hz streams, clean time stamps) logged them.
Held-out phones are slower, noisier and less regular, so here every trace is replayed again with its streams
degraded, and the peers run on the very same degraded streams, so that what the degradation costs the product
is compared with what it costs them:

``none``
    the traces as logged (the peers re-run here: a check of the runners against ``walked_peers.csv``);
``mag_10hz``
    every fifth magnetometer sample (a 10 Hz magnetometer);
``imu_25hz``
    every second accelerometer and gyroscope sample (25 Hz);
``drop_20``
    a fifth of every stream's samples left out at random (a logger under load);
``jitter_4ms``
    every time stamp moved by up to ±4 ms (uniform), the samples then in time order (a logger that stamps
    samples when it reads them);
``mag_noise_1uT``
    Gaussian noise of 1 µT per axis added to the magnetometer (a noisier magnetometer).

The product: ``replay`` of the degraded recording as ``pdr-mag replay TRACE`` runs it (the raw field and the
phone's own estimates it carries; walked.py's ``default`` run).  The peers: VQF and imufusion with the
settings of ``walked_peers.csv``, fed the OS-calibrated field (``TYPE_MAGNETIC_FIELD``, degraded alike) and
the gyroscope less the OS's bias (``TYPE_GYROSCOPE``), on a regular grid at the gyroscope's median interval
with the latest gyroscope sample and field held and the accelerometer interpolated
(``_peers.on_gyro_grid`` with a period: the mall logger repeats a stalled gyroscope's last value, which the
reader drops and the peers' fixed sample period needs back); their magnetic north turned to true north with
the WMM declination.  They are not the CSV's run (its runner's grid is not known here): compare each method
with itself across the degradations.  Every degradation is random only through a generator seeded by the
trace and the stream, so the product and the peers see the same samples.  Scoring:
:mod:`replay.heading_scores` (``../shared/tools/walked-direction``'s definitions).

Usage::

    python benchmarks/walked_degraded.py [--only NAME ...] [--jobs 2] [--write-results]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
import zlib
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import write_section  # noqa: E402
from _peers import _to_true, on_gyro_grid, run_imufusion, run_vqf  # noqa: E402
from walked import os_field_copy, traces  # noqa: E402

from pdr_mag.conventions import heading_deg_from_quat  # noqa: E402
from pdr_mag.field import earth_field_from_meta  # noqa: E402
from replay.formats import read_recording  # noqa: E402
from replay.heading_scores import pooled, score_segments, walked_segments  # noqa: E402
from replay.recording import Stream  # noqa: E402
from replay.run import replay  # noqa: E402

SECTION = "## Heading against the walked direction on degraded streams (issue 19)"
DEGRADATIONS = ("none", "mag_10hz", "imu_25hz", "drop_20", "jitter_4ms", "mag_noise_1uT")
PEERS = {"vqf": run_vqf, "imufusion": run_imufusion}


def degrade(rec, name: str, trace: str):
    """``rec`` with its streams degraded as ``name`` says (module docstring), in place; the random choices
    seeded by the trace's name and the stream's, so that two recordings of one trace get the same ones."""
    for i, key in enumerate(("mag", "accel", "gyro")):
        s = getattr(rec, key)
        t, x = s.t, s.xyz
        rng = np.random.default_rng([zlib.crc32(trace.encode()), i])
        if name == "mag_10hz" and key == "mag":
            t, x = t[::5], x[::5]
        elif name == "imu_25hz" and key != "mag":
            t, x = t[::2], x[::2]
        elif name == "drop_20":
            keep = rng.random(len(t)) >= 0.2
            t, x = t[keep], x[keep]
        elif name == "jitter_4ms":
            t = t + rng.uniform(-0.004, 0.004, len(t))
            order = np.argsort(t, kind="stable")
            t, x = t[order], x[order]
            keep = np.r_[True, np.diff(t) > 0]  # a stamp repeated by the jitter: one sample
            t, x = t[keep], x[keep]
        elif name == "mag_noise_1uT" and key == "mag":
            x = x + rng.normal(0.0, 1.0, x.shape)
        setattr(rec, key, Stream(np.ascontiguousarray(t), np.ascontiguousarray(x)))
    return rec


def one_trace(args) -> dict:
    """``{method: [(error_deg, sigma_deg), …]}`` of one trace's segments under one degradation."""
    path, os_path, name = args
    rec = degrade(read_recording(path), name, path.stem)
    out = {"pdr_mag": [(s["error_deg"], s["sigma_deg"]) for s in
                       (replay(rec, progress=False).get("walked_direction") or {}).get("segments", [])]}
    segments = walked_segments(rec.meta["waypoints"])
    cal = degrade(read_recording(os_path), name, path.stem)  # its field is the OS-calibrated one
    declination = earth_field_from_meta(cal.meta).declination_deg
    tg, gyr, acc, mag = on_gyro_grid(cal, cal.mag.xyz, float(np.median(np.diff(cal.gyro.t))))
    gyr = gyr - np.asarray(cal.meta.get("gyro_os_bias_rad_s", (0.0, 0.0, 0.0)))  # TYPE_GYROSCOPE
    for peer, run in PEERS.items():
        q = _to_true(run(tg, gyr, acc, mag), declination)
        out[peer] = score_segments(tg, heading_deg_from_quat(q), None, segments)
    return out


def run(name: str, paths: list[Path], os_paths: list[Path], jobs: int) -> dict:
    """Every trace under degradation ``name``: ``{method: [(error, sigma), …]}`` over all segments."""
    out: dict[str, list] = {}
    with ProcessPoolExecutor(jobs) as pool:
        for res in pool.map(one_trace, [(p, o, name) for p, o in zip(paths, os_paths, strict=True)]):
            for method, segs in res.items():
                out.setdefault(method, []).extend(segs)
    return out


def table(results: dict) -> list[str]:
    """One row per degradation: each method's median / mean |error| and segments > 45°, and its median and
    mean against its own run on the streams as logged (``none``); pdr_mag's share within 2σ."""
    lines = [
        "| streams | pdr_mag median / mean / > 45° | Δ median / mean | within 2σ | vqf | Δ | imufusion | Δ |",
        "| --- | --- | --- | ---: | --- | --- | --- | --- |",
    ]
    base = {m: pooled(v) for m, v in results["none"].items()} if "none" in results else None
    for name, res in results.items():
        cells = []
        for m in ("pdr_mag", "vqf", "imufusion"):
            f = pooled(res[m])
            fig = f"{f['median_deg']:.2f} / {f['mean_deg']:.2f} / {f['n_over_45']}"
            cells.append(f"**{fig}**" if m == "pdr_mag" else fig)
            b = base[m] if base and name != "none" else None
            cells.append("—" if b is None else
                         f"{f['median_deg'] - b['median_deg']:+.2f} / {f['mean_deg'] - b['mean_deg']:+.2f}")
            if m == "pdr_mag":
                cells.append(f"{100 * f['within_2sigma_share']:.1f} %")
        lines.append(f"| `{name}` | " + " | ".join(cells) + " |")
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="+", choices=DEGRADATIONS, default=list(DEGRADATIONS))
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--write-results", action="store_true")
    a = ap.parse_args()
    paths = traces()
    if not paths:
        sys.exit("no mall trace under ../shared/datasets")
    results = {}
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        os_paths = [os_field_copy(p, Path(tmp)) for p in paths]
        for name in a.only:
            results[name] = run(name, paths, os_paths, a.jobs)
            print(f"{name}: done", file=sys.stderr)
    lines = table(results)
    print("\n".join(lines))
    if a.write_results:
        import subprocess

        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                                cwd=Path(__file__).parent).stdout.strip()
        text = "\n".join([
            SECTION, "",
            f"`python benchmarks/walked_degraded.py --write-results` (commit {commit}, "
            f"{time.perf_counter() - t0:.0f} s on {a.jobs} processes): the {len(paths)} mall traces of "
            "`walked.py`, each stream degraded as the script's docstring says (the same samples for every "
            "method); pdr_mag's default replay, VQF and imufusion on the same degraded streams (fed as the "
            "script says, not as `walked_peers.csv`'s run: compare each method with itself across rows). "
            f"|error| of the walked direction over the {len(next(iter(results.values()))['pdr_mag'])} "
            "segments, deg: median / mean / segments > 45°, and "
            "the change against the method's own `none` row; pdr_mag's share of segments within 2σ.",
            "", *lines,
        ])
        write_section(SECTION, text)


if __name__ == "__main__":
    main()
