"""The recording's own null (issue 11): surrogate residuals and the decision threshold."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from pdr_mag.modelcheck.fit import fit_model, make_problem
from pdr_mag.modelcheck.null import (
    NullSettings,
    null_threshold,
    robust_sigma,
    stride_for,
    subsample,
    surrogate_residuals,
)
from pdr_mag.modelcheck.orientation import estimate_orientation
from pdr_mag.sim import simulate


@pytest.fixture(scope="module")
def walk_fit():
    r = simulate("walk", seed=4, duration_s=60.0, effects={"hard_iron": (22.0, -31.0, 48.0), "noise": 0.4},
                 defaults=False)
    tr = estimate_orientation(*r.gyro, *r.accel)
    p = make_problem(*r.mag, tr)
    return p, fit_model(p, ())


def _field_frame(p, f):
    b = np.asarray(f.linear["field_w"])
    u = b / np.linalg.norm(b)
    h = p.r_dw0 @ u  # field direction in device axes per sample
    return u, h


def _along(res, h):
    return np.einsum("ni,ni->n", res, h)


@pytest.mark.parametrize("alpha", [0.01, 0.05])
def test_prediction_bound_false_alarm_is_alpha_for_gaussian_draws(alpha):
    """One more draw beats the bound of m Gaussian draws with probability α (replicates' randomness
    included): estimated over 3000 sets, binomial 4-σ tolerance."""
    rng = np.random.default_rng(7)
    m, sets = 12, 3000
    thr = np.array([null_threshold(rng.normal(2.0, 0.5, m), alpha, cube_root=False) for _ in range(sets)])
    fa = stats.norm.sf(thr, 2.0, 0.5).mean()
    assert abs(fa - alpha) < 4 * np.sqrt(alpha * (1 - alpha) / sets) + 0.1 * alpha


@pytest.mark.parametrize("shape", [0.5, 1.5, 5.0, 25.0])
def test_cube_root_bound_holds_for_chi2_like_statistics(shape):
    """A nested fit's gain is χ²-like (Gamma, shape k/2): the Wilson–Hilferty bound keeps the false-alarm
    rate within a factor 1.6 of α from one to fifty degrees of freedom."""
    rng = np.random.default_rng(8)
    alpha, m, sets = 0.01, 12, 3000
    thr = np.array([null_threshold(rng.gamma(shape, 1.0, m), alpha) for _ in range(sets)])
    fa = stats.gamma.sf(thr, shape).mean()
    assert alpha / 1.6 < fa < alpha * 1.6


def test_threshold_needs_two_replicates():
    assert null_threshold([0.3], 1e-3) == float("inf")
    assert null_threshold([0.1, 0.2, 0.15], 1e-3) > 0.2


def test_surrogate_keeps_noise_along_the_field_and_power_across_it(walk_fit):
    p, f = walk_fit
    u, h = _field_frame(p, f)
    par = _along(f.residual, h)
    perp2 = np.sum(f.residual**2, axis=1) - par**2
    reps = surrogate_residuals(p, f, np.random.default_rng(1), 12)
    power = []
    for s in reps:
        s_par = _along(s, h)
        # along the field: white noise of the residual's own σ (the sample σ of 3000 draws: ±1.3 %)
        assert np.std(s_par) == pytest.approx(robust_sigma(par), rel=0.05)
        assert abs(np.corrcoef(s_par[1:], s_par[:-1])[0, 1]) < 0.08  # white
        power.append(np.mean(np.sum(s**2, axis=1) - s_par**2))
        # not the residual itself
        assert abs(np.corrcoef(s[:, 0], f.residual[:, 0])[0, 1]) < 0.5
    # across it: the residual's power on average (random phases keep the amplitude spectrum; the
    # envelope of the band of bursts makes a replicate's power vary, by ≈ 8 % here)
    assert np.mean(power) == pytest.approx(np.mean(perp2), rel=0.2)


def test_surrogate_keeps_a_burst_in_place(walk_fit):
    """A burst of orientation error (a turn) stays where it is in every replicate; its shape does not."""
    from dataclasses import replace

    p, f = walk_fit
    u, _ = _field_frame(p, f)
    e1 = np.cross(u, [0.0, 0.0, 1.0])
    e1 /= np.linalg.norm(e1)
    t_mid = p.t[0] + 0.6 * (p.t[-1] - p.t[0])
    bump = 4.0 * np.exp(-0.5 * ((p.t - t_mid) / 0.8) ** 2)  # µT, across the field, world frame
    res = f.residual + np.einsum("nij,j->ni", p.r_dw0, e1) * bump[:, None]
    f2 = replace(f, residual=res)
    near = np.abs(p.t - t_mid) < 1.5
    far = np.abs(p.t - t_mid) > 10.0

    def rms(x):
        return np.sqrt(np.mean(np.sum(x**2, axis=1)))

    # the residual: 2.8 µT near the burst, 1.2 µT elsewhere; a stationary surrogate would spread the
    # burst's energy over the minute (≈ 1.3 µT near and far: ratio ≈ 1)
    assert rms(res[near]) > 2.0 * rms(res[far])
    reps = surrogate_residuals(p, f2, np.random.default_rng(2), 12)
    ratio = [rms(s[near]) / rms(s[far]) for s in reps]
    assert np.mean(ratio) > 1.4  # a replicate's own ratio varies (1–3) with its random phases
    assert np.mean([rms(s[near]) for s in reps]) > 0.6 * rms(res[near])


def test_subsample_to_the_null_rate(walk_fit):
    p, _ = walk_fit
    k = stride_for(p, NullSettings().max_rate_hz)
    assert k == 4  # ≈ 50 Hz magnetometer → 12.5 Hz
    s = subsample(p, k)
    assert np.array_equal(s.t, p.t[::k]) and np.array_equal(s.mag, p.mag[::k])
    assert s.r_dw0.shape == (len(s.t), 3, 3)
    assert subsample(p, 1) is p


def test_pick_asks_only_about_local_anomaly_after_a_winner():
    """select._pick: after the first candidate that passes, only a local_anomaly ranked after a winning
    hard_iron_change is asked about (each question is a null test); it displaces it within the margin."""
    from pdr_mag.modelcheck.select import _LOCAL_MARGIN, _pick

    def run(ranked, passing):
        asked = []

        def passes(eff):
            asked.append(eff)
            return eff in passing

        return _pick(ranked, passes), asked

    close = 2.0 * (1.0 - _LOCAL_MARGIN / 2)  # local_anomaly's gap within the margin of hard_iron_change's 2.0
    ranked = {"time_offset": 1.0, "hard_iron_change": 2.0, "soft_iron": 2.0, "local_anomaly": close}
    assert run(ranked, {"hard_iron_change", "soft_iron", "local_anomaly"}) == (
        "local_anomaly", ["time_offset", "hard_iron_change", "local_anomaly"])
    assert run(ranked, {"hard_iron_change", "soft_iron"}) == (
        "hard_iron_change", ["time_offset", "hard_iron_change", "local_anomaly"])
    far = dict(ranked, local_anomaly=3.0)
    assert run(far, {"hard_iron_change", "local_anomaly"})[0] == "hard_iron_change"
    assert run(ranked, {"time_offset", "hard_iron_change"}) == ("time_offset", ["time_offset"])
    before = {"local_anomaly": close, "hard_iron_change": 2.0, "soft_iron": 2.0}
    assert run(before, {"hard_iron_change", "soft_iron"}) == (
        "hard_iron_change", ["local_anomaly", "hard_iron_change"])
    assert run(ranked, set()) == (None, list(ranked))
