"""Ellipsoid-specific algebraic fit and its noise-compensated form (adjusted least squares), [Huang2018].

Quadric (see :mod:`pdr_mag.calibration.geometry`): ``θ·z(x) = 0`` with
``z(x) = (x², y², z², 2yz, 2xz, 2xy, 2x, 2y, 2z, 1)`` and ``θ = (a, b, c, f, g, h, p, q, r, d)``.

**Ellipsoid-specific LS** ([Huang2018] step 3; the constraint of Li & Griffiths 2004, cited there as the
ellipsoid constraint): minimise ``θᵀ Ψ θ`` with ``Ψ = Σ z(x_l) z(x_l)ᵀ`` subject to

    4J − I² = θᵀ C θ = 1,   I = a + b + c,   J = ab + bc + ca − f² − g² − h²,

which admits only ellipsoids.  Stationarity gives the generalised eigenproblem ``Ψ θ = λ C θ``; with
``Ψ = [[Ψ11, Ψ12], [Ψ21, Ψ22]]`` split after the six quadratic terms, the linear part is eliminated,
``θ₂ = −Ψ22⁻¹ Ψ21 θ₁``, and ``(Ψ11 − Ψ12 Ψ22⁻¹ Ψ21) θ₁ = λ C₁ θ₁`` is solved for the eigenvector with
``θ₁ᵀC₁θ₁ > 0`` and the smallest λ (the cost at the constraint).

**Noise compensation with unknown variance** ([Huang2018] steps 1–2, the adjusted least squares of Kukush,
Markovsky & Van Huffel): for ``x = x₀ + ε``, ``ε ~ N(0, s·diag(w²))``, every monomial ``x^k`` in ``Ψ`` is
replaced by the polynomial ``t_k(x)`` with ``E t_k(x₀ + ε) = x₀^k``:

    t₀ = 1, t₁ = x, t₂ = x² − s, t₃ = x³ − 3 s x, t₄ = x⁴ − 6 s x² + 3 s²,

(coordinates independent, so products of the ``t`` per coordinate), giving
``Ψ_als(s) = Ψ₀ − s Ψ₁ + s² Ψ₂`` (the patent's ``Y₀(μ) = Y − μC₁ − μ²C₂``).  ``E Ψ_als(s_true) = Ψ(x₀)``
which is singular at the true θ, so the unknown noise amplitude is the smallest ``s > 0`` with
``λ_min(Ψ_als(s)) = 0`` (the patent's zero-determinant condition), found by bracketing and Brent's method.
The ellipsoid-specific solve above is then applied to ``Ψ_als(ŝ)``.

The data are centred and scaled to unit RMS radius first (isotropic noise stays isotropic), and the
ellipsoid is mapped back.  The fits return :class:`MagCalibration` decomposed as in ``geometry``.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import brentq

from pdr_mag.calibration.geometry import build_calibration, monomials, normalise_data, quadric_to_ellipsoid
from pdr_mag.calibration.model import MagCalibration
from pdr_mag.calibration.sphere import _check_mag

# exponents (per coordinate) and scale of each entry of z(x)
_EXP = np.array([[2, 0, 0], [0, 2, 0], [0, 0, 2], [0, 1, 1], [1, 0, 1], [1, 1, 0],
                 [1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, 0]])
_SCALE = np.array([1, 1, 1, 2, 2, 2, 2, 2, 2, 1], dtype=float)
_C1 = np.zeros((6, 6))
_C1[:3, :3] = np.array([[-1.0, 1.0, 1.0], [1.0, -1.0, 1.0], [1.0, 1.0, -1.0]])
_C1[3:, 3:] = -4.0 * np.eye(3)
# coefficients of t_k in powers of s: t_k = Σ_j _T[k][j] · s^j · x^(k−2j)
_T = [[1.0], [1.0], [1.0, -1.0], [1.0, -3.0], [1.0, -6.0, 3.0]]


def ellipsoid_specific_solve(psi: np.ndarray) -> np.ndarray:
    """θ (10,) minimising ``θᵀΨθ`` subject to ``4J − I² = 1`` (generalised eigenproblem, module docstring)."""
    s11, s12, s22 = psi[:6, :6], psi[:6, 6:], psi[6:, 6:]
    try:
        k = np.linalg.solve(s22, s12.T)
    except np.linalg.LinAlgError as exc:
        raise ValueError("mag: samples do not determine an ellipsoid (singular linear block)") from exc
    m = s11 - s12 @ k
    m = 0.5 * (m + m.T)
    lam, vec = np.linalg.eig(np.linalg.solve(_C1, m))
    best, best_lam = None, np.inf
    for i in range(6):
        if abs(lam[i].imag) > 1e-9 * (1 + abs(lam[i].real)):
            continue
        v = vec[:, i].real
        c = v @ _C1 @ v
        if c <= 0:
            continue
        if lam[i].real < best_lam:
            best_lam, best = lam[i].real, v / np.sqrt(c)
    if best is None:
        raise ValueError("mag: no ellipsoid satisfies the constraint (degenerate geometry)")
    return np.concatenate([best, -k @ best])


def _unbiased_moment_polys(x: np.ndarray, w2: np.ndarray) -> np.ndarray:
    """Ψ₀, Ψ₁, Ψ₂ (3, 10, 10) with ``Ψ_als(s) = Ψ₀ + s Ψ₁' + s² Ψ₂`` (Ψ₁' already carries the sign)."""
    n = len(x)
    # per coordinate c, power k (0..4), s-order j: array over samples
    tabs = []
    for c in range(3):
        pw = [np.ones(n), x[:, c], x[:, c] ** 2, x[:, c] ** 3, x[:, c] ** 4]
        tabs.append([[coef * (w2[c] ** j) * pw[k - 2 * j] for j, coef in enumerate(_T[k])] for k in range(5)])
    cache: dict[tuple, np.ndarray] = {}
    out = np.zeros((3, 10, 10))
    for i in range(10):
        for j in range(i, 10):
            e = tuple(_EXP[i] + _EXP[j])
            if e not in cache:
                poly = [np.ones(n)]
                for c in range(3):
                    tc = tabs[c][e[c]]
                    new = [np.zeros(n) for _ in range(len(poly) + len(tc) - 1)]
                    for a, pa in enumerate(poly):
                        for b, tb in enumerate(tc):
                            new[a + b] = new[a + b] + pa * tb
                    poly = new
                sums = np.zeros(3)
                for o, arr in enumerate(poly[:3]):
                    sums[o] = arr.sum() / n
                cache[e] = sums
            out[:, i, j] = out[:, j, i] = cache[e] * _SCALE[i] * _SCALE[j]
    return out


def estimate_noise_variance(polys: np.ndarray) -> float:
    """Smallest s > 0 with ``λ_min(Ψ₀ + sΨ₁ + s²Ψ₂) = 0`` ([Huang2018] step 2), in normalised units²."""
    def lam(s: float) -> float:
        return float(np.linalg.eigvalsh(polys[0] + s * polys[1] + s * s * polys[2])[0])

    lo, f_lo = 0.0, lam(0.0)
    if f_lo <= 0:
        return 0.0
    hi = 1e-6
    while lam(hi) > 0:
        lo = hi
        hi *= 2.0
        if hi > 1.0:
            raise ValueError("mag: could not find the noise level (λ_min never reaches zero)")
    return float(brentq(lam, lo, hi, xtol=1e-14, rtol=1e-12))


def fit_ellipsoid(mag: np.ndarray) -> MagCalibration:
    """Ellipsoid-specific algebraic LS fit ([Huang2018] step 3; ``method='ellipsoid'``).

    Parameters
    ----------
    mag : ndarray (N, 3)
        Raw samples, µT, N ≥ 10.

    Returns
    -------
    MagCalibration
        ``soft_iron = F̄ L⁻¹`` (SPD, det 1), ``field_uT = F̄`` (geometry module).  Acceptance is not judged.
    """
    m = _check_mag(mag, 10)
    xs, c, sc = normalise_data(m)
    z = monomials(xs)
    theta = ellipsoid_specific_solve(z.T @ z / len(z))
    b, L = quadric_to_ellipsoid(theta)
    return build_calibration(m, c + sc * b, sc * L, "ellipsoid")


def fit_als(mag: np.ndarray, noise_shape=None) -> MagCalibration:
    """Noise-compensated (adjusted) LS with unknown noise variance + ellipsoid constraint ([Huang2018]).

    Parameters
    ----------
    mag : ndarray (N, 3)
        Raw samples, µT, N ≥ 10.
    noise_shape : array (3,), optional
        Relative noise standard deviations per axis ([Huang2018]'s known σx:σy:σz); isotropic by default.

    Returns
    -------
    MagCalibration
        ``extra["noise_std_uT"]`` is the estimated noise σ (per axis when ``noise_shape`` is given).
    """
    m = _check_mag(mag, 10)
    w = np.ones(3) if noise_shape is None else np.asarray(noise_shape, dtype=float)
    if w.shape != (3,) or not np.all(w > 0):
        raise ValueError(f"noise_shape: expected 3 positive relative σ, got {noise_shape!r}")
    w = w / np.sqrt(np.mean(w**2))
    xs, c, sc = normalise_data(m)
    polys = _unbiased_moment_polys(xs, w * w)
    s = estimate_noise_variance(polys)
    psi = polys[0] + s * polys[1] + s * s * polys[2]
    theta = ellipsoid_specific_solve(psi)
    b, L = quadric_to_ellipsoid(theta)
    sigma = sc * np.sqrt(s) * w
    extra = {"noise_std_uT": float(sigma[0]) if noise_shape is None else sigma.tolist()}
    return build_calibration(m, c + sc * b, sc * L, "als", extra=extra)
