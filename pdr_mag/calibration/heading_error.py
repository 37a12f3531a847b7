"""The heading error a calibration's parameter uncertainty can cause, worst case over heading and pose.

Model (the ellipsoid of :mod:`pdr_mag.calibration.geometry`): raw samples ``m = b + L u``, ``u`` the unit
field direction in magnetometer axes.  A calibration ``(b̂, L̂) = (b + δb, L + δL)`` returns the direction

    û ∝ L̂⁻¹ (m − b̂) ≈ u − L⁻¹ (δb + δL u) = u − L⁻¹ G(u) δθ,   G(u) = [I, B_k u],

the same ``G`` as the Cramér–Rao bound of :mod:`pdr_mag.calibration.crlb` (θ = (b, l), ``L = Σ l_k B_k``).
The isotropic part of ``δL`` (the radius) moves ``û`` along ``u`` and changes nothing but ``|m_cal|``.

The heading is the azimuth of the horizontal part of the calibrated field.  An error ``e`` of the unit
direction changes it by ``δψ = wᵀ e / cos I``: ``w`` the unit vector pointing east (horizontal and
perpendicular to the field, so ``w ⊥ u``) in magnetometer axes, ``I`` the inclination (dip), so that
``cos I = H / F`` is the horizontal share of the field.  With ``Σ = Cov(θ̂)``:

    var δψ(u, w) = wᵀ K(u) Σ K(u)ᵀ w / cos² I,   K(u) = L⁻¹ G(u).

Every pair ``(u, w ⊥ u)`` is one orientation of the phone, and every device axis is horizontal in some
common way of carrying a phone (x and y when texting, z at the ear or in a pocket), so the bound is the
worst case over all of them:

    σ_ψ = max_u sqrt(λ_max(P_u K(u) Σ K(u)ᵀ P_u)) / cos I,   P_u = I − u uᵀ,

evaluated on a near-uniform grid of field directions ``u``.  For the offset alone it is
``sqrt(λ_max(L⁻¹ Σ_bb L⁻¹)) / cos I`` ≈ ``sqrt(λ_max(Σ_bb)) / H``: an offset error of δ µT turns the
heading by up to δ / H radians.

The *undetermined direction* is the top eigenvector of the offset error as the calibration passes it on,
``A Σ_bb Aᵀ`` (``A`` = soft iron, rotated into IMU axes when ``mag_to_imu`` is set): the device axis along
which the calibrated field is least known.  The offset along an axis ``a`` is determined by samples in
which the field points along ``+a`` and along ``−a`` (the spread of ``u · a``); turning the phone about an
axis perpendicular to ``a`` sweeps ``a`` through the field, which is the motion :func:`motion_hint` names.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import lru_cache

import numpy as np

from pdr_mag.calibration.geometry import (
    Projection,
    ellipsoid_from_calibration,
    geometric_jacobian,
    param_names,
    sym_basis,
)
from pdr_mag.calibration.model import MagCalibration

#: Inclination assumed when only the field strength (or nothing) is known: the dip of the populated
#: mid-latitudes (Europe, North America, East Asia: 50–70°); cos 60° = 0.5 is the horizontal share.
DEFAULT_INCLINATION_DEG = 60.0

_AXES = ("x", "y", "z")
_SYM = {"xx": (0, 0), "yy": (1, 1), "zz": (2, 2), "xy": (0, 1), "xz": (0, 2), "yz": (1, 2)}


@dataclass(frozen=True)
class HeadingBound:
    """The worst-case heading error of a calibration (module docstring).

    Attributes
    ----------
    std_deg : float
        1-σ heading error, worst case over heading and pose, degrees (``inf``: not determined).
    offset_std_deg : float
        The same from the offset's uncertainty alone, degrees.
    direction : tuple of 3 float or None
        Unit vector (device axes) along which the calibrated offset is least known.
    direction_std_uT : float
        1-σ of the calibrated offset along ``direction``, µT.
    inclination_deg : float
        The inclination used for ``cos I``.
    """

    std_deg: float
    offset_std_deg: float
    direction: tuple[float, float, float] | None
    direction_std_uT: float
    inclination_deg: float

    def to_dict(self) -> dict:
        return {"std_deg": self.std_deg, "offset_std_deg": self.offset_std_deg,
                "direction": None if self.direction is None else list(self.direction),
                "direction_std_uT": self.direction_std_uT, "inclination_deg": self.inclination_deg}


def fibonacci_directions(n: int = 600) -> np.ndarray:
    """``n`` near-uniform unit vectors (n, 3) on the sphere (golden-angle spiral)."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    r = np.sqrt(1.0 - z * z)
    phi = np.pi * (3.0 - np.sqrt(5.0)) * k
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def _basis_from_names(names: list[str], p: int) -> np.ndarray:
    """Matrices ``B_k`` (p − 3, 3, 3) of the non-offset parameters, from ``covariance_params`` names."""
    out = np.zeros((p - 3, 3, 3))
    for k, name in enumerate(names[3:p]):
        if name == "radius":
            out[k] = np.eye(3)
        elif name.startswith("L_") and name[2:] in _SYM:
            i, j = _SYM[name[2:]]
            out[k, i, j] = out[k, j, i] = 1.0
        else:
            raise ValueError(f"covariance_params: unknown parameter {name!r}")
    return out


