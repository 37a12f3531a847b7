"""Gravity-aided hard-iron fit: the offset from yaw turns alone ([Liu2018]'s strength equation + a dip one).

Model.  Raw magnetometer samples ``m_i`` (device frame, µT), unit up vectors ``u_i`` (device frame: the
normalised specific force at rest, or the attitude filter's), the Earth field of strength ``F`` and
inclination ``I`` (positive down), ``s = F sin I``.  The calibrated field ``m_i − b`` of a device with
hard-iron offset ``b`` obeys two equations::

    |m_i − b|        = F           (strength: [Liu2018] eq. 3, R = F)
    (m_i − b) · u_i  = −s          (dip: the field points below the horizon)

Under pure yaw (the texting pose of a walk) the ``m_i`` lie on a circle about the axis ``u``: the circle's
centre gives the two components of ``b`` across ``u``, the dip equation the one along ``u`` — so ``b`` is
observable from yaw turns alone, where [Liu2018]'s sphere fit (eqs. 7–16) needs samples over the whole
sphere.

Unknowns: ``b``; ``F`` and ``s`` too when they are not given (no World Magnetic Model, no earlier
calibration — which then needs some tilt diversity), or when they are given with prior σ > 0 (Gaussian
priors ``N(F_WMM, σ_F²)`` and ``N(s_WMM, σ_s²)``: the local field indoors differs from the WMM by a few µT
and degrees, and a hard constraint would push that error into the offset).

Solution, on samples centred for conditioning (``x_i = m_i − m̄``, ``b`` of the centred samples):

1. Linear initial value, least squares of the rows (scaled by ``1/(2F σ_str)`` and ``1/σ_dip``)::

       F, s given:  2 x_i·b − k = |x_i|² − F²     u_i·b     = x_i·u_i + s    (k = |b|² free, [Liu2018] eq. 7)
       F, s free:   2 x_i·b + c = |x_i|²           u_i·b − s = x_i·u_i         (c = F² − |b|²)

2. Gauss–Newton on the residuals ``r_i = (|x_i − b| − F) / σ_str`` and ``d_i = ((x_i − b)·u_i + s) / σ_dip``
   with Huber weights ``w(r) = min(1, 2.5 / |r|)`` (and the priors' residuals when F, s are estimated),
   until the step is below 1e-6 or after ``iterations`` steps; ``σ_dip = F sin σ_tilt``.
3. Covariance ``(JᵀWJ)⁻¹ · max(χ² / (2N − p), 1)`` (p unknowns), residual RMS of the strength equation
   Huber-weighted, RMS of the dip equation plain.

What the fit cannot see.  It assumes the calibrated field is ``m − b``; a phone's is ``A (m − b)`` with a
soft iron ``A = I + L`` of a few per cent (``L`` symmetric), which moves the fitted offset by
``δb = D vec(L)`` to first order (:func:`soft_iron_offset_covariance`): under yaw turns in one pose the
vertical scale ``L_zz`` moves b along up by ``F sin I`` per unit — 1.3 µT for 3 % in a 45-µT field at 63° of
dip — which no number of samples removes.
"""

from __future__ import annotations

from functools import lru_cache
from typing import NamedTuple

import numpy as np
from numba import njit

from pdr_mag.calibration.model import MagCalibration

#: Huber threshold of the Gauss–Newton weights, in σ.
HUBER = 2.5
# outcome of _fit
_OK = 0
_DEGENERATE = 1
_BAD_INPUT = 2


class GravityFit(NamedTuple):
    """The numbers of a gravity-aided fit (``ok`` False: degenerate geometry, the rest meaningless)."""

    ok: bool
    offset: np.ndarray  # b, µT
    strength: float  # F, µT
    f_sin_dip: float  # s = F sin I, µT
    offset_cov: np.ndarray  # (3, 3), µT²
    estimated: bool  # F and s were estimated (free, or with priors)
    rms: float  # Huber-weighted RMS of |m − b| − F, µT
    dip_rms: float  # RMS of (m − b)·u + s, µT


