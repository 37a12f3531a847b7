"""Heading accuracy on the real tyrex walks, each walk bounded by the peers on the same walk (issue 10).

Walks: every folder of ``../shared/datasets/tyrex-pdrcsv`` whose ``trial.json`` says ``"kind": "trial"``
(discovered, not listed).  ``trial.json`` is read here — never by the library — for the day's calibration
recording and, by the shared scorer ``../shared/benchmarks/tyrex/score.py`` (imported), for the scoring
window.  Mode a = ``replay(REC, calibration=FILE)`` with FILE written by ``pdr-mag calibrate`` on the day's
``calib_mag_*``; mode b = ``replay(REC)`` (online calibration only).

The peers' figures come from ``tests/fixtures/tyrex_peers.json``, written by
``python benchmarks/heading.py --write-fixture`` (derived numbers: the PEERS.md peers run as that page
describes, on the same day's calibration file; vqf and ahrs are in the ``bench`` extra, not ``test``).

Bounds (mean |heading error| per walk, degrees):

* mode a ≤ min(max(best ``_cal_gcal`` peer + :data:`MARGIN_DEG`, :data:`FLOOR_DEG`), :data:`FAIL_A_DEG`).
  The peers given the day's magnetometer calibration *and* the day's gyro offset are the strongest
  reference on each walk; mode a gets the magnetometer file only and must learn the gyro offset itself,
  which a filter with a bias state can.  ``MARGIN_DEG`` = 2°: the motion-capture body is not exactly aligned
  with the phone (PEERS.md: a 1–2° floor), so two estimators that are equally right about the phone differ
  by up to that much.  ``FLOOR_DEG`` = 3°: that floor plus the residual phone/mocap clock offset
  (−30…+35 ms, PEERS.md), which moves a walk's figure by up to 1.5° (mode a shifted by ±35 ms on six NoDist
  walks: 0.1–1.5°).
* mode b ≤ min(max(``os``, best ``_cal`` peer), :data:`FAIL_B_DEG`) + ``MARGIN_DEG``: starting with no
  calibration at all, mode b fails when it is worse than both the phone's own fusion (``os``: its own
  long-term calibration, no day file) and every peer given the day's magnetometer file but a raw gyroscope.
* the caps are issue 10's failure lines (mode a: no walk above 20°, mode b: none above 45°).  Without them
  the walks on which the phone's own fusion is broken (``os`` 62–114°) bound mode b at 64–116°, near or
  beyond the 90° a random heading averages: bounds that cannot fail (and mode a's at 28° on one walk).
* honesty, both modes: at most :data:`BEYOND_3SIGMA_MAX` of a walk's scored frames with |error| beyond
  3σ of ``heading_std_deg`` (a Gaussian gives 0.3 %; issue 10's target).
* groups (:func:`test_the_groups_meet_issue_10s_targets`): mode a's mean over all / Dist / NoDist walks no
  higher than the best ``_cal_gcal`` column's, mode b's mean and median per phone no higher than ``os``'s.

Walks that fail a bound today are ``xfail`` naming issue 10, strict when their figure is 15 % or more beyond
its bound (see the lists below): a strict one flips (and fails) when the filter is fixed — then delete it
from its list.  A walk that passes today, by however little, is not listed: its bound is asserted.
"""

from __future__ import annotations

import contextlib
import importlib.util
import io
import json
import sys
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pytest

from tests.conftest import DATASETS, ROOT, absent, dataset

TYREX = DATASETS / "tyrex-pdrcsv"
SCORER = ROOT.parent / "shared" / "benchmarks" / "tyrex" / "score.py"
FIXTURE = ROOT / "tests" / "fixtures" / "tyrex_peers.json"
MARGIN_DEG = 2.0
FLOOR_DEG = 3.0
#: issue 10's lines for a failed walk, deg: mode a none above 20°, mode b none above 45°
FAIL_A_DEG = 20.0
FAIL_B_DEG = 45.0
BEYOND_3SIGMA_MAX = 0.10
ISSUE = "issue 10 (a heading that never fails): "

