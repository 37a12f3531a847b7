"""THE forward model of the phone's sensors, with named, switchable effects.

The simulator (:mod:`pdr_mag.sim`), the calibration and the model check share this module, so an effect
has one name, one unit and one meaning everywhere (names as in ``../shared/INTERFACE.md``).

Model
-----
A magnetometer sample stamped ``t`` (magnetometer clock) is, with the symbols of the code::

    τ        = t − time_offset                               true measurement time on the IMU clock
    h_w      = field_w + local_anomaly(p_w(τ))               field at the phone, ENU, µT
    h_d      = rot_wd(τ)ᵀ · h_w                              in device (= IMU) axes
    m_mag    = mag_to_imuᵀ · h_d                             in magnetometer axes,
               mag_to_imu = exp([μ]×), μ = radians(mag_imu_misalignment)
    b(t)     = hard_iron + bias_drift · (t − t_ref) / 60     drifting offset (bias_drift is per minute)
    m_raw(t) = soft_iron⁻¹ · m_mag + b(t) + n,   n ~ N(0, diag(noise²))

then saturation at the sensor's range and rounding to its resolution (:class:`PhoneSpec`).  This is the
lumped error model ``H_m = S·H_i + b + ε`` of [Long2013] (eqs. 3–4, ``S = C_k C_n C_s``) with
``S = soft_iron⁻¹ · mag_to_imuᵀ``, plus the time and position dependence a moving phone adds.

``soft_iron`` is the *correction* matrix, the very one :class:`~pdr_mag.calibration.model.MagCalibration`
estimates: ``m_cal = soft_iron @ (m_raw − offset)`` with ``offset = b(t)`` gives back ``m_mag`` exactly
(noise aside), and ``mag_to_imu @ m_cal`` gives ``h_d``.  :func:`correct_mag` is that inverse.

The inertial sensors (device axes, IMU clock)::

    gyro_d  = ω_d + gyro_bias + n_g                          ω_d: body rate of rot_wd, rad/s
    accel_d = rot_wdᵀ · (a_w + g·ẑ) + n_a                    a_w: linear acceleration, m/s²

Effects (:data:`EFFECTS`, in this order)
-----------------------------------------
``hard_iron`` µT (3,), ``soft_iron`` (3, 3) SPD, ``time_offset`` s, ``mag_imu_misalignment`` deg (rotation
vector (3,)), ``bias_drift`` µT/min (3,), ``local_anomaly`` µT (a field object of position:
:class:`DipoleField` for steel, :class:`~pdr_mag.sim.building.BuildingField` for a building's own weak field,
:class:`~pdr_mag.sim.building.FieldSum` for both), ``gyro_bias`` rad/s (3,), ``noise`` µT (σ per axis,
(3,)).  An effect that is absent is off (its neutral value: zero, identity or no field).

Using it
--------
::

    model = SensorModel({"hard_iron": [30, -12, 80], "noise": 0.4})   # values normalised, immutable
    motion = Motion(t, q_wd)                          # orientation samples (slerped), optional positions
    m = predict_mag(model, t_mag, motion, field_w)    # noise-free raw magnetometer at the stamps t_mag
    m_noisy = measure_mag(model, t_mag, motion, field_w, rng)          # + noise, saturation, rounding
    h_d = correct_mag(model, t_mag, m_raw)            # the inverse: field in device axes
    model.with_effects(time_offset=0.04).without("noise").only("hard_iron", "time_offset")
    pack_effect("soft_iron", s), unpack_effect("soft_iron", p)          # flat parameters for fitting
    q = integrate_gyro(t_gyro, gyro - gyro_bias, q0)  # gyro-predicted orientation (for Motion)
    model.ideal_calibration(t)                        # the MagCalibration that undoes this phone exactly

Any object with ``orientation(t)`` and ``position(t)`` (:class:`MotionLike`) can replace :class:`Motion`;
the simulator's trajectories are evaluated analytically that way.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Protocol

import numpy as np

from pdr_mag.calibration.model import MagCalibration
from pdr_mag.conventions import (  # noqa: F401  (quaternion helpers re-exported for callers)
    GRAVITY,
    quat_multiply,
    quat_rotate,
    quat_slerp,
    rotvec_to_matrix,
)
from pdr_mag.sim.building import field_from_json
from pdr_mag.sim.effects import (  # noqa: F401  (the effects' names re-exported for callers)
    _NEUTRAL,
    EFFECT_SIZES,
    EFFECTS,
    DipoleField,
    EffectInfo,
    normalise_effect,
    pack_effect,
    parse_effect_value,
    unpack_effect,
)

# ---------------------------------------------------------------------------------------------- quaternions


def integrate_gyro(t: np.ndarray, omega_d: np.ndarray, q0: np.ndarray) -> np.ndarray:
    """Orientation from body rates: ``q_{k+1} = q_k ⊗ exp(½ ω̄_k Δt_k)``, ``ω̄_k = (ω_k + ω_{k+1}) / 2``.

    Trapezoid rate, one rotation per step: local error ≈ Δt³/12 (|ω̈| + |ω × ω̇|).  The running product is
    a parallel prefix scan (log₂ N vectorised rounds), so an hour at 200 Hz takes a fraction of a second.
    Subtract a known gyro bias from ``omega_d`` first.  Returns w-first quaternions (N, 4), ``q[0] = q0``.
    """
    t = np.asarray(t, dtype=float)
    w = np.asarray(omega_d, dtype=float)
    if w.shape != (len(t), 3):
        raise ValueError(f"omega_d: expected shape ({len(t)}, 3) in rad/s, got {w.shape}")
    wm = 0.5 * (w[1:] + w[:-1])
    norm = np.linalg.norm(wm, axis=1)
    ang = norm * np.diff(t)
    axis = wm / np.where(norm > 0, norm, 1.0)[:, None]
    p = np.empty((len(t), 4))
    p[0] = np.asarray(q0, dtype=float) / np.linalg.norm(q0)
    p[1:, 0] = np.cos(0.5 * ang)
    p[1:, 1:] = axis * np.sin(0.5 * ang)[:, None]
    step = 1
    while step < len(p):  # inclusive scan: p[i] = p[i − step] ⊗ p[i]
        p[step:] = quat_multiply(p[:-step], p[step:])
        step *= 2
    return p / np.linalg.norm(p, axis=1, keepdims=True)


# ---------------------------------------------------------------------------------------------- motion


class MotionLike(Protocol):
    """What the model needs of a motion: orientation (and position) at any time on the IMU clock."""

    def orientation(self, t: np.ndarray) -> np.ndarray:
        """w-first quaternions ``rot_wd`` (N, 4) at times ``t`` (N,)."""

    def position(self, t: np.ndarray) -> np.ndarray | None:
        """Positions ``p_w`` (N, 3), m, ENU — or None when unknown."""


@dataclass(frozen=True, eq=False)
class Motion:
    """A sampled motion: orientation samples (slerped in between) and optional positions (linear).

    Attributes
    ----------
    t : (N,) array
        Strictly increasing times, s (IMU clock).
    q_wd : (N, 4) array
        w-first quaternions device → world (ENU).
    position_w : (N, 3) array or None
        Phone positions, m, ENU; needed only for ``local_anomaly``.
    """

    t: np.ndarray
    q_wd: np.ndarray
    position_w: np.ndarray | None = None

    def __post_init__(self) -> None:
        t = np.asarray(self.t, dtype=float)
        q = np.asarray(self.q_wd, dtype=float)
        if t.ndim != 1 or len(t) < 1 or np.any(np.diff(t) <= 0):
            raise ValueError(f"t: expected strictly increasing times (N,), s; got shape {t.shape}")
        if q.shape != (len(t), 4):
            raise ValueError(f"q_wd: expected w-first quaternions of shape ({len(t)}, 4), got {q.shape}")
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "q_wd", q / np.linalg.norm(q, axis=1, keepdims=True))
        if self.position_w is not None:
            p = np.asarray(self.position_w, dtype=float)
            if p.shape != (len(t), 3):
                raise ValueError(f"position_w: expected shape ({len(t)}, 3) in m, got {p.shape}")
            object.__setattr__(self, "position_w", p)

    def orientation(self, t: np.ndarray) -> np.ndarray:
        return quat_slerp(self.t, self.q_wd, t)

    def position(self, t: np.ndarray) -> np.ndarray | None:
        if self.position_w is None:
            return None
        t = np.asarray(t, dtype=float)
        return np.stack([np.interp(t, self.t, self.position_w[:, k]) for k in range(3)], axis=-1)


# ---------------------------------------------------------------------------------------------- the model


@dataclass(frozen=True)
class SensorModel:
    """A phone's sensor errors: the active effects and their values (settings; immutable).

    Parameters
    ----------
    effects : mapping name → value
        Active effects (names of :data:`EFFECTS`); values are normalised on construction
        (``value(name)`` returns the canonical array).  Absent effects are off.
    t_ref : float
        Time (s, magnetometer stamps) at which the offset equals ``hard_iron`` (``bias_drift`` reference).
    """

    effects: Mapping[str, Any] = field(default_factory=dict)
    t_ref: float = 0.0

    def __post_init__(self) -> None:
        norm = {}
        for name in EFFECTS:  # canonical order
            if name in self.effects and self.effects[name] is not None:
                norm[name] = normalise_effect(name, self.effects[name])
        unknown = set(self.effects) - set(EFFECTS)
        if unknown:
            raise ValueError(f"unknown effect(s) {sorted(unknown)}; known: {', '.join(EFFECTS)}")
        object.__setattr__(self, "effects", MappingProxyType(norm))
        object.__setattr__(self, "t_ref", float(self.t_ref))

    def __hash__(self) -> int:  # consistent with __eq__: array contents, field objects by identity
        items = tuple(
            (k, v.tobytes() if isinstance(v, np.ndarray) else id(v)) for k, v in self.effects.items()
        )
        return hash((self.t_ref, items))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, SensorModel) or set(self.effects) != set(other.effects):
            return False
        if self.t_ref != other.t_ref:
            return False
        for k, v in self.effects.items():
            w = other.effects[k]
            if isinstance(v, np.ndarray):
                if not np.array_equal(v, w):
                    return False
            elif v is not w:
                return False
        return True

    @property
    def active(self) -> tuple[str, ...]:
        """Names of the active effects, in :data:`EFFECTS` order."""
        return tuple(self.effects)

    def value(self, name: str):
        """The effect's value, or its neutral value (zeros, identity, None) when it is off."""
        if name not in EFFECTS:
            raise ValueError(f"unknown effect {name!r}; known: {', '.join(EFFECTS)}")
        return self.effects.get(name, _NEUTRAL[name])

    def with_effects(self, **values) -> SensorModel:
        """A copy with these effects set (``None`` switches one off)."""
        eff = dict(self.effects)
        eff.update(values)
        return SensorModel({k: v for k, v in eff.items() if v is not None}, self.t_ref)

    def without(self, *names: str) -> SensorModel:
        """A copy with these effects switched off."""
        return SensorModel({k: v for k, v in self.effects.items() if k not in names}, self.t_ref)

    def only(self, *names: str) -> SensorModel:
        """A copy keeping only these effects."""
        return SensorModel({k: v for k, v in self.effects.items() if k in names}, self.t_ref)

    # -------------------------------------------------------------- derived quantities
    @property
    def mag_to_imu(self) -> np.ndarray:
        """Rotation matrix from magnetometer axes to IMU (device) axes."""
        return rotvec_to_matrix(np.radians(self.value("mag_imu_misalignment")))

    def offset(self, t_mag: np.ndarray) -> np.ndarray:
        """``b(t) = hard_iron + bias_drift · (t − t_ref) / 60``, (N, 3), µT."""
        t = np.asarray(t_mag, dtype=float)
        return self.value("hard_iron") + np.multiply.outer(t - self.t_ref, self.value("bias_drift") / 60.0)

    def measurement_time(self, t_mag: np.ndarray) -> np.ndarray:
        """True measurement time on the IMU clock of magnetometer stamps: ``τ = t − time_offset``."""
        return np.asarray(t_mag, dtype=float) - float(self.value("time_offset"))

    def ideal_calibration(self, t_mag: float | None = None):
        """The exact :class:`~pdr_mag.calibration.model.MagCalibration` of this phone at time ``t_mag``
        (default ``t_ref``): ``offset = b(t)``, ``soft_iron``, ``mag_to_imu`` (None without misalignment),
        ``field_uT`` NaN (it belongs to the place, not the phone), method ``"truth"``."""
        t = self.t_ref if t_mag is None else float(t_mag)
        mis = self.mag_to_imu if "mag_imu_misalignment" in self.effects else None
        return MagCalibration.from_arrays(
            self.offset(t), self.value("soft_iron"), method="truth", mag_to_imu=mis
        )

    def to_json(self) -> dict:
        """JSON-ready dict of the active effects (lists, floats; ``local_anomaly`` via its ``to_json``)."""
        out: dict[str, Any] = {}
        for k, v in self.effects.items():
            if isinstance(v, np.ndarray):
                out[k] = v.tolist()
            elif hasattr(v, "to_json"):
                out[k] = v.to_json()
            else:
                out[k] = repr(v)
        return out

    @classmethod
    def from_json(cls, obj: Mapping[str, Any], t_ref: float = 0.0) -> SensorModel:
        eff = dict(obj)
        if isinstance(eff.get("local_anomaly"), dict):
            eff["local_anomaly"] = field_from_json(eff["local_anomaly"])
        return cls(eff, t_ref)


