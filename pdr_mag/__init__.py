"""pdr_mag — magnetometer calibration, interference detection and fused heading for pedestrian navigation.

Conventions (stated once; every module follows them)
-----------------------------------------------------
Units
    magnetic field µT, acceleration m/s² (specific force: a phone lying flat, screen up, reads about +9.81
    on +z), angular rate rad/s (right-handed), time s (float). Only exceptions carry a suffix:
    ``heading_deg``, ``t_ns``, ``field_nT``.
Frames
    device frame ``_d``: Android sensor frame — x to the right of the screen, y to the top, z out of the
    screen.  World frame ``_w``: ENU — x east, y north, z up.
Orientation
    ``rot_wd`` rotates device-frame vectors into the world frame: ``v_w = rot_wd @ v_d``.  As a quaternion it
    is written **w-first** ``(qw, qx, qy, qz)`` at every edge of the library (files, dataclasses, JSON).
    Internally :class:`scipy.spatial.transform.Rotation` is used (which is x, y, z, w); the helpers in
    :mod:`pdr_mag.conventions` are the only place that converts.
Heading
    ``heading_deg`` in [0, 360): clockwise from north of the device +y axis projected on the horizontal
    plane, ``atan2(R[0, 1], R[1, 1])`` with ``R = rot_wd`` (Android's azimuth).  North is true north when
    position and date are known (declination from the World Magnetic Model), otherwise magnetic north; every
    output says which.
Magnetometer calibration
    ``m_cal = soft_iron @ (m_raw - offset)`` with ``soft_iron`` symmetric positive definite and
    ``|m_cal| ≈ field``.

The library knows no file format; reading recordings and writing files is the job of the ``replay``
package (readers) and :mod:`pdr_mag.sinks` (MCAP, rerun).
"""

from pdr_mag.calibration.model import MagCalibration
from pdr_mag.calibration.sphere import fit_sphere
from pdr_mag.conventions import heading_deg_from_quat, quat_to_rot, rot_to_quat
from pdr_mag.field import EarthField, earth_field

__all__ = [
    "EarthField",
    "MagCalibration",
    "earth_field",
    "fit_sphere",
    "heading_deg_from_quat",
    "quat_to_rot",
    "rot_to_quat",
]

__version__ = "0.1.0"