#: Known failures: walk → (its figure against its bound today, strict, the figure in degrees).  One rule:
#: strict when the figure is 15 % or more beyond its bound (a mean ≥ 1.15 × its bound; a share of frames
#: beyond 3σ ≥ 11.5 %, 1.15 × :data:`BEYOND_3SIGMA_MAX`): such an xfail that starts passing means the filter
#: changed, and the entry must go.  A figure within 15 % of its bound is a non-strict xfail: floating point
#: differs across CPUs and may carry it either side of the bound.
XFAIL_A: dict[str, tuple[str, bool, float]] = {
    "Thibaud_Nexus5_Dist_Phoning": (
        "11.8° > 11.1° (madgwick_cal_gcal 9.1° + 2°): the phone moves at the start, its first fix is made"
        " through an unsettled tilt and made anew 1.1 s later (a 30° turn); the heading then crosses the"
        " flagged part on the gyroscope, 2–4° apart from the linearised correction's (10.7°) all the way",
        False,
        11.8,
    ),
    "Thibaud_Nexus5_Dist_Texting": ("9.5° > 8.4° (madgwick_cal_gcal 6.4° + 2°)", False, 9.5),
    "Thibaud_iPhone5_Dist_BackPocket": (
        "6.8° > 6.1° (madgwick_cal_gcal 4.1° + 2°); the field left out for up to 20 s in the disturbed area,"
        " and the update that ends the gate's rejections after it does not teach the gyro bias (the rule a"
        " start in motion needs, tests/test_start_in_motion.py)",
        False,
        6.8,
    ),
}
#: walk → its mode-b figure against its bound today, strict, the figure (only walks that miss their bound;
#: none today)
XFAIL_B: dict[str, tuple[str, bool, float]] = {}
#: (walk, mode) → the share of its frames beyond 3σ today, strict (none today: Thibaud_iPhone5_Dist_AR
#: mode b, 27 % without the consider covariance of the place's disturbance, is at 2 %)
XFAIL_STD: dict[tuple[str, str], tuple[str, bool]] = {}


def _walks() -> list[str]:
    if not TYREX.is_dir():
        return ["(no walks: ../shared/datasets/tyrex-pdrcsv absent)"]
    out = []
    for d in sorted(TYREX.iterdir()):
        tj = d / "trial.json"
        if tj.is_file() and (d / "truth.csv").is_file() and json.loads(tj.read_text()).get("kind") == "trial":
            out.append(d.name)
    return out


WALKS = _walks()


def _xfail(entry: tuple):
    reason, strict = entry[:2]
    return pytest.mark.xfail(
        strict=strict, reason=ISSUE + reason + ("" if strict else " (within 15 % of its bound)")
    )


def _known_miss(request, xfails: dict, walk: str, mean: float, bound: float, ceiling: float) -> None:
    """A listed walk is an expected failure, but not a free pass: a non-strict entry (within 15 % of its
    bound, either side within reach of another CPU's rounding) must stay within 1.15 × its bound, a strict
    one within 1.15 × its own figure (and issue 10's line, ``ceiling``); beyond that it fails as a
    regression."""
    entry = xfails.get(walk)
    if entry is None:
        return
    limit = min(1.15 * entry[2], ceiling) if entry[1] else 1.15 * bound
    assert mean <= limit, f"{walk}: {mean:.1f}° beyond even its known miss ({limit:.1f}°)"
    request.applymarker(_xfail(entry))


# ------------------------------------------------------------------------------------------ machinery
class Figures(NamedTuple):
    """One walk replayed in one mode, over the frames the shared scorer scores: its mean |heading error|
    (deg), the share of frames beyond 3σ, Σ (error/σ)², the number of frames, those within 2σ, and those more
    than 45° off at σ ≤ 20° (what a user keeping σ ≤ 20° would keep wrongly)."""

    mean: float
    beyond: float
    sum_z2: float
    n: int
    within_2sigma: int
    kept_wrong: int


