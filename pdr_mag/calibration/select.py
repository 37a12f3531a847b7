"""``calibrate()``: one entry point for every estimator, the ``auto`` model choice, alignment and acceptance.

``auto`` fits the geometric ML (:mod:`pdr_mag.calibration.ml`) with three nested models — offset only
(``sphere``, k = 4 parameters), axis scale factors (``diagonal``, k = 6) and full soft iron (``full``,
k = 9) — and keeps the one with the smallest Bayesian information criterion

    BIC = N ln(RSS / N) + k ln N,   RSS = Σ d_i²  (orthogonal distances, Gaussian noise),

so a sphere is not over-fitted (a spurious extra pair of parameters must lower ``N ln RSS`` by ``ln N``
each, false-alarm probability ≈ P(χ²₂ > 2 ln N), 1e-3 at N = 1000) and a real ellipsoid is not
under-fitted (its RSS drop grows with N).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from pdr_mag.calibration.alignment import fit_alignment
from pdr_mag.calibration.coverage import AcceptanceSettings, assess
from pdr_mag.calibration.ellipsoid import fit_als, fit_ellipsoid
from pdr_mag.calibration.ml import fit_lm9, fit_ml, fit_radial_newton
from pdr_mag.calibration.model import MagCalibration
from pdr_mag.calibration.sphere import _check_mag, fit_sphere, sphere_lls
from pdr_mag.calibration.twostep import fit_twostep, initial_ellipsoid

METHODS = ("auto", "sphere", "ellipsoid", "als", "ml", "radial", "lm9", "twostep")
_K = {"sphere": 4, "diagonal": 6, "full": 9}


def _admissible(cal: MagCalibration) -> bool:
    """A fit that can compete: finite offset σ (non-singular information) and a finite positive radius."""
    std = np.asarray(cal.offset_std_uT, dtype=float)
    return bool(np.all(np.isfinite(std)) and np.isfinite(cal.field_uT) and cal.field_uT > 0)


def select_model(mag: np.ndarray, models=("sphere", "diagonal", "full")) -> MagCalibration:
    """Geometric ML fits of the nested models; the one with the smallest BIC (module docstring).

    Only *admissible* fits compete (a finite offset covariance and radius).  Plausibility is not part of
    the choice: a strongly elongated ellipsoid that the samples support is kept, and the acceptance rules
    say that its soft iron is beyond plausibility, instead of keeping a sphere whose residual would then be
    blamed on the field.  With poor coverage an over-fitted richer model gains too little RSS to pay its
    BIC penalty, and one the samples do not determine is refused by the heading rule.  If none is
    admissible, the simplest model is returned (and the acceptance rules will say why it is not
    accepted).  ``extra["model_selection"]`` lists ``{model: {"rss_uT2", "bic", "k", "admissible"}}`` and
    ``extra["model"]`` the choice.
    """
    m = _check_mag(mag, 10)
    n = len(m)
    fits: dict[str, MagCalibration] = {}
    table: dict[str, dict] = {}
    b0, r0, _ = sphere_lls(m)
    init = {"sphere": (b0, r0 * np.eye(3))}
    for model in models:
        if model == "full":
            bi, Li, _ = initial_ellipsoid(m)
        elif model == "diagonal" and "sphere" in fits:
            c = fits["sphere"]
            bi, Li = c.offset_array, c.field_uT * np.eye(3)
        else:
            bi, Li = init.get(model, (b0, r0 * np.eye(3)))
        cal = fit_ml(m, model=model, init=(bi, Li))
        rss = float(cal.extra["rss_uT2"])
        k = _K[model]
        table[model] = {"rss_uT2": rss, "k": k, "bic": n * np.log(max(rss, 1e-300) / n) + k * np.log(n),
                        "admissible": _admissible(cal)}
        fits[model] = cal
    ok = [key for key in table if table[key]["admissible"]] or [models[0]]
    best = min(ok, key=lambda key: table[key]["bic"])
    cal = fits[best]
    extra = dict(cal.extra)
    extra.update({"model_selection": table, "model": best, "criterion": "bic"})
    return replace(cal, extra=extra)


def calibrate(mag: np.ndarray, method: str = "auto", accel: np.ndarray | None = None, field=None,
              settings: AcceptanceSettings | None = None) -> MagCalibration:
    """Batch magnetometer calibration ``m_cal = soft_iron @ (m_raw − offset)`` with its verdict.

    Parameters
    ----------
    mag : ndarray (N, 3)
        Raw magnetometer samples, µT.
    method : str
        ``auto`` (geometric ML, model chosen by BIC), ``sphere`` (LLS, [Liu2018]), ``ellipsoid``
        (ellipsoid-specific LS, [Huang2018]), ``als`` (noise-compensated, [Huang2018]), ``ml`` (geometric ML,
        full soft iron), ``radial`` ([Long2013] Newton), ``lm9`` ([Zhong2017] LM), ``twostep`` (the initial
        value).
    accel : ndarray (N, 3), optional
        Specific force (m/s², IMU axes) at the magnetometer instants, low-passed, NaN where the device
        moves (:func:`alignment.quasi_static_accel` makes it from a raw stream); when given, the
        magnetometer → IMU rotation is estimated (:mod:`alignment`) and stored in ``mag_to_imu`` only if
        significant (identity — ``None`` — otherwise); ``extra["alignment"]`` reports it either way.
    field : float or EarthField, optional
        Reference field strength (µT), e.g. the WMM field for the recording's position and date; used by
        the radius rule of the acceptance check.  An ``EarthField`` also gives the expected dip angle,
        which the alignment must reproduce to be accepted as significant, and the horizontal share of the
        field that turns field errors into heading errors (the heading rule of :func:`coverage.accept`).
    settings : AcceptanceSettings, optional
        Thresholds of the acceptance rules (the documented defaults when omitted).

    Returns
    -------
    MagCalibration
        With ``coverage``, ``accepted`` and ``reasons`` set (:func:`coverage.assess`).  When the samples
        are well-formed but support no fit at all (all equal, collinear, exactly planar) the result is a
        refusal: ``accepted=False``, ``reasons=["no calibration possible: …"]``, ``extra["failed"]``.

    Raises
    ------
    ValueError
        For malformed arguments (shape, NaN, unknown method, non-positive field).
    """
    if method not in METHODS:
        raise ValueError(f"method: expected one of {', '.join(METHODS)}, got {method!r}")
    m = _check_mag(mag, 4)
    ref = None
    if field is not None:
        ref = float(getattr(field, "strength", field))
        if not (np.isfinite(ref) and ref > 0):
            raise ValueError(f"field: expected a positive strength in µT, got {field!r}")
    try:
        if len(m) < 10:
            cal = fit_sphere(m)
        elif method == "auto":
            cal = select_model(m)
        else:
            fn = {"sphere": fit_sphere, "ellipsoid": fit_ellipsoid, "als": fit_als, "ml": fit_ml,
                  "radial": fit_radial_newton, "lm9": fit_lm9, "twostep": fit_twostep}[method]
            cal = fn(m)
    except (ValueError, np.linalg.LinAlgError) as exc:
        # well-formed samples whose geometry supports no fit (all equal, on a line or a plane): an honest
        # refusal, not an error — the placeholder (mean as offset, identity, no radius) is never accepted
        return MagCalibration.from_arrays(
            m.mean(axis=0), None, method=method, n_samples=len(m), coverage=0.0, accepted=False,
            reasons=[f"no calibration possible: {exc}"], extra={"failed": True})
    if accel is not None:
        inc = getattr(field, "inclination_deg", None)
        sin_dip = None if inc is None else -float(np.sin(np.radians(inc)))
        al = fit_alignment(cal.apply(m), accel, sin_dip=sin_dip)
        extra = dict(cal.extra)
        extra["alignment"] = None if al is None else al.to_dict()
        cal = replace(cal, extra=extra)
        if al is not None and al.significant:
            cal = replace(cal, mag_to_imu=tuple(tuple(float(v) for v in row) for row in al.rotation))
    return assess(m, cal, field if ref is not None else None, settings)
