"""A building's own field: what the tyrex room's field does along a walk, the simulator with and without a
building like it, and what such a building does to the heading and to the online calibration.

The model-check workflow on one effect: the simulated walks' field is the Earth's and the steel's, the
recordings' turns a little everywhere; the missing effect is a building's own weak field
(:class:`pdr_mag.sim.building.BuildingField`); added, the gap shrinks.

1. **The field seen** (``--part field``).  For each walk the world-frame field ``B_i = R_i A (m_i − b_w)``
   (``R_i`` the truth attitude — the motion capture's, the simulation's —, ``A`` the soft iron of the day's
   ``pdr-mag calibrate`` or of the simulated phone, ``b_w`` the walk's own best constant offset, as
   ``field_truth.py``), after the first 5 s: the RMS of its east and north variation, and the structure
   function of its horizontal direction ``δ(ℓ)`` = robust RMS (√ median of squares) of the direction's
   increments over a lag ℓ.  ``δ`` at the shortest lag is the white part (sensor noise, the attitude's
   jitter), its rise with ℓ the building's turning: ``σ_c ≈ √((δ(16 s)² − δ(0.2 s)²) / 2)``.  The tyrex
   walks held in the hand (Texting, Phoning, AR) are the measure; in pockets, swinging and running the
   attitude's alignment and timing errors at fast rotation turn the field as much (listed, not used).
   Simulated: the ``walk`` scenario (texting pose) seeds 1–6 in buildings of RMS 0–1.6 µT, L 2–4 m.
2. **The heading in a building** (``--part heading``).  ``walk``, ``swing``, ``pocket`` × seeds 1–6 through
   :class:`~pdr_mag.pipeline.HeadingPipeline` with the simulation's site, mode a (the phone's exact
   calibration given) and mode b (online calibration only), frames after 20 s: mean |error|, RMS of
   error/σ, truth within 2σ, frames 45° off at σ ≤ 20°; and every accepted online calibration's offset
   error against its σ (``z`` per axis, the largest per fit): RMS of z and the fits more than 3σ off —
   against the fit's own σ (its acceptance's) and the σ the filter takes (with the unseen soft iron of an
   offset-only first fit, ``OnlineSettings.soft_iron_std``).

Usage::

    python benchmarks/building_field.py [--part field|heading|all] [--jobs N]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from field_truth import own_offset, walk_samples  # noqa: E402
from heading import DATA, day_files, discover_walks  # noqa: E402
from heading_sim import errors  # noqa: E402

LAGS_S = (0.2, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0)
HELD = ("Texting", "Phoning", "AR")
SEEDS = (1, 2, 3, 4, 5, 6)
#: buildings simulated: (horizontal RMS µT, correlation length m); (0, 0): none
FIELD_BUILDINGS = ((0.0, 0.0), (0.8, 3.0), (1.2, 2.0), (1.2, 3.0), (1.2, 4.0), (1.6, 3.0))
HEADING_BUILDINGS = ((0.0, 0.0), (0.8, 3.0), (1.2, 3.0), (1.6, 3.0))
T_SKIP_S = 20.0


def field_stats(t: np.ndarray, m: np.ndarray, rot: np.ndarray, soft: np.ndarray) -> dict:
    """Part 1's figures of one walk: ``t`` (N,) s, raw ``m`` (N, 3) µT, ``rot`` (N, 3, 3) device → world."""
    n = len(m)
    b_w, _ = own_offset(m, rot, soft)
    b = np.einsum("nij,nj->ni", rot, (m - b_w) @ soft.T)
    rms = np.sqrt(np.mean((b - b.mean(axis=0)) ** 2, axis=0))
    direction = np.degrees(np.arctan2(b[:, 0], b[:, 1]))
    sf = []
    for lag in LAGS_S:
        j = np.searchsorted(t, t + lag)
        ok = j < n
        d = (direction[j[ok]] - direction[ok] + 180.0) % 360.0 - 180.0
        sf.append(float(np.sqrt(np.median(d**2))))
    return {"rms_e": float(rms[0]), "rms_n": float(rms[1]), "sf": sf}


def tyrex_walk(job: tuple[str, str]) -> tuple[str, dict]:
    walk, cal_path = job
    cal, t, m, rot = walk_samples(walk, cal_path, skip_s=5.0)
    return walk, field_stats(t, m, rot, cal.soft_iron_array)


def _simulate(scenario: str, seed: int, building: tuple[float, float]):
    from pdr_mag.sim import simulate

    return simulate(scenario, seed=seed, building=building if building[0] > 0 else None)


def sim_walk(job: tuple[int, tuple[float, float]]) -> tuple[tuple, dict]:
    from scipy.spatial.transform import Rotation

    from pdr_mag.conventions import quat_slerp

    seed, building = job
    res = _simulate("walk", seed, building)
    t, m = res.mag
    keep = t > 5.0
    t, m = t[keep], m[keep]
    q = quat_slerp(*res.truth, t)
    rot = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()
    return building, field_stats(t, m, rot, np.asarray(res.model.value("soft_iron"), dtype=float))


