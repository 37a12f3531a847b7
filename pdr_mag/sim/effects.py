"""The named effects of the sensor model: their units, shapes and meanings, how a value is checked and
normalised, read from ``--effect NAME=VALUE`` and packed into flat parameters for fitting; and the
``local_anomaly`` value of the simulator, a field of point dipoles.

The model that applies them is :mod:`pdr_mag.sim.sensor_model` (which re-exports these names).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

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