def gravity_aided_offset(
    mag: np.ndarray,
    up: np.ndarray,
    strength: float | None = None,
    sin_dip: float | None = None,
    sigma_strength_uT: float = 1.0,
    sigma_tilt_deg: float = 3.0,
    iterations: int = 8,
    prior_strength_std_uT: float = 0.0,
    prior_dip_std_deg: float = 0.0,
) -> MagCalibration:
    """Hard-iron offset from the strength and dip equations (see the module docstring).

    Parameters
    ----------
    mag : ndarray (N, 3)
        Raw magnetometer samples m_i, µT, device frame.
    up : ndarray (N, 3)
        Up vectors u_i in the device frame (normalised here).
    strength, sin_dip : float, optional
        F (µT) and sin I of the Earth field; both estimated when either is omitted.
    sigma_strength_uT, sigma_tilt_deg : float
        1-σ of the two residuals (µT, and deg of tilt).
    iterations : int
        Most Gauss–Newton steps.
    prior_strength_std_uT, prior_dip_std_deg : float
        With F and sin I given and both > 0: F and F sin I are estimated too, with the given values as
        Gaussian priors of these 1-σ (µT, deg).  0: F and sin I fixed.

    Returns
    -------
    MagCalibration
        ``method="gravity"``, identity soft iron, ``field_uT`` = F, offset covariance, ``extra`` with
        ``sin_dip``, ``dip_rms_uT`` and ``strength_estimated``.  Acceptance is not judged here.

    Raises
    ------
    ValueError
        Wrong shapes, fewer than 5 samples, NaN/infinite/zero vectors, or an unobservable offset.
    """
    m = np.asarray(mag, dtype=float)
    u = np.asarray(up, dtype=float)
    if m.ndim != 2 or m.shape[1] != 3 or u.shape != m.shape:
        raise ValueError(f"mag, up: expected two (N, 3) arrays, got {m.shape} and {u.shape}")
    if len(m) < 5:
        raise ValueError(f"mag: need at least 5 samples, got {len(m)}")
    model = fit_model(  # (plain floats: the models are cached by their arguments)
        None if strength is None else float(strength), None if sin_dip is None else float(sin_dip),
        float(sigma_strength_uT), float(sigma_tilt_deg), float(prior_strength_std_uT),
        float(prior_dip_std_deg),
    )
    fit = fit_offset(m, u, model, iterations)
    if not fit.ok:
        raise ValueError("mag, up: offset not observable from these samples (degenerate geometry)")
    f = fit.strength
    return MagCalibration.from_arrays(
        fit.offset,
        None,
        field_uT=f,
        method="gravity",
        residual_rms_uT=fit.rms,
        offset_std_uT=np.sqrt(np.maximum(fit.offset_cov.diagonal(), 0)),
        n_samples=len(m),
        covariance=fit.offset_cov,
        extra={
            "covariance_params": ["offset_x", "offset_y", "offset_z"],
            "sin_dip": fit.f_sin_dip / f if f > 0 else float("nan"),
            "dip_rms_uT": fit.dip_rms,
            "strength_estimated": fit.estimated,
        },
    )


