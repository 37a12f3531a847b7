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

Sources: the documents the methods follow are listed once, in :mod:`pdr_mag.references`, and cited
elsewhere by their key and equation (``[Liu2018] eqs. 7–16``).
"""

import importlib as _importlib

#: public name → module that defines it (imported on first use, so ``import pdr_mag`` stays light:
#: the compiled fusion kernel, the simulator and the model check load only when asked for)
_EXPORTS = {
    # conventions and the Earth field
    "heading_deg_from_quat": "pdr_mag.conventions",
    "heading_deg_from_rot": "pdr_mag.conventions",
    "quat_to_rot": "pdr_mag.conventions",
    "rot_to_quat": "pdr_mag.conventions",
    "wrap_deg": "pdr_mag.conventions",
    "EarthField": "pdr_mag.field",
    "earth_field": "pdr_mag.field",
    "earth_field_from_meta": "pdr_mag.field",
    # calibration ([Long2013], [Zhong2017], [Liu2018], [Huang2018]: pdr_mag.references)
    "MagCalibration": "pdr_mag.calibration",
    "DevicePrior": "pdr_mag.calibration.prior",
    "PriorSettings": "pdr_mag.calibration.prior",
    "phone_prior": "pdr_mag.calibration.prior",
    "DeviceStore": "pdr_mag.calibration.store",
    "calibrate": "pdr_mag.calibration",
    "fit_sphere": "pdr_mag.calibration",
    "fit_twostep": "pdr_mag.calibration",
    "fit_ellipsoid": "pdr_mag.calibration",
    "fit_als": "pdr_mag.calibration",
    "fit_ml": "pdr_mag.calibration",
    "fit_radial_newton": "pdr_mag.calibration",
    "fit_lm9": "pdr_mag.calibration",
    "fit_alignment": "pdr_mag.calibration",
    "AcceptanceSettings": "pdr_mag.calibration",
    "assess": "pdr_mag.calibration",
    "coverage": "pdr_mag.calibration",
    "crlb": "pdr_mag.calibration",
    "OnlineCalibrator": "pdr_mag.calibration.online",
    "OnlineSettings": "pdr_mag.calibration.online",
    "gravity_aided_offset": "pdr_mag.calibration.online",
    # detection, fusion, pipeline
    "InterferenceSettings": "pdr_mag.fusion",
    "StrengthSettings": "pdr_mag.fusion",
    "DipSettings": "pdr_mag.fusion",
    "VarianceSettings": "pdr_mag.fusion",
    "ConsistencySettings": "pdr_mag.fusion",
    "FusionSettings": "pdr_mag.fusion",
    "GyroSettings": "pdr_mag.fusion",
    "AccelSettings": "pdr_mag.fusion",
    "MagSettings": "pdr_mag.fusion",
    "UncertaintySettings": "pdr_mag.fusion",
    "FusionCore": "pdr_mag.fusion",
    "PipelineSettings": "pdr_mag.pipeline",
    "HeadingPipeline": "pdr_mag.pipeline",
    "HeadingEstimate": "pdr_mag.estimates",
    "EstimateBatch": "pdr_mag.estimates",
    "Event": "pdr_mag.estimates",
    # the sensor model and the simulator
    "SensorModel": "pdr_mag.sim.sensor_model",
    "EFFECTS": "pdr_mag.sim.sensor_model",
    "Motion": "pdr_mag.sim.sensor_model",
    "DipoleField": "pdr_mag.sim.sensor_model",
    "PhoneSpec": "pdr_mag.sim.sensor_model",
    "predict_mag": "pdr_mag.sim.sensor_model",
    "measure_mag": "pdr_mag.sim.sensor_model",
    "correct_mag": "pdr_mag.sim.sensor_model",
    "integrate_gyro": "pdr_mag.sim.sensor_model",
    "simulate": "pdr_mag.sim",
    # simulation vs measured
    "diagnose": "pdr_mag.modelcheck",
    "DiagnoseSettings": "pdr_mag.modelcheck",
}

__all__ = sorted(_EXPORTS)

__version__ = "0.1.0"


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'pdr_mag' has no attribute {name!r}")
    value = getattr(_importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__))
