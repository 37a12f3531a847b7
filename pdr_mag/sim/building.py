"""A building's own magnetic field, and fields summed: ``local_anomaly`` values of the simulator.

Steel areas (:class:`~pdr_mag.sim.effects.DipoleField`) turn the field by tens of µT over a few metres; a
building turns it everywhere by a little — the reinforcement of its floors, its pipes and wiring, a few µT
that vary over metres.  That weak, pervasive field is what the heading filter's field error c stands for
(:mod:`pdr_mag.fusion`: σ 6°, correlated over 5 s), and it is measured on the shared recordings (the world-
frame field through the motion-capture attitude, ``benchmarks/NOTES.md``, "A building's own field").

Model (sources outside the space walked in: below the floor or above the ceiling): a scalar potential of K
evanescent modes,

    Φ(p) = Σ_k a_k exp(−s_k |κ_k| (z − z₀)) cos(κ_k · p_h + φ_k),        B = −∇Φ,

with horizontal wave vectors ``κ_k ~ N(0, I₂ / L²)``, phases ``φ_k`` uniform, ``s_k = ±1`` (a source below
the walker: the field weakens upwards; above: downwards) and ``a_k = 2 σ_h / (√K |κ_k|)``.  Each mode is
harmonic (``∇²Φ = 0``), so B is free of curl and divergence, as a magnetic field where no current flows and
no magnetised matter is; per mode ``B_x = a κ_x e sin θ``, ``B_y = a κ_y e sin θ``, ``B_z = s a |κ| e cos θ``,
so each horizontal component has RMS ``σ_h`` at the height ``z₀`` (the vertical one √2 σ_h: half a mode's
energy is vertical) and decorrelates over about ``L`` along the walk.  A walker at speed v sees it turn the
horizontal field ``B_h`` by ``σ_h / B_h`` rad RMS, correlated over about ``L / v``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pdr_mag.sim.effects import DipoleField

#: Rows of positions evaluated at once (K modes × this many rows of temporaries).
_CHUNK = 4096


@dataclass(frozen=True, eq=False)
class BuildingField:
    """A building's own field (module docstring), a ``local_anomaly`` value.

    Attributes
    ----------
    wavevectors : (K, 2) array
        Horizontal wave vectors κ_k, rad/m (east, north).
    phases : (K,) array
        φ_k, rad.
    sides : (K,) array
        s_k: +1 a source below the walker, −1 above.
    amplitudes : (K,) array
        a_k, µT·m.
    z0_m : float
        Height at which the horizontal components have RMS ``rms_uT``, m above the floor (the walker's
        origin).
    rms_uT : float
        σ_h, µT (what it was made for; informative).
    length_m : float
        L, m (informative).
    """

    wavevectors: np.ndarray
    phases: np.ndarray
    sides: np.ndarray
    amplitudes: np.ndarray
    z0_m: float = 1.0
    rms_uT: float = float("nan")
    length_m: float = float("nan")

    def __post_init__(self) -> None:
        k = np.atleast_2d(np.asarray(self.wavevectors, dtype=float))
        n = len(k)
        names = ("phases", "sides", "amplitudes")
        parts = [np.asarray(getattr(self, a), dtype=float).reshape(-1) for a in names]
        finite = all(np.all(np.isfinite(p)) for p in parts)
        if k.shape[1] != 2 or any(len(p) != n for p in parts) or not finite:
            raise ValueError(
                f"wavevectors (K, 2), phases, sides, amplitudes (K,): expected finite values of one K, got "
                f"{k.shape}, {[p.shape for p in parts]}"
            )
        if not np.all(np.isin(parts[1], (-1.0, 1.0))):
            raise ValueError("sides: expected +1 (a source below) or −1 (above) per mode")
        object.__setattr__(self, "wavevectors", k)
        for name, p in zip(names, parts, strict=True):
            object.__setattr__(self, name, p)
        object.__setattr__(self, "z0_m", float(self.z0_m))

    @classmethod
    def random(
        cls, rms_uT: float, length_m: float, rng: np.random.Generator, n_modes: int = 128, z0_m: float = 1.0
    ) -> BuildingField:
        """A random building: horizontal RMS ``rms_uT`` (µT, at ``z0_m``) correlated over ``length_m`` m."""
        if not (np.isfinite(rms_uT) and rms_uT >= 0):
            raise ValueError(f"rms_uT: expected an RMS ≥ 0 in µT, got {rms_uT!r}")
        if not (np.isfinite(length_m) and length_m > 0):
            raise ValueError(f"length_m: expected a correlation length > 0 in m, got {length_m!r}")
        if not (isinstance(n_modes, int | np.integer) and n_modes >= 1):
            raise ValueError(f"n_modes: expected an integer ≥ 1, got {n_modes!r}")
        k = rng.standard_normal((int(n_modes), 2)) / length_m
        kn = np.maximum(np.linalg.norm(k, axis=1), 1e-9)
        phases = rng.uniform(0.0, 2.0 * np.pi, int(n_modes))
        sides = np.where(rng.random(int(n_modes)) < 0.5, 1.0, -1.0)
        amplitudes = 2.0 * rms_uT / (np.sqrt(n_modes) * kn)
        return cls(k, phases, sides, amplitudes, z0_m, float(rms_uT), float(length_m))

    def field_w(self, position_w: np.ndarray) -> np.ndarray:
        """The building's field (N, 3), µT, ENU, at positions (N, 3), m."""
        pos = np.asarray(position_w, dtype=float).reshape(-1, 3)
        out = np.empty_like(pos)
        k, kn = self.wavevectors, np.linalg.norm(self.wavevectors, axis=1)
        for i in range(0, len(pos), _CHUNK):
            p = pos[i:i + _CHUNK]
            theta = p[:, :2] @ k.T + self.phases
            amp = self.amplitudes * np.exp(-self.sides * kn * (p[:, 2:3] - self.z0_m))
            s = amp * np.sin(theta)
            out[i:i + _CHUNK, 0] = s @ k[:, 0]
            out[i:i + _CHUNK, 1] = s @ k[:, 1]
            out[i:i + _CHUNK, 2] = (amp * np.cos(theta)) @ (self.sides * kn)
        return out

    def to_json(self) -> dict:
        return {
            "kind": "building",
            "rms_uT": float(self.rms_uT),
            "length_m": float(self.length_m),
            "z0_m": self.z0_m,
            "wavevectors_rad_m": self.wavevectors.tolist(),
            "phases_rad": self.phases.tolist(),
            "sides": self.sides.tolist(),
            "amplitudes_uT_m": self.amplitudes.tolist(),
        }

    @classmethod
    def from_json(cls, obj: dict) -> BuildingField:
        return cls(
            np.asarray(obj["wavevectors_rad_m"], dtype=float),
            np.asarray(obj["phases_rad"], dtype=float),
            np.asarray(obj["sides"], dtype=float),
            np.asarray(obj["amplitudes_uT_m"], dtype=float),
            obj.get("z0_m", 1.0),
            obj.get("rms_uT", np.nan),
            obj.get("length_m", np.nan),
        )