# ---------------------------------------------------------------------------------------------- hardware


@dataclass(frozen=True)
class PhoneSpec:
    """The realities of a phone's sensors beyond the named effects (documented defaults: a typical phone).

    Rates are nominal; each stream gets its own clock error and jitter.  A step of 0 means no
    quantisation, a range of ``inf`` no saturation.

    Attributes
    ----------
    accel_rate_hz, gyro_rate_hz, mag_rate_hz : float
        Nominal sample rates (100, 100, 50 Hz).
    rate_error : float
        σ of the relative clock-rate error per stream (0.002: 0.2 %).
    imu_jitter_s, mag_jitter_s : float
        σ of the timestamp jitter (0.3 ms, 1 ms), clipped to ±0.4 of a period.
    drop_prob : float
        Probability that a sample is dropped (0.002).
    gap_rate_hz, gap_max_s : float
        Rate of longer gaps (0.01 per second) and their longest length (0.3 s).
    accel_noise, gyro_noise : float
        White noise σ per sample (0.015 m/s², 0.0015 rad/s).
    accel_range, gyro_range, mag_range : float
        Full scale (±8 g = 78.45 m/s², ±2000 °/s = 34.9 rad/s, ±4912 µT).
    accel_step, gyro_step, mag_step : float
        Resolution (0.0024 m/s², 0.00107 rad/s, 0.15 µT — 16-bit IMU, AK09918-like magnetometer).
    """

    accel_rate_hz: float = 100.0
    gyro_rate_hz: float = 100.0
    mag_rate_hz: float = 50.0
    rate_error: float = 0.002
    imu_jitter_s: float = 0.0003
    mag_jitter_s: float = 0.001
    drop_prob: float = 0.002
    gap_rate_hz: float = 0.01
    gap_max_s: float = 0.3
    accel_noise: float = 0.015
    gyro_noise: float = 0.0015
    accel_range: float = 78.45
    gyro_range: float = 34.9
    mag_range: float = 4912.0
    accel_step: float = 0.0024
    gyro_step: float = 0.00107
    mag_step: float = 0.15

    @classmethod
    def ideal(cls, **overrides) -> PhoneSpec:
        """No noise, jitter, drops, quantisation or saturation (rates as given)."""
        base = dict(
            rate_error=0.0,
            imu_jitter_s=0.0,
            mag_jitter_s=0.0,
            drop_prob=0.0,
            gap_rate_hz=0.0,
            accel_noise=0.0,
            gyro_noise=0.0,
            accel_range=np.inf,
            gyro_range=np.inf,
            mag_range=np.inf,
            accel_step=0.0,
            gyro_step=0.0,
            mag_step=0.0,
        )
        base.update(overrides)
        return cls(**base)


