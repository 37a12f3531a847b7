"""Maximum-likelihood refinement: geometric (orthogonal-distance) ML, [Long2013]'s Newton, [Zhong2017]'s LM.

**Geometric ML** (``fit_ml``, the default refinement).  Model ([Long2013] eqs. 4–7): ``m_i = b + L u_i +
ε_i``, ``|u_i| = 1``, ``ε_i ~ N(0, σ²I)``; the unit directions ``u_i`` are per-sample nuisance parameters.
The likelihood ([Long2013] eq. 7) is maximised by

    min_{b, L, u}  Σ_i |m_i − b − L u_i|²  =  min_{b, L}  Σ_i d_i(b, L)²,

``d_i`` the signed orthogonal distance of ``m_i`` to the ellipsoid: the nuisance directions are eliminated
by the exact orthogonal projection (vectorised Newton on the secular equation, ``geometry.Projection``).
By the envelope theorem ``∂d_i/∂θ = −n_iᵀ G_i`` with ``G_i = [I, B_k u_i]`` (``L = Σ l_k B_k``), so the
Gauss–Newton normal matrix is exactly ``Σ G_iᵀ n_i n_iᵀ G_i`` — the effective Fisher information of
:mod:`pdr_mag.calibration.crlb` times σ².  Levenberg–Marquardt damping guards the steps.

Second-order bias: ``E d_i = σ² (κ₁ + κ₂)_i / 2 + O(σ⁴)`` (mean curvature of the ellipsoid at the foot
point), which biases the radius and, with partial coverage, the offset.  With ``bias_correction`` (default)
the residual is ``d_i − σ̂² (κ₁+κ₂)_i / 2`` with ``σ̂² = Σ d_i² / (N − p)``, which removes this leading term.

Models: ``full`` (L SPD, 9 parameters), ``diagonal`` (L diagonal, 6), ``sphere`` (L = R·I, 4).

**[Long2013] — radial objective, Newton** (``fit_radial_newton``): ``min Σ_i (|T(m_i − b)| − C)²``
([Long2013] eq. 10) by Newton's method with the exact Hessian, from the two-step value.  ``T`` is taken
symmetric (its left rotation is invisible to the norm, [Long2013] "V_L 并不会参与计算"), and the SVD
``T = U₁S₁V₁ᵀ`` gives ``R_L = V₁``, ``S_L = S₁⁻¹`` (eq. 11).  ``C`` is the known field if given, otherwise
the two-step norm.  The radial residual is not the orthogonal distance: its noise is ``(Tε)·ŵ``, whose
variance varies with direction when T is not a multiple of I, so it is not efficient, and with partial
coverage its O(σ²) bias does not cancel.

Measured (``benchmarks/RESULTS.md``, N = 300, soft iron ±15 %): with full coverage all three reach
1.00–1.08 × the CRLB.  With a hemisphere only at σ/F = 3 %, the geometric ML stays at 1.03 × CRLB with a
bias indistinguishable from zero, whereas the radial objective is biased — [Zhong2017]'s LM by ≈ 5.6 µT
(≈ 70 standard errors, 3.7 × CRLB) and [Long2013]'s Newton runs away along the missing side (the radial
objective keeps decreasing towards a large, flat ellipsoid; offset errors of hundreds of µT).
``tests/test_calibration_crlb.py`` asserts both.  The curvature correction changes the ML results by far
less than their standard error at σ/F ≤ 5 %.

**[Zhong2017] — 9 parameters, Levenberg–Marquardt** (``fit_lm9``): ``m = K N h + b``, ``|h| = F``, with
``K = diag(k_x, k_y, 1)`` (sensitivities relative to z, [Zhong2017] §2.1), ``N`` the non-orthogonal axes
with unit rows ``(1,0,0)``, ``(sin ε₁, cos ε₁, 0)``, ``(sin ε₂, cos ε₂ sin ε₃, cos ε₂ cos ε₃)`` (three small
mounting angles), ``b`` the offset, ``F`` the norm: β = (ε₁, ε₂, ε₃, k_x, k_y, b_x, b_y, b_z, F), residual
``r_i = |N⁻¹K⁻¹(m_i − b)| − F`` ([Zhong2017] eq. 9), LM step ``(JᵀJ + μI)δ = −g`` (eq. 14) from the two-step
value (eq. 13).  The paper's eqs. 1–4 are not legible in our copy; this lower-triangular axis model is our
reading of "three small mounting angles + relative sensitivities".
"""

from __future__ import annotations

import numpy as np

from pdr_mag.calibration.geometry import (
    Projection,
    build_calibration,
    spd_part,
    sym_basis,
    sym_coords,
)
from pdr_mag.calibration.model import MagCalibration
from pdr_mag.calibration.sphere import _check_mag, sphere_lls
from pdr_mag.calibration.twostep import initial_ellipsoid

