"""Heading accuracy on every tyrex walk: pdr_mag in modes (a) and (b) against the peers, in one run.

Walks: every folder of ``../shared/datasets/tyrex-pdrcsv`` whose ``trial.json`` says ``"kind": "trial"``
(found by listing).  ``trial.json`` is read here — never by the pipeline — for the day's calibration
recordings (``calib``, ``calib_gyr``), the groups (device, Dist/NoDist, motion) and, by the shared scorer,
the time alignment of the scoring window.

Columns, all in the same run on the same inputs:

``a``
    the whole :class:`~pdr_mag.pipeline.HeadingPipeline` through ``replay(REC, calibration=FILE)`` — the code
    of ``pdr-mag replay REC --calibration FILE`` — with FILE written by ``pdr-mag calibrate`` (the command
    itself, run in-process) on the day's ``calib_mag_*`` recording.  Each day's file is made once per run.
``b``
    the same pipeline with no calibration: online calibration only.
``core``
    :class:`~pdr_mag.fusion.FusionCore` alone with the same calibrated magnetometer (cheap; left out when
    the core's interface is not the one this script knows).
peers
    :mod:`_peers` (the columns of ``../shared/benchmarks/PEERS.md``), magnetometer calibrated with the
    same day's file scaled to the WMM strength; ``_gcal``: the day's gyro offset removed first.
``os``
    the phone's own fusion (``os.csv``).

Metric: the shared scorer ``../shared/benchmarks/tyrex/score.py`` (imported): mean |heading error| over
5–120 s of the mocap clock.  Honesty of ``heading_std_deg`` (modes a, b): over the same scored frames,
the share with |error| ≤ 1σ / ≤ 2σ (a Gaussian gives 68 / 95 %), the walks with more than 10 % of their
frames beyond 3σ, the frames more than 45° off with σ ≤ 20° (kept by a user filtering at 20°), the median
σ and the share of frames with σ > 20°.

Usage::

    python benchmarks/heading.py [--walks PATTERN] [--jobs N] [--json FILE] [--series DIR]
                                 [--peers-from FILE] [--no-core] [--check-peers] [--write-results]
                                 [--write-fixture]

``PATTERN``: comma-separated globs on the walk names (no wildcard: a substring).  ``--peers-from``: take the
peer and ``os`` figures from an earlier ``--json`` (or the test fixture) instead of running them (the peers
take most of the time: pure-Python ahrs filters).  ``--json FILE``: per walk and mode, the scorer's figures,
the frames within 2σ / beyond 3σ, the median σ, the longest time since a magnetometer update over the
scored frames (``mag_age_max_s``), events by kind, the final ``cal_state``, throughput; ``core``; the peers.
``--series DIR``: ``DIR/WALK.npz`` with the scored truth times (``t``, ``t_b``), the signed heading error
(``err_a``, ``err_b``), σ (``std_a``, ``std_b``) and the time since the last magnetometer update
(``mag_age_a``, ``mag_age_b``), deg and s.  ``--write-fixture``: the peers' figures per walk into
``tests/fixtures/tyrex_peers.json`` (the bounds of ``tests/test_real_walks.py``).
"""

from __future__ import annotations

import argparse
import contextlib
import fnmatch
import io
import json
import os
import re
import resource
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import ROOT, SHARED, TRIALS, load_scorer  # noqa: E402, F401  (TRIALS: other scripts)
from _common import TYREX as DATA  # noqa: E402
from _common import write_section as _write_section  # noqa: E402
from _peers import PEER_COLUMNS, _to_true, on_gyro_grid, run_imufusion, run_madgwick, run_vqf  # noqa: E402, F401

SECTION = "## Heading accuracy on the tyrex walks (issue 10)"
OLD_SECTIONS = ("## Heading accuracy (issue 4)",)
PEERS_MD = SHARED / "benchmarks" / "PEERS.md"
FIXTURE = ROOT / "tests" / "fixtures" / "tyrex_peers.json"
#: |heading error| limits counted as failures, deg (issue 10's targets: mode a none > 20°, mode b none > 45°)
FAIL = (20.0, 45.0)
#: a walk's std is dishonest when more than this share of its frames is beyond 3σ (issue 10)
BEYOND_3SIGMA_MAX = 0.10


