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
3. The part of ``b_g`` the accelerometer observes is estimated from the drift of gravity in the gyro frame
   (:func:`tilt_gyro_bias`), on top of a start value that is zero unless given (or, with
   ``bias_from_still``, the median gyro over still stretches).  Step 2 corrects the tilt *after* the
   integration, so without it a bias across the up axis tilts ``R_g`` without bound (1°/s: 120° in two
   minutes), and the minimal rotation that takes such a tilt back turns the heading by an amount that is
   no function of ``∫up_d dt`` — which the ``gyro_bias`` candidate's heading drift then cannot fit.
   It is applied direction by direction, where significant; the component along an axis that points up
   most of the time (about which a texting walk turns) the accelerometer sees only through the phone's
   wobble, and it is left to the magnetometer: left over, it shows as a heading drift
   ``ψ̇ = up_d · δb_g`` that the ``gyro_bias`` candidate fits.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import stats
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
    bias_from_tilt : bool
        Estimate the components of the gyro bias that the accelerometer observes (:func:`tilt_gyro_bias`).
    tilt_quiet_deg : float
        Most the heading may turn within the averaging span around a time that bounds a segment of
        :func:`tilt_gyro_bias`: a walker's turn accelerates the phone toward the turn's centre for
        seconds, which the averages do not remove.
    tilt_segment_s : float
        Shortest segment of :func:`tilt_gyro_bias`, s.
    tilt_max_std : float
        Largest 1-σ, rad/s, of a direction of the bias that :func:`tilt_gyro_bias` estimates; a less
        well observed direction (the up axis of a walk) is left at its start value.
    tilt_up_share, tilt_up_exclude_deg : float
        When one device axis points up (within 25°) for at least ``tilt_up_share`` of the recording (a
        walk, a calibration followed by a walk), the directions within ``tilt_up_exclude_deg`` of it are
        not the accelerometer's: it sees them mostly through the phone's wobble, a short lever whose
        errors the jackknife understates (12 σ on a 2.5-min calibration + walk), while the magnetometer
        sees them directly, as a heading drift.
    tilt_false_alarm : float
        Probability that :func:`tilt_gyro_bias` applies an estimate when there is no bias.
    tilt_max_std_ratio : float
        Largest 1-σ of an estimated direction as a multiple of the best one's: a direction seen only
        through a small lever (the up axis of a walk, through the phone's wobble) is not trusted.  The
        directions across a texting walk's up axis differ by up to 8×; its up axis by 50×.
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
    bias_from_tilt: bool = True
    tilt_quiet_deg: float = 10.0
    tilt_segment_s: float = 4.0
    tilt_max_std: float = 0.002
    tilt_max_std_ratio: float = 20.0
    tilt_up_share: float = 0.5
    tilt_up_exclude_deg: float = 30.0
    tilt_false_alarm: float = 1e-3


@dataclass(frozen=True)
class TiltBias:
    """What the accelerometer says of the gyro bias (:func:`tilt_gyro_bias`).

    Attributes
    ----------
    correction : ndarray (3,)
        Added to the start value, rad/s (device axes); zero along the directions not estimated.
    information : ndarray (3, 3)
        Information of the bias from the accelerometer, (rad/s)⁻²: the inverse of the segments'
        jackknife covariance (zero along what they leave undetermined).
    estimated : ndarray (k, 3)
        Unit directions (device axes) along which the estimate was applied (well observed and
        significant, :func:`tilt_gyro_bias`).
    observed : ndarray (m, 3)
        Unit directions the accelerometer observes well (1-σ within ``tilt_max_std`` and
        ``tilt_max_std_ratio``), applied or not: the bias left along them is known to be near zero.
        Along the others it is the magnetometer's to find.
    n_segments : int
        Segments between quiet times that entered the regression.
    t2, threshold : float
        The estimate is applied along each of those directions where it is significant on its own:
        ``t² = (v·δ)²/σ_v²`` (σ_v² the jackknife variance) beyond Student's ``t²`` at ``α/2k`` two-sided
        (α = ``tilt_false_alarm``, Bonferroni over the k directions) with as many degrees of freedom as
        segments carry the direction (``(Σh)²/Σh²``, ``h_i = |A_i v|²``), less one — the jackknife's own
        randomness counted, so a direction few segments carry needs a stronger drift (the up axis of a
        10-min calibration + walk, carried by the walk's wobble, came out 0.0011 rad/s at 2 σ: with a
        joint test over the three directions it was applied, a 38° heading drift for the magnetometer
        to undo).  ``t2`` and ``threshold`` are those of the direction
        closest to (or furthest beyond) its threshold.
    """

    correction: np.ndarray
    information: np.ndarray
    estimated: np.ndarray
    n_segments: int
    t2: float = 0.0
    threshold: float = float("inf")
    observed: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))

    @property
    def significant(self) -> bool:
        """Whether the accelerometer saw a bias (and its estimate was applied, in one direction at least)."""
        return bool(self.t2 > self.threshold)

    @property
    def prior_information(self) -> np.ndarray:
        """The information within the well-observed directions, (rad/s)⁻²: a prior on what is left of
        the bias there, centred at zero — where the estimate was applied, and where it was not
        significant.  Along a direction seen only through a short lever (a walk's up axis) it would
        hold the magnetometer's heading drift back to a poor estimate."""
        proj = self.observed.T @ self.observed
        return proj @ self.information @ proj

    @staticmethod
    def none() -> TiltBias:
        return TiltBias(np.zeros(3), np.zeros((3, 3)), np.zeros((0, 3)), 0)