def soft_iron_offset_covariance(
    mag: np.ndarray, up: np.ndarray, cal: MagCalibration, model: FitModel, soft_iron_std: float
) -> np.ndarray:
    """The offset error an unknown soft iron leaves in an offset-only fit ``cal`` of ``mag`` and ``up``
    (:func:`gravity_aided_offset`'s, with ``model``), µT², 3 × 3.

    To first order the fitted offset moves by ``δb = D vec(L)`` for a soft iron ``A = I + L`` (module
    docstring), ``D`` the first three rows of ``−(JᵀWJ)⁻¹ JᵀW G``: ``J`` and the Huber weights ``W`` the
    fit's at its solution (its priors on F and s included), ``G`` the residuals' derivatives with respect
    to the six elements of ``L`` (``d = m − b``, ``n = d / |d|``)::

        ∂(|A d| − F) / ∂L_jk    = (n_j d_k + n_k d_j) / σ_str      (n_j d_j on the diagonal)
        ∂((A d)·u + s) / ∂L_jk  = (u_j d_k + u_k d_j) / σ_dip      (u_j d_j)

    With the six elements independent, each of std ``soft_iron_std``: ``σ_L² D Dᵀ``.  A uniform scale of
    A is F's (estimated under its prior, it leaves b alone); the shape is what moves b.
    """
    m = np.ascontiguousarray(mag, dtype=float)
    u = np.asarray(up, dtype=float)
    u = np.ascontiguousarray(u / np.linalg.norm(u, axis=1, keepdims=True))
    b = cal.offset_array
    f = float(cal.field_uT)
    s = float(cal.extra.get("sin_dip", np.nan)) * f
    if not (soft_iron_std > 0 and np.isfinite(f) and np.isfinite(s) and len(m) >= 5):
        return np.zeros((3, 3))
    est = bool(cal.extra.get("strength_estimated", False))
    npar = 5 if est else 3
    h, _ = _normal_equations(m, u, b, f, s, npar, 1.0 / model.sig_str, 1.0 / model.sig_dip)
    if est and model.prior:
        h[3, 3] += 1.0 / (model.sig_f * model.sig_f)
        h[4, 4] += 1.0 / (model.sig_s * model.sig_s)
    jwg = _shape_gradient(m, u, b, f, s, npar, 1.0 / model.sig_str, 1.0 / model.sig_dip)
    try:
        d = -np.linalg.solve(h, jwg)
    except np.linalg.LinAlgError:
        return np.zeros((3, 3))
    return soft_iron_std**2 * (d[:3] @ d[:3].T)


class FitModel(NamedTuple):
    """What a fit assumes besides the samples: the references and the σ of each equation (µT)."""

    strength: float | None  # F given (None: estimated, with sin I)
    sin_dip: float | None  # sin I given
    sig_str: float  # σ of the strength equation
    sig_dip: float  # σ of the dip equation: F sin σ_tilt (F = 50 µT when not given)
    prior: bool  # F and s = F sin I estimated around the given values
    sig_f: float  # … with these σ: σ_F
    sig_s: float  # … and σ_s = F cos I σ_I


@lru_cache(maxsize=64)
def fit_model(
    strength: float | None,
    sin_dip: float | None,
    sigma_strength_uT: float,
    sigma_tilt_deg: float,
    prior_strength_std_uT: float = 0.0,
    prior_dip_std_deg: float = 0.0,
) -> FitModel:
    """The :class:`FitModel` of these references and settings (as :func:`gravity_aided_offset` takes them);
    cached, as every refit and stale test of a run asks for one of the same few."""
    free = strength is None or sin_dip is None
    f_guess = float(strength) if strength is not None else 50.0
    prior = not free and prior_strength_std_uT > 0 and prior_dip_std_deg > 0
    sig_dip = max(f_guess * np.sin(np.radians(sigma_tilt_deg)), 1e-3)
    sig_f = sig_s = 1.0
    if prior:
        sig_f = float(prior_strength_std_uT)
        sig_s = float(f_guess * np.cos(np.arcsin(np.clip(sin_dip, -1, 1))) * np.radians(prior_dip_std_deg))
    return FitModel(
        None if strength is None else float(strength),
        None if sin_dip is None else float(sin_dip),
        float(sigma_strength_uT),
        float(sig_dip),
        prior,
        sig_f,
        sig_s,
    )


def fit_offset(m: np.ndarray, u: np.ndarray, model: FitModel, iterations: int = 8) -> GravityFit:
    """:func:`gravity_aided_offset`'s numbers (``ok`` False: degenerate geometry).

    Raises ValueError for NaN, infinite or zero vectors, and when the normal equations are singular.
    """
    f, sd = model.strength, model.sin_dip
    free = f is None or sd is None
    f_guess = f if f is not None else 50.0  # scales the strength rows only
    try:
        outcome, b, f, s, cov, est, rms, dip_rms = _fit(
            np.ascontiguousarray(m, dtype=float), np.ascontiguousarray(u, dtype=float), f_guess,
            0.0 if free else f, 0.0 if free else f * sd, free, model.sig_str, model.sig_dip, int(iterations),
            model.prior, model.sig_f, model.sig_s,
        )  # fmt: skip
    except np.linalg.LinAlgError as exc:
        raise ValueError("mag, up: singular normal equations") from exc
    if outcome == _BAD_INPUT:
        raise ValueError("mag, up: contain NaN, infinite or zero vectors")
    return GravityFit(
        outcome == _OK, b, float(f), float(s), cov[:3, :3].copy(), bool(est), float(rms), float(dip_rms)
    )


