"""Ellipsoid geometry shared by the fits: parameterisation, orthogonal projection, normals, curvature.

The ellipsoid of raw magnetometer readings is written

    x = b + L u,   |u| = 1,

with ``b`` the hard-iron offset (µT) and ``L`` symmetric positive definite (µT; its eigenvalues are the
semi-axes).  Any linear distortion ``m = S h + b`` with ``|h| = F`` is of this form with ``L`` the SPD polar
factor of ``F·S`` ([Long2013], eq. 5: ``S = R_L S_L V_Lᵀ``; ``L = R_L S_L R_Lᵀ·F`` absorbs the rotation
``V_L`` which the norm constraint cannot see).  The calibration of the contract then is

    m_cal = soft_iron @ (m − b),   soft_iron = F̄ L⁻¹,   F̄ = det(L)^{1/3},

so ``soft_iron`` is SPD with ``det(soft_iron) = 1`` (volume preserving, the sensor's own scale kept on
average) and ``field_uT = F̄`` is the geometric mean of the semi-axes.

A quadric is written ``xᵀA x + 2pᵀx + d = 0`` with the parameter vector
``θ = (A11, A22, A33, A23, A13, A12, p1, p2, p3, d)`` against the monomials
``z(x) = (x², y², z², 2yz, 2xz, 2xy, 2x, 2y, 2z, 1)``, so that ``θ·z(x) = 0`` on the surface.
"""

from __future__ import annotations

import numpy as np

from pdr_mag.calibration.model import MagCalibration

# Symmetric basis of L (or T): index pairs in the order (xx, yy, zz, xy, xz, yz).
SYM_PAIRS = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))
SYM_NAMES = ("xx", "yy", "zz", "xy", "xz", "yz")


def sym_basis(model: str = "full") -> np.ndarray:
    """Basis ``B_k`` (K, 3, 3) with ``L = Σ l_k B_k``: ``full`` (6), ``diagonal`` (3), ``sphere`` (1)."""
    if model == "sphere":
        return np.eye(3)[None]
    pairs = SYM_PAIRS[:3] if model == "diagonal" else SYM_PAIRS
    if model not in ("full", "diagonal"):
        raise ValueError(f"model: expected 'sphere', 'diagonal' or 'full', got {model!r}")
    out = np.zeros((len(pairs), 3, 3))
    for k, (i, j) in enumerate(pairs):
        out[k, i, j] = 1.0
        out[k, j, i] = 1.0
    return out


def sym_coords(mat: np.ndarray, model: str = "full") -> np.ndarray:
    """Coordinates ``l`` of a symmetric matrix in :func:`sym_basis` (least squares for the reduced models)."""
    basis = sym_basis(model)
    a = basis.reshape(len(basis), 9).T
    return np.linalg.lstsq(a, np.asarray(mat, float).reshape(9), rcond=None)[0]


def sqrtm_spd(mat: np.ndarray, power: float = 0.5) -> np.ndarray:
    """``mat^power`` for a symmetric positive-definite 3×3 matrix."""
    w, v = np.linalg.eigh(0.5 * (mat + mat.T))
    if w[0] <= 0:
        raise ValueError("matrix is not positive definite")
    return (v * w**power) @ v.T


def spd_part(g: np.ndarray) -> np.ndarray:
    """SPD polar factor ``P = (GᵀG)^{1/2}`` of a non-singular G, so that ``|G x| = |P x|``."""
    return sqrtm_spd(g.T @ g)


def calibration_from_ellipsoid(L: np.ndarray) -> tuple[np.ndarray, float]:
    """``(soft_iron, field_uT)`` from the SPD semi-axes L: ``soft_iron = F̄ L⁻¹``, ``F̄ = det(L)^{1/3}``."""
    w, v = np.linalg.eigh(L)
    if w[0] <= 0:
        raise ValueError("ellipsoid matrix L is not positive definite")
    f = float(np.prod(w) ** (1.0 / 3.0))
    return (v / w) @ v.T * f, f


def ellipsoid_from_calibration(soft_iron: np.ndarray, field_uT: float) -> np.ndarray:
    """Inverse of :func:`calibration_from_ellipsoid`: ``L = field · soft_iron⁻¹``."""
    return field_uT * np.linalg.inv(soft_iron)


