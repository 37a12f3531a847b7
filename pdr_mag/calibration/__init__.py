"""Magnetometer calibration: ``m_cal = soft_iron @ (m_raw - offset)``."""

from pdr_mag.calibration.model import MagCalibration
from pdr_mag.calibration.sphere import fit_sphere

__all__ = ["MagCalibration", "fit_sphere"]
