"""Magnetometer calibration: ``m_cal = soft_iron @ (m_raw - offset)``.

Estimators (each module documents its formula and source): :func:`fit_sphere` ([Liu2018]),
:func:`fit_twostep` ([Zhong2017]/[Long2013]), :func:`fit_ellipsoid` and :func:`fit_als` ([Huang2018]),
:func:`fit_ml` (geometric maximum likelihood, attains the Cramér–Rao bound of :mod:`.crlb`),
:func:`fit_radial_newton` ([Long2013]) and :func:`fit_lm9` ([Zhong2017]).  :func:`calibrate` picks one,
chooses the model (``auto``), estimates the magnetometer → IMU alignment and judges acceptance
(:mod:`.coverage`).
"""

from pdr_mag.calibration.alignment import Alignment, fit_alignment, fit_reference_rotation
from pdr_mag.calibration.coverage import AcceptanceSettings, accept, assess, coverage, direction_stats
from pdr_mag.calibration.crlb import crlb, effective_fisher, offset_rmse_bound
from pdr_mag.calibration.ellipsoid import fit_als, fit_ellipsoid
from pdr_mag.calibration.ml import fit_lm9, fit_ml, fit_radial_newton
from pdr_mag.calibration.model import MagCalibration
from pdr_mag.calibration.select import METHODS, calibrate, select_model
from pdr_mag.calibration.sphere import fit_sphere
from pdr_mag.calibration.twostep import fit_twostep, initial_ellipsoid

__all__ = [
    "METHODS",
    "AcceptanceSettings",
    "Alignment",
    "MagCalibration",
    "accept",
    "assess",
    "calibrate",
    "coverage",
    "crlb",
    "direction_stats",
    "effective_fisher",
    "fit_alignment",
    "fit_als",
    "fit_ellipsoid",
    "fit_lm9",
    "fit_ml",
    "fit_radial_newton",
    "fit_reference_rotation",
    "fit_sphere",
    "fit_twostep",
    "initial_ellipsoid",
    "offset_rmse_bound",
    "select_model",
]
