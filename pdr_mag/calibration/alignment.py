"""Rotation between the magnetometer axes and the IMU axes ([Long2013] eq. 12 idea).

After the ellipsoid calibration, ``m_cal = soft_iron (m − b)`` has the right length but is known only up to
a rotation: the SPD ``soft_iron`` leaves out the rotation part of the distortion ([Long2013]'s ``V_L``, which
"does not take part in the fit") plus any mounting rotation between the magnetometer and the IMU.  [Long2013]
(eq. 12) fits ``V_L`` by least squares against reference vectors.  Without a reference the accelerometer
gives one constraint per sample: the angle between gravity and the Earth field (the dip) is constant,

    ĝ_iᵀ R m̂_i = c   for all i,    m̂_i = m_cal,i / |m_cal,i|,  ĝ_i = a_i / |a_i|  (IMU frame),

with ``c = sin(dip)`` up to sign.  ``R`` (magnetometer → IMU, so ``m_imu = R m_cal``) and ``c`` are found
by Gauss–Newton on ``R ← exp([δ]ₓ) R``: ``∂r_i/∂δ = (R m̂_i × ĝ_i)ᵀ``, ``∂r_i/∂c = −1``.  Only quasi-static
samples (low-passed specific force with ``| |a| − g | < static_tol``) are used.

``R`` is reported as significant only if its rotation angle is above ``min_angle_deg`` *and* the χ² test
``ωᵀ Σ_ω⁻¹ ω > χ²₃(0.999)`` passes, with ``Σ_ω`` the GN covariance inflated by the autocorrelation of the
residuals (consecutive samples are not independent).  Otherwise the identity is kept.

:func:`fit_reference_rotation` is [Long2013] eq. 12 itself: the least-squares rotation onto known reference
vectors (orthogonal Procrustes via SVD), used in the known-answer test.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

CHI2_3_999 = 16.266  # 0.999 quantile of χ² with 3 degrees of freedom


@dataclass(frozen=True)
class Alignment:
    """Result of :func:`fit_alignment`.

    Attributes
    ----------
    rotation : ndarray (3, 3)
        Estimated ``R`` (magnetometer → IMU axes).
    angle_deg, angle_std_deg : float
        Rotation angle of ``R`` and its 1-σ uncertainty (inflated as in the module docstring).
    significant : bool
        Whether ``R`` passes the tests; when False the identity should be used.
    sin_dip : float
        The constant ``c = ĝᵀ R m̂``.
    dip_rms : float
        RMS of the residuals ``ĝᵀ R m̂ − c`` (dimensionless).
    n_used : int
        Quasi-static samples used.
    spread_deg : float
        Spread of the static gravity directions (see ``min_spread_deg``).
    reason : str
        Why the rotation is not significant (empty when it is).
    """

    rotation: np.ndarray
    angle_deg: float
    angle_std_deg: float
    significant: bool
    sin_dip: float
    dip_rms: float
    n_used: int
    spread_deg: float = float("nan")
    reason: str = ""

    def to_dict(self) -> dict:
        return {"angle_deg": self.angle_deg, "angle_std_deg": self.angle_std_deg,
                "significant": self.significant, "sin_dip": self.sin_dip, "dip_rms": self.dip_rms,
                "n_used": self.n_used, "spread_deg": self.spread_deg, "reason": self.reason,
                "rotation": self.rotation.tolist()}


def _hat(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _expm_so3(v: np.ndarray) -> np.ndarray:
    th = float(np.linalg.norm(v))
    k = _hat(v)
    if th < 1e-12:
        return np.eye(3) + k
    return np.eye(3) + np.sin(th) / th * k + (1.0 - np.cos(th)) / th**2 * (k @ k)


def rotation_angle(r: np.ndarray) -> float:
    """Rotation angle of a rotation matrix, radians."""
    return float(np.arccos(np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0)))


def _rotvec(r: np.ndarray) -> np.ndarray:
    th = rotation_angle(r)
    w = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    if th < 1e-9:
        return 0.5 * w
    return th / (2.0 * np.sin(th)) * w


def resample(t_src: np.ndarray, xyz_src: np.ndarray, t_dst: np.ndarray, window_s: float = 0.0) -> np.ndarray:
    """``xyz_src`` (optionally moving-averaged over ``window_s`` seconds) linearly interpolated at ``t_dst``.

    Samples of ``t_dst`` outside ``[t_src[0], t_src[-1]]`` get NaN.
    """
    t = np.asarray(t_src, dtype=float)
    x = np.asarray(xyz_src, dtype=float)
    if window_s > 0 and len(t) > 2:
        cs = np.vstack([np.zeros((1, 3)), np.cumsum(x, axis=0)])
        lo = np.searchsorted(t, t - 0.5 * window_s, side="left")
        hi = np.searchsorted(t, t + 0.5 * window_s, side="right")
        x = (cs[hi] - cs[lo]) / (hi - lo)[:, None]
    out = np.column_stack([np.interp(t_dst, t, x[:, k]) for k in range(3)])
    out[(t_dst < t[0]) | (t_dst > t[-1])] = np.nan
    return out


def quasi_static_accel(t_acc: np.ndarray, accel: np.ndarray, t_dst: np.ndarray, window_s: float = 0.5,
                       max_std: float = 0.3, max_norm_dev: float = 0.5) -> np.ndarray:
    """Low-passed specific force at ``t_dst`` where the device is quasi-static, NaN elsewhere.

    Quasi-static: over a window of ``window_s`` seconds the accelerometer's standard deviation (norm of the
    per-axis std) is below ``max_std`` m/s² and the mean's norm is within ``max_norm_dev`` m/s² of the
    recording's median norm.  During a continuous hand motion (no such instants) everything is NaN, and
    :func:`fit_alignment` then returns None.
    """
    t = np.asarray(t_acc, dtype=float)
    a = np.asarray(accel, dtype=float)
    if len(t) < 3:
        return np.full((len(t_dst), 3), np.nan)
    cs = np.vstack([np.zeros((1, 3)), np.cumsum(a, axis=0)])
    cs2 = np.vstack([np.zeros((1, 3)), np.cumsum(a * a, axis=0)])
    lo = np.searchsorted(t, t - 0.5 * window_s, side="left")
    hi = np.searchsorted(t, t + 0.5 * window_s, side="right")
    cnt = (hi - lo)[:, None]
    mean = (cs[hi] - cs[lo]) / cnt
    var = np.clip((cs2[hi] - cs2[lo]) / cnt - mean**2, 0.0, None)
    std = np.sqrt(var.sum(axis=1))
    nrm = np.linalg.norm(mean, axis=1)
    static = (std < max_std) & (np.abs(nrm - np.median(np.linalg.norm(a, axis=1))) < max_norm_dev)
    mean[~static] = np.nan
    out = np.column_stack([np.interp(t_dst, t, mean[:, k]) for k in range(3)])
    out[(t_dst < t[0]) | (t_dst > t[-1])] = np.nan
    return out


def fit_alignment(mag_cal: np.ndarray, accel: np.ndarray, static_tol: float = 0.5,
                  min_angle_deg: float = 1.0, min_samples: int = 30, max_iter: int = 20,
                  sin_dip: float | None = None, min_spread_deg: float = 15.0,
                  max_dip_error: float = 0.05) -> Alignment | None:
    """Magnetometer → IMU rotation from the constancy of the dip angle (module docstring).

    Parameters
    ----------
    mag_cal : ndarray (N, 3)
        Calibrated magnetometer samples (any scale), magnetometer axes.
    accel : ndarray (N, 3)
        Specific force at the same instants, m/s², IMU axes (low-passed; NaN rows are skipped).
    static_tol : float
        Keep samples with ``| |a| − median |a| | < static_tol`` m/s².
    sin_dip : float, optional
        Expected ``ĝ·f̂`` from the WMM (``−sin I`` for specific force and inclination I positive down);
        a fitted constant further than ``max_dip_error`` from it makes the result not significant.
    min_spread_deg : float
        The static gravity directions must spread at least this much in two dimensions (√ of the middle
        eigenvalue of their covariance, degrees); a few poses only cannot determine a rotation.

    Returns
    -------
    Alignment or None
        None when fewer than ``min_samples`` quasi-static samples remain.
    """
    m = np.asarray(mag_cal, dtype=float)
    a = np.asarray(accel, dtype=float)
    if m.shape != a.shape or m.ndim != 2 or m.shape[1] != 3:
        raise ValueError(f"accel: expected shape {m.shape} (one row per magnetometer sample), got {a.shape}")
    ok = np.all(np.isfinite(a), axis=1) & np.all(np.isfinite(m), axis=1)
    an = np.linalg.norm(a, axis=1)
    if ok.sum() < min_samples:
        return None
    ok &= np.abs(an - np.median(an[ok])) < static_tol
    if ok.sum() < min_samples:
        return None
    g = a[ok] / an[ok, None]
    mh = m[ok] / np.linalg.norm(m[ok], axis=1)[:, None]
    r = np.eye(3)
    c = float(np.mean(np.einsum("ij,ij->i", g, mh)))
    for _ in range(max_iter):
        v = mh @ r.T
        res = np.einsum("ij,ij->i", g, v) - c
        jac = np.hstack([np.cross(v, g), -np.ones((len(g), 1))])
        delta = -np.linalg.lstsq(jac, res, rcond=None)[0]
        r = _expm_so3(delta[:3]) @ r
        c += delta[3]
        if np.max(np.abs(delta)) < 1e-12:
            break
    v = mh @ r.T
    res = np.einsum("ij,ij->i", g, v) - c
    jac = np.hstack([np.cross(v, g), -np.ones((len(g), 1))])
    n = len(res)
    s2 = float(res @ res) / max(n - 4, 1)
    # effective sample size from the lag-1 autocorrelation of the residuals (AR(1) approximation)
    rho = float(np.clip(np.corrcoef(res[:-1], res[1:])[0, 1], 0.0, 0.999)) if n > 3 else 0.0
    inflate = (1.0 + rho) / (1.0 - rho)
    jtj = jac.T @ jac
    if np.linalg.cond(jtj) < 1e12:
        cov = np.linalg.inv(jtj) * s2 * inflate
    else:  # a single pose (or rotations about one axis only) cannot determine the rotation
        cov = np.full((4, 4), np.nan)
    w = _rotvec(r)
    angle = float(np.linalg.norm(w))
    cw = cov[:3, :3]
    try:
        stat = float(w @ np.linalg.solve(cw, w)) if np.all(np.isfinite(cw)) else 0.0
    except np.linalg.LinAlgError:
        stat = 0.0
    if not np.all(np.isfinite(cw)):
        angle_std = float("nan")
    elif angle > 0:
        angle_std = float(np.sqrt(max(w @ cw @ w, 0.0)) / angle)
    else:
        angle_std = float(np.sqrt(np.trace(cw) / 3))
    spread = float(np.degrees(np.sqrt(max(np.linalg.eigvalsh(np.cov(g.T))[1], 0.0))))
    consistent = abs(c) < 0.995 and (sin_dip is None or abs(c - sin_dip) < max_dip_error)
    if spread < min_spread_deg:
        reason = f"static samples in too few poses (gravity spread {spread:.1f}° < {min_spread_deg:g}°)"
    elif not consistent:
        reason = f"fitted dip constant {c:+.3f} inconsistent" + (
            f" with the WMM ({sin_dip:+.3f})" if sin_dip is not None else " (degenerate)")
    elif np.degrees(angle) <= min_angle_deg:
        reason = f"angle below {min_angle_deg:g}°"
    elif not stat > CHI2_3_999:
        reason = "not distinguishable from zero (χ² test)"
    else:
        reason = ""
    significant = not reason
    return Alignment(rotation=r, angle_deg=float(np.degrees(angle)),
                     angle_std_deg=float(np.degrees(angle_std)), significant=significant,
                     sin_dip=float(c), dip_rms=float(np.sqrt(np.mean(res**2))),
                     n_used=int(n), spread_deg=spread, reason=reason)


def fit_reference_rotation(mag_cal: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """[Long2013] eq. 12: rotation ``V`` minimising ``Σ |V m_cal,i − h_i|²`` (orthogonal Procrustes, SVD)."""
    m = np.asarray(mag_cal, dtype=float)
    h = np.asarray(reference, dtype=float)
    if m.shape != h.shape or m.ndim != 2 or m.shape[1] != 3:
        raise ValueError(f"reference: expected shape {m.shape}, got {h.shape}")
    u, _, vt = np.linalg.svd(h.T @ m)
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt
