"""Robustness on simulated phones and effects unlike the shared data's: the pipeline as a new user runs it.

Every case is a :func:`pdr_mag.sim.simulate` recording (scenarios ``mixed``, ``walk``, ``pocket``, ``swing``,
``chain``, ``steel``; seeds 1–2) pushed through :class:`pdr_mag.pipeline.HeadingPipeline` with no calibration
given (mode b: online calibration from the recording's own samples) and the simulation's site (WMM).  Each row
changes one thing from the default phone (IMU 100 Hz, magnetometer 50 Hz) and the scenario's default effects:

phones (:data:`PHONES`)
    the magnetometer at 10 or 5 Hz (Android's ``SENSOR_DELAY_NORMAL``), everything at 25 Hz, a 0.6-µT
    magnetometer step (the AK09911's resolution), 4× the gyroscope and accelerometer noise, 5-ms / 20-ms clock
    jitter with 2 % drops and gaps up to 1 s, a ±2 g accelerometer, a ±500 °/s gyroscope;
effects (:data:`EFFECTS`)
    a 600-µT hard iron (an iPhone 4S's), a soft iron of 6 % (an iPhone 5's figure-8 fits) and of 15 %, 1.5-µT
    field noise, a 3 °/s gyroscope offset, an 80-ms magnetometer clock offset, a 3° magnetometer–IMU
    misalignment, a hard iron drifting 1 µT/min, a 15-µT anomaly along the path;
sites (:data:`SITES`)
    places whose field is unlike the shared data's (France, Hangzhou: 47–49 µT at a dip of 46–63°): near the
    magnetic pole (Reykjavik, dip 75°, the horizontal field a quarter of F), near the magnetic equator
    (Singapore, dip −13°), the South Atlantic Anomaly's weak field (São Paulo, 23 µT), the south (Sydney,
    dip −64°, 57 µT);
no place (:data:`NO_PLACE`)
    the default site and the four above with the recording's meta withheld (a logger without position or
    date: no reference field, F and the dip the calibration's own; headings against magnetic north);
jumps (:data:`JUMPS`)
    the hard iron jumping by 25 µT 60 s in (a case's magnet clasped; in a stream the OS calibrates, the OS
    replacing its estimate): the simulated raw field shifted from then on;
buildings (:data:`BUILDINGS`)
    a building's own weak field everywhere along the walk, on top of the scenarios' steel: the tyrex room's
    (about 1 µT at 3 m, benchmarks/NOTES.md "A building's own field") and twice it.

Metrics after the first 20 s of each case (twist about up of ``q_est q_true⁻¹``): the median and the mean
over the row's cases of each case's mean |heading error|, its worst case, the share of cases that reached a
full (ellipsoid) calibration, truth within 2σ (pooled frames) and the frames more than 45° off at σ ≤ 20°
(summed).  A case that raises is counted and named (none should).

Usage::

    python benchmarks/robustness.py [--write-results] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import write_section  # noqa: E402
from heading_sim import errors  # noqa: E402

from pdr_mag.sim.sensor_model import PhoneSpec  # noqa: E402

SECTION = "## Robustness on simulated phones and effects (issue 19)"
SCENARIOS = ("mixed", "walk", "pocket", "swing", "chain", "steel")
SEEDS = (1, 2)
#: the phones, each one change from the default
PHONES = {
    "default": PhoneSpec(),
    "mag 10 Hz": PhoneSpec(mag_rate_hz=10.0),
    "mag 5 Hz": PhoneSpec(mag_rate_hz=5.0),
    "all 25 Hz": PhoneSpec(accel_rate_hz=25.0, gyro_rate_hz=25.0, mag_rate_hz=25.0),
    "mag step 0.6 µT": PhoneSpec(mag_step=0.6),
    "IMU noise ×4": PhoneSpec(gyro_noise=0.006, accel_noise=0.05),
    "jitter, drops, gaps": PhoneSpec(imu_jitter_s=0.005, mag_jitter_s=0.02, drop_prob=0.02, gap_rate_hz=0.05,
                                     gap_max_s=1.0),  # fmt: skip
    "accel ±2 g": PhoneSpec(accel_range=2.0 * 9.80665),
    "gyro ±500 °/s": PhoneSpec(gyro_range=np.radians(500.0)),
}
#: the effects, each one change from the scenario's defaults (with the default phone)
EFFECTS = {
    "hard iron 600 µT": {"hard_iron": (85.0, 205.0, -550.0)},
    "soft iron 6 %": {"soft_iron": ((1.0, 0.04, 0.03), (0.04, 1.06, -0.02), (0.03, -0.02, 0.94))},
    "soft iron 15 %": {"soft_iron": ((1.15, 0.05, 0.0), (0.05, 0.88, 0.03), (0.0, 0.03, 1.0))},
    "field noise 1.5 µT": {"noise": 1.5},
    "gyro offset 3 °/s": {"gyro_bias": tuple(np.radians([2.0, -3.0, 2.5]))},
    "mag clock 80 ms late": {"time_offset": 0.08},
    "mag–IMU misalignment 3°": {"mag_imu_misalignment": (2.0, -2.0, 1.5)},
    "hard iron drift 1 µT/min": {"bias_drift": (1.0, -0.5, 0.8)},
    "anomaly 15 µT": {"local_anomaly": 15.0},
}
#: the places, each instead of the simulator's default site (Zurich: 48.4 µT, dip 63.5°)
SITES = {
    "site Reykjavik (dip 75°)": (64.13, -21.90),
    "site Singapore (dip −13°)": (1.35, 103.82),
    "site São Paulo (23 µT)": (-23.55, -46.63),
    "site Sydney (dip −64°)": (-33.87, 151.21),
}
#: the default site and :data:`SITES` with the meta withheld (no reference field), all in one row
NO_PLACE = "no place known (5 sites, meta withheld)"
#: the hard iron jumping mid-walk: (time after the start, s; the jump, µT), with the default phone and effects
JUMPS = {
    "hard iron jumps 25 µT at 60 s": (60.0, (15.0, -12.0, 16.0)),
}
#: a building's own field everywhere along the walk (``simulate(building=...)``: horizontal RMS µT, length m),
#: with the default phone, effects and site: the tyrex room's (about 1 µT, 3 m) and twice it
BUILDINGS = {
    "building's field 1.2 µT, 3 m": (1.2, 3.0),
    "building's field 2.4 µT, 3 m": (2.4, 3.0),
}
T_SKIP = 20.0
KEEP_STD, WRONG = 20.0, 45.0
#: the table's rows, in order
ROWS = [*PHONES, *EFFECTS, *SITES, NO_PLACE, *JUMPS, *BUILDINGS]


def run_case(args) -> dict:
    """One case: ``(row, scenario, seed, phone, effects, site)`` → its figures (or the error it raised);
    ``site``: a :data:`SITES` name, or None for the default site."""
    row, scenario, seed, phone, effects, site_name = args
    from dataclasses import replace

    from pdr_mag.pipeline import HeadingPipeline
    from pdr_mag.sim import DEFAULT_SITE, simulate

    out = {"row": row, "scenario": scenario, "seed": seed, "site": site_name}
    site = None
    if site_name is not None:
        lat, lon = SITES[site_name]
        site = {**DEFAULT_SITE, "latitude_deg": lat, "longitude_deg": lon, "altitude_m": 10.0}
    try:
        building = BUILDINGS.get(row)
        res = simulate(scenario, seed=seed, effects=effects, phone=phone, site=site, building=building)
        if row in JUMPS:
            t_jump, jump = JUMPS[row]
            t, xyz = res.mag
            res = replace(res, mag=(t, np.where((t >= t[0] + t_jump)[:, None], xyz + np.asarray(jump), xyz)))
        pipe = HeadingPipeline(meta={} if row == NO_PLACE else res.meta)
        b = pipe.run({k: getattr(res, k) for k in ("accel", "gyro", "mag")})
        head, _ = errors(b.t, b.q_wd, res.truth)
        if row == NO_PLACE:  # magnetic north: the declination is the place's
            head = (head - res.meta["simulation"]["declination_deg"] + 180.0) % 360.0 - 180.0
        k = b.t > b.t[0] + T_SKIP
        e, s = np.abs(head[k]), b.heading_std_deg[k]
        out.update(mean=float(np.mean(e)), n=int(k.sum()), within2=int(np.sum(e <= 2.0 * s)),
                   wrong_kept=int(np.sum((e > WRONG) & (s <= KEEP_STD))),
                   cal_state=pipe.cal_state)  # fmt: skip
    except Exception as exc:  # a case that raises is a finding, reported by name
        out["error"] = f"{type(exc).__name__}: {exc}"
    return out


def cases() -> list:
    rows = [(name, PHONES[name], {}, None) for name in PHONES]
    rows += [(name, PHONES["default"], eff, None) for name, eff in EFFECTS.items()]
    rows += [(name, PHONES["default"], {}, name) for name in SITES]
    rows += [(NO_PLACE, PHONES["default"], {}, site) for site in (None, *SITES)]
    rows += [(name, PHONES["default"], {}, None) for name in JUMPS]
    rows += [(name, PHONES["default"], {}, None) for name in BUILDINGS]
    return [
        (name, sc, seed, phone, eff, site)
        for name, phone, eff, site in rows
        for sc in SCENARIOS
        for seed in SEEDS
    ]


def _worst(results: list, row: str) -> dict | None:
    """The row's case of the largest mean error (None: every case raised)."""
    ok = [r for r in results if r["row"] == row and "error" not in r]
    return max(ok, key=lambda r: r["mean"], default=None)