def _scorer():
    if not SCORER.is_file():
        absent(f"shared scorer {SCORER} not found (../shared is not beside this checkout)")
    sys.path.insert(0, str(SCORER.parent))
    spec = importlib.util.spec_from_file_location("tyrex_score", SCORER)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def peers() -> dict:
    return json.loads(FIXTURE.read_text())["peers"]


@pytest.fixture(scope="module")
def day_file(tmp_path_factory):
    """``day_file(walk)`` → the day's calibration file of a walk, written by ``pdr-mag calibrate`` on the
    ``calib_mag_*`` recording its ``trial.json`` names; each day's file made once per module."""
    from replay.cli import main

    tmp = tmp_path_factory.mktemp("day_calibrations")

    def make(walk: str) -> Path:
        name = json.loads((dataset("tyrex-pdrcsv", walk) / "trial.json").read_text())["calib"]
        path = tmp / f"{name}.json"
        if not path.exists():
            with contextlib.redirect_stdout(io.StringIO()):
                assert main(["calibrate", str(dataset("tyrex-pdrcsv", name)), "--json", str(path)]) == 0
        return path

    return make


@pytest.fixture(scope="module")
def run(day_file):
    """``run(walk, mode)`` → its :class:`Figures`; each replay done once."""
    from replay.run import MemorySink, replay

    score = _scorer()
    cache: dict = {}

    def figures(b, t_ref, q_ref, t0) -> Figures:
        mean = score.score_arrays(t_ref, q_ref, b.t, b.q_wd, t0)["heading_err_mean"]
        # the frames score_arrays scores: in the window, inside the estimate, no estimate gap > 1 s
        w = (t_ref >= t0 + score.WINDOW[0]) & (t_ref <= t0 + score.WINDOW[1])
        qi, valid = score.C.slerp_at(b.t, b.q_wd, t_ref[w])
        i = np.clip(np.searchsorted(b.t, t_ref[w], side="right") - 1, 0, len(b.t) - 2)
        valid &= b.t[i + 1] - b.t[i] <= 1.0
        _, head, _ = score.error_angles(qi[valid], q_ref[w][valid])
        err = np.abs(head)
        sd = np.interp(t_ref[w][valid], b.t, b.heading_std_deg)
        return Figures(
            mean=mean,
            beyond=float(np.mean(err > 3.0 * sd)),
            sum_z2=float(np.sum((err / sd) ** 2)),
            n=len(err),
            within_2sigma=int(np.sum(err <= 2.0 * sd)),
            kept_wrong=int(np.sum((err > 45.0) & (sd <= 20.0))),
        )

    def go(walk: str, mode: str):
        if (walk, mode) not in cache:  # both modes at once: the recording is read once
            from pdr_mag.estimates import EstimateBatch
            from replay.formats import read_recording

            d = dataset("tyrex-pdrcsv", walk)
            rec = read_recording(d)
            t_ref, q_ref = score.C.read_quat_csv(str(d / "truth.csv"))
            ok = np.all(np.isfinite(q_ref), axis=1)
            t_ref, q_ref = t_ref[ok], q_ref[ok]
            t0, _ = score.truth_t0(str(d / "truth.csv"), t_ref)
            for m, cal in (("a", day_file(walk)), ("b", None)):
                sink = MemorySink()
                replay(rec, calibration=cal, sinks=[sink], progress=False)
                cache[(walk, m)] = figures(EstimateBatch.concat(sink.batches), t_ref, q_ref, t0)
        return cache[(walk, mode)]

    return go


