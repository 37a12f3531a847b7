"""Scenarios: named trajectories, their steel layouts and the default effects of a typical phone.

Default effects (every scenario; ``--effect NAME=off`` removes one)::

    hard_iron  = (22, −31, 48) µT                           a typical phone's own magnetisation
    soft_iron  = [[1.04, 0.02, −0.01], [0.02, 0.97, 0.015], [−0.01, 0.015, 1.0]]   (correction matrix)
    gyro_bias  = (0.6, −0.8, 0.5) °/s = (0.01047, −0.01396, 0.00873) rad/s
    noise      = 0.4 µT
    local_anomaly = 30 µT peak           mixed and chain only (a steel area on the walk)
    local_anomaly = 250 µT peak          steel (a dense steel area hiding the Earth's field for a minute)

``time_offset``, ``mag_imu_misalignment`` and ``bias_drift`` are off by default.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from pdr_mag.sim import modes as M
from pdr_mag.sim.sensor_model import DipoleField
from pdr_mag.sim.trajectory import Heading, Trajectory

DEG = np.pi / 180.0

#: Range of each laid-out steel dipole, m (see :class:`~pdr_mag.sim.sensor_model.DipoleField`).
DIPOLE_CUTOFF_M = 25.0

DEFAULT_EFFECTS: dict[str, object] = {
    "hard_iron": (22.0, -31.0, 48.0),
    "soft_iron": ((1.04, 0.02, -0.01), (0.02, 0.97, 0.015), (-0.01, 0.015, 1.0)),
    "gyro_bias": tuple(round(float(v), 6) for v in np.radians([0.6, -0.8, 0.5])),
    "noise": 0.4,
}


@dataclass(frozen=True)
class Plan:
    """A built scenario: the trajectory, its segments and where the steel areas are (time windows).

    ``steel_spacing_m``, ``steel_lateral_m``, ``steel_height_m``: ranges of the distance between steel
    dipoles along the path, of their distance to the side of it and of their height; ``steel_aligned``:
    the dipoles' moments share one direction (±0.3 rad scatter), as in one large structure magnetised by
    the ambient field, instead of independent random directions (:func:`layout_dipoles`).
    """

    trajectory: Trajectory
    segments: list[tuple[str, float, float]]
    anomaly_windows: list[tuple[float, float]]
    steel_spacing_m: tuple[float, float] = (1.5, 3.0)
    steel_lateral_m: tuple[float, float] = (0.9, 2.0)
    steel_height_m: tuple[float, float] = (0.0, 2.8)
    steel_aligned: bool = False


@dataclass(frozen=True)
class Scenario:
    name: str
    description: str
    default_duration_s: float
    build: Callable[[float, np.random.Generator], Plan]
    default_effects: dict = field(default_factory=dict)


def _turns(rng: np.random.Generator, windows: list[tuple[float, float]], zigzag: bool = False) -> np.ndarray:
    """Random turns (t_center, dpsi, duration) inside walking windows, every 8–20 s.

    ``zigzag``: ±45/90° turns of alternating sign, so the walk keeps its general direction and never
    comes back (a steel area is passed once); otherwise any of ±45, ±90, 180°.
    """
    rows = []
    sign = 1.0
    for a, b in windows:
        t = a + rng.uniform(6.0, 12.0)
        while t < b - 4.0:
            if zigzag:
                d = sign * rng.choice([45.0, 90.0])
                sign = -sign
            else:
                d = rng.choice([90.0, -90.0, 45.0, -45.0, 180.0, 90.0, -90.0])
            dur = 1.5 + abs(d) / 90.0 * rng.uniform(0.6, 1.0)
            rows.append((t, d * DEG, dur))
            t += rng.uniform(8.0, 20.0)
    return np.asarray(rows, dtype=float).reshape(-1, 3)


def _wander(rng: np.random.Generator) -> np.ndarray:
    return np.array(
        [[rng.uniform(2.0, 4.0) * DEG, 2 * np.pi / rng.uniform(15.0, 30.0), rng.uniform(0, 2 * np.pi)]]
    )


def _plan(
    rng: np.random.Generator,
    duration: float,
    parts: list[tuple[str, float]],
    steel: list[tuple[float, float]] = (),
    zigzag: bool = False,
    **layout,
) -> Plan:
    """Modes in sequence with given durations (scaled to ``duration``); turns on walking parts."""
    total = sum(p[1] for p in parts)
    scale = duration / total
    modes, bounds, segs, walking = [], [], [], []
    t = 0.0
    cache: dict[str, M.Mode] = {}
    for i, (name, d) in enumerate(parts):
        kind = name.removeprefix("stand:")
        if kind not in cache:  # the same person: one gait per mode kind
            cache[kind] = M.MODES[kind](rng)
        if name not in cache:
            cache[name] = M.standing(cache[kind])
        modes.append(cache[name])
        t1 = duration if i == len(parts) - 1 else t + d * scale
        segs.append((name, round(t, 6), round(t1, 6)))
        if cache[name].speed > 0:
            walking.append((t, t1))
        if i < len(parts) - 1:
            bounds.append(t1)
        t = t1
    heading = Heading(
        psi0=float(rng.uniform(0, 2 * np.pi)),
        turns=_turns(rng, walking, zigzag),
        wander=_wander(rng) if walking else np.zeros((0, 3)),
    )
    traj = Trajectory(modes, bounds, heading, duration)
    windows = [(round(a * scale, 6), round(b * scale, 6)) for a, b in steel]
    return Plan(traj, segs, windows, **layout)


def _single(mode: str) -> Callable[[float, np.random.Generator], Plan]:
    def build(duration: float, rng: np.random.Generator) -> Plan:
        return _plan(rng, duration, [(mode, duration)])

    return build


def _walking(mode: str) -> Callable[[float, np.random.Generator], Plan]:
    """Standing still in the mode's pose for min(3 s, 10 %), then walking."""

    def build(duration: float, rng: np.random.Generator) -> Plan:
        stand = min(3.0, 0.1 * duration)
        return _plan(rng, duration, [(f"stand:{mode}", stand), (mode, duration - stand)])

    return build


