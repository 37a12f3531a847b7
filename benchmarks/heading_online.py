"""Mode (b) accuracy: the pipeline with NO calibration given (online calibration only) on the tyrex walks.

Runs ``replay`` (the same code as ``pdr-mag replay REC --out-csv``) on each of the seven walks of
``../shared/datasets/tyrex-pdrcsv``, writes the estimate CSV and scores it with the shared scorer
(``../shared/benchmarks/tyrex/score.py``, which alone reads ``trial.json`` for the time window).  The
phone's own fusion (``os``) is scored in the same run from ``os.csv``.

Usage::

    python benchmarks/heading_online.py [--out DIR] [--markdown]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import ROOT, TRIALS, load_scorer  # noqa: E402
from _common import TYREX as DATA  # noqa: E402


def _score(score, trial_dir: Path, est_csv: Path) -> dict:
    truth = trial_dir / "truth.csv"
    arr = np.genfromtxt(truth, delimiter=",", names=True)
    est = np.genfromtxt(est_csv, delimiter=",", names=True, dtype=None, encoding="utf-8")
    t_ref = arr["t"]
    q_ref = np.column_stack([arr[k] for k in ("qw", "qx", "qy", "qz")])
    ok = np.all(np.isfinite(q_ref), axis=1)
    t0, _ = score.truth_t0(str(truth), t_ref)
    q_est = np.column_stack([est[k] for k in ("qw", "qx", "qy", "qz")]).astype(float)
    return score.score_arrays(t_ref[ok], q_ref[ok], est["t"].astype(float), q_est, t0)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "heading_online")
    ap.add_argument("--markdown", action="store_true", help="print the RESULTS.md table")
    args = ap.parse_args(argv)
    from replay.run import CsvSink, replay

    score = load_scorer()
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for trial in TRIALS:
        d = DATA / trial
        est = args.out / f"{trial}.csv"
        t_start = time.perf_counter()
        summary = replay(d, sinks=[CsvSink(est)], progress=False)
        elapsed = time.perf_counter() - t_start
        ours = _score(score, d, est)
        os_ = _score(score, d, d / "os.csv")
        first = next((e["t"] for e in summary["events"] if e["kind"] == "calibration_accepted"), None)
        rows.append(
            {
                "trial": trial,
                "dist": "_Dist_" in trial,
                "ours": ours["heading_err_mean"],
                "ours_p95": ours["heading_err_p95"],
                "ours_tilt": ours["tilt_err_mean"],
                "os": os_["heading_err_mean"],
                "first_cal_s": None if first is None else first - (summary.get("t_start") or 0.0),
                "recal_requests": sum(e["kind"] == "recalibration_requested" for e in summary["events"]),
                "final_cal_state": summary["cal_state"],
                "final_offset_uT": summary["calibrations"][-1]["offset_uT"]
                if summary["calibrations"]
                else None,
                "elapsed_s": elapsed,
            }
        )
        print(f"{trial:34s} ours {rows[-1]['ours']:6.1f}°  os {rows[-1]['os']:6.1f}°", file=sys.stderr)
    (args.out / "results.json").write_text(json.dumps(rows, indent=1) + "\n")
    table = [
        "| trial | os | pdr_mag online (b) | p95 | tilt | final cal_state |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        cells = [r["trial"], f"{r['os']:.1f}", f"**{r['ours']:.1f}**", f"{r['ours_p95']:.1f}"]
        cells += [f"{r['ours_tilt']:.1f}", r["final_cal_state"]]
        table.append("| " + " | ".join(cells) + " |")
    for label, sel in (("Dist (4)", True), ("NoDist (3)", False), ("all 7", None)):
        rr = [r for r in rows if sel is None or r["dist"] == sel]
        m = {k: np.mean([r[k] for r in rr]) for k in ("os", "ours", "ours_p95", "ours_tilt")}
        table.append(
            f"| **mean, {label}** | {m['os']:.1f} | **{m['ours']:.1f}** | {m['ours_p95']:.1f} "
            f"| {m['ours_tilt']:.1f} | |"
        )
    print("\n".join(table))
    return 0


if __name__ == "__main__":
    sys.exit(main())