# ---------------------------------------------------------------------------------------------- walks
def discover_walks(pattern: str | None = None) -> list[str]:
    """Names of the walks in ``DATA`` (``trial.json`` with ``kind == "trial"`` and a ``truth.csv``)."""
    names = []
    for d in sorted(DATA.iterdir()) if DATA.is_dir() else []:
        tj = d / "trial.json"
        if tj.is_file() and (d / "truth.csv").is_file() and json.loads(tj.read_text()).get("kind") == "trial":
            names.append(d.name)
    if pattern:
        pats = [p if any(c in p for c in "*?[") else f"*{p}*" for p in pattern.split(",") if p]
        names = [n for n in names if any(fnmatch.fnmatchcase(n, p) for p in pats)]
    return names


def trial_info(walk: str) -> dict:
    return json.loads((DATA / walk / "trial.json").read_text())


# ---------------------------------------------------------------------------------------------- day files
def make_day_files(job: tuple[str, str, str]) -> tuple[str, str, list[float]]:
    """``pdr-mag calibrate`` on a day's ``calib_mag_*`` (written to ``tmp``), and that day's gyro offset."""
    calib, calib_gyr, tmp = job
    from replay.cli import main
    from replay.formats import read_recording

    path = Path(tmp) / f"{calib}.json"
    with contextlib.redirect_stdout(io.StringIO()):
        if main(["calibrate", str(DATA / calib), "--json", str(path)]) != 0:
            raise RuntimeError(f"pdr-mag calibrate {DATA / calib} failed")
    goff = read_recording(DATA / calib_gyr).gyro.xyz.mean(axis=0)
    return calib, str(path), [float(v) for v in goff]


def day_files(walks: list[str], pool, tmp: str) -> dict[str, tuple[str, list[float]]]:
    """Each walk's day files, each day made once on ``pool`` into ``tmp``: walk → (the day's ``pdr-mag
    calibrate`` JSON, the day's gyro offset)."""
    infos = {w: trial_info(w) for w in walks}
    days = sorted({(i["calib"], i["calib_gyr"]) for i in infos.values()})
    made = {c: (p, g) for c, p, g in pool.map(make_day_files, [(c, g, tmp) for c, g in days])}
    return {w: made[infos[w]["calib"]] for w in walks}


def day_calibration(name: str, field):
    """The day's calibration in memory, as ``pdr-mag calibrate`` fits it (for ``pipeline_speed.py``)."""
    from pdr_mag.calibration import calibrate
    from pdr_mag.calibration.alignment import quasi_static_accel
    from replay.formats import read_recording

    rec = read_recording(DATA / name)
    accel = quasi_static_accel(rec.accel.t, rec.accel.xyz, rec.mag.t)
    return calibrate(rec.mag.xyz, method="auto", accel=accel, field=field)


# ---------------------------------------------------------------------------------------------- scoring
class Truth:
    """A walk's mocap truth and the scorer's window (``score.truth_t0``: ``mocap_t0`` of trial.json)."""

    def __init__(self, score, walk_dir: Path):
        self.score = score
        t, q = score.C.read_quat_csv(str(walk_dir / "truth.csv"))
        ok = np.all(np.isfinite(q), axis=1)
        self.t, self.q = t[ok], q[ok]
        self.t0, _ = score.truth_t0(str(walk_dir / "truth.csv"), self.t)

    def figures(self, t_est, q_est, window=None) -> dict:
        """The shared scorer's figures (``heading_err_mean`` etc.) of an estimate; ``window``: s after
        ``t0``, the scorer's ``WINDOW`` unless given."""
        t_est, q_est = np.asarray(t_est, float), np.asarray(q_est, float)
        r = self.score.score_arrays(self.t, self.q, t_est, q_est, self.t0, window=window or self.score.WINDOW)
        return {k: r[k] for k in ("heading_err_mean", "heading_err_median", "heading_err_p95",
                                  "heading_err_max", "tilt_err_mean", "n_frames", "coverage") if k in r}

    def frames(self, t_est, q_est, max_gap: float = 1.0, window=None):
        """Scored truth times and the signed heading error there (the frames ``score_arrays`` scores with
        the same ``window``)."""
        C = self.score.C
        window = window or self.score.WINDOW
        lo, hi = self.t0 + window[0], self.t0 + window[1]
        w = (self.t >= lo) & (self.t <= hi)
        tr, qr = self.t[w], self.q[w]
        qi, valid = C.slerp_at(t_est, q_est, tr)
        idx = np.clip(np.searchsorted(t_est, tr, side="right") - 1, 0, len(t_est) - 2)
        valid &= (t_est[idx + 1] - t_est[idx]) <= max_gap
        _, head, _ = self.score.error_angles(qi[valid], qr[valid])
        return tr[valid], head


