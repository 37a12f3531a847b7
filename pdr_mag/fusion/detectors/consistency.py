"""Gyro consistency: does the field stay fixed in the world frame while the device turns?

A field fixed in the world frame stays fixed when rotated by the filter's attitude, ``m_w = R_wd m_d``;
its direction is compared with an exponentially weighted mean direction ``m̄_w`` (time constant
``window_s``), which the fusion rotates with every correction it applies to the attitude (so the angle is
the field's motion against the gyro-propagated frame, not hidden by the filter following a disturbed field):
``s_G = ∠(m_w, m̄_w) / (tol_deg + bias_k σ_b window_s)``, widened by the filter's bias uncertainty σ_b so
that drift the filter knows it may have does not fire it.  A field that turns in the device frame without
the device turning (a passing magnet, a car) moves ``m_w``; the Earth's does not.

Its part in the filter's noise: a disturbance ``d`` turns the field by at most ``|d| / F``, so
``d_min² ≥ k_c (F angle)²`` with the angle beyond what σ_b explains over the window (``k_c``
``MagSettings.cons_k``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from pdr_mag._records import check_numbers
from pdr_mag.fusion.detectors._unit import Example, Plot, field_example, no_learn, no_tolerance2
from pdr_mag.fusion.ew import ew_alpha
from pdr_mag.fusion.quat import rotate_vector

NAME = "consistency"
ABSOLUTE = False
LEARNT = ()


@dataclass(frozen=True)
class ConsistencySettings:
    """Thresholds of the gyro-consistency check.

    Attributes
    ----------
    window_s : float
        Time constant of the mean world-frame field direction, s.
    tol_deg : float
        Angle between the current and the mean world-frame field direction above which the field is
        flagged, deg.
    bias_k : float
        The tolerance is widened by ``bias_k · σ_b · window_s`` (σ_b the filter's gyro bias uncertainty),
        so the check cannot fire on drift the filter knows it may have.
    """

    window_s: float = 2.0
    tol_deg: float = 30.0
    bias_k: float = 3.0

    def __post_init__(self):
        check_numbers(self, positive=("window_s", "tol_deg"))


Settings = ConsistencySettings

STATE = np.dtype(
    [
        ("mean", np.float64, (3,)),  # EW mean m̄_w of the world-frame field direction (NaN in x: restart)
        ("angle", np.float64),  # ∠(m_w, m̄_w) of the latest sample, deg
        ("score", np.float64),  # s_G of the latest sample
    ],
    align=True,
)

COLUMNS = {"consistency_deg": "angle between the field's world-frame direction and its recent mean, deg"}
BAND = None
PLOT = Plot("consistency", "angle", "consistency_deg", "angle", "olive",
            "Gyro consistency: turn of the field in the world frame, deg", main=False)


@njit(cache=True, error_model="numpy")
def angle_deg(ax, ay, az, bx, by, bz):
    """Angle between two vectors, deg."""
    cx = ay * bz - az * by
    cy = az * bx - ax * bz
    cz = ax * by - ay * bx
    return np.degrees(np.arctan2(np.sqrt(cx * cx + cy * cy + cz * cz), ax * bx + ay * by + az * bz))


@njit(cache=True, error_model="numpy")
def observe(det, ip):
    x = det.x
    c = det.consistency
    window = ip.consistency.window_s
    mw = c.mean
    u = x.mw
    if x.dt > 5.0 * window or not np.isfinite(mw[0]):  # (re)start the mean direction
        mw[0], mw[1], mw[2] = u[0], u[1], u[2]
        c.angle = 0.0
    else:
        c.angle = angle_deg(u[0], u[1], u[2], mw[0], mw[1], mw[2])
        a = ew_alpha(x.dt, window)
        mw[0] += a * (u[0] - mw[0])
        mw[1] += a * (u[1] - mw[1])
        mw[2] += a * (u[2] - mw[2])
    c.score = c.angle / (ip.consistency.tol_deg + ip.consistency.bias_k * x.sigma_b_deg * window)
    return c.score


learn = no_learn  # the mean direction is its reference, learnt at every sample


@njit(cache=True, error_model="numpy")
def score(det, ip):
    return det.consistency.score


@njit(cache=True, error_model="numpy")
def disturbance2(det, p):
    x = det.x
    beyond = max(det.consistency.angle - x.sigma_b_deg * p.interference.consistency.window_s, 0.0)
    return p.mag.cons_k * (x.f * np.radians(beyond)) ** 2


tolerance2 = no_tolerance2  # a turn says nothing of the disturbances between the flags


@njit(cache=True, error_model="numpy")
def turn(det, ex, ey, ez):
    """The mean direction turns with the attitude correction ``Exp(e)`` (it stays in the corrected frame)."""
    mw = det.consistency.mean
    if np.isfinite(mw[0]):
        rotate_vector(mw, ex, ey, ez)


@njit(cache=True, error_model="numpy")
def restart(det):
    """A jump of the attitude: the mean direction starts again."""
    mw = det.consistency.mean
    mw[0], mw[1], mw[2] = np.nan, 0.0, 0.0


@njit(cache=True, error_model="numpy")
def write(det, out, n, col):
    out[col.consistency_deg, n] = det.consistency.angle


def consistency_angle_deg(t: np.ndarray, mag_w: np.ndarray, window_s: float) -> np.ndarray:
    """Angle (deg) between each world-frame field sample and the exponentially weighted mean direction
    of the previous samples (time constant ``window_s``)."""
    return _cons(np.asarray(t, dtype=float), np.asarray(mag_w, dtype=float), float(window_s))


@njit(cache=True, error_model="numpy")
def _cons(t, m, tau):
    n = len(t)
    out = np.empty(n)
    mx = np.nan
    my = 0.0
    mz = 0.0
    for i in range(n):
        f = np.sqrt(m[i, 0] ** 2 + m[i, 1] ** 2 + m[i, 2] ** 2)
        ux, uy, uz = m[i, 0] / f, m[i, 1] / f, m[i, 2] / f
        if not np.isfinite(mx):
            mx, my, mz = ux, uy, uz
            out[i] = 0.0
            continue
        out[i] = angle_deg(ux, uy, uz, mx, my, mz)
        a = ew_alpha(t[i] - t[i - 1], tau)
        mx += a * (ux - mx)
        my += a * (uy - my)
        mz += a * (uz - mz)
    return out


def example() -> Example:
    """The horizontal field swings round by 150° from one sample to the next (a car passing close by), its
    strength and dip unchanged: the direction is 56° from its mean, which then follows within seconds."""
    t = np.arange(0.0, 25.0, 0.02)
    azimuth = np.where(t >= 10.0, 152.0, 2.0)
    m_w = field_example(t, np.full(len(t), 47.0), np.full(len(t), 61.0), azimuth)
    return Example(t, m_w, 47.0, 61.0, 10.0, 11.0, 10.0)
