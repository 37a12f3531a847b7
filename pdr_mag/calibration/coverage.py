"""How much of the sphere of field directions the samples cover, and the acceptance rules with reasons.

Coverage is measured on the calibrated directions ``û_i = m_cal,i / |m_cal,i|`` with an equal-area grid
(Lambert's cylindrical projection): ``n_bands`` bands equal in ``z`` times ``n_sectors`` equal longitude
sectors, every cell of area ``4π / (n_bands · n_sectors)``.  ``coverage`` is the share of cells holding at
least one sample.  Two further figures catch the classic bad calibrations:

* ``worst_cap_coverage``: the smallest share of covered cells inside any 60° cap (a quarter of the sphere)
  centred on a grid cell — ≈ 0 when one side of the sphere was never seen (a hemisphere only);
* ``out_of_plane_deg``: ``sqrt(λ_min)`` of the covariance of ``û`` in degrees — ≈ 0 when the phone was only
  turned about one axis (a planar rotation: the directions lie on one circle).

:func:`accept` turns a calibration (its ``coverage``, ``extra`` figures, offset, shape, covariance) and an
optional reference field strength (WMM) into a verdict with human-readable reasons; :func:`assess` first
computes the figures from the samples.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pdr_mag.calibration.model import MagCalibration


@dataclass(frozen=True)
class AcceptanceSettings:
    """Thresholds of the acceptance rules (defaults in brackets).

    Attributes
    ----------
    min_samples : int
        Fewer samples than this cannot support a 9-parameter fit [50].
    min_coverage : float
        Minimum share of the equal-area grid cells covered [0.5].
    min_cap_coverage : float
        Minimum covered share inside the emptiest 60° cap; below it "only one side (hemisphere)" [0.15].
    min_out_of_plane_deg : float
        Minimum spread of directions out of their best plane, degrees; below it "planar rotation" [8].
    max_radius_error : float
        Maximum relative difference of the radius from the reference (WMM) field [0.2].
    max_offset_uT : float
        Largest plausible hard-iron offset norm, µT (phone sensors saturate at a few mT) [1500].
    max_axis_ratio : float
        Largest plausible ratio of soft-iron eigenvalues (eigenvalue spread) [1.5].
    max_offset_std_frac : float
        Largest 1-σ offset uncertainty as a share of the field [0.02].
    max_condition : float
        Largest condition number of the parameter correlation matrix [1e6].
    max_residual_frac : float
        Largest residual RMS as a share of the field [0.05].
    """

    min_samples: int = 50
    min_coverage: float = 0.5
    min_cap_coverage: float = 0.15
    min_out_of_plane_deg: float = 8.0
    max_radius_error: float = 0.2
    max_offset_uT: float = 1500.0
    max_axis_ratio: float = 1.5
    max_offset_std_frac: float = 0.02
    max_condition: float = 1e6
    max_residual_frac: float = 0.05


def _grid(n_bands: int, n_sectors: int) -> np.ndarray:
    z = -1.0 + (np.arange(n_bands) + 0.5) * 2.0 / n_bands
    phi = -np.pi + (np.arange(n_sectors) + 0.5) * 2.0 * np.pi / n_sectors
    zz, pp = np.meshgrid(z, phi, indexing="ij")
    r = np.sqrt(1.0 - zz**2)
    return np.stack([r * np.cos(pp), r * np.sin(pp), zz], axis=-1).reshape(-1, 3)


def _cells(directions: np.ndarray, n_bands: int, n_sectors: int) -> np.ndarray:
    band = np.clip(((directions[:, 2] + 1.0) * 0.5 * n_bands).astype(int), 0, n_bands - 1)
    phi = np.arctan2(directions[:, 1], directions[:, 0])
    sec = np.clip(((phi + np.pi) / (2.0 * np.pi) * n_sectors).astype(int), 0, n_sectors - 1)
    hit = np.zeros(n_bands * n_sectors, dtype=bool)
    hit[band * n_sectors + sec] = True
    return hit


def _unit(mag_cal: np.ndarray) -> np.ndarray:
    m = np.asarray(mag_cal, dtype=float)
    if m.ndim != 2 or m.shape[1] != 3:
        raise ValueError(f"mag_cal: expected shape (N, 3) in µT, got {m.shape}")
    nrm = np.linalg.norm(m, axis=1)
    m = m[nrm > 0]
    return m / np.linalg.norm(m, axis=1)[:, None]


def coverage(mag_cal: np.ndarray, n_bands: int = 8, n_sectors: int = 16) -> float:
    """Share of the equal-area grid cells (module docstring) holding a calibrated direction, in [0, 1]."""
    u = _unit(mag_cal)
    if len(u) == 0:
        return 0.0
    return float(_cells(u, n_bands, n_sectors).mean())


def direction_stats(mag_cal: np.ndarray, n_bands: int = 8, n_sectors: int = 16) -> dict:
    """``coverage``, ``worst_cap_coverage``, ``out_of_plane_deg``, ``mean_direction`` (|mean û|)."""
    u = _unit(mag_cal)
    if len(u) < 3:
        return {"coverage": 0.0, "worst_cap_coverage": 0.0, "out_of_plane_deg": 0.0, "mean_direction": 1.0}
    hit = _cells(u, n_bands, n_sectors)
    centres = _grid(n_bands, n_sectors)
    in_cap = (centres @ centres.T) >= 0.5  # caps of 60° half-angle around each cell centre
    cap_cov = (in_cap & hit[None, :]).sum(axis=1) / in_cap.sum(axis=1)
    lam = np.linalg.eigvalsh(np.cov(u.T))
    return {
        "coverage": float(hit.mean()),
        "worst_cap_coverage": float(cap_cov.min()),
        "out_of_plane_deg": float(np.degrees(np.sqrt(max(lam[0], 0.0)))),
        "mean_direction": float(np.linalg.norm(u.mean(axis=0))),
    }


def accept(cal: MagCalibration, field: float | None = None,
           settings: AcceptanceSettings | None = None) -> MagCalibration:
    """The verdict: a copy of ``cal`` with ``accepted`` and human-readable ``reasons``.

    Uses ``cal.n_samples``, ``cal.coverage``, ``cal.extra`` (``worst_cap_coverage``, ``out_of_plane_deg``,
    as set by :func:`assess`), the offset, the soft-iron eigenvalues, the covariance and the residual.
    ``field`` is the reference strength in µT (the WMM field when position and date are known).
    """
    s = settings if settings is not None else AcceptanceSettings()
    reasons: list[str] = []
    f = cal.field_uT
    ex = cal.extra if isinstance(cal.extra, dict) else {}
    few = cal.n_samples < s.min_samples
    if few:
        reasons.append(f"too few samples: {cal.n_samples} < {s.min_samples}")
    plane = ex.get("out_of_plane_deg")
    if plane is not None and plane < s.min_out_of_plane_deg:
        reasons.append(f"nearly planar rotation: field directions leave their plane by only {plane:.1f}° "
                       f"(< {s.min_out_of_plane_deg:g}°); turn the phone about all its axes")
    cap = ex.get("worst_cap_coverage")
    if (cap is not None and cap < s.min_cap_coverage and not few
            and (plane is None or plane >= s.min_out_of_plane_deg)):
        reasons.append(f"one side of the sphere is missing (hemisphere only): the emptiest quarter of the "
                       f"sphere is {cap:.0%} covered (< {s.min_cap_coverage:.0%})")
    if np.isfinite(cal.coverage) and cal.coverage < s.min_coverage:
        reasons.append(f"too little coverage: {cal.coverage:.0%} of orientations (< {s.min_coverage:.0%})")
    if not (np.isfinite(f) and f > 0):
        reasons.append("no finite field radius")
    else:
        if field is not None and np.isfinite(field) and abs(f / field - 1.0) > s.max_radius_error:
            reasons.append(f"radius {f:.1f} µT differs from the reference field {field:.1f} µT by "
                           f"{abs(f / field - 1.0):.0%} (> {s.max_radius_error:.0%})")
        if np.isfinite(cal.residual_rms_uT) and cal.residual_rms_uT > s.max_residual_frac * f:
            rms = cal.residual_rms_uT
            reasons.append(f"residual RMS {rms:.2f} µT is {rms / f:.1%} of the "
                           f"field (> {s.max_residual_frac:.0%}): the field was not constant (interference?)")
        std = np.asarray(cal.offset_std_uT, dtype=float)
        if not np.all(np.isfinite(std)):
            reasons.append("offset uncertainty unknown (singular fit)")
        elif std.max() > s.max_offset_std_frac * f:
            reasons.append(f"offset poorly determined: 1-σ {std.max():.2f} µT > {s.max_offset_std_frac:.0%} "
                           f"of the field")
    off = float(np.linalg.norm(cal.offset_array))
    if off > s.max_offset_uT:
        reasons.append(f"offset {off:.0f} µT outside the plausible range (≤ {s.max_offset_uT:g} µT)")
    ev = np.linalg.eigvalsh(cal.soft_iron_array)
    if ev[0] <= 0:
        reasons.append("soft-iron matrix not positive definite")
    elif ev[-1] / ev[0] > s.max_axis_ratio:
        reasons.append(f"soft-iron eigenvalue spread {ev[-1] / ev[0]:.2f} > {s.max_axis_ratio:g} "
                       f"(implausible distortion)")
    if cal.covariance is not None:
        cov = np.asarray(cal.covariance, dtype=float)
        d = np.sqrt(np.abs(np.diag(cov)))
        if np.all(np.isfinite(cov)) and np.all(d > 0):
            cond = float(np.linalg.cond(cov / np.outer(d, d)))
            if cond > s.max_condition:
                reasons.append(f"ill-conditioned fit (condition number {cond:.1e} > {s.max_condition:.0e})")
    return cal.with_acceptance(not reasons, reasons)


def assess(mag: np.ndarray, cal: MagCalibration, field: float | None = None,
           settings: AcceptanceSettings | None = None) -> MagCalibration:
    """Coverage figures of ``cal`` on its samples ``mag`` (raw, µT), then :func:`accept`."""
    from dataclasses import replace

    stats = direction_stats(cal.apply(np.asarray(mag, dtype=float)))
    extra = dict(cal.extra)
    extra.update({k: v for k, v in stats.items() if k != "coverage"})
    if field is not None:
        extra["reference_field_uT"] = float(field)
    return accept(replace(cal, coverage=stats["coverage"], extra=extra), field, settings)
