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
lumped error model ``H_m = S·H_i + b + ε`` of seed 000 (eqs. 3–4, ``S = C_k C_n C_s``) with
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
vector (3,)), ``bias_drift`` µT/min (3,), ``local_anomaly`` µT (a field object of position, e.g.
:class:`DipoleField`), ``gyro_bias`` rad/s (3,), ``noise`` µT (σ per axis, (3,)).  An effect that is
absent is off (its neutral value: zero, identity or no field).

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

from pdr_mag.conventions import (  # noqa: F401  (quaternion helpers re-exported for callers)
    GRAVITY,
    quat_multiply,
    quat_rotate,
    quat_slerp,
    rotvec_to_matrix,
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


# ---------------------------------------------------------------------------------------------- anomalies


@dataclass(frozen=True, eq=False)
class DipoleField:
    """External field of point dipoles (steel in a building), a ``local_anomaly`` value.

    ``B(p) = Σ_{k: |r_k| ≤ cutoff_m} (3 r̂_k (m_k · r̂_k) − m_k) / |r_k|³`` with ``r_k = p − positions_w[k]``
    (|r_k| floored at 1 cm); the moments carry the factor μ0/4π, so they are in µT·m³ and B is in µT.
    Dipoles beyond ``cutoff_m`` contribute nothing (a k-d tree finds the near ones, so long walks past many
    dipoles stay fast); at 25 m a dipole that gives 30 µT at 1 m adds less than 0.002 µT.

    Attributes
    ----------
    positions_w : (K, 3) array
        Dipole positions, m, ENU (same origin as the motion's positions).
    moments_w : (K, 3) array
        Moments × μ0/4π, µT·m³, ENU.
    peak_uT : float
        The strength it was scaled to (largest |B| along the path it was laid out for), µT; informative.
    cutoff_m : float
        Range of each dipole, m (``inf``: all dipoles everywhere).
    """

    positions_w: np.ndarray
    moments_w: np.ndarray
    peak_uT: float = float("nan")
    cutoff_m: float = float("inf")

    def __post_init__(self) -> None:
        p = np.atleast_2d(np.asarray(self.positions_w, dtype=float))
        m = np.atleast_2d(np.asarray(self.moments_w, dtype=float))
        if p.shape != m.shape or p.shape[1] != 3:
            raise ValueError(
                f"positions_w, moments_w: expected equal shapes (K, 3), got {p.shape}, {m.shape}"
            )
        if not float(self.cutoff_m) > 0:
            raise ValueError(f"cutoff_m: expected a range > 0 in m, got {self.cutoff_m!r}")
        object.__setattr__(self, "positions_w", p)
        object.__setattr__(self, "moments_w", m)
        object.__setattr__(self, "cutoff_m", float(self.cutoff_m))

    def field_w(self, position_w: np.ndarray) -> np.ndarray:
        """Anomaly field (N, 3), µT, ENU, at positions (N, 3), m."""
        pos = np.asarray(position_w, dtype=float)
        out = np.zeros_like(pos)
        if len(pos) == 0 or len(self.positions_w) == 0:
            return out
        if np.isfinite(self.cutoff_m):
            from scipy.spatial import cKDTree

            near = cKDTree(pos).query_ball_point(self.positions_w, self.cutoff_m, return_sorted=True)
        else:
            near = [None] * len(self.positions_w)
        for pk, mk, idx in zip(self.positions_w, self.moments_w, near, strict=True):
            if idx is not None:
                if not len(idx):
                    continue
                idx = np.asarray(idx, dtype=np.intp)
            r = (pos if idx is None else pos[idx]) - pk
            r2 = np.maximum(np.einsum("ij,ij->i", r, r), 1e-4)[:, None]
            mr = (r @ mk)[:, None]
            b = (3.0 * mr * r / r2 - mk) / (r2 * np.sqrt(r2))
            if idx is None:
                out += b
            else:
                out[idx] += b
        return out

    def scaled(self, factor: float) -> DipoleField:
        return DipoleField(self.positions_w, self.moments_w * factor, self.peak_uT * factor, self.cutoff_m)

    def to_json(self) -> dict:
        return {
            "kind": "dipoles",
            "peak_uT": round(float(self.peak_uT), 6),
            "cutoff_m": self.cutoff_m if np.isfinite(self.cutoff_m) else None,
            "positions_m": self.positions_w.tolist(),
            "moments_uT_m3": self.moments_w.tolist(),
        }

    @classmethod
    def from_json(cls, obj: dict) -> DipoleField:
        cutoff = obj.get("cutoff_m")
        return cls(
            np.asarray(obj["positions_m"], dtype=float),
            np.asarray(obj["moments_uT_m3"], dtype=float),
            obj.get("peak_uT", np.nan),
            float("inf") if cutoff is None else float(cutoff),
        )


# ---------------------------------------------------------------------------------------------- effects


@dataclass(frozen=True)
class EffectInfo:
    """One named effect: unit, value shape, meaning, and the values ``--effect NAME=VALUE`` accepts."""

    name: str
    unit: str
    shape: str
    description: str
    cli: str


EFFECTS: dict[str, EffectInfo] = {
    e.name: e
    for e in (
        EffectInfo(
            "hard_iron",
            "µT",
            "(3,)",
            "constant offset b of the raw magnetometer, magnetometer axes",
            "bx,by,bz (one value: all axes)",
        ),
        EffectInfo(
            "soft_iron",
            "1",
            "(3,3) SPD",
            "correction matrix S of m_cal = S (m_raw − b); the distortion applied is S⁻¹",
            "s | sxx,syy,szz | sxx,syy,szz,sxy,sxz,syz | 9 values row-major",
        ),
        EffectInfo(
            "time_offset",
            "s",
            "scalar",
            "magnetometer stamps are late: a sample stamped t was measured at IMU time t − time_offset",
            "seconds",
        ),
        EffectInfo(
            "mag_imu_misalignment",
            "deg",
            "(3,)",
            "rotation mag_to_imu of the magnetometer axes relative to the IMU axes, rotation vector",
            "rx,ry,rz | angle about (1,1,1)/√3",
        ),
        EffectInfo(
            "bias_drift",
            "µT/min",
            "(3,)",
            "hard-iron offset changing linearly in time from t_ref",
            "dx,dy,dz (one value: all axes)",
        ),
        EffectInfo(
            "local_anomaly",
            "µT",
            "field",
            "external field depending on the phone's position (steel dipoles along the path)",
            "peak |B| along the path, µT (the scenario lays the dipoles out)",
        ),
        EffectInfo(
            "gyro_bias",
            "rad/s",
            "(3,)",
            "constant gyroscope bias, device axes",
            "bx,by,bz (one value: all axes)",
        ),
        EffectInfo("noise", "µT", "(3,)", "white magnetometer noise σ per axis", "σ | σx,σy,σz"),
    )
}


def _vec3(name: str, value: Any, nonneg: bool = False) -> np.ndarray:
    v = np.asarray(value, dtype=float)
    if v.ndim == 0 or v.shape == (1,):
        v = np.full(3, float(v.reshape(-1)[0]))
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise ValueError(f"{name}: expected 3 finite values ({EFFECTS[name].unit}), got {value!r}")
    if nonneg and np.any(v < 0):
        raise ValueError(f"{name}: expected values ≥ 0 ({EFFECTS[name].unit}), got {value!r}")
    return v


def _soft_iron(value: Any) -> np.ndarray:
    v = np.asarray(value, dtype=float)
    flat = v.reshape(-1)
    if flat.size == 1:
        s = flat[0] * np.eye(3)
    elif flat.size == 3 and v.ndim <= 1:
        s = np.diag(flat)
    elif flat.size == 6 and v.ndim <= 1:
        xx, yy, zz, xy, xz, yz = flat
        s = np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])
    elif flat.size == 9:
        s = flat.reshape(3, 3)
    else:
        raise ValueError(f"soft_iron: expected 1, 3, 6 or 9 values, got {flat.size}")
    if not np.all(np.isfinite(s)):
        raise ValueError("soft_iron: values must be finite")
    if not np.allclose(s, s.T, rtol=0.0, atol=1e-9 * max(1.0, np.abs(s).max())):
        raise ValueError(f"soft_iron: expected a symmetric matrix, got {s.tolist()}")
    s = 0.5 * (s + s.T)
    if np.linalg.eigvalsh(s).min() <= 0:
        raise ValueError(f"soft_iron: expected a positive-definite matrix, got {s.tolist()}")
    return s


