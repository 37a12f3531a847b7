"""Orientation from the gyroscope and accelerometer alone (no magnetometer), for the model check.

The model check must not use the magnetometer to estimate the orientation it then predicts the
magnetometer along, so the heading reference is left free: the yaw of the estimate's world frame is
arbitrary and the fitted world field ``B_w`` absorbs it (see :mod:`pdr_mag.modelcheck.fit`).

Model (batch, vectorised)
-------------------------
1. Gyro integration with a bias ``b_g``: body-frame increments ``ΔR_i = exp((ω̄_i − b_g) Δt_i)`` with ω̄_i
   the mean of consecutive samples, chained ``R_g(t_{i+1}) = R_g(t_i) ΔR_i`` by a log-depth parallel prefix
   product of quaternions (Hillis–Steele scan), starting from the accelerometer tilt at ``t_0``.
2. Tilt from the accelerometer: the specific force rotated into the gyro frame, ``a_w = R_g a_d``, averaged
   over centred windows (walking accelerations average out) must point up; the minimal rotation ``C(t)``
   (axis horizontal, no yaw) taking the average onto ``+z`` corrects the slow tilt drift:
   ``R_wd(t) = C(t) R_g(t)``.  This is a zero-phase complementary filter: high frequencies from the gyro,
   tilt at low frequencies from the accelerometer.  The average is three moving averages in a row, of
   ``tilt_window_s`` × (1, 3/4, 3/5): a single window of length W passes a periodic acceleration of
   frequency f with gain |sinc(W f)|, up to 9 % above 0.8 Hz for W = 4 s — a hand swinging ±35° at the
   stride frequency then tilts the estimate by ≈ 5° in step with the swing; the three windows' gains
   multiply and their zeros fall at different frequencies, which leaves ≤ 0.06 % above 0.8 Hz.
3. ``b_g`` is zero unless given (or, with ``bias_from_still``, the median gyro over still stretches); a
   bias left over shows as a heading drift ``ψ̇ = up_d · δb_g`` that the ``gyro_bias`` candidate fits.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from pdr_mag.conventions import GRAVITY, quat_multiply


@dataclass(frozen=True)
class OrientationSettings:
    """Settings of :func:`estimate_orientation`.

    Attributes
    ----------
    tilt_window_s : float
        Length of the first centred averaging window of the world-frame specific force, s.
    tilt_passes : tuple of float
        Lengths of the successive moving averages, as multiples of ``tilt_window_s``.
    still_gyro : float
        Gyro norm below which (after removing the median) the device may be still, rad/s.
    still_accel : float
        Largest deviation of the specific-force norm from g while still, m/s².
    still_min_s : float
        Shortest still stretch used for the bias, s.
    bias_from_still : bool
        Estimate the gyro bias from still stretches when none is given.  Off by default: a phone held
        still in the hand still turns slowly, which such an estimate takes for bias; the baseline then
        integrates the raw gyro and a bias is left to the ``gyro_bias`` candidate to earn its place.
    """

    tilt_window_s: float = 4.0
    tilt_passes: tuple[float, ...] = (1.0, 0.75, 0.6)
    still_gyro: float = 0.05
    still_accel: float = 0.3
    still_min_s: float = 1.0
    bias_from_still: bool = False


@dataclass(frozen=True)
class OrientationTrack:
    """Orientation ``rot_wd`` at the gyro times ``t`` (quaternions w-first), with the bias used.

    ``at(t)`` interpolates (slerp); ``up_integral(t)`` gives ``∫ up_d dt`` from ``t[0]`` (for the
    heading drift of a gyro bias).
    """

    t: np.ndarray
    quat: np.ndarray
    gyro_bias: np.ndarray
    up_cumint: np.ndarray

    def rotation(self) -> Rotation:
        return Rotation.from_quat(self.quat[:, [1, 2, 3, 0]])

    def at(self, t: np.ndarray) -> Rotation:
        tt = np.clip(np.asarray(t, dtype=float), self.t[0], self.t[-1])
        return Slerp(self.t, self.rotation())(tt)

    def up_integral(self, t: np.ndarray) -> np.ndarray:
        tt = np.asarray(t, dtype=float)
        return np.column_stack([np.interp(tt, self.t, self.up_cumint[:, k]) for k in range(3)])


def _rotvec_to_quat(v: np.ndarray) -> np.ndarray:
    ang = np.linalg.norm(v, axis=-1)
    half = 0.5 * ang
    s = np.where(ang > 1e-12, np.sin(half) / np.where(ang > 1e-12, ang, 1.0), 0.5 - ang**2 / 48.0)
    return np.column_stack([np.cos(half), v * s[:, None]])


def prefix_product(q: np.ndarray) -> np.ndarray:
    """Cumulative product ``q_0 q_1 … q_i`` for every i, in ⌈log2 N⌉ vectorised steps."""
    out = np.array(q, dtype=float, copy=True)
    k = 1
    n = len(out)
    while k < n:
        out[k:] = quat_multiply(out[:-k], out[k:])
        k *= 2
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def _minimal_rotation_to_up(v: np.ndarray) -> np.ndarray:
    """w-first quaternions of the smallest rotations taking unit vectors ``v`` (N, 3) onto +z."""
    u = v / np.linalg.norm(v, axis=1, keepdims=True)
    # q = (1 + u·z, u × z) normalised; u × z = (u_y, −u_x, 0)
    q = np.column_stack([1.0 + u[:, 2], u[:, 1], -u[:, 0], np.zeros(len(u))])
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def window_mean(t: np.ndarray, x: np.ndarray, half_s: float) -> np.ndarray:
    """Centred moving average over ±half_s of irregularly sampled x (N, d) — cumulative sums."""
    c = np.vstack([np.zeros((1, x.shape[1])), np.cumsum(x, axis=0)])
    lo = np.searchsorted(t, t - half_s, side="left")
    hi = np.searchsorted(t, t + half_s, side="right")
    return (c[hi] - c[lo]) / (hi - lo)[:, None]


def still_gyro_bias(t, gyro, accel_on_gyro_t, settings: OrientationSettings = OrientationSettings()):
    """Median gyro over still stretches (rad/s), or zeros when the device never rests long enough.

    Still: over a centred window of ``still_min_s`` the gyro's standard deviation (norm over axes) stays
    below ``still_gyro`` / 5 and the specific force's below ``still_accel`` / 5, its mean norm within
    ``still_accel`` of g.  A bias is steady, so a large one (a breadboard's 0.08 rad/s) is still found.
    """
    g = np.asarray(gyro, dtype=float)
    a = np.asarray(accel_on_gyro_t, dtype=float)
    half = 0.5 * settings.still_min_s

    def wstd(x):
        m = window_mean(t, x, half)
        m2 = window_mean(t, x * x, half)
        return np.sqrt(np.clip(m2 - m * m, 0.0, None).sum(axis=1)), m

    sg, _ = wstd(g)
    sa, ma = wstd(a)
    still = (sg < settings.still_gyro / 5.0) & (sa < settings.still_accel / 5.0)
    still &= np.abs(np.linalg.norm(ma, axis=1) - GRAVITY) < settings.still_accel
    if np.count_nonzero(still) < 10:
        return np.zeros(3)
    return np.median(g[still], axis=0)


def estimate_orientation(
    t_gyro: np.ndarray,
    gyro: np.ndarray,
    t_accel: np.ndarray,
    accel: np.ndarray,
    gyro_bias: np.ndarray | None = None,
    settings: OrientationSettings = OrientationSettings(),
) -> OrientationTrack:
    """Device→world orientation from gyro + accelerometer (heading reference arbitrary).

    Parameters
    ----------
    t_gyro, gyro : ndarray (N,), (N, 3)
        Gyro times (s) and rates (rad/s, device frame).
    t_accel, accel : ndarray (M,), (M, 3)
        Accelerometer times (s) and specific force (m/s², device frame).
    gyro_bias : ndarray (3,), optional
        Bias to subtract (rad/s); by default the median over still stretches (:func:`still_gyro_bias`).
    settings : OrientationSettings

    Returns
    -------
    OrientationTrack
    """
    t = np.asarray(t_gyro, dtype=float)
    w = np.asarray(gyro, dtype=float)
    ta = np.asarray(t_accel, dtype=float)
    a = np.asarray(accel, dtype=float)
    if w.ndim != 2 or w.shape[1] != 3 or len(t) != len(w) or len(t) < 2:
        raise ValueError(f"gyro: expected (N≥2, 3) rad/s with N times, got {w.shape}")
    if a.ndim != 2 or a.shape[1] != 3 or len(ta) != len(a) or len(ta) < 2:
        raise ValueError(f"accel: expected (M≥2, 3) m/s² with M times, got {a.shape}")
    a_g = np.column_stack([np.interp(t, ta, a[:, k]) for k in range(3)])
    if gyro_bias is not None:
        bias = np.asarray(gyro_bias, dtype=float)
    elif settings.bias_from_still:
        bias = still_gyro_bias(t, w, a_g, settings)
    else:
        bias = np.zeros(3)

    wc = w - bias
    dt = np.diff(t)
    inc = _rotvec_to_quat(0.5 * (wc[1:] + wc[:-1]) * dt[:, None])
    # initial tilt from the first half second of accelerometer
    a0 = a_g[t <= t[0] + 0.5].mean(axis=0)
    q0 = _minimal_rotation_to_up(a0[None, :])[0]
    q = prefix_product(np.vstack([q0, inc]))

    # tilt correction from the averaged world-frame specific force
    rot_g = Rotation.from_quat(q[:, [1, 2, 3, 0]])
    a_w = rot_g.apply(a_g)
    a_w_mean = a_w
    for k in settings.tilt_passes:
        a_w_mean = window_mean(t, a_w_mean, 0.5 * k * settings.tilt_window_s)
    corr = _minimal_rotation_to_up(a_w_mean)
    q = quat_multiply(corr, q)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)

    # ∫ up_d dt (trapezoid) with up_d = R_dw e_z = third row of R_wd
    up_d = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()[:, 2, :]
    cum = np.vstack([np.zeros((1, 3)), np.cumsum(0.5 * (up_d[1:] + up_d[:-1]) * dt[:, None], axis=0)])
    return OrientationTrack(t=t, quat=q, gyro_bias=np.asarray(bias, float), up_cumint=cum)


def track_from_truth(t: np.ndarray, q_wxyz: np.ndarray) -> OrientationTrack:
    """An :class:`OrientationTrack` from ``truth.csv`` (evaluation mode only)."""
    t = np.asarray(t, dtype=float)
    q = np.asarray(q_wxyz, dtype=float)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    up_d = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()[:, 2, :]
    dt = np.diff(t)
    cum = np.vstack([np.zeros((1, 3)), np.cumsum(0.5 * (up_d[1:] + up_d[:-1]) * dt[:, None], axis=0)])
    return OrientationTrack(t=t, quat=q, gyro_bias=np.zeros(3), up_cumint=cum)
