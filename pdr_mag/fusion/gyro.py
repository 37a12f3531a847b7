"""Prediction with the gyroscope, and the zero-rate update while the device is still.

Prediction, per gyroscope sample after an interval Δt::

    q ← q ⊗ Exp((ω̄ − b) Δt)          ω̄ the mean of this and the previous raw rate
    P ← Φ P Φᵀ + Q
    Φ = [[I, −R Δt, 0, 0], [0, I, 0, 0], [0, 0, φ, 0], [0, 0, 0, I]],   φ = exp(−Δt / τ_c − |ω̄_up| Δt / θ_c)
    Q = diag(σ_g² Δt I, σ_b² Δt I, σ_c² (1 − φ²), σ_o² Δt I)
    c ← φ c
    U ← Φ U Φᵀ + diag(0, 0, V_u (1 − φ²))    (at its next use: pdr_mag.fusion.eskf.settle_u)

with ``R = R(q)`` (the attitude error is in the world frame, the bias in the device frame, so a bias
error turns the attitude by ``−R δb Δt``), σ_g ``gyro.noise``, σ_b ``gyro.bias_rw``, and ``c`` a first-order
Gauss–Markov process (τ_c ``mag.error_tau_s``, stationary σ_c ``mag.error_std_deg``): the heading error
of a calibrated magnetometer indoors — residual calibration error, the building's own field — is
correlated over seconds, and modelling it keeps the filter from reading its slow drift as gyro bias.  It
decorrelates as the device turns too (θ_c ``mag.error_turn_deg``): a walker who turns leaves the anomaly
walked along.  The calibration's offset error ``o`` (device frame, µT; σ_o ``mag.offset_rw_uT``) is
constant but for a slow random walk (``mag.offset_states``; :mod:`pdr_mag.fusion.mag`).  ``ω̄_up`` is
the rate about the world's up averaged over :data:`TURN_TAU_S` (``turn_rate``), so the yaw a stride swings
back and forth cancels and only the walker's net turning counts.
``U`` is the consider covariance (:mod:`pdr_mag.fusion.eskf`): the error that the part ``V_u`` of c's
stationary variance the filter's weighting leaves out causes (:func:`unmodelled_var`).
An unknown heading is uniform: ``P[δθ_z, δθ_z]`` is capped at π² by scaling its row and column (which
keeps ``P`` positive semi-definite).

Gaps.  Up to ``GAP_DT`` the mean rate of the two ends is the rate in between.  Longer intervals up to
``gyro.max_dt`` are integrated the same way, but the rate in between deviates from that mean by about the
recent motion level, so each attitude variance grows by ``var(ω) (Δt − GAP_DT)²``; longer still, the interval
is not integrated (only ``P`` is propagated) and the unknown rotation ``(|ω̄|² + var(ω)) Δt²`` is added — a
0.25-s gap of a phone turning at 2 rad/s is 30° that must not be hidden from ``P``.  What a gap adds
to the tilt variances is capped at ``TILT_VAR_MAX`` (a gap's rotation is not a tilt error beyond it), the
heading's at π².

Zero-rate update.  The still detector keeps exponentially weighted means and mean square deviations of
gyroscope and accelerometer (time constant ``gyro.still_tau_s``).  While both deviations stay below
``gyro.still_gyro`` / ``gyro.still_acc`` for ``gyro.still_min_s``, every gyroscope sample observes the bias
directly, ``ω_m = b + δb + n`` (three scalar updates), with per-sample noise ``gyro.zupt_noise² / Δt`` — a
noise density, so the information per second does not depend on the gyroscope's rate.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from pdr_mag.fusion.eskf import inject, update
from pdr_mag.fusion.ew import ew_alpha
from pdr_mag.fusion.quat import rotate_body, rotation_matrix
from pdr_mag.fusion.state import BIAS, C_ERR, NX, OFFSET, TH_Z

#: gyro sample intervals longer than this are gaps (any phone gyroscope runs at ≥ 20 Hz), s
GAP_DT = 0.05
#: largest tilt-error variance a gap may add up to, rad² (30°)
TILT_VAR_MAX = (np.pi / 6.0) ** 2
#: time over which the rate about up is averaged for c's turn decorrelation, s: about a stride (a walker's
#: two steps), over which a swinging or pocketed phone's yaw oscillation averages out
TURN_TAU_S = 1.0

#: Scratch space of :func:`predict` (a one-record array made once per kernel call, rather than arrays
#: allocated per gyroscope sample): the blocks A, B, C of the old ``P``, the products ``G C`` and
#: ``G Bᵀ``, and the new cross terms with c.
PREDICT_WORK = np.dtype(
    [
        ("A", np.float64, (3, 3)),
        ("B", np.float64, (3, 3)),
        ("C", np.float64, (3, 3)),
        ("GC", np.float64, (3, 3)),
        ("GB", np.float64, (3, 3)),
        ("pac", np.float64, (3,)),
    ]
)


@njit(cache=True, error_model="numpy")
def predict(s, R, work, wx, wy, wz, dt, p):
    """Propagate record ``s`` by Δt = ``dt`` with the bias-corrected rate w (rad/s); ``R`` scratch 3×3,
    ``work`` a one-record array of :data:`PREDICT_WORK`."""
    rotate_body(s.q, wx * dt, wy * dt, wz * dt)
    rotate_body(s.q_gyro, wx * dt, wy * dt, wz * dt)
    rotation_matrix(s.q, R)
    w_up = R[2, 0] * wx + R[2, 1] * wy + R[2, 2] * wz
    s.turn_rate += ew_alpha(dt, TURN_TAU_S) * (w_up - s.turn_rate)
    x = dt / p.mag.error_tau_s
    if p.mag.error_turn_rad > 0.0:
        x += abs(s.turn_rate) * dt / p.mag.error_turn_rad
    phi = np.exp(-x)
    qc = magerr_var(s, p) * (1.0 - phi * phi)
    qo = p.mag.offset_rw_uT**2 * dt if p.mag.offset_states else 0.0
    propagate(s.P, R, work, dt, phi, p.gyro.noise**2 * dt, p.gyro.bias_rw**2 * dt, qc, qo)
    # the consider covariance: the same Φ, applied at its next use (pdr_mag.fusion.eskf.settle_u)
    for i in range(3):
        for m in range(3):
            s.u_G[i, m] -= R[i, m] * dt
    s.u_phi *= phi
    s.u_pending = True
    s.c *= phi


@njit(cache=True, error_model="numpy")
def propagate(P, R, work, dt, phi, qa, qb, qc, qo):
    """``P ← Φ P Φᵀ + diag(qa I, qb I, qc, qo I)`` with ``Φ = [[I, −R Δt, 0, 0], [0, I, 0, 0], [0, 0, φ, 0],
    [0, 0, 0, I]]``; the heading's variance capped at π² (an unknown heading is uniform)."""
    # the offset error's columns first (the rows of δb they read are Φ's identity): P[δθ, δo] ← P[δθ, δo] −
    # R Δt P[δb, δo], P[δc, δo] ← φ P[δc, δo]
    for j in range(OFFSET, OFFSET + 3):
        for i in range(3):
            s1 = 0.0
            for k in range(3):
                s1 += R[i, k] * P[3 + k, j]
            P[i, j] -= dt * s1
            P[j, i] = P[i, j]
        P[C_ERR, j] *= phi
        P[j, C_ERR] = P[C_ERR, j]
        P[j, j] += qo
    # P's rows: 0–2 δθ, 3–5 δb, 6 δc.  Blocks A (attitude), B (attitude–bias), C (bias); G = −R Δt
    scratch = work[0]
    A = scratch.A
    B = scratch.B
    C = scratch.C
    for i in range(3):
        for m in range(3):
            A[i, m] = P[i, m]
            B[i, m] = P[i, 3 + m]
            C[i, m] = P[3 + i, 3 + m]
    GC = scratch.GC  # G C
    GB = scratch.GB  # G Bᵀ
    for i in range(3):
        for m in range(3):
            s1 = 0.0
            s2 = 0.0
            for k in range(3):
                s1 += R[i, k] * C[k, m]
                s2 += R[i, k] * B[m, k]
            GC[i, m] = -dt * s1
            GB[i, m] = -dt * s2
    # cross terms with c (column 6), from the old P
    pac = scratch.pac
    for i in range(3):
        s1 = 0.0
        for k in range(3):
            s1 += R[i, k] * P[3 + k, 6]
        pac[i] = phi * (P[i, 6] - dt * s1)
    for i in range(3):
        P[3 + i, 6] = phi * P[3 + i, 6]
        P[6, 3 + i] = P[3 + i, 6]
        P[i, 6] = pac[i]
        P[6, i] = pac[i]
    P[6, 6] = phi * phi * P[6, 6] + qc
    for i in range(3):
        for m in range(3):
            gcg = 0.0
            for k in range(3):
                gcg += GC[i, k] * (-dt * R[m, k])
            a = A[i, m] + GB[i, m] + GB[m, i] + gcg
            if i == m:
                a += qa
            P[i, m] = a
            bb = B[i, m] + GC[i, m]
            P[i, 3 + m] = bb
            P[3 + m, i] = bb
            if i == m:
                P[3 + i, 3 + m] = C[i, m] + qb
    if P[TH_Z, TH_Z] > np.pi**2:  # an unknown heading is uniform
        fs = np.pi / np.sqrt(P[TH_Z, TH_Z])
        for i in range(NX):
            P[TH_Z, i] *= fs
            P[i, TH_Z] *= fs


