"""Known-answer reproductions of the seeds' own simulations (seed 000 §4, seed 001 §3.1)."""

from __future__ import annotations

import numpy as np
import pytest
from _calibration_sim import seed000, seed001

from pdr_mag.calibration import (
    fit_als,
    fit_ellipsoid,
    fit_lm9,
    fit_ml,
    fit_radial_newton,
    fit_reference_rotation,
)

H_UT = 48.152
FITS = [fit_ml, fit_radial_newton, fit_lm9, fit_ellipsoid, fit_als]


def _compensated(cal, m, h):
    """Seed 000 eqs. 11–12: scale to the known |H|, then the rotation V_L fitted against the references."""
    mc = cal.apply(m) * (H_UT / cal.field_uT)
    v = fit_reference_rotation(mc, h)
    return mc @ v.T


@pytest.mark.parametrize("fit", FITS)
def test_seed000_noise_free_is_exact(fit):
    m, h, _, b = seed000()
    cal = fit(m)
    np.testing.assert_allclose(cal.offset_array, b, atol=1e-9 * H_UT)
    np.testing.assert_allclose(_compensated(cal, m, h), h, atol=1e-9 * H_UT)


@pytest.mark.parametrize("fit", [fit_ml, fit_radial_newton])
def test_seed000_with_noise_within_two_percent(fit):
    """The seed gives no noise level; at σ = 0.25 µT (0.5 % of H) the calibration compensates the field
    (eqs. 11–12 applied to the error-free readings) to a worst case of ≈ 0.085 % — the paper claims 2 %.
    On the noisy samples themselves the error is the propagated noise (RMS ≈ 0.74 %, max ≈ 1.9 %)."""
    rng = np.random.default_rng(0)
    sigma = 0.25
    m, h, s, b = seed000(sigma, rng)
    m_clean, _, _, _ = seed000()
    cal = fit(m)
    mc = cal.apply(m_clean) * (H_UT / cal.field_uT)
    v = fit_reference_rotation(cal.apply(m) * (H_UT / cal.field_uT), h)
    comp = mc @ v.T
    vec_err = np.linalg.norm(comp - h, axis=1) / H_UT
    assert vec_err.max() < 0.02
    noisy = _compensated(cal, m, h)
    rms = np.sqrt(np.mean(np.sum((noisy - h) ** 2, axis=1)))
    # the noise ε maps to (H/F)·V·soft_iron·ε: E|.|² = σ² (H/F)² ‖soft_iron‖_F²; over 1440 samples the
    # RMS has a relative sd ≈ 1/sqrt(2·1440) ≈ 2 %, so ±10 % is a 5-sd band
    expected = sigma * H_UT / cal.field_uT * np.linalg.norm(cal.soft_iron_array)
    assert rms == pytest.approx(expected, rel=0.1)


def test_seed001_parameters_recovered():
    """Seed 001 §3.1: every parameter of the 9-parameter model within 4 of its own 1-σ (from the LM
    Jacobian), and over repeated trials unbiased within 4 standard errors (the norm relative to k_z)."""
    rng = np.random.default_rng(1)
    est, std = [], []
    for _ in range(30):
        m, truth = seed001(rng)
        cal = fit_lm9(m)
        est.append(cal.extra["beta"])
        std.append(cal.extra["beta_std"])
        assert cal.extra["converged"]
    est, std = np.array(est), np.array(std)
    assert np.all(np.abs(est - truth) < 4 * std)
    se = est.std(axis=0, ddof=1) / np.sqrt(len(est))
    assert np.all(np.abs(est.mean(axis=0) - truth) < 4 * se)


def test_seed001_two_step_start_is_needed_and_ml_agrees():
    """The geometric ML on the same data gives the same offset within the joint uncertainty."""
    rng = np.random.default_rng(2)
    m, truth = seed001(rng)
    a, b = fit_lm9(m), fit_ml(m)
    sd = np.hypot(np.asarray(a.offset_std_uT), np.asarray(b.offset_std_uT))
    assert np.all(np.abs(a.offset_array - b.offset_array) < 4 * sd)
    assert np.all(np.abs(b.offset_array - truth[5:8]) < 4 * np.asarray(b.offset_std_uT))