_N_PARAMS = {"sphere": 4, "diagonal": 6, "full": 9}
_I = [0, 0, 1]  # off-diagonal pairs (xy, xz, yz) of geometry.SYM_PAIRS
_J = [1, 2, 2]


def _theta_from(b: np.ndarray, L: np.ndarray, model: str) -> np.ndarray:
    if model == "sphere":
        l = np.array([np.prod(np.linalg.eigvalsh(L)) ** (1.0 / 3.0)])
    else:
        l = sym_coords(L, model)
    return np.concatenate([b, l])


def geometric_solve(mag: np.ndarray, b0: np.ndarray, L0: np.ndarray, model: str = "full",
                    bias_correction: bool = True, max_iter: int = 50, tol: float = 1e-8) -> dict:
    """Levenberg–Marquardt on the reduced geometric problem (module docstring).

    Returns a dict with ``b``, ``L``, ``cov`` (σ̂²(JᵀJ)⁻¹ or None), ``sigma`` (σ̂, µT), ``iterations``,
    ``converged``, ``rss`` (Σ d_i², µT²) and ``jtj`` (JᵀJ at the optimum).
    """
    basis = sym_basis(model)
    bflat = basis.reshape(len(basis), 9).T
    n = len(mag)
    p = 3 + len(basis)
    dof = max(n - p, 1)

    def evaluate(theta, s2):
        L = np.tensordot(theta[3:], basis, axes=1)
        proj = Projection(mag, theta[:3], L)
        nv, uv = proj.n, proj.u
        jac = np.empty((n, p))
        jac[:, :3] = -nv
        if model == "full":  # columns −n_iᵀB_k u_i written out for speed (B_k of sym_basis)
            jac[:, 3:6] = -nv * uv
            jac[:, 6:9] = -(nv[:, _I] * uv[:, _J] + nv[:, _J] * uv[:, _I])
        elif model == "diagonal":
            jac[:, 3:6] = -nv * uv
        elif model == "sphere":
            jac[:, 3] = -np.einsum("ij,ij->i", nv, uv)
        else:
            jac[:, 3:] = -((nv[:, :, None] * uv[:, None, :]).reshape(n, 9) @ bflat)
        r = proj.d - 0.5 * s2 * proj.mean_curv2 if bias_correction else proj.d
        return r, jac, proj

    theta = _theta_from(np.asarray(b0, float), np.asarray(L0, float), model)
    s2 = 0.0
    r, jac, proj = evaluate(theta, s2)
    lam = 1e-9
    converged = False
    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007 (it is reported)
        if bias_correction:  # σ̂² from the current fit; J does not depend on it
            s2 = float(proj.d @ proj.d) / dof
            r = proj.d - 0.5 * s2 * proj.mean_curv2
        cost = float(r @ r)
        g = jac.T @ r
        h = jac.T @ jac
        dh = np.diag(h).copy()
        step_ok = False
        while lam < 1e12:
            try:
                delta = -np.linalg.solve(h + lam * np.diag(dh), g)
                r2, jac2, proj2 = evaluate(theta + delta, s2)
            except (np.linalg.LinAlgError, ValueError):
                lam *= 10.0
                continue
            if float(r2 @ r2) <= cost * (1.0 + 1e-12):
                step_ok = True
                break
            lam *= 10.0
        if not step_ok:
            converged = True  # no descent possible: at the optimum to numerical precision
            break
        theta = theta + delta
        r, jac, proj = r2, jac2, proj2
        lam = max(lam * 0.1, 1e-12)
        # stop when the step is a negligible fraction of the parameters' own uncertainty
        # (Mahalanobis length δᵀJᵀJδ/σ̂² below tol) or tiny in absolute terms
        s2_now = max(float(proj.d @ proj.d) / dof, 1e-300)
        if float(delta @ h @ delta) / s2_now < tol or np.max(np.abs(delta)) <= 1e-13 * (
                1.0 + np.max(np.abs(theta))):
            converged = True
            break
    h = jac.T @ jac
    try:
        cov = np.linalg.inv(h) * (float(proj.d @ proj.d) / dof) if np.linalg.cond(h) < 1e14 else None
    except np.linalg.LinAlgError:
        cov = None
    L = np.tensordot(theta[3:], basis, axes=1)
    return {"b": theta[:3].copy(), "L": L, "cov": cov, "sigma": float(np.sqrt(proj.d @ proj.d / dof)),
            "iterations": it, "converged": converged, "rss": float(proj.d @ proj.d), "jtj": h}