# ------------------------------------------------------------------------------------------ tests
def test_the_peer_fixture_covers_every_walk(peers):
    """The fixture is rewritten (``benchmarks/heading.py --write-fixture``) when walks are added."""
    dataset("tyrex-pdrcsv")
    assert sorted(peers) == WALKS
    for walk, p in peers.items():
        assert {"os", "vqf_cal", "vqf_cal_gcal", "madgwick_cal_gcal", "imufusion_cal_gcal"} <= set(p), walk
    named = set(XFAIL_A) | set(XFAIL_B) | {walk for walk, _ in XFAIL_STD}
    assert named <= set(WALKS), f"xfail entries naming no walk: {sorted(named - set(WALKS))}"
    assert {mode for _, mode in XFAIL_STD} <= {"a", "b"}


def _best(p: dict, suffix: str) -> float:
    return min(v for k, v in p.items() if k.endswith(suffix))


@pytest.mark.parametrize("walk", WALKS)
def test_mode_a_within_the_best_peer_given_the_day_calibration(walk, peers, run, request):
    mean = run(walk, "a").mean
    bound = min(max(_best(peers[walk], "_cal_gcal") + MARGIN_DEG, FLOOR_DEG), FAIL_A_DEG)
    _known_miss(request, XFAIL_A, walk, mean, bound, FAIL_A_DEG)
    assert mean <= bound, f"{walk}: mode a {mean:.1f}° > {bound:.1f}°"


@pytest.mark.parametrize("walk", WALKS)
def test_mode_b_not_worse_than_both_the_phone_and_the_peers(walk, peers, run, request):
    mean = run(walk, "b").mean
    p = peers[walk]
    bound = min(max(p["os"], _best(p, "_cal")) + MARGIN_DEG, FAIL_B_DEG)
    _known_miss(request, XFAIL_B, walk, mean, bound, FAIL_B_DEG)
    assert mean <= bound, f"{walk}: mode b {mean:.1f}° > {bound:.1f}°"


@pytest.mark.parametrize("mode", ["a", "b"])
@pytest.mark.parametrize("walk", WALKS)
def test_heading_std_warns_when_the_heading_is_wrong(walk, mode, run, request):
    if (walk, mode) in XFAIL_STD:
        request.applymarker(_xfail(XFAIL_STD[(walk, mode)]))
    beyond = run(walk, mode).beyond
    assert beyond <= BEYOND_3SIGMA_MAX, f"{walk} mode {mode}: {beyond:.0%} of the frames beyond 3σ"


#: the top of issue 19's band for the RMS of error/σ (0.8–1.25: σ neither loose — a backend weighting by 1/σ²
#: under-uses a heading whose σ is twice its error — nor tight)
RMS_Z_MAX = 1.25
#: where each mode stands today, below the band: the floor a change may not fall under (pooled over the 42
#: walks: mode a 0.64, mode b 0.57 — benchmarks/RESULTS.md; 0.51 and 0.49 with c decorrelating in time only)
RMS_Z_FLOOR = 0.55


@pytest.mark.parametrize("mode", ["a", "b"])
def test_the_std_is_safe_and_as_sharp_as_today_over_the_walks(mode, run):
    """Issue 19's σ targets pooled over every frame of the 42 walks: truth within 2σ in ≥ 93 % of the frames
    and no frame 45° off at σ ≤ 20°, and the RMS of error/σ no higher than the band's top; its bottom (0.8) is
    not met (benchmarks/NOTES.md, "c decorrelates as the walker turns"), so the test holds the sharpness
    reached, :data:`RMS_Z_FLOOR` — a σ that grows back towards twice the error fails."""
    figs = [run(w, mode) for w in WALKS]
    n = sum(f.n for f in figs)
    rms = float(np.sqrt(sum(f.sum_z2 for f in figs) / n))
    within = sum(f.within_2sigma for f in figs) / n
    kept = sum(f.kept_wrong for f in figs)
    assert within >= 0.93, f"mode {mode}: within 2σ in {within:.1%} of the frames"
    assert kept == 0, f"mode {mode}: {kept} frames 45° off at σ ≤ 20°"
    assert RMS_Z_FLOOR <= rms <= RMS_Z_MAX, f"mode {mode}: RMS of error/σ {rms:.3f}"


