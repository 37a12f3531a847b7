"""Tilt from the accelerometer: the first sample sets it, later samples correct it.

Start.  The first usable sample once the gyroscope streams gives the tilt (up = a/|a| in device
coordinates; a tilt set before the first gyroscope sample could not be carried forward and would go stale
as the phone turns — some phones start their gyroscope 0.3–0.7 s after the accelerometer); the heading is then
arbitrary (device +y, or device −z for a phone held upright, projected on the horizontal plane points
north) with variance π², the tilt variance ``tilt0_std² + (||a| − g| / g)² + (rate_k |ω|)²`` per axis (the
sample's own acceleration turns it by at least that much; a rotating device's centripetal and tangential
acceleration by about ``rate_k |ω|``), the bias ``bias0_std²`` per axis and ``c`` its stationary
variance.

Averaged update (default, ``accel.tau_s > 0``).  The specific force is averaged in the almost inertial world
frame over **every** sample, ``ā_w ← ā_w + α (R a − ā_w)`` with ``α = 1 − exp(−Δt/τ)``: the mean linear
acceleration of a walking, swinging or pocketed phone over τ is Δv/τ ≈ 0, so ``ā_w`` points up (single
samples of a swinging arm point along the arm; gating them before averaging would bias the average).  At
most every ``accel.interval_s`` the direction ``u_w = ā_w / |ā_w| ≈ e_z + (−δθ_y, δθ_x, 0)`` is observed:
the window's mean tilt error.  Since ``δθ' = −R δb``, the error of the sample at ``t − s`` is
``δθ(t) + ∫ R δb``, and its exponentially weighted mean over the window is ``δθ(t) + τ R̄ δb`` with ``R̄``
the same weighted mean of ``R`` (kept beside ``ā_w``), so the two scalar updates have

    u_w,x:  H = −e_δθy − τ (row y of R̄) on δb
    u_w,y:  H = +e_δθx + τ (row x of R̄) on δb

and the tilt drift of an unknown raw gyro offset (4–6 °/s on real phones) is read as bias instead of being
smeared over the average.  Noise::

    avg_noise² + (dyn · ||ā| − g| / g)² + (spread_k² s² + (clip_k c)²) · τ / interval_s     (accel.*)

with ``s²`` the weighted mean square of the horizontal specific force about ``ā_w`` over g² (the
dynamics: ``ā_w``'s direction is off by ≈ 0.19 s rad per axis, measured with motion-capture attitude on
42 walks — texting 1–2°, running in the hand ~15°) and ``c`` the weight of clipped samples in the window
(their missing excess of about a g; the range is ``accel.range`` or found in the data); both count once per
independent window, the updates being ``accel.interval_s`` apart in a window of τ.  Skipped when
``||ā| − g| > accel.gate · g``.  While the heading is unknown (no magnetometer yet), or known only through a
tilt that was then beyond the linear range (:mod:`pdr_mag.fusion.mag`, a first fix through an unsettled tilt),
its errors are consider states of these updates: through the bias terms the linearised update would
otherwise shrink its (capped, uniform) variance, and through the tilt terms carry a tilt correction tens of
degrees wide over to the heading by a first-order correlation that does not hold that far.

No update is made from a part of a window (the first ``accel.tau_s`` after the average starts): it has not
averaged out the dynamics, and a start during a run would teach the bias the arm's swing.

Tilt reset.  The linearised update corrects small errors; a tilt started from one sample of a running arm
can be 150° off, and correcting it would teach the bias instead.  An average farther from up than
``LINEAR_RAD`` while the tilt is unsettled too (its own σ that large: a start in motion,
:func:`pdr_mag.fusion.eskf.tilt_unsettled`) corrects the tilt only (the bias a consider state, its ``τ R̄``
terms dropped); with a tilt known better it is dynamics.  One farther than
``accel.tilt_reset_min_deg`` and ``accel.tilt_reset_k`` σ (tilt error and the update's noise) is never an
update (:func:`_beyond_linear`).  The specific force is also averaged over ``accel.tilt_reset_tau_s``
(several strides: the swing cancels, where the short average passes a quarter of it); once that window is full
and its average is that far from up, the attitude is turned about the horizontal axis that takes it to up
(:func:`_tilt_reset`), as the magnetometer's re-acquisition does for the heading.

Per-sample update (``accel.tau_s = 0``).  ``u_w = (R a)_h / g``, the horizontal specific force over g (not
over |a|: a tilt error δ shows as g·δ whatever the vertical acceleration, and a walking hand's horizontal
and vertical accelerations are correlated over a step, so dividing by |a| would bias the mean direction by
``−E[a_h a_v] / g²``, ≈ 1° for ±2 m/s²), observing ``(−δθ_y, δθ_x)``; noise ``accel.noise² + (accel.dyn ·
||a| − g| / g)² + (accel.rate_k |ω|)² + var(a)/g² · accel.corr_s / Δt_a`` (the linear acceleration's recent
variance, correlated over ``accel.corr_s``, spread over the samples) ``+ (accel.turn_speed · ω_up / g)² ·
accel.turn_corr_s / Δt_a`` (the centripetal acceleration of a turn); skipped when
``||a| − g| > accel.gate · g`` or when the sample is clipped.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from pdr_mag.fusion.detectors import restart
from pdr_mag.fusion.eskf import LINEAR_RAD, inject, settle_u, tilt_unsettled, update, update_h
from pdr_mag.fusion.ew import ew_alpha
from pdr_mag.fusion.gyro import bias_prior_var, ew_stats_step
from pdr_mag.fusion.quat import rotate_world, rotation_matrix
from pdr_mag.fusion.state import BIAS, C_ERR, NX, OFFSET, TH_X, TH_Y, TH_Z

#: largest starting tilt variance per axis, rad² (a quarter turn: the linearised updates say nothing beyond)
TILT0_VAR_MAX = (np.pi / 2) ** 2


@njit(cache=True, error_model="numpy")
def init_tilt(s, ax, ay, az, p):
    """Attitude of record ``s`` from one accelerometer sample; covariance at its start values."""
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
        sq = np.sqrt(tr + 1.0) * 2
        w, x, y, z = 0.25 * sq, (r21 - r12) / sq, (r02 - r20) / sq, (r10 - r01) / sq
    elif r00 > r11 and r00 > r22:
        sq = np.sqrt(1.0 + r00 - r11 - r22) * 2
        w, x, y, z = (r21 - r12) / sq, 0.25 * sq, (r01 + r10) / sq, (r02 + r20) / sq
    elif r11 > r22:
        sq = np.sqrt(1.0 + r11 - r00 - r22) * 2
        w, x, y, z = (r02 - r20) / sq, (r01 + r10) / sq, 0.25 * sq, (r12 + r21) / sq
    else:
        sq = np.sqrt(1.0 + r22 - r00 - r11) * 2
        w, x, y, z = (r10 - r01) / sq, (r02 + r20) / sq, (r12 + r21) / sq, 0.25 * sq
    qn = np.sqrt(w * w + x * x + y * y + z * z)
    q = s.q
    q[0], q[1], q[2], q[3] = w / qn, x / qn, y / qn, z / qn
    for k in range(4):
        s.q_gyro[k] = q[k]
    P = s.P
    for i in range(NX):
        for m in range(NX):
            P[i, m] = 0.0
            s.U[i, m] = 0.0
    for i in range(3):
        for m in range(3):
            s.u_G[i, m] = 0.0
    s.u_phi = 1.0
    s.u_pending = False
    # the sample's own acceleration turns its direction by up to ||a| − g| / g rad (a lower bound of the
    # linear acceleration over g), and a rotating device's centripetal and tangential acceleration by about
    # accel.rate_k |ω| (as in the per-sample update's noise; |ω| at this sample, bias included): a start in
    # motion — mid-stride, in a swinging hand or a pocket — is that uncertain, even when |a| happens to be g
    da = abs(n - p.accel.gravity) / p.accel.gravity
    w2 = s.w_gyro[0] ** 2 + s.w_gyro[1] ** 2 + s.w_gyro[2] ** 2
    t0 = min(p.accel.tilt0_std**2 + da * da + p.accel.rate_k**2 * w2, TILT0_VAR_MAX)
    P[TH_X, TH_X] = t0
    P[TH_Y, TH_Y] = t0
    P[TH_Z, TH_Z] = np.pi**2
    b0 = bias_prior_var(s, p)
    for i in range(BIAS, BIAS + 3):
        P[i, i] = b0
    P[C_ERR, C_ERR] = p.mag.error_std_rad**2
    if p.mag.offset_states:
        for i in range(3):
            for m in range(3):
                P[OFFSET + i, OFFSET + m] = s.cal_cov[i, m]
    s.c = 0.0
    s.init = 1


@njit(cache=True, error_model="numpy")
def accel_step(s, R, ax, ay, az, t, p):
    """One accelerometer sample (m/s², device frame) at time t; ``R`` scratch 3×3."""
    first = not (s.have_acc and np.isfinite(s.t_acc))
    ew_stats_step(s.acc_stats, first, t - s.t_acc, ax, ay, az, p.gyro.still_tau_s)
    s.t_acc_prev = s.t_acc
    s.t_acc = t
    s.have_acc = True
    n = np.sqrt(ax * ax + ay * ay + az * az)
    if n < 1e-6:
        return
    clipped = _clipped(s, ax, ay, az, p)
    if s.init == 0:
        if s.have_gyro:  # before the gyroscope streams, nothing would carry the tilt forward
            init_tilt(s, ax, ay, az, p)
        return
    g = p.accel.gravity
    da = abs(n - g) / g
    rotation_matrix(s.q, R)
    if p.accel.tau_s > 0.0:
        _averaged_update(s, R, ax, ay, az, t, clipped, p)
        return
    if da > p.accel.gate or clipped:
        return
    wx, wy, wz = s.w_gyro[0] - s.b[0], s.w_gyro[1] - s.b[1], s.w_gyro[2] - s.b[2]
    wn = np.sqrt(wx * wx + wy * wy + wz * wz)
    dta = t - s.t_acc_prev if np.isfinite(s.t_acc_prev) else 0.01
    dta = min(max(dta, 1e-4), 0.1)
    rv = (
        p.accel.noise**2
        + (p.accel.dyn * da) ** 2
        + (p.accel.rate_k * wn) ** 2
        + s.acc_stats.var / (g * g) * p.accel.corr_s / dta
    )
    wup = R[2, 0] * wx + R[2, 1] * wy + R[2, 2] * wz
    rv += (p.accel.turn_speed * wup / g) ** 2 * p.accel.turn_corr_s / dta
    uxw = (R[0, 0] * ax + R[0, 1] * ay + R[0, 2] * az) / g
    uyw = (R[1, 0] * ax + R[1, 1] * ay + R[1, 2] * az) / g
    dx = np.zeros(NX)
    update(s, dx, TH_Y, -1.0, uxw, rv)
    update(s, dx, TH_X, 1.0, uyw, rv)
    inject(s, dx)


@njit(cache=True, error_model="numpy")
def _clipped(s, ax, ay, az, p):
    """Whether this sample has an axis at the accelerometer's range (given, or found in the data: the
    settings' ``accel.range``); keeps the running peak and its hits."""
    m = max(abs(ax), max(abs(ay), abs(az)))
    if p.accel.range > 0.0:
        return m >= (1.0 - p.accel.clip_band) * p.accel.range
    if m > s.acc_peak:
        if m > s.acc_peak * (1.0 + p.accel.clip_band):
            s.acc_peak_hits = 0  # a new, higher level: the old one was no range
        s.acc_peak = m
    near = m >= (1.0 - p.accel.clip_band) * s.acc_peak
    if near:
        s.acc_peak_hits += 1
    return near and s.acc_peak_hits >= p.accel.clip_min_hits and s.acc_peak > 1.5 * p.accel.gravity


