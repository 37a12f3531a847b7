"""Synthetic magnetometer data with known truth for the calibration tests and benchmark (seeded).

``m = b + L u + ε`` with ``u`` unit directions drawn over a chosen part of the sphere, ``L`` SPD (the
ellipsoid's semi-axis matrix), ``ε ~ N(0, σ²I)``.  Also the seeds' own simulation settings.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from pdr_mag.calibration.geometry import sqrtm_spd

F_UT = 50.0


def soft_iron_ellipsoid(rng: np.random.Generator, field: float = F_UT, spread: float = 0.1,
                        offset_uT: float = 100.0) -> tuple[np.ndarray, np.ndarray]:
    """A random offset (uniform in ±offset_uT) and SPD L = field·(I + spread·sym(N(0,1))) polar factor."""
    a = np.eye(3) + spread * rng.standard_normal((3, 3))
    return rng.uniform(-offset_uT, offset_uT, 3), sqrtm_spd((field * a) @ (field * a).T)


def directions(rng: np.random.Generator, n: int, cover: str = "full") -> np.ndarray:
    """Unit vectors: ``full`` sphere, ``hemi`` (z ≥ 0), ``band`` (|z| ≤ 0.5), ``planar`` (±3° about z = 0)."""
    if cover == "full":
        u = rng.standard_normal((n, 3))
        return u / np.linalg.norm(u, axis=1)[:, None]
    if cover == "hemi":
        u = directions(rng, n)
        u[:, 2] = np.abs(u[:, 2])
        return u
    if cover in ("band", "planar"):
        half = 0.5 if cover == "band" else np.sin(np.radians(3.0))
        z = rng.uniform(-half, half, n)
        ph = rng.uniform(0, 2 * np.pi, n)
        r = np.sqrt(1 - z * z)
        return np.column_stack([r * np.cos(ph), r * np.sin(ph), z])
    raise ValueError(cover)


def sample(rng, n, b, L, sigma, cover="full"):
    """(noisy samples, true points on the ellipsoid)."""
    x = b + directions(rng, n, cover) @ L.T
    return x + sigma * rng.standard_normal(x.shape), x


def seed000(noise_uT: float = 0.0, rng: np.random.Generator | None = None):
    """Seed 000 §4: H = 48 152 nT, declination −4.57°, inclination 44.57°, C_k = diag(1, 0.9, 1.2),
    α, β, γ = 1.2°, 87.6°, 87°, b_h = (700, 750, 800) nT, b_o = (900, 850, 750) nT, the given C_s;
    rotations at 1° steps about x, y, z, then about all three at once (Euler x-y-z, equal angles).

    Returns (m µT (1440, 3), true body field h µT, S, b) with ``m = S h + b`` (seed 000 eq. 4).
    """
    H = 48.152
    dec, inc = np.radians(-4.57), np.radians(44.57)
    h_w = H * np.array([np.cos(inc) * np.sin(dec), np.cos(inc) * np.cos(dec), -np.sin(inc)])
    ck = np.diag([1.0, 0.9, 1.2])
    al, be, ga = np.radians([1.2, 87.6, 87.0])
    cn = np.array([[np.sqrt(1 - np.cos(be) ** 2 - np.cos(ga) ** 2), np.cos(be), np.cos(ga)],
                   [0.0, np.cos(al), np.sin(al)], [0.0, 0.0, 1.0]])
    cs = np.array([[1.23, 0.23, 0.32], [0.23, 1.45, 0.45], [0.32, 0.45, 1.56]])
    bh = np.array([700.0, 750.0, 800.0]) / 1000.0
    bo = np.array([900.0, 850.0, 750.0]) / 1000.0
    ang = np.radians(np.arange(360.0))
    rots = [Rotation.from_rotvec(np.outer(ang, e)) for e in np.eye(3)]
    rots.append(Rotation.from_euler("xyz", np.column_stack([ang, ang, ang])))
    h = np.vstack([r.inv().apply(h_w) for r in rots])
    s = ck @ cn @ cs
    b = ck @ cn @ bh + bo
    m = h @ s.T + b
    if noise_uT:
        m = m + noise_uT * rng.standard_normal(m.shape)
    return m, h, s, b


def seed001(rng: np.random.Generator, n: int = 1000):
    """Seed 001 §3.1: norm 10, mounting angles 5°, sensitivities 0.98/1.02/0.96, offsets −3, noise
    variance 0.01.  Returns (m, β_true) with β in :func:`fit_lm9`'s order (relative to the z sensitivity).
    """
    from pdr_mag.calibration.ml import _lm9_matrix

    e = np.radians(5.0)
    k = np.array([0.98, 1.02, 0.96])
    b = np.full(3, -3.0)
    norm = 10.0
    nmat = _lm9_matrix(np.array([e, e, e, 1.0, 1.0]))
    u = directions(rng, n)
    m = (norm * u) @ (np.diag(k) @ nmat).T + b + np.sqrt(0.01) * rng.standard_normal((n, 3))
    return m, np.array([e, e, e, k[0] / k[2], k[1] / k[2], *b, norm * k[2]])


# ------------------------------------------------------------------------------ phone-like recordings
# Calibration motions through the project's simulator (pdr_mag.sim: modes, trajectory, sensor_model):
# a standing user turns the phone; the chain angles (yaw, pitch about the device x, roll about y, twist about
# z; pdr_mag.sim.kinematics) are sines, so the motion is smooth and its range is what the kind says.

#: Sites of the suite's recordings (WMM 2025): strong and steep, moderate, weak and flat fields.
SITES = {"zurich": (47.3769, 8.5417), "singapore": (1.35, 103.82), "sao_paulo": (-23.55, -46.63),
         "sydney": (-33.87, 151.21)}


def soft_iron_with_ratio(rng: np.random.Generator, ratio: float) -> np.ndarray:
    """A random SPD correction matrix with eigenvalue ratio ``ratio`` (max/min) and det 1."""
    ev = np.array([1.0, ratio ** rng.uniform(0.3, 0.7), ratio])
    ev /= np.prod(ev) ** (1.0 / 3.0)
    q = Rotation.random(random_state=rng).as_matrix()
    return (q * ev) @ q.T


def calibration_motion(kind: str, rng: np.random.Generator, amplitude: float = 1.0, wobble_deg: float = 3.0):
    """A :class:`pdr_mag.sim.modes.Mode` for a calibration motion.

    ``figure8``: the simulator's figure-8 (pitch ±75°, roll ±160°, yaw ±70°) scaled by ``amplitude``
    (below 1: partial coverage).  ``screen_up``: yaw turned all round, pitch and roll within
    ±``amplitude``·80° (the screen never faces down: a hemisphere or less of field directions).
    ``tumble``: turned end over end about the device x axis, held pointing east (the field's directions
    sweep a great circle), wobbling by ±``wobble_deg`` out of that plane.  ``yaw``: lying flat and turned
    about the vertical, tilting by ±``wobble_deg``.
    """
    from pdr_mag.sim import modes as M

    deg = np.pi / 180.0
    if kind == "figure8":
        base = M.figure8(rng)
        return M.Mode("figure8", tuple(M.Sines(f.const, tuple((amplitude * a, w, p) for a, w, p in f.terms))
                                       for f in base.angles_fn), base.offset_fn, warp=base.warp)
    ph = rng.uniform(0, 2 * np.pi, 8)
    w = 2 * np.pi * rng.uniform(0.05, 0.08)
    small = wobble_deg * deg
    if kind == "screen_up":
        angles = (M.Sines(0.0, ((200 * deg, 0.6 * w, ph[0]),)),
                  M.Sines(0.0, ((amplitude * 80 * deg, 1.7 * w, ph[1]),)),
                  M.Sines(0.0, ((amplitude * 80 * deg, 2.3 * w, ph[2]),)), M.Sines(0.0))
    elif kind == "tumble":
        angles = (M.Sines(0.0, ((small, 2.9 * w, ph[0]),)), M.Sines(0.0, ((200 * deg, w, ph[1]),)),
                  M.Sines(0.0, ((small, 4.1 * w, ph[2]),)), M.Sines(0.0))
    elif kind == "yaw":
        angles = (M.Sines(0.0, ((200 * deg, w, ph[0]),)), M.Sines(0.0, ((small, 3.3 * w, ph[1]),)),
                  M.Sines(0.0, ((small, 4.7 * w, ph[2]),)), M.Sines(0.0))
    else:
        raise ValueError(f"kind: expected figure8, screen_up, tumble or yaw, got {kind!r}")

    def offset(t):
        return np.tile([0.0, 0.35, 1.2], (len(t), 1)) + 0.05 * np.sin(w * t[:, None] + ph[3:6])

    return M.Mode(kind, angles, offset)


def phone_recording(kind: str, seed: int, duration_s: float, noise_uT: float, offset_norm_uT: float,
                    soft_ratio: float, site: str = "zurich", amplitude: float = 1.0, wobble_deg: float = 3.0,
                    disturbance_uT: float = 0.0) -> dict:
    """A simulated calibration recording with its truth.

    Hard iron of norm ``offset_norm_uT`` in a random direction, soft iron with eigenvalue ratio
    ``soft_ratio`` (:func:`soft_iron_with_ratio`), white noise ``noise_uT`` per axis, the phone's 0.15 µT
    resolution, 50 Hz with the jitter and drops of :class:`pdr_mag.sim.sensor_model.PhoneSpec`.
    ``disturbance_uT`` > 0 puts a steel dipole 0.5 m from the phone, scaled so that the field it adds
    varies by that much (RMS about its mean) as the phone moves: a field that is not constant.

    Returns a dict: ``mag`` (N, 3) raw µT, ``points`` (N, 3) noise-free raw samples of the Earth's field
    alone (on the true ellipsoid), ``offset``, ``L`` (true ellipsoid, ``m = b + L u``), ``soft_iron``,
    ``sigma`` (noise σ including the resolution), ``field`` (EarthField).
    """
    from pdr_mag.field import earth_field
    from pdr_mag.sim.sampling import sample_times
    from pdr_mag.sim.sensor_model import DipoleField, PhoneSpec, SensorModel, measure_mag, predict_mag
    from pdr_mag.sim.trajectory import Heading, Trajectory

    rng = np.random.default_rng(seed)
    r_motion, r_eff, r_t, r_n = (np.random.default_rng(s) for s in rng.bit_generator.seed_seq.spawn(4))
    lat, lon = SITES[site]
    fld = earth_field(lat, lon, 0.0, "2026-06-15")
    mode = calibration_motion(kind, r_motion, amplitude, wobble_deg)
    traj = Trajectory([mode], [], Heading(psi0=0.0), duration_s)
    d = r_eff.standard_normal(3)
    b = offset_norm_uT * d / np.linalg.norm(d)
    s = soft_iron_with_ratio(r_eff, soft_ratio)
    phone = PhoneSpec()
    effects = {"hard_iron": b, "soft_iron": s, "noise": noise_uT}
    t = sample_times(phone.mag_rate_hz, duration_s, r_t, phone.rate_error, phone.mag_jitter_s,
                     phone.drop_prob, phone.gap_rate_hz, phone.gap_max_s)
    clean = SensorModel(effects)
    if disturbance_uT > 0:
        pos = traj.position(t)
        where = pos.mean(axis=0) + 0.5 * np.array([0.6, 0.0, -0.8])
        unit = DipoleField(where[None], r_eff.standard_normal((1, 3)))
        add = unit.field_w(pos)
        scale = disturbance_uT / np.sqrt(np.mean(np.sum((add - add.mean(0)) ** 2, axis=1)))
        effects["local_anomaly"] = unit.scaled(scale)
    mag = measure_mag(SensorModel(effects), t, traj, fld, r_n, phone)
    points = predict_mag(clean, t, traj, fld)
    L = fld.strength * np.linalg.inv(s)
    return {"mag": mag, "points": points, "offset": b, "L": 0.5 * (L + L.T), "soft_iron": s,
            "sigma": float(np.sqrt(noise_uT**2 + phone.mag_step**2 / 12.0)), "field": fld, "t": t}


def truth_heading_bound(rec: dict):
    """The Cramér–Rao bound of a :func:`phone_recording` (full model at the true ellipsoid, true noise)
    as the worst-case heading error it allows: a :class:`pdr_mag.calibration.heading_error.HeadingBound`,
    and the offset bound ``sqrt(tr CRLB_bb)`` in µT."""
    from pdr_mag.calibration import crlb
    from pdr_mag.calibration.geometry import calibration_from_ellipsoid, param_names
    from pdr_mag.calibration.heading_error import heading_bound
    from pdr_mag.calibration.model import MagCalibration

    cov = crlb(rec["points"], rec["offset"], rec["L"], rec["sigma"], "full")
    soft, f = calibration_from_ellipsoid(rec["L"])
    cal = MagCalibration.from_arrays(rec["offset"], soft, field_uT=f, covariance=cov,
                                     extra={"covariance_params": param_names("full")})
    return heading_bound(cal, rec["field"].inclination_deg), float(np.sqrt(np.trace(cov[:3, :3])))


def true_heading_error_deg(rec: dict, cal, n_dirs: int = 4000) -> float:
    """The largest heading error, degrees, that calibration ``cal`` makes on the recording's true phone,
    over all field directions and headings: ``max_u |P_u (û − u)| / cos I`` (linearised in the angle)."""
    from pdr_mag.calibration.heading_error import fibonacci_directions

    u = fibonacci_directions(n_dirs)
    v = cal.apply(rec["offset"] + u @ rec["L"].T)
    v /= np.linalg.norm(v, axis=1)[:, None]
    e = v - u
    e -= np.sum(e * u, axis=1)[:, None] * u
    cos_i = np.cos(np.radians(rec["field"].inclination_deg))
    return float(np.degrees(np.linalg.norm(e, axis=1).max() / cos_i))