@njit(cache=True, error_model="numpy")
def bias_prior_var(s, p):
    """Variance per axis of what is known of the gyro bias before any correction, (rad/s)²: the prior given
    to the filter (:meth:`pdr_mag.fusion.FusionCore.set_gyro_prior`: the phone's own drift estimate, a
    device store's), else ``gyro.bias0_std²`` (a raw gyroscope of unknown offset)."""
    return s.bias0_var if np.isfinite(s.bias0_var) else p.gyro.bias0_std**2


@njit(cache=True, error_model="numpy")
def magerr_var(s, p):
    """Stationary variance of c, rad²: ``σ_c² + (mag.env_k · d_env / B_h)²`` (the environment's recent
    disturbance level ``d_env``, see :mod:`pdr_mag.fusion.mag`), and without the offset states
    (``mag.offset_states``) ``g Σ_b gᵀ``, the calibration's offset covariance seen in the heading at the
    latest sample."""
    v = p.mag.error_std_rad**2 + (0.0 if p.mag.offset_states else s.cal_var)
    if p.mag.env_k > 0.0 and s.env_d2 > 0.0 and s.bh_ref > 0.0:
        v += p.mag.env_k**2 * s.env_d2 / (s.bh_ref * s.bh_ref)
    return v


@njit(cache=True, error_model="numpy")
def horizontal_ref(s):
    """The horizontal strength the place's terms are scaled by, µT: the local reference's ``B_h`` once the
    detectors have learnt it, else the reference field's ``F_ref cos I_ref`` (``F_ref`` while its dip is
    unknown); not positive (or NaN) when there is none."""
    if s.bh_ref > 0.0:
        return s.bh_ref
    return s.f_ref * np.cos(np.radians(s.dip_ref)) if np.isfinite(s.dip_ref) else s.f_ref