def digitise(values: np.ndarray, full_scale: float, step: float) -> np.ndarray:
    """Saturate at ``±full_scale`` then round to multiples of ``step`` (0: no rounding)."""
    v = np.clip(values, -full_scale, full_scale)
    if step > 0:
        v = np.round(v / step) * step
    return v


# ---------------------------------------------------------------------------------------------- forward


def _field_vec(field_w) -> np.ndarray:
    f = getattr(field_w, "field_w_array", field_w)
    f = np.asarray(f, dtype=float)
    if f.shape[-1:] != (3,):
        raise ValueError(f"field_w: expected an EarthField or ENU vector(s) (…, 3) in µT, got {f.shape}")
    return f


def mag_from_orientation(model: SensorModel, t_mag, q_wd, field_w, position_w=None) -> np.ndarray:
    """Noise-free raw magnetometer (N, 3), µT, given the orientation (and position) at the *true*
    measurement times ``τ = t_mag − time_offset`` (see the module docstring for the formula).

    ``field_w`` is an :class:`~pdr_mag.field.EarthField` or ENU vector(s) (3,) / (N, 3), µT.
    """
    t = np.asarray(t_mag, dtype=float)
    h_w = np.broadcast_to(_field_vec(field_w), (len(t), 3))
    anomaly = model.value("local_anomaly")
    if anomaly is not None:
        if position_w is None:
            raise ValueError("position_w: local_anomaly is on, so positions (N, 3) in m are needed")
        h_w = h_w + anomaly.field_w(np.asarray(position_w, dtype=float))
    h_d = quat_rotate(q_wd, h_w, inverse=True)
    m = h_d
    if "mag_imu_misalignment" in model.effects:
        m = m @ model.mag_to_imu  # row-wise mag_to_imuᵀ @ h_d
    if "soft_iron" in model.effects:
        m = np.linalg.solve(model.value("soft_iron"), m.T).T
    return m + model.offset(t)


