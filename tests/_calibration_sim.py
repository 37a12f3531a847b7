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
