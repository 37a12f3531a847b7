"""Mode (a) heading accuracy and fusion speed on the tyrex walks: pdr_mag's fusion core against the peers.

Mode (a): each walk is processed with the day's magnetometer calibration —
:func:`pdr_mag.calibration.calibrate` on that day's ``calib_mag_*`` recording, exactly as
``pdr-mag calibrate`` makes it (``auto`` method, quasi-static accelerometer for the alignment, WMM
field for the radius check) — and nothing else: raw gyroscope, raw accelerometer, the WMM field of
``meta.json``.  ``trial.json`` is read here only to know which calibration recording belongs to the
walk and (by the shared scorer) for the scoring window.

Columns, all in the same run on the same inputs:

``pdr_mag``
    :class:`pdr_mag.attitude.FusionCore` with default settings, fed the merged raw streams with the
    calibrated magnetometer, its strength reference set to the calibration radius (as the pipeline does).
``pdr_mag_pipe``
    the whole :class:`pdr_mag.pipeline.HeadingPipeline` through ``replay(REC, calibration=…)`` (the same
    code as ``pdr-mag replay REC --calibration FILE``), when available.
peers (as in ``../shared/benchmarks/PEERS.md``)
    imufusion 1.3.3 (gain 0.5, acceleration rejection 10°, magnetic rejection 10°, recovery 5 s), vqf 2.1.2
    (defaults), ahrs 0.4.0 Madgwick (gain 0.041) and Mahony (defaults); fed on the gyroscope's time grid
    with the accelerometer interpolated and the latest magnetometer sample, calibrated with the same
    calibration scaled to the WMM strength; declination from the WMM.  ``*_gcal``: also the day's gyro
    offset removed (mean of the static ``calib_gyr_*`` recording) — the peers' best case.
``os``
    the phone's own fusion (``os.csv``).

Metric: the shared scorer ``../shared/benchmarks/tyrex/score.py`` (imported, not reimplemented): mean
|heading error| over 5–120 s of the mocap clock, per trial.  Also reported for pdr_mag: how often the truth
lies within 1σ / 2σ of the reported ``heading_std_deg`` (Gaussian: 68 % / 95 %).

Speed: replay throughput (sensor samples per second) of the fusion core against imufusion's ``Ahrs`` on the
same recording in the same run; both timings include the preparation of their inputs (merge / resampling).

Usage::

    python benchmarks/heading.py [--write-results] [--speed-repeats N] [--commit HASH]
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
from _common import DIST, NODIST, TRIALS, imufusion_ahrs, load_scorer  # noqa: E402
from _common import TYREX as DATA  # noqa: E402
from _common import write_section as _write_section  # noqa: E402

SECTION = "## Heading accuracy (issue 4)"
#: best column of ../shared/benchmarks/PEERS.md (mean heading error, deg)
PEERS_BEST = {"dist": 10.6, "nodist": 2.3}
PEERS = (
    "os",
    "imufusion_cal",
    "vqf_cal",
    "madgwick_cal",
    "mahony_cal",
    "imufusion_cal_gcal",
    "vqf_cal_gcal",
    "madgwick_cal_gcal",
)


def day_calibration(name: str, field):
    """The day's calibration, as ``pdr-mag calibrate`` makes it."""
    from pdr_mag.calibration import calibrate
    from pdr_mag.calibration.alignment import quasi_static_accel
    from replay.formats import read_recording

    rec = read_recording(DATA / name)
    accel = quasi_static_accel(rec.accel.t, rec.accel.xyz, rec.mag.t)
    return calibrate(rec.mag.xyz, method="auto", accel=accel, field=field)


def merged(rec, mag_cal):
    kind = np.concatenate(
        [np.zeros(len(rec.accel.t)), np.ones(len(rec.gyro.t)), np.full(len(rec.mag.t), 2)]
    ).astype(np.int8)
    t = np.concatenate([rec.accel.t, rec.gyro.t, rec.mag.t])
    xyz = np.concatenate([rec.accel.xyz, rec.gyro.xyz, mag_cal])
    order = np.argsort(t, kind="stable")
    return kind[order], t[order], xyz[order]


def run_core(rec, cal, field):
    from pdr_mag.attitude import FusionCore

    core = FusionCore(field=field)
    core.set_reference_strength(cal.field_uT)
    kind, t, xyz = merged(rec, cal.apply(rec.mag.xyz))
    return core.process(kind, t, xyz)


def on_gyro_grid(rec, mag_cal):
    """Accelerometer interpolated and the latest magnetometer sample at the gyroscope's times."""
    tg = rec.gyro.t
    acc = np.column_stack([np.interp(tg, rec.accel.t, rec.accel.xyz[:, k]) for k in range(3)])
    j = np.clip(np.searchsorted(rec.mag.t, tg, side="right") - 1, 0, len(rec.mag.t) - 1)
    return tg, rec.gyro.xyz, acc, mag_cal[j]


