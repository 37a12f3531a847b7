"""Calibration benchmark (issues 2, 11): acceptance against the bound, accuracy against the Cramér–Rao
bound, noise bias, speed, real data.

    python benchmarks/calibration.py [--trials 200] [--write]
    python benchmarks/calibration.py --suite          # the acceptance suite only (≈ 20 s)

**Acceptance suite** (issue 11): seeded phone-like calibration recordings made with the project's
simulator (motions of ``pdr_mag.sim`` modes, ``pdr_mag.sim.sensor_model`` with hard iron, soft iron, noise,
the phone's resolution and clock; ``tests/_calibration_sim.phone_recording``): figure-8s, partial
figure-8s, screen-up motions (a hemisphere or less), near-planar rotations, yaw only, strong soft iron,
and disturbed ones (a steel dipole near the moving hand).  Each is judged against its own Cramér–Rao
bound turned into the worst-case heading error (``truth_heading_bound``): *determined* when that bound is
within the tolerance; a determined, undisturbed, plausible recording should be accepted, every other
refused — with a reason true to its cause (the field for a disturbed one, the undetermined heading for
one beyond the bound, the soft iron for an implausible one).  ``true error`` is the largest heading
error the accepted-or-not calibration makes on the true phone, over all poses.

For every method: offset RMSE / CRLB, offset bias, soft-iron shape error and bias at σ/F = 1, 3, 5 %
(N = 300 samples, full coverage; plus a hemisphere at 3 %), time per fit at 100 … 100 000 samples, and
a plain ``scipy.optimize.least_squares`` geometric fit (the per-sample directions as explicit unknowns,
finite-difference Jacobian with its sparsity pattern) as the reference peer in the same run.  ``--write``
replaces the ``## Calibration (issue 2)`` section of benchmarks/RESULTS.md (other sections untouched).
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from functools import partial
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT))

from _calibration_sim import (  # noqa: E402
    F_UT,
    phone_recording,
    sample,
    soft_iron_ellipsoid,
    true_heading_error_deg,
    truth_heading_bound,
)

from pdr_mag.calibration import (  # noqa: E402
    AcceptanceSettings,
    calibrate,
    crlb,
    fit_als,
    fit_ellipsoid,
    fit_lm9,
    fit_ml,
    fit_radial_newton,
    fit_sphere,
    fit_twostep,
    initial_ellipsoid,
)
from pdr_mag.calibration.geometry import (  # noqa: E402
    build_calibration,
    calibration_from_ellipsoid,
    sqrtm_spd,
    sym_basis,
    sym_coords,
)

SECTION = "## Calibration (issue 2)"


def fit_scipy_reference(mag: np.ndarray):
    """Plain geometric fit: unknowns (b, L, φ_i, λ_i), residuals m_i − b − L u(φ_i, λ_i), scipy TRF."""
    n = len(mag)
    b0, L0, _ = initial_ellipsoid(mag)
    u0 = np.linalg.solve(L0, (mag - b0).T).T
    u0 /= np.linalg.norm(u0, axis=1)[:, None]
    phi0 = np.arctan2(u0[:, 1], u0[:, 0])
    lam0 = np.arcsin(np.clip(u0[:, 2], -1, 1))
    basis = sym_basis("full")
    x0 = np.concatenate([b0, sym_coords(L0), phi0, lam0])

    def resid(x):
        b, L = x[:3], np.tensordot(x[3:9], basis, 1)
        phi, lam = x[9:9 + n], x[9 + n:]
        u = np.column_stack([np.cos(lam) * np.cos(phi), np.cos(lam) * np.sin(phi), np.sin(lam)])
        return (mag - b - u @ L.T).ravel()

    sp = lil_matrix((3 * n, 9 + 2 * n), dtype=int)
    sp[:, :9] = 1
    rows = np.arange(3 * n)
    sp[rows, 9 + rows // 3] = 1
    sp[rows, 9 + n + rows // 3] = 1
    res = least_squares(resid, x0, jac_sparsity=sp, method="trf", x_scale="jac", xtol=1e-10, ftol=1e-10)
    b, L = res.x[:3], sqrtm_spd(np.tensordot(res.x[3:9], basis, 1) @ np.tensordot(res.x[3:9], basis, 1))
    return build_calibration(mag, b, L, "scipy-ref", "full")


METHODS = {
    "sphere (LLS, seed 003)": fit_sphere,
    "twostep (seed 001 §2.3)": fit_twostep,
    "ellipsoid (seed 004 LS)": fit_ellipsoid,
    "als (seed 004 ALS)": fit_als,
    "ml (geometric)": fit_ml,
    "ml without curvature correction": partial(fit_ml, bias_correction=False),
    "radial (seed 000 Newton)": fit_radial_newton,
    "lm9 (seed 001 LM)": fit_lm9,
    "scipy least_squares geometric (ref)": fit_scipy_reference,
}


def accuracy(trials: int, n: int = 300, cover: str = "full", sig_fracs=(0.01, 0.03, 0.05), methods=None):
    rng = np.random.default_rng(2024)
    b, L = soft_iron_ellipsoid(rng, spread=0.15)
    a_true, _ = calibration_from_ellipsoid(L)
    _, xref = sample(rng, 100000, b, L, 0.0, cover)
    rows = []
    for sf in sig_fracs:
        sigma = sf * F_UT
        bound = np.sqrt(np.trace(crlb(xref, b, L, sigma)[:3, :3]) * 100000 / n)
        data = [sample(np.random.default_rng(10_000 * int(sf * 100) + k), n, b, L, sigma, cover)[0]
                for k in range(trials)]
        for name, fit in (methods or METHODS).items():
            eo, es, fails = [], [], 0
            for m in data:
                try:
                    cal = fit(m)
                except (ValueError, np.linalg.LinAlgError):
                    fails += 1
                    continue
                eo.append(cal.offset_array - b)
                es.append((cal.soft_iron_array - a_true).ravel())
            eo, es = np.array(eo), np.array(es)
            rmse = np.sqrt(np.mean(np.sum(eo**2, 1)))
            rows.append({"sigma": sf, "method": name, "rmse_crlb": rmse / bound, "crlb": bound,
                         "bias": np.linalg.norm(eo.mean(0)),
                         "bias_se": np.linalg.norm(eo.std(0)) / np.sqrt(len(eo)),
                         "median_crlb": np.median(np.linalg.norm(eo, axis=1)) / bound,
                         "shape_rms": np.sqrt(np.mean(np.sum(es**2, 1))),
                         "shape_bias": np.linalg.norm(es.mean(0)), "fails": fails})
    return rows


def timing(sizes=(100, 1000, 10000, 100000), scipy_max=10000, budget_s=1.0):
    rng = np.random.default_rng(7)
    b, L = soft_iron_ellipsoid(rng, spread=0.1)
    out = {}
    for n in sizes:
        m, _ = sample(rng, n, b, L, 0.02 * F_UT)
        entries = list(METHODS.items()) + [("calibrate(auto) incl. acceptance", lambda x: calibrate(x))]
        for name, fit in entries:
            if "scipy" in name and n > scipy_max:
                out[(name, n)] = None
                continue
            fit(m)  # warm-up
            ts = []
            t_end = time.perf_counter() + budget_s
            while len(ts) < 3 or (time.perf_counter() < t_end and len(ts) < 50):
                t0 = time.perf_counter()
                fit(m)
                ts.append(time.perf_counter() - t0)
            out[(name, n)] = float(np.median(ts))
    return out


def real_data():
    """``calibrate`` (auto, WMM from meta.json) on every tyrex-pdrcsv ``calib_mag_*`` recording."""
    from pdr_mag.field import earth_field_from_meta
    from replay.formats import read_recording

    base = ROOT / ".." / "shared" / "datasets" / "tyrex-pdrcsv"
    rows = []
    for d in sorted(base.glob("calib_mag_*")):
        rec = read_recording(d)
        wmm = earth_field_from_meta(rec.meta)
        cal = calibrate(rec.mag.xyz, field=wmm)
        fig = cal.extra["heading"]
        rows.append({"rec": d.name, "model": cal.extra.get("model", "-"), "n": cal.n_samples,
                     "field": cal.field_uT, "wmm": wmm.strength, "rms": cal.residual_rms_uT,
                     "coverage": cal.coverage, "accepted": cal.accepted,
                     "std": float(np.max(cal.offset_std_uT)),
                     "heading": fig["std_deg"], "white": fig["white_std_deg"],
                     "correlated": fig["correlated_std_deg"], "field_err": fig["field_error_deg"]})
    return rows


# (name, motion kind, phone_recording keywords); seeds are 1000 + the row index (--seed-base)
SUITE = [
    ("figure-8", "figure8", dict(duration_s=25, noise_uT=0.2, offset_norm_uT=10, soft_ratio=1.05)),
    ("figure-8", "figure8", dict(duration_s=20, noise_uT=0.6, offset_norm_uT=80, soft_ratio=1.2,
                                 site="singapore")),
    ("figure-8", "figure8", dict(duration_s=30, noise_uT=1.0, offset_norm_uT=150, soft_ratio=1.4,
                                 site="sao_paulo")),
    ("figure-8", "figure8", dict(duration_s=20, noise_uT=1.5, offset_norm_uT=300, soft_ratio=1.3,
                                 site="sydney")),
    ("partial figure-8", "figure8", dict(duration_s=30, noise_uT=0.3, offset_norm_uT=40, soft_ratio=1.1,
                                         amplitude=0.6)),
    ("partial figure-8", "figure8", dict(duration_s=30, noise_uT=0.8, offset_norm_uT=120, soft_ratio=1.3,
                                         amplitude=0.5)),
    ("partial figure-8", "figure8", dict(duration_s=20, noise_uT=1.2, offset_norm_uT=60, soft_ratio=1.2,
                                         amplitude=0.45, site="sydney")),
    ("partial figure-8", "figure8", dict(duration_s=30, noise_uT=0.5, offset_norm_uT=200, soft_ratio=1.3,
                                         amplitude=0.35)),
    ("screen up (hemisphere)", "screen_up", dict(duration_s=30, noise_uT=0.5, offset_norm_uT=100,
                                                 soft_ratio=1.2)),
    ("screen up (hemisphere)", "screen_up", dict(duration_s=30, noise_uT=0.4, offset_norm_uT=30,
                                                 soft_ratio=1.1, amplitude=0.8, site="singapore")),
    ("screen up (hemisphere)", "screen_up", dict(duration_s=30, noise_uT=0.8, offset_norm_uT=250,
                                                 soft_ratio=1.3, amplitude=0.6)),
    ("screen up (hemisphere)", "screen_up", dict(duration_s=10, noise_uT=1.5, offset_norm_uT=70,
                                                 soft_ratio=1.2, amplitude=0.5)),
    ("near-planar", "tumble", dict(duration_s=40, noise_uT=0.2, offset_norm_uT=50, soft_ratio=1.1,
                                   wobble_deg=9)),
    ("near-planar", "tumble", dict(duration_s=30, noise_uT=0.3, offset_norm_uT=20, soft_ratio=1.1,
                                   wobble_deg=8)),
    ("near-planar", "tumble", dict(duration_s=30, noise_uT=0.5, offset_norm_uT=90, soft_ratio=1.2,
                                   wobble_deg=5)),
    ("near-planar", "tumble", dict(duration_s=30, noise_uT=0.3, offset_norm_uT=60, soft_ratio=1.1,
                                   wobble_deg=3)),
    ("yaw only", "yaw", dict(duration_s=10, noise_uT=0.4, offset_norm_uT=50, soft_ratio=1.1, wobble_deg=2)),
    ("yaw only", "yaw", dict(duration_s=30, noise_uT=0.3, offset_norm_uT=120, soft_ratio=1.2, wobble_deg=4,
                             site="sao_paulo")),
    ("strong soft iron", "figure8", dict(duration_s=30, noise_uT=0.5, offset_norm_uT=150, soft_ratio=1.56)),
    ("strong soft iron", "figure8", dict(duration_s=30, noise_uT=0.6, offset_norm_uT=60, soft_ratio=1.6,
                                         amplitude=0.6)),
    ("implausible soft iron", "figure8", dict(duration_s=30, noise_uT=0.5, offset_norm_uT=80,
                                              soft_ratio=3.0)),
    ("disturbed", "figure8", dict(duration_s=25, noise_uT=0.4, offset_norm_uT=60, soft_ratio=1.1,
                                  disturbance_uT=6.0)),
    ("disturbed", "figure8", dict(duration_s=25, noise_uT=1.0, offset_norm_uT=100, soft_ratio=1.2,
                                  disturbance_uT=4.0, site="singapore")),
    ("disturbed", "figure8", dict(duration_s=25, noise_uT=0.3, offset_norm_uT=40, soft_ratio=1.1,
                                  disturbance_uT=3.0)),
    ("disturbed", "screen_up", dict(duration_s=30, noise_uT=0.5, offset_norm_uT=100, soft_ratio=1.2,
                                    disturbance_uT=5.0)),
]

#: Phrases of the refusal reasons, by cause (coverage.accept).
CAUSES = {"field": ("not constant", "residuals are correlated"), "undetermined": ("determine the heading",),
          "soft iron": ("eigenvalue spread",)}


def _causes(reasons) -> set[str]:
    return {c for c, keys in CAUSES.items() for r in reasons if any(k in r for k in keys)}


def acceptance_suite(settings: AcceptanceSettings | None = None, seed_base: int = 1000) -> list[dict]:
    """Every SUITE recording (seed ``seed_base`` + row): its bound, what it should get, what it got
    (module docstring)."""
    s = settings or AcceptanceSettings()
    rows = []
    for i, (name, kind, kw) in enumerate(SUITE):
        rec = phone_recording(kind, seed_base + i, **kw)
        hb, off = truth_heading_bound(rec)
        cal = calibrate(rec["mag"], field=rec["field"], settings=s)
        disturbed = kw.get("disturbance_uT", 0.0) > 0
        implausible = kw["soft_ratio"] > s.max_axis_ratio
        determined = hb.std_deg <= s.max_heading_std_deg
        should = "accept" if determined and not (disturbed or implausible) else "refuse"
        cause = ("field" if disturbed else "soft iron" if implausible else
                 "undetermined" if not determined else None)
        got = _causes(cal.reasons)
        fig = cal.extra.get("heading", {})
        d_true = np.asarray(hb.direction if hb.direction is not None else (np.nan,) * 3)
        d_est = np.asarray(fig.get("direction") or (np.nan,) * 3)
        rows.append({
            "name": name, "n": len(rec["mag"]), "noise": kw["noise_uT"], "offset": kw["offset_norm_uT"],
            "ratio": kw["soft_ratio"], "site": kw.get("site", "zurich"), "coverage": cal.coverage,
            "plane": cal.extra.get("out_of_plane_deg", np.nan), "cap": cal.extra.get("worst_cap_coverage"),
            "offset_bound": off, "bound": hb.std_deg, "estimate": fig.get("std_deg", np.nan),
            "true_error": true_heading_error_deg(rec, cal), "should": should,
            "got": "accept" if cal.accepted else "refuse", "cause": cause, "causes": sorted(got),
            "reason_true": (cal.accepted and should == "accept") or (
                not cal.accepted and (cause in got if cause else False) and got <= {cause}),
            "direction_cos": float(abs(d_true @ d_est)) if cause == "undetermined" else np.nan,
            "reasons": list(cal.reasons), "model": cal.extra.get("model")})
    return rows


def suite_summary(rows: list[dict]) -> dict:
    det = [r for r in rows if r["should"] == "accept"]
    return {"n": len(rows), "determined": len(det),
            "wrong_accepts": sum(r["got"] == "accept" and r["should"] == "refuse" for r in rows),
            "wrong_refusals": sum(r["got"] == "refuse" for r in det),
            "untrue_reasons": sum(r["got"] == "refuse" and not r["reason_true"] for r in rows)}


def render_suite(rows: list[dict], settings: AcceptanceSettings) -> list[str]:
    sm = suite_summary(rows)
    lines = [f"### Acceptance against the bound ({sm['n']} simulated calibration recordings)", "",
             f"Tolerance {settings.max_heading_std_deg:g}° (1-σ heading error, worst heading and pose); "
             f"**{sm['wrong_accepts']} wrong accepts, {sm['wrong_refusals']} wrong refusals of the "
             f"{sm['determined']} that should be accepted, {sm['untrue_reasons']} refusals for a reason not "
             f"their cause.**", "",
             "| recording | N | σ µT | offset µT | soft-iron ratio | coverage | out of plane ° | "
             "offset CRLB µT | bound ° | claimed ° | true error ° | should | got | reason |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        why = "—" if r["got"] == "accept" else ", ".join(r["causes"]) or "other"
        if r["cause"] == "undetermined" and r["got"] == "refuse" and np.isfinite(r["direction_cos"]):
            why += f" (direction cos {r['direction_cos']:.2f})"
        mark = "" if r["got"] == r["should"] and (r["got"] == "accept" or r["reason_true"]) else " ✗"
        lines.append(f"| {r['name']} | {r['n']} | {r['noise']:g} | {r['offset']:g} | {r['ratio']:g} | "
                     f"{r['coverage']:.0%} | {r['plane']:.1f} | {r['offset_bound']:.3f} | "
                     f"{_deg(r['bound'])} | {_deg(r['estimate'])} | {_deg(r['true_error'])} | "
                     f"{r['should']} | {r['got']}{mark} | {why} |")
    lines += ["", "bound: the recording's Cramér–Rao bound (full model, true noise) as the worst-case "
              "heading error; claimed: what `calibrate` derives from the samples; true error: the largest "
              "heading error of the fitted calibration on the true phone.  direction cos: absolute cosine "
              "between the undetermined direction named in the refusal and the bound's.", ""]
    return lines


def _deg(v: float) -> str:
    return "∞" if not np.isfinite(v) else f"{v:.0f}" if v >= 100 else f"{v:.2f}"


def render(acc, hemi, tim, real, trials, suite, seed_sets) -> str:
    s = AcceptanceSettings()
    lines = [SECTION, "",
             f"`python benchmarks/calibration.py --write` ({time.strftime('%Y-%m-%d')}, "
             f"{platform.processor() or platform.machine()}, Python {platform.python_version()}, "
             f"numpy {np.__version__}).", ""]
    lines += render_suite(suite, s)
    tot = {k: sum(sm[k] for sm in seed_sets) for k in seed_sets[0]}
    lines += [f"Same suite, seeds 1000, 2000, …, {1000 * len(seed_sets)} ({tot['n']} recordings): "
              f"{tot['wrong_accepts']} wrong accepts, {tot['wrong_refusals']} wrong refusals of "
              f"{tot['determined']}, {tot['untrue_reasons']} untrue reasons.", ""]
    lines += ["### Real calibration recordings (tyrex-pdrcsv `calib_mag_*`, method auto, WMM from "
              "meta.json)", "",
              "| recording | model | N | radius / WMM − 1 | residual RMS µT | coverage | heading ° (white / "
              "correlated / field) | accepted |",
              "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in real:
        lines.append(f"| {r['rec']} | {r['model']} | {r['n']} | {r['field'] / r['wmm'] - 1:+.1%} | "
                     f"{r['rms']:.2f} | {r['coverage']:.0%} | {r['heading']:.2f} ({r['white']:.2f} / "
                     f"{r['correlated']:.2f} / {r['field_err']:.2f}) | {'yes' if r['accepted'] else 'no'} |")
    lines += ["", f"### Accuracy against the Cramér–Rao bound (offset RMSE / CRLB, {trials} trials of "
              "N = 300; offset ±100 µT, soft iron I + 0.15·N(0,1), F = 50 µT)", "",
              "| method | σ/F 1 % | 3 % | 5 % | hemisphere 3 % | offset bias at hemisphere µT (se) |",
              "| --- | --- | --- | --- | --- | --- |"]
    for name in dict.fromkeys(r["method"] for r in acc):
        cells = [next(r for r in acc if r["method"] == name and r["sigma"] == sf)
                 for sf in (0.01, 0.03, 0.05)]
        h = next(r for r in hemi if r["method"] == name)
        lines.append(f"| {name} | " + " | ".join(f"{c['rmse_crlb']:.3f}" for c in cells)
                     + f" | {h['rmse_crlb']:.3f} | {h['bias']:.3f} ({h['bias_se']:.3f}) |")
    sizes = sorted({n for (_, n) in tim})
    lines += ["", "### Time per fit (median ms, full sphere, σ/F = 2 %, shared 2-core machine)", "",
              "| method | " + " | ".join(f"N = {n}" for n in sizes) + " |",
              "| --- | " + " | ".join("---" for _ in sizes) + " |"]
    for name in ("ml (geometric)", "als (seed 004 ALS)", "calibrate(auto) incl. acceptance",
                 "scipy least_squares geometric (ref)"):
        cells = ["—" if tim.get((name, n)) is None else f"{1e3 * tim[(name, n)]:.2f}" for n in sizes]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    lines.append("")
    return "\n".join(lines) + "\n"


def write_section(text: str) -> None:
    from _common import write_section as write

    write(SECTION, text)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=200)
    ap.add_argument("--write", action="store_true", help="update benchmarks/RESULTS.md")
    ap.add_argument("--suite", action="store_true", help="run and print the acceptance suite only")
    ap.add_argument("--seed-base", type=int, default=1000, help="seed of the suite's first recording")
    ap.add_argument("--seed-sets", type=int, default=4, help="seed sets summed in the suite's summary line")
    args = ap.parse_args()
    suite = acceptance_suite(seed_base=args.seed_base)
    if args.suite:
        print("\n".join(render_suite(suite, AcceptanceSettings())))
        for r in suite:
            if r["got"] == "refuse":
                print(f"- {r['name']} ({r['should']}): " + " | ".join(r["reasons"]))
        return
    seed_sets = [suite_summary(suite)] + [suite_summary(acceptance_suite(seed_base=1000 * k))
                                          for k in range(2, args.seed_sets + 1)]
    acc = accuracy(args.trials)
    hemi = accuracy(args.trials, cover="hemi", sig_fracs=(0.03,))
    tim = timing()
    real = real_data()
    text = render(acc, hemi, tim, real, args.trials, suite, seed_sets)
    print(text)
    if args.write:
        write_section(text)


if __name__ == "__main__":
    main()