def _mixed(duration: float, rng: np.random.Generator) -> Plan:
    f8 = min(25.0, 0.3 * duration)
    walk = duration - f8
    return _plan(
        rng,
        duration,
        [("figure8", f8), ("texting", walk)],
        steel=[(f8 + 0.4 * walk, f8 + 0.7 * walk)],
        zigzag=True,
    )


def _chain(duration: float, rng: np.random.Generator) -> Plan:
    # calibrate 20, walk 90 (steel 30..60 of it), recalibrate 20, walk out 50 — scaled to the duration
    return _plan(
        rng,
        duration,
        [("figure8", 20.0), ("texting", 90.0), ("figure8", 20.0), ("texting", 50.0)],
        steel=[(50.0, 80.0)],
        zigzag=True,
    )


def _steel(duration: float, rng: np.random.Generator) -> Plan:
    # a texting walk of 120 s (3 s standing first); 30..90 s of it along steel shelving at the phone's
    # height, magnetised as one structure: dipoles every 0.3–0.6 m, 0.6–1.0 m to either side, 0.8–1.6 m
    # high, so the anomaly at the phone exceeds the Earth's horizontal field almost all along — a minute
    # without a heading reference; zigzag turns, so the area is passed once; scaled to the duration
    return _plan(
        rng,
        duration,
        [("stand:texting", 3.0), ("texting", 117.0)],
        steel=[(30.0, 90.0)],
        zigzag=True,
        steel_spacing_m=(0.3, 0.6),
        steel_lateral_m=(0.6, 1.0),
        steel_height_m=(0.8, 1.6),
        steel_aligned=True,
    )