def _to_true(q_wxyz, declination_deg, pre_yaw_deg=0.0):
    r = Rotation.from_quat(np.asarray(q_wxyz)[:, [1, 2, 3, 0]])
    r = Rotation.from_euler("z", pre_yaw_deg - declination_deg, degrees=True) * r
    q = r.as_quat()[:, [3, 0, 1, 2]]
    return q


def run_imufusion(tg, gyr, acc, mag):
    ahrs = imufusion_ahrs((len(tg) - 1) / (tg[-1] - tg[0]))
    gd = np.degrees(gyr)
    ag = acc / 9.80665
    q = np.empty((len(tg), 4))
    for i in range(len(tg)):
        ahrs.update(gd[i], ag[i], mag[i])
        q[i] = ahrs.get_quaternion()
    return q


def run_vqf(tg, gyr, acc, mag):
    from vqf import VQF

    dt = (tg[-1] - tg[0]) / (len(tg) - 1)
    v = VQF(dt)
    out = v.updateBatch(np.ascontiguousarray(gyr), np.ascontiguousarray(acc), np.ascontiguousarray(mag))
    return out["quat9D"]


def run_madgwick(tg, gyr, acc, mag):
    from ahrs.filters import Madgwick

    fs = (len(tg) - 1) / (tg[-1] - tg[0])
    return Madgwick(gyr=gyr, acc=acc, mag=mag, frequency=fs, gain=0.041).Q


def run_mahony(tg, gyr, acc, mag):
    from ahrs.filters import Mahony

    fs = (len(tg) - 1) / (tg[-1] - tg[0])
    return Mahony(gyr=gyr, acc=acc, mag=mag, frequency=fs).Q


#: why pdr_mag_pipe once trailed pdr_mag (static record; the table is the current code)
PIPE_NOTE = (
    "Pipeline = core (after fa66245; before: Thibaud_iPhone5_NoDist_Texting 3.0° pipe vs 1.7° core,"
    " NoDist 2.4° vs 2.0°). Cause: the stale-calibration test of the online calibrator requested a"
    " recalibration at 40.5 s and replaced the given calibration by a gravity-aided refit (offset shift"
    " (−2.5, −3.4, +7.1) µT, mostly along the walk's mean up vector). On that walk |m_cal| is 38.6 µT with"
    " the file's calibration against the WMM's 47.1 µT (the file's radius 46.6 µT): the building's vertical"
    " field is weaker. In a texting pose (device z ≈ up, yaw turns) a weaker local vertical field and an"
    " offset shift along the mean up vector ū look the same, and the stale test's fit held the local field"
    " within 3 µT / 3° of the WMM, so it read the building as a moved offset and put the shift's across-ū"
    " part (4.2 µT) into the horizontal field. Now a shift counts only where the data determine it with F"
    " and F sin I free (the alternative \"the local field differs\" gets its two unknowns): on this walk"
    " the free fit finds F 37–43 µT, sin I 0.81–0.86 (WMM 0.875) and a determined shift of ≈ 4.3 µT, below"
    " the 6-µT bound, so no request; a magnetised case (test: (15, −10, 8) µT) is still found."
)


# ---------------------------------------------------------------------------------------------- scoring
def score_est(score, trial_dir, t_est, q_est):
    from replay.formats import read_recording

    rec = read_recording(trial_dir)
    t_ref, q_ref = rec.truth
    ok = np.all(np.isfinite(q_ref), axis=1)
    t0, _ = score.truth_t0(str(trial_dir / "truth.csv"), t_ref)
    return score.score_arrays(t_ref[ok], q_ref[ok], np.asarray(t_est, float), np.asarray(q_est, float), t0)


def std_calibration(score, trial_dir, batch):
    """Counts of scored truth frames with |heading error| < 1σ and < 2σ of the reported std."""
    from replay.formats import read_recording

    rec = read_recording(trial_dir)
    t_ref, q_ref = rec.truth
    ok = np.all(np.isfinite(q_ref), axis=1)
    t_ref, q_ref = t_ref[ok], q_ref[ok]
    t0, _ = score.truth_t0(str(trial_dir / "truth.csv"), t_ref)
    w = (t_ref >= t0 + 5) & (t_ref <= t0 + 120) & (t_ref >= batch.t[0]) & (t_ref <= batch.t[-1])
    qi, _ = score.C.slerp_at(batch.t, batch.q_wd, t_ref[w])
    _, head, _ = score.error_angles(qi, q_ref[w])
    sd = np.interp(t_ref[w], batch.t, batch.heading_std_deg)
    a = np.abs(head)
    return int(np.sum(a < sd)), int(np.sum(a < 2 * sd)), int(len(a))


