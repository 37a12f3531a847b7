"""Quaternion helpers of the fusion kernel (numba, scalar code).

Quaternions are w-first Hamilton quaternions, ``q`` rotates device into world coordinates
(``v_w = R(q) v_d``, rows of ``R``: world east, north, up); a correction in the world frame is applied on
the left (``q ← Exp(v) ⊗ q``), a gyroscope increment in the device frame on the right.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, error_model="numpy")
def rotation_matrix(q, R):
    """``R ← R(q)``: the rotation matrix of unit quaternion ``q`` (rows: world east, north, up)."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    R[0, 0] = 1 - 2 * (y * y + z * z)
    R[0, 1] = 2 * (x * y - w * z)
    R[0, 2] = 2 * (x * z + w * y)
    R[1, 0] = 2 * (x * y + w * z)
    R[1, 1] = 1 - 2 * (x * x + z * z)
    R[1, 2] = 2 * (y * z - w * x)
    R[2, 0] = 2 * (x * z - w * y)
    R[2, 1] = 2 * (y * z + w * x)
    R[2, 2] = 1 - 2 * (x * x + y * y)


@njit(cache=True, error_model="numpy")
def exp_quat(vx, vy, vz):
    """Unit quaternion ``Exp(v)`` of a rotation vector v (rad), w-first."""
    a = np.sqrt(vx * vx + vy * vy + vz * vz)
    if a < 1e-12:
        c, s = 1.0, 0.5
    else:
        c, s = np.cos(0.5 * a), np.sin(0.5 * a) / a
    return c, s * vx, s * vy, s * vz


@njit(cache=True, error_model="numpy")
def store_product(q, aw, ax, ay, az, bw, bx, by, bz):
    """``q ← a ⊗ b``, normalised."""
    w = aw * bw - ax * bx - ay * by - az * bz
    x = aw * bx + ax * bw + ay * bz - az * by
    y = aw * by - ax * bz + ay * bw + az * bx
    z = aw * bz + ax * by - ay * bx + az * bw
    n = np.sqrt(w * w + x * x + y * y + z * z)
    q[0], q[1], q[2], q[3] = w / n, x / n, y / n, z / n


@njit(cache=True, error_model="numpy")
def rotate_body(q, vx, vy, vz):
    """``q ← q ⊗ Exp(v)``, v a rotation vector in the device frame (gyroscope integration)."""
    bw, bx, by, bz = exp_quat(vx, vy, vz)
    store_product(q, q[0], q[1], q[2], q[3], bw, bx, by, bz)


@njit(cache=True, error_model="numpy")
def rotate_world(q, vx, vy, vz):
    """``q ← Exp(v) ⊗ q``, v a rotation vector in the world frame (an attitude correction)."""
    aw, ax, ay, az = exp_quat(vx, vy, vz)
    store_product(q, aw, ax, ay, az, q[0], q[1], q[2], q[3])


@njit(cache=True, error_model="numpy")
def rotate_vector(v, ex, ey, ez):
    """``v ← Exp(e) v`` to second order in e (a world-frame vector carried along with a correction e)."""
    vx, vy, vz = v[0], v[1], v[2]
    cx, cy, cz = ey * vz - ez * vy, ez * vx - ex * vz, ex * vy - ey * vx
    dx, dy, dz = ey * cz - ez * cy, ez * cx - ex * cz, ex * cy - ey * cx
    v[0], v[1], v[2] = vx + cx + 0.5 * dx, vy + cy + 0.5 * dy, vz + cz + 0.5 * dz


@njit(cache=True, error_model="numpy")
def heading_deg(q):
    """Heading of the device's +y axis, deg clockwise from north, in [0, 360)."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    r01 = 2.0 * (x * y - w * z)
    r11 = 1.0 - 2.0 * (x * x + z * z)
    return np.degrees(np.arctan2(r01, r11)) % 360.0


@njit(cache=True, error_model="numpy")
def wrap(a):
    """Angle wrapped to [−π, π)."""
    return (a + np.pi) % (2.0 * np.pi) - np.pi