def test_the_groups_meet_issue_10s_targets(peers, run):
    """Issue 10's targets over groups of walks, which a per-walk bound with its margin cannot see: a
    regression of a few degrees on every walk.  Mode a's mean of the walk means, over all / Dist / NoDist
    walks, no higher than the best ``_cal_gcal`` column's over the same walks (best: the lowest such mean);
    mode b's mean and median per phone no higher than the phone's own fusion's (``os``).  No margin: the
    motion-capture misalignment costs every estimator the same on a walk.

    Measured (42 walks, means over walks, deg; benchmarks/heading.py at 3f4a68b): mode a all 4.38 vs
    vqf_cal_gcal 6.02, Dist 6.01 vs 9.05, NoDist 3.17 vs 3.75 — 2° more on every walk fails all and NoDist.
    Mode b per phone, mean: Nexus5 6.24 vs os 12.35, iPhone4S 4.45 vs 27.66, iPhone5 5.18 vs 23.89 (only a
    gross regression fails these); median: Nexus5 4.37 vs 4.57, iPhone4S 3.24 vs 20.36, iPhone5 4.30 vs
    18.30 — 2° more on every walk fails the Nexus5 median by 1.8°.  That median is the tightest figure (0.20°
    to spare): a few tenths of a degree on the two middle Nexus5 walks carry it over."""
    failed = []
    groups = {"all": WALKS, "Dist": [w for w in WALKS if "_Dist_" in w],
              "NoDist": [w for w in WALKS if "_NoDist_" in w]}
    for group, walks in groups.items():
        assert walks, group
        cols = [c for c in peers[walks[0]] if c.endswith("_cal_gcal")]
        col = min(cols, key=lambda c: np.mean([peers[w][c] for w in walks]))
        mine = float(np.mean([run(w, "a").mean for w in walks]))
        theirs = float(np.mean([peers[w][col] for w in walks]))
        if mine > theirs:
            failed.append(f"mode a, {group}: mean {mine:.2f}° > {col} {theirs:.2f}°")
    for phone in ("Nexus5", "iPhone4S", "iPhone5"):
        walks = [w for w in WALKS if w.split("_")[1] == phone]
        assert walks, phone
        mine = np.array([run(w, "b").mean for w in walks])
        theirs = np.array([peers[w]["os"] for w in walks])
        for name, f in (("mean", np.mean), ("median", np.median)):
            if f(mine) > f(theirs):
                failed.append(f"mode b, {phone}: {name} {f(mine):.2f}° > os {f(theirs):.2f}°")
    assert not failed, ISSUE + "; ".join(failed)


def _restarted(walk: str, start_s: float, calibration, phone: bool = True):
    """The walk replayed from ``start_s`` into its recording (``calibration``: a day's file, or None), as a
    backend started then would: the output rows and the start's time.  ``phone`` False: without the phone's
    own attitude (the rows whose heading is unknown keep the filter's)."""
    from pdr_mag.estimates import EstimateBatch
    from replay.formats import read_recording
    from replay.recording import Stream
    from replay.run import MemorySink, replay

    rec = read_recording(dataset("tyrex-pdrcsv", walk))
    start = rec.t0 + start_s
    for name in ("mag", "accel", "gyro"):
        s = getattr(rec, name)
        keep = s.t >= start
        setattr(rec, name, Stream(s.t[keep], s.xyz[keep]))
    if not phone:
        rec.references = {}
    sink = MemorySink()
    replay(rec, calibration=calibration, sinks=[sink], progress=False)
    return EstimateBatch.concat(sink.batches), start


