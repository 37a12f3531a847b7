"""The field each tyrex walk really saw: the magnetometer turned into the world frame by the mocap attitude.

What the heading filter has to assume — a constant Earth field of the World Magnetic Model's strength F and
inclination I, and one hard-iron offset for the walk — is measured here against the walks themselves.  For
every walk of ``../shared/datasets/tyrex-pdrcsv`` with the day's calibration (``pdr-mag calibrate`` on its
``calib_mag_*`` recording, as ``heading.py`` makes it), each magnetometer sample ``m_i`` is calibrated,
``y_i = A (m_i − b)``, and turned into the mocap (ENU) frame with the truth attitude ``R_i`` (the truth
frame at or after the sample, 60 Hz): ``B_i = R_i y_i``.  Per walk:

* the strength ``|B_i|`` and the inclination ``I_i = asin(−B_z / |B|)``: median and 10–90 % range, against
  the WMM of ``trial.json``;
* the declination ``atan2(B_x, B_y)`` (mocap north = the room's y axis, so only its spread is physical):
  its 10–90 % range, the heading error an ideal filter would see if it trusted every sample;
* the walk's own offset: the ``b_w`` (and constant field ``B̄``) minimising ``Σ |R_i A (m_i − b_w) − B̄|²``
  (linear least squares), and ``|b_w − b|`` against the day's offset — how far the best constant offset
  for this walk is from the day's calibration.

Usage::

    python benchmarks/field_truth.py [--walks PATTERN] [--jobs N] [--write-notes]

``--write-notes``: the summary table into ``benchmarks/NOTES.md`` (section "Field truth"), replacing the
whole section: the reading of the table written under it there goes too.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import ROOT, write_section  # noqa: E402
from heading import DATA, day_files, discover_walks, trial_info  # noqa: E402

NOTES = ROOT / "benchmarks" / "NOTES.md"
SECTION = "## Field truth: what the tyrex walks' field really was"


def walk_samples(walk: str, cal_path: str, skip_s: float = 0.0):
    """A walk's magnetometer under its truth: ``(cal, t, m, R)`` — the day's calibration, the samples' times
    (s) and raw fields (µT) from ``skip_s`` after the truth's start to its end, and the truth attitude at or
    after each (device → mocap ENU, (N, 3, 3))."""
    from scipy.spatial.transform import Rotation

    from pdr_mag import MagCalibration
    from replay.formats import read_recording

    cal = MagCalibration.from_json(cal_path)
    rec = read_recording(DATA / walk)
    tr, qr = rec.truth
    ok = np.all(np.isfinite(qr), axis=1)
    tr, qr = tr[ok], qr[ok]
    tm, m = rec.mag.t, rec.mag.xyz
    inside = (tm > tr[0] + skip_s) & (tm < tr[-1]) & np.all(np.isfinite(m), axis=1)
    tm, m = tm[inside], m[inside]
    q = qr[np.clip(np.searchsorted(tr, tm), 0, len(tr) - 1)]
    return cal, tm, m, Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()


def own_offset(m: np.ndarray, rot: np.ndarray, soft: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The walk's own constant offset ``b_w`` and field ``B̄``: ``R_i A m_i − R_i c − B̄ = 0`` in least
    squares, ``c = A b_w`` (raw ``m`` (N, 3) µT, ``rot`` (N, 3, 3) device → world, soft iron ``A``)."""
    n = len(m)
    jac = np.zeros((3 * n, 6))
    jac[:, :3] = rot.reshape(-1, 3)
    jac[:, 3:] = np.tile(np.eye(3), (n, 1))
    sol = np.linalg.lstsq(jac, np.einsum("nij,nj->ni", rot, m @ soft.T).reshape(-1), rcond=None)[0]
    return np.linalg.solve(soft, sol[:3]), sol[3:]


