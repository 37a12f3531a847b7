"""Hard-iron offset and field radius by linear least squares ([Liu2018], eqs. 3–16).

Model (soft iron neglected, [Liu2018] eq. 2): ``m̂ = m − O`` with ``|m̂| = R``.  Expanding
``(m − O)ᵀ(m − O) = R²`` gives, per sample i (eq. 7),

    Y_i = |m_i|² = [m_ix, m_iy, m_iz, 1] · β,   β = (2O_x, 2O_y, 2O_z, R² − |O|²)

and for N ≥ 4 samples ``β = (AᵀA)⁻¹AᵀY`` (eqs. 9–16), solved here with a least-squares solver on the
centred data for conditioning.  ``O = β[:3]/2`` and ``R = sqrt(β[3] + |O|²)``.

The offset covariance is the linear-LS one, ``σ_r² (AᵀA)⁻¹`` propagated to O, with σ_r estimated from
the algebraic residuals; it is a good first-order uncertainty when the coverage is broad.
"""

from __future__ import annotations

import numpy as np

from pdr_mag.calibration.model import MagCalibration


def _check_mag(mag: np.ndarray, min_samples: int = 4) -> np.ndarray:
    m = np.asarray(mag, dtype=float)
    if m.ndim != 2 or m.shape[1] != 3:
        raise ValueError(f"mag: expected shape (N, 3) in µT, got {m.shape}")
    if m.shape[0] < min_samples:
        raise ValueError(f"mag: need at least {min_samples} samples, got {m.shape[0]}")
    if not np.all(np.isfinite(m)):
        raise ValueError("mag: contains NaN or infinite values")
    return m


def sphere_lls(mag: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """The bare linear LS solve: offset (3,), radius, and the 3×3 offset covariance.

    Raises ValueError when the geometry is degenerate (e.g. all samples equal).
    """
    m = _check_mag(mag)
    center = m.mean(axis=0)
    mc = m - center
    a = np.column_stack([mc, np.ones(len(mc))])
    y = np.einsum("ij,ij->i", mc, mc)
    beta, _, rank, _ = np.linalg.lstsq(a, y, rcond=None)
    if rank < 4:
        raise ValueError("mag: samples do not span 3-D (degenerate sphere fit)")
    o_c = 0.5 * beta[:3]
    r2 = beta[3] + o_c @ o_c
    if r2 <= 0:
        raise ValueError("mag: sphere fit gave a negative squared radius")
    resid = y - a @ beta
    dof = max(len(m) - 4, 1)
    s2 = float(resid @ resid) / dof
    cov_beta = s2 * np.linalg.inv(a.T @ a)
    cov_o = 0.25 * cov_beta[:3, :3]
    return center + o_c, float(np.sqrt(r2)), cov_o


def fit_sphere(mag: np.ndarray) -> MagCalibration:
    """Offset-only calibration by linear least squares ([Liu2018]).

    Parameters
    ----------
    mag : ndarray, shape (N, 3)
        Raw magnetometer samples, µT, N ≥ 4.

    Returns
    -------
    MagCalibration
        ``soft_iron`` is the identity, ``field_uT`` the fitted radius.  Acceptance is not judged here
        (``accepted`` is True); see :mod:`pdr_mag.calibration.coverage` for the rules.
    """
    m = _check_mag(mag)
    offset, radius, cov_o = sphere_lls(m)
    norms = np.linalg.norm(m - offset, axis=1)
    return MagCalibration.from_arrays(
        offset,
        None,
        field_uT=radius,
        method="sphere",
        residual_rms_uT=float(np.sqrt(np.mean((norms - radius) ** 2))),
        offset_std_uT=np.sqrt(np.clip(np.diag(cov_o), 0, None)),
        n_samples=len(m),
        covariance=cov_o,
        extra={"covariance_params": ["offset_x", "offset_y", "offset_z"]},
    )