def quadric_to_ellipsoid(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centre ``b`` and SPD ``L`` of the quadric θ (module docstring); ValueError if it is no ellipsoid."""
    th = np.asarray(theta, dtype=float)
    a = np.array([[th[0], th[5], th[4]], [th[5], th[1], th[3]], [th[4], th[3], th[2]]])
    p = th[6:9]
    d = th[9]
    try:
        b = -np.linalg.solve(a, p)
    except np.linalg.LinAlgError as exc:
        raise ValueError("quadric is degenerate (singular quadratic part)") from exc
    k = b @ a @ b - d
    q = a / k if k != 0 else a * np.nan
    w = np.linalg.eigvalsh(q) if np.all(np.isfinite(q)) else np.array([np.nan])
    if not np.all(w > 0):
        raise ValueError("quadric is not an ellipsoid")
    return b, sqrtm_spd(q, -0.5)


def monomials(x: np.ndarray) -> np.ndarray:
    """The design rows ``z(x)`` (N, 10) of the quadric (module docstring)."""
    x0, x1, x2 = x[:, 0], x[:, 1], x[:, 2]
    one = np.ones(len(x))
    return np.column_stack([x0 * x0, x1 * x1, x2 * x2, 2 * x1 * x2, 2 * x0 * x2, 2 * x0 * x1,
                            2 * x0, 2 * x1, 2 * x2, one])


def normalise_data(mag: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Centred and scaled data ``(m − c)/s`` (RMS radius 1) for well-conditioned algebraic fits."""
    c = mag.mean(axis=0)
    s = float(np.sqrt(np.mean(np.sum((mag - c) ** 2, axis=1))))
    if not s > 0:
        raise ValueError("mag: all samples are equal")
    return (mag - c) / s, c, s


class Projection:
    """Orthogonal projection of samples onto the ellipsoid ``x = b + L u``.

    In the principal frame ``L = V diag(a) Vᵀ``, ``y = Vᵀ(m − b)``, the foot point is
    ``p_k = a_k² y_k / (a_k² + t)`` with ``t`` the root of ``Σ a_k² y_k² / (a_k² + t)² = 1`` (Newton,
    vectorised over samples, started from the radial approximation).  Then ``m − x = t V (p / a²)``, so the
    signed orthogonal distance is ``d = t |p / a²|`` (positive outside), the unit normal is
    ``n = V (p/a²) / |p/a²|`` and ``u = L⁻¹(x − b) = V (p / a)``.

    Two samples have no foot point from the iteration, and are set apart where the division would meet
    zero: one exactly at the centre (``y = 0``: the secular function is −1 for every t, its derivative 0)
    has the ends of the shortest axis as its nearest points, ``p = (a₀, 0, 0)``, ``t = −a₀²``, ``d = −a₀``
    (closed form); one whose ``t`` lands exactly on a pole ``t = −a_k²`` (where ``p_k`` is undefined) stops
    iterating and takes the radial point below, as the samples inside the evolute do.

    Attributes
    ----------
    d : (N,) signed orthogonal distance, µT.  x : (N, 3) foot points.  u : (N, 3) unit directions.
    n : (N, 3) outward unit normals.  mean_curv2 : (N,) sum of principal curvatures κ₁+κ₂ at x, 1/µT.
    fallback : number of samples deep inside the ellipsoid (inside its evolute) for which the radial point
    ``y / |y/a|`` replaced the orthogonal foot point (d is then the normal component of ``m − x``).
    """

    def __init__(self, mag: np.ndarray, b: np.ndarray, L: np.ndarray, iters: int = 30, tol: float = 1e-13):
        a, v = np.linalg.eigh(L)
        if a[0] <= 0:
            raise ValueError("ellipsoid matrix L is not positive definite")
        # component-major (3, N) layout: every operation below is on contiguous length-N vectors
        a2 = a * a
        y = v.T @ (mag - b).T
        yy = y * y
        r = np.sqrt(yy[0] + yy[1] + yy[2])
        centre = r == 0.0
        s = np.sqrt(yy[0] / a2[0] + yy[1] / a2[1] + yy[2] / a2[2])
        s[centre] = 1.0
        t = (r / s) ** 2 * (s - 1.0)  # radial approximation a_eff²(s − 1), exact for a sphere
        lo = -a2[0] * (1.0 - 1e-12)
        ay2 = a2[:, None] * yy
        pole = np.zeros_like(centre)  # t exactly at some −a_k²: no Newton step from there
        step = np.zeros_like(t)
        q, qd = np.zeros_like(ay2), np.zeros_like(ay2)  # a_k² y_k² / d_k², and that over d_k (d_k = a_k² + t)
        for _ in range(iters):
            dk = a2[:, None] + t
            pole |= np.any(dk == 0.0, axis=0)
            go = ~(centre | pole)
            np.divide(ay2, dk * dk, out=q, where=go)
            np.divide(q, dk, out=qd, where=go)
            f = q[0] + q[1] + q[2] - 1.0
            fp = -2.0 * (qd[0] + qd[1] + qd[2])  # < 0 wherever go (some q_k > 0)
            np.divide(f, fp, out=step, where=go)
            step[~go] = 0.0  # a sample that met a pole stops (its last step would hold off the break)
            t = np.maximum(t - step, 0.5 * (t + lo))
            if np.max(np.abs(step)) < tol * (a2[0] + np.max(np.abs(t))):
                break
        dk = a2[:, None] + t
        pole |= np.any(dk == 0.0, axis=0)
        live = ~(centre | pole)
        p = np.zeros_like(y)
        np.divide(a2[:, None] * y, dk, out=p, where=live)
        pa = p / a[:, None]
        bad = pole | (live & (~np.isfinite(t) | (np.abs(pa[0] ** 2 + pa[1] ** 2 + pa[2] ** 2 - 1.0) > 1e-8)))
        if np.any(bad):
            # inside the evolute (deeper than the smallest radius of curvature — never the case for samples
            # within noise of the surface) the secular root can be missing: fall back to the radial point
            pr = y[:, bad] / s[bad]
            p[:, bad] = pr
            w = pr / a2[:, None]
            t[bad] = np.sum((y[:, bad] - pr) * w, axis=0) / np.sum(w * w, axis=0)
        if np.any(centre):
            p[:, centre] = np.array([a[0], 0.0, 0.0])[:, None]
            t[centre] = -a2[0]
        pa = p / a[:, None]
        pn = p / a2[:, None]
        pn_norm = np.sqrt(pn[0] ** 2 + pn[1] ** 2 + pn[2] ** 2)
        self.d = t * pn_norm
        self.n = (v @ (pn / pn_norm)).T
        self.x = b + (v @ p).T
        self.u = (v @ pa).T
        self.fallback = int(bad.sum())
        # κ1+κ2 = (|g|² tr Q − gᵀQg)/|g|³ with Q = L⁻², g = Q(x − b) (implicit-surface formula)
        g_norm2 = pn_norm**2
        gqg = pn[0] ** 2 / a2[0] + pn[1] ** 2 / a2[1] + pn[2] ** 2 / a2[2]
        self.mean_curv2 = (g_norm2 * np.sum(1.0 / a2) - gqg) / pn_norm**3


def geometric_jacobian(proj: Projection, basis: np.ndarray) -> np.ndarray:
    """Jacobian of the signed distances w.r.t. θ = (b, l): ``∂d_i/∂θ = −n_iᵀ G_i``, ``G_i = [I, B_k u_i]``.

    By the envelope theorem the foot point's own motion does not enter (it is a stationary point of the
    distance), so this is the exact first derivative of the reduced (nuisance-eliminated) problem.
    """
    n, u = proj.n, proj.u
    jb = -n
    jl = -np.einsum("ij,kjm,im->ik", n, basis, u)
    return np.hstack([jb, jl])


def calibrated_residuals(mag: np.ndarray, soft_iron: np.ndarray, offset: np.ndarray,
                         field: float) -> np.ndarray:
    """``|soft_iron (m − b)| − field`` per sample, µT."""
    w = (mag - offset) @ np.asarray(soft_iron).T
    return np.sqrt(np.einsum("ij,ij->i", w, w)) - field


def param_names(model: str = "full") -> list[str]:
    """Names of θ = (b, l) in the order of :func:`geometric_jacobian` (``covariance_params``)."""
    k = {"sphere": ["radius"], "diagonal": [f"L_{n}" for n in SYM_NAMES[:3]],
         "full": [f"L_{n}" for n in SYM_NAMES]}[model]
    return ["offset_x", "offset_y", "offset_z", *k]


def build_calibration(mag: np.ndarray, b: np.ndarray, L: np.ndarray, method: str, model: str = "full",
                      extra: dict | None = None, cov: np.ndarray | None = None) -> MagCalibration:
    """A :class:`MagCalibration` from the ellipsoid (b, L), with residual RMS and parameter covariance.

    When ``cov`` is not given it is the first-order (Gauss–Newton) covariance of the geometric fit at
    (b, L): ``σ̂² (JᵀJ)⁻¹`` with ``J`` from :func:`geometric_jacobian` and ``σ̂² = Σ d_i² / (N − p)``.  This
    is the covariance of the efficient (ML) estimate; for the algebraic fits it is a lower bound.
    """
    soft_iron, field = calibration_from_ellipsoid(L)
    basis = sym_basis(model)
    names = param_names(model)
    if cov is None:
        proj = Projection(mag, b, L)
        jac = geometric_jacobian(proj, basis)
        dof = max(len(mag) - jac.shape[1], 1)
        s2 = float(proj.d @ proj.d) / dof
        cov = _safe_inv(jac.T @ jac)
        cov = None if cov is None else s2 * cov
    res = calibrated_residuals(mag, soft_iron, b, field)
    ex = {"covariance_params": names, "model": model}
    ex.update(extra or {})
    return MagCalibration.from_arrays(
        b, soft_iron,
        field_uT=field,
        method=method,
        residual_rms_uT=float(np.sqrt(np.mean(res**2))),
        offset_std_uT=(np.full(3, np.nan) if cov is None else np.sqrt(np.clip(np.diag(cov)[:3], 0, None))),
        n_samples=len(mag),
        covariance=cov,
        extra=ex,
    )


def _safe_inv(m: np.ndarray) -> np.ndarray | None:
    """Inverse of a normal matrix, or None when it is (numerically) singular."""
    if not np.all(np.isfinite(m)) or np.linalg.cond(m) > 1e14:
        return None
    return np.linalg.inv(m)