def fit_ml(mag: np.ndarray, model: str = "full", init: tuple | None = None,
           bias_correction: bool = True, max_iter: int = 50) -> MagCalibration:
    """Geometric (orthogonal-distance) maximum-likelihood calibration (module docstring).

    Parameters
    ----------
    mag : ndarray (N, 3)
        Raw samples, µT.
    model : {"full", "diagonal", "sphere"}
        Shape of L: full SPD (soft iron), diagonal (axis scale factors only), or sphere (offset only).
    init : (b, L), optional
        Initial ellipsoid; the two-step value (:func:`twostep.initial_ellipsoid`) by default.
    bias_correction : bool
        Remove the O(σ²) curvature bias of the orthogonal distance (module docstring).

    Returns
    -------
    MagCalibration
        ``method='ml'``; ``covariance`` over ``extra["covariance_params"]`` is ``σ̂²(JᵀJ)⁻¹``;
        ``extra`` holds ``noise_std_uT``, ``iterations``, ``converged``, ``rss_uT2``, ``n_params``.
    """
    if model not in _N_PARAMS:
        raise ValueError(f"model: expected 'sphere', 'diagonal' or 'full', got {model!r}")
    m = _check_mag(mag, _N_PARAMS[model] + 1)
    if init is None:
        b0, L0, _ = initial_ellipsoid(m)
    else:
        b0, L0 = init
    res = geometric_solve(m, b0, L0, model, bias_correction, max_iter)
    extra = {"noise_std_uT": res["sigma"], "iterations": res["iterations"], "converged": res["converged"],
             "rss_uT2": res["rss"], "n_params": _N_PARAMS[model], "objective": "geometric",
             "bias_correction": bool(bias_correction)}
    return build_calibration(m, res["b"], res["L"], "ml", model, extra, cov=res["cov"])


# ---------------------------------------------------------------------------------------------- [Long2013]
def fit_radial_newton(mag: np.ndarray, field: float | None = None, max_iter: int = 50,
                      tol: float = 1e-10) -> MagCalibration:
    """[Long2013]: ``min Σ (|T(m_i − b)| − C)²`` by Newton's method, T = U₁S₁V₁ᵀ (module docstring).

    Parameters
    ----------
    mag : ndarray (N, 3)
        Raw samples, µT.
    field : float, optional
        Known field strength C ([Long2013] uses the true |H|); the two-step norm otherwise.  The returned
        calibration is normalised as all others (det soft_iron = 1); ``extra["T"]`` keeps the paper's T.

    Returns
    -------
    MagCalibration
        ``method='radial'``; ``extra`` holds ``T``, ``R_L``, ``S_L``, ``C``, ``iterations``, ``converged``.
    """
    m = _check_mag(mag, 10)
    b0, L0, _ = initial_ellipsoid(m)
    c = float(field) if field is not None else float(np.prod(np.linalg.eigvalsh(L0)) ** (1.0 / 3.0))
    basis = sym_basis("full")
    theta = np.concatenate([b0, sym_coords(c * np.linalg.inv(L0))])
    n = len(m)

    def parts(th):
        t = np.tensordot(th[3:], basis, axes=1)
        d = m - th[:3]
        w = d @ t.T
        wn = np.sqrt(np.einsum("ij,ij->i", w, w))
        return t, d, w, wn, wn - c

    def grad_hess(th):
        t, d, w, wn, r = parts(th)
        wh = w / wn[:, None]
        # W_i = ∂w_i/∂θ  (N, 3, 9): [−T, B_k d_i]
        wmat = np.empty((n, 3, 9))
        wmat[:, :, :3] = -t
        wmat[:, :, 3:] = np.einsum("kab,nb->nak", basis, d)
        jr = np.einsum("na,nak->nk", wh, wmat)  # ∇r_i
        g = jr.T @ r
        h = jr.T @ jr
        # Σ r_i/|w_i| W_iᵀ (I − ŵŵᵀ) W_i
        coef = r / wn
        pw = wmat - wh[:, :, None] * jr[:, None, :]
        h += np.einsum("n,nak,nal->kl", coef, pw, wmat)
        # cross terms r_i ŵ_iᵀ ∂²w_i/∂b_j∂t_k = −(B_k s)_j with s = Σ r_i ŵ_i
        s = wh.T @ r
        cross = -np.einsum("kab,b->ak", basis, s)
        h[:3, 3:] += cross
        h[3:, :3] += cross.T
        return g, h, float(r @ r)

    it, converged = 0, False
    g, h, f = grad_hess(theta)
    for it in range(1, max_iter + 1):  # noqa: B007 (it is reported)
        mu = 0.0
        while True:
            try:
                hm = h + mu * np.diag(np.abs(np.diag(h)))
                np.linalg.cholesky(hm)
                delta = -np.linalg.solve(hm, g)
                break
            except np.linalg.LinAlgError:
                mu = 1e-6 if mu == 0 else mu * 10
        step = 1.0
        while step > 1e-8:
            f2 = float(np.sum(parts(theta + step * delta)[4] ** 2))
            if f2 <= f:
                break
            step *= 0.5
        theta = theta + step * delta
        g, h, f = grad_hess(theta)
        if np.max(np.abs(step * delta)) <= tol * (1 + np.max(np.abs(theta))):
            converged = True
            break
    t = np.tensordot(theta[3:], basis, axes=1)
    u1, s1, v1t = np.linalg.svd(t)
    L = c * np.linalg.inv(spd_part(t))
    extra = {"T": t, "R_L": v1t.T, "S_L": np.diag(1.0 / s1), "C": c, "iterations": it,
             "converged": converged, "objective": "radial"}
    return build_calibration(m, theta[:3], L, "radial", "full", extra)