def predict_mag(model: SensorModel, t_mag, motion: MotionLike, field_w) -> np.ndarray:
    """Noise-free raw magnetometer (N, 3), µT, at the magnetometer stamps ``t_mag``.

    Evaluates ``motion`` at ``τ = t_mag − time_offset`` (a :class:`Motion` slerps its samples) and applies
    :func:`mag_from_orientation`.
    """
    tau = model.measurement_time(t_mag)
    pos = motion.position(tau) if "local_anomaly" in model.effects else None
    return mag_from_orientation(model, t_mag, motion.orientation(tau), field_w, pos)


def measure_mag(
    model: SensorModel,
    t_mag,
    motion: MotionLike,
    field_w,
    rng: np.random.Generator,
    phone: PhoneSpec | None = None,
) -> np.ndarray:
    """:func:`predict_mag` plus white noise σ = ``noise``, then saturation and quantisation."""
    phone = phone or PhoneSpec()
    m = predict_mag(model, t_mag, motion, field_w)
    m = m + rng.standard_normal(m.shape) * model.value("noise")
    return digitise(m, phone.mag_range, phone.mag_step)


def correct_mag(model: SensorModel, t_mag, mag_raw) -> np.ndarray:
    """Invert the static part of the model: ``h_d = mag_to_imu · soft_iron · (m_raw − b(t))``, device axes.

    With the true model this returns ``rot_wd(τ)ᵀ (field_w + local_anomaly)`` plus the transformed noise.
    """
    m = np.asarray(mag_raw, dtype=float) - model.offset(t_mag)
    m = m @ model.value("soft_iron").T
    return m @ model.mag_to_imu.T


