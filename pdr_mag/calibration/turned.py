"""The turned-field test: the Earth's field keeps its azimuth in a frame that turns with the device.

Before any calibration is in force the fusion filter's heading is the gyroscope's alone (no magnetometer
update reaches it), so the attitude at each buffered sample — its device-frame up ``u_k`` and north ``n_k``
(:data:`pdr_mag.pipeline._kernel.MAG_ROW`) — turns exactly as the device did.  For a fit's offset ``b`` the
calibrated field of sample ``k`` has, in that frame, the azimuth

    α_k = atan2(e_k · (m_k − b), n_k · (m_k − b)),   e_k = n_k × u_k  (east),

and the Earth's field, fixed in the world, gives one α for every sample but for the gyroscope's bias (a drift
``a + c t`` over the buffer's span) and the tilt's and the noise's few degrees.  Two things make α scatter by
tens of degrees instead: a wrong offset (the samples' errors turn with the device, not with the world) and a
field that turned while the device did not (a pass by steel, a magnet).  A reference field (F and the dip
from the place, the WMM) exposes both through the fit's radius and dip; without one the gravity-aided fit
has F and the dip free, and the few seconds of a pass by steel can fit a sphere of plausible radius about an
offset tens of µT off (benchmarks/NOTES.md, "No location, no reference field").  There the gyroscope's turn
against the field's is the physics left: the online calibrator judges a first calibration without a
reference by it.  (With a reference it is not applied: on the tyrex walks replayed from 5 and 20 s in it
refused first fits the restarts needed — from 20 s, mode b, 9 walks above 45° instead of 1.)
"""

from __future__ import annotations

import numpy as np

from pdr_mag.calibration.refit import robust_spread

#: samples (with a known north axis) below which the azimuth's spread is not judged
MIN_SAMPLES = 5


def azimuth_spread_deg(m_cal: np.ndarray, u: np.ndarray, n: np.ndarray, t: np.ndarray) -> float:
    """Robust spread (:func:`~pdr_mag.calibration.refit.robust_spread`), deg, of the azimuth ``α_k`` of
    the calibrated field ``m_cal`` (device frame: ``m − b`` for an offset, :meth:`MagCalibration.apply` in
    general) in the frame of the device-frame up ``u`` and north ``n`` axes (module docstring), a straight
    line in time ``t`` (the gyroscope's bias) removed.  NaN with fewer than :data:`MIN_SAMPLES` samples
    whose axes are known."""
    ok = np.all(np.isfinite(n), axis=1) & np.all(np.isfinite(u), axis=1) & np.isfinite(t)
    if np.count_nonzero(ok) < MIN_SAMPLES:
        return float("nan")
    alpha = azimuths(np.asarray(m_cal, dtype=float)[ok], u[ok], n[ok])
    tk = t[ok]
    centre = np.angle(np.mean(np.exp(1j * alpha)))
    alpha = np.angle(np.exp(1j * (alpha - centre)))  # about the circular mean, in (−π, π]
    design = np.c_[np.ones_like(tk), tk - tk.mean()]
    coef, *_ = np.linalg.lstsq(design, alpha, rcond=None)
    return float(np.degrees(robust_spread(alpha - design @ coef)))


def azimuths(m_cal: np.ndarray, u: np.ndarray, n: np.ndarray) -> np.ndarray:
    """``α_k`` (rad, from north towards east) of the calibrated fields ``m_cal`` (N, 3, device frame) in the
    frame of the device-frame up ``u`` and north ``n`` axes of the filter's attitude at each sample (module
    docstring); NaN where an axis is unknown."""
    east = np.cross(n, u)
    return np.arctan2(np.einsum("ij,ij->i", east, m_cal), np.einsum("ij,ij->i", n, m_cal))


def azimuth_gradients(m_cal: np.ndarray, u: np.ndarray, n: np.ndarray) -> np.ndarray:
    """``∂α_k/∂m`` (N, 3, rad/µT) of :func:`azimuths`: ``(n_m e − e_m n) / (e_m² + n_m²)`` with
    ``e_m = e·m``, ``n_m = n·m`` — how an error of the calibrated field (an offset error, device frame) turns
    each azimuth."""
    east = np.cross(n, u)
    em = np.einsum("ij,ij->i", east, m_cal)[:, None]
    nm = np.einsum("ij,ij->i", n, m_cal)[:, None]
    return (nm * east - em * n) / (em * em + nm * nm)


#: tan of the dip up to which the bound is the setting itself (63.4°: the tyrex walks' 61°, Zurich's 63.5°)
TAN_DIP_REF = 2.0


def bound_deg(base_deg: float, sin_dip: float) -> float:
    """The spread a first fit may show, deg: ``base_deg`` where the dip is at most 63.4°, growing as tan|I|
    beyond.  A tilt error δ turns the horizontal field's azimuth by about δ tan|I| (the vertical field leaks
    into the horizontal plane), so near the magnetic pole (Longyearbyen 82.5°: tan 7.6; Resolute 86.7°:
    17) a right fit's azimuth spreads by what a wrong one's does at mid latitudes."""
    s = min(abs(float(sin_dip)), 1.0 - 1e-12) if np.isfinite(sin_dip) else 0.0
    tan_dip = s / np.sqrt(1.0 - s * s)
    return base_deg * max(1.0, tan_dip / TAN_DIP_REF)