# ---------------------------------------------------------------------------------------------- run
def accuracy(with_pipeline: bool = True, verbose: bool = True):
    from pdr_mag.field import earth_field_from_meta
    from replay.formats import read_recording

    score = load_scorer()
    table: dict[str, dict[str, float]] = {}
    calib_counts = np.zeros(3, dtype=int)
    cal_cache: dict[str, object] = {}
    gyr_cache: dict[str, np.ndarray] = {}
    for trial in TRIALS:
        d = DATA / trial
        info = json.loads((d / "trial.json").read_text())
        rec = read_recording(d)
        field = earth_field_from_meta(rec.meta)
        if info["calib"] not in cal_cache:
            cal_cache[info["calib"]] = day_calibration(info["calib"], field)
        cal = cal_cache[info["calib"]]
        if info["calib_gyr"] not in gyr_cache:
            gyr_cache[info["calib_gyr"]] = read_recording(DATA / info["calib_gyr"]).gyro.xyz.mean(axis=0)
        goff = gyr_cache[info["calib_gyr"]]
        row: dict[str, float] = {}
        batch = run_core(rec, cal, field)
        row["pdr_mag"] = score_est(score, d, batch.t, batch.q_wd)["heading_err_mean"]
        calib_counts += np.array(std_calibration(score, d, batch))
        if with_pipeline:
            row["pdr_mag_pipe"] = _pipeline(score, d, rec, cal)
        # peers
        mag_cal = cal.apply(rec.mag.xyz) * (field.strength / cal.field_uT)
        tg, gyr, acc, mag = on_gyro_grid(rec, mag_cal)
        decl = field.declination_deg
        runners = {"imufusion": (run_imufusion, 0.0), "vqf": (run_vqf, 0.0), "madgwick": (run_madgwick, 90.0),
                   "mahony": (run_mahony, 0.0)}
        for name, (fn, pre_yaw) in runners.items():
            for suffix, g in (("_cal", gyr), ("_cal_gcal", gyr - goff)):
                col = name + suffix
                if col not in PEERS:
                    continue
                q = _to_true(fn(tg, g, acc, mag), decl, pre_yaw)
                row[col] = score_est(score, d, tg, q)["heading_err_mean"]
        os_t, os_q = _read_quat_csv(d / "os.csv")
        row["os"] = score_est(score, d, os_t, os_q)["heading_err_mean"]
        table[trial] = row
        if verbose:
            print(trial, " ".join(f"{k}={v:.2f}" for k, v in row.items()), flush=True)
    return table, calib_counts


def _pipeline(score, d, rec, cal) -> float:
    try:
        import tempfile

        from replay.run import CsvSink, replay
    except ImportError:
        return float("nan")
    with tempfile.TemporaryDirectory() as tmp:
        est = Path(tmp) / "est.csv"
        try:
            replay(rec, calibration=cal, sinks=[CsvSink(est)], progress=False)
        except Exception as exc:  # noqa: BLE001 - a broken pipeline must not hide the core's figures
            print(f"pipeline failed on {d.name}: {exc}", file=sys.stderr)
            return float("nan")
        t, q = _read_quat_csv(est)
    return score_est(score, d, t, q)["heading_err_mean"]


def _read_quat_csv(path):
    arr = np.genfromtxt(path, delimiter=",", names=True, dtype=None, encoding="utf-8")
    q = np.column_stack([arr[k] for k in ("qw", "qx", "qy", "qz")]).astype(float)
    return arr["t"].astype(float), q


def speed(trial: str = "Thibaud_Nexus5_NoDist_Texting", repeats: int = 3):
    """Samples per second of the fusion core and of imufusion's Ahrs on the same recording."""
    from pdr_mag.attitude import FusionCore
    from pdr_mag.field import earth_field_from_meta
    from replay.formats import read_recording

    rec = read_recording(DATA / trial)
    field = earth_field_from_meta(rec.meta)
    info = json.loads((DATA / trial / "trial.json").read_text())
    cal = day_calibration(info["calib"], field)
    mag_cal = cal.apply(rec.mag.xyz)
    n = len(rec.accel.t) + len(rec.gyro.t) + len(rec.mag.t)
    FusionCore(field=field).process(*merged(rec, mag_cal)[:3])  # compile / load the cache
    best_core = np.inf
    best_imu = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        core = FusionCore(field=field)
        core.set_reference_strength(cal.field_uT)
        core.process(*merged(rec, mag_cal))
        best_core = min(best_core, time.perf_counter() - t0)
        t0 = time.perf_counter()
        tg, gyr, acc, mag = on_gyro_grid(rec, mag_cal)
        run_imufusion(tg, gyr, acc, mag)
        best_imu = min(best_imu, time.perf_counter() - t0)
    return {"trial": trial, "samples": n, "core_per_s": n / best_core, "imufusion_per_s": n / best_imu,
            "ratio": best_imu / best_core}


