"""Benchmark of ``pdr-mag diagnose`` (issues 6 and 11): simulated suites and the real recordings.

``--suite``: false alarms and detections on simulated recordings (:data:`CONTROLS`, :data:`HIDDEN`).
Controls have nothing missing (hard iron + white noise only) in several motions and lengths, 1–40 min;
the hidden-effect suite is two sets of 1.5–2.5-min recordings — 25 s of figure-8 calibration, then a
texting walk with turns, clocks that do not start at zero (10³ s and 1.7·10⁹ s, a phone's uptime and Unix
time) — each with one effect hidden (or none), at a typical and a weak strength.  Per recording: what
``diagnose`` names, the gap before and after, which candidates passed the fixed ΔBIC and gap rules but not
the recording's null, and the wall time.

``--pairs``: two hidden effects at once — every pair of six effects on calibration + walk recordings
(:data:`MIXED_PAIRS`), and walking only (:data:`WALK_PAIRS`: texting walks of 3–6 min with turns, each with a
real phone's gyro bias, :data:`REAL_GYRO_BIAS`).  Per hidden effect: named, reported not identifiable (the
verdict ``not_identifiable``, or ``partly_identifiable`` with the hidden value's part in the identifiable
directions below the smallest size worth naming: "not identifiable here"), or missed; extras and false
alarms on the controls; and whether the phone's gyro bias was named.  "Gap before" is the baseline's, or,
when the accelerometer named gyro_bias (its part of the bias is in the baseline's orientation from the
start), the final model's along the raw gyro if larger (:func:`_gap_before`).

Real recordings: the baseline gap (hard_iron + noise along the gyro + accelerometer orientation), the
missing effects in the order added with their key estimates, the final gap, how much it shrank, and the
wall time.  The tyrex recordings are also run in evaluation mode (``use_truth``: along the mocap
orientation), which separates what the sensor model misses from what the orientation estimate misses.
The sunsided breadboard gets its MPU6050 temperature channel (read here from ``mpu6050.csv``, since the
reader does not expose it yet), which enables the ``temperature_offset`` candidate.

    python benchmarks/diagnose.py --suite [--only SUBSTRING|cost] [--json OUT]   # ~15 min on 2 busy cores
    python benchmarks/diagnose.py --pairs [--only SUBSTRING] [--json OUT]        # ~15 min on 2 busy cores
    python benchmarks/diagnose.py [--json OUT] [--only SUBSTRING] [--no-truth] [--all-tyrex]
    python benchmarks/diagnose.py --synthetic                                  # one recording per effect

Prints Markdown tables (those in benchmarks/RESULTS.md, section "Diagnose (issues 6, 11, 21)").
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
DATA = (ROOT / ".." / "shared" / "datasets").resolve()


#: The tyrex recordings of the table: the seven walks the pipeline was tuned on and the magnetometer
#: calibrations of the same phones (``--all-tyrex``: every walk and calibration of the folder).
TYREX = (
    "Thibaud_Nexus5_Dist_FrontPocket", "Thibaud_Nexus5_Dist_Swinging", "Thibaud_Nexus5_Dist_Texting",
    "Thibaud_Nexus5_NoDist_Swinging", "Thibaud_Nexus5_NoDist_Texting", "Thibaud_iPhone5_Dist_Texting",
    "Thibaud_iPhone5_NoDist_Texting", "calib_mag_Nexus5_d1", "calib_mag_Nexus5_d2", "calib_mag_Nexus5_d3",
    "calib_mag_Nexus5_d4", "calib_mag_iPhone5_d3",
)


def recordings(all_tyrex: bool = False) -> list[tuple[str, Path]]:
    out = []
    ty = DATA / "tyrex-pdrcsv"
    for name in sorted(p.name for p in ty.iterdir()) if ty.is_dir() else []:
        if name.startswith("calib_gyr"):
            continue  # static gyro calibrations: no rotation, nothing for the model check to see
        if all_tyrex or name in TYREX:
            out.append((f"tyrex/{name}", ty / name))
    ss = DATA / "sunsided-marg" / "set-2"
    for name in sorted(p.name for p in ss.iterdir()) if ss.is_dir() else []:
        out.append((f"sunsided/{name}", ss / name))
    br = DATA / "broad" / "data_mat"
    for p in sorted(br.glob("*.mat")) if br.is_dir() else []:
        out.append((f"broad/{p.stem}", p))
    xio = DATA / "xio-fusion" / "sensor_data.csv"
    if xio.exists():
        out.append(("xio/sensor_data", xio))
    ms = DATA / "ms-indoor-location-2020" / "site1"
    for p in sorted(ms.glob("*/path_data_files/*.txt")) if ms.is_dir() else []:
        out.append((f"msindoor/{p.parent.parent.name}/{p.stem[:8]}", p))
    return out


def sunsided_temperature(path: Path):
    f = path / "mpu6050.csv"
    if not f.exists():
        return None
    a = np.genfromtxt(f, delimiter=",", names=True)
    names = a.dtype.names
    return np.asarray(a[names[0]], float), np.asarray(a["temp_C"], float)


def _key_estimate(name: str, est: dict) -> str:
    if name == "time_offset":
        return f"{est['seconds'] * 1000:.0f} ms"
    if name == "gyro_bias":
        return "|b| " + f"{np.linalg.norm(est['rad_per_s']):.3f} rad/s"
    if name == "soft_iron":
        return f"axis ratio {est['axis_ratio']:.3f}"
    if name == "mag_imu_misalignment":
        return f"{est['degrees']:.1f}°"
    if name == "bias_drift":
        return f"{np.linalg.norm(est['uT_per_min']):.1f} µT/min"
    if name in ("local_anomaly", "hard_iron_change"):
        amb = ", ambiguous" if est.get("ambiguous") else ""
        return f"peak {est['uT']:.0f} µT, {est['share'] * 100:.0f} % of time{amb}"
    if name == "temperature_offset":
        return f"{np.linalg.norm(est['uT_per_degC']):.2f} µT/°C"
    return ""


def run_one(label: str, path: Path, use_truth: bool) -> dict:
    from pdr_mag.modelcheck import diagnose
    from replay.formats import read_recording

    rec = read_recording(path)
    temp = sunsided_temperature(path) if label.startswith("sunsided/") else None
    if temp is not None and len(rec.gyro) and abs(temp[0][0] - rec.gyro.t[0]) > 1.0:
        temp = None  # the reader re-timed the stream: do not guess the alignment
    t0, c0 = time.perf_counter(), time.process_time()
    d = diagnose(rec.mag.t, rec.mag.xyz, rec.gyro.t, rec.gyro.xyz, rec.accel.t, rec.accel.xyz,
                 truth=rec.truth, use_truth=use_truth, temperature=temp)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    out = d.to_dict()
    out["wall_s"] = wall
    out["cpu_s"] = cpu
    out["label"] = label
    out["temperature"] = temp is not None
    return out


SYNTHETIC = (
    # (label, scenario, duration, hidden effect, value, how to read the estimate)
    ("control", "figure8", 40.0, None, None),
    ("control", "walk", 40.0, None, None),
    ("time_offset", "figure8", 40.0, "time_offset", 0.04),
    ("mag_imu_misalignment", "figure8", 40.0, "mag_imu_misalignment", (3.0, -2.0, 1.5)),
    ("soft_iron", "figure8", 40.0, "soft_iron",
     ((1.08, 0.03, -0.02), (0.03, 0.94, 0.02), (-0.02, 0.02, 1.0))),
    ("bias_drift", "figure8", 40.0, "bias_drift", (6.0, -4.0, 3.0)),
    ("gyro_bias", "walk", 40.0, "gyro_bias", (0.0, 0.0, 0.03)),
    ("local_anomaly", "mixed", 50.0, "local_anomaly", 30.0),
    ("noise", "figure8", 30.0, "noise", 2.0),
)


def _synthetic_estimate(name, est):
    if name == "time_offset":
        return f"{est['seconds']:.4f} ± {est['std']:.4f} s"
    if name == "mag_imu_misalignment":
        return f"({', '.join(f'{v:.2f}' for v in est['rotvec_deg'])}) ± {max(est['std_deg']):.2f}°"
    if name == "soft_iron":
        m = np.asarray(est["matrix"])
        return f"diag ({', '.join(f'{v:.3f}' for v in np.diag(m))}) ± {est['std']:.3f} (det 1)"
    if name == "bias_drift":
        return f"({', '.join(f'{v:.2f}' for v in est['uT_per_min'])}) ± {max(est['std']):.2f} µT/min"
    if name == "gyro_bias":
        return f"along up {est['along_up_rad_per_s']:.4f} ± {est['along_up_std']:.4f} rad/s"
    if name == "local_anomaly":
        return f"peak {est['uT']:.1f} µT at {est['t_peak']:.0f} s"
    return ""


def synthetic() -> None:
    from pdr_mag.modelcheck import diagnose
    from pdr_mag.sim import simulate

    print("| hidden effect | scenario | true value | found (in order) | estimate ± 1σ | baseline gap (µT) "
          "| final gap (µT) | score | time (s) |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for label, scen, dur, eff, val in SYNTHETIC:
        effects = {"hard_iron": (22.0, -31.0, 48.0), "noise": 0.4}
        if eff is not None:
            effects[eff] = val
        r = simulate(scen, seed=3, duration_s=dur, effects=effects, defaults=False)
        t0 = time.perf_counter()
        d = diagnose(*r.mag, *r.gyro, *r.accel)
        wall = time.perf_counter() - t0
        dd = d.to_dict()
        found = ", ".join(d.missing_effects) or "null"
        first = d.missing_effect
        est = _synthetic_estimate(first, dd["final"]["estimate"].get(first, {})) if first else ""
        if label == "noise":
            est = "σ " + ", ".join(f"{v:.2f}" for v in dd["baseline"]["estimate"]["noise"]["uT"]) + " µT"
        score = next((c["score"] for c in dd["candidates"] if c["effect"] == first), None)
        sval = "—" if val is None else (np.round(np.asarray(val, float), 3).tolist() if np.ndim(val) < 2
                                         else "diag " + str(np.round(np.diag(val), 3).tolist()))
        print(f"| {label} | {scen} {dur:.0f} s | {sval} | {found} | {est} | {d.baseline.gap:.2f} "
              f"| {d.final.gap:.2f} | {score if score is not None else '—'} | {wall:.1f} |", flush=True)


# ---------------------------------------------------------------------------------------------- suites

HARD_IRON = (22.0, -31.0, 48.0)
NOISE = 0.4
SOFT = ((1.08, 0.03, -0.02), (0.03, 0.94, 0.02), (-0.02, 0.02, 1.0))
SOFT_WEAK = ((1.04, 0.015, -0.01), (0.015, 0.97, 0.01), (-0.01, 0.01, 1.0))

#: Controls: (scenario, duration s, seed, clock offset s); nothing hidden (mixed and chain without steel).
CONTROLS = (
    ("mixed", 90.0, 101, 1000.0),
    ("mixed", 120.0, 102, 1.7e9),
    ("mixed", 150.0, 103, 1000.0),
    ("mixed", 135.0, 104, 1.7e9),
    ("walk", 60.0, 105, 0.0),
    ("figure8", 60.0, 106, 500.0),
    ("swing", 120.0, 107, 0.0),
    ("swing", 180.0, 3, 0.0),
    ("pocket", 120.0, 108, 2000.0),
    ("pocket", 180.0, 3, 0.0),
    ("chain", 180.0, 109, 0.0),
    ("walk", 600.0, 110, 1.7e9),
    ("swing", 600.0, 111, 0.0),
    ("pocket", 1200.0, 112, 0.0),
    ("mixed", 2400.0, 113, 1.7e9),
)

#: Hidden effects (label, effect, value), each in two suites of calibration + texting walk recordings.
HIDDEN = (
    ("time_offset 40 ms", "time_offset", 0.04),
    ("time_offset 15 ms", "time_offset", 0.015),
    ("misalignment 3.9°", "mag_imu_misalignment", (3.0, -2.0, 1.5)),
    ("misalignment 2.0°", "mag_imu_misalignment", (1.5, -1.0, 0.8)),
    ("soft_iron ratio 1.15", "soft_iron", SOFT),
    ("soft_iron ratio 1.08", "soft_iron", SOFT_WEAK),
    ("bias_drift 7.8 µT/min", "bias_drift", (6.0, -4.0, 3.0)),
    ("bias_drift 1.2 µT/min", "bias_drift", (0.7, -0.7, 0.7)),
    ("gyro_bias 1.1 °/s", "gyro_bias", (0.01047, -0.01396, 0.00873)),
    ("gyro_bias 0.3 °/s", "gyro_bias", (0.0, 0.0, 0.005)),
    ("local_anomaly 30 µT", "local_anomaly", 30.0),
    ("local_anomaly 15 µT", "local_anomaly", 15.0),
    ("noise 1.5 µT (in the baseline)", "noise", 1.5),
    ("control", None, None),
    ("control", None, None),
)
#: The two hidden-effect suites: (first seed, clock offset s).
SUITES = ((201, 1000.0), (301, 1.7e9))

#: What the null costs: (scenario, duration s, seed, effect, value), each run with and without the null.
COST = (
    ("mixed", 120.0, 401, "soft_iron", SOFT_WEAK),
    ("mixed", 120.0, 402, "local_anomaly", 15.0),
    ("mixed", 600.0, 403, "soft_iron", SOFT_WEAK),
    ("mixed", 2400.0, 404, "soft_iron", SOFT_WEAK),
    ("mixed", 2400.0, 405, "local_anomaly", 15.0),
)


#: Gyro biases of real phones, rad/s: the median gyro of the tyrex static recordings (calib_gyr_Nexus5_d1,
#: calib_gyr_iPhone5_d3, calib_gyr_iPhone4S_d3 in ``../shared/datasets/tyrex-pdrcsv``; 21, 8 and 31 s, std
#: ≤ 0.004 rad/s per axis): 4.3, 6.1 and 0.5 °/s.
REAL_GYRO_BIAS = {
    "Nexus 5": (0.01181, 0.00017, 0.07463),
    "iPhone 5": (0.1035, -0.0219, 0.0197),
    "iPhone 4S": (-0.0088, -0.0012, 0.0009),
}
MISALIGN = (3.0, -2.0, 1.5)
DRIFT = (6.0, -4.0, 3.0)

#: Two hidden effects at once on calibration + texting walk recordings (1.5–2.5 min): every pair of the six
#: effects a recording can show, nothing else (no steel unless local_anomaly is one of the two).
_SIX = (("time_offset", 0.04), ("mag_imu_misalignment", MISALIGN), ("soft_iron", SOFT), ("bias_drift", DRIFT),
        ("gyro_bias", (0.01047, -0.01396, 0.00873)), ("local_anomaly", 30.0))
MIXED_PAIRS = tuple((a, b) for i, a in enumerate(_SIX) for b in _SIX[i + 1:])

#: Walking only (``walk``: 3 s standing, then a texting walk with turns every 8–20 s), 3–6 min, each with
#: a real phone's gyro bias (cycled through :data:`REAL_GYRO_BIAS`) and two hidden effects; the
#: misalignment with soft iron three times (the issue's unnamed pair).  ``None``: the walk's controls —
#: the phone's gyro bias alone, or nothing at all (``"none"``).
WALK_PAIRS = (
    (("time_offset", 0.04), ("soft_iron", SOFT)),
    (("mag_imu_misalignment", MISALIGN), ("soft_iron", SOFT)),
    (("mag_imu_misalignment", (-2.0, 2.5, 1.0)), ("soft_iron", SOFT_WEAK)),
    (("mag_imu_misalignment", (1.5, 1.5, -3.0)), ("soft_iron", SOFT)),
    (("time_offset", 0.04), ("bias_drift", DRIFT)),
    (("soft_iron", SOFT), ("bias_drift", DRIFT)),
    (("mag_imu_misalignment", MISALIGN), ("time_offset", 0.04)),
    (("mag_imu_misalignment", MISALIGN), ("bias_drift", DRIFT)),
    (("time_offset", 0.015), ("soft_iron", SOFT_WEAK)),
    (("bias_drift", (0.7, -0.7, 0.7)), ("time_offset", 0.04)),
    None, None, None, "none", "none",
)


def _suite_run(scenario, duration, seed, t0, effect=None, value=None, settings=None) -> dict:
    from pdr_mag.modelcheck import diagnose
    from pdr_mag.sim import simulate

    effects = {"hard_iron": HARD_IRON, "noise": NOISE}
    if effect is not None:
        effects[effect] = value
    r = simulate(scenario, seed=seed, duration_s=duration, effects=effects, defaults=False)
    def shift(stream):
        return stream[0] + t0, stream[1]

    w0, c0 = time.perf_counter(), time.process_time()
    d = diagnose(*shift(r.mag), *shift(r.gyro), *shift(r.accel), settings=settings)
    wall, cpu = time.perf_counter() - w0, time.process_time() - c0
    stopped = sorted({c.effect for rnd in d.rounds for c in rnd if c.null is not None and not c.null.passed})
    n_tested = sum(c.null is not None for rnd in d.rounds for c in rnd)
    return {"scenario": scenario, "duration_s": duration, "seed": seed, "t0": t0, "effect": effect,
            "found": list(d.missing_effects), "baseline_gap": d.baseline.gap, "gap_before": _gap_before(d),
            "final_gap": d.final.gap, "stopped_by_null": stopped, "n_tested": n_tested, "wall_s": wall,
            "cpu_s": cpu}


def _gap_before(d) -> float:
    """The gap before the missing effects: the baseline's, or — when the accelerometer named gyro_bias, its
    part of the bias being in the baseline's orientation from the start — the final model's along the raw
    gyro, if larger (for a gyro bias alone that is the baseline along the raw gyro)."""
    acc = d.gyro_bias_from_accelerometer
    if acc.get("named") and acc.get("gap_raw_gyro") is not None:
        return max(d.baseline.gap, acc["gap_raw_gyro"])
    return d.baseline.gap


def _pair_run(scenario, duration, seed, t0, hidden: dict, background: dict) -> dict:
    """One recording with ``hidden`` effects (scored) and ``background`` ones (a real phone's gyro bias):
    what ``diagnose`` names, and for each hidden effect it does not name, what it says of it."""
    from pdr_mag.modelcheck import diagnose
    from pdr_mag.sim import simulate

    effects = {"hard_iron": HARD_IRON, "noise": NOISE, **background, **hidden}
    r = simulate(scenario, seed=seed, duration_s=duration, effects=effects, defaults=False)

    def shift(stream):
        return stream[0] + t0, stream[1]

    w0, c0 = time.perf_counter(), time.process_time()
    d = diagnose(*shift(r.mag), *shift(r.gyro), *shift(r.accel))
    wall, cpu = time.perf_counter() - w0, time.process_time() - c0
    dd = d.to_dict()
    ident = dd.get("identifiability", {})
    found = list(d.missing_effects)
    status = {}
    for e, v in {**hidden, **background}.items():
        status[e] = "named" if e in found else ident.get(e, {}).get("status", "missed")
        if status[e] == "partly_identifiable" and _in_open_directions(e, v, ident[e]):
            status[e] = "not_identifiable_here"  # what was hidden lies where the motion cannot see
    return {"scenario": scenario, "duration_s": duration, "seed": seed, "t0": t0, "hidden": list(hidden),
            "background": list(background), "found": found, "status": status,
            "extra": [e for e in found if e not in hidden and e not in background],
            "not_identifiable": [e for e, v in ident.items() if v.get("status") == "not_identifiable"],
            "baseline_gap": d.baseline.gap, "gap_before": _gap_before(d), "final_gap": d.final.gap,
            "wall_s": wall, "cpu_s": cpu}


def _true_parameters(effect: str, value) -> np.ndarray:
    """A hidden effect's value in the fit's parameters (those of the identifiability directions)."""
    from scipy.linalg import logm

    if effect == "mag_imu_misalignment":
        return np.radians(np.asarray(value, float))
    if effect == "soft_iron":  # the value is the correction S; the fit's distortion is S⁻¹ = expm(E)
        e = np.real(logm(np.linalg.inv(np.asarray(value, float))))
        e = 0.5 * (e + e.T) - np.trace(e) / 3.0 * np.eye(3)
        return np.array([e[0, 0], e[1, 1], e[0, 1], e[0, 2], e[1, 2]])
    return np.atleast_1d(np.asarray(value, float))


def _in_open_directions(effect: str, value, verdict: dict) -> bool:
    """Whether a hidden effect that a partly identifiable verdict leaves unnamed lies in the directions the
    verdict calls not identifiable: its part in the identifiable ones is below the smallest size worth
    naming.  Otherwise it is a miss."""
    from pdr_mag.modelcheck.identify import SMALLEST

    theta = _true_parameters(effect, value)
    dirs = [np.asarray(x["vector"]) for x in verdict.get("directions", []) if x["identifiable"]]
    seen = sum(((v @ theta) * v for v in dirs), np.zeros_like(theta))
    return bool(np.linalg.norm(seen) < SMALLEST[effect])


def _pair_row(label: str, r: dict) -> str:
    def say(e):
        st = r["status"][e]
        return e if st == "named" else f"~~{e}~~ ({st.replace('_', ' ')})"

    hidden = ", ".join(say(e) for e in r["hidden"]) or "—"
    bg = ", ".join(say(e) for e in r["background"]) or "—"
    return (f"| {label} | {r['duration_s']:.0f} | {hidden} | {bg} | {', '.join(r['found']) or 'null'} "
            f"| {', '.join(r['extra']) or '—'} | {', '.join(r['not_identifiable']) or '—'} "
            f"| {r['gap_before']:.2f} → {r['final_gap']:.2f} | {r['wall_s']:.1f} / {r['cpu_s']:.1f} |")


def _pair_summary(name: str, rows: list[dict]) -> None:
    hid = [(r, e) for r in rows for e in r["hidden"]]
    named = sum(r["status"][e] == "named" for r, e in hid)
    unident = sum(r["status"][e] in ("not_identifiable", "not_identifiable_here") for r, e in hid)
    other = len(hid) - named - unident
    extra = sum(len(r["extra"]) for r in rows if r["hidden"])
    ctrl = [r for r in rows if not r["hidden"]]
    fa = sum(len(r["extra"]) for r in ctrl)
    bg = [(r, e) for r in rows for e in r["background"]]
    bg_named = sum(r["status"][e] == "named" for r, e in bg)
    print(f"\n{name}: hidden effects named {named} of {len(hid)}, reported not identifiable {unident}, "
          f"missed (not named, not reported) {other}; extra effects on recordings with hidden ones {extra}; "
          f"false alarms on the {len(ctrl)} controls {fa}; the phone's gyro bias named on {bg_named} of "
          f"{len(bg)}")


def pairs(only: str = "") -> list[dict]:
    """Two hidden effects at once: calibration + walk recordings (:data:`MIXED_PAIRS`) and walking-only
    recordings with a real phone's gyro bias (:data:`WALK_PAIRS`)."""
    head = ("| recording | s | hidden (struck: not named, and what diagnose says) | background | found "
            "(in order) | extra | reported not identifiable | gap before → after (µT) | wall / CPU (s) |")
    print("### Two hidden effects: calibration figure-8 + texting walk, 1.5–2.5 min\n")
    print(head)
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    mixed = []
    for i, pair in enumerate(MIXED_PAIRS):
        label = f"mixed {i + 1}"
        if only not in f"{label} {pair[0][0]} {pair[1][0]}":
            continue
        dur = 90.0 + 60.0 * ((5 * i) % 13) / 12.0
        r = _pair_run("mixed", dur, 501 + i, 1000.0 * (i % 2), dict(pair), {})
        r["label"] = label
        mixed.append(r)
        print(_pair_row(label, r), flush=True)
    if mixed:
        _pair_summary("mixed, two hidden", mixed)
    print("\n### Walking only: texting walks with turns, 3–6 min, a real phone's gyro bias\n")
    print(head)
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    walks = []
    phones = list(REAL_GYRO_BIAS)
    for i, pair in enumerate(WALK_PAIRS):
        phone = phones[i % len(phones)]
        hidden = {} if pair in (None, "none") else dict(pair)
        background = {} if pair == "none" else {"gyro_bias": REAL_GYRO_BIAS[phone]}
        label = f"walk {i + 1}" + ("" if pair == "none" else f" ({phone})")
        if only not in f"{label} {' '.join(hidden)} walk":
            continue
        dur = 180.0 + 180.0 * ((7 * i) % 11) / 10.0
        r = _pair_run("walk", dur, 601 + i, 1.7e9 * (i % 2), hidden, background)
        r["label"] = label
        walks.append(r)
        print(_pair_row(label, r), flush=True)
    if walks:
        _pair_summary("walking only, two hidden", walks)
    return mixed + walks


def suite(only: str = "") -> list[dict]:
    """Run the controls and the hidden-effect suites; print both tables and a summary."""
    out = []
    print("### Controls (nothing hidden)\n")
    print("| scenario | length | clock starts at (s) | found | gap (µT) | stopped by the null "
          "| wall / CPU (s) |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for scen, dur, seed, t0 in CONTROLS:
        if only not in f"control {scen}":
            continue
        r = _suite_run(scen, dur, seed, t0)  # no default effects: no steel in mixed and chain
        r["label"] = "control"
        out.append(r)
        print(f"| {scen} | {dur / 60:.0f} min | {t0:.3g} | {', '.join(r['found']) or 'null'} "
              f"| {r['baseline_gap']:.2f} | {', '.join(r['stopped_by_null']) or '—'} "
              f"| {r['wall_s']:.1f} / {r['cpu_s']:.1f} |", flush=True)
    print("\n### Hidden effects (calibration figure-8 + texting walk, 1.5–2.5 min)\n")
    print("| hidden | suite | length (s) | found (in order) | gap before → after (µT) | shrink "
          "| stopped by the null | wall / CPU (s) |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for k, (seed0, t0) in enumerate(SUITES):
        for i, (label, eff, val) in enumerate(HIDDEN):
            if only not in label:
                continue
            dur = 90.0 + 60.0 * ((7 * i + 3 * k) % 13) / 12.0
            r = _suite_run("mixed", dur, seed0 + i, t0, eff, val)  # steel only when it is the hidden effect
            r["label"] = label
            out.append(r)
            print(f"| {label} | {'AB'[k]} | {dur:.0f} | {', '.join(r['found']) or 'null'} "
                  f"| {r['gap_before']:.2f} → {r['final_gap']:.2f} "
                  f"| {r['gap_before'] / r['final_gap']:.2f}× | {', '.join(r['stopped_by_null']) or '—'} "
                  f"| {r['wall_s']:.1f} / {r['cpu_s']:.1f} |", flush=True)
    if out:
        _suite_summary(out)
    if not only or only == "cost":
        out += cost()
    return out


def cost() -> list[dict]:
    """Wall and CPU time of ``diagnose`` with and without the null on the recordings of :data:`COST`."""
    from pdr_mag.modelcheck import DiagnoseSettings, NullSettings

    print("\n### What the null costs\n")
    print("| hidden | length | found | candidates tested against the null | with the null: wall / CPU (s) "
          "| fixed rules alone: wall / CPU (s) |")
    print("| --- | --- | --- | --- | --- | --- |")
    rows = []
    off = DiagnoseSettings(null=NullSettings(replicates=0))
    for scen, dur, seed, eff, val in COST:
        r = _suite_run(scen, dur, seed, 0.0, eff, val)
        r0 = _suite_run(scen, dur, seed, 0.0, eff, val, settings=off)
        r.update(label="cost", wall_fixed_s=r0["wall_s"], cpu_fixed_s=r0["cpu_s"], found_fixed=r0["found"])
        rows.append(r)
        print(f"| {eff} | {dur / 60:.0f} min | {', '.join(r['found']) or 'null'} | {r['n_tested']} "
              f"| {r['wall_s']:.1f} / {r['cpu_s']:.1f} | {r0['wall_s']:.1f} / {r0['cpu_s']:.1f} |",
              flush=True)
    return rows


def _suite_summary(rows: list[dict]) -> None:
    nulls = [r for r in rows if r["effect"] in (None, "noise")]
    fa = [r for r in nulls if r["found"]]
    hid = [r for r in rows if r["effect"] not in (None, "noise")]
    named = [r for r in hid if r["found"][:1] == [r["effect"]]]
    extra = [r for r in named if len(r["found"]) > 1]
    shrink = [r["gap_before"] / r["final_gap"] for r in named]
    print(f"\nfalse alarms: {len(fa)} of {len(nulls)} recordings with nothing missing; "
          f"hidden effect named first: {len(named)} of {len(hid)} "
          f"(with an extra effect: {len(extra)}), gap shrink median "
          f"{np.median(shrink) if shrink else float('nan'):.2f}×")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", type=Path, help="write all results to this JSON file")
    ap.add_argument("--only", default="", help="only recordings whose label contains this")
    ap.add_argument("--no-truth", action="store_true", help="skip the evaluation-mode runs")
    ap.add_argument("--synthetic", action="store_true", help="the simulator table (each effect hidden)")
    ap.add_argument("--suite", action="store_true", help="controls and the hidden-effect suites")
    ap.add_argument("--pairs", action="store_true",
                    help="two hidden effects at once: calibration + walk, and walking only")
    ap.add_argument("--all-tyrex", action="store_true", help="every tyrex walk, not only those of the table")
    args = ap.parse_args()
    if args.synthetic:
        synthetic()
        return 0
    if args.suite or args.pairs:
        rows = suite(args.only) if args.suite else pairs(args.only)
        if args.json:
            args.json.write_text(json.dumps(rows, indent=1, ensure_ascii=False) + "\n", encoding="utf-8")
        return 0
    rows, results = [], []
    print("| recording | s | orientation | baseline gap (µT) | missing effects (in order; key estimate) "
          "| final gap (µT) | shrink | stopped by the null | wall / CPU (s) |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for label, path in recordings(args.all_tyrex):
        if args.only not in label:
            continue
        modes = [False]
        if label.startswith("tyrex/") and not args.no_truth and (path / "truth.csv").exists():
            modes.append(True)
        for use_truth in modes:
            try:
                r = run_one(label, path, use_truth)
            except Exception as exc:  # report and go on: a benchmark, not a test
                print(f"| {label} | | | failed: {type(exc).__name__}: {str(exc)[:80]} | | | | | |")
                continue
            results.append(r)
            fin = r["final"]["estimate"]
            eff = "; ".join(f"{e} ({_key_estimate(e, fin.get(e, {}))})" for e in r["missing_effects"])
            eff = eff or "none"
            orient = r["orientation"] + (" +T" if r["temperature"] else "")
            stopped = sorted({c["effect"] for rnd in r["rounds"] for c in rnd
                              if c.get("null") is not None and not c["null"]["passed"]})
            line = (f"| {label} | {r['duration_s']:.0f} | {orient} "
                    f"| {r['baseline']['gap']:.2f} | {eff} | {r['final']['gap']:.2f} "
                    f"| {r['baseline']['gap'] / r['final']['gap']:.1f}× | {', '.join(stopped) or '—'} "
                    f"| {r['wall_s']:.1f} / {r['cpu_s']:.1f} |")
            rows.append(line)
            print(line, flush=True)
    if args.json:
        args.json.write_text(json.dumps(results, indent=1, ensure_ascii=False) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