# ---------------------------------------------------------------------------------------------- compiled


@njit(cache=True, error_model="numpy")
def _huber(r):
    """Huber weight of a residual in σ."""
    a = abs(r)
    return 1.0 if a <= HUBER else HUBER / max(a, 1e-12)


@njit(cache=True, error_model="numpy")
def _fit(m, up, f_guess, strength, s_given, free, sig_str, sig_dip, iterations, prior, sig_f, sig_s):
    """Steps 1–3 of the module docstring.  Returns ``(outcome, b, F, s, cov, estimated, rms, dip_rms)``,
    ``cov`` (p, p) over ``(b, F, s)``; outcome ``_BAD_INPUT`` for NaN, infinite or zero vectors,
    ``_DEGENERATE`` when the linear initial value is rank-deficient."""
    n = m.shape[0]
    est = free or prior
    npar = 5 if est else 3
    u = np.empty((n, 3))
    centre = np.zeros(3)
    for i in range(n):
        un = np.sqrt(up[i, 0] * up[i, 0] + up[i, 1] * up[i, 1] + up[i, 2] * up[i, 2])
        if not (np.isfinite(un) and un > 0 and np.isfinite(m[i, 0] + m[i, 1] + m[i, 2])):
            return _BAD_INPUT, centre, 0.0, 0.0, np.zeros((npar, npar)), est, 0.0, 0.0
        for c in range(3):
            u[i, c] = up[i, c] / un
            centre[c] += m[i, c]
    centre /= n
    x = np.empty((n, 3))
    for i in range(n):
        for c in range(3):
            x[i, c] = m[i, c] - centre[c]
    ok, b, f, s = _initial_value(x, u, f_guess, strength, s_given, free, sig_str, sig_dip)
    if not ok:
        return _DEGENERATE, b, 0.0, 0.0, np.zeros((npar, npar)), est, 0.0, 0.0
    f0 = f
    s0 = s
    h = np.zeros((npar, npar))
    for _ in range(iterations):
        h, g = _normal_equations(x, u, b, f, s, npar, 1.0 / sig_str, 1.0 / sig_dip)
        if prior:
            h[3, 3] += 1.0 / (sig_f * sig_f)
            g[3] += (f - f0) / sig_f / sig_f
            h[4, 4] += 1.0 / (sig_s * sig_s)
            g[4] += (s - s0) / sig_s / sig_s
        step = np.linalg.solve(h, -g)
        b += step[:3]
        if est:
            f += step[3]
            s += step[4]
        if np.max(np.abs(step)) < 1e-6:
            break
    chi, rms, dip_rms = _residual_stats(x, u, b, f, s, sig_str, sig_dip)
    cov = np.linalg.inv(h) * max(chi / max(2 * n - npar, 1), 1.0)
    return _OK, b + centre, f, s, cov, est, rms, dip_rms


