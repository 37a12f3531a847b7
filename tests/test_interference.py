"""Interference detectors: each with its disturbance present and absent — the vectorised functions and the
same checks inside the fusion kernel on a simulated walk with injected world-frame disturbances."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pdr_mag._records import settings_record
from pdr_mag.estimates import EstimateBatch
from pdr_mag.fusion import FusionCore
from pdr_mag.fusion.detectors import DipSettings, InterferenceSettings, hold_off
from pdr_mag.fusion.detectors.consistency import consistency_angle_deg
from pdr_mag.fusion.detectors.dip import dip_deg
from pdr_mag.fusion.detectors.strength import strength_score
from pdr_mag.fusion.detectors.variance import windowed_variance
from pdr_mag.sim import simulate
from tests.test_attitude import error_at_truth, merge

S = InterferenceSettings()


# ------------------------------------------------------------------------------------------ vectorised
def test_strength_score_present_and_absent():
    ref = 48.0
    tol = max(S.strength.tol_uT, S.strength.tol_rel * ref)
    d = np.array([[0.0, 0.0, 1.0]])
    f, s = strength_score(ref * d, ref)
    assert f[0] == pytest.approx(ref) and s[0] == pytest.approx(0.0)
    f, s = strength_score((ref + 1.5 * tol) * d, ref)
    assert s[0] == pytest.approx(1.5)


def test_dip_angle_of_known_geometry():
    inc = np.radians(61.0)
    m = 47.0 * np.array([[0.0, np.cos(inc), -np.sin(inc)]])  # device = world (flat, y north)
    assert dip_deg(m, [[0.0, 0.0, 9.81]])[0] == pytest.approx(61.0)
    tilted = Rotation.from_euler("x", 20.0, degrees=True)  # device pitched: both vectors turn together
    assert dip_deg(tilted.inv().apply(m), tilted.inv().apply([[0.0, 0.0, 1.0]]))[0] == pytest.approx(61.0)
    assert dip_deg(m, [[0.0, np.sin(0.3), np.cos(0.3)]])[0] != pytest.approx(61.0, abs=5.0)


def test_windowed_variance_present_and_absent():
    t = np.arange(0.0, 10.0, 0.02)
    assert np.all(windowed_variance(t, np.full(len(t), 47.0), 1.0) < 1e-9)
    amp = 5.0
    v = windowed_variance(t, 47.0 + amp * np.sin(2 * np.pi * 3.0 * t), 1.0)
    assert np.mean(v[t > 5]) == pytest.approx(amp**2 / 2, rel=0.2)


def test_consistency_angle_present_and_absent():
    t = np.arange(0.0, 10.0, 0.02)
    f = np.tile([0.0, 22.8, -41.2], (len(t), 1))
    assert np.all(consistency_angle_deg(t, f, 2.0) < 1e-6)
    turned = f.copy()
    turned[t >= 5.0] = Rotation.from_euler("z", 90.0, degrees=True).apply(f[t >= 5.0])
    a = consistency_angle_deg(t, turned, 2.0)
    assert a[np.searchsorted(t, 5.0)] > 30.0  # the field turned in the world frame
    assert a[-1] < 5.0  # …and the mean direction follows a field that stays turned


def test_hold_off_neither_flickers_nor_sticks():
    t = np.arange(0.0, 10.0, 0.02)
    score = np.zeros(len(t))
    score[(t >= 2.0) & (t < 4.0)] = np.where(np.arange(np.sum((t >= 2.0) & (t < 4.0))) % 2, 0.0, 3.0)
    flag = hold_off(t, score)
    on = (t >= 2.0) & (t < 4.0)
    assert flag[on].all()  # alternating good/bad samples: no flicker
    assert not flag[t < 2.0].any()
    assert not flag[t >= 4.0 + S.hold_off_s + 0.05].any()  # falls after hold_off_s of clean samples
    assert flag[(t > 4.0) & (t < 4.0 + S.hold_off_s - 0.05)].all()


def test_settings_validation():
    with pytest.raises(ValueError, match=r"DipSettings\.tol_deg"):
        InterferenceSettings(dip=DipSettings(tol_deg=0.0))
    with pytest.raises(ValueError, match="hold_off_s"):
        InterferenceSettings(hold_off_s=-1.0)


# ------------------------------------------------------------------------------------------ in the kernel
@pytest.fixture(scope="module")
def walk():
    return simulate(
        "walk", seed=5, effects={"hard_iron": None, "soft_iron": None, "gyro_bias": (0.0, 0.0, 0.07)}
    )


T0, T1 = 60.0, 70.0  # the disturbance window


def _disturbed(walk, field_w_fn):
    """Magnetometer with the world-frame field replaced by field_w_fn(field_w) inside [T0, T1)."""
    tm, m = walk.mag
    f_w = np.asarray(walk.field.field_w)
    inside = (tm >= T0) & (tm < T1)
    rot = Rotation.from_quat(walk.trajectory.orientation(tm[inside])[:, [1, 2, 3, 0]])
    m = m.copy()
    m[inside] += rot.inv().apply(field_w_fn(f_w) - f_w)
    return m


def _run(walk, mag):
    core = FusionCore(field=walk.field)
    b = core.process(*merge(walk, mag))
    return b


def _fractions(b):
    inside = (b.t >= T0 + 0.2) & (b.t < T1)
    outside = ((b.t > 10.0) & (b.t < T0)) | (b.t > T1 + 2.0)
    return b.interference[inside].mean(), b.interference[outside].mean(), inside


def test_clean_walk_is_not_flagged(walk):
    b = _run(walk, walk.mag[1])
    assert b.interference[b.t > 5.0].mean() < 0.01
    late = b.t > 30.0
    # the learnt local references settle on the true field
    assert np.median(b.diag["field_ref_uT"][late]) == pytest.approx(walk.field.strength, abs=1.0)
    # (the measured dip carries the tilt error of a walking hand, ~1–2°)
    assert np.median(b.diag["dip_ref_deg"][late]) == pytest.approx(walk.field.inclination_deg, abs=3.0)


def test_strength_detector(walk):
    # +30 µT along the field: strength off, dip and direction unchanged
    mag = _disturbed(walk, lambda f: f * (1.0 + 30.0 / np.linalg.norm(f)))
    b = _run(walk, mag)
    fin, fout, inside = _fractions(b)
    assert fin > 0.95 and fout < 0.01
    assert not b.mag_used[inside].any()
    assert np.all(b.diag["interference_score"][inside] >= 1.0)


def test_dip_detector(walk):
    # the field tilted 25° about east: same strength, same horizontal direction, dip 25° off
    rot = Rotation.from_euler("x", 25.0, degrees=True)
    mag = _disturbed(walk, lambda f: rot.apply(f))
    b = _run(walk, mag)
    fin, fout, inside = _fractions(b)
    assert fin > 0.95 and fout < 0.01
    assert np.all(np.abs(b.diag["dip_deg"][inside] - b.diag["dip_ref_deg"][inside]) > S.dip.tol_deg)


def test_gyro_consistency_detector(walk):
    # the field turned 120° about up: strength and dip unchanged — only the gyroscope can tell
    rot = Rotation.from_euler("z", 120.0, degrees=True)
    mag = _disturbed(walk, lambda f: rot.apply(f))
    b = _run(walk, mag)
    onset = (b.t >= T0 + 0.05) & (b.t < T0 + 1.0)
    assert b.interference[onset].all()
    assert b.diag["consistency_deg"][onset].max() > S.consistency.tol_deg
    # strength and dip saw nothing
    f_ok = np.abs(b.diag["field_strength_uT"][onset] - walk.field.strength) < 3.0
    assert f_ok.all()
    # the heading does not follow the turned field (flag, then the innovation gate): against the clean
    # walk's own error it moves by what 10 s on the gyroscope drift, measured 1.3° at most (following the
    # field would be 120°); 3° leaves the gyro's drift its spread
    tt, qt = walk.truth
    w = (tt >= T0) & (tt < T1 + 5.0)
    err = error_at_truth(b, tt[w], qt[w])
    clean = _run(walk, walk.mag[1])
    err_clean = error_at_truth(clean, tt[w], qt[w])
    assert np.max(np.abs(err_clean)) < 3.0  # the clean walk itself: 1.13° at most, measured
    assert np.max(np.abs(err - err_clean)) < 3.0
    assert not clean.interference[(clean.t >= T0) & (clean.t < T1)].any()


def test_variance_detector(walk):
    # strength oscillating ±15 µT at 3 Hz along the field (a motor, a vibrating magnet)
    def osc_mag():
        tm, m = walk.mag
        f_w = np.asarray(walk.field.field_w)
        inside = (tm >= T0) & (tm < T1)
        rot = Rotation.from_quat(walk.trajectory.orientation(tm[inside])[:, [1, 2, 3, 0]])
        amp = 15.0 * np.sin(2 * np.pi * 3.0 * tm[inside])[:, None]
        m = m.copy()
        m[inside] += rot.inv().apply(amp * f_w / np.linalg.norm(f_w))
        return m

    b = _run(walk, osc_mag())
    inside = (b.t >= T0 + 1.0) & (b.t < T1)
    assert np.median(b.diag["strength_var_uT2"][inside]) > S.variance.max_uT2
    assert b.interference[inside].mean() > 0.95
    clean = _run(walk, walk.mag[1])
    assert np.max(clean.diag["strength_var_uT2"][clean.t > 5.0]) < 0.1 * S.variance.max_uT2


def test_heading_survives_a_strong_disturbance(walk):
    # a magnet-like 80 µT field fixed in the world for 10 s: rejected; heading on the gyro meanwhile
    mag = _disturbed(walk, lambda f: f + np.array([60.0, -40.0, 35.0]))
    b = _run(walk, mag)
    tt, qt = walk.truth
    w = (tt >= T0) & (tt < T1 + 5.0)
    err = error_at_truth(b, tt[w], qt[w])
    # against the clean walk's own error: 10 s on the gyroscope, measured 1.5° at most
    clean = _run(walk, walk.mag[1])
    err_clean = error_at_truth(clean, tt[w], qt[w])
    assert np.max(np.abs(err_clean)) < 3.0  # the clean walk itself: 1.13° at most, measured
    assert np.max(np.abs(err - err_clean)) < 3.0
    inside = (b.t >= T0 + 0.2) & (b.t < T1)
    assert np.all(np.diff(b.heading_std_deg[inside]) >= -1e-9)  # std grows while rejected


def test_kernel_step_matches_the_vectorised_functions():
    """detect_step (what the fusion kernel runs per sample) gives the numbers of the array functions."""
    from pdr_mag.fusion.detectors import detect_step, new_detector_state


    rng = np.random.default_rng(3)
    t = np.cumsum(rng.uniform(0.015, 0.025, 400))
    f_w = np.array([0.6, 22.8, -41.2])
    turn = Rotation.from_euler("z", np.cumsum(rng.normal(0.0, 1.0, len(t)))[:, None], degrees=True)
    m_w = turn.apply(f_w) * (1.0 + 0.05 * np.sin(t))[:, None]
    f = np.linalg.norm(m_w, axis=1)
    u = m_w / f[:, None]
    det = new_detector_state()
    ip = settings_record(S)[0]
    out = []
    for i in range(len(t)):
        det["x"]["t"], det["x"]["f"], det["x"]["dip"], det["x"]["mw"] = t[i], f[i], 61.0, u[i]
        det["x"]["f_ref"], det["x"]["dip_ref"], det["x"]["sigma_b_deg"] = 47.0, 61.0, 0.0
        flag = detect_step(det, ip)
        out.append((flag, det["score"], det["variance"]["var"], det["consistency"]["angle"]))
    out = np.array(out)
    np.testing.assert_allclose(out[:, 2], windowed_variance(t, f, S.variance.window_s), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(out[:, 3], consistency_angle_deg(t, m_w, S.consistency.window_s), atol=1e-6)
    np.testing.assert_array_equal(out[:, 0].astype(bool), hold_off(t, out[:, 1]))


def test_a_start_next_to_steel_guesses_from_the_flagged_fields():
    """A start inside a disturbed area (a site where the field is shallow, I ≈ 36°: B_h ≈ 36 µT): the first
    sample's field is turned 60° by 60 µT across it, then for 20 s the walker passes steel that adds 22 µT
    along the field (flagged against the reference's band) and ±10 µT across it (turning it ±11°,
    alternating every 1.5 s).  The heading is a guess (std 180°) until the field is clean; meanwhile it is
    the weighted mean of the flagged fields' headings, not the first sample's."""
    site = {"latitude_deg": 25.0, "longitude_deg": 121.5, "date": "2026-06-01"}
    w = simulate("walk", seed=7, site=site, effects={"hard_iron": None, "soft_iron": None, "gyro_bias": None})
    tm, m = w.mag
    f_w = np.asarray(w.field.field_w)
    along = f_w / np.linalg.norm(f_w)
    across = np.array([-f_w[1], f_w[0], 0.0]) / np.hypot(f_w[0], f_w[1])
    d_w = np.zeros((len(tm), 3))
    walk_in = tm < 20.0
    d_w[walk_in] = 22.0 * along + 10.0 * np.sign(np.sin(2 * np.pi * tm[walk_in] / 3.0))[:, None] * across
    d_w[tm < tm[0] + 0.3] = 60.0 * across
    rot = Rotation.from_quat(w.trajectory.orientation(tm)[:, [1, 2, 3, 0]])
    b = _run(w, m + rot.inv().apply(d_w))
    tt, qt = w.truth
    err = error_at_truth(b, tt, qt)
    tt = tt[(tt >= b.t[0]) & (tt <= b.t[-1])]
    assert abs(err[0]) > 45.0  # the first field alone
    flagged = (b.t > 1.0) & (b.t < 19.0)
    assert np.all(b.heading_std_deg[flagged] > 179.0)  # still a guess
    assert not b.mag_used[flagged].any()
    guess = (tt > 10.0) & (tt < 19.0)
    assert np.median(np.abs(err[guess])) < 10.0  # measured 3.6° (the first sample's guess held: 60°)
    late = tt > 30.0
    assert np.max(np.abs(err[late])) < 3.0  # measured 0.7°: the clean field takes over, the bias untaught

    # the guess is state like any other: cut anywhere, resumed from JSON inside the guess, the same rows
    kind, t, xyz = merge(w, m + rot.inv().apply(d_w))
    cuts = np.sort(np.random.default_rng(3).choice(np.arange(1, len(t)), size=20, replace=False))
    mid = int(np.searchsorted(t, 10.0))
    core = FusionCore(field=w.field)
    parts = []
    for a, z in zip(np.r_[0, cuts], np.r_[cuts, len(t)], strict=True):
        if a <= mid < z:
            parts.append(core.process(kind[a:mid], t[a:mid], xyz[a:mid]))
            saved = json.loads(json.dumps(core.get_state()))
            assert saved["state"]["guess_w"] > 0.0
            core = FusionCore(field=w.field)
            core.set_state(saved)
            a = mid
        parts.append(core.process(kind[a:z], t[a:z], xyz[a:z]))
    chunked = EstimateBatch.concat(parts)
    for name in ("t", "q_wd", "heading_std_deg", "mag_used", "interference"):
        assert np.array_equal(getattr(b, name), getattr(chunked, name)), name
