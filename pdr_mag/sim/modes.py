"""Motion modes: how the phone moves relative to the walker (texting, swinging, pocket, figure-8, still).

A mode gives, as smooth analytic functions of time,

* the chain angles relative to the walking direction: ``(yaw_rel, pitch, roll, twist)`` and their rates
  (the trajectory adds ``−ψ(t)`` to the yaw, ψ being the heading of the walker, clockwise from north);
* the phone's offset from the walker's reference point in the walker frame (x right, y forward, z up), m;
* the walker's speed, m/s.

Gait numbers: step frequency 1.6–2.0 Hz (stride half that), vertical bounce ±2.5 cm (≈ 3 m/s² at the
step frequency), lateral sway ±3 cm at the stride frequency, arm swing ±35°, thigh swing ±25°.  Running
(:func:`running`, :func:`running_pocket`): steps at 2.5–3.0 Hz, 2.4–3.8 m/s, the trunk's vertical specific
force a train of ground-contact pulses peaking at 2.2–2.9 g (:func:`_run_bounce`), so a ±2 g accelerometer
clips.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from pdr_mag.conventions import GRAVITY

DEG = np.pi / 180.0


@dataclass(frozen=True)
class Sines:
    """``f(t) = const + Σ_k amp_k sin(omega_k t + phase_k)`` and its derivative."""

    const: float = 0.0
    terms: tuple[tuple[float, float, float], ...] = ()  # (amp, omega rad/s, phase rad)

    def __call__(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        v = np.full(t.shape, float(self.const))
        dv = np.zeros(t.shape)
        for amp, om, ph in self.terms:
            arg = om * t + ph
            v += amp * np.sin(arg)
            dv += amp * om * np.cos(arg)
        return v, dv


@dataclass(frozen=True)
class Mode:
    """A motion mode (see the module docstring)."""

    name: str
    angles_fn: tuple[Sines, Sines, Sines, Sines]
    offset_fn: Callable[[np.ndarray], np.ndarray]
    speed: float = 0.0
    step_hz: float = 0.0
    warp: tuple[float, float] = (0.0, 0.0)

    def _time(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """Warped time ``τ = t − (A/ω) sin ωt`` and ``τ' = 1 − A cos ωt`` (None without a warp): with A
        near 1 the motion slows to a near stop once per period 2π/ω, as a hand does between strokes."""
        a, om = self.warp
        if a == 0.0:
            return t, None
        return t - (a / om) * np.sin(om * t), 1.0 - a * np.cos(om * t)

    def angles(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Relative chain angles (N, 4) and rates (N, 4), radians, rad/s.

        Terms sharing a frequency share one sin/cos pair (``sin(ωt + φ) = sin ωt cos φ + cos ωt sin φ``).
        """
        t, dtau = self._time(t)
        base: dict[float, tuple[np.ndarray, np.ndarray]] = {}
        th = np.empty((len(t), 4))
        dth = np.empty((len(t), 4))
        for i, f in enumerate(self.angles_fn):
            v = np.full(len(t), float(f.const))
            dv = np.zeros(len(t))
            for amp, om, ph in f.terms:
                if om not in base:
                    base[om] = (np.sin(om * t), np.cos(om * t))
                sn, cs = base[om]
                cp, sp = amp * np.cos(ph), amp * np.sin(ph)
                v += sn * cp + cs * sp
                dv += om * (cs * cp - sn * sp)
            th[:, i] = v
            dth[:, i] = dv
        if dtau is not None:
            dth *= dtau[:, None]
        return th, dth

    def offset(self, t: np.ndarray) -> np.ndarray:
        """Phone offset (N, 3) in the walker frame (x right, y forward, z up), m."""
        return self.offset_fn(self._time(t)[0])


def standing(mode: Mode, t_freeze: float = 0.0) -> Mode:
    """The mode frozen at one instant: same pose and place, no motion, speed 0 (standing before a walk)."""
    th, _ = mode.angles(np.array([float(t_freeze)]))
    off = mode.offset(np.array([float(t_freeze)]))[0]

    def offset(t: np.ndarray) -> np.ndarray:
        return np.broadcast_to(off, (len(t), 3)).copy()

    return Mode(f"stand:{mode.name}", tuple(Sines(float(v)) for v in th[0]), offset)