#: the row filter of issue 10's "an uncertainty that warns": a user who keeps rows with σ ≤ 20° must never
#: keep one that is 45° wrong
KEEP_STD, WRONG = 20.0, 45.0


def honesty(err_deg: np.ndarray, std_deg: np.ndarray) -> dict:
    """Counts of scored frames with |error| ≤ 1σ, ≤ 2σ and > 3σ of the reported std; frames a user keeping
    σ ≤ 20° keeps (and of those, the ones more than 45° off); the sum of (error/σ)²."""
    a = np.abs(err_deg)
    kept = std_deg <= KEEP_STD
    return {"n": int(len(a)), "within_1sigma": int(np.sum(a <= std_deg)),
            "within_2sigma": int(np.sum(a <= 2.0 * std_deg)),
            "beyond_3sigma": int(np.sum(a > 3.0 * std_deg)),
            "kept": int(np.sum(kept)), "kept_wrong": int(np.sum(kept & (a > WRONG))),
            "sum_z2": float(np.sum((a / std_deg) ** 2)),
            "std_median_deg": float(np.median(std_deg)) if len(a) else float("nan")}


def run_mode(walk_dir: Path, cal, truth: Truth) -> tuple[dict, dict]:
    """Replay one walk (``cal``: the calibration file, or None for mode b); figures and frame series."""
    from pdr_mag.estimates import EstimateBatch
    from replay.run import MemorySink, replay

    sink = MemorySink()
    summary = replay(walk_dir, calibration=cal, sinks=[sink], progress=False)
    b = EstimateBatch.concat(sink.batches)
    fig = truth.figures(b.t, b.q_wd)
    tf, err = truth.frames(b.t, b.q_wd)
    std = np.interp(tf, b.t, b.heading_std_deg)
    t_used = b.t[b.mag_used.astype(bool)]
    k = np.searchsorted(t_used, tf, side="right") - 1
    last = np.where(k >= 0, t_used[np.maximum(k, 0)], b.t[0])
    age = tf - last  # s since the last magnetometer update (or since the start, before the first one)
    kinds: dict[str, int] = {}
    for ev in summary["events"]:
        kinds[ev["kind"]] = kinds.get(ev["kind"], 0) + 1
    fig.update(honesty(err, std))
    fig.update({"mag_age_max_s": float(np.max(age)) if len(age) else float("nan"),
                "mag_age_over_5s_share": float(np.mean(age > 5.0)) if len(age) else float("nan"),
                "events": kinds, "final_cal_state": str(b.cal_state[-1]) if len(b) else "",
                "samples_per_s": summary.get("samples_per_s"),
                "n_samples": int(sum(summary.get("n_samples", {}).values()))})
    return fig, {"t": tf, "err": err, "std": std, "mag_age": age}


def run_core(rec, cal, field, truth: Truth) -> dict | None:
    """The fusion core alone on the merged raw streams with the calibrated magnetometer."""
    try:
        from pdr_mag.fusion import FusionCore

        core = FusionCore(field=field)
        core.set_reference_strength(cal.field_uT)
        n_a, n_g, n_m = len(rec.accel.t), len(rec.gyro.t), len(rec.mag.t)
        kind = np.concatenate([np.zeros(n_a), np.ones(n_g), np.full(n_m, 2)]).astype(np.int8)
        t = np.concatenate([rec.accel.t, rec.gyro.t, rec.mag.t])
        xyz = np.concatenate([rec.accel.xyz, rec.gyro.xyz, cal.apply(rec.mag.xyz)])
        o = np.argsort(t, kind="stable")
        b = core.process(kind[o], t[o], xyz[o])
    except (ImportError, AttributeError, TypeError, ValueError) as exc:
        print(f"core column left out: {type(exc).__name__}: {exc}", file=sys.stderr)
        return None
    return truth.figures(b.t, b.q_wd)