# ---------------------------------------------------------------------------------------------- report
def markdown(table, calib_counts, spd, commit: str = "") -> str:
    pipe = ["pdr_mag_pipe"] if any("pdr_mag_pipe" in r for r in table.values()) else []
    cols = ["pdr_mag", *pipe, *PEERS]
    lines = [
        SECTION,
        "",
        "Mode (a): the day's magnetometer calibration (`calibrate`, as `pdr-mag calibrate` makes it) and"
        " nothing else; raw gyroscope. Measured by `python benchmarks/heading.py --write-results` — every"
        " column in the same run on the same inputs, scored with `../shared/benchmarks/tyrex/score.py` (mean"
        " |heading error|, degrees, 5–120 s). `pdr_mag` = `FusionCore` defaults; `pdr_mag_pipe` = the whole"
        " pipeline via `replay(REC, calibration=…)`; peers as in PEERS.md (`*_gcal`: also handed the day's"
        " gyro offset)." + (f" Commit measured: {commit}." if commit else ""),
        "",
        "| trial | " + " | ".join(cols) + " |",
        "|---|" + "---|" * len(cols),
    ]
    for trial in TRIALS:
        lines.append(f"| {trial} | " + " | ".join(_fmt(table[trial].get(c)) for c in cols) + " |")
    for label, group in (("Dist (4)", DIST), ("NoDist (3)", NODIST), ("all 7", TRIALS)):
        vals = [np.mean([table[t].get(c, np.nan) for t in group]) for c in cols]
        lines.append(f"| **mean, {label}** | " + " | ".join(_fmt(v) for v in vals) + " |")
    n1, n2, n = calib_counts
    groups = (("dist", DIST), ("nodist", NODIST))
    ours = {g: np.mean([table[t]["pdr_mag"] for t in grp]) for g, grp in groups}
    pipe_m = {g: np.mean([table[t].get("pdr_mag_pipe", np.nan) for t in grp]) for g, grp in groups}
    both = {g: f"{ours[g]:.2f}°" for g in ours}
    for g in both:
        if np.isfinite(pipe_m[g]):
            both[g] += f" (pipeline {pipe_m[g]:.2f}°)"
    lines += [
        "",
        f"Against PEERS.md's published bests (best column separately): disturbed {both['dist']} vs"
        f" {PEERS_BEST['dist']}° (vqf_cal_gcal), undisturbed {both['nodist']} vs {PEERS_BEST['nodist']}°"
        " (madgwick_cal_gcal). The peers above are re-run on this project's calibration (the same inputs as"
        " ours), so a few of their figures differ from PEERS.md, which used its own ellipsoid fit.",
        "",
        PIPE_NOTE,
        "",
        f"Honesty of `heading_std_deg` (pdr_mag, all scored frames of the 7 walks, n = {n}): truth within"
        f" 1σ in {n1 / n:.0%} of the frames, within 2σ in {n2 / n:.0%} (Gaussian: 68 % / 95 %).",
        "",
        f"Speed (same recording `{spd['trial']}`, {spd['samples']} sensor samples, same run, best of"
        f" several): fusion core {spd['core_per_s'] / 1e6:.2f} M samples/s, imufusion `Ahrs` (per-sample"
        f" Python calls) {spd['imufusion_per_s'] / 1e6:.3f} M samples/s — ratio **{spd['ratio']:.1f}×**.",
        "",
    ]
    return "\n".join(lines)


def _fmt(v) -> str:
    return "–" if v is None or not np.isfinite(v) else f"{v:.1f}"


def write_section(text: str) -> None:
    _write_section(SECTION, text)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--write-results", action="store_true", help=f"write the section '{SECTION}' of RESULTS.md"
    )
    ap.add_argument("--no-pipeline", action="store_true", help="skip the pdr_mag_pipe column")
    ap.add_argument("--speed-repeats", type=int, default=3)
    ap.add_argument("--commit", default="", help="commit to name in the section")
    args = ap.parse_args(argv)
    table, counts = accuracy(with_pipeline=not args.no_pipeline)
    spd = speed(repeats=args.speed_repeats)
    text = markdown(table, counts, spd, args.commit)
    print(text)
    if args.write_results:
        write_section(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