def _scalar(name: str, value: Any) -> np.ndarray:
    v = np.asarray(value, dtype=float)
    if v.size != 1 or not np.isfinite(v.reshape(-1)[0]):
        raise ValueError(f"{name}: expected one finite value ({EFFECTS[name].unit}), got {value!r}")
    return np.asarray(float(v.reshape(-1)[0]))


def _misalignment(value: Any) -> np.ndarray:
    v = np.asarray(value, dtype=float)
    if v.size == 1:
        v = float(v.reshape(-1)[0]) * np.ones(3) / np.sqrt(3.0)
    return _vec3("mag_imu_misalignment", v)


def _anomaly(value: Any):
    if not callable(getattr(value, "field_w", None)):
        raise ValueError(
            "local_anomaly: expected a field object with field_w(position_w) (e.g. DipoleField), "
            f"got {value!r}; a peak strength in µT is laid out as dipoles by pdr_mag.sim"
        )
    return value


_NORMALISE = {
    "hard_iron": lambda v: _vec3("hard_iron", v),
    "soft_iron": _soft_iron,
    "time_offset": lambda v: _scalar("time_offset", v),
    "mag_imu_misalignment": _misalignment,
    "bias_drift": lambda v: _vec3("bias_drift", v),
    "local_anomaly": _anomaly,
    "gyro_bias": lambda v: _vec3("gyro_bias", v),
    "noise": lambda v: _vec3("noise", v, nonneg=True),
}