def _u(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(rng.uniform(lo, hi))


def _ph(rng: np.random.Generator) -> float:
    return float(rng.uniform(0.0, 2.0 * np.pi))


def _gait(rng: np.random.Generator) -> tuple[float, float, float]:
    """Step frequency (Hz), step angular frequency (rad/s), speed (m/s)."""
    f = _u(rng, 1.6, 2.0)
    step_len = _u(rng, 0.62, 0.75)
    return f, 2.0 * np.pi * f, f * step_len


def _bounce(rng: np.random.Generator, w: float) -> tuple[Sines, Sines, Sines]:
    """Walker-frame (lateral, forward, vertical) trunk motion around zero."""
    a = _ph(rng)
    return (
        Sines(0.0, ((_u(rng, 0.02, 0.035), 0.5 * w, a),)),
        Sines(0.0, ((_u(rng, 0.01, 0.02), w, _ph(rng)),)),
        Sines(0.0, ((_u(rng, 0.02, 0.03), w, a), (0.006, 2.0 * w, _ph(rng)))),
    )


def texting(rng: np.random.Generator) -> Mode:
    """Walking with the phone held in front for texting: tilted ~35° up, swaying with the steps."""
    f, w, v = _gait(rng)
    lat, fwd, up = _bounce(rng, w)
    angles = (
        Sines(0.0, ((2.5 * DEG, 0.5 * w, _ph(rng)),)),
        Sines(_u(rng, 28, 42) * DEG, ((2.0 * DEG, w, _ph(rng)), (1.0 * DEG, 0.5 * w, _ph(rng)))),
        Sines(_u(rng, -3, 3) * DEG, ((3.0 * DEG, 0.5 * w, _ph(rng)),)),
        Sines(0.0, ((1.0 * DEG, 0.5 * w, _ph(rng)),)),
    )
    x0, y0, z0 = _u(rng, -0.05, 0.1), _u(rng, 0.25, 0.35), _u(rng, 1.15, 1.3)

    def offset(t: np.ndarray) -> np.ndarray:
        return np.stack([x0 + lat(t)[0], y0 + fwd(t)[0], z0 + up(t)[0]], axis=1)

    return Mode("texting", angles, offset, speed=v, step_hz=f)


def swing(rng: np.random.Generator) -> Mode:
    """Walking with the phone in the swinging hand: top down along the arm, screen sideways, ±35°."""
    f, w, v = _gait(rng)
    lat, fwd, up = _bounce(rng, w)
    amp, ph = _u(rng, 28, 40) * DEG, _ph(rng)
    swing_angle = Sines(0.0, ((amp, 0.5 * w, ph),))
    arm = _u(rng, 0.6, 0.7)
    angles = (
        Sines(0.0, ((3.0 * DEG, 0.5 * w, _ph(rng)),)),
        Sines(-90.0 * DEG, ((amp, 0.5 * w, ph),)),
        Sines(90.0 * DEG, ((4.0 * DEG, 0.5 * w, _ph(rng)),)),
        Sines(0.0, ((5.0 * DEG, 0.5 * w, _ph(rng)),)),
    )

    def offset(t: np.ndarray) -> np.ndarray:
        a = swing_angle(t)[0]
        return np.stack(
            [0.22 + lat(t)[0], fwd(t)[0] + arm * np.sin(a), 1.45 + up(t)[0] - arm * np.cos(a)], axis=1
        )

    return Mode("swing", angles, offset, speed=v, step_hz=f)


def pocket(rng: np.random.Generator) -> Mode:
    """Walking with the phone in a front trouser pocket: top up along the thigh, screen to the leg."""
    f, w, v = _gait(rng)
    lat, fwd, up = _bounce(rng, w)
    amp, ph = _u(rng, 20, 30) * DEG, _ph(rng)
    thigh = Sines(0.0, ((amp, 0.5 * w, ph),))
    along = _u(rng, 0.15, 0.25)
    angles = (
        Sines(0.0, ((6.0 * DEG, 0.5 * w, _ph(rng)),)),
        Sines(90.0 * DEG, ((amp, 0.5 * w, ph),)),
        Sines(_u(rng, 5, 12) * DEG, ((3.0 * DEG, 0.5 * w, _ph(rng)),)),
        Sines(0.0, ((2.0 * DEG, w, _ph(rng)),)),
    )

    def offset(t: np.ndarray) -> np.ndarray:
        b = thigh(t)[0]
        return np.stack(
            [0.12 + lat(t)[0], fwd(t)[0] + along * np.sin(b), 0.95 + up(t)[0] - along * np.cos(b)], axis=1
        )

    return Mode("pocket", angles, offset, speed=v, step_hz=f)


def figure8(rng: np.random.Generator) -> Mode:
    """Standing, the phone waved in figure-8s and rolled over: the calibration motion covering all
    orientations (pitch ±75°, roll ±160°, yaw ±70°; rates up to ≈ 4 rad/s), in strokes: time is warped so
    the phone nearly stops every 3.5–5 s (quasi-static moments, as a hand between strokes)."""
    fp, fr, fy = _u(rng, 0.11, 0.14), _u(rng, 0.07, 0.09), _u(rng, 0.045, 0.056)
    wp, wr, wy = 2 * np.pi * fp, 2 * np.pi * fr, 2 * np.pi * fy
    angles = (
        Sines(0.0, ((70.0 * DEG, wy, _ph(rng)),)),
        Sines(0.0, ((75.0 * DEG, wp, _ph(rng)),)),
        Sines(0.0, ((160.0 * DEG, wr, _ph(rng)), (10.0 * DEG, 3.1 * wr, _ph(rng)))),
        Sines(0.0, ((20.0 * DEG, 1.7 * wp, _ph(rng)),)),
    )
    ph1, ph2 = _ph(rng), _ph(rng)

    def offset(t: np.ndarray) -> np.ndarray:
        return np.stack(
            [
                0.2 * np.sin(wp * t + ph1),
                0.35 + 0.05 * np.sin(wr * t + ph2),
                1.2 + 0.12 * np.sin(2 * wp * t + ph1),
            ],
            axis=1,
        )

    return Mode("figure8", angles, offset, warp=(0.95, 2 * np.pi / _u(rng, 3.5, 5.0)))


def still(rng: np.random.Generator) -> Mode:
    """Lying still on a table, screen up."""
    z = _u(rng, 0.72, 0.78)
    angles = (Sines(0.0), Sines(0.0), Sines(0.0), Sines(0.0))

    def offset(t: np.ndarray) -> np.ndarray:
        out = np.zeros((len(t), 3))
        out[:, 1] = 0.3
        out[:, 2] = z
        return out

    return Mode("still", angles, offset)


def _run_gait(rng: np.random.Generator) -> tuple[float, float, float]:
    """Running: step frequency (Hz), step angular frequency (rad/s), speed (m/s)."""
    f = _u(rng, 2.5, 3.0)
    step_len = _u(rng, 0.95, 1.25)
    return f, 2.0 * np.pi * f, f * step_len


#: Harmonics of the step frequency kept in the running bounce (the contact pulse's spectrum falls as 1/n²).
RUN_HARMONICS = 8


def _run_bounce(rng: np.random.Generator, w: float) -> tuple[Sines, Sines, Sines]:
    """Walker-frame (lateral, forward, vertical) trunk motion of running.

    The vertical specific force of the trunk is the ground reaction per unit mass: a half-sine pulse of
    contact share ``D`` of the step period ``T`` and zero in flight, its mean g (the body neither rises nor
    sinks over a step), so its peak is ``P = π g / (2 D)`` (D 0.53–0.7: 2.2–2.9 g)::

        s(t) = P cos(π t / (D T))  for |t| < D T / 2,   z̈ = s − g
        s(t) = g + Σ_n A_n cos(n w t),   A_n = (2/T) P cos(π n D) · 2a / (a² − (n w)²),   a = π / (D T)
        z(t) = −Σ_n A_n / (n w)² cos(n w t)

    (first :data:`RUN_HARMONICS` harmonics).  Lateral sway ±2–3 cm at the stride frequency, fore-aft surge
    ±1–2 cm at the step frequency.
    """
    duty = _u(rng, 0.53, 0.7)
    period = 2.0 * np.pi / w
    peak = np.pi * GRAVITY / (2.0 * duty)
    a = np.pi / (duty * period)
    ph = _ph(rng)
    terms = []
    for n in range(1, RUN_HARMONICS + 1):
        b = n * w
        a_n = (2.0 / period) * peak * np.cos(np.pi * n * duty) * 2.0 * a / (a * a - b * b)
        terms.append((-a_n / (b * b), b, n * ph + 0.5 * np.pi))  # cos x = sin(x + π/2)
    return (
        Sines(0.0, ((_u(rng, 0.02, 0.03), 0.5 * w, ph),)),
        Sines(0.0, ((_u(rng, 0.01, 0.02), w, ph + _u(rng, 0.0, 0.5)),)),
        Sines(0.0, tuple(terms)),
    )


def running(rng: np.random.Generator) -> Mode:
    """Running with the phone in the hand: the forearm bent and swinging with the arm (±20–35° of pitch,
    the hand ±12–20 cm fore and aft at the stride frequency), the phone gripped top forward, screen to the
    body side (x down: rolled 75–95°)."""
    f, w, v = _run_gait(rng)
    lat, fwd, up = _run_bounce(rng, w)
    amp, ph = _u(rng, 20, 35) * DEG, _ph(rng)
    reach, lift = _u(rng, 0.12, 0.2), _u(rng, 0.04, 0.08)
    angles = (
        Sines(0.0, ((_u(rng, 8, 15) * DEG, 0.5 * w, ph + 0.5 * np.pi),)),
        Sines(_u(rng, 15, 35) * DEG, ((amp, 0.5 * w, ph), (3.0 * DEG, w, _ph(rng)))),
        Sines(_u(rng, 75, 95) * DEG, ((5.0 * DEG, 0.5 * w, _ph(rng)),)),
        Sines(0.0, ((5.0 * DEG, 0.5 * w, _ph(rng)),)),
    )
    x0, z0 = _u(rng, 0.2, 0.3), _u(rng, 1.0, 1.15)

    def offset(t: np.ndarray) -> np.ndarray:
        s = np.sin(0.5 * w * t + ph)
        return np.stack(
            [x0 + lat(t)[0], 0.15 + fwd(t)[0] + reach * s, z0 + up(t)[0] + lift * s], axis=1
        )

    return Mode("running", angles, offset, speed=v, step_hz=f)


def running_pocket(rng: np.random.Generator) -> Mode:
    """Running with the phone in a front trouser pocket: as :func:`pocket`, the thigh swinging ±35–50°
    at the stride frequency, on the running trunk."""
    f, w, v = _run_gait(rng)
    lat, fwd, up = _run_bounce(rng, w)
    amp, ph = _u(rng, 35, 50) * DEG, _ph(rng)
    thigh = Sines(0.0, ((amp, 0.5 * w, ph),))
    along = _u(rng, 0.15, 0.25)
    angles = (
        Sines(0.0, ((8.0 * DEG, 0.5 * w, _ph(rng)),)),
        Sines(90.0 * DEG, ((amp, 0.5 * w, ph),)),
        Sines(_u(rng, 5, 12) * DEG, ((4.0 * DEG, 0.5 * w, _ph(rng)),)),
        Sines(0.0, ((3.0 * DEG, w, _ph(rng)),)),
    )

    def offset(t: np.ndarray) -> np.ndarray:
        b = thigh(t)[0]
        return np.stack(
            [0.12 + lat(t)[0], fwd(t)[0] + along * np.sin(b), 0.95 + up(t)[0] - along * np.cos(b)], axis=1
        )

    return Mode("running_pocket", angles, offset, speed=v, step_hz=f)


MODES = {
    "texting": texting,
    "swing": swing,
    "pocket": pocket,
    "figure8": figure8,
    "still": still,
    "running": running,
    "running_pocket": running_pocket,
}