@njit(cache=True, error_model="numpy")
def unmodelled_var(s, p):
    """The part of c's stationary variance the filter's weighting leaves out, rad², carried in ``U``:
    ``V_u = [max(k_u² d_seen² − k_e² d_env², 0) + k_f · s_flag · d_tol² / 2] / B_h²`` (``k_u``, ``k_f``
    ``uncertainty.env_k``, ``uncertainty.flag_k``, ``k_e`` ``mag.env_k``; ``d_seen²`` the environment level of
    the samples seen, ``d_env²`` the filter's, which starts from a prior; ``s_flag`` the recent share of
    flagged samples, ``d_tol`` the detectors' tolerance as a disturbance; ``B_h`` the local reference's
    horizontal strength, or until the detectors have learnt it the reference field's ``F_ref cos I_ref``
    (``F_ref`` while its dip is unknown): the first fix of a start is made before they learn)."""
    b = horizontal_ref(s)
    if not b > 0.0:
        return 0.0
    v = max(p.uncertainty.env_k**2 * s.env_seen2 - p.mag.env_k**2 * s.env_d2, 0.0)
    if p.uncertainty.flag_k > 0.0 and s.flag_share > 0.0:
        v += p.uncertainty.flag_k * s.flag_share * 0.5 * s.flag_d2
    return v / (b * b)