@njit(cache=True, error_model="numpy")
def _averaged_update(s, R, ax, ay, az, t, clipped, p):
    """The world-frame average ``ā_w``; at most every ``accel.interval_s``, the update from its direction."""
    aw = s.acc_w
    awx = R[0, 0] * ax + R[0, 1] * ay + R[0, 2] * az
    awy = R[1, 0] * ax + R[1, 1] * ay + R[1, 2] * az
    awz = R[2, 0] * ax + R[2, 1] * ay + R[2, 2] * az
    Rb = s.R_bar
    if not np.isfinite(aw[0]) or not np.isfinite(s.t_acc_update) or t - s.t_acc_update > 10.0 * p.accel.tau_s:
        aw[0], aw[1], aw[2] = awx, awy, awz
        s.acc_spread = 0.0
        s.clip_share = 1.0 if clipped else 0.0
        for i in range(3):
            for m in range(3):
                Rb[i, m] = R[i, m]
        s.t_acc_update = t
        s.t_acc_w0 = t
        al = s.acc_w_long
        al[0], al[1], al[2] = awx, awy, awz
        return
    dt = t - s.t_acc_prev
    if p.accel.tilt_reset_k > 0.0:  # a running mean until the window is full, then exponentially weighted
        al = s.acc_w_long
        b = max(ew_alpha(dt, p.accel.tilt_reset_tau_s), dt / (t - s.t_acc_w0 + dt))
        al[0] += b * (awx - al[0])
        al[1] += b * (awy - al[1])
        al[2] += b * (awz - al[2])
    a = ew_alpha(dt, p.accel.tau_s)
    aw[0] += a * (awx - aw[0])
    aw[1] += a * (awy - aw[1])
    aw[2] += a * (awz - aw[2])
    ex, ey = awx - aw[0], awy - aw[1]
    s.acc_spread += a * (ex * ex + ey * ey - s.acc_spread)
    s.clip_share += a * ((1.0 if clipped else 0.0) - s.clip_share)
    for i in range(3):
        for m in range(3):
            Rb[i, m] += a * (R[i, m] - Rb[i, m])
    if t - s.t_acc_update < p.accel.interval_s or t - s.t_acc_w0 < p.accel.tau_s:
        return  # (a part of a window does not average out the dynamics)
    s.t_acc_update = t
    g = p.accel.gravity
    if _tilt_reset(s, t, p):
        return
    na = np.sqrt(aw[0] ** 2 + aw[1] ** 2 + aw[2] ** 2)
    dev = abs(na - g) / g
    if dev > p.accel.gate:
        return
    tau = p.accel.tau_s
    rv = p.accel.avg_noise**2 + (p.accel.dyn * dev) ** 2
    windows = tau / max(p.accel.interval_s, 1e-3)  # updates per independent window
    rv += (p.accel.spread_k**2 * s.acc_spread / (g * g) + (p.accel.clip_k * s.clip_share) ** 2) * windows
    if _beyond_linear(s, aw[2] / na, rv, p):
        return  # a tilt that far off is the reset's, never the bias's
    hx = np.zeros(NX)
    hy = np.zeros(NX)
    hx[TH_Y] = -1.0
    hy[TH_X] = 1.0
    # the window's mean tilt error: δθ(t) + τ R̄ δb (R̄ the window's mean of R) — a linearisation that holds
    # for small errors only: an average farther off than LINEAR_RAD while the tilt is unsettled is the
    # tilt's, the bias a consider state; with a tilt known better, it is dynamics
    linear = aw[2] / na >= np.cos(LINEAR_RAD) or not tilt_unsettled(s.P, p)
    if linear:
        for m in range(3):
            hx[BIAS + m] = -tau * Rb[1, m]
            hy[BIAS + m] = tau * Rb[0, m]
    dx = np.zeros(NX)
    unknown = s.init < 2 or s.fix_beyond_linear  # no heading yet, or a first one maybe beyond linear
    update_h(s, dx, hx, aw[0] / na, rv, False, unknown, not linear)
    update_h(s, dx, hy, aw[1] / na, rv, False, unknown, not linear)
    inject(s, dx)