@dataclass(frozen=True)
class OrientationTrack:
    """Orientation ``rot_wd`` at the gyro times ``t`` (quaternions w-first), with the bias used.

    ``at(t)`` interpolates (slerp); ``up_integral(t)`` gives ``∫ up_d dt`` from ``t[0]`` (for the
    heading drift of a gyro bias).  ``tilt_bias``: what the accelerometer contributed to ``gyro_bias``.
    """

    t: np.ndarray
    quat: np.ndarray
    gyro_bias: np.ndarray
    up_cumint: np.ndarray
    tilt_bias: TiltBias = field(default_factory=TiltBias.none)

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


def _integrate(t: np.ndarray, w: np.ndarray, a_g: np.ndarray) -> np.ndarray:
    """Gyro-only orientation ``R_g`` (w-first quaternions) from the accelerometer tilt at ``t_0``."""
    dt = np.diff(t)
    inc = _rotvec_to_quat(0.5 * (w[1:] + w[:-1]) * dt[:, None])
    a0 = a_g[t <= t[0] + 0.5].mean(axis=0)
    q0 = _minimal_rotation_to_up(a0[None, :])[0]
    return prefix_product(np.vstack([q0, inc]))


def _smooth(t: np.ndarray, x: np.ndarray, settings: OrientationSettings) -> np.ndarray:
    """The successive centred moving averages of step 2 (module docstring)."""
    for k in settings.tilt_passes:
        x = window_mean(t, x, 0.5 * k * settings.tilt_window_s)
    return x


