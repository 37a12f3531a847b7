"""How much of the sphere of field directions the samples cover, and the acceptance rules with reasons.

Coverage is measured on the calibrated directions ``û_i = m_cal,i / |m_cal,i|`` with an equal-area grid
(Lambert's cylindrical projection): ``n_bands`` bands equal in ``z`` times ``n_sectors`` equal longitude
sectors, every cell of area ``4π / (n_bands · n_sectors)``.  ``coverage`` is the share of cells holding at
least one sample.  Two further figures catch the classic bad calibrations:

* ``worst_cap_coverage``: the smallest share of covered cells inside any 60° cap (a quarter of the sphere)
  centred on a grid cell — ≈ 0 when one side of the sphere was never seen (a hemisphere only);
* ``out_of_plane_deg``: ``sqrt(λ_min)`` of the covariance of ``û`` in degrees — ≈ 0 when the phone was only
  turned about one axis (a planar rotation: the directions lie on one circle).

:func:`accept` turns a calibration and an optional reference field (WMM) into a verdict with
human-readable reasons.  The rule is what the samples determine: the heading error the parameter
uncertainty can cause, worst case over heading and pose (:mod:`pdr_mag.calibration.heading_error`),
against a stated tolerance; plausibility of the offset and the soft iron; a field that was not constant.
The coverage figures above never refuse on their own: they explain a refusal (what the motion lacked),
next to the undetermined direction and the motion that determines it.  :func:`assess` first computes
the figures from the samples.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from pdr_mag.calibration.heading_error import (
    axis_name,
    fit_figures,
    heading_bound,
    inclination_of,
    motion_hint,
)
from pdr_mag.calibration.model import MagCalibration
from pdr_mag.field import EARTH_STRENGTH_RANGE_UT, plausible_strength


@dataclass(frozen=True)
class AcceptanceSettings:
    """Thresholds of the acceptance rules (defaults in brackets).

    The rule is the heading error the calibration's uncertainty can cause (:mod:`.heading_error`); the
    coverage figures only explain a refusal (they are what the motion lacked), they never refuse.

    Attributes
    ----------
    min_samples : int
        Fewer samples than this cannot support a 9-parameter fit [50].
    max_heading_std_deg : float
        Tolerance: the largest 1-σ heading error, worst case over heading and pose, that the parameter
        uncertainty may cause, degrees [2.0] — a phone's heading indoors is good to a few degrees, and
        2° in the worst pose adds ≈ 0.5° in quadrature to the fusion's own 4–5°.
    default_inclination_deg : float
        Inclination of the field when only its strength is known, degrees [60, mid-latitudes]; the
        horizontal share ``cos I`` of the field converts field errors into heading errors.
    residual_lag : int
        Samples over which residuals are taken as correlated in the parameter covariance (Newey–West lag)
        [100: 2–5 s at 50–20 Hz, a stroke of the hand in a figure-8, so that a field that follows the
        motion is seen as correlated].
    noise_lag : int
        Samples over which the noise part of the residual is measured; what varies more slowly is a field
        that was not constant [10] (a phone's filtered noise decorrelates within a few samples).
    max_radius_error : float
        Maximum relative difference of the radius from the reference (WMM) field [0.2].
    max_offset_uT : float
        Largest plausible hard-iron offset norm, µT (phone sensors saturate at a few mT) [1500].
    max_axis_ratio : float
        Largest plausible ratio of soft-iron eigenvalues [2.5]: [Long2013]'s own simulated sensor (gains
        1 : 0.9 : 1.2 and its soft-iron matrix) has 2.33; a phone's own iron distorts far less.
    max_residual_frac, max_noise_uT : float
        Residual RMS above this share of the (reference, else fitted) field [0.05] and above the noise of
        the noisiest phone magnetometers [2.0 µT; 1–1.5 µT RMS per axis, iPhone 4S 1.2 µT]: the samples
        lie on no ellipsoid, the field was not constant.
    min_coverage, min_cap_coverage, min_out_of_plane_deg : float
        Hints only: a refusal mentions a coverage below ``min_coverage`` [0.5], an emptiest 60° cap
        covered below ``min_cap_coverage`` [0.15] (one side missing) and directions leaving their best
        plane by less than ``min_out_of_plane_deg`` degrees [8] (a planar rotation).
    """

    min_samples: int = 50
    max_heading_std_deg: float = 2.0
    default_inclination_deg: float = 60.0
    residual_lag: int = 100
    noise_lag: int = 10
    max_radius_error: float = 0.2
    max_offset_uT: float = 1500.0
    max_axis_ratio: float = 2.5
    max_residual_frac: float = 0.05
    max_noise_uT: float = 2.0
    min_coverage: float = 0.5
    min_cap_coverage: float = 0.15
    min_out_of_plane_deg: float = 8.0


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


def _strength(field) -> float | None:
    """The reference strength in µT of a float or an ``EarthField``; None when unknown."""
    if field is None:
        return None
    f = float(getattr(field, "strength", field))
    return f if np.isfinite(f) and f > 0 else None


def _hints(cal: MagCalibration, s: AcceptanceSettings) -> str:
    """What the motion lacked, from the coverage figures: the explanation of a refusal, never its rule."""
    ex = cal.extra if isinstance(cal.extra, dict) else {}
    out = []
    if np.isfinite(cal.coverage) and cal.coverage < s.min_coverage:
        out.append(f"they cover {cal.coverage:.0%} of the orientations")
    plane, cap = ex.get("out_of_plane_deg"), ex.get("worst_cap_coverage")
    if plane is not None and plane < s.min_out_of_plane_deg:
        out.append(f"nearly planar rotation: the field directions leave their plane by only {plane:.1f}°")
    elif cap is not None and cap < s.min_cap_coverage:
        out.append(f"one side of the sphere is missing (hemisphere only): its emptiest quarter is "
                   f"{cap:.0%} covered")
    return " (the samples: " + "; ".join(out) + ")" if out else ""


def _heading_figures(cal: MagCalibration, field, s: AcceptanceSettings) -> dict:
    """``extra["heading"]`` as :func:`assess` computed it from the samples, else the bound of
    ``cal.covariance`` alone (white residuals, the fit's own model), or of ``offset_std_uT`` alone."""
    ex = cal.extra if isinstance(cal.extra, dict) else {}
    fig = ex.get("heading")
    if isinstance(fig, dict) and fig.get("std_deg") is not None:
        return fig
    if cal.covariance is None:  # only the offset's 1-σ known (e.g. a calibration file)
        std = np.asarray(cal.offset_std_uT, dtype=float)
        cal = replace(cal, covariance=tuple(map(tuple, np.diag(std**2).tolist())),
                      extra={"covariance_params": ["offset_x", "offset_y", "offset_z"]})
    hb = heading_bound(cal, inclination_of(field, s.default_inclination_deg))
    return {**hb.to_dict(), "white_std_deg": hb.std_deg}


def _heading_reasons(cal: MagCalibration, fig: dict, s: AcceptanceSettings) -> list[str]:
    """Refusal reasons when the heading error ``fig["std_deg"]`` exceeds the tolerance.

    ``std_deg² = max(white, correlated)² + field² + shift²`` (:func:`heading_error.fit_figures`); the
    reasons are its largest part and any other part beyond the tolerance on its own: the heading the
    samples leave undetermined (the direction, the motion that determines it and what the motion lacked),
    residuals correlated in time, a field that was not constant, soft iron a simpler model leaves out.
    """
    tol = s.max_heading_std_deg
    std = float(fig["std_deg"])
    if not std > tol:
        return []
    white = float(fig.get("white_std_deg", std))
    corr = float(np.sqrt(max(float(fig.get("correlated_std_deg", 0.0)) ** 2 - white**2, 0.0)))
    parts = {"undetermined": white, "correlated": corr, "field": float(fig.get("field_error_deg", 0.0)),
             "model": float(fig.get("model_shift_deg", 0.0))}
    largest = max(parts, key=parts.get)
    # the largest part, and any other that is beyond the tolerance and at least half the whole; the
    # correlation and a simpler model's shift only where the samples determine the full model (else
    # they are the noise of an undetermined fit)
    said = {k for k, v in parts.items() if k == largest or (v > tol and v >= 0.5 * std)}
    if white > tol:
        said -= {"correlated", "model"}
        said.add("undetermined")
    worst = f"1-σ, worst heading and pose; tolerance {tol:g}°"
    out = []
    if "field" in said:
        out.append(f"the field was not constant while calibrating (steel or a magnet nearby?): "
                   f"{fig['residual_slow_uT']:.2f} µT RMS of the residual vary slowly, beyond the "
                   f"{fig['residual_noise_uT']:.2f} µT noise — a field change that turns a heading by "
                   f"{parts['field']:.1f}°, and the part of it that followed the motion the fit took for "
                   f"calibration (heading uncertain by up to {std:.1f}°, {worst})")
    if "model" in said:
        ex = cal.extra if isinstance(cal.extra, dict) else {}
        model = ex.get("model") or cal.method
        out.append(f"the {model} model leaves out soft iron that the samples show, which turns the heading "
                   f"by up to {parts['model']:.1f}° (tolerance {tol:g}°): fit the full model (method auto "
                   f"or ml)" if model != "full" else
                   f"the fit stopped short of its optimum by a heading change of up to {parts['model']:.1f}° "
                   f"(tolerance {tol:g}°)")
    if "correlated" in said and "field" not in said:
        out.append(f"the residuals are correlated over time (a filtered sensor, or a field that changed), "
                   f"which leaves the heading uncertain by up to {std:.1f}° ({worst}): calibrate longer, "
                   f"away from steel")
    if "undetermined" in said:
        size = "not at all" if white > 90.0 else f"only to {white:.1f}°"
        text = f"the samples determine the heading {size} ({worst})"
        d = fig.get("direction")
        if d is not None:
            name = axis_name(d)
            where = f"device {name} axis" if len(name) == 1 else f"device direction {name}"
            text += (f": the offset along the {where} is known to ±{fig['direction_std_uT']:.2f} µT only — "
                     f"{motion_hint(d)}")
        out.append(text + _hints(cal, s))
    return out


def accept(cal: MagCalibration, field=None, settings: AcceptanceSettings | None = None) -> MagCalibration:
    """The verdict: a copy of ``cal`` with ``accepted`` and human-readable ``reasons``.

    Refused when: too few samples; no finite radius; the residual RMS exceeds ``max_residual_frac`` of
    the field and ``max_noise_uT`` (the samples lie on no ellipsoid: the field was not constant); the
    heading error the calibration leaves exceeds ``max_heading_std_deg`` (:mod:`.heading_error`); the
    offset is beyond plausibility; and — where the samples determine them (heading within the
    tolerance; radius farther than 3 σ from the reference) — the soft-iron eigenvalue spread is beyond
    plausibility or the radius differs from the reference field by more than ``max_radius_error``.
    The heading figures are ``cal.extra["heading"]`` as :func:`assess` computes them from the samples
    (full model, correlated residuals, a changing field, the soft iron a simpler model leaves out) or,
    without them, those of ``cal.covariance`` (or of ``offset_std_uT``).  Coverage, a missing side and a
    planar rotation (``cal.coverage``, ``extra["worst_cap_coverage"]``, ``extra["out_of_plane_deg"]``)
    only explain a heading refusal.

    ``field`` is the reference field: a strength in µT, or an ``EarthField`` (the WMM field for the
    recording's position and date), whose inclination then converts field errors into heading errors.
    """
    s = settings if settings is not None else AcceptanceSettings()
    reasons: list[str] = []
    f = cal.field_uT
    ref = _strength(field)
    ev = np.linalg.eigvalsh(cal.soft_iron_array)
    if cal.n_samples < s.min_samples:
        reasons.append(f"too few samples: {cal.n_samples} < {s.min_samples}")
    if not (np.isfinite(f) and f > 0):
        reasons.append("no finite field radius")
    if ev[0] <= 0:
        reasons.append("soft-iron matrix not positive definite")
    if reasons and (ev[0] <= 0 or not (np.isfinite(f) and f > 0)):
        return cal.with_acceptance(False, reasons)
    rms = cal.residual_rms_uT
    gross = bool(np.isfinite(rms) and rms > max(s.max_residual_frac * (ref or f), s.max_noise_uT))
    if gross:
        ex = cal.extra if isinstance(cal.extra, dict) else {}
        model = ex.get("model")
        tried_full = "model_selection" in ex or model == "full"
        cause = ("the field was not constant (interference?)" if tried_full
                 else f"the field was not constant, or the {model or cal.method} model lacks the soft "
                      f"iron (method auto fits it)")
        reasons.append(f"residual RMS {rms:.2f} µT is {rms / (ref or f):.1%} of the field "
                       f"(> {s.max_residual_frac:.0%}) and beyond a magnetometer's noise "
                       f"(> {s.max_noise_uT:g} µT): {cause}")
    fig = _heading_figures(cal, field, s)
    if not gross:  # otherwise the heading figures of a fit to no ellipsoid say nothing more
        reasons += _heading_reasons(cal, fig, s)
    off = float(np.linalg.norm(cal.offset_array))
    if off > s.max_offset_uT:
        reasons.append(f"offset {off:.0f} µT outside the plausible range (≤ {s.max_offset_uT:g} µT)")
    determined = float(fig.get("white_std_deg", fig["std_deg"])) <= s.max_heading_std_deg
    if determined and ev[-1] / ev[0] > s.max_axis_ratio:
        reasons.append(f"soft-iron eigenvalue spread {ev[-1] / ev[0]:.2f} (largest / smallest) is beyond the "
                       f"plausible {s.max_axis_ratio:g}: an ellipsoid this elongated is not a "
                       f"magnetometer's own distortion")
    if ref is None and not plausible_strength(f, None, s.max_radius_error):
        lo, hi = EARTH_STRENGTH_RANGE_UT
        reasons.append(f"radius {f:.1f} µT: the Earth's field is {lo:g}–{hi:g} µT everywhere (± "
                       f"{s.max_radius_error:.0%} indoors)")
    if ref is not None and abs(f / ref - 1.0) > s.max_radius_error:
        r_std = float(fig.get("radius_std_uT", 0.0))
        if abs(f - ref) > 3.0 * r_std:
            reasons.append(f"radius {f:.1f} µT differs from the reference field {ref:.1f} µT by "
                           f"{abs(f / ref - 1.0):.0%} (> {s.max_radius_error:.0%})")
    return cal.with_acceptance(not reasons, reasons)


def assess(mag: np.ndarray, cal: MagCalibration, field=None,
           settings: AcceptanceSettings | None = None) -> MagCalibration:
    """Coverage and heading figures of ``cal`` on its samples ``mag`` (raw µT, in time order), then
    :func:`accept`.

    Sets ``coverage``, ``extra["worst_cap_coverage"]``, ``extra["out_of_plane_deg"]``,
    ``extra["mean_direction"]``, ``extra["heading"]`` (:func:`heading_error.fit_figures`) and, with a
    reference field, ``extra["reference_field_uT"]``.
    """
    s = settings if settings is not None else AcceptanceSettings()
    m = np.asarray(mag, dtype=float)
    stats = direction_stats(cal.apply(m))
    extra = dict(cal.extra)
    extra.update({k: v for k, v in stats.items() if k != "coverage"})
    ref = _strength(field)
    if ref is not None:
        extra["reference_field_uT"] = ref
    try:
        extra["heading"] = fit_figures(m, cal, inclination_of(field, s.default_inclination_deg),
                                       s.residual_lag, s.noise_lag)
    except (ValueError, np.linalg.LinAlgError):
        extra.pop("heading", None)  # no ellipsoid to evaluate at: accept() falls back to the covariance
    return accept(replace(cal, coverage=stats["coverage"], extra=extra), field, s)
