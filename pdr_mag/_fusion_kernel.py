"""The compiled per-sample recursion of :class:`pdr_mag.attitude.FusionCore` (numba, ``cache=True``).

Everything the filter carries from one sample to the next lives in one float64 state vector ``st``
(layout: the ``S_*`` indices below), so a chunked run equals a single run and the state round-trips
through JSON as a plain list.  Settings arrive packed in ``p`` (``P_*`` indices, built by
:meth:`pdr_mag.attitude.FusionSettings.as_array`) and ``ip`` (:meth:`InterferenceSettings.as_array`).

Filter (error-state / multiplicative EKF, world-frame attitude error)
--------------------------------------------------------------------
Nominal state: ``q`` (device → ENU true north, w-first), gyro bias ``b`` (device frame, rad/s), and ``c``
the slowly varying error of the magnetometer heading (rad).  Error state ``δx = (δθ, δb, δc)`` (NX = 7)
with ``R_true = Exp(δθ) R`` (δθ in the world frame, so ``δθ_z`` is the heading error and
``heading_std = sqrt(P[2, 2])``), ``b_true = b + δb``, ``c_true = c + δc``.

predict (per gyro sample, Δt)
    ``q ← q ⊗ Exp((ω̄ − b) Δt)`` with ω̄ the mean of the last two gyro samples (gaps up to ``max_dt``
    too, adding ``var(ω) (Δt − GAP_DT)²`` to the attitude variance; longer gaps are not integrated and add
    ``(|ω̄|² + var(ω)) Δt²`` — a 0.25-s gap of a phone turning at 2 rad/s is 30° that must not be
    hidden from P);
    ``Φ = [[I, −R Δt, 0], [0, I, 0], [0, 0, φ]]``, ``φ = exp(−Δt/τ_c)``,
    ``Q = diag(σ_g² Δt I, σ_b² Δt I, σ_c² (1 − φ²))``, ``P ← Φ P Φᵀ + Q``; ``c ← φ c`` (first-order
    Gauss–Markov: the heading error of a calibrated magnetometer — residual calibration error, the
    building's own field — is correlated over seconds, so the filter must not read its slow drift as
    gyro bias, and the reported std stays honest).  ``P[2, 2]`` is capped at π² (unknown heading).
accelerometer (default: the specific force averaged in the almost-inertial world frame, as VQF does)
    ``ā_w ← ā_w + α (R a − ā_w)``, ``α = 1 − exp(−Δt/τ)`` (``acc_tau_s``) over **every** sample: the mean
    linear acceleration of a walking, swinging or pocketed phone over τ is Δv/τ ≈ 0, so ā_w points up
    (gating single samples before averaging biased it — a swinging arm's large samples point along the
    arm — and was why this option once did worse).  At most every ``acc_interval_s``: ``u_w = ā_w/|ā_w|
    ≈ e_z + (−δθ_y, δθ_x, 0)`` evaluated τ ago (the mean delay of the exponential window): since
    ``δθ' = −R δb``, ``δθ(t − τ) = δθ(t) + τ R δb``, so the two scalar updates have
    ``H_x = −e_δθy − τ (R row y) on δb`` and ``H_y = e_δθx + τ (R row x) on δb`` — the tilt drift of an
    unknown raw offset (4–6 °/s on real phones) is read as bias instead of being smeared over the
    average; noise ``σ_avg² + (k_a (|ā| − g)/g)²``; skipped when
    ``||ā| − g| > gate · g``.  ``acc_tau_s = 0``: per-sample updates from ``u_w = (R a)_h / g`` (the
    horizontal specific force over g, unbiased when horizontal and vertical accelerations are
    correlated), noise ``σ_a0² + (k_a (|a| − g)/g)² + (k_ω |ω|)² + var(a)/g² · τ_a/Δt_a``, skipped when
    ``||a| − g| > gate · g``.
magnetometer (calibrated, per sample, at most every ``mag_interval_s``)
    heading-only: ``ψ = atan2(m_w,x, m_w,y)`` with ``m_w = R m_d``; residual ``r = wrap(ψ − D − c)`` (D the
    declination, 0 for magnetic north) observes ``h_t·δθ_xy + δθ_z + δc`` with
    ``h_t = −(m_x m_z, m_y m_z)/B_h²`` the sensitivity of ψ to tilt errors (× tan I about north).  The tilt
    errors are *consider* states of this update (Schmidt–Kalman: in the gain and in P, never corrected),
    so a disturbed field can never tilt the attitude, yet a tilt error is not taken for a heading error
    and a later accelerometer correction of the tilt carries over to the heading through P.  (Before, the
    tilt entered as white noise ``h_t P_tilt h_tᵀ``: the same tilt error, repeated in every update, was
    averaged as if independent and ended in the heading × tan I.)  Noise
    ``σ_ψ² = σ_h² + (σ_m² + k² d_min²) / B_h²``: ``B_h`` the measured horizontal
    strength, ``d_min² = (F − F_loc)² + (F (I − I_loc))² + (F ∠cons)²`` the smallest disturbance that
    explains the deviations of strength, dip and world-frame direction from the detectors' references
    (a disturbance d turns the horizontal field by at most |d|/B_h).  Skipped while the interference
    flag (:mod:`pdr_mag.interference`) is up, when the caller disallows it, or when the innovation fails
    a χ² gate computed with the undisturbed noise (a suspect field gets less weight; it cannot widen the
    gate).  In ``d_min`` the consistency angle counts only beyond what the filter's own bias uncertainty
    explains over the detector's window: ``∠cons_d = max(∠cons − σ_b W, 0)`` (σ_b = √tr P_bb, W =
    ``consistency_window_s``).  The detector's mean world-frame field direction is rotated with every
    correction injected into the attitude (as the averaged specific force is), so ``∠cons`` measures how the
    field moved against the gyro-propagated frame — before, the mean lived in the corrected frame, and a
    disturbed field that the filter was following looked consistent (the filter hid its own evidence).
    The first usable sample sets the heading directly; the residual is then zero, so
    ``δθ_z = −(δc + h_t·δθ_xy + n)``: the heading error *is* that sample's (correlated) field error, and
    ``P[δθ_z, ·] = −P[c, ·] − h_t P[δθ_xy, ·]``, ``P[δθ_z, δθ_z] = σ_ψ² + P_cc + h_t P_tilt h_tᵀ +
    2 h_t P[δθ_xy, c]`` (before, the heading was set uncorrelated with c, so a later field with the same
    offset — a disturbance present since the start — was read as drift, i.e. as gyro bias along up).
zero-rate (per gyro sample while the device is still)
    ``ω_m = b + δb + n``: three scalar updates of the bias.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from pdr_mag.interference import (
    DET_FLAG,
    DET_MW,
    I_CONS_WIN,
    I_DIP_TOL,
    N_DET,
    detect_step,
    dip_of,
    ew_alpha,
    new_detector_state,
)

# ---------------------------------------------------------------- state layout
NX = 7  # error states: δθ (3, world), δb (3, device), c (magnetometer heading error, Gauss-Markov)
S_Q = 0  # 4: q w,x,y,z
S_B = 4  # 3: gyro bias
S_P = 96  # 49: covariance 7x7 row-major (δθ, δb, c)
S_INIT = 43  # 0 nothing, 1 tilt initialised, 2 heading initialised from the magnetometer
S_TG = 44  # time of last gyro sample
S_WG = 45  # 3: last raw gyro
S_HAVEG = 48
S_ACC = 49  # 3: last raw accel
S_TA = 52
S_HAVEA = 53
S_GMEAN = 54  # 3: EW mean of gyro (still detection)
S_GVAR = 57  # EW mean of |ω − mean|²
S_AMEAN = 58  # 3: EW mean of accel
S_AVAR = 61
S_STILL_SINCE = 62
S_NEXT_OUT = 63
S_MAGUSED = 64  # magnetometer used since last output row
S_QG = 74  # 4: gyro-only quaternion
S_D_F = 78  # diag: strength
S_D_FREF = 79
S_D_FTOL = 80
S_D_DIP = 81
S_D_DIPREF = 82
S_D_DIPTOL = 83
S_D_VAR = 84
S_D_SCORE = 85
S_TMU = 86  # time of last magnetometer update
S_FREF = 87  # reference strength (NaN = unknown)
S_DIPREF = 88  # reference inclination, deg (NaN = learn)
S_DECL = 89  # declination, rad
S_INTERF = 90  # interference seen since last output row
S_NREJ = 91  # consecutive innovation-gate rejections
S_CONS = 92  # diag: consistency angle
S_C = 95  # magnetometer heading error estimate c, rad
S_AW = 7  # 3: EW mean of the world-frame specific force (almost-inertial frame), m/s²
S_TAU = 10  # time of the last averaged accelerometer update
S_TA_PREV = 11  # time of the accelerometer sample before the last
S_TREJ = 12  # time of the last gate rejection of a clean-looking field (NaN: last one accepted)
S_DET = 13  # N_DET: the interference detectors' state (pdr_mag.interference, DET_* layout)
N_STATE = 96 + NX * NX

#: gyro sample intervals longer than this are gaps (any phone gyroscope runs at ≥ 20 Hz), s
GAP_DT = 0.05
#: largest tilt-error variance a gap may add up to, rad² (30°: the accelerometer linearisation holds)
TILT_VAR_MAX = (np.pi / 6.0) ** 2

# ---------------------------------------------------------------- settings layout
P_GYRO_NOISE = 0
P_BIAS_RW = 1
P_BIAS0 = 2
P_ACC_NOISE = 3
P_ACC_DYN = 4
P_ACC_GATE = 5
P_ACC_W = 6
P_MAG_NOISE = 7  # rad
P_MAG_NOISE_UT = 8
P_MAG_INTERVAL = 9
P_MAG_GATE = 10
P_STILL_GYRO = 11
P_STILL_ACC = 12
P_STILL_TAU = 13
P_STILL_MIN = 14
P_ZUPT_NOISE = 15
P_OUT_DT = 16
P_TILT0 = 17
P_GRAV = 18
P_MAX_DT = 19
P_MAG_DIST_K = 20
P_MAGERR_TAU = 21
P_MAGERR_STD = 22
P_MAG_CONS_K = 23
P_ACC_TAU = 24
P_ACC_INTERVAL = 25
P_ACC_AVG_NOISE = 26
P_ACC_CORR = 27
P_MAG_TILT_K = 28
P_TURN_SPEED = 29
P_TURN_CORR = 30
P_REJ_INFLATE = 31
P_MAG_DT_UNC = 32
N_PARAM = 33

# ---------------------------------------------------------------- output diag columns
D_GYRO_HEADING = 0
D_F = 1
D_FREF = 2
D_FTOL = 3
D_DIP = 4
D_DIPREF = 5
D_DIPTOL = 6
D_VAR = 7
D_SCORE = 8
D_BX = 9
D_BY = 10
D_BZ = 11
D_CONS = 12
N_DIAG = 13


def new_state() -> np.ndarray:
    st = np.zeros(N_STATE)
    st[S_Q] = 1.0
    st[S_QG] = 1.0
    for k in (
        S_AW,
        S_AW + 1,
        S_AW + 2,
        S_TAU,
        S_TA_PREV,
        S_TREJ,
        S_NEXT_OUT,
        S_TMU,
        S_FREF,
        S_DIPREF,
        S_STILL_SINCE,
        S_TG,
        S_TA,
    ):
        st[k] = np.nan
    for k in range(S_D_F, S_D_SCORE + 1):
        st[k] = np.nan
    st[S_CONS] = np.nan
    st[S_DET : S_DET + N_DET] = new_detector_state()
    return st


# ---------------------------------------------------------------- small maths
@njit(cache=True, error_model="numpy")
def _rot(st, R):
    w, x, y, z = st[S_Q], st[S_Q + 1], st[S_Q + 2], st[S_Q + 3]
    R[0, 0] = 1 - 2 * (y * y + z * z)
    R[0, 1] = 2 * (x * y - w * z)
    R[0, 2] = 2 * (x * z + w * y)
    R[1, 0] = 2 * (x * y + w * z)
    R[1, 1] = 1 - 2 * (x * x + z * z)
    R[1, 2] = 2 * (y * z - w * x)
    R[2, 0] = 2 * (x * z - w * y)
    R[2, 1] = 2 * (y * z + w * x)
    R[2, 2] = 1 - 2 * (x * x + y * y)


@njit(cache=True, error_model="numpy")
def _exp_half(vx, vy, vz):
    """Unit quaternion ``Exp(v)`` of a rotation vector v (rad), w-first."""
    a = np.sqrt(vx * vx + vy * vy + vz * vz)
    if a < 1e-12:
        c, s = 1.0, 0.5
    else:
        c, s = np.cos(0.5 * a), np.sin(0.5 * a) / a
    return c, s * vx, s * vy, s * vz


@njit(cache=True, error_model="numpy")
def _store_product(st, k, aw, ax, ay, az, bw, bx, by, bz):
    """q[k:k+4] ← normalised Hamilton product ``a ⊗ b``."""
    w = aw * bw - ax * bx - ay * by - az * bz
    x = aw * bx + ax * bw + ay * bz - az * by
    y = aw * by - ax * bz + ay * bw + az * bx
    z = aw * bz + ax * by - ay * bx + az * bw
    n = np.sqrt(w * w + x * x + y * y + z * z)
    st[k], st[k + 1], st[k + 2], st[k + 3] = w / n, x / n, y / n, z / n


@njit(cache=True, error_model="numpy")
def _qmul_right(st, k, vx, vy, vz):
    """q[k:k+4] ← q ⊗ Exp(v) (v a rotation vector in the body frame)."""
    bw, bx, by, bz = _exp_half(vx, vy, vz)
    _store_product(st, k, st[k], st[k + 1], st[k + 2], st[k + 3], bw, bx, by, bz)


@njit(cache=True, error_model="numpy")
def _qmul_left(st, k, vx, vy, vz):
    """q[k:k+4] ← Exp(v) ⊗ q (v a rotation vector in the world frame)."""
    aw, ax, ay, az = _exp_half(vx, vy, vz)
    _store_product(st, k, aw, ax, ay, az, st[k], st[k + 1], st[k + 2], st[k + 3])


@njit(cache=True, error_model="numpy")
def _heading(st, k):
    w, x, y, z = st[k], st[k + 1], st[k + 2], st[k + 3]
    r01 = 2.0 * (x * y - w * z)
    r11 = 1.0 - 2.0 * (x * x + z * z)
    return np.degrees(np.arctan2(r01, r11)) % 360.0


@njit(cache=True, error_model="numpy")
def _wrap(a):
    return (a + np.pi) % (2.0 * np.pi) - np.pi


@njit(cache=True, error_model="numpy")
def _upd(st, dx, j, s, r, rv):
    """Scalar update with H = s·e_j; r is the residual before this update (dx applied inside)."""
    _upd2(st, dx, j, s, j, 0.0, r, rv)


@njit(cache=True, error_model="numpy")
def _upd2(st, dx, j, s, j2, s2, r, rv):
    """Scalar update with H = s·e_j + s2·e_j2 (j ≠ j2 or s2 = 0); r is the residual before this update."""
    P = st[S_P : S_P + NX * NX]
    col = np.empty(NX)
    for i in range(NX):
        col[i] = s * P[i * NX + j] + s2 * P[i * NX + j2]
    r = r - s * dx[j] - s2 * dx[j2]
    S = s * col[j] + s2 * col[j2] + rv
    if S <= 0.0:
        return
    for i in range(NX):
        dx[i] += col[i] * r / S
    for i in range(NX):
        ci = col[i] / S
        for m in range(NX):
            P[i * NX + m] -= ci * col[m]


@njit(cache=True, error_model="numpy")
def _upd_h(st, dx, h, r, rv, consider_tilt, consider_heading=False):
    """Scalar update with a general H = h; with ``consider_tilt`` the tilt errors (0, 1), with
    ``consider_heading`` the heading errors (2 and c) are consider states (Schmidt–Kalman): their gain is
    zero, ``P ← P − k cᵀ − c kᵀ + S k kᵀ`` (``c = P h``; the Joseph form, valid for any gain).  r is the
    residual before this update."""
    P = st[S_P : S_P + NX * NX]
    col = np.empty(NX)
    for i in range(NX):
        v = 0.0
        for m in range(NX):
            v += P[i * NX + m] * h[m]
        col[i] = v
    S = rv
    for i in range(NX):
        S += h[i] * col[i]
        r -= h[i] * dx[i]
    if S <= 0.0:
        return
    k = np.empty(NX)
    for i in range(NX):
        k[i] = col[i] / S
    if consider_tilt:
        k[0] = 0.0
        k[1] = 0.0
    if consider_heading:
        k[2] = 0.0
        k[6] = 0.0
    for i in range(NX):
        dx[i] += k[i] * r
    for i in range(NX):
        for m in range(NX):
            P[i * NX + m] += S * k[i] * k[m] - k[i] * col[m] - col[i] * k[m]


@njit(cache=True, error_model="numpy")
def _rotvec_left(st, k, ex, ey, ez):
    """st[k:k+3] ← Exp(e) st[k:k+3] (second order in e)."""
    vx, vy, vz = st[k], st[k + 1], st[k + 2]
    cx, cy, cz = ey * vz - ez * vy, ez * vx - ex * vz, ex * vy - ey * vx
    dx, dy, dz = ey * cz - ez * cy, ez * cx - ex * cz, ex * cy - ey * cx
    st[k], st[k + 1], st[k + 2] = vx + cx + 0.5 * dx, vy + cy + 0.5 * dy, vz + cz + 0.5 * dz


@njit(cache=True, error_model="numpy")
def _inject(st, dx):
    _qmul_left(st, S_Q, dx[0], dx[1], dx[2])
    if np.isfinite(st[S_AW]):  # the averaged specific force lives in the corrected frame too
        _rotvec_left(st, S_AW, dx[0], dx[1], dx[2])
    if np.isfinite(st[S_DET + DET_MW]):  # so does the detectors' mean field direction
        _rotvec_left(st, S_DET + DET_MW, dx[0], dx[1], dx[2])
    for i in range(3):
        st[S_B + i] += dx[3 + i]
    st[S_C] += dx[6]
    for i in range(NX):
        dx[i] = 0.0
    P = st[S_P : S_P + NX * NX]
    for i in range(NX):  # keep P symmetric
        for m in range(i + 1, NX):
            v = 0.5 * (P[i * NX + m] + P[m * NX + i])
            P[i * NX + m] = v
            P[m * NX + i] = v


@njit(cache=True, error_model="numpy")
def _predict(st, R, wx, wy, wz, dt, p):
    _qmul_right(st, S_Q, wx * dt, wy * dt, wz * dt)
    _qmul_right(st, S_QG, wx * dt, wy * dt, wz * dt)
    _rot(st, R)
    P = st[S_P : S_P + NX * NX]
    # blocks A (att), B (att-bias), C (bias); G = -R dt
    A = np.empty((3, 3))
    B = np.empty((3, 3))
    C = np.empty((3, 3))
    for i in range(3):
        for m in range(3):
            A[i, m] = P[i * NX + m]
            B[i, m] = P[i * NX + 3 + m]
            C[i, m] = P[(3 + i) * NX + 3 + m]
    GC = np.empty((3, 3))  # G C
    GB = np.empty((3, 3))  # G Bᵀ
    for i in range(3):
        for m in range(3):
            s1 = 0.0
            s2 = 0.0
            for k in range(3):
                s1 += R[i, k] * C[k, m]
                s2 += R[i, k] * B[m, k]
            GC[i, m] = -dt * s1
            GB[i, m] = -dt * s2
    qa = p[P_GYRO_NOISE] ** 2 * dt
    qb = p[P_BIAS_RW] ** 2 * dt
    # c: first-order Gauss-Markov, c' = φ c + w
    phi = np.exp(-dt / p[P_MAGERR_TAU])
    # cross terms with c (column 6), from the old P
    pac = np.empty(3)
    for i in range(3):
        s1 = 0.0
        for k in range(3):
            s1 += R[i, k] * P[(3 + k) * NX + 6]
        pac[i] = phi * (P[i * NX + 6] - dt * s1)
    for i in range(3):
        P[(3 + i) * NX + 6] = phi * P[(3 + i) * NX + 6]
        P[6 * NX + 3 + i] = P[(3 + i) * NX + 6]
        P[i * NX + 6] = pac[i]
        P[6 * NX + i] = pac[i]
    P[6 * NX + 6] = phi * phi * P[6 * NX + 6] + p[P_MAGERR_STD] ** 2 * (1.0 - phi * phi)
    st[S_C] *= phi
    for i in range(3):
        for m in range(3):
            gcg = 0.0
            for k in range(3):
                gcg += GC[i, k] * (-dt * R[m, k])
            a = A[i, m] + GB[i, m] + GB[m, i] + gcg
            if i == m:
                a += qa
            P[i * NX + m] = a
            bb = B[i, m] + GC[i, m]
            P[i * NX + 3 + m] = bb
            P[(3 + m) * NX + i] = bb
            if i == m:
                P[(3 + i) * NX + 3 + m] = C[i, m] + qb
    # an unknown heading is uniform: keep its variance at most π² (scaling row and column keeps P ⪰ 0)
    if P[2 * NX + 2] > np.pi**2:
        fs = np.pi / np.sqrt(P[2 * NX + 2])
        for i in range(NX):
            P[2 * NX + i] *= fs
            P[i * NX + 2] *= fs


@njit(cache=True, error_model="numpy")
def _inflate_att(st, v):
    """Add v (rad²) to the variance of each attitude error; tilt capped at TILT_VAR_MAX, heading at π²."""
    P = st[S_P : S_P + NX * NX]
    for j in range(3):
        cap = np.pi**2 if j == 2 else TILT_VAR_MAX
        vj = min(v, max(cap - P[j * NX + j], 0.0))
        P[j * NX + j] += vj


@njit(cache=True, error_model="numpy")
def _init_tilt(st, ax, ay, az, p):
    """Attitude from one accelerometer sample, heading 0 (device +y horizontal projection to north)."""
    n = np.sqrt(ax * ax + ay * ay + az * az)
    ux, uy, uz = ax / n, ay / n, az / n
    # north = device y projected on the horizontal plane (fallback: device -z, for a phone held upright)
    d = uy
    nx, ny, nz = -d * ux, 1.0 - d * uy, -d * uz
    nn = np.sqrt(nx * nx + ny * ny + nz * nz)
    if nn < 0.2:
        d = -uz
        nx, ny, nz = -d * ux, -d * uy, -1.0 - d * uz
        nn = np.sqrt(nx * nx + ny * ny + nz * nz)
    nx, ny, nz = nx / nn, ny / nn, nz / nn
    ex, ey, ez = ny * uz - nz * uy, nz * ux - nx * uz, nx * uy - ny * ux
    # R rows = east, north, up in device coordinates
    r00, r01, r02 = ex, ey, ez
    r10, r11, r12 = nx, ny, nz
    r20, r21, r22 = ux, uy, uz
    tr = r00 + r11 + r22
    if tr > 0:
        s = np.sqrt(tr + 1.0) * 2
        w, x, y, z = 0.25 * s, (r21 - r12) / s, (r02 - r20) / s, (r10 - r01) / s
    elif r00 > r11 and r00 > r22:
        s = np.sqrt(1.0 + r00 - r11 - r22) * 2
        w, x, y, z = (r21 - r12) / s, 0.25 * s, (r01 + r10) / s, (r02 + r20) / s
    elif r11 > r22:
        s = np.sqrt(1.0 + r11 - r00 - r22) * 2
        w, x, y, z = (r02 - r20) / s, (r01 + r10) / s, 0.25 * s, (r12 + r21) / s
    else:
        s = np.sqrt(1.0 + r22 - r00 - r11) * 2
        w, x, y, z = (r10 - r01) / s, (r02 + r20) / s, (r12 + r21) / s, 0.25 * s
    qn = np.sqrt(w * w + x * x + y * y + z * z)
    st[S_Q], st[S_Q + 1], st[S_Q + 2], st[S_Q + 3] = w / qn, x / qn, y / qn, z / qn
    for k in range(4):
        st[S_QG + k] = st[S_Q + k]
    P = st[S_P : S_P + NX * NX]
    for i in range(NX * NX):
        P[i] = 0.0
    t0 = p[P_TILT0] ** 2
    P[0] = t0
    P[NX + 1] = t0
    P[2 * NX + 2] = np.pi**2
    b0 = p[P_BIAS0] ** 2
    for i in range(3, 6):
        P[i * NX + i] = b0
    P[6 * NX + 6] = p[P_MAGERR_STD] ** 2
    st[S_C] = 0.0
    st[S_INIT] = 1.0


@njit(cache=True, error_model="numpy")
def _still_stats(st, i_mean, i_var, first, dt, x, y, z, tau):
    """Exponentially weighted mean (``st[i_mean:i_mean+3]``) and mean square deviation (``st[i_var]``) of a
    vector stream, for the still detector; ``first``: start them at this sample."""
    if first:
        st[i_mean], st[i_mean + 1], st[i_mean + 2] = x, y, z
        st[i_var] = 1.0
        return
    a = ew_alpha(dt, tau)
    dx, dy, dz = x - st[i_mean], y - st[i_mean + 1], z - st[i_mean + 2]
    st[i_var] += a * (dx * dx + dy * dy + dz * dz - st[i_var])
    st[i_mean] += a * dx
    st[i_mean + 1] += a * dy
    st[i_mean + 2] += a * dz


@njit(cache=True, error_model="numpy")
def _accel(st, R, ax, ay, az, t, p):
    st[S_ACC], st[S_ACC + 1], st[S_ACC + 2] = ax, ay, az
    # still detection statistics
    first = not (st[S_HAVEA] > 0 and np.isfinite(st[S_TA]))
    _still_stats(st, S_AMEAN, S_AVAR, first, t - st[S_TA], ax, ay, az, p[P_STILL_TAU])
    st[S_TA_PREV] = st[S_TA]
    st[S_TA] = t
    st[S_HAVEA] = 1.0
    n = np.sqrt(ax * ax + ay * ay + az * az)
    if n < 1e-6:
        return
    if st[S_INIT] == 0:
        _init_tilt(st, ax, ay, az, p)
        return
    g = p[P_GRAV]
    da = abs(n - g) / g
    _rot(st, R)
    if p[P_ACC_TAU] > 0.0:
        # average the specific force in the (almost inertial) world frame: the mean linear acceleration
        # of a walking / swinging hand over the window is Δv / τ ≈ 0, so the average points up
        awx = R[0, 0] * ax + R[0, 1] * ay + R[0, 2] * az
        awy = R[1, 0] * ax + R[1, 1] * ay + R[1, 2] * az
        awz = R[2, 0] * ax + R[2, 1] * ay + R[2, 2] * az
        if not np.isfinite(st[S_AW]) or not np.isfinite(st[S_TAU]) or t - st[S_TAU] > 10.0 * p[P_ACC_TAU]:
            st[S_AW], st[S_AW + 1], st[S_AW + 2] = awx, awy, awz
            st[S_TAU] = t
            return
        a = ew_alpha(t - st[S_TA_PREV], p[P_ACC_TAU])
        st[S_AW] += a * (awx - st[S_AW])
        st[S_AW + 1] += a * (awy - st[S_AW + 1])
        st[S_AW + 2] += a * (awz - st[S_AW + 2])
        if t - st[S_TAU] < p[P_ACC_INTERVAL]:
            return
        st[S_TAU] = t
        na = np.sqrt(st[S_AW] ** 2 + st[S_AW + 1] ** 2 + st[S_AW + 2] ** 2)
        dev = abs(na - g) / g
        # every sample enters the average (gating single samples would bias it: a swinging arm's large
        # samples point along the arm); the gate applies to the average
        if dev > p[P_ACC_GATE]:
            return
        rv = p[P_ACC_AVG_NOISE] ** 2 + (p[P_ACC_DYN] * dev) ** 2
        # the average lags by τ (the mean delay of the exponential window): it observes the tilt error of
        # τ ago, δθ(t − τ) = δθ(t) + τ R δb (δθ' = −R δb), so H carries the bias error too — the tilt drift
        # of an unknown offset is then read as bias, not smeared over the average
        tau = p[P_ACC_TAU]
        hx = np.zeros(NX)
        hy = np.zeros(NX)
        hx[1] = -1.0
        hy[0] = 1.0
        for m in range(3):
            hx[3 + m] = -tau * R[1, m]
            hy[3 + m] = tau * R[0, m]
        dx = np.zeros(NX)
        # an unknown heading (before the first magnetometer sample) stays unknown: through the bias terms
        # the linearised update would otherwise shrink its (capped, uniform) variance
        unknown = st[S_INIT] < 2
        _upd_h(st, dx, hx, st[S_AW] / na, rv, False, unknown)
        _upd_h(st, dx, hy, st[S_AW + 1] / na, rv, False, unknown)
        _inject(st, dx)
        return
    else:
        if da > p[P_ACC_GATE]:
            return
        wx, wy, wz = st[S_WG] - st[S_B], st[S_WG + 1] - st[S_B + 1], st[S_WG + 2] - st[S_B + 2]
        wn = np.sqrt(wx * wx + wy * wy + wz * wz)
        # linear acceleration: its recent variance, correlated over acc_corr_s, spread over the samples
        dta = t - st[S_TA_PREV] if np.isfinite(st[S_TA_PREV]) else 0.01
        dta = min(max(dta, 1e-4), 0.1)
        rv = (
            p[P_ACC_NOISE] ** 2
            + (p[P_ACC_DYN] * da) ** 2
            + (p[P_ACC_W] * wn) ** 2
            + st[S_AVAR] / (g * g) * p[P_ACC_CORR] / dta
        )
        # walking around a bend: a sustained centripetal acceleration v·ω_up (ω_up the turn rate)
        wup = R[2, 0] * wx + R[2, 1] * wy + R[2, 2] * wz
        rv += (p[P_TURN_SPEED] * wup / g) ** 2 * p[P_TURN_CORR] / dta
        # horizontal specific force over g (not over |a|): a tilt error δ shows as g·δ whatever the vertical
        # acceleration, and a walking hand's horizontal and vertical accelerations are correlated over a
        # step, so dividing by |a| would bias the mean direction by −E[a_h a_v] / g² (≈ 1° for ±2 m/s²)
        uxw = (R[0, 0] * ax + R[0, 1] * ay + R[0, 2] * az) / g
        uyw = (R[1, 0] * ax + R[1, 1] * ay + R[1, 2] * az) / g
    dx = np.zeros(NX)
    _upd(st, dx, 1, -1.0, uxw, rv)
    _upd(st, dx, 0, 1.0, uyw, rv)
    _inject(st, dx)


@njit(cache=True, error_model="numpy")
def _gyro(st, R, wx, wy, wz, t, p):
    # still detection statistics
    first = not (st[S_HAVEG] > 0 and np.isfinite(st[S_TG]))
    _still_stats(st, S_GMEAN, S_GVAR, first, t - st[S_TG], wx, wy, wz, p[P_STILL_TAU])
    if st[S_INIT] > 0 and st[S_HAVEG] > 0:
        dt = t - st[S_TG]
        if dt > 0.0:
            ox = 0.5 * (wx + st[S_WG]) - st[S_B]
            oy = 0.5 * (wy + st[S_WG + 1]) - st[S_B + 1]
            oz = 0.5 * (wz + st[S_WG + 2]) - st[S_B + 2]
            if dt <= p[P_MAX_DT]:
                _predict(st, R, ox, oy, oz, dt, p)
                if dt > GAP_DT:
                    # a gap: the rate between the two samples is not the mean of the ends; it deviates
                    # by about the recent motion level (running std of the gyro) for the excess time
                    _inflate_att(st, st[S_GVAR] * (dt - GAP_DT) ** 2)
            else:
                # too long to integrate: propagate the uncertainty only; the rotation meanwhile is
                # unknown, of the order of (|ω̄|² + var ω) dt²
                _predict(st, R, 0.0, 0.0, 0.0, dt, p)
                _inflate_att(st, (ox * ox + oy * oy + oz * oz + st[S_GVAR]) * dt * dt)
        # zero-rate update while still
        still = (st[S_GVAR] < p[P_STILL_GYRO] ** 2) and (st[S_AVAR] < p[P_STILL_ACC] ** 2)
        if still:
            if not np.isfinite(st[S_STILL_SINCE]):
                st[S_STILL_SINCE] = t
            if t - st[S_STILL_SINCE] >= p[P_STILL_MIN]:
                dx = np.zeros(NX)
                # per-sample noise of a density: the same information per second at any gyro rate
                dtg = min(max(t - st[S_TG], 1e-4), 0.1) if np.isfinite(st[S_TG]) else 0.01
                rv = p[P_ZUPT_NOISE] ** 2 / dtg
                _upd(st, dx, 3, 1.0, wx - st[S_B], rv)
                _upd(st, dx, 4, 1.0, wy - st[S_B + 1], rv)
                _upd(st, dx, 5, 1.0, wz - st[S_B + 2], rv)
                _inject(st, dx)
        else:
            st[S_STILL_SINCE] = np.nan
    st[S_WG], st[S_WG + 1], st[S_WG + 2] = wx, wy, wz
    st[S_TG] = t
    st[S_HAVEG] = 1.0


@njit(cache=True, error_model="numpy")
def _mag(st, R, mx, my, mz, t, allowed, p, ip):
    if not (np.isfinite(mx) and np.isfinite(my) and np.isfinite(mz)) or st[S_INIT] == 0:
        return
    _rot(st, R)
    f = np.sqrt(mx * mx + my * my + mz * mz)
    if f <= 0.0:
        return
    # --- detectors (pdr_mag.interference)
    ux, uy, uz = R[2, 0], R[2, 1], R[2, 2]  # world up in device coordinates
    dip = dip_of(mx, my, mz, ux, uy, uz)
    mwx = (R[0, 0] * mx + R[0, 1] * my + R[0, 2] * mz) / f
    mwy = (R[1, 0] * mx + R[1, 1] * my + R[1, 2] * mz) / f
    mwz = (R[2, 0] * mx + R[2, 1] * my + R[2, 2] * mz) / f
    P = st[S_P : S_P + NX * NX]
    sb = np.sqrt(max(P[3 * NX + 3] + P[4 * NX + 4] + P[5 * NX + 5], 0.0))
    det = st[S_DET : S_DET + N_DET]
    flag, score, score_f, score_d, var, cons, floc, diploc, ftol = detect_step(
        det, f, dip, mwx, mwy, mwz, t, st[S_FREF], st[S_DIPREF], np.degrees(sb), ip
    )
    if flag:
        st[S_INTERF] = 1.0
    st[S_D_F] = f
    st[S_D_FREF] = floc
    st[S_D_FTOL] = ftol
    st[S_D_DIP] = dip
    st[S_D_DIPREF] = diploc
    st[S_D_DIPTOL] = ip[I_DIP_TOL]
    st[S_D_VAR] = var
    st[S_D_SCORE] = score
    st[S_CONS] = cons
    # --- heading update
    if not allowed:
        return
    if flag and not (st[S_INIT] < 2 and score_f < 1.0 and score_d < 1.0):
        return
    if np.isfinite(st[S_TMU]) and t - st[S_TMU] < p[P_MAG_INTERVAL]:
        return
    bh = np.sqrt(mwx * mwx + mwy * mwy) * f
    if bh < 1e-3:
        return
    psi = np.arctan2(mwx, mwy)
    r = _wrap(psi - st[S_DECL])
    # a disturbance d changes the strength by at most |d| and the dip by at most |d|/F: the smallest
    # disturbance that explains the deviations from the local references, seen horizontally, bounds the
    # heading error it may cause
    dmin2 = 0.0
    if np.isfinite(floc):
        dmin2 += (f - floc) ** 2
    if np.isfinite(diploc):
        dmin2 += (f * np.radians(dip - diploc)) ** 2
    # the consistency angle that the filter's own bias uncertainty explains over the detector's window
    # (σ_b W) is no evidence of a disturbance; only the excess is
    cons_d = max(cons - np.degrees(sb) * ip[I_CONS_WIN], 0.0)
    dmin2 += p[P_MAG_CONS_K] * (f * np.radians(cons_d)) ** 2
    rv_clean = p[P_MAG_NOISE] ** 2 + p[P_MAG_NOISE_UT] ** 2 / (bh * bh)
    # timestamp uncertainty of the magnetometer against the gyroscope: the device turns by |ω| τ meanwhile,
    # which moves the field direction by up to that angle (× F / B_h on the horizontal projection)
    if p[P_MAG_DT_UNC] > 0.0:
        wx, wy, wz = st[S_WG] - st[S_B], st[S_WG + 1] - st[S_B + 1], st[S_WG + 2] - st[S_B + 2]
        rv_clean += (np.sqrt(wx * wx + wy * wy + wz * wz) * p[P_MAG_DT_UNC] * f / bh) ** 2
    rv = rv_clean + p[P_MAG_DIST_K] ** 2 * dmin2 / (bh * bh)
    # the horizontal projection depends on the tilt: dψ = δθ_z − (m_x m_z δθ_x + m_y m_z δθ_y) / B_h²
    # (× tan I ≈ 2 for a tilt error about north).  The tilt errors enter H as consider states (Schmidt):
    # their uncertainty and correlations shape the gain and P — so when the accelerometer later corrects
    # the tilt, the heading follows through P — but the magnetometer never corrects the tilt itself
    bh2 = mwx * mwx + mwy * mwy
    h = np.zeros(NX)
    h[0] = -p[P_MAG_TILT_K] * mwx * mwz / bh2
    h[1] = -p[P_MAG_TILT_K] * mwy * mwz / bh2
    h[2] = 1.0
    h[6] = 1.0
    if st[S_INIT] < 2:
        # first usable field (strength and dip right; variance and consistency need a history):
        # set the heading directly, keep the tilt and bias
        _qmul_left(st, S_Q, 0.0, 0.0, r)
        _qmul_left(st, S_QG, 0.0, 0.0, r)
        if np.isfinite(st[S_AW]):  # the averaged specific force lives in the re-headed world frame
            c, sn = np.cos(r), np.sin(r)
            x0, y0 = st[S_AW], st[S_AW + 1]
            st[S_AW], st[S_AW + 1] = c * x0 - sn * y0, sn * x0 + c * y0
        for i in range(NX):
            P[2 * NX + i] = 0.0
            P[i * NX + 2] = 0.0
        # after the reset the residual is zero: δθ_z = −(δc + h_t·δθ_xy + n), so the heading error is the
        # (correlated) field error of this sample — its covariances follow, and a later field with the same
        # offset is no evidence of drift (hence of gyro bias)
        rt = h[0] * h[0] * P[0] + 2.0 * h[0] * h[1] * P[1] + h[1] * h[1] * P[NX + 1]
        P[2 * NX + 2] = rv + P[6 * NX + 6] + rt + 2.0 * (h[0] * P[6] + h[1] * P[NX + 6])
        for j in (0, 1, 3, 4, 5, 6):
            v = -P[6 * NX + j] - h[0] * P[j] - h[1] * P[NX + j]
            P[2 * NX + j] = v
            P[j * NX + 2] = v
        st[S_INIT] = 2.0
        st[S_TMU] = t
        st[S_MAGUSED] = 1.0
        det[DET_MW], det[DET_MW + 1], det[DET_MW + 2] = np.nan, 0.0, 0.0
        return
    r = _wrap(r - st[S_C])
    # the χ² gate asks whether the innovation fits an undisturbed field (the inflation of rv for a suspect
    # field lowers the gain, it must not widen the gate)
    S = rv_clean
    for i in range(NX):
        for m in range(NX):
            S += h[i] * P[i * NX + m] * h[m]
    if r * r > p[P_MAG_GATE] ** 2 * S:
        # a clean-looking field that keeps disagreeing: our heading may be wrong rather than the field;
        # let its variance grow (only the heading's, so the bias is not dragged when the gate opens)
        st[S_NREJ] += 1.0
        if np.isfinite(st[S_TREJ]):
            P[2 * NX + 2] += p[P_REJ_INFLATE] ** 2 * min(t - st[S_TREJ], 1.0)
        st[S_TREJ] = t
        return
    st[S_TREJ] = np.nan
    st[S_NREJ] = 0.0
    dx = np.zeros(NX)
    _upd_h(st, dx, h, r, rv, True)
    _inject(st, dx)
    st[S_TMU] = t
    st[S_MAGUSED] = 1.0


@njit(cache=True, error_model="numpy")
def run(kind, t, xyz, allowed, st, p, ip, out_t, out_q, out_std, out_mag, out_int, out_diag):
    """Process a merged, time-ordered chunk; returns the number of output rows written."""
    R = np.empty((3, 3))
    n_out = 0
    for i in range(len(t)):
        k = kind[i]
        x, y, z = xyz[i, 0], xyz[i, 1], xyz[i, 2]
        ti = t[i]
        if k == 0:
            if np.isfinite(x) and np.isfinite(y) and np.isfinite(z):
                _accel(st, R, x, y, z, ti, p)
        elif k == 2:
            _mag(st, R, x, y, z, ti, allowed[i], p, ip)
        elif k == 1:
            if not (np.isfinite(x) and np.isfinite(y) and np.isfinite(z)):
                continue
            _gyro(st, R, x, y, z, ti, p)
            if st[S_INIT] == 0:
                continue
            nxt = st[S_NEXT_OUT]
            if np.isfinite(nxt) and ti < nxt:
                continue
            if p[P_OUT_DT] > 0:
                if not np.isfinite(nxt):
                    nxt = ti
                while nxt <= ti:
                    nxt += p[P_OUT_DT]
                st[S_NEXT_OUT] = nxt
            out_t[n_out] = ti
            for c in range(4):
                out_q[n_out, c] = st[S_Q + c]
            out_std[n_out] = np.degrees(np.sqrt(max(st[S_P + 2 * NX + 2], 0.0)))
            out_mag[n_out] = st[S_MAGUSED] > 0
            out_int[n_out] = st[S_DET + DET_FLAG] > 0 or st[S_INTERF] > 0
            st[S_MAGUSED] = 0.0
            st[S_INTERF] = 0.0
            out_diag[n_out, D_GYRO_HEADING] = _heading(st, S_QG) if st[S_INIT] >= 2 else np.nan
            out_diag[n_out, D_F] = st[S_D_F]
            out_diag[n_out, D_FREF] = st[S_D_FREF]
            out_diag[n_out, D_FTOL] = st[S_D_FTOL]
            out_diag[n_out, D_DIP] = st[S_D_DIP]
            out_diag[n_out, D_DIPREF] = st[S_D_DIPREF]
            out_diag[n_out, D_DIPTOL] = st[S_D_DIPTOL]
            out_diag[n_out, D_VAR] = st[S_D_VAR]
            out_diag[n_out, D_SCORE] = st[S_D_SCORE]
            out_diag[n_out, D_BX] = st[S_B]
            out_diag[n_out, D_BY] = st[S_B + 1]
            out_diag[n_out, D_BZ] = st[S_B + 2]
            out_diag[n_out, D_CONS] = st[S_CONS]
            n_out += 1
    return n_out


@njit(cache=True, error_model="numpy")
def run_cut(kind, t, xyz, allowed, st, p, ip, cuts, snaps, out_t, out_q, out_std, out_mag, out_int, out_diag,
            h_y, h_x):  # fmt: skip
    """:func:`run` over the whole chunk with a copy of ``st`` put in ``snaps[j]`` before sample ``cuts[j]``
    (increasing); then each row's quaternion sign made non-negative in w (``q * ±1``) and the arguments
    ``h_y = 2 (x y − w z)``, ``h_x = 1 − 2 (x² + z²)`` of its heading's ``arctan2`` written.  Returns the
    number of output rows (the result of one :func:`run` call per piece: the same rows, a cut or not)."""
    n = len(t)
    k = 0
    a = 0
    for j in range(len(cuts) + 1):
        b = cuts[j] if j < len(cuts) else n
        if b > a or j == len(cuts):
            k += run(
                kind[a:b], t[a:b], xyz[a:b], allowed[a:b], st, p, ip,
                out_t[k:], out_q[k:], out_std[k:], out_mag[k:], out_int[k:], out_diag[k:],
            )  # fmt: skip
        if j < len(cuts):
            snaps[j, :] = st
        a = b
    for i in range(k):
        s = -1.0 if out_q[i, 0] < 0 else 1.0
        for c in range(4):
            out_q[i, c] = out_q[i, c] * s
        w = out_q[i, 0]
        x = out_q[i, 1]
        y = out_q[i, 2]
        z = out_q[i, 3]
        h_y[i] = 2.0 * (x * y - w * z)
        h_x[i] = 1.0 - 2.0 * (x * x + z * z)
    return k
