"""Exponentially weighted means over irregularly sampled streams (numba): the weight of a new sample."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, error_model="numpy")
def ew_alpha(dt, tau):
    """Weight ``α = 1 − exp(−Δt/τ)`` of a new sample, ``Δt`` after the previous one, in an exponentially
    weighted mean with time constant ``τ`` (0 for ``Δt ≤ 0``)."""
    if dt <= 0.0:
        return 0.0
    return 1.0 - np.exp(-dt / tau)
