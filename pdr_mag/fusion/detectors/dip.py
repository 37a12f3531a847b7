"""Dip: does the calibrated field dip below the horizon as the Earth's does here?

``s_I = max(|I − I_loc| / tol_deg, |I − I_ref| / band_deg)`` with the measured dip
``I = asin(−(m_d · u_d) / |m_d|)`` from the calibrated field and the device-frame up direction ``u_d`` (the
filter's gravity estimate), ``I_ref`` the reference inclination (World Magnetic Model) and ``I_loc`` the
local dip learnt from clean samples like the local strength (without a reference: learnt from the first
clean samples).

Its part in the filter's noise: a disturbance ``d`` turns the dip by at most ``|d| / F``, so
``d_min² ≥ (F (I − I_loc))²`` (I in rad); its tolerance stands for a disturbance of ``F tol_I``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from pdr_mag._records import check_numbers
from pdr_mag.fusion.detectors._unit import Band, Example, Plot, field_example, no_restart, no_turn

NAME = "dip"
ABSOLUTE = True
LEARNT = ("loc",)


@dataclass(frozen=True)
class DipSettings:
    """Thresholds of the dip check.

    Attributes
    ----------
    tol_deg : float
        Half-width of the accepted dip band around the local dip, deg.
    band_deg : float
        The learnt dip may not leave ``I_ref ± band_deg``: samples outside are flagged.
    """

    tol_deg: float = 15.0
    band_deg: float = 25.0

    def __post_init__(self):
        check_numbers(self, positive=("tol_deg", "band_deg"))


Settings = DipSettings

STATE = np.dtype(
    [
        ("loc", np.float64),  # learnt local dip I_loc, deg (NaN: nothing learnt)
        ("band", np.float64),  # |I − I_ref| / band_deg of the latest sample (0: no reference)
        ("tol", np.float64),  # half-width of the dip band, deg
        ("score", np.float64),  # s_I of the latest sample
    ],
    align=True,
)

COLUMNS = {
    "dip_deg": "measured dip angle (field below horizon) from calibrated field and gravity, deg",
    "dip_ref_deg": "reference inclination, deg",
    "dip_tol_deg": "half-width of the accepted dip band, deg",
}
BAND = Band("dip_deg", "dip_ref_deg", "dip_tol_deg", "deg")
PLOT = Plot("dip", "measured", "dip_deg", "measured", "purple", "Dip angle, deg", main=True)


@njit(cache=True, error_model="numpy")
def dip_of(mx, my, mz, ux, uy, uz):
    """Dip (deg, positive below the horizon) of field m against the unit up direction u."""
    n = np.sqrt(mx * mx + my * my + mz * mz)
    if n <= 0.0:
        return np.nan
    s = -(mx * ux + my * uy + mz * uz) / n
    s = min(1.0, max(-1.0, s))
    return np.degrees(np.arcsin(s))


@njit(cache=True, error_model="numpy")
def observe(det, ip):
    x = det.x
    d = det.dip
    d.band = abs(x.dip - x.dip_ref) / ip.dip.band_deg if np.isfinite(x.dip_ref) else 0.0
    return d.band


@njit(cache=True, error_model="numpy")
def learn(det, a, ip):
    d = det.dip
    if not np.isfinite(d.loc):
        d.loc = det.x.dip
    else:
        d.loc += a * (det.x.dip - d.loc)


@njit(cache=True, error_model="numpy")
def score(det, ip):
    d = det.dip
    d.tol = ip.dip.tol_deg
    d.score = max(d.band, abs(det.x.dip - d.loc) / d.tol) if np.isfinite(d.loc) else d.band
    return d.score


@njit(cache=True, error_model="numpy")
def disturbance2(det, p):
    loc = det.dip.loc
    return (det.x.f * np.radians(det.x.dip - loc)) ** 2 if np.isfinite(loc) else 0.0


@njit(cache=True, error_model="numpy")
def tolerance2(det):
    return (det.x.f * np.radians(det.dip.tol)) ** 2


turn = no_turn  # the dip does not depend on the heading
restart = no_restart


@njit(cache=True, error_model="numpy")
def write(det, out, n, col):
    out[col.dip_deg, n] = det.x.dip
    out[col.dip_ref_deg, n] = det.dip.loc
    out[col.dip_tol_deg, n] = det.dip.tol


def dip_deg(mag_d: np.ndarray, up_d: np.ndarray) -> np.ndarray:
    """Dip angle (deg, positive below the horizon) between calibrated field and device-frame up (N, 3)."""
    m = np.asarray(mag_d, dtype=float)
    u = np.asarray(up_d, dtype=float)
    u = u / np.linalg.norm(u, axis=-1, keepdims=True)
    s = -np.sum(m * u, axis=-1) / np.linalg.norm(m, axis=-1)
    return np.degrees(np.arcsin(np.clip(s, -1.0, 1.0)))


def example() -> Example:
    """After a minute of clean field, it dips 22° less for 8 s (a steel floor), its strength and azimuth
    unchanged: the turn is within the gyro-consistency tolerance and the dip within the reference's loose
    band, so the local dip learns from it (time constant ``learn_ref_s``) but not fast enough to hide it."""
    t = np.arange(0.0, 75.0, 0.02)
    dip = np.where((t >= 60.0) & (t < 68.0), 61.0 - 22.0, 61.0)
    m_w = field_example(t, np.full(len(t), 47.0), dip, np.full(len(t), 2.0))
    return Example(t, m_w, 47.0, 61.0, 60.0, 68.0, 60.0)