def _restart_frames(walk: str, b, start: float) -> tuple[np.ndarray, np.ndarray]:
    """The signed heading error (shared scorer, deg) and the reported σ at every truth frame from 5 s after
    the start of a replay started late (:func:`_restarted`) to its last row."""
    score = _scorer()
    t_ref, q_ref = score.C.read_quat_csv(str(dataset("tyrex-pdrcsv", walk) / "truth.csv"))
    ok = np.all(np.isfinite(q_ref), axis=1) & (t_ref >= start + 5.0) & (t_ref <= b.t[-1])
    qi, valid = score.C.slerp_at(b.t, b.q_wd, t_ref[ok])
    _, head, _ = score.error_angles(qi[valid], q_ref[ok][valid])
    return head, np.interp(t_ref[ok][valid], b.t, b.heading_std_deg)


#: (walk, mode) whose first seconds are a run: a replay started 5 s in begins mid-stride
MID_RUN = (("Thibaud_Nexus5_NoDist_RunningHand", "a"), ("Thibaud_Nexus5_NoDist_RunningHand", "b"))


@pytest.mark.parametrize(("walk", "mode"), MID_RUN)
def test_a_replay_started_mid_run_stays_honest(walk, mode, day_file):
    """A backend (re)starts the filter while its user runs: the walk replayed from 5 s in, with the day's
    calibration (mode a, what a backend keeps across restarts) or none (mode b).  The tilt then starts from
    one sample of a swinging, clipping accelerometer (144–150° off here) and its corrections taught the gyro
    bias the swing: in mode b the heading was 62° off on average, 43 % of the frames beyond 3σ.  Scored from
    5 s after the start to the end of the walk: mean error below 20° (issue 10's line for a failed walk in
    mode a, held in both modes here) and at most 10 % of the frames beyond 3σ (issue 10).  Measured: 7.5° and
    0.9 % in mode a, 9.7° and 0.4 % in mode b; the same frames of the replay from the walk's start: 6.1°,
    6.4°.  (The iPhone 4S in a running pocket, restarted so, is left out: its bias is still taught 0.28 rad/s
    from the clipped average in mode a, 25° — see benchmarks/heading_restart.py.)"""
    b, start = _restarted(walk, 5.0, day_file(walk) if mode == "a" else None)
    head, sd = _restart_frames(walk, b, start)
    assert len(head) > 3000
    mean = float(np.mean(np.abs(head)))
    assert mean < 20.0, f"{walk} mode {mode} from 5 s: mean |error| {mean:.1f}°"
    beyond = float(np.mean(np.abs(head) > 3.0 * sd))
    assert beyond <= BEYOND_3SIGMA_MAX, f"{walk} mode {mode} from 5 s: {beyond:.0%} of the frames beyond 3σ"


def _restart_mean(walk: str, b, start: float) -> float:
    """The shared scorer's mean |heading error| of a replay started at ``start`` (:func:`_restarted`), scored
    from 5 s after it."""
    score = _scorer()
    truth = dataset("tyrex-pdrcsv", walk) / "truth.csv"
    t_ref, q_ref = score.C.read_quat_csv(str(truth))
    ok = np.all(np.isfinite(q_ref), axis=1)
    t_ref, q_ref = t_ref[ok], q_ref[ok]
    t0, _ = score.truth_t0(str(truth), t_ref)
    window = (max(score.WINDOW[0], start + 5.0 - t0), score.WINDOW[1])
    return score.score_arrays(t_ref, q_ref, b.t, b.q_wd, t0, window=window)["heading_err_mean"]


