"""Adapter from a fitted model to :mod:`pdr_mag.sim.sensor_model`: the model check's simulated magnetometer.

Every gap the model check reports is ``rms(measured − predict_mag(SensorModel(...), …))`` — the prediction
of THE forward model, with the fitted values put in under the shared effect names.  What the sensor model
does not have, this adapter supplies, and nothing else:

* the orientation comes from the gyro + accelerometer track (:mod:`.orientation`); a fitted ``gyro_bias``
  enters the magnetometer only through that orientation, as the heading drift ``Rz(−ψ)`` it causes
  (:class:`TrackMotion`);
* ``local_anomaly`` is a :class:`TimeKnotField`: a recording has no positions, so the "position" handed to
  the field is the measurement time (``p = (τ, 0, 0)``) and the field is piecewise linear in it;
* ``temperature_offset`` (µT/°C, an effect real breadboard data demand) is not in the sensor model: it is
  added to the prediction here, ``+ c (T − T_ref)``;
* so is ``hard_iron_change`` (a temporary body-fixed offset, e.g. a magnet on the phone, as in BROAD's
  attached-magnet trials): ``+ Δb(t)``, piecewise linear in time.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pdr_mag.conventions import quat_multiply, quat_slerp
from pdr_mag.modelcheck.fit import FitResult, Problem, soft_iron_distortion
from pdr_mag.sim.sensor_model import SensorModel, predict_mag


@dataclass(frozen=True, eq=False)
class TimeKnotField:
    """``local_anomaly`` field piecewise linear in time: ``field_w(p)`` with ``p[:, 0]`` the time, s.

    Attributes
    ----------
    knots : (K,) times, s
    values_w : (K, 3) field at the knots, µT, ENU of the orientation track
    """

    knots: np.ndarray
    values_w: np.ndarray

    def field_w(self, position_w: np.ndarray) -> np.ndarray:
        tau = np.asarray(position_w, dtype=float)[:, 0]
        # held constant beyond the end knots (which are zero when the anomaly is confined to windows)
        return np.stack([np.interp(tau, self.knots, self.values_w[:, k]) for k in range(3)], axis=-1)

    def to_json(self) -> dict:
        return {"kind": "time_knots", "knots_s": self.knots.tolist(), "values_uT": self.values_w.tolist()}


@dataclass(frozen=True, eq=False)
class TrackMotion:
    """The orientation track as a :class:`~pdr_mag.sim.sensor_model.MotionLike`, with the heading drift of a
    residual gyro bias δ applied (``q' = qz(−ψ) ⊗ q``, ``ψ = δ · ∫up_d dt``) and time as position."""

    problem: Problem
    delta_gyro: np.ndarray | None = None

    def orientation(self, t: np.ndarray) -> np.ndarray:
        tr = self.problem.track
        q = quat_slerp(tr.t, tr.quat, t)
        if self.delta_gyro is not None:
            psi = tr.up_integral(t) @ self.delta_gyro
            qz = np.zeros((len(psi), 4))
            qz[:, 0], qz[:, 3] = np.cos(-0.5 * psi), np.sin(-0.5 * psi)
            q = quat_multiply(qz, q)
        return q

    def position(self, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, dtype=float)
        return np.column_stack([t, np.zeros_like(t), np.zeros_like(t)])


def anomaly_field(problem: Problem, fit: FitResult) -> TimeKnotField | None:
    if "local_anomaly" not in fit.linear:
        return None
    vals = np.zeros((len(problem.knots), 3))
    vals[problem.knot_free] = fit.linear["local_anomaly"]
    return TimeKnotField(problem.knots, vals)


def to_sensor_model(problem: Problem, fit: FitResult) -> SensorModel:
    """The fitted model under the shared effect names (values in the sensor model's units)."""
    eff: dict = {"hard_iron": fit.linear["hard_iron"], "noise": np.sqrt(np.mean(fit.residual**2, axis=0))}
    nl = fit.nonlinear
    if "soft_iron" in nl:
        s = np.linalg.inv(soft_iron_distortion(nl["soft_iron"]))
        eff["soft_iron"] = 0.5 * (s + s.T)
    if "time_offset" in nl:
        eff["time_offset"] = float(nl["time_offset"][0])
    if "mag_imu_misalignment" in nl:
        eff["mag_imu_misalignment"] = np.degrees(nl["mag_imu_misalignment"])
    if "bias_drift" in fit.linear:
        eff["bias_drift"] = fit.linear["bias_drift"]
    if "gyro_bias" in nl or np.any(problem.track.gyro_bias):
        eff["gyro_bias"] = problem.track.gyro_bias + nl.get("gyro_bias", np.zeros(3))
    anomaly = anomaly_field(problem, fit)
    if anomaly is not None:
        eff["local_anomaly"] = anomaly
    return SensorModel(eff, t_ref=problem.t_ref)


def simulate_mag(problem: Problem, fit: FitResult) -> np.ndarray:
    """Noise-free simulated magnetometer (N, 3), µT, at the recording's stamps, through the sensor model."""
    model = to_sensor_model(problem, fit)
    motion = TrackMotion(problem, fit.nonlinear.get("gyro_bias"))
    m = predict_mag(model, problem.t, motion, fit.linear["field_w"])
    if "hard_iron_change" in fit.linear:
        m = m + offset_change(problem, fit)
    if "temperature_offset" in fit.linear:
        m = m + np.multiply.outer(problem.temperature - problem.temp_ref, fit.linear["temperature_offset"])
    return m


def offset_change(problem: Problem, fit: FitResult) -> np.ndarray:
    """The fitted body-fixed offset change Δb(t) (N, 3), µT (``hard_iron_change``; not in the sensor
    model)."""
    vals = np.zeros((len(problem.offset_knots), 3))
    vals[problem.offset_knot_free] = fit.linear["hard_iron_change"]
    return np.stack([np.interp(problem.t, problem.offset_knots, vals[:, k]) for k in range(3)], axis=-1)


def gap(problem: Problem, fit: FitResult) -> float:
    """RMS of measured minus simulated magnetometer, µT (all axes)."""
    return float(np.sqrt(np.mean((problem.mag - simulate_mag(problem, fit)) ** 2)))
