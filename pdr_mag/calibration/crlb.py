"""Cramér–Rao lower bound of the ellipsoid calibration with unknown per-sample field directions.

Model: ``m_i = x_i(θ, u_i) + ε_i``, ``x_i = b + L u_i``, ``|u_i| = 1``, ``ε_i ~ N(0, σ²I)``, θ = (b, l)
with ``L = Σ l_k B_k`` (``geometry.sym_basis``).  The directions ``u_i`` are nuisance parameters; the
Fisher information of (θ, u) is block structured and eliminating each ``u_i`` (Schur complement: the
tangent-plane part of ``∂x_i/∂θ`` is absorbed by moving the point along the surface) leaves the
effective information (seed-independent; the standard result for errors-in-variables curve fitting)

    J_eff = Σ_i G_iᵀ n_i n_iᵀ G_i / σ²,   G_i = ∂x_i/∂θ = [I, B_k u_i],

with ``n_i`` the unit normal of the ellipsoid at ``x_i``.  ``J_eff⁻¹`` bounds the covariance of any
unbiased estimator of θ; the offset bound is its top-left 3×3 block.  It is exactly the Gauss–Newton
normal matrix of the geometric ML fit (:mod:`pdr_mag.calibration.ml`) divided by σ², which is why that fit
attains it asymptotically.
"""

from __future__ import annotations

import numpy as np

from pdr_mag.calibration.geometry import sym_basis


def effective_fisher(points: np.ndarray, offset, L, sigma: float, model: str = "full") -> np.ndarray:
    """``J_eff`` (p × p) for true points ``points`` (N, 3) on the ellipsoid ``x = b + L u`` (µT, σ in µT)."""
    x = np.asarray(points, dtype=float)
    Lm = np.asarray(L, dtype=float)
    b = np.asarray(offset, dtype=float)
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"points: expected shape (N, 3) in µT, got {x.shape}")
    if not sigma > 0:
        raise ValueError(f"sigma: expected a positive noise σ in µT, got {sigma!r}")
    u = np.linalg.solve(Lm, (x - b).T).T
    u /= np.linalg.norm(u, axis=1)[:, None]
    n = np.linalg.solve(Lm, u.T).T  # normal ∝ L⁻¹u  (gradient of |L⁻¹(x − b)|²)
    n /= np.linalg.norm(n, axis=1)[:, None]
    basis = sym_basis(model)
    a = np.hstack([n, np.einsum("ij,kjm,im->ik", n, basis, u)])  # rows n_iᵀ G_i
    return a.T @ a / sigma**2


def crlb(points: np.ndarray, offset, L, sigma: float, model: str = "full") -> np.ndarray:
    """The bound ``J_eff⁻¹`` (p × p) on the covariance of θ = (b, l)."""
    return np.linalg.inv(effective_fisher(points, offset, L, sigma, model))


def offset_rmse_bound(points: np.ndarray, offset, L, sigma: float, model: str = "full") -> float:
    """``sqrt(tr CRLB_bb)``: the smallest achievable RMS of the offset error vector, µT."""
    return float(np.sqrt(np.trace(crlb(points, offset, L, sigma, model)[:3, :3])))