@njit(cache=True, error_model="numpy")
def _initial_value(x, u, f_guess, strength, s_given, free, sig_str, sig_dip):
    """Step 1: ``(ok, b, F, s)`` from the linear rows of the module docstring (``ok`` False when they are
    rank-deficient: singular values ``σ_min < 1e-9 σ_max``).

    The least squares of the 2N × p rows ``A z = y`` is solved by its normal equations ``AᵀA z = Aᵀy`` when
    they are well conditioned, ``λ_min(AᵀA) > 1e-10 λ_max`` (so ``σ_min / σ_max > 1e-5``: not
    rank-deficient, and the solution good to ~cond(AᵀA)·ε), otherwise by an SVD of the rows, which also
    tells a rank-deficient set.  On the tyrex walks ``σ_max / σ_min`` stays below 400; for a window of 300
    samples the SVD costs ~30 µs of the fit's ~85 µs, the normal equations ~9 µs."""
    n = x.shape[0]
    p = 5 if free else 4
    a = np.zeros((2 * n, p))
    y = np.empty(2 * n)
    k2 = 2.0 * f_guess
    for i in range(n):
        xx = x[i, 0] * x[i, 0] + x[i, 1] * x[i, 1] + x[i, 2] * x[i, 2]
        xu = x[i, 0] * u[i, 0] + x[i, 1] * u[i, 1] + x[i, 2] * u[i, 2]
        for c in range(3):
            a[i, c] = 2.0 * x[i, c] / k2 / sig_str
            a[n + i, c] = u[i, c] / sig_dip
        if free:  # unknowns (b, c, s)
            a[i, 3] = 1.0 / k2 / sig_str
            a[n + i, 4] = -1.0 / sig_dip
            y[i] = xx / k2 / sig_str
            y[n + i] = xu / sig_dip
        else:  # unknowns (b, k)
            a[i, 3] = -1.0 / k2 / sig_str
            y[i] = (xx - strength * strength) / k2 / sig_str
            y[n + i] = (xu + s_given) / sig_dip
    b = np.zeros(3)
    ata = a.T @ a
    lam = np.linalg.eigvalsh(ata)  # ascending
    if lam[0] > 1e-10 * lam[-1]:
        sol = np.linalg.solve(ata, a.T @ y)
    else:
        rcond = np.finfo(np.float64).eps * max(2 * n, p)
        sol, _, rank, sv = np.linalg.lstsq(a, y, rcond)
        if rank < p or sv[-1] < 1e-9 * sv[0]:
            return False, b, 0.0, 0.0
    b[:] = sol[:3]
    if free:
        return True, b, np.sqrt(max(sol[3] + b[0] * b[0] + b[1] * b[1] + b[2] * b[2], 1e-6)), sol[4]
    return True, b, strength, s_given


@njit(cache=True, error_model="numpy")
def _normal_equations(x, u, b, f, s, npar, inv_str, inv_dip):
    """Step 2's ``(H, g) = (JᵀWJ, JᵀWr)`` over the first ``npar`` of ``(b, F, s)``.

    Per sample (``d = x − b``) two Huber-weighted residuals: the strength residual ``(|d| − F)/σ_str`` with
    gradient ``(−d/|d|, −1, 0)/σ_str``, and the dip residual ``(d·u + s)/σ_dip`` with gradient
    ``(−u, 0, 1)/σ_dip``.  The sums are kept in scalars (the hot loop of the online refits).
    """
    # H's upper triangle: hbb (b×b), hbf (b×F), hff, hbs (b×s), hss; H_fs = 0.  g: gb, gf, gs.
    hbb00 = hbb01 = hbb02 = hbb11 = hbb12 = hbb22 = 0.0
    hbf0 = hbf1 = hbf2 = hff = hbs0 = hbs1 = hbs2 = hss = 0.0
    gb0 = gb1 = gb2 = gf = gs = 0.0
    for i in range(x.shape[0]):
        d0 = x[i, 0] - b[0]
        d1 = x[i, 1] - b[1]
        d2 = x[i, 2] - b[2]
        nd = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        # strength
        r = (nd - f) * inv_str
        w = _huber(r)
        a0 = -d0 / nd * inv_str
        a1 = -d1 / nd * inv_str
        a2 = -d2 / nd * inv_str
        wa0 = w * a0
        wa1 = w * a1
        wa2 = w * a2
        hbb00 += wa0 * a0
        hbb01 += wa0 * a1
        hbb02 += wa0 * a2
        hbb11 += wa1 * a1
        hbb12 += wa1 * a2
        hbb22 += wa2 * a2
        gb0 += wa0 * r
        gb1 += wa1 * r
        gb2 += wa2 * r
        hbf0 -= wa0 * inv_str
        hbf1 -= wa1 * inv_str
        hbf2 -= wa2 * inv_str
        hff += w * inv_str * inv_str
        gf -= w * inv_str * r
        # dip
        r = (d0 * u[i, 0] + d1 * u[i, 1] + d2 * u[i, 2] + s) * inv_dip
        w = _huber(r)
        c0 = -u[i, 0] * inv_dip
        c1 = -u[i, 1] * inv_dip
        c2 = -u[i, 2] * inv_dip
        wc0 = w * c0
        wc1 = w * c1
        wc2 = w * c2
        hbb00 += wc0 * c0
        hbb01 += wc0 * c1
        hbb02 += wc0 * c2
        hbb11 += wc1 * c1
        hbb12 += wc1 * c2
        hbb22 += wc2 * c2
        gb0 += wc0 * r
        gb1 += wc1 * r
        gb2 += wc2 * r
        hbs0 += wc0 * inv_dip
        hbs1 += wc1 * inv_dip
        hbs2 += wc2 * inv_dip
        hss += w * inv_dip * inv_dip
        gs += w * inv_dip * r
    h = np.zeros((npar, npar))
    g = np.zeros(npar)
    h[0, 0] = hbb00
    h[0, 1] = h[1, 0] = hbb01
    h[0, 2] = h[2, 0] = hbb02
    h[1, 1] = hbb11
    h[1, 2] = h[2, 1] = hbb12
    h[2, 2] = hbb22
    g[0] = gb0
    g[1] = gb1
    g[2] = gb2
    if npar == 5:
        h[0, 3] = h[3, 0] = hbf0
        h[1, 3] = h[3, 1] = hbf1
        h[2, 3] = h[3, 2] = hbf2
        h[3, 3] = hff
        h[0, 4] = h[4, 0] = hbs0
        h[1, 4] = h[4, 1] = hbs1
        h[2, 4] = h[4, 2] = hbs2
        h[4, 4] = hss
        g[3] = gf
        g[4] = gs
    return h, g