def walk_field(job: tuple[str, str]) -> dict:
    """The figures of the module docstring for one walk (``job``: walk name, day's calibration file)."""
    walk, cal_path = job
    cal, _, m, R = walk_samples(walk, cal_path)
    a = cal.soft_iron_array
    bw = np.einsum("nij,nj->ni", R, (m - cal.offset_array) @ a.T)
    f = np.linalg.norm(bw, axis=1)
    dip = np.degrees(np.arcsin(-bw[:, 2] / f))
    dec = np.degrees(np.arctan2(bw[:, 0], bw[:, 1]))
    dec = (dec - np.median(dec) + 180.0) % 360.0 - 180.0  # about its median: the spread, not the room's north
    b_walk, _ = own_offset(m, R, a)
    wmm = trial_info(walk)["wmm"]
    return {
        "walk": walk,
        "dist": "_Dist_" in walk,
        "F_wmm": wmm["F_uT"],
        "I_wmm": wmm["inclination_deg"],
        "F": np.percentile(f, [10, 50, 90]).tolist(),
        "I": np.percentile(dip, [10, 50, 90]).tolist(),
        "dec_spread": float(np.percentile(dec, 90) - np.percentile(dec, 10)),
        "offset_gap": float(np.linalg.norm(b_walk - cal.offset_array)),
    }


def run(walks: list[str], jobs: int) -> list[dict]:
    with tempfile.TemporaryDirectory() as tmp, ProcessPoolExecutor(jobs) as ex:
        made = day_files(walks, ex, tmp)
        return list(ex.map(walk_field, [(w, made[w][0]) for w in walks]))


def table(rows: list[dict]) -> list[str]:
    """One line per group (NoDist, Dist): medians over the walks of each figure, and its range."""
    out = [
        "| walks | n | \\|B\\| median (walk medians: range) | WMM F | dip median (range) | WMM I |"
        " declination spread p10–p90 (range) | \\|b_walk − b_day\\| (range) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, sel in (("NoDist", False), ("Dist", True)):
        g = [r for r in rows if r["dist"] == sel]
        if not g:
            continue
        fm = np.array([r["F"][1] for r in g])
        im = np.array([r["I"][1] for r in g])
        ds = np.array([r["dec_spread"] for r in g])
        og = np.array([r["offset_gap"] for r in g])
        rng = lambda v, d: f"{np.median(v):.{d}f} ({v.min():.{d}f}–{v.max():.{d}f})"  # noqa: E731
        out.append(
            f"| {name} | {len(g)} | {rng(fm, 1)} µT | {g[0]['F_wmm']:.1f} µT | {rng(im, 1)}°"
            f" | {g[0]['I_wmm']:.1f}° | {rng(ds, 0)}° | {rng(og, 1)} µT |"
        )
    return out


def write_notes(lines: list[str]) -> None:
    """Replace this script's section of ``benchmarks/NOTES.md`` (its heading, then ``lines``); the other
    sections are left as they are."""
    write_section(SECTION, "\n".join([SECTION, "", *lines, ""]), path=NOTES)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--walks", default=None, help="comma-separated globs on the walk names")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--write-notes", action="store_true")
    a = ap.parse_args(argv)
    walks = discover_walks(a.walks)
    if not walks:
        print(f"no walks found in {DATA}", file=sys.stderr)
        return 2
    rows = run(walks, a.jobs)
    for r in rows:
        print(
            f"{r['walk']:38s} |B| {r['F'][1]:5.1f} [{r['F'][0]:5.1f}, {r['F'][2]:6.1f}] dip {r['I'][1]:5.1f}"
            f" dec spread {r['dec_spread']:5.1f}  |b_walk − b_day| {r['offset_gap']:5.1f}"
        )
    lines = table(rows)
    print("\n".join(lines))
    if a.write_notes:
        write_notes(
            [
                f"`python benchmarks/field_truth.py --write-notes` ({len(rows)} walks; the method in the"
                " script's docstring): each walk's field seen through the mocap attitude and the day's"
                " calibration.",
                "",
                *lines,
            ]
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
