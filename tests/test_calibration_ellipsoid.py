"""Ellipsoid-specific algebraic fit and noise-compensated ALS (seed 004), two-step initial value."""

from __future__ import annotations

import numpy as np
import pytest
from _calibration_sim import F_UT, sample, soft_iron_ellipsoid

from pdr_mag.calibration import fit_als, fit_ellipsoid, fit_twostep, initial_ellipsoid
from pdr_mag.calibration.ellipsoid import ellipsoid_specific_solve
from pdr_mag.calibration.geometry import calibration_from_ellipsoid, monomials, quadric_to_ellipsoid
from pdr_mag.calibration.sphere import sphere_lls

Z = 3.5


@pytest.mark.parametrize("fit", [fit_ellipsoid, fit_als, fit_twostep])
def test_exact_on_noise_free_data(fit):
    rng = np.random.default_rng(4)
    b, L = soft_iron_ellipsoid(rng, spread=0.2)
    m, _ = sample(rng, 200, b, L, 0.0, "hemi")
    cal = fit(m)
    a, f = calibration_from_ellipsoid(L)
    np.testing.assert_allclose(cal.offset_array, b, atol=1e-8 * F_UT)
    np.testing.assert_allclose(cal.soft_iron_array, a, atol=1e-9)
    assert cal.field_uT == pytest.approx(f, rel=1e-10)
    assert np.linalg.det(cal.soft_iron_array) == pytest.approx(1.0, rel=1e-12)


def test_constraint_always_gives_an_ellipsoid():
    """Samples on a hyperboloid: plain LS would return a hyperboloid; the constrained fit an ellipsoid."""
    rng = np.random.default_rng(5)
    u = rng.uniform(-1, 1, (300, 2))
    x = np.column_stack([u, np.sqrt(1 + u[:, 0] ** 2 - u[:, 1] ** 2 * 0.5)])
    z = monomials(x)
    theta = ellipsoid_specific_solve(z.T @ z)
    b, L = quadric_to_ellipsoid(theta)  # raises if not an ellipsoid
    assert np.all(np.linalg.eigvalsh(L) > 0)


def test_als_estimates_noise_level():
    rng = np.random.default_rng(6)
    b, L = soft_iron_ellipsoid(rng)
    sigma = 0.03 * F_UT
    n = 2000
    cal = fit_als(sample(rng, n, b, L, sigma)[0])
    # the variance estimate has relative sd ≈ sqrt(2/(3N)) (3N noise components) to first order
    assert cal.extra["noise_std_uT"] == pytest.approx(sigma, abs=Z * sigma * np.sqrt(2 / (3 * n)))


@pytest.mark.parametrize("cover,what", [("full", "shape"), ("hemi", "offset")])
def test_als_removes_the_noise_bias_of_plain_ls(cover, what):
    """σ = 5 % of the field: ALS bias ≤ 1/5 of the plain (ellipsoid-specific) LS bias and consistent with
    zero.  Plain LS is biased in the shape with full coverage (noise rounds the ellipsoid) and, with a
    hemisphere only, in the offset too."""
    b, L = soft_iron_ellipsoid(np.random.default_rng(3), spread=0.15)
    a_true, _ = calibration_from_ellipsoid(L)
    trials, n = 100, 500

    def errors(fit):
        out = []
        for k in range(trials):
            cal = fit(sample(np.random.default_rng(1000 + k), n, b, L, 0.05 * F_UT, cover)[0])
            out.append(cal.offset_array - b if what == "offset" else (cal.soft_iron_array - a_true).ravel())
        return np.array(out)

    e_ls, e_als = errors(fit_ellipsoid), errors(fit_als)
    bias_ls, bias_als = np.linalg.norm(e_ls.mean(0)), np.linalg.norm(e_als.mean(0))
    se_als = np.linalg.norm(e_als.std(0, ddof=1)) / np.sqrt(trials)
    assert bias_als <= bias_ls / 5, f"ALS bias {bias_als:.4g} vs LS {bias_ls:.4g}"
    assert bias_als < Z * se_als


def test_twostep_on_planar_data_and_its_sphere_fallback():
    """Directions within ±3° of the x-y plane: the in-plane offset and semi-axes are determined (the
    circle fit's σ·sqrt(2/N) per component), the out-of-plane axis is not.  The ellipsoid is kept only
    while its axis ratio is within ``max_axis_ratio``; below the ratio it has, step 1's sphere is used."""
    rng = np.random.default_rng(8)
    b, L = soft_iron_ellipsoid(rng, spread=0.0)
    sigma, n = 0.5, 300
    m, _ = sample(rng, n, b, L, sigma, "planar")
    b0, L0, source = initial_ellipsoid(m)
    assert source == "ellipsoid"
    assert np.all(np.abs(b0[:2] - b[:2]) < Z * sigma * np.sqrt(2 / n))
    in_plane = np.linalg.eigvalsh(L0[:2, :2])
    np.testing.assert_allclose(in_plane, F_UT, atol=Z * sigma * np.sqrt(2 / n) * 2)
    ax = np.linalg.eigvalsh(L0)
    assert ax[-1] / ax[0] <= 3.0
    b1, L1, source1 = initial_ellipsoid(m, max_axis_ratio=0.9 * ax[-1] / ax[0])
    assert source1 == "sphere"
    b_s, r_s, _ = sphere_lls(m)  # step 1 itself
    np.testing.assert_allclose(b1, b_s, rtol=0, atol=1e-12 * F_UT)
    np.testing.assert_allclose(L1, r_s * np.eye(3), rtol=1e-14, atol=0)


def test_als_with_known_noise_shape():
    """Seed 004's per-axis noise σx:σy:σz known, amplitude unknown: the amplitude is recovered and the
    shape is unbiased, while assuming isotropic noise leaves a bias of many standard errors."""
    from _calibration_sim import directions

    b, L = soft_iron_ellipsoid(np.random.default_rng(3), spread=0.15)
    a_true, _ = calibration_from_ellipsoid(L)
    w, amp, trials = np.array([1.0, 2.0, 0.5]), 1.5, 60
    e_shape, e_iso, sig = [], [], []
    for k in range(trials):
        rng = np.random.default_rng(k)
        x = b + directions(rng, 600) @ L.T
        m = x + rng.standard_normal(x.shape) * w * amp
        cal = fit_als(m, noise_shape=w)
        e_shape.append((cal.soft_iron_array - a_true).ravel())
        e_iso.append((fit_als(m).soft_iron_array - a_true).ravel())
        sig.append(cal.extra["noise_std_uT"])
    e_shape, e_iso, sig = np.array(e_shape), np.array(e_iso), np.array(sig)
    se = np.linalg.norm(e_shape.std(0, ddof=1)) / np.sqrt(trials)
    assert np.linalg.norm(e_shape.mean(0)) < Z * se
    assert np.linalg.norm(e_iso.mean(0)) > 3 * Z * se
    se_sig = sig.std(0, ddof=1) / np.sqrt(trials)
    assert np.all(np.abs(sig.mean(0) - w * amp) < Z * se_sig)