# ---------------------------------------------------------------------------------------------- one walk
def run_walk(job: dict) -> dict:
    """Every column on one walk (runs in a worker process)."""
    from _peers import run_peers

    from pdr_mag.field import earth_field_from_meta
    from replay.formats import read_recording
    from replay.run import load_calibration

    walk = job["walk"]
    d = DATA / walk
    info = trial_info(walk)
    score = load_scorer()
    truth = Truth(score, d)
    out = {"walk": walk, "device": info["device"], "dist": info["dist"], "motion": info["motion"],
           "calib": info["calib"], "calib_gyr": info["calib_gyr"]}
    t_start = time.perf_counter()
    cal = load_calibration(job["cal_json"])
    out["a"], ser_a = run_mode(d, cal, truth)
    out["b"], ser_b = run_mode(d, None, truth)
    out["time_replay_s"] = time.perf_counter() - t_start
    rec = read_recording(d)
    field = earth_field_from_meta(rec.meta)
    if job["core"]:
        out["core"] = run_core(rec, cal, field, truth)
    t_peers = time.perf_counter()
    if job["peers"]:
        mag_wmm = cal.apply(rec.mag.xyz) * (field.strength / cal.field_uT)
        times = {}
        peers = {}
        for col in PEER_COLUMNS:
            t1 = time.perf_counter()
            (tg, q), = run_peers(rec, mag_wmm, np.asarray(job["gyro_offset"]), field.declination_deg,
                                 (col,)).values()
            times[col] = time.perf_counter() - t1
            peers[col] = truth.figures(tg, q)["heading_err_mean"]
        t_os, q_os = score.C.read_quat_csv(str(d / "os.csv"))
        peers["os"] = truth.figures(t_os, q_os)["heading_err_mean"]
        out["peers"] = peers
        n = len(rec.accel.t) + len(rec.gyro.t) + len(rec.mag.t)
        out["imufusion_samples_per_s"] = n / times["imufusion_cal"]
    out["time_peers_s"] = time.perf_counter() - t_peers
    if job.get("series"):
        sdir = Path(job["series"])
        sdir.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(sdir / f"{walk}.npz", t=ser_a["t"], err_a=ser_a["err"], std_a=ser_a["std"],
                            mag_age_a=ser_a["mag_age"], t_b=ser_b["t"], err_b=ser_b["err"],
                            std_b=ser_b["std"], mag_age_b=ser_b["mag_age"])
    return out


def run_all(walks: list[str], jobs: int, core: bool = True, peers: bool = True, series=None) -> list[dict]:
    """Day files first (each once), then every walk; ``jobs`` worker processes."""
    with tempfile.TemporaryDirectory() as tmp, ProcessPoolExecutor(max_workers=jobs) as pool:
        made = day_files(walks, pool, tmp)
        work = [{"walk": w, "cal_json": made[w][0], "gyro_offset": made[w][1],
                 "core": core, "peers": peers, "series": str(series) if series else None} for w in walks]
        results = []
        for r in pool.map(run_walk, work):
            a, b = r["a"]["heading_err_mean"], r["b"]["heading_err_mean"]
            print(f"{r['walk']:<40} a {a:6.1f}  b {b:6.1f}  ({r['time_replay_s']:.1f} s + peers "
                  f"{r['time_peers_s']:.1f} s)", flush=True)
            results.append(r)
    return results


# ---------------------------------------------------------------------------------------------- peers
def peers_md_table(path: Path = PEERS_MD) -> dict[str, dict[str, float]]:
    """The per-trial table of PEERS.md: walk → column → mean heading error, deg."""
    cols, rows = None, {}
    for line in path.read_text().splitlines():
        if line.startswith("| trial |") and cols is None:
            cols = [c.strip() for c in line.strip().strip("|").split("|")][1:]
        m = re.match(r"\| (\w+) \|(.*)\|\s*$", line)
        if cols and m and m.group(1) != "trial" and not m.group(1).startswith("*"):
            vals = [v.strip() for v in m.group(2).split("|")]
            if len(vals) == len(cols):
                rows[m.group(1)] = {c: float(v) for c, v in zip(cols, vals, strict=True)}
    return rows