@pytest.mark.parametrize("mode", ("a", "b"))
@pytest.mark.parametrize("walk", WALKS)
def test_a_backend_started_20_s_into_a_walk_does_not_fail(walk, mode, day_file):
    """Issue 19: a backend started in the middle of a walk (replayed from 20 s in, the day's calibration in
    mode a, none in mode b), scored by the shared scorer from 5 s after the start: no walk above 45°.  The
    worst measured: mode a 23.2° (Nexus5_Dist_FrontPocket), mode b 25.5° (iPhone5_Dist_BackPocket;
    Nexus5_Dist_AR 19.7°: the next test)."""
    b, start = _restarted(walk, 20.0, day_file(walk) if mode == "a" else None)
    mean = _restart_mean(walk, b, start)
    assert mean < 45.0, f"{walk} mode {mode} from 20 s: mean |error| {mean:.1f}°"


def test_rows_without_a_heading_take_the_phones_on_a_restart_next_to_magnets():
    """Nexus5_Dist_AR replayed from 20 s in, no calibration: its first 33 s are inside the magnets' field (at
    most 6 % of the buffered samples the Earth's), no fit is possible and the heading is unknown (σ 180°).
    Those rows take the phone's own heading (``pdr_mag.pipeline.fill_unknown_heading``).  Scored from 5 s
    after the start, measured: the 1 717 frames at σ 180° 121.2° off with the filter's arbitrary start, 39.7°
    with the phone's heading; the walk's mean 43.5° → 19.7°; the σ as before."""
    from pdr_mag.pipeline.phone_heading import UNKNOWN_STD_DEG

    walk = "Thibaud_Nexus5_Dist_AR"
    figures = []
    for phone in (False, True):
        b, start = _restarted(walk, 20.0, None, phone)
        head, sd = _restart_frames(walk, b, start)
        unknown = sd >= UNKNOWN_STD_DEG
        assert unknown.sum() > 1500
        figures.append((float(np.mean(np.abs(head[unknown]))), _restart_mean(walk, b, start), b))
    (unknown_own, mean_own, own), (unknown_phone, mean_phone, with_phone) = figures
    assert unknown_phone < min(60.0, unknown_own), (unknown_own, unknown_phone)
    assert mean_phone < min(30.0, mean_own), (mean_own, mean_phone)
    assert np.array_equal(own.heading_std_deg, with_phone.heading_std_deg)


def test_a_heading_one_history_set_gives_way_to_a_longer_run_of_clean_fields():
    """A backend started 7.5 s into iPhone4S_Dist_Phoning, no calibration: its first calibration's heading,
    the mean of the fit's recent fields, is 161–175° off, and every clean field after it fails the gate.
    The run of those fields agrees among themselves long before the 20 s a heading resting on minutes of
    fields is held for; a run as long as the fields behind this heading span re-acquires it.  Scored as the
    20-s restarts (from 5 s after the start): mean below 45° — measured 34.9°, 46.7° when every lost heading
    was held for 20 s."""
    walk = "Thibaud_iPhone4S_Dist_Phoning"
    b, start = _restarted(walk, 7.5, None)
    mean = _restart_mean(walk, b, start)
    assert mean < 45.0, f"{walk} mode b from 7.5 s: mean |error| {mean:.1f}°"


def test_a_first_calibration_next_to_magnets_counts_the_place(day_file):
    """A backend started 30 s into Nexus5_Dist_AR, no calibration: the first fit comes 21 s later, its first
    heading from a field next to the magnets 127° off.  The filter's detectors had judged no field before
    (none was calibrated) and weighed that heading as a clean place's, at σ 10°: 2 733 frames 45° off at
    σ ≤ 20° until the field came back 46 s later.  Now the recent fields the fit calibrates give the share the
    detectors would have flagged (0.58) and its consider part: σ 21° from that heading on, no such frame."""
    b, start = _restarted("Thibaud_Nexus5_Dist_AR", 30.0, None)
    head, sd = _restart_frames("Thibaud_Nexus5_Dist_AR", b, start)
    assert np.sum(np.abs(head) > 45.0) > 2000  # the heading itself is as wrong as before: the σ says so
    kept = int(np.sum((np.abs(head) > 45.0) & (sd <= 20.0)))
    assert kept == 0, f"{kept} frames 45° off at σ ≤ 20°"