@njit(cache=True, error_model="numpy")
def _beyond_linear(s, cos_up, rv, p):
    """Whether the average's direction (``cos_up`` its cosine to up) is farther from up than
    ``accel.tilt_reset_min_deg`` and ``accel.tilt_reset_k`` σ of the tilt error and the update's noise ``rv``
    per axis."""
    if p.accel.tilt_reset_k <= 0.0:
        return False
    ang = np.arccos(min(max(cos_up, -1.0), 1.0))
    P = s.P
    var = P[TH_X, TH_X] + P[TH_Y, TH_Y] + 2.0 * rv
    return ang >= p.accel.tilt_reset_min_rad and ang * ang >= p.accel.tilt_reset_k**2 * var


@njit(cache=True, error_model="numpy")
def _tilt_reset(s, t, p):
    """Turn the attitude so that the long average ``ā_long`` (``accel.tilt_reset_tau_s``) is up, when that
    window is full, ``||ā_long| − g| < 0.3 g`` (a clipping accelerometer shortens the average of a running arm
    by up to a quarter; its direction holds) and ``ā_long`` is farther from up than ``tilt_reset_min`` and
    ``accel.tilt_reset_k`` σ of the tilt error.  Both averages and the window's mean R turn with the attitude;
    the tilt variance restarts at ``tilt0_std²`` per axis, uncorrelated, and the bias variance at no less
    than ``bias0_std²`` (the corrections of a tilt that far off went into the bias).  Returns whether it
    did."""
    if p.accel.tilt_reset_k <= 0.0 or t - s.t_acc_w0 < p.accel.tilt_reset_tau_s:
        return False
    al = s.acc_w_long
    na = np.sqrt(al[0] * al[0] + al[1] * al[1] + al[2] * al[2])
    if abs(na - p.accel.gravity) > 0.3 * p.accel.gravity:
        return False
    if not _beyond_linear(s, al[2] / na, 0.0, p):
        return False
    ang = np.arccos(min(max(al[2] / na, -1.0), 1.0))
    P = s.P
    # the rotation taking ā_long to up: axis ā_long × e_z (horizontal), angle ang
    hx, hy = al[1], -al[0]
    hn = np.sqrt(hx * hx + hy * hy)
    if hn <= 0.0:  # straight down: any horizontal axis
        hx, hy, hn = 1.0, 0.0, 1.0
    vx, vy = ang * hx / hn, ang * hy / hn
    rotate_world(s.q, vx, vy, 0.0)
    rotate_world(s.q_gyro, vx, vy, 0.0)
    _turn_vector(al, vx, vy)
    _turn_vector(s.acc_w, vx, vy)
    Rb = s.R_bar
    col = np.zeros(3)
    for m in range(3):  # the columns of the window's mean R are world vectors
        col[0], col[1], col[2] = Rb[0, m], Rb[1, m], Rb[2, m]
        _turn_vector(col, vx, vy)
        Rb[0, m], Rb[1, m], Rb[2, m] = col[0], col[1], col[2]
    settle_u(s)
    for i in range(NX):
        for j in (TH_X, TH_Y):
            for M in (P, s.U):
                M[i, j] = 0.0
                M[j, i] = 0.0
    P[TH_X, TH_X] = p.accel.tilt0_std**2
    P[TH_Y, TH_Y] = p.accel.tilt0_std**2
    b0 = bias_prior_var(s, p)
    for i in range(BIAS, BIAS + 3):
        P[i, i] = max(P[i, i], b0)
    restart(s.det)  # the detectors' world-frame state restarts in the turned world frame
    s.tilt_resets += 1
    return True


@njit(cache=True, error_model="numpy")
def _turn_vector(v, vx, vy):
    """``v ← Exp((vx, vy, 0)) v`` exactly (Rodrigues), for a rotation about a horizontal axis."""
    ang = np.sqrt(vx * vx + vy * vy)
    if ang <= 0.0:
        return
    kx, ky = vx / ang, vy / ang
    c, sn = np.cos(ang), np.sin(ang)
    x, y, z = v[0], v[1], v[2]
    kv = kx * x + ky * y
    cx, cy, cz = ky * z, -kx * z, kx * y - ky * x  # k × v
    v[0] = x * c + cx * sn + kx * kv * (1.0 - c)
    v[1] = y * c + cy * sn + ky * kv * (1.0 - c)
    v[2] = z * c + cz * sn