@njit(cache=True, error_model="numpy")
def _residual_stats(x, u, b, f, s, sig_str, sig_dip):
    """Step 3: ``(χ², rms, dip_rms)`` — Huber-weighted χ² of both residuals, Huber-weighted RMS of the
    strength residual, plain RMS of the dip residual (µT)."""
    chi = 0.0
    sw1 = 0.0
    swe1 = 0.0
    se2 = 0.0
    n = x.shape[0]
    for i in range(n):
        d0 = x[i, 0] - b[0]
        d1 = x[i, 1] - b[1]
        d2 = x[i, 2] - b[2]
        e1 = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2) - f
        e2 = d0 * u[i, 0] + d1 * u[i, 1] + d2 * u[i, 2] + s
        r1 = e1 / sig_str
        r2 = e2 / sig_dip
        w1 = _huber(r1)
        w2 = _huber(r2)
        chi += w1 * r1 * r1 + w2 * r2 * r2
        sw1 += w1
        swe1 += w1 * e1 * e1
        se2 += e2 * e2
    return chi, np.sqrt(swe1 / max(sw1, 1e-12)), np.sqrt(se2 / n)


@njit(cache=True, error_model="numpy")
def _shape_gradient(m, u, b, f, s, npar, inv_str, inv_dip):
    """``JᵀW G`` (npar × 6) of :func:`soft_iron_offset_covariance`: per sample the Huber-weighted strength
    and dip rows of J (as :func:`_normal_equations`) times their derivatives with respect to ``L_xx, L_yy,
    L_zz, L_xy, L_xz, L_yz``."""
    out = np.zeros((npar, 6))
    jr = np.zeros(npar)
    gr = np.zeros(6)
    for i in range(m.shape[0]):
        d = m[i] - b
        nd = np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
        nv = d / nd
        for k in range(2):  # 0: strength, 1: dip
            v = nv if k == 0 else u[i]
            inv = inv_str if k == 0 else inv_dip
            r = ((nd - f) if k == 0 else (d[0] * u[i, 0] + d[1] * u[i, 1] + d[2] * u[i, 2] + s)) * inv
            w = _huber(r)
            jr[:] = 0.0
            for c in range(3):
                jr[c] = -v[c] * inv
            if npar == 5:
                jr[3 + k] = -inv if k == 0 else inv
            gr[0] = v[0] * d[0] * inv
            gr[1] = v[1] * d[1] * inv
            gr[2] = v[2] * d[2] * inv
            gr[3] = (v[0] * d[1] + v[1] * d[0]) * inv
            gr[4] = (v[0] * d[2] + v[2] * d[0]) * inv
            gr[5] = (v[1] * d[2] + v[2] * d[1]) * inv
            for p in range(npar):
                for q in range(6):
                    out[p, q] += w * jr[p] * gr[q]
    return out