SCENARIOS: dict[str, Scenario] = {
    s.name: s
    for s in (
        Scenario(
            "figure8",
            "standing, calibration figure-8 strokes covering all orientations, brief pauses",
            60.0,
            _single("figure8"),
        ),
        Scenario(
            "walk",
            "3 s standing, then walking with the phone held for texting; steps 1.6–2 Hz, turns, sway",
            120.0,
            _walking("texting"),
        ),
        Scenario(
            "swing",
            "3 s standing, then walking, phone swinging in the hand (±28–40° at the stride frequency)",
            120.0,
            _walking("swing"),
        ),
        Scenario(
            "pocket",
            "3 s standing, then walking with the phone in a front trouser pocket",
            120.0,
            _walking("pocket"),
        ),
        Scenario(
            "run",
            "3 s standing, then running with the phone in the hand; steps 2.5–3 Hz, contact peaks 2.2–2.9 g",
            120.0,
            _walking("running"),
        ),
        Scenario(
            "run_pocket",
            "3 s standing, then running with the phone in a front trouser pocket; steps 2.5–3 Hz",
            120.0,
            _walking("running_pocket"),
        ),
        Scenario("still", "phone lying still on a table, screen up", 60.0, _single("still")),
        Scenario(
            "mixed",
            "figure8 calibration (25 s), then a texting walk through a steel area (40–70 % of the walk)",
            90.0,
            _mixed,
            {"local_anomaly": 30.0},
        ),
        Scenario(
            "chain",
            "calibrate → walk → steel area → walk out → recalibrate → walk "
            "(20/90/20/50 s scaled; steel 50–80 s)",
            180.0,
            _chain,
            {"local_anomaly": 30.0},
        ),
        Scenario(
            "steel",
            "a texting walk through a dense steel area hiding the Earth's field for a minute "
            "(30–90 s of 120 s, scaled)",
            120.0,
            _steel,
            {"local_anomaly": 250.0},
        ),
    )
}


def layout_dipoles(plan: Plan, peak_uT: float, rng: np.random.Generator) -> DipoleField:
    """Steel as point dipoles beside the path in the plan's steel windows, scaled so the largest |B| the
    phone meets is ``peak_uT``.

    Dipoles every ``plan.steel_spacing_m`` (1.5–3 m) of path, ``plan.steel_lateral_m`` (0.9–2 m) to the
    side (left or right), ``plan.steel_height_m`` (0–2.8 m) high, random moment directions (or one shared
    direction, ``plan.steel_aligned``), log-normal magnitudes.  Without windows
    the middle third of the recording is used; where the walker does not move, one dipole sits 0.6–0.9 m
    from the phone.
    """
    traj = plan.trajectory
    windows = plan.anomaly_windows or [(traj.t_end / 3.0, 2.0 * traj.t_end / 3.0)]
    positions = []
    for a, b in windows:
        ts = np.arange(a, b, 0.1)
        walker = traj.walker_position(ts)
        step = np.linalg.norm(np.diff(walker, axis=0), axis=1)
        dist = np.concatenate([[0.0], np.cumsum(step)])
        if dist[-1] < 1.0:
            p = traj.position(ts).mean(axis=0)
            ang = rng.uniform(0, 2 * np.pi)
            r = rng.uniform(0.6, 0.9)
            positions.append(p + [r * np.cos(ang), r * np.sin(ang), rng.uniform(-0.3, 0.0)])
            continue
        psi, _ = traj.heading(ts)
        d = rng.uniform(0.0, 1.5)
        while d < dist[-1]:
            i = int(np.searchsorted(dist, d))
            side = rng.choice([-1.0, 1.0])
            lat = side * rng.uniform(*plan.steel_lateral_m)
            right = np.array([np.cos(psi[i]), -np.sin(psi[i]), 0.0])
            positions.append(walker[i] + lat * right + [0.0, 0.0, rng.uniform(*plan.steel_height_m)])
            d += rng.uniform(*plan.steel_spacing_m)
    pos = np.asarray(positions, dtype=float).reshape(-1, 3)
    dirs = rng.standard_normal((len(pos), 3))
    if plan.steel_aligned:  # one structure magnetised along one direction (induced by the ambient field)
        dirs = np.broadcast_to(dirs[0], dirs.shape) + 0.3 * dirs
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    mom = dirs * np.exp(rng.normal(0.0, 0.5, (len(pos), 1)))
    unit = DipoleField(pos, mom, cutoff_m=DIPOLE_CUTOFF_M)
    t_all = np.arange(0.0, traj.t_end, 0.05)
    bmax = float(np.linalg.norm(unit.field_w(traj.position(t_all)), axis=1).max())
    return DipoleField(pos, mom * (peak_uT / bmax), peak_uT, DIPOLE_CUTOFF_M)