def predict_gyro(model: SensorModel, omega_d) -> np.ndarray:
    """Noise-free gyroscope ``ω_d + gyro_bias`` (N, 3), rad/s."""
    return np.asarray(omega_d, dtype=float) + model.value("gyro_bias")


def measure_gyro(
    model: SensorModel, omega_d, rng: np.random.Generator, phone: PhoneSpec | None = None
) -> np.ndarray:
    """:func:`predict_gyro` plus white noise, saturation and quantisation (:class:`PhoneSpec`)."""
    phone = phone or PhoneSpec()
    g = predict_gyro(model, omega_d)
    g = g + rng.standard_normal(g.shape) * phone.gyro_noise
    return digitise(g, phone.gyro_range, phone.gyro_step)


def predict_accel(q_wd, accel_w) -> np.ndarray:
    """Specific force in device axes ``rot_wdᵀ (a_w + g ẑ)`` (N, 3), m/s²."""
    a = np.array(accel_w, dtype=float)
    a[..., 2] += GRAVITY
    return quat_rotate(q_wd, a, inverse=True)


def measure_accel(q_wd, accel_w, rng: np.random.Generator, phone: PhoneSpec | None = None) -> np.ndarray:
    """:func:`predict_accel` plus white noise, saturation and quantisation (:class:`PhoneSpec`)."""
    phone = phone or PhoneSpec()
    f = predict_accel(q_wd, accel_w)
    f = f + rng.standard_normal(f.shape) * phone.accel_noise
    return digitise(f, phone.accel_range, phone.accel_step)