def _where(case: dict, row: str) -> str:
    """The place of a :data:`NO_PLACE` case, for its row's worst case."""
    if row != NO_PLACE:
        return ""
    site = case.get("site")
    return ", Zurich" if site is None else ", " + site.split(" (")[0].removeprefix("site ")


def table(results: list) -> list[str]:
    lines = ["| phone or effect | cases | median / mean \\|error\\| | worst case | full calibration "
             "| within 2σ | frames > 45° at σ ≤ 20° | raised |",
             "| --- | ---: | ---: | --- | ---: | ---: | ---: | ---: |"]  # fmt: skip
    for name in ROWS:
        rs = [r for r in results if r["row"] == name]
        ok = [r for r in rs if "error" not in r]
        worst = _worst(results, name)
        means = [r["mean"] for r in ok]
        lines.append(
            f"| {name} | {len(rs)} | {np.median(means):.2f} / {np.mean(means):.2f}° "
            f"| {worst['mean']:.1f}° ({worst['scenario']} {worst['seed']}{_where(worst, name)}) "
            f"| {sum(r['cal_state'] == 'ellipsoid' for r in ok)} of {len(ok)} "
            f"| {100.0 * sum(r['within2'] for r in ok) / max(sum(r['n'] for r in ok), 1):.0f} % "
            f"| {sum(r['wrong_kept'] for r in ok)} | {len(rs) - len(ok)} |"
        )
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--write-results", action="store_true")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--commit", default="")
    a = ap.parse_args()
    t0 = time.perf_counter()
    with ProcessPoolExecutor(2) as ex:
        results = list(ex.map(run_case, cases()))
    wall = time.perf_counter() - t0
    for r in results:
        if "error" in r:
            print(f"raised: {r['row']} {r['scenario']} {r['seed']}: {r['error']}", file=sys.stderr)
    lines = table(results)
    print("\n".join(lines))
    print(f"{len(results)} cases in {wall:.0f} s on 2 processes", file=sys.stderr)
    if a.json:
        a.json.write_text(json.dumps(results, indent=1))
    if a.write_results:
        commit = f", commit {a.commit}" if a.commit else ""
        intro = (
            f"`python benchmarks/robustness.py --write-results` ({len(results)} simulated cases{commit}): "
            "the pipeline with no calibration given (online calibration only) on phones, effects and places "
            "the shared data do not have, one change per row from the default phone, the scenarios' default "
            "effects and the default site (Zurich: 48.4 µT, dip 63.5°); six scenarios × seeds 1–2 per row, "
            "after the first 20 s. Median / mean \\|error\\|: "
            "over the cases, of each case's mean \\|heading error\\|; full calibration: cases that reached "
            "an ellipsoid fit."
        )
        worst = [_worst(results, row) for row in ROWS]
        worst_cases = {(w["scenario"], w["seed"]) for w in worst if w is not None}
        if len(worst_cases) == 1:
            scenario, seed = worst_cases.pop()
            intro += f" The worst case of every row is `{scenario}` seed {seed} (benchmarks/NOTES.md: why)."
        write_section(SECTION, "\n".join([SECTION, "", intro, "", *lines, ""]))


if __name__ == "__main__":
    main()