def _skew(v: np.ndarray) -> np.ndarray:
    """``[v]×`` for rows of v (N, 3) → (N, 3, 3)."""
    out = np.zeros((len(v), 3, 3))
    out[:, 0, 1], out[:, 0, 2], out[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    out[:, 1, 0], out[:, 2, 0], out[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
    return out


def tilt_gyro_bias(t: np.ndarray, gyro: np.ndarray, a_g: np.ndarray, bias: np.ndarray,
                   settings: OrientationSettings = OrientationSettings()) -> TiltBias:
    """The correction to a gyro bias ``bias`` that the accelerometer observes, by least squares.

    Model: the gyro-only orientation ``R_g`` (integrated with ``bias``) errs by a rotation ``E`` of its
    world frame, ``R_g = E R_wd``, that a bias error δ drives as ``Ė = [R_g δ]× E``.  The specific force
    in that frame, ``a_w = R_g a_d = E (g e_z + a_lin)``, therefore obeys ``ȧ_w = [R_g δ]× a_w + E ȧ_lin``
    exactly, however large E grows; averaged (step 2's windows, which commute with d/dt), the walking
    accelerations' term vanishes and between two times t₀ < t₁::

        ā_w(t₁) − ā_w(t₀) = − ∫ avg([a_w]× R_g) dt · δ

    which is linear in δ.  The times are *quiet*: the heading turns by less than ``tilt_quiet_deg``
    within the averaging span around them (the median rate set aside: a bias left about the up axis turns
    the estimate steadily, a walker only now and then), so a turn's centripetal acceleration (``ω × v``,
    sustained for seconds, which the averages do not remove) has come and gone between them and cancels
    from the difference; and they lie one span inside the recording's ends, where the averages are
    centred.  The segments between successive quiet times ≥ ``tilt_segment_s`` apart are stacked,
    ``Y = A δ``, and solved by least squares; its covariance is the segments' jackknife
    (:func:`_jackknife`), and δ is applied along those of the covariance's eigenvectors where it is
    significant (:class:`TiltBias`), whose 1-σ is at most ``tilt_max_std`` and at most
    ``tilt_max_std_ratio`` times the best direction's — never along the up
    axis of a phone that only turns about it, where ``R_g δ`` stays parallel to gravity and leaves a trace
    only through the phone's wobble (±3° in a texting walk), a lever too short to trust: with a real
    Nexus 5's 3.6 °/s about that axis it came out 0.06 rad/s wrong at a jackknife σ of 0.002.
    """
    if not settings.bias_from_tilt:
        return TiltBias.none()
    q = _integrate(t, gyro - bias, a_g)
    r_g = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()
    a_w = np.einsum("nij,nj->ni", r_g, a_g)
    x = -(_skew(a_w) @ r_g).reshape(-1, 9)
    a_bar = _smooth(t, a_w, settings)
    x_bar = _smooth(t, x, settings)
    dt = np.diff(t)
    cum_x = np.vstack([np.zeros((1, 9)), np.cumsum(0.5 * (x_bar[1:] + x_bar[:-1]) * dt[:, None], axis=0)])
    span = 0.5 * settings.tilt_window_s * sum(settings.tilt_passes)
    up = a_bar / np.linalg.norm(a_bar, axis=1, keepdims=True)
    yaw_rate = np.einsum("ni,ni->n", np.einsum("nij,nj->ni", r_g, gyro - bias), up)
    yaw_rate = yaw_rate - np.median(yaw_rate)  # a bias about the up axis turns steadily: not a walker's turn
    yaw = np.concatenate([[0.0], np.cumsum(0.5 * (yaw_rate[1:] + yaw_rate[:-1]) * dt)])
    lo = np.searchsorted(t, t - span)
    hi = np.clip(np.searchsorted(t, t + span), 0, len(t) - 1)
    quiet = (np.abs(yaw[hi] - yaw[lo]) < np.radians(settings.tilt_quiet_deg))
    quiet &= (t >= t[0] + span) & (t <= t[-1] - span)
    edges: list[int] = []
    for i in np.flatnonzero(quiet):
        if not edges or t[i] - t[edges[-1]] >= settings.tilt_segment_s:
            edges.append(int(i))
    if len(edges) < 3:
        return TiltBias.none()
    e = np.asarray(edges)
    y = np.diff(a_bar[e], axis=0).reshape(-1, 3)
    a = np.diff(cum_x[e], axis=0).reshape(-1, 3, 3)
    sol, cov = _jackknife(a, y)
    lam, vec = np.linalg.eigh(cov)
    std = np.sqrt(np.clip(lam, 0.0, None))
    keep = (std <= settings.tilt_max_std) & (std <= settings.tilt_max_std_ratio * std.min())
    axis = dominant_up_axis(up, r_g, settings.tilt_up_share)
    if axis is not None:
        keep &= np.abs(vec.T @ axis) < np.cos(np.radians(settings.tilt_up_exclude_deg))
    # segments that carry each direction: h_i = |A_i v|², counted as (Σh)² / Σh²
    h = np.sum((a @ vec) ** 2, axis=1)  # (segments, directions)
    support = h.sum(axis=0) ** 2 / np.maximum(np.sum(h * h, axis=0), 1e-300)
    info = (vec / np.where(lam > 0, lam, np.inf)) @ vec.T
    k = int(keep.sum())
    if k == 0:
        return TiltBias(np.zeros(3), info, np.zeros((0, 3)), len(e) - 1)
    # each direction on its own: Student's t with the segments that carry it, Bonferroni over the k
    t2 = (vec.T @ sol) ** 2 / np.where(lam > 0, lam, np.inf)
    thr = stats.t.ppf(1.0 - settings.tilt_false_alarm / (2 * k), np.maximum(support - 1.0, 1.0)) ** 2
    ratio = np.where(keep, t2 / thr, -np.inf)
    best = int(np.argmax(ratio))
    sig = keep & (t2 > thr)
    corr = vec[:, sig] @ (vec[:, sig].T @ sol)
    return TiltBias(corr, info, vec[:, sig].T.copy(), len(e) - 1, float(t2[best]), float(thr[best]),
                    vec[:, keep].T.copy())


def dominant_up_axis(up_w: np.ndarray, r_g: np.ndarray, share: float) -> np.ndarray | None:
    """The device axis that points up most of the time, or None: the mean of the up direction in device
    axes (``R_gᵀ up_w``), when at least ``share`` of the samples lie within 25° of it."""
    up_d = np.einsum("nji,nj->ni", r_g, up_w)
    m = up_d.mean(axis=0)
    m /= max(float(np.linalg.norm(m)), 1e-12)
    return m if np.mean(up_d @ m > np.cos(np.radians(25.0))) >= share else None


def _solve(a: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Least squares ``y = A δ`` over stacked segments (a: (S, 3, 3), y: (S, 3)), minimum norm along what
    the segments do not determine."""
    a2, y2 = a.reshape(-1, 3), y.ravel()
    lam, vec = np.linalg.eigh(a2.T @ a2)
    ok = lam > 1e-9 * max(lam[-1], 1e-300)
    return vec[:, ok] @ ((vec[:, ok].T @ (a2.T @ y2)) / lam[ok])


def _jackknife(a: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The estimate and its delete-one jackknife covariance over segments (Efron & Stein 1981):
    ``(S − 1)/S Σ (δ₍ᵢ₎ − δ̄)(δ₍ᵢ₎ − δ̄)ᵀ``.  Unlike ``σ² (AᵀA)⁻¹`` it holds when a direction rests on a
    few segments whose errors are not the others' (a calibration stroke's hand accelerations, which the
    averages do not remove): leaving such a segment out moves the estimate, and its variance shows it."""
    sol = _solve(a, y)
    n = len(a)
    reps = np.array([_solve(np.delete(a, i, axis=0), np.delete(y, i, axis=0)) for i in range(n)])
    d = reps - reps.mean(axis=0)
    return sol, (n - 1) / n * d.T @ d


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
        Start value of the bias (rad/s); by default zero, or the median over still stretches
        (:func:`still_gyro_bias`) with ``bias_from_still``.  What the accelerometer observes of the
        bias is then estimated on top of it (:func:`tilt_gyro_bias`; when significant, twice: the second
        pass starts where the first left the tilt nearly level).
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
    start = bias.copy()
    first = tilt = tilt_gyro_bias(t, w, a_g, bias, settings)
    bias = bias + tilt.correction
    if first.significant:  # the second pass starts where the first left the tilt nearly level
        tilt = tilt_gyro_bias(t, w, a_g, bias, settings)
        bias = bias + tilt.correction
    applied = np.vstack([first.estimated, tilt.estimated])  # the directions either pass applied
    u, sv, vt = np.linalg.svd(applied, full_matrices=False) if len(applied) else (None, np.zeros(0), None)
    applied = vt[sv > 0.5] if len(sv) else np.zeros((0, 3))  # the same plane twice: two, not three
    tilt = TiltBias(bias - start, tilt.information, applied, tilt.n_segments, first.t2, first.threshold,
                    tilt.observed)

    q = _integrate(t, w - bias, a_g)
    # tilt correction from the averaged world-frame specific force
    rot_g = Rotation.from_quat(q[:, [1, 2, 3, 0]])
    corr = _minimal_rotation_to_up(_smooth(t, rot_g.apply(a_g), settings))
    q = quat_multiply(corr, q)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)

    # ∫ up_d dt (trapezoid) with up_d = R_dw e_z = third row of R_wd
    dt = np.diff(t)
    up_d = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()[:, 2, :]
    cum = np.vstack([np.zeros((1, 3)), np.cumsum(0.5 * (up_d[1:] + up_d[:-1]) * dt[:, None], axis=0)])
    return OrientationTrack(t=t, quat=q, gyro_bias=np.asarray(bias, float), up_cumint=cum, tilt_bias=tilt)


def track_from_truth(t: np.ndarray, q_wxyz: np.ndarray) -> OrientationTrack:
    """An :class:`OrientationTrack` from ``truth.csv`` (evaluation mode only)."""
    t = np.asarray(t, dtype=float)
    q = np.asarray(q_wxyz, dtype=float)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    up_d = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()[:, 2, :]
    dt = np.diff(t)
    cum = np.vstack([np.zeros((1, 3)), np.cumsum(0.5 * (up_d[1:] + up_d[:-1]) * dt[:, None], axis=0)])
    return OrientationTrack(t=t, quat=q, gyro_bias=np.zeros(3), up_cumint=cum)