def heading_case(job: tuple[str, int, tuple[float, float], str]) -> dict:
    from pdr_mag.pipeline import HeadingPipeline

    scenario, seed, building, mode = job
    res = _simulate(scenario, seed, building)
    given = res.model.ideal_calibration() if mode == "a" else None
    pipe = HeadingPipeline(calibration=given, meta=res.meta)
    b = pipe.run({k: getattr(res, k) for k in ("accel", "gyro", "mag")})
    head, _ = errors(b.t, b.q_wd, res.truth)
    k = b.t > b.t[0] + T_SKIP_S
    e, s = np.abs(head[k]), b.heading_std_deg[k]
    z, zf = [], []  # against the fit's σ, and the σ the filter takes (with the unseen soft iron)
    for t, cal in pipe.calibrations:
        sd = np.asarray(cal.offset_std_uT, dtype=float)
        if cal is not given and np.all(np.isfinite(sd)):
            err = np.abs(cal.offset_array - res.model.offset(t))
            z.append(float(np.max(err / sd)))
            zf.append(float(np.max(err / np.sqrt(np.diag(cal.offset_error_covariance)))))
    return {"job": job, "mean": float(e.mean()), "e": e, "s": s, "z": z, "zf": zf}


def field_table(ty: list, sims: list) -> list[str]:
    lines = ["| walks | n | RMS east / north, µT | δ(ℓ) at " + ", ".join(f"{v:g}" for v in LAGS_S)
             + " s, deg | σ_c, deg |", "| --- | ---: | --- | --- | ---: |"]  # fmt: skip

    def row(name, stats):
        e = np.median([s["rms_e"] for s in stats])
        n = np.median([s["rms_n"] for s in stats])
        sf = np.median([s["sf"] for s in stats], axis=0)
        sc = np.sqrt(max(sf[-1] ** 2 - sf[0] ** 2, 0.0) / 2.0)
        lines.append(f"| {name} | {len(stats)} | {e:.2f} / {n:.2f} | " + " ".join(f"{v:.2f}" for v in sf)
                     + f" | {sc:.1f} |")  # fmt: skip

    held = [s for w, s in ty if any(h in w for h in HELD) and "NoDist" in w]
    if held:
        row("tyrex NoDist, held in the hand (Texting, Phoning, AR)", held)
        for h in HELD:
            row(f"… {h}", [s for w, s in ty if h in w and "NoDist" in w])
        other = [s for w, s in ty if "NoDist" in w and not any(h in w for h in HELD)]
        row("tyrex NoDist, pockets, swinging, running (not used)", other)
    for bld in FIELD_BUILDINGS:
        name = "no building" if bld[0] == 0 else f"building {bld[0]:g} µT, {bld[1]:g} m"
        row(f"simulated walk, {name}", [s for b, s in sims if b == bld])
    return lines


def heading_table(cases: list) -> list[str]:
    lines = ["| building | mode | mean \\|error\\| (worst case) | RMS error/σ | within 2σ"
             " | 45° off at σ ≤ 20° | online fits: RMS z, > 3σ (the filter's σ) |",
             "| --- | --- | --- | ---: | ---: | ---: | --- |"]  # fmt: skip
    for bld in HEADING_BUILDINGS:
        for mode in ("a", "b"):
            g = [c for c in cases if c["job"][2] == bld and c["job"][3] == mode]
            e = np.concatenate([c["e"] for c in g])
            s = np.concatenate([c["s"] for c in g])
            means = np.array([c["mean"] for c in g])
            z = np.array([v for c in g for v in c["z"]])
            zf = np.array([v for c in g for v in c["zf"]])
            zs = "—"
            if len(z):
                zs = (f"{np.sqrt(np.mean(z**2)):.2f}, {int(np.sum(z > 3))} of {len(z)}"
                      f" ({np.sqrt(np.mean(zf**2)):.2f}, {int(np.sum(zf > 3))})")  # fmt: skip
            name = "none" if bld[0] == 0 else f"{bld[0]:g} µT, {bld[1]:g} m"
            ratio = np.sqrt(np.mean((e / s) ** 2))
            lines.append(
                f"| {name} | {mode} | {means.mean():.2f}° ({means.max():.1f}°) | {ratio:.2f}"
                f" | {100 * np.mean(e <= 2 * s):.1f} % | {int(np.sum((e > 45) & (s <= 20)))} | {zs} |"
            )
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--part", choices=("field", "heading", "all"), default="all")
    ap.add_argument("--jobs", type=int, default=2)
    a = ap.parse_args(argv)
    with ProcessPoolExecutor(a.jobs) as ex:
        if a.part in ("field", "all"):
            walks = [w for w in discover_walks(None) if "NoDist" in w]
            ty = []
            if walks:
                with tempfile.TemporaryDirectory() as tmp:
                    made = day_files(walks, ex, tmp)
                    ty = list(ex.map(tyrex_walk, [(w, made[w][0]) for w in walks]))
            else:
                print(f"no tyrex walks in {DATA}: the simulated rows only", file=sys.stderr)
            sims = list(ex.map(sim_walk, [(sd, b) for b in FIELD_BUILDINGS for sd in SEEDS]))
            print("\n".join(field_table(ty, sims)), "\n", flush=True)
        if a.part in ("heading", "all"):
            jobs = [(sc, sd, b, m) for m in ("a", "b") for b in HEADING_BUILDINGS
                    for sc in ("walk", "swing", "pocket") for sd in SEEDS]  # fmt: skip
            print("\n".join(heading_table(list(ex.map(heading_case, jobs)))))
    return 0


if __name__ == "__main__":
    sys.exit(main())
