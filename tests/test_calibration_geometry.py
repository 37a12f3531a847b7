"""Ellipsoid geometry: orthogonal projection, its Jacobian, curvature, decomposition."""

from __future__ import annotations

import numpy as np
import pytest
from _calibration_sim import directions, soft_iron_ellipsoid
from scipy.optimize import minimize_scalar

from pdr_mag.calibration.geometry import (
    Projection,
    calibration_from_ellipsoid,
    geometric_jacobian,
    sym_basis,
    sym_coords,
)


def test_projection_is_the_closest_point():
    rng = np.random.default_rng(0)
    b, L = soft_iron_ellipsoid(rng, spread=0.2)
    m = b + directions(rng, 50) @ L.T * rng.uniform(0.85, 1.15, (50, 1))
    p = Projection(m, b, L)
    assert p.fallback == 0
    np.testing.assert_allclose(np.linalg.norm(p.u, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(p.x, b + p.u @ L.T, atol=1e-9)
    np.testing.assert_allclose(np.abs(p.d), np.linalg.norm(m - p.x, axis=1), atol=1e-9)
    # no point of the ellipsoid is closer: check along a fine sweep of directions near the foot point
    for i in range(0, 50, 7):
        for tang in np.linalg.svd(p.u[i : i + 1])[2][1:]:
            def dist(s, i=i, tang=tang):
                v = p.u[i] * np.cos(s) + tang * np.sin(s)
                return np.linalg.norm(m[i] - b - L @ v)
            best = minimize_scalar(dist, bounds=(-0.3, 0.3), method="bounded", options={"xatol": 1e-10})
            assert best.fun >= abs(p.d[i]) - 1e-7


def test_jacobian_matches_finite_differences():
    rng = np.random.default_rng(1)
    b, L = soft_iron_ellipsoid(rng, spread=0.2)
    m = b + directions(rng, 40) @ L.T * rng.uniform(0.9, 1.1, (40, 1))
    basis = sym_basis("full")
    theta = np.concatenate([b, sym_coords(L)])
    jac = geometric_jacobian(Projection(m, b, L), basis)
    h = 1e-6
    for k in range(9):
        tp, tm = theta.copy(), theta.copy()
        tp[k] += h
        tm[k] -= h
        dp = Projection(m, tp[:3], np.tensordot(tp[3:], basis, 1)).d
        dm = Projection(m, tm[:3], np.tensordot(tm[3:], basis, 1)).d
        np.testing.assert_allclose(jac[:, k], (dp - dm) / (2 * h), atol=1e-6)


def test_mean_curvature_of_a_sphere():
    rng = np.random.default_rng(2)
    p = Projection(directions(rng, 10) * 40.0, np.zeros(3), 40.0 * np.eye(3))
    np.testing.assert_allclose(p.mean_curv2, 2 / 40.0, rtol=1e-12)


def test_decomposition_is_spd_with_unit_determinant():
    rng = np.random.default_rng(3)
    _, L = soft_iron_ellipsoid(rng, spread=0.3)
    a, f = calibration_from_ellipsoid(L)
    np.testing.assert_allclose(a, a.T, atol=1e-12)
    assert np.all(np.linalg.eigvalsh(a) > 0)
    assert np.linalg.det(a) == pytest.approx(1.0)
    u = directions(rng, 20)
    np.testing.assert_allclose(np.linalg.norm((u @ L.T) @ a.T, axis=1), f, rtol=1e-12)


def test_points_deep_inside_stay_finite():
    rng = np.random.default_rng(4)
    b, L = soft_iron_ellipsoid(rng, spread=0.3)
    m = b + directions(rng, 200) @ L.T * rng.uniform(0.0, 0.5, (200, 1))
    p = Projection(m, b, L)
    assert np.all(np.isfinite(p.d)) and np.all(p.d < 0)
    np.testing.assert_allclose(np.linalg.norm(p.u, axis=1), 1.0, atol=1e-9)


def test_a_sample_at_the_centre_projects_onto_the_end_of_the_shortest_axis():
    """A sample exactly at the centre (a phone's all-zero reading under a zero offset) has the ends of the
    shortest axis as its nearest points: d = −a₀, the normal along that axis; the other samples are projected
    as without it. Without the closed form, Newton divided by a zero derivative (numpy warned; the tests
    fail on any warning from pdr_mag)."""
    rng = np.random.default_rng(5)
    b, L = soft_iron_ellipsoid(rng, spread=0.3)
    a, v = np.linalg.eigh(L)
    near = b + directions(rng, 20) @ L.T * rng.uniform(0.9, 1.1, (20, 1))
    # and one deep inside, along the longest axis, next to the centre (the radial fallback: finite)
    m = np.vstack([near[:10], b, near[10:], b + 1e-3 * v[:, 2]])
    p = Projection(m, b, L)
    assert abs(p.d[10] + a[0]) < 1e-9 * a[0]
    assert abs(abs(p.n[10] @ v[:, 0]) - 1.0) < 1e-12
    np.testing.assert_allclose(np.linalg.norm(p.x[10] - b), a[0], rtol=1e-12)
    alone = Projection(near, b, L)
    # the same to the iteration's tolerance (1e-13 relative: its stop is global, so one more step may run)
    np.testing.assert_allclose(np.delete(p.d, [10, 21]), alone.d, rtol=0, atol=1e-12 * a[0])
    np.testing.assert_allclose(np.delete(p.x, [10, 21], axis=0), alone.x, rtol=0, atol=1e-12 * a[0])
    assert np.all(np.isfinite(p.d)) and np.all(np.isfinite(p.n)) and np.all(np.isfinite(p.mean_curv2))
