"""A smooth, physically consistent trajectory: a chain of motion modes along a walked path.

Segments ``k`` (a :class:`~pdr_mag.sim.modes.Mode` over ``[t_k, t_{k+1}]``) are blended with C² weights
that sum to one, ``w_k(t) = S((t − t_k)/B + ½) − S((t − t_{k+1})/B + ½)`` (S the quintic smoothstep, B the
blend time), so every quantity below is smooth across segment changes::

    θ(t)   = Σ_k w_k θ_k(t) + (−ψ(t), 0, 0, 0)            chain angles (see kinematics)
    θ̇(t)   = Σ_k (w_k θ̇_k + ẇ_k θ_k) + (−ψ̇, 0, 0, 0)
    v(t)   = Σ_k w_k v_k                                   walking speed along the heading ψ
    p_w(t) = ∫ v (sin ψ, cos ψ, 0) dt + Rz(−ψ) · o(t)      o = Σ_k w_k o_k: phone offset, walker frame
    a_w(t) = v̇ (sin ψ, cos ψ, 0) + v ψ̇ (cos ψ, −sin ψ, 0) + d²/dt² [Rz(−ψ) o]

The path integral is evaluated on a 100 Hz grid (cumulative trapezoid, then cubic Hermite with the exact
velocity); the second derivative of the small lever term by a central difference (h = 1 ms,
error ≈ h²/12 · |o⁗| < 1e-4 m/s²).  Orientation and body rate are exact (analytic).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pdr_mag.sim.kinematics import chain_body_rate, chain_quat, smoothstep
from pdr_mag.sim.modes import Mode

_GRID_S = 0.01
_FD_H = 1e-3


def _where(mask: np.ndarray):
    """Index for the True entries: a slice when they are contiguous (sorted times), None when none are."""
    idx = np.flatnonzero(mask)
    if not len(idx):
        return None
    if idx[-1] - idx[0] + 1 == len(idx):
        return slice(int(idx[0]), int(idx[-1]) + 1)
    return idx


@dataclass(frozen=True, eq=False)
class Heading:
    """Walker heading ψ(t), rad, clockwise from north: ``ψ0 + Σ Δψ_j S((t − t_j)/d_j + ½) + wander``.

    ``turns`` rows are ``(t_center, dpsi, duration)``, in time order and not overlapping (so at most one
    turn is in progress at a time: evaluated with one ``searchsorted``, O(N log J));
    ``wander`` rows ``(amp, omega, phase)`` sines.
    """

    psi0: float
    turns: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    wander: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))

    def __post_init__(self) -> None:
        tr = np.asarray(self.turns, dtype=float).reshape(-1, 3)
        start, end = tr[:, 0] - 0.5 * tr[:, 2], tr[:, 0] + 0.5 * tr[:, 2]
        if np.any(tr[:, 2] <= 0) or np.any(start[1:] < end[:-1]):
            raise ValueError("turns: expected positive durations, in time order, not overlapping")
        object.__setattr__(self, "turns", tr)
        object.__setattr__(self, "wander", np.asarray(self.wander, dtype=float).reshape(-1, 3))

    def __call__(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = np.asarray(t, dtype=float)
        psi = np.full(t.shape, float(self.psi0))
        dpsi = np.zeros(t.shape)
        tr = self.turns
        if len(tr):
            tc, d, dur = tr[:, 0], tr[:, 1], tr[:, 2]
            k = np.searchsorted(tc - 0.5 * dur, t, side="right") - 1  # last turn started
            started = k >= 0
            kk = np.maximum(k, 0)
            done_before = np.concatenate([[0.0], np.cumsum(d)])[kk]  # turns completed before turn k
            s, ds = smoothstep((t - tc[kk]) / dur[kk] + 0.5)
            psi += np.where(started, done_before + d[kk] * s, 0.0)
            dpsi += np.where(started, d[kk] * ds / dur[kk], 0.0)
        for amp, om, ph in self.wander:
            psi += amp * np.sin(om * t + ph)
            dpsi += amp * om * np.cos(om * t + ph)
        return psi, dpsi


@dataclass(frozen=True)
class TrajectoryState:
    """Everything at a set of times: orientation, body rate, position, linear acceleration, heading."""

    t: np.ndarray
    q_wd: np.ndarray
    omega_d: np.ndarray
    position_w: np.ndarray
    accel_w: np.ndarray


class Trajectory:
    """Modes over segments, blended, along a walked path (see the module docstring).

    Parameters
    ----------
    modes : sequence of Mode
    bounds : sequence of float
        Segment boundaries ``t_1 < … < t_{K−1}`` between consecutive modes (len(modes) − 1 values), s.
    heading : Heading
    t_end : float
        Duration, s; the path is integrated over ``[−margin, t_end + margin]``.
    blend_s : float
        Blend time B between modes, s.
    """

    def __init__(
        self, modes, bounds, heading: Heading, t_end: float, blend_s: float = 2.0, margin_s: float = 10.0
    ):
        self.modes: tuple[Mode, ...] = tuple(modes)
        self.bounds = np.asarray(bounds, dtype=float)
        if len(self.bounds) != len(self.modes) - 1:
            raise ValueError("bounds: expected len(modes) − 1 segment boundaries")
        self.heading = heading
        self.t_end = float(t_end)
        self.blend_s = float(blend_s)
        self._t0_grid = -margin_s
        n = int(np.ceil((t_end + 2 * margin_s) / _GRID_S)) + 1
        tg = self._t0_grid + _GRID_S * np.arange(n)
        v, _ = self._speed(tg)
        psi, _ = heading(tg)
        vel = np.stack([v * np.sin(psi), v * np.cos(psi)], axis=1)
        pos = np.zeros_like(vel)
        pos[1:] = np.cumsum(0.5 * (vel[1:] + vel[:-1]) * _GRID_S, axis=0)
        i0 = int(round(-self._t0_grid / _GRID_S))
        self._grid_pos = pos - pos[i0]  # walker at the origin at t = 0
        self._grid_vel = vel

    # ------------------------------------------------------------------ blending
    def weights(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Blend weights (K, N) and their time derivatives."""
        k = len(self.modes)
        w = np.zeros((k, len(t)))
        dw = np.zeros((k, len(t)))
        up = [smoothstep((t - b) / self.blend_s + 0.5) for b in self.bounds]
        for i in range(k):
            s_in, ds_in = (np.ones(len(t)), np.zeros(len(t))) if i == 0 else up[i - 1]
            s_out, ds_out = (np.zeros(len(t)), np.zeros(len(t))) if i == k - 1 else up[i]
            w[i] = s_in - s_out
            dw[i] = (ds_in - ds_out) / self.blend_s
        return w, dw

    def segment_index(self, t: np.ndarray) -> np.ndarray:
        """Index of the mode each time belongs to (boundaries at the blend centres)."""
        return np.searchsorted(self.bounds, np.asarray(t, dtype=float), side="right")

    def _speed(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        w, dw = self.weights(t)
        sp = np.array([m.speed for m in self.modes])
        return sp @ w, sp @ dw

    def _offset(self, t: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
        if w is None:
            w, _ = self.weights(t)
        out = np.zeros((len(t), 3))
        for i, m in enumerate(self.modes):
            idx = _where(w[i] > 0)
            if idx is not None:
                out[idx] += w[i, idx, None] * m.offset(t[idx])
        return out

    def _lever(self, t: np.ndarray) -> np.ndarray:
        """``Rz(−ψ) · o(t)`` in ENU."""
        o = self._offset(t)
        psi, _ = self.heading(t)
        c, s = np.cos(psi), np.sin(psi)
        # Rz(−ψ): x' = c x + s y, y' = −s x + c y
        return np.stack([c * o[:, 0] + s * o[:, 1], -s * o[:, 0] + c * o[:, 1], o[:, 2]], axis=1)

    # ------------------------------------------------------------------ queries
    def angles(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Chain angles (N, 4) and rates (N, 4)."""
        t = np.asarray(t, dtype=float)
        w, dw = self.weights(t)
        th = np.zeros((len(t), 4))
        dth = np.zeros((len(t), 4))
        for i, m in enumerate(self.modes):
            idx = _where((w[i] > 0) | (dw[i] != 0))
            if idx is not None:
                a, da = m.angles(t[idx])
                th[idx] += w[i, idx, None] * a
                dth[idx] += w[i, idx, None] * da + dw[i, idx, None] * a
        psi, dpsi = self.heading(t)
        th[:, 0] -= psi
        dth[:, 0] -= dpsi
        return th, dth

    def orientation(self, t: np.ndarray) -> np.ndarray:
        """w-first quaternions ``rot_wd`` (N, 4), device → ENU (true north)."""
        th, _ = self.angles(np.atleast_1d(t))
        return chain_quat(th)

    def omega_d(self, t: np.ndarray) -> np.ndarray:
        """Body rate (N, 3), rad/s, device axes."""
        th, dth = self.angles(np.atleast_1d(t))
        return chain_body_rate(th, dth)

    def walker_position(self, t: np.ndarray) -> np.ndarray:
        """Walker reference point (N, 3) on the floor, m, ENU (origin at t = 0)."""
        t = np.asarray(t, dtype=float)
        u = (t - self._t0_grid) / _GRID_S
        i = np.clip(np.floor(u).astype(int), 0, len(self._grid_pos) - 2)
        x = np.clip(u - i, 0.0, 1.0)[:, None]
        p0, p1 = self._grid_pos[i], self._grid_pos[i + 1]
        v0, v1 = self._grid_vel[i] * _GRID_S, self._grid_vel[i + 1] * _GRID_S
        h00 = 2 * x**3 - 3 * x**2 + 1
        h10 = x**3 - 2 * x**2 + x
        h01 = -2 * x**3 + 3 * x**2
        h11 = x**3 - x**2
        xy = h00 * p0 + h10 * v0 + h01 * p1 + h11 * v1
        return np.column_stack([xy, np.zeros(len(t))])

    def position(self, t: np.ndarray) -> np.ndarray:
        """Phone position (N, 3), m, ENU."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        return self.walker_position(t) + self._lever(t)

    def accel_w(self, t: np.ndarray) -> np.ndarray:
        """Linear acceleration of the phone (N, 3), m/s², ENU (gravity not included)."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        v, dv = self._speed(t)
        psi, dpsi = self.heading(t)
        s, c = np.sin(psi), np.cos(psi)
        a = np.stack([dv * s + v * dpsi * c, dv * c - v * dpsi * s, np.zeros(len(t))], axis=1)
        h = _FD_H
        lev = (self._lever(t + h) - 2.0 * self._lever(t) + self._lever(t - h)) / (h * h)
        return a + lev

    def state(self, t: np.ndarray) -> TrajectoryState:
        """All quantities at times ``t``."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        th, dth = self.angles(t)
        return TrajectoryState(
            t=t,
            q_wd=chain_quat(th),
            omega_d=chain_body_rate(th, dth),
            position_w=self.position(t),
            accel_w=self.accel_w(t),
        )
