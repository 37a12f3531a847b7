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
