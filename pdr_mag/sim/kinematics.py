"""Smooth building blocks of the trajectories: blend weights and a chain of elementary rotations.

Orientation of every trajectory is the chain ::

    rot_wd = Rz(θ0) · Rx(θ1) · Ry(θ2) · Rz(θ3)

(yaw about ENU up, then pitch about the device x, roll about y, twist about z — Android's azimuth,
pitch, roll order, plus a final twist), with the angles smooth analytic functions of time.  Its body rate
follows exactly from the angle rates (``Rᵀ Ṙ = [ω_d]×``)::

    ω_d = Σ_i (R_{i+1} ⋯ R_3)ᵀ e_i θ̇_i

evaluated Horner-style, so the gyroscope is the true body rate and integrating it reproduces ``rot_wd``.
"""

from __future__ import annotations

import numpy as np

from pdr_mag.conventions import quat_multiply

#: Axes of the chain Rz · Rx · Ry · Rz.
CHAIN_AXES = (2, 0, 1, 2)


def smoothstep(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Quintic smoothstep ``S(x) = 10x³ − 15x⁴ + 6x⁵`` on [0, 1] (0 below, 1 above) and its derivative.

    C²-continuous, so blended accelerations stay continuous.
    """
    x = np.clip(np.asarray(x, dtype=float), 0.0, 1.0)
    s = x * x * x * (10.0 + x * (-15.0 + 6.0 * x))
    ds = 30.0 * x * x * (1.0 - x) ** 2
    return s, ds


def _elementary_quat(axis: int, angle: np.ndarray) -> np.ndarray:
    q = np.zeros((*angle.shape, 4))
    q[..., 0] = np.cos(0.5 * angle)
    q[..., 1 + axis] = np.sin(0.5 * angle)
    return q


def chain_quat(angles: np.ndarray) -> np.ndarray:
    """w-first quaternions (N, 4) of ``Rz(θ0)·Rx(θ1)·Ry(θ2)·Rz(θ3)`` for angles (N, 4), radians."""
    q = _elementary_quat(CHAIN_AXES[0], angles[:, 0])
    for i in range(1, 4):
        q = quat_multiply(q, _elementary_quat(CHAIN_AXES[i], angles[:, i]))
    return q


def _rotate_inverse(axis: int, angle: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``R_axis(angle)ᵀ @ v`` row-wise."""
    c, s = np.cos(angle), np.sin(angle)
    x, y, z = v[:, 0], v[:, 1], v[:, 2]
    if axis == 0:
        return np.stack([x, c * y + s * z, -s * y + c * z], axis=1)
    if axis == 1:
        return np.stack([c * x - s * z, y, s * x + c * z], axis=1)
    return np.stack([c * x + s * y, -s * x + c * y, z], axis=1)


def chain_body_rate(angles: np.ndarray, rates: np.ndarray) -> np.ndarray:
    """Body rate ω_d (N, 3), rad/s, of the chain for angles (N, 4) and their rates (N, 4)."""
    n = len(angles)
    v = np.zeros((n, 3))
    v[:, CHAIN_AXES[0]] = rates[:, 0]
    for i in range(1, 4):
        v = _rotate_inverse(CHAIN_AXES[i], angles[:, i], v)
        v[:, CHAIN_AXES[i]] += rates[:, i]
    return v
