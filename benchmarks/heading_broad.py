"""Heading on the BROAD trials in ``../shared/datasets/broad`` (a lab IMU with optical truth), no calibration.

BROAD (Laidig et al., *Data* 6(7):72, 2021) is not a phone, but it has what the tyrex walks lack: a
factory-calibrated magnetometer under a 70° dip (horizontal field ≈ 15 µT), slow rotations over every
orientation, a magnet fixed in the room, and a magnet attached to the board at 1 / 3 / 5 cm for part of
the trial (a temporary hard-iron change).  Each trial found there is replayed as ``pdr-mag replay`` would
(``replay.run.replay``) in mode a, given the factory calibration (offset 0, no soft iron: what the peers
are given), and mode b, no calibration (the online calibrator must find the factory offset, ≈ 1 µT); the
peers vqf and imufusion run on the same streams with the raw (factory-calibrated) magnetometer, fed as
``benchmarks/_peers.py`` feeds them.  The truth's north is the lab's magnetic north, as is ours without
a location and the peers'.

Heading error: the shared tyrex scorer's (the twist about up of ``q_est q_true⁻¹``, interpolated at the
truth's samples, NaN rows and gaps of more than 1 s between estimates left out), over the whole trial after
the first 5 s of our output (rest phases included: a heading must hold at rest too);
our honesty over the same frames: within 1σ / 2σ of ``heading_std_deg``, the share beyond 3σ, and frames
more than 45° off while σ ≤ 20°.

Usage::

    python benchmarks/heading_broad.py [--write-results] [--commit HASH]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import SHARED, load_scorer, write_section  # noqa: E402
from _peers import on_gyro_grid, run_imufusion, run_vqf  # noqa: E402
from heading import honesty  # noqa: E402

DATA = SHARED / "datasets" / "broad" / "data_mat"
SECTION = "## Heading on BROAD (a lab IMU with optical truth)"


def twist_deg(score, t_est, q_est, t_true, q_true) -> tuple[np.ndarray, np.ndarray]:
    """Signed heading error at the truth's times, deg, as the shared scorer measures it (``slerp_at`` and
    ``error_angles``; times outside the estimate's span or across a gap of more than 1 s between its rows
    left out), and the mask of the times kept."""
    qi, valid = score.C.slerp_at(t_est, q_est, t_true)
    idx = np.clip(np.searchsorted(t_est, t_true, side="right") - 1, 0, len(t_est) - 2)
    valid &= (t_est[idx + 1] - t_est[idx]) <= 1.0
    _, head, _ = score.error_angles(qi[valid], q_true[valid])
    return head, valid


def _ours(score, rec, tt, qt, calibration) -> tuple[dict, float]:
    """Replay with ``calibration`` (None: none given); the figures, and our first output time."""
    from pdr_mag.estimates import EstimateBatch
    from replay.run import MemorySink, replay

    sink = MemorySink()
    summary = replay(rec, calibration=calibration, sinks=[sink], progress=False)
    b = EstimateBatch.concat(sink.batches)
    err, kept = twist_deg(score, b.t, b.q_wd, tt, qt)
    ts = tt[kept]
    late = ts >= b.t[0] + 5.0
    err, ts = np.abs(err[late]), ts[late]
    h = honesty(err, np.interp(ts, b.t, b.heading_std_deg))
    n = max(h["n"], 1)
    return {
        "mean": float(np.mean(err)),
        "p95": float(np.percentile(err, 95)),
        "in1": h["within_1sigma"] / n,
        "in2": h["within_2sigma"] / n,
        "out3": h["beyond_3sigma"] / n,
        "kept_wrong": h["kept_wrong"],
        "recalibrations": sum(e["kind"] == "recalibrated" for e in summary["events"]),
    }, float(b.t[0])


def run_trial(path: Path) -> dict:
    from pdr_mag.calibration.model import MagCalibration
    from replay.formats import read_recording

    rec = read_recording(path)
    tt, qt = rec.truth
    ok = np.all(np.isfinite(qt), axis=1)
    tt, qt = tt[ok], qt[ok]
    score = load_scorer()
    row = {"trial": path.stem}
    row["b"], t_first = _ours(score, rec, tt, qt, None)
    # the factory calibration the peers are given: offset 0, no soft iron
    row["a"], _ = _ours(score, rec, tt, qt, MagCalibration.from_arrays([0.0, 0.0, 0.0], method="factory"))
    tg, gyr, acc, mag = on_gyro_grid(rec, rec.mag.xyz)
    for name, run in (("vqf", run_vqf), ("imufusion", run_imufusion)):
        q = run(tg, gyr, acc, mag)
        e, kept = twist_deg(score, tg, q, tt, qt)
        e = np.abs(e[tt[kept] >= t_first + 5.0])
        row[name] = float(np.mean(e))
    return row


def _cell(f: dict) -> str:
    return (f"{f['mean']:.1f} / {f['p95']:.1f} | {f['in1']:.0%} / {f['in2']:.0%} | {f['out3']:.0%}"
            f" | {f['kept_wrong']} | {f['recalibrations']}")


def table(rows: list[dict]) -> list[str]:
    head = ["trial"]
    for m in ("a", "b"):
        head += [f"{m}: mean / p95", f"{m}: ≤1σ / ≤2σ", f"{m}: >3σ", f"{m}: 45° kept", f"{m}: recal."]
    head += ["vqf", "imufusion"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        peers = f"{r['vqf']:.1f} | {r['imufusion']:.1f}"
        lines.append(f"| {r['trial']} | {_cell(r['a'])} | {_cell(r['b'])} | {peers} |")
    return lines


def reading(rows: list[dict]) -> list[str]:
    """One line of what the table says, counted from it."""
    n = len(rows)
    honest = {m: sum(r[m]["out3"] <= 0.10 for r in rows) for m in ("a", "b")}
    ahead = sum(r["a"]["mean"] < r["imufusion"] for r in rows)
    ahead_vqf = sum(r["a"]["mean"] < r["vqf"] for r in rows)
    worst = max(rows, key=lambda r: r["b"]["mean"])
    return [
        f"Mode a: at most 10 % of the frames beyond 3σ on {honest['a']} of {n} trials; below imufusion on"
        f" {ahead} and below vqf on {ahead_vqf} of {n}.  Mode b: {honest['b']} of {n} within that honesty"
        f" line; its worst trial is {worst['trial']} ({worst['b']['mean']:.1f}°).",
        "",
    ]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--write-results", action="store_true")
    ap.add_argument("--commit", default="")
    a = ap.parse_args(argv)
    trials = sorted(DATA.glob("*.mat"))
    if not trials:
        print(f"no BROAD trials in {DATA}", file=sys.stderr)
        return 2
    rows = [run_trial(p) for p in trials]
    text = "\n".join(
        [
            SECTION,
            "",
            f"`python benchmarks/heading_broad.py --write-results` ({len(rows)} trials"
            + (f", commit {a.commit}" if a.commit else "")
            + "): mean / 95th percentile of |heading error| against the optical truth after our first 5 s,"
            " deg; mode a given the factory calibration, b none; vqf and imufusion on the same streams with"
            " the factory-calibrated magnetometer; our `heading_std_deg` honesty over the same frames (≤1σ /"
            " ≤2σ, the share beyond 3σ, frames 45° off at σ ≤ 20°), and our recalibrations (see the script).",
            "",
            *table(rows),
            "",
            *reading(rows),
        ]
    )
    print(text)
    if a.write_results:
        write_section(SECTION, text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