@njit(cache=True, error_model="numpy")
def inflate_attitude(P, v):
    """Add v (rad²) to the variance of each attitude error; tilt capped at TILT_VAR_MAX, heading at π²."""
    for j in range(3):
        cap = np.pi**2 if j == TH_Z else TILT_VAR_MAX
        vj = min(v, max(cap - P[j, j], 0.0))
        P[j, j] += vj


@njit(cache=True, error_model="numpy")
def ew_stats_step(st, first, dt, x, y, z, tau):
    """One sample into an :data:`~pdr_mag.fusion.state.EW_STATS` record (time constant tau);
    ``first``: start it at this sample."""
    mean = st.mean
    if first:
        mean[0], mean[1], mean[2] = x, y, z
        st.var = 1.0
        return
    a = ew_alpha(dt, tau)
    dx, dy, dz = x - mean[0], y - mean[1], z - mean[2]
    st.var += a * (dx * dx + dy * dy + dz * dz - st.var)
    mean[0] += a * dx
    mean[1] += a * dy
    mean[2] += a * dz


@njit(cache=True, error_model="numpy")
def gyro_step(s, R, work, wx, wy, wz, t, p):
    """One gyroscope sample (rad/s) at time t: still statistics, prediction, zero-rate update; ``R`` scratch
    3×3, ``work`` a one-record array of :data:`PREDICT_WORK`."""
    first = not (s.have_gyro and np.isfinite(s.t_gyro))
    ew_stats_step(s.gyro_stats, first, t - s.t_gyro, wx, wy, wz, p.gyro.still_tau_s)
    if s.init > 0 and s.have_gyro:
        dt = t - s.t_gyro
        if dt > 0.0:
            ox = 0.5 * (wx + s.w_gyro[0]) - s.b[0]
            oy = 0.5 * (wy + s.w_gyro[1]) - s.b[1]
            oz = 0.5 * (wz + s.w_gyro[2]) - s.b[2]
            if dt <= p.gyro.max_dt:
                predict(s, R, work, ox, oy, oz, dt, p)
                if dt > GAP_DT:  # a gap: the rate in between is known to the recent motion level only
                    inflate_attitude(s.P, s.gyro_stats.var * (dt - GAP_DT) ** 2)
            else:  # too long to integrate: P only, and the unknown rotation meanwhile
                predict(s, R, work, 0.0, 0.0, 0.0, dt, p)
                inflate_attitude(s.P, (ox * ox + oy * oy + oz * oz + s.gyro_stats.var) * dt * dt)
        still = (s.gyro_stats.var < p.gyro.still_gyro**2) and (s.acc_stats.var < p.gyro.still_acc**2)
        if still:
            if not np.isfinite(s.still_since):
                s.still_since = t
            if t - s.still_since >= p.gyro.still_min_s:
                dx = np.zeros(NX)
                dtg = min(max(t - s.t_gyro, 1e-4), 0.1) if np.isfinite(s.t_gyro) else 0.01
                rv = p.gyro.zupt_noise**2 / dtg  # a noise density: the same information a second at any rate
                update(s, dx, BIAS, 1.0, wx - s.b[0], rv)
                update(s, dx, BIAS + 1, 1.0, wy - s.b[1], rv)
                update(s, dx, BIAS + 2, 1.0, wz - s.b[2], rv)
                inject(s, dx)
        else:
            s.still_since = np.nan
    s.w_gyro[0], s.w_gyro[1], s.w_gyro[2] = wx, wy, wz
    s.t_gyro = t
    s.have_gyro = True