def _param_names(cal: MagCalibration, p: int) -> list[str]:
    names = cal.extra.get("covariance_params") if isinstance(cal.extra, dict) else None
    if names is not None and len(names) == p:
        return list(names)
    default = {3: ["offset_x", "offset_y", "offset_z"], 4: param_names("sphere"), 6: param_names("diagonal"),
               9: param_names("full")}
    if p not in default:
        raise ValueError(f"covariance: {p} parameters without covariance_params names")
    return default[p]


def inclination_of(field, default_deg: float = DEFAULT_INCLINATION_DEG) -> float:
    """The inclination of an ``EarthField`` (anything with ``inclination_deg``), else ``default_deg``."""
    inc = getattr(field, "inclination_deg", None)
    return float(default_deg if inc is None or not np.isfinite(inc) else inc)


@lru_cache(maxsize=4)
def _grid(n: int = 600) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Field directions ``u`` (n, 3) and an orthonormal basis ``e1, e2`` of the plane ⊥ each (read-only)."""
    u = fibonacci_directions(n)
    ref = np.where(np.abs(u[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    e1 = np.cross(u, ref)
    e1 /= np.linalg.norm(e1, axis=1)[:, None]
    e2 = np.cross(u, e1)
    for a in (u, e1, e2):
        a.flags.writeable = False
    return u, e1, e2


def _tangent_sensitivity(linv: np.ndarray, basis: np.ndarray, u: np.ndarray, e: np.ndarray) -> np.ndarray:
    """``eᵀ K(u)`` (n, 3 + K), ``K(u) = L⁻¹ [I, B_k u]``: the heading-plane component ``e`` (⊥ u) of the
    direction error per unit parameter change, at the field directions ``u`` (n, 3)."""
    v = e @ linv.T  # (L⁻ᵀ e)ᵀ = eᵀ L⁻¹
    if not len(basis):
        return v
    return np.hstack([v, np.einsum("ni,kij,nj->nk", v, basis, u)])


def heading_shift(cal: MagCalibration, delta, inclination_deg: float = DEFAULT_INCLINATION_DEG) -> float:
    """The largest heading change, degrees, over heading and pose, of the full-model parameter change
    ``delta`` = (δb, δl) (9,) at ``cal``: ``max_u |P_u K(u) δθ| / cos I`` (module docstring)."""
    u, e1, e2 = _grid()
    linv, basis, d = cal.soft_iron_array / cal.field_uT, sym_basis("full"), np.asarray(delta, dtype=float)
    x1, x2 = _tangent_sensitivity(linv, basis, u, e1) @ d, _tangent_sensitivity(linv, basis, u, e2) @ d
    return float(np.degrees(np.sqrt(np.max(x1 * x1 + x2 * x2)) / np.cos(np.radians(inclination_deg))))


def heading_bound(cal: MagCalibration, inclination_deg: float = DEFAULT_INCLINATION_DEG) -> HeadingBound:
    """The worst-case 1-σ heading error that ``cal.covariance`` allows (module docstring).

    With ``Σ = C Cᵀ`` and ``z_j = e_jᵀ K(u) C`` for the basis ``e1, e2`` of the plane ⊥ u, the 2 × 2
    matrix ``[z_j · z_k]`` is ``P_u K Σ Kᵀ P_u`` in that plane; its largest eigenvalue
    ``(a + c)/2 + sqrt(((a − c)/2)² + b²)`` is maximised over the grid of 600 directions.
    ``std_deg`` is ``inf`` (and ``direction`` None) when the covariance is missing or not finite, or the
    field radius or soft iron cannot be inverted.
    """
    nothing = HeadingBound(float("inf"), float("inf"), None, float("inf"), float(inclination_deg))
    if cal.covariance is None or not (np.isfinite(cal.field_uT) and cal.field_uT > 0):
        return nothing
    cov = np.asarray(cal.covariance, dtype=float)
    p = cov.shape[0]
    if cov.shape != (p, p) or p < 3 or not np.all(np.isfinite(cov)):
        return nothing
    cov = 0.5 * (cov + cov.T)
    soft = cal.soft_iron_array
    try:
        basis = _basis_from_names(_param_names(cal, p), p)
        linv = soft / cal.field_uT  # L⁻¹ = soft_iron / F̄  (geometry.calibration_from_ellipsoid)
        np.linalg.cholesky(soft)
    except (ValueError, np.linalg.LinAlgError):
        return nothing
    cos_i = np.cos(np.radians(inclination_deg))
    w, v = np.linalg.eigh(cov)
    c = v * np.sqrt(np.maximum(w, 0.0))
    u, e1, e2 = _grid()
    z1 = _tangent_sensitivity(linv, basis, u, e1) @ c
    z2 = _tangent_sensitivity(linv, basis, u, e2) @ c
    a11, a22, a12 = np.sum(z1 * z1, axis=1), np.sum(z2 * z2, axis=1), np.sum(z1 * z2, axis=1)
    lam = 0.5 * (a11 + a22) + np.sqrt(0.25 * (a11 - a22) ** 2 + a12**2)
    std = float(np.sqrt(max(lam.max(), 0.0)) / cos_i)
    cb = linv @ cov[:3, :3] @ linv.T
    off = float(np.sqrt(max(np.linalg.eigvalsh(0.5 * (cb + cb.T))[-1], 0.0)) / cos_i)
    # the calibrated offset error M δb (M = cal.matrix), in device (IMU) axes
    a = cal.matrix
    ca = a @ cov[:3, :3] @ a.T
    w, v = np.linalg.eigh(0.5 * (ca + ca.T))
    d = v[:, -1] * (1.0 if v[np.argmax(np.abs(v[:, -1])), -1] > 0 else -1.0)
    return HeadingBound(float(np.degrees(std)), float(np.degrees(off)), tuple(float(x) for x in d),
                        float(np.sqrt(max(w[-1], 0.0))), float(inclination_deg))


def axis_name(direction) -> str:
    """``"z"`` for a direction within 25° of a device axis (sign ignored), else ``"(0.71, 0.00, 0.71)"``."""
    d = np.asarray(direction, dtype=float)
    k = int(np.argmax(np.abs(d)))
    if abs(d[k]) >= np.cos(np.radians(25.0)):
        return _AXES[k]
    return "(" + ", ".join(f"{x:.2f}" for x in d) + ")"


_MOTION = {
    "x": "rotate the phone about its y axis (roll it onto its side and over) and about its z axis "
         "(turn it flat), so that its x axis (right edge) points along the field and against it",
    "y": "rotate the phone about its x axis (tip the top edge down and over) and about its z axis "
         "(turn it flat), so that its y axis (top edge) points along the field and against it",
    "z": "rotate the phone about its x and y axes (turn it screen down and back up), so that its "
         "z axis (screen normal) points along the field and against it",
}
_ABOUT = {"x": "its x axis (tip the top edge down and over)",
          "y": "its y axis (roll it onto its side and over)",
          "z": "its z axis (turn it flat, all round)"}


def motion_hint(direction) -> str:
    """The motion that determines the offset along ``direction`` (device axes), in words: a rotation
    about an axis perpendicular to it (module docstring) — the two other device axes for a direction
    along one, else the device axis most nearly perpendicular to it."""
    name = axis_name(direction)
    if name in _MOTION:
        return _MOTION[name]
    k = _AXES[int(np.argmin(np.abs(np.asarray(direction, dtype=float))))]
    return (f"rotate the phone about {_ABOUT[k]}, so that the direction {name} points along the field and "
            "against it")


def fit_figures(mag: np.ndarray, cal: MagCalibration, inclination_deg: float = DEFAULT_INCLINATION_DEG,
                lag: int = 100, noise_lag: int = 10) -> dict:
    """What the samples ``mag`` (raw µT, in time order) determine about the heading, at the fit ``cal``.

    The information is that of the full model (offset and full soft iron, :mod:`.crlb`) at the fitted
    ellipsoid, whatever model the fit chose: every phone has some soft iron, and a simpler model only
    says that the samples do not show it, not that they would show it in the poses they miss.  With
    ``J`` the Jacobian of the orthogonal distances ``d_i`` (``geometry``), ``H = JᵀJ`` and the full
    model's Gauss–Newton step from the fit ``δθ = −H⁻¹Jᵀd`` (zero at a full-model optimum), the residuals
    are ``r = d + J δθ``, and the heading error (1-σ, worst heading and pose) has four parts:

    * ``white_std_deg``: the covariance ``Σ_w = σ_noise² H⁻¹ · N/(N − p)`` with the noise ``σ_noise`` below
      (:func:`heading_bound`) — what the motion and the sensor's noise leave undetermined;
    * ``correlated_std_deg``: the same from the Newey–West (Bartlett kernel, ``lag`` samples) long-run
      covariance of the scores ``s_i = J_iᵀ r_i``, ``Σ_hac = H⁻¹ (Σ_{|l| ≤ lag} (1 − |l|/(lag + 1))
      Σ_i s_i s_{i+l}ᵀ) H⁻¹ · N/(N − p)``: residuals correlated in time (a filtered sensor, a field that
      changes as the phone moves) carry less information than white ones;
    * ``field_error_deg``: a field that changes while the phone turns.  Where it follows the motion (a
      hand near steel) the fit absorbs it into the parameters, a bias no covariance shows; what it cannot
      absorb stays in the residual as a slowly varying part.  With the noise measured over ``noise_lag``
      samples, ``σ_noise² = mean((r_{i+k} − r_i)²)/2`` (k longer than the few samples over which a
      phone's filtered noise is correlated, shorter than a turn of the hand), the slow part is
      ``δ_slow = sqrt(max(RMS² − σ_noise², 0))``, a change of the field that turns a heading by
      ``δ_slow / (F cos I)`` radians — the scale of the bias it leaves;
    * ``model_shift_deg``: what the full model's step ``δθ`` would still change (:func:`heading_shift`):
      the soft iron a simpler model (offset only, axis scales) leaves out.

    ``std_deg = sqrt(max(white, correlated)² + field² + shift²)`` is the figure the tolerance applies to.

    Returns
    -------
    dict
        ``std_deg``, ``white_std_deg``, ``correlated_std_deg``, ``field_error_deg``, ``model_shift_deg``;
        ``offset_std_deg``, ``direction``, ``direction_std_uT`` (of the larger covariance);
        ``radius_std_uT`` (1-σ of ``field_uT = det(L)^{1/3}``); ``residual_noise_uT`` (σ_noise),
        ``residual_slow_uT`` (δ_slow), ``inclination_deg``, ``lag``, ``noise_lag``.
    """
    m = np.asarray(mag, dtype=float)
    n = len(m)
    p = 9
    basis = sym_basis("full")
    L = ellipsoid_from_calibration(cal.soft_iron_array, cal.field_uT)
    proj = Projection(m, cal.offset_array, L)
    jac = geometric_jacobian(proj, basis)
    h = jac.T @ jac
    w, v = np.linalg.eigh(0.5 * (h + h.T))
    w = np.maximum(w, max(w[-1], 1e-300) * 1e-15)  # a direction the data do not see: huge, not inf
    h_inv = (v / w) @ v.T
    seen = w >= w[-1] * 1e-10  # the step only along directions the samples determine
    delta = -(v[:, seen] / w[seen]) @ (v[:, seen].T @ (jac.T @ proj.d))
    r = proj.d + jac @ delta
    dof = max(n - p, 1)
    k = int(min(max(noise_lag, 1), max(n - 1, 1)))
    noise = float(np.sqrt(np.mean((r[k:] - r[:-k]) ** 2) / 2.0)) if n > k else float("nan")
    rms = float(np.sqrt(np.mean(r**2)))
    slow = float(np.sqrt(max(rms**2 - noise**2, 0.0))) if np.isfinite(noise) else 0.0
    cov_w = h_inv * (min(noise, rms) if np.isfinite(noise) else rms) ** 2 * n / dof
    sc = jac * r[:, None]
    meat = sc.T @ sc
    for j in range(1, min(int(lag), n - 1) + 1):
        c = sc[j:].T @ sc[:-j]
        meat += (1.0 - j / (lag + 1.0)) * (c + c.T)
    cov_h = h_inv @ meat @ h_inv * n / dof
    names = {"covariance_params": param_names("full")}
    b_w = heading_bound(replace(cal, covariance=_tup(cov_w), extra=names), inclination_deg)
    b_h = heading_bound(replace(cal, covariance=_tup(cov_h), extra=names), inclination_deg)
    worst, cov = (b_h, cov_h) if b_h.std_deg > b_w.std_deg else (b_w, cov_w)
    field_err = float(np.degrees(slow / (cal.field_uT * np.cos(np.radians(inclination_deg)))))
    shift = heading_shift(cal, delta, inclination_deg)
    # F̄ = det(L)^(1/3): ∂F̄/∂l_k = F̄/3 · tr(L⁻¹ B_k)
    grad_f = np.zeros(p)
    grad_f[3:] = cal.field_uT / 3.0 * np.einsum("ij,kji->k", np.linalg.inv(L), basis)
    return {"std_deg": float(np.sqrt(worst.std_deg**2 + field_err**2 + shift**2)),
            "white_std_deg": b_w.std_deg, "correlated_std_deg": b_h.std_deg,
            "field_error_deg": field_err, "model_shift_deg": shift,
            "offset_std_deg": worst.offset_std_deg,
            "direction": None if worst.direction is None else list(worst.direction),
            "direction_std_uT": worst.direction_std_uT,
            "radius_std_uT": float(np.sqrt(max(grad_f @ cov @ grad_f, 0.0))),
            "residual_noise_uT": noise, "residual_slow_uT": slow,
            "inclination_deg": float(inclination_deg), "lag": int(lag), "noise_lag": k}


def _tup(a: np.ndarray) -> tuple:
    return tuple(map(tuple, np.asarray(a, dtype=float).tolist()))