def check_peers(results: list[dict], tol: float = 0.5) -> tuple[str, list[tuple]]:
    """Our peer figures against PEERS.md: a one-line summary and the figures differing by more than tol."""
    ref = peers_md_table()
    diffs, off = [], []
    for r in results:
        for col, v in r.get("peers", {}).items():
            if r["walk"] in ref and col in ref[r["walk"]]:
                d = v - ref[r["walk"]][col]
                diffs.append(abs(d))
                if abs(d) > tol:
                    off.append((r["walk"], col, v, ref[r["walk"]][col]))
    if not diffs:
        return "no peer figures to compare with PEERS.md", []
    d = np.asarray(diffs)
    line = (f"peers vs PEERS.md: {np.sum(d <= 0.1)} / {len(d)} walk×column figures within 0.1°, "
            f"{np.sum(d <= tol)} within {tol}°, median |Δ| {np.median(d):.2f}°, max {d.max():.1f}°")
    return line, off


def load_peers(path: Path) -> dict[str, dict[str, float]]:
    """Peer and os figures per walk from a ``--json`` dump or the fixture."""
    obj = json.loads(Path(path).read_text())
    if "walks" in obj:
        return {r["walk"]: r["peers"] for r in obj["walks"] if "peers" in r}
    return obj["peers"]


# ---------------------------------------------------------------------------------------------- report
def _groups(results):
    out = [("all", results), ("Dist", [r for r in results if r["dist"] == "Dist"]),
           ("NoDist", [r for r in results if r["dist"] == "NoDist"])]
    for key in ("device", "motion"):
        for v in sorted({r[key] for r in results}):
            out.append((v, [r for r in results if r[key] == v]))
    return [(g, rs) for g, rs in out if rs]


def best_peer_column(results) -> str | None:
    cols = [c for c in PEER_COLUMNS if all(c in r.get("peers", {}) for r in results)]
    if not cols:
        return None
    return min(cols, key=lambda c: np.mean([r["peers"][c] for r in results]))


def _stats(vals) -> str:
    v = np.asarray(vals, float)
    return f"{v.mean():.1f} / {np.median(v):.1f} | {np.sum(v > FAIL[0])} / {np.sum(v > FAIL[1])}"


def _honest(rs, mode) -> str:
    """Pooled ≤1σ / ≤2σ | walks with > 10 % beyond 3σ | frames kept at σ ≤ 20° that are > 45° off | the
    median of the walks' median σ / the pooled share of frames with σ > 20°."""
    n = max(sum(r[mode]["n"] for r in rs), 1)
    w1 = sum(r[mode]["within_1sigma"] for r in rs)
    w2 = sum(r[mode]["within_2sigma"] for r in rs)
    bad = sum(r[mode]["beyond_3sigma"] > BEYOND_3SIGMA_MAX * max(r[mode]["n"], 1) for r in rs)
    wrong = sum(r[mode]["kept_wrong"] for r in rs)
    over = 1.0 - sum(r[mode]["kept"] for r in rs) / n
    sd = np.median([r[mode]["std_median_deg"] for r in rs])
    return f"{w1 / n:.0%} / {w2 / n:.0%} | {bad} | {wrong} | {sd:.0f}° / {over:.0%}"