@dataclass(frozen=True, eq=False)
class FieldSum:
    """Several external fields at once (a building's own field and its steel areas), a ``local_anomaly``
    value: ``B(p) = Σ_i parts[i].field_w(p)``."""

    parts: tuple

    def __post_init__(self) -> None:
        parts = tuple(self.parts)
        if not parts or not all(callable(getattr(p, "field_w", None)) for p in parts):
            raise ValueError(f"parts: expected field objects with field_w(position_w), got {self.parts!r}")
        object.__setattr__(self, "parts", parts)

    def field_w(self, position_w: np.ndarray) -> np.ndarray:
        out = self.parts[0].field_w(position_w)
        for p in self.parts[1:]:
            out = out + p.field_w(position_w)
        return out

    def to_json(self) -> dict:
        return {"kind": "sum", "parts": [p.to_json() for p in self.parts]}


def field_from_json(obj: dict):
    """A ``local_anomaly`` field from its ``to_json`` (``kind``: ``dipoles`` — also when absent —,
    ``building`` or ``sum``)."""
    kind = obj.get("kind", "dipoles")
    if kind == "building":
        return BuildingField.from_json(obj)
    if kind == "sum":
        return FieldSum(tuple(field_from_json(p) for p in obj["parts"]))
    if kind == "dipoles":
        return DipoleField.from_json(obj)
    raise ValueError(f"local_anomaly: unknown field kind {kind!r} (dipoles, building, sum)")
