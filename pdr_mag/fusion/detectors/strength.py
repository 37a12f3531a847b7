"""Strength: is the calibrated field as strong as the Earth's here?

``s_F = max(|F − F_loc| / tol_F, |F − F_ref| / (band_rel · F_ref))`` with ``F = |m_d|`` the calibrated
strength, ``F_ref`` the reference strength (the calibration radius when the caller gives one, else the
World Magnetic Model), ``F_loc`` the local strength learnt from clean samples (time constant
``InterferenceSettings.learn_ref_s``; indoor fields differ from the WMM by several µT) and
``tol_F = max(tol_uT, tol_rel · F_ref)`` (``F_loc`` in place of ``F_ref`` while there is no reference).
[Liu2018] §4 takes "the modulus of the magnetometer and its variance as the criterion of magnetic
interference"; this is the modulus.

Its part in the filter's noise: a disturbance ``d`` changes the strength by at most ``|d|``, so
``d_min² ≥ (F − F_loc)²``; its tolerance stands for a disturbance of ``tol_F``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from pdr_mag._records import check_numbers
from pdr_mag.fusion.detectors._unit import Band, Example, Plot, field_example, no_restart, no_turn

NAME = "strength"
ABSOLUTE = True
LEARNT = ("loc",)


@dataclass(frozen=True)
class StrengthSettings:
    """Thresholds of the strength check.

    Attributes
    ----------
    tol_uT : float
        Minimum half-width of the accepted strength band, µT.
    tol_rel : float
        Half-width of the strength band relative to the reference strength.
    band_rel : float
        The learnt strength may not leave ``F_ref (1 ± band_rel)``: samples outside are flagged.
    """

    tol_uT: float = 10.0
    tol_rel: float = 0.3
    band_rel: float = 0.4

    def __post_init__(self):
        check_numbers(self, positive=("tol_uT", "tol_rel", "band_rel"))


Settings = StrengthSettings

STATE = np.dtype(
    [
        ("loc", np.float64),  # learnt local strength F_loc, µT (NaN: nothing learnt)
        ("band", np.float64),  # |F − F_ref| / (band_rel · F_ref) of the latest sample (0: no reference)
        ("tol", np.float64),  # half-width tol_F of the strength band at the latest sample, µT
        ("score", np.float64),  # s_F of the latest sample
    ],
    align=True,
)

COLUMNS = {
    "field_strength_uT": "|calibrated field| at the latest magnetometer sample, µT",
    "field_ref_uT": "reference strength the detector compares with (WMM or fitted radius), µT",
    "strength_tol_uT": "half-width of the accepted strength band around field_ref_uT, µT",
}
BAND = Band("field_strength_uT", "field_ref_uT", "strength_tol_uT", "uT")
PLOT = Plot("field", "strength", "field_strength_uT", "|m_cal|", "blue", "Field strength, µT", main=True)


@njit(cache=True, error_model="numpy")
def tolerance(ref_uT, ip):
    """``tol_F``, the half-width of the accepted strength band, µT."""
    return max(ip.strength.tol_uT, ip.strength.tol_rel * ref_uT)


@njit(cache=True, error_model="numpy")
def observe(det, ip):
    x = det.x
    s = det.strength
    f_ref = x.f_ref
    s.band = abs(x.f - f_ref) / (ip.strength.band_rel * f_ref) if np.isfinite(f_ref) else 0.0
    return s.band


@njit(cache=True, error_model="numpy")
def learn(det, a, ip):
    s = det.strength
    if not np.isfinite(s.loc):
        s.loc = det.x.f
    else:
        s.loc += a * (det.x.f - s.loc)


@njit(cache=True, error_model="numpy")
def score(det, ip):
    x = det.x
    s = det.strength
    s.tol = tolerance(x.f_ref if np.isfinite(x.f_ref) else s.loc, ip)
    s.score = max(s.band, abs(x.f - s.loc) / s.tol) if np.isfinite(s.loc) else s.band
    return s.score


@njit(cache=True, error_model="numpy")
def disturbance2(det, p):
    loc = det.strength.loc
    return (det.x.f - loc) ** 2 if np.isfinite(loc) else 0.0


@njit(cache=True, error_model="numpy")
def tolerance2(det):
    return det.strength.tol**2


turn = no_turn  # nothing kept in the world frame
restart = no_restart


@njit(cache=True, error_model="numpy")
def write(det, out, n, col):
    out[col.field_strength_uT, n] = det.x.f
    out[col.field_ref_uT, n] = det.strength.loc
    out[col.strength_tol_uT, n] = det.strength.tol


def strength_score(mag_d: np.ndarray, ref_uT: float, settings: StrengthSettings | None = None):
    """Strength F (µT), and score ``|F − F_ref| / tol_F`` for calibrated samples (N, 3)."""
    s = settings or StrengthSettings()
    f = np.linalg.norm(np.asarray(mag_d, dtype=float), axis=-1)
    tol = max(s.tol_uT, s.tol_rel * float(ref_uT))
    return f, np.abs(f - ref_uT) / tol


def example() -> Example:
    """The field grows by 20 µT for 5 s (a steel door), its direction unchanged."""
    t = np.arange(0.0, 20.0, 0.02)
    strength = np.where((t >= 10.0) & (t < 15.0), 67.0, 47.0)
    m_w = field_example(t, strength, np.full(len(t), 61.0), np.full(len(t), 2.0))
    return Example(t, m_w, 47.0, 61.0, 10.0, 15.0, 10.0)