# ---------------------------------------------------------------------------------------------- [Zhong2017]
def _lm9_matrix(beta: np.ndarray) -> np.ndarray:
    e1, e2, e3, kx, ky = beta[:5]
    nmat = np.array([[1.0, 0.0, 0.0],
                     [np.sin(e1), np.cos(e1), 0.0],
                     [np.sin(e2), np.cos(e2) * np.sin(e3), np.cos(e2) * np.cos(e3)]])
    return np.diag([kx, ky, 1.0]) @ nmat


def fit_lm9(mag: np.ndarray, max_iter: int = 100, tol: float = 1e-12) -> MagCalibration:
    """[Zhong2017]: the 9-parameter model with the field norm as a parameter, Levenberg–Marquardt.

    Returns
    -------
    MagCalibration
        ``method='lm9'``; ``extra["beta"]`` = (ε₁, ε₂, ε₃ [rad], k_x, k_y, b_x, b_y, b_z, F) in the paper's
        order, ``extra["beta_std"]`` their 1-σ from ``σ̂²(JᵀJ)⁻¹``; ``field_uT`` is normalised as for
        every other fit (det soft_iron = 1).
    """
    m = _check_mag(mag, 10)
    b0, r0, _ = sphere_lls(m)  # step 1 of the two-step method ([Zhong2017] eq. 13)
    beta = np.array([0.0, 0.0, 0.0, 1.0, 1.0, *b0, r0])
    eps = 1e-7

    def resid(bt):
        mi = np.linalg.inv(_lm9_matrix(bt))
        h = (m - bt[5:8]) @ mi.T
        return np.sqrt(np.einsum("ij,ij->i", h, h)) - bt[8]

    def jac(bt, r0_):
        jmat = np.empty((len(m), 9))
        mi = np.linalg.inv(_lm9_matrix(bt))
        h = (m - bt[5:8]) @ mi.T
        hn = h / np.sqrt(np.einsum("ij,ij->i", h, h))[:, None]
        jmat[:, 5:8] = -hn @ mi
        jmat[:, 8] = -1.0
        for k in range(5):
            bp = bt.copy()
            bp[k] += eps
            jmat[:, k] = (resid(bp) - r0_) / eps
        return jmat

    r = resid(beta)
    cost = float(r @ r)
    mu = 1e-3
    it, converged = 0, False
    for it in range(1, max_iter + 1):  # noqa: B007 (it is reported)
        jm = jac(beta, r)
        g = jm.T @ r
        h = jm.T @ jm
        while mu < 1e12:
            delta = -np.linalg.solve(h + mu * np.diag(np.diag(h)), g)
            r2 = resid(beta + delta)
            c2 = float(r2 @ r2)
            if c2 <= cost:
                break
            mu *= 10.0
        else:
            converged = True
            break
        beta = beta + delta
        r, cost = r2, c2
        mu = max(mu * 0.1, 1e-12)
        if np.max(np.abs(delta)) <= tol * (1 + np.max(np.abs(beta))):
            converged = True
            break
    gmat = np.linalg.inv(_lm9_matrix(beta))
    L = beta[8] * np.linalg.inv(spd_part(gmat))
    jm = jac(beta, r)
    try:
        beta_cov = np.linalg.inv(jm.T @ jm) * float(r @ r) / max(len(m) - 9, 1)
        beta_std = np.sqrt(np.clip(np.diag(beta_cov), 0, None))
    except np.linalg.LinAlgError:
        beta_std = np.full(9, np.nan)
    extra = {"beta": beta, "beta_std": beta_std, "iterations": it, "converged": converged,
             "objective": "radial-9"}
    return build_calibration(m, beta[5:8], L, "lm9", "full", extra)