def summary_table(results) -> list[str]:
    best = best_peer_column(results)
    has_os = all("os" in r.get("peers", {}) for r in results)
    head = ["group", "n"]
    for m in ("a", "b"):
        head += [f"{m}: mean / median", f"{m}: >20° / >45°", f"{m}: ≤1σ / ≤2σ", f"{m}: >3σ walks",
                 f"{m}: 45° kept", f"{m}: σ / >20°"]
    if best:
        head += [f"{best}: mean / median", ">20° / >45°"]
    if has_os:
        head += ["os: mean / median", ">20° / >45°"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for g, rs in _groups(results):
        cells = [g, str(len(rs)),
                 _stats([r["a"]["heading_err_mean"] for r in rs]), _honest(rs, "a"),
                 _stats([r["b"]["heading_err_mean"] for r in rs]), _honest(rs, "b")]
        if best:
            cells.append(_stats([r["peers"][best] for r in rs]))
        if has_os:
            cells.append(_stats([r["peers"]["os"] for r in rs]))
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def _f(v, bold_above=None) -> str:
    if v is None or not np.isfinite(v):
        return "–"
    s = f"{v:.1f}"
    return f"**{s}**" if bold_above is not None and v > bold_above else s


def walk_table(results) -> list[str]:
    """One row per way of carrying the phone (disturbed or not), one column per phone: ``a · b · peer ·
    os`` — modes a and b, the best ``_cal_gcal`` peer, the phone's own fusion; † after a mode with more
    than 10 % of its frames beyond 3σ."""
    phones = sorted({r["walk"].split("_")[1] for r in results})
    rows: dict[str, dict[str, str]] = {}
    for r in results:
        _, phone, dist, motion = r["walk"].split("_", 3)
        p = r.get("peers", {})
        cell = []
        for m, fail in (("a", FAIL[0]), ("b", FAIL[1])):
            n = max(r[m]["n"], 1)
            dagger = "†" if r[m]["beyond_3sigma"] / n > 0.10 else ""
            cell.append(_f(r[m]["heading_err_mean"], fail) + dagger)
        gcal = [v for k, v in p.items() if k.endswith("_gcal")]
        cell += [_f(min(gcal)) if gcal else "—", _f(p.get("os"))]
        rows.setdefault(f"{dist} {motion}", {})[phone] = " · ".join(cell)
    lines = ["| walk | " + " | ".join(f"{ph}: a · b · peer · os" for ph in phones) + " |",
             "|---|" + "---|" * len(phones)]
    for key in sorted(rows, key=lambda k: (k.startswith("NoDist"), k)):
        lines.append(f"| {key} | " + " | ".join(rows[key].get(ph, "") for ph in phones) + " |")
    return lines


def markdown(results, elapsed_s: float, cpu_s: float, jobs: int, peer_line: str, commit: str = "") -> str:
    a_sps = np.median([r["a"]["samples_per_s"] for r in results if r["a"].get("samples_per_s")])
    imu = [r["imufusion_samples_per_s"] for r in results if r.get("imufusion_samples_per_s")]
    speed = (f" Throughput (median over walks, this run, the peers in the same processes: the speed benchmark"
             f" is `pipeline_speed.py`): replay mode a {a_sps / 1e6:.2f} M samples/s, imufusion"
             f" {np.median(imu) / 1e6:.2f} M samples/s." if imu else "")
    rms = [np.sqrt(sum(r[m]["sum_z2"] for r in results) / max(sum(r[m]["n"] for r in results), 1))
           for m in ("a", "b")]
    lines = [
        SECTION,
        "",
        f"`python benchmarks/heading.py --jobs {jobs} --write-results` ({len(results)} walks found in"
        f" `../shared/datasets/tyrex-pdrcsv`, {elapsed_s:.0f} s wall on {jobs} processes, {cpu_s:.0f} s CPU"
        + (f", commit {commit}" if commit else "") + "). Mean |heading error| per walk (shared scorer,"
        " 5–120 s), degrees; group cells: mean / median over walks, and walks above 20° / 45°. Mode a ="
        " `replay` with the day's `pdr-mag calibrate` file; mode b = no calibration. ≤1σ / ≤2σ: pooled share"
        " of scored frames with |error| ≤ 1σ / 2σ of `heading_std_deg` (Gaussian 68 / 95 %); >3σ walks: walks"
        " with more than 10 % of their frames beyond 3σ; 45° kept: frames with σ ≤ 20° more than 45° off"
        " (what a user keeping σ ≤ 20° would keep wrongly); σ / >20°: median of the walks' median σ, and the"
        " share of frames with σ > 20° (what that user would drop). Peers as in PEERS.md, fed the same day's"
        f" calibration (best column in this run shown). {peer_line}.{speed}",
        "",
        *summary_table(results),
        "",
        f"RMS of error/σ over every scored frame (a Gaussian: 1): mode a {rms[0]:.2f}, mode b {rms[1]:.2f}."
        " Per walk: the script's output and `--json`.",
        "",
    ]
    return "\n".join(lines)


def per_walk(results) -> str:
    """The per-walk table the script prints (RESULTS.md keeps the groups)."""
    return "\n".join([
        "Per walk (mean |error|, bold: a > 20°, b > 45°; peer: the best `_cal_gcal` column; †: more than 10 %"
        " of the frames beyond 3σ):",
        "",
        *walk_table(results),
    ])


def write_section(text: str) -> None:
    from _common import RESULTS

    old = RESULTS.read_text()
    for sec in OLD_SECTIONS:  # this script's earlier section (7 walks, mode a only)
        start = old.find(sec)
        if start >= 0:
            nxt = old.find("\n## ", start + len(sec))
            old = old[:start] + (old[nxt + 1:] if nxt >= 0 else "")
    RESULTS.write_text(old)
    _write_section(SECTION, text)


def write_fixture(results, path: Path = FIXTURE) -> None:
    """The peers' figures per walk, for the real-walk tests' bounds (derived numbers, not data)."""
    obj = {"about": "mean |heading error| (deg, shared tyrex scorer) of the PEERS.md peers and the phone's"
                    " own fusion per walk, as benchmarks/heading.py runs them (day's pdr-mag calibrate file"
                    " scaled to the WMM; _gcal: the day's gyro offset removed). Written by"
                    " `python benchmarks/heading.py --write-fixture`.",
           "peers": {r["walk"]: {k: round(v, 3) for k, v in r["peers"].items()} for r in results}}
    path.write_text(json.dumps(obj, indent=1, sort_keys=True) + "\n")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--walks", default=None, help="comma-separated globs (no wildcard: substring)")
    ap.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="worker processes")
    ap.add_argument("--json", type=Path, default=None, help="dump the per-walk figures to FILE")
    ap.add_argument("--series", type=Path, default=None, help="per-walk error and σ series (npz) into DIR")
    ap.add_argument("--peers-from", type=Path, default=None, help="peer/os figures from an earlier --json")
    ap.add_argument("--no-core", action="store_true", help="leave out the fusion-core-only column")
    ap.add_argument("--check-peers", action="store_true", help="list peer figures off PEERS.md by > 0.5°")
    ap.add_argument("--write-results", action="store_true", help=f"write the section '{SECTION}'")
    ap.add_argument("--write-fixture", action="store_true", help=f"write {FIXTURE.relative_to(ROOT)}")
    ap.add_argument("--commit", default="", help="commit to name in the section")
    args = ap.parse_args(argv)
    walks = discover_walks(args.walks)
    if not walks:
        print(f"no walks match {args.walks!r} in {DATA}", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    results = run_all(walks, max(1, args.jobs), core=not args.no_core, peers=args.peers_from is None,
                      series=args.series)
    elapsed = time.perf_counter() - t0
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)  # the pool's workers, reaped when it closed
    cpu = ru.ru_utime + ru.ru_stime
    if args.peers_from is not None:
        given = load_peers(args.peers_from)
        for r in results:
            if r["walk"] in given:
                r["peers"] = given[r["walk"]]
    peer_line, off = check_peers(results)
    text = markdown(results, elapsed, cpu, max(1, args.jobs), peer_line, args.commit)
    print(text)
    print(per_walk(results))
    if args.check_peers:
        for w, c, v, ref in off:
            print(f"  {w:<40} {c:<20} ours {v:6.1f}  PEERS.md {ref:6.1f}  Δ {v - ref:+.1f}")
    print(f"wall time {elapsed:.0f} s on {args.jobs} processes, CPU {cpu:.0f} s", file=sys.stderr)
    if args.json:
        args.json.write_text(json.dumps({"elapsed_s": elapsed, "cpu_s": cpu, "walks": results}, indent=1,
                                        default=float))
    if args.write_results:
        write_section(text)
    if args.write_fixture:
        write_fixture(results)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
