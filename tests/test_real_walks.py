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

* mode a ≤ max(best ``_cal_gcal`` peer + :data:`MARGIN_DEG`, :data:`FLOOR_DEG`).  The peers given the day's
  magnetometer calibration *and* the day's gyro offset are the strongest reference on each walk; mode a
  gets the magnetometer file only and must learn the gyro offset itself, which a filter with a bias state
  can.  ``MARGIN_DEG`` = 2°: the motion-capture body is not exactly aligned with the phone (PEERS.md: a
  1–2° floor), so two estimators that are equally right about the phone differ by up to that much.
  ``FLOOR_DEG`` = 3°: that floor plus the residual phone/mocap clock offset (−30…+35 ms, PEERS.md), which
  moves a walk's figure by up to 1.5° (mode a shifted by ±35 ms on six NoDist walks: 0.1–1.5°).
* mode b ≤ max(``os``, best ``_cal`` peer) + ``MARGIN_DEG``: starting with no calibration at all, mode b
  fails when it is worse than both the phone's own fusion (``os``: its own long-term calibration, no day
  file) and every peer given the day's magnetometer file but a raw gyroscope.
* honesty, both modes: at most :data:`BEYOND_3SIGMA_MAX` of a walk's scored frames with |error| beyond
  3σ of ``heading_std_deg`` (a Gaussian gives 0.3 %; issue 10's target).

Walks that fail a bound today are ``xfail(strict=True)`` naming issue 10: they flip (and the strict xfail
fails) when the filter is fixed — then delete them from the lists below.
"""

from __future__ import annotations

import contextlib
import importlib.util
import io
import json
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import DATASETS, ROOT, absent, dataset

TYREX = DATASETS / "tyrex-pdrcsv"
SCORER = ROOT.parent / "shared" / "benchmarks" / "tyrex" / "score.py"
FIXTURE = ROOT / "tests" / "fixtures" / "tyrex_peers.json"
MARGIN_DEG = 2.0
FLOOR_DEG = 3.0
BEYOND_3SIGMA_MAX = 0.10
ISSUE = "issue 10 (a heading that never fails): "

#: walk → its mode-a figure against its bound today (benchmarks/heading.py; p95, the magnetometer's
#: longest absence over the scored frames)
XFAIL_A: dict[str, str] = {
    "Thibaud_Nexus5_Dist_Phoning": "12.6° > 11.1° (madgwick_cal_gcal 9.1° + 2°); p95 83°, the field left"
    " out for up to 19 s in the disturbed area",
    "Thibaud_Nexus5_NoDist_BackPocket": "5.4° > 4.3° (imufusion_cal_gcal 2.3° + 2°); a steady offset,"
    " median 5.0°",
    "Thibaud_Nexus5_NoDist_RunningHand": "9.6° > 9.0° (vqf_cal_gcal 7.0° + 2°; vqf_cal 3.1°); running in"
    " hand, the ±2-g accelerometer clipped on 23 % of the samples",
    "Thibaud_iPhone4S_NoDist_Phoning": "8.7° > 5.4° (vqf_cal_gcal 3.4° + 2°); p95 23°, a recalibration"
    " requested mid-walk",
    "Thibaud_iPhone4S_NoDist_RunningHand": "91.1° > 3.9° (vqf_cal_gcal 1.9° + 2°); running in hand: the"
    " field left out for up to 15 s, the heading 90° off and never re-acquired; the ±2-g accelerometer"
    " clipped on 27 % of the samples",
    "Thibaud_iPhone4S_NoDist_RunningPocket": "4.1° > 3.9° (vqf_cal_gcal 1.9° + 2°)",
    "Thibaud_iPhone5_Dist_BackPocket": "6.9° > 6.1° (madgwick_cal_gcal 4.1° + 2°); the field left out for up"
    " to 20 s in the disturbed area",
    "Thibaud_iPhone5_Dist_Swinging": "10.9° > 10.4° (imufusion_cal_gcal 8.4° + 2°); the field left out for up"
    " to 15 s in the disturbed area",
}
#: walk → its mode-b figure against its bound today
XFAIL_B: dict[str, str] = {
    "Thibaud_Nexus5_NoDist_FrontPocket": "6.42° > 6.41° (os 4.4° + 2°), by 0.01°; median 2.2°: the error is"
    " before and around the first online calibration",
    "Thibaud_Nexus5_NoDist_RunningHand": "9.5° > 6.7° (os 4.7° + 2°); running in hand",
    "Thibaud_Nexus5_NoDist_RunningPocket": "7.5° > 6.4° (os 4.4° + 2°); running, phone in a pocket",
    "Thibaud_iPhone4S_NoDist_AR": "10.6° > 7.7° (os 5.7° + 2°); median 9.6°: a steady error of the online"
    " calibration (hard iron 593 µT)",
    "Thibaud_iPhone4S_NoDist_Texting": "97.5° > 6.4° (os 4.4° + 2°); the field left out for half of the walk"
    " after the online calibration, the heading 100° off",
}
#: (walk, mode) → the share of its frames beyond 3σ today
XFAIL_STD: dict[tuple[str, str], str] = {
    ("Thibaud_Nexus5_NoDist_RunningHand", "a"): "30 % of the frames beyond 3σ",
    ("Thibaud_Nexus5_NoDist_RunningHand", "b"): "30 % of the frames beyond 3σ",
    ("Thibaud_iPhone4S_NoDist_RunningHand", "a"): "77 % of the frames beyond 3σ (error 91°, median σ 14°)",
    ("Thibaud_iPhone5_Dist_AR", "a"): "16 % of the frames beyond 3σ",
    ("Thibaud_iPhone4S_Dist_AR", "b"): "23 % of the frames beyond 3σ",
    ("Thibaud_iPhone4S_NoDist_AR", "b"): "17 % of the frames beyond 3σ",
    ("Thibaud_iPhone4S_NoDist_Texting", "b"): "80 % of the frames beyond 3σ (error 97°, median σ 16°)",
    ("Thibaud_iPhone5_Dist_AR", "b"): "53 % of the frames beyond 3σ",
}


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


def _params(xfails: dict, key=lambda w: w):
    return [
        pytest.param(w, marks=pytest.mark.xfail(strict=True, reason=ISSUE + xfails[key(w)]))
        if key(w) in xfails
        else w
        for w in WALKS
    ]


# ------------------------------------------------------------------------------------------ machinery
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
def run(tmp_path_factory):
    """``run(walk, mode)`` → (mean |heading error|, share of frames beyond 3σ); each replay done once."""
    from replay.cli import main
    from replay.run import CsvSink, replay

    score = _scorer()
    tmp = tmp_path_factory.mktemp("day_calibrations")
    cache: dict = {}

    class Keep(CsvSink):  # the settings of `replay --out-csv`, nothing written
        def __init__(self):
            self.batches = []

        def open(self, meta):
            pass

        def estimates(self, batch):
            self.batches.append(batch)

        def close(self):
            pass

    def day_file(name: str) -> Path:
        path = tmp / f"{name}.json"
        if not path.exists():
            with contextlib.redirect_stdout(io.StringIO()):
                assert main(["calibrate", str(dataset("tyrex-pdrcsv", name)), "--json", str(path)]) == 0
        return path

    def figures(b, t_ref, q_ref, t0):
        mean = score.score_arrays(t_ref, q_ref, b.t, b.q_wd, t0)["heading_err_mean"]
        # the frames score_arrays scores: in the window, inside the estimate, no estimate gap > 1 s
        w = (t_ref >= t0 + score.WINDOW[0]) & (t_ref <= t0 + score.WINDOW[1])
        qi, valid = score.C.slerp_at(b.t, b.q_wd, t_ref[w])
        i = np.clip(np.searchsorted(b.t, t_ref[w], side="right") - 1, 0, len(b.t) - 2)
        valid &= b.t[i + 1] - b.t[i] <= 1.0
        _, head, _ = score.error_angles(qi[valid], q_ref[w][valid])
        sd = np.interp(t_ref[w][valid], b.t, b.heading_std_deg)
        beyond = float(np.mean(np.abs(head) > 3.0 * sd))
        return mean, beyond

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
            for m, cal in (("a", day_file(json.loads((d / "trial.json").read_text())["calib"])), ("b", None)):
                sink = Keep()
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


def _best(p: dict, suffix: str) -> float:
    return min(v for k, v in p.items() if k.endswith(suffix))


@pytest.mark.parametrize("walk", _params(XFAIL_A))
def test_mode_a_within_the_best_peer_given_the_day_calibration(walk, peers, run):
    mean, _ = run(walk, "a")
    bound = max(_best(peers[walk], "_cal_gcal") + MARGIN_DEG, FLOOR_DEG)
    assert mean <= bound, f"{walk}: mode a {mean:.1f}° > {bound:.1f}°"


@pytest.mark.parametrize("walk", _params(XFAIL_B))
def test_mode_b_not_worse_than_both_the_phone_and_the_peers(walk, peers, run):
    mean, _ = run(walk, "b")
    p = peers[walk]
    bound = max(p["os"], _best(p, "_cal")) + MARGIN_DEG
    assert mean <= bound, f"{walk}: mode b {mean:.1f}° > {bound:.1f}°"


@pytest.mark.parametrize("mode", ["a", "b"])
@pytest.mark.parametrize("walk", WALKS)
def test_heading_std_warns_when_the_heading_is_wrong(walk, mode, run, request):
    if (walk, mode) in XFAIL_STD:
        request.applymarker(pytest.mark.xfail(strict=True, reason=ISSUE + XFAIL_STD[(walk, mode)]))
    _, beyond = run(walk, mode)
    assert beyond <= BEYOND_3SIGMA_MAX, f"{walk} mode {mode}: {beyond:.0%} of the frames beyond 3σ"
