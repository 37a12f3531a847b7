"""Frames, unit constants and quaternion helpers (see the conventions in :mod:`pdr_mag`).

Quaternions are w-first ``(qw, qx, qy, qz)`` everywhere outside this module; scipy's
:class:`~scipy.spatial.transform.Rotation` (x, y, z, w) is used inside.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

#: Standard gravity, m/s².
GRAVITY = 9.80665
#: Conversions into the library's units.
NT_PER_UT = 1000.0
UT_PER_GAUSS = 100.0
UT_PER_TESLA = 1e6
DEG = np.pi / 180.0


def quat_to_rotation(q_wxyz: np.ndarray) -> Rotation:
    """scipy Rotation from w-first quaternion(s), shape (4,) or (N, 4)."""
    q = np.asarray(q_wxyz, dtype=float)
    return Rotation.from_quat(q[..., [1, 2, 3, 0]])


def rotation_to_quat(rot: Rotation) -> np.ndarray:
    """w-first quaternion(s) from a scipy Rotation, with qw >= 0."""
    q = rot.as_quat()[..., [3, 0, 1, 2]]
    sign = np.where(q[..., :1] < 0, -1.0, 1.0)
    return q * sign


def quat_to_rot(q_wxyz: np.ndarray) -> np.ndarray:
    """Rotation matrix/matrices ``rot_wd`` (…, 3, 3) from w-first quaternion(s)."""
    return quat_to_rotation(q_wxyz).as_matrix()


def rot_to_quat(rot_wd: np.ndarray) -> np.ndarray:
    """w-first quaternion(s) from rotation matrix/matrices (…, 3, 3)."""
    return rotation_to_quat(Rotation.from_matrix(rot_wd))


def heading_deg_from_rot(rot_wd: np.ndarray) -> np.ndarray:
    """Heading in [0, 360) of the device +y axis, clockwise from north: ``atan2(R[0,1], R[1,1])``."""
    r = np.asarray(rot_wd, dtype=float)
    return np.mod(np.degrees(np.arctan2(r[..., 0, 1], r[..., 1, 1])), 360.0)


def heading_deg_from_quat(q_wxyz: np.ndarray) -> np.ndarray:
    """Heading in [0, 360) from w-first quaternion(s) (device→ENU); see :func:`heading_deg_from_rot`.

    Computed directly from the quaternion components (no matrix), valid for any attitude.
    """
    q = np.asarray(q_wxyz, dtype=float)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    r01 = 2.0 * (x * y - w * z)
    r11 = 1.0 - 2.0 * (x * x + z * z)
    return np.mod(np.degrees(np.arctan2(r01, r11)), 360.0)


def wrap_deg(angle_deg: np.ndarray | float) -> np.ndarray | float:
    """Wrap angle(s) to [-180, 180)."""
    return np.mod(np.asarray(angle_deg) + 180.0, 360.0) - 180.0


def rotation_about_up(angle_rad: float | np.ndarray) -> Rotation:
    """Rotation of world vectors about ENU up by ``angle_rad`` (counter-clockwise seen from above).

    A heading increase of δ degrees (clockwise) is ``rotation_about_up(-radians(δ))``.
    """
    return Rotation.from_rotvec(np.multiply.outer(np.asarray(angle_rad, dtype=float), [0.0, 0.0, 1.0]))


# ---------------------------------------------------------------------------------------------- vectorised
# Plain-numpy quaternion algebra for large arrays (the simulator, the model check): w-first, no scipy objects.


def quat_multiply(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product ``p ⊗ q`` of w-first quaternions (…, 4); the rotation ``R(p) · R(q)``."""
    pw, px, py, pz = np.moveaxis(np.asarray(p, dtype=float), -1, 0)
    qw, qx, qy, qz = np.moveaxis(np.asarray(q, dtype=float), -1, 0)
    return np.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        axis=-1,
    )


def quat_rotate(q_wd: np.ndarray, v: np.ndarray, inverse: bool = False) -> np.ndarray:
    """``rot_wd @ v`` (or ``rot_wdᵀ @ v`` with ``inverse``) for w-first unit quaternions, vectorised."""
    q = np.asarray(q_wd, dtype=float)
    w = q[..., :1]
    u = q[..., 1:] if not inverse else -q[..., 1:]
    v = np.asarray(v, dtype=float)
    c = 2.0 * np.cross(u, v)
    return v + w * c + np.cross(u, c)


def quat_slerp(t_key: np.ndarray, q_key: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Spherical linear interpolation of w-first quaternions ``q_key`` (N, 4) at times ``t``.

    Times outside ``[t_key[0], t_key[-1]]`` take the end values.  The shorter arc is used.
    """
    tk = np.asarray(t_key, dtype=float)
    qk = np.asarray(q_key, dtype=float)
    t = np.asarray(t, dtype=float)
    if len(tk) == 1:
        return np.broadcast_to(qk[0], (*t.shape, 4)).copy()
    i = np.clip(np.searchsorted(tk, t, side="right") - 1, 0, len(tk) - 2)
    u = np.clip((t - tk[i]) / (tk[i + 1] - tk[i]), 0.0, 1.0)[..., None]
    q0, q1 = qk[i], qk[i + 1]
    d = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(d < 0, -q1, q1)
    d = np.abs(d)
    ang = np.arccos(np.clip(d, -1.0, 1.0))
    s = np.sin(ang)
    small = s < 1e-9
    s_safe = np.where(small, 1.0, s)
    w0 = np.where(small, 1.0 - u, np.sin((1.0 - u) * ang) / s_safe)
    w1 = np.where(small, u, np.sin(u * ang) / s_safe)
    q = w0 * q0 + w1 * q1
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def rotvec_to_matrix(rotvec: np.ndarray) -> np.ndarray:
    """Rotation matrix ``exp([r]×)`` of a rotation vector r (3,), radians (Rodrigues)."""
    r = np.asarray(rotvec, dtype=float)
    ang = float(np.linalg.norm(r))
    if ang < 1e-15:
        return np.eye(3)
    k = r / ang
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(ang) * kx + (1.0 - np.cos(ang)) * (kx @ kx)