_NEUTRAL = {
    "hard_iron": np.zeros(3),
    "soft_iron": np.eye(3),
    "time_offset": np.asarray(0.0),
    "mag_imu_misalignment": np.zeros(3),
    "bias_drift": np.zeros(3),
    "local_anomaly": None,
    "gyro_bias": np.zeros(3),
    "noise": np.zeros(3),
}


def normalise_effect(name: str, value: Any):
    """Check and normalise one effect value to its canonical form (see :data:`EFFECTS`).

    Raises ValueError naming the effect for an unknown name or a bad value.
    """
    if name not in EFFECTS:
        raise ValueError(f"unknown effect {name!r}; known: {', '.join(EFFECTS)}")
    out = _NORMALISE[name](value)
    if isinstance(out, np.ndarray):
        out = out.copy()
        out.flags.writeable = False
    return out


def parse_effect_value(name: str, text: str):
    """Parse a command-line value: ``"off"``, a number, or comma-separated numbers.

    Returns None for ``off``; a float or float array otherwise (``local_anomaly``: the peak in µT, which
    a simulator scenario turns into a :class:`DipoleField`).  Checks the value with
    :func:`normalise_effect` (except ``local_anomaly``: a finite value ≥ 0).
    """
    if name not in EFFECTS:
        raise ValueError(f"unknown effect {name!r}; known: {', '.join(EFFECTS)}")
    s = text.strip()
    if s.lower() == "off":
        return None
    try:
        vals = np.array([float(x) for x in s.split(",")], dtype=float)
    except ValueError:
        raise ValueError(
            f"{name}: expected 'off' or comma-separated numbers ({EFFECTS[name].cli}), got {text!r}"
        ) from None
    if name == "local_anomaly":
        if vals.size != 1 or not np.isfinite(vals[0]) or vals[0] < 0:
            raise ValueError(f"local_anomaly: expected one peak strength ≥ 0 in µT, got {text!r}")
        return float(vals[0])
    value = vals[0] if vals.size == 1 else vals
    normalise_effect(name, value)
    return value


#: Number of free parameters of each effect in :func:`pack_effect` (local_anomaly has no fixed size).
EFFECT_SIZES = {
    "hard_iron": 3,
    "soft_iron": 6,
    "time_offset": 1,
    "mag_imu_misalignment": 3,
    "bias_drift": 3,
    "gyro_bias": 3,
    "noise": 3,
}


def pack_effect(name: str, value: Any) -> np.ndarray:
    """Flat parameter vector of an effect, for fitting: sizes in :data:`EFFECT_SIZES`, units of
    :data:`EFFECTS` (``soft_iron``: ``xx, yy, zz, xy, xz, yz``; misalignment: rotation vector, deg)."""
    if name not in EFFECT_SIZES:
        raise ValueError(f"{name}: no flat parameter form (packable: {', '.join(EFFECT_SIZES)})")
    v = normalise_effect(name, value)
    if name == "soft_iron":
        return np.array([v[0, 0], v[1, 1], v[2, 2], v[0, 1], v[0, 2], v[1, 2]])
    return np.atleast_1d(np.array(v, dtype=float))


def unpack_effect(name: str, params) -> np.ndarray:
    """Inverse of :func:`pack_effect`: the canonical (normalised) value from a flat vector."""
    p = np.asarray(params, dtype=float).reshape(-1)
    if name not in EFFECT_SIZES or p.size != EFFECT_SIZES[name]:
        raise ValueError(f"{name}: expected {EFFECT_SIZES.get(name, '?')} parameters, got {p.size}")
    return normalise_effect(name, p[0] if name == "time_offset" else p)


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
        from pdr_mag.calibration.model import MagCalibration

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
            eff["local_anomaly"] = DipoleField.from_json(eff["local_anomaly"])
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
