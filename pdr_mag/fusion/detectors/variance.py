"""Variance: is the calibrated field's strength steady?

``s_V = var_τ(F) / max_uT2`` with ``var_τ`` an exponentially weighted variance of the strength F over the
time constant ``τ = window_s`` (irregular sampling: weight ``α = 1 − exp(−Δt/τ)`` per sample; restarted
after a gap of ``5 τ``).  [Liu2018] §4 takes "the modulus of the magnetometer and its variance as the
criterion of magnetic interference"; this is the variance.  A strength that stays within its band but
fluctuates (a motor, a moving car) fails it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from pdr_mag._records import check_numbers
from pdr_mag.fusion.detectors._unit import (
    Example,
    Plot,
    field_example,
    no_disturbance2,
    no_learn,
    no_restart,
    no_tolerance2,
    no_turn,
)
from pdr_mag.fusion.ew import ew_alpha

NAME = "variance"
ABSOLUTE = False
LEARNT = ()


@dataclass(frozen=True)
class VarianceSettings:
    """Thresholds of the variance check.

    Attributes
    ----------
    window_s : float
        Time constant of the exponentially weighted strength variance, s.
    max_uT2 : float
        Variance of the strength above which the field is flagged, µT².
    """

    window_s: float = 1.0
    max_uT2: float = 100.0

    def __post_init__(self):
        check_numbers(self, positive=("window_s", "max_uT2"))


Settings = VarianceSettings

STATE = np.dtype(
    [
        ("mean", np.float64),  # EW mean of the strength F, µT (NaN: restart)
        ("mean2", np.float64),  # EW mean of F², µT²
        ("var", np.float64),  # var_τ(F) at the latest sample, µT²
        ("score", np.float64),  # s_V of the latest sample
    ],
    align=True,
)

COLUMNS = {"strength_var_uT2": "windowed variance of the strength, µT²"}
BAND = None
PLOT = Plot("variance", "strength", "strength_var_uT2", "var |m_cal|", "orange",
            "Strength variance, µT² (flagged above max_uT2)", main=False)


@njit(cache=True, error_model="numpy")
def observe(det, ip):
    x = det.x
    v = det.variance
    f = x.f
    if x.dt > 5.0 * ip.variance.window_s or not np.isfinite(v.mean):
        v.mean = f
        v.mean2 = f * f
    else:
        a = ew_alpha(x.dt, ip.variance.window_s)
        v.mean += a * (f - v.mean)
        v.mean2 += a * (f * f - v.mean2)
    v.var = max(v.mean2 - v.mean**2, 0.0)
    v.score = v.var / ip.variance.max_uT2
    return v.score


learn = no_learn  # no reference: the variance is its own


@njit(cache=True, error_model="numpy")
def score(det, ip):
    return det.variance.score


disturbance2 = no_disturbance2  # a fluctuation says nothing about the size of a steady disturbance
tolerance2 = no_tolerance2
turn = no_turn
restart = no_restart


@njit(cache=True, error_model="numpy")
def write(det, out, n, col):
    out[col.strength_var_uT2, n] = det.variance.var


def windowed_variance(t: np.ndarray, x: np.ndarray, window_s: float) -> np.ndarray:
    """Exponentially weighted variance of x (time constant ``window_s``), sample by sample."""
    t = np.asarray(t, dtype=float)
    x = np.asarray(x, dtype=float)
    return _ew_var(t, x, float(window_s))


@njit(cache=True, error_model="numpy")
def _ew_var(t, x, tau):
    out = np.empty(len(x))
    m = np.nan
    m2 = 0.0
    for i in range(len(x)):
        if not np.isfinite(m):
            m = x[i]
            m2 = x[i] * x[i]
        else:
            a = ew_alpha(t[i] - t[i - 1], tau)
            m += a * (x[i] - m)
            m2 += a * (x[i] * x[i] - m2)
        out[i] = max(m2 - m * m, 0.0)
    return out


def example() -> Example:
    """The strength alternates 12 µT above and below its value at every sample for 8 s (an AC motor),
    within the strength band: its variance, 144 µT², exceeds the limit once the window has filled (2 s)."""
    t = np.arange(0.0, 25.0, 0.02)
    on = (t >= 10.0) & (t < 18.0)
    strength = 47.0 + np.where(on, 12.0 * (-1.0) ** np.arange(len(t)), 0.0)
    m_w = field_example(t, strength, np.full(len(t), 61.0), np.full(len(t), 2.0))
    return Example(t, m_w, 47.0, 61.0, 12.0, 18.0, 10.0)
