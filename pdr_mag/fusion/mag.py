"""Heading from the calibrated magnetometer: the interference detectors, then a heading-only update.

Detectors.  Every finite sample goes through :func:`pdr_mag.fusion.detectors.detect_step` (each registered
detector — strength, dip against the filter's up direction, variance, gyro consistency of the world-frame
direction ``m_w = R m_d`` — and the hold timer), whatever the caller allows; their state is the record
``det`` inside the filter's state, the sample in ``det.x``.

Measurement.  Heading only: ``ψ = atan2(m_w,x, m_w,y)`` of the calibrated field less the offset error
found, ``m − o``; the residual ``r = wrap(ψ − D − c)`` (D the declination, 0 for magnetic north) observes

    h = (h_t, 1 on δθ_z, 0 on δb, 1 on δc, g on δo),    h_t = −k_t (m_x m_z, m_y m_z) / B_h²

``h_t`` being the sensitivity of ψ to tilt errors (× tan I about north; ``k_t`` = ``mag.tilt_k``) and
``g = ∂ψ/∂m_d`` (:func:`_heading_gradient`) its sensitivity to the field in the device frame, through which
the calibration's offset error turns the heading.  That error is constant in the device frame, so its turn
``g·δo`` changes with the device's orientation — its sign reverses between opposite headings — while the
gyroscope says the device turned by what it turned: over a walker's turns the updates tell ``δo`` from the
heading and from c (``mag.offset_states``; without them g is 0 and the offset's error joins c's variance).
The tilt errors are *consider* states (Schmidt–Kalman: in the gain and in ``P``, never corrected), so a
disturbed field can never tilt the attitude, yet a tilt error is not taken for a heading error, and a later
accelerometer correction of the tilt carries over to the heading through ``P``.  While the tilt is unsettled
(``tr P_tilt > 2 accel.tilt0_std²``, :func:`pdr_mag.fusion.eskf.tilt_unsettled`: a start in motion), the
heading's changes say more about the tilt than about the gyroscope, and the bias and the offset error are
consider states too.

Noise::

    σ_ψ² = σ_h² + σ_m² / B_h² + (|ω| τ_m F / B_h)² + k_d² d_min² / B_h²
    d_min² = (F − F_loc)² + (F (I − I_loc))² + k_c (F ∠cons_d)²,   ∠cons_d = max(∠cons − σ_b W, 0)
           (each detector's part: :func:`pdr_mag.fusion.detectors.disturbance2`)

σ_h ``mag.noise_deg``, σ_m ``mag.noise_uT``, ``B_h`` the measured horizontal strength, τ_m
``mag.time_unc_s`` (the device turns by ``|ω| τ_m`` within the timestamp uncertainty), k_d ``mag.dist_k``,
k_c ``mag.cons_k``.  ``d_min`` is the smallest disturbance that explains the deviations of strength, dip
and world-frame direction from the detectors' references (a disturbance d changes the strength by at most
|d|, the dip by at most |d|/F and turns the horizontal field by at most |d|/B_h); the consistency angle
counts only beyond what the filter's own bias uncertainty explains over the detector's window
(σ_b = √tr P_bb, W ``ConsistencySettings.window_s``).

Gates. No update while the interference flag is up (except the first fix, below), when the caller disallows
it, within ``mag.interval_s`` of the last update (the errors are correlated in time), when ``B_h`` < 1e-3 µT,
or when ``r² > mag.gate² · S`` with ``S = h P hᵀ`` plus the *undisturbed* part of σ_ψ² (a suspect field gets
less weight; it cannot widen the gate). While a clean-looking field keeps failing the gate, the heading's
variance grows as the gyroscope's own uncertainty makes it grow, no faster: a field that disagrees with a
heading the gyroscope vouches for is more likely turned (an offset that moved, a building's steel) than the
heading lost, and a lost heading is re-acquired (below). (``mag.reject_inflate_deg`` > 0 adds that squared
per second to ``P[δθ_z, δθ_z]`` during such a run, the heading's alone, so the bias is not dragged when the
gate opens: a faster recovery that lets a turned field in as well.) The update that ends such a run takes the
bias and the offset error as consider states, whatever the run's length: a heading that was wrong from its
start (a first fix through a tilt 40° off) and is corrected after seconds of rejections would otherwise teach
the gyro bias ``Δψ / Δt`` (15–18 °/s on two tyrex walks started 20 s in, more than any phone's offset), and
the offset error a turn ``g·δo`` it did not make, where re-acquisition lets the bias variance grow by that
rate at most.
No heading update (the first fix aside, whose variance carries ``h_t P_tilt h_tᵀ``) while the tilt's
variance exceeds ``2 · LINEAR_RAD²`` (:mod:`pdr_mag.fusion.accel`: a start in motion whose first sample's
tilt is that uncertain): the heading row ``h_t`` is linearised about a tilt that may be tens of degrees
off, and its updates would shrink the heading's variance around a heading off by ``tan I`` times that.

Re-acquisition.  A filter can be lost while believing itself — a bias taught wrong, a start in a turned field
— and then rejects every correct field that follows.  When a clean-looking field has failed the gate without a
break and its innovations agree among themselves, the heading is set to the magnetometer's.  The run must span
as long as the fields behind the heading do — from when it was set from the field (a first fix; a mean of the
first calibration's fields, from the oldest of them; a re-acquisition, from its run's start; the first clean
field after a guess) to its latest accepted update — at least two of c's correlation times
(``mag.error_tau_s``: the run's fields then carry errors of their own, not one turned field's) and at most
``mag.reacquire_s``: a heading that one turned field set is not held against many clean ones for longer than a
heading that minutes of fields agree with.  A lost heading is off by one angle whatever the device does, which
drifts at the gyro bias's error; a turned field in a steel building changes as the walker moves.  So the
innovations ``x = wrap(r − r₀)`` (r₀ the run's first) are fitted by a line in time, ``x ≈ x̄ + β (τ − τ̄)``,
from their exponentially weighted moments over the run (weights as the run's, time constant
``mag.reacquire_s``), and they agree when the scatter about it, ``var(x − β τ)``, is below
``mag.reacquire_spread_deg²`` — a slope ``|β|`` beyond three times the filter's own bias σ about up being no
drift it can have, the scatter is then taken about the mean (``β = 0``).  The heading is turned by the line's
value now, ``q ← Exp(r̄ e_z) ⊗ q`` with ``r̄ = r₀ + x̄ + β (τ − τ̄)``, exactly as at the first fix (the
covariance below), and the bias variance about up grows by ``min((r̄ / max(Δt, 10 s))², σ_b0²)``, the drift
rate that the jump implies over the time Δt since the last heading update (σ_b0 the bias prior's,
:func:`pdr_mag.fusion.gyro.bias_prior_var`).  The jump is reported in the ``heading_reset_deg`` output column
(a ``heading_reset`` event in the pipeline).

First fix.  The first usable sample sets the heading directly (``q ← Exp(r e_z) ⊗ q``, the averaged
specific force turned with it).  The residual is then zero, so ``δθ_z = −(h′·δx′ + n)``, with ``h′`` and
``δx′`` the row and the states other than δθ_z (the tilt, c and the offset error): the heading error *is*
that sample's correlated field error, and

    P[δθ_z, ·] = −h′ P[δx′, ·]
    P[δθ_z, δθ_z] = σ_ψ² + h′ P[δx′, δx′] h′ᵀ

so a later field with the same offset — a disturbance present since the start — is not read as drift (that is,
as gyro bias about up).  c's variance there is at least ``σ_c² + d₀² / (2 B_h²)``, d₀ ``mag.env_prior_uT``:
nothing of the place is known yet, and the first field may be turned by the unseen component of a disturbance
at the level an indoor place has before the detectors have seen it (``UNSEEN_SHARE``; the filter's
environment term weighs later fields with its smaller ``mag.env_k``).  The corrections that follow a first
field that was turned then go to the heading rather than to the bias about up, which would carry the error on
through the next stretch on the gyroscope.

A first sample that the detectors flag against an absolute reference (strength or dip: a start next to steel)
is still taken, as a guess with ``σ_ψ² = π²``: a disturbance may turn the field by anything, so the std says
180° until a clean field comes, which the gate then lets in whatever its innovation, but the heading meanwhile
is the field's rather than the device's +y, which a backend that must start somewhere prefers.  Until that
clean field, each flagged field that can still carry a heading — its smallest disturbance below the expected
horizontal strength B (``d < B``: a disturbance as strong as the horizontal field may turn it by anything) —
refines the guess (:func:`_refine_guess`): the heading is the weighted mean of those fields' headings, weights
``1 / (σ_h² + d² / B²)``, one a ``mag.interval_s`` at most (d the larger of ``d_min`` and the field's
deviation from the reference: a flagged start has learnt no local reference).  A walker passing steel sees its
disturbances change while the Earth's field stays, so the mean is nearer north than any one of them; the
variance stays π² and no covariance changes (a guess teaches the bias nothing), only the attitude is
corrected.
The consider covariance ``U`` (:mod:`pdr_mag.fusion.gyro`) takes the same form with its own c and no white
noise, ``U_cc`` starting at the place's unmodelled variance.

First heading from the first fit's own samples.  A filter without a calibration has no heading: its
frame has turned with the gyroscope alone since the start.  When the first calibration is found, the
fields of the last seconds that its fit explains (the calibrator's recent samples within the admission
bands) each give the Earth's field's azimuth in that frame, which holds but for the gyro bias's drift; their
fitted mean is the heading at once (:meth:`pdr_mag.fusion.FusionCore.fix_heading_from_history`,
:func:`history_fix`), with the variance of a mean of correlated fields, rather than one field's — which may
be disturbed then: a walker passing steel as the fit is accepted would otherwise start from a guess at σ 180°.
The heading's covariance with the rest is dropped (its error is the fields' mean's, not the current c).  Only
fields spanning two of c's correlation times or more: a shorter history averages nothing, and its samples'
tilts are the start's, often unsettled — the first fix is then the next field's, as above.  A mean whose σ
exceeds ``LINEAR_RAD`` (fields that scatter: steel) is treated as a first fix through an unsettled tilt
(below): the first update finding it more than ``LINEAR_RAD`` off sets the heading anew rather than teach
the gyro bias the difference.

A first fix through an unsettled tilt.  A first fix made while the tilt is beyond the linear range
(``P_xx + P_yy > 2 · LINEAR_RAD²``: a start in motion, whose first accelerometer sample may point 40° from up)
saw the field through that tilt, and its heading is off by up to ``tan I`` times as much.  No linearised
update undoes that: the accelerometer's corrections of the tilt would carry over to the heading through
``P``'s first-order correlation (a 40° tilt error turned a heading 18° off into 87° off on a tyrex walk
started 20 s in), and the first heading updates after would teach the gyro bias the difference (8 °/s
there).  So, until the first heading update once the tilt is in the linear range (``fix_beyond_linear``), the
heading is a consider state of the accelerometer's updates, as before any fix; and when that update's residual
is beyond ``LINEAR_RAD`` the heading is set from the field anew (:func:`_set_heading`: the attitude turned
onto the field's heading and its covariance rows as at the first fix, the gyroscope-only attitude turned with
it; the turn reported in ``heading_reset_deg`` as a re-acquisition's) rather than corrected; a smaller
residual is an ordinary update.

Calibration change.  When the calibration in force changes the calibrated field by ``dm`` (device frame,
:meth:`pdr_mag.fusion.FusionCore.note_calibration_change`; the offset error found under the old calibration,
dropped then, is part of ``dm``: :meth:`pdr_mag.fusion.FusionCore.use_calibration`), the heading so far was
taken from fields turned by the change — to first order ``g · dm`` (``g = ∂ψ/∂m_d``,
:func:`_heading_gradient`), exactly the turn between the horizontal fields ``R m`` and ``R (m − dm)``, which
may be anything for a change as large as the horizontal field (one along the field that reversed it has
``g · dm`` = 0): at the next sample the square of the larger joins ``P[δθ_z, δθ_z]`` (capped at π²), so the
corrected field is within the gate at once — a flagged sample too, with the latest usable one's field and
gradient (``cal_m``, ``cal_g``), so that a heading taken through a wrong calibration does not keep its small σ
while the flags hold the corrected field out. (A change of the soft-iron matrix makes ``dm`` depend on the
field: ``dm = D m + e``, see the method.)
"""

from __future__ import annotations

import numpy as np
from numba import njit

from pdr_mag.fusion.detectors import detect_step, disturbance2, reference_horizontal, restart, tolerance2
from pdr_mag.fusion.detectors.dip import dip_of
from pdr_mag.fusion.eskf import LINEAR_RAD, inject, settle_u, tilt_beyond_linear, tilt_unsettled, update_h
from pdr_mag.fusion.ew import ew_alpha
from pdr_mag.fusion.gyro import bias_prior_var, horizontal_ref, magerr_var, unmodelled_var
from pdr_mag.fusion.quat import rotate_world, rotation_matrix, wrap
from pdr_mag.fusion.state import BIAS, C_ERR, NX, OFFSET, TH_X, TH_Y, TH_Z

#: the weight of a first field's guess that says nothing of north (its disturbance at least the horizontal
#: field): the next flagged field that can carry a heading replaces it
GUESS_W_NONE = 1e-9
#: a lost heading's innovations drift at most this many times the filter's bias σ about up (re-acquisition)
DRIFT_K = 3.0
#: the share of a disturbance's variance in its unseen component, the one that turns the horizontal field: a
#: disturbance with no preferred direction has it as large as the mean of the two the detectors see (strength,
#: dip), half their sum (the first fix's c; ``UncertaintySettings.env_k`` = √0.5 is the same for the std)
UNSEEN_SHARE = 0.5


@njit(cache=True, error_model="numpy")
def mag_step(s, R, mx, my, mz, t, allowed, p):
    """One calibrated magnetometer sample (µT, device frame) at time t; ``allowed``: the caller permits a
    heading update from it.  ``R`` scratch 3×3."""
    if not (np.isfinite(mx) and np.isfinite(my) and np.isfinite(mz)) or s.init == 0:
        return
    if p.mag.offset_states:  # the field less the offset error the filter has found
        mx, my, mz = mx - s.offset[0], my - s.offset[1], mz - s.offset[2]
    rotation_matrix(s.q, R)
    f = np.sqrt(mx * mx + my * my + mz * mz)
    if f <= 0.0:
        return
    # --- detectors
    ux, uy, uz = R[2, 0], R[2, 1], R[2, 2]  # world up in device coordinates
    dip = dip_of(mx, my, mz, ux, uy, uz)
    mwx = (R[0, 0] * mx + R[0, 1] * my + R[0, 2] * mz) / f
    mwy = (R[1, 0] * mx + R[1, 1] * my + R[1, 2] * mz) / f
    mwz = (R[2, 0] * mx + R[2, 1] * my + R[2, 2] * mz) / f
    P = s.P
    sb = np.sqrt(max(P[BIAS, BIAS] + P[BIAS + 1, BIAS + 1] + P[BIAS + 2, BIAS + 2], 0.0))  # σ_b
    det = s.det
    x = det.x
    x.t, x.f, x.dip, x.f_ref, x.dip_ref, x.sigma_b_deg = t, f, dip, s.f_ref, s.dip_ref, np.degrees(sb)
    x.mw[0], x.mw[1], x.mw[2] = mwx, mwy, mwz
    flag = detect_step(det, p.interference)
    if flag:
        s.interference_seen = True
    _flag_share_step(s, flag, t, det, p)
    if s.init >= 2 and (flag or not allowed):
        # a calibration change noted: the heading's variance grows now, not at the next clean field (the
        # latest usable sample's field and gradient: this field's direction is not to be trusted)
        _calibration_jump(s, s.cal_g, mx, my, mz, R, t, p, False)
    # --- gates
    if not allowed:
        return
    if flag and s.init >= 2 and s.guess_w == 0.0:
        return
    if np.isfinite(s.t_mag_update) and t - s.t_mag_update < p.mag.interval_s:
        return
    bh = np.sqrt(mwx * mwx + mwy * mwy) * f
    if bh < 1e-3:
        return
    if flag and s.init >= 2:
        w = _guess_weight(s, det, bh, disturbance2(det, p), p)
        _refine_guess(s, wrap(np.arctan2(mwx, mwy) - s.declination), w, t)
        return
    g = np.empty(3)
    _heading_gradient(R, mwx * f, mwy * f, g)
    _calibration_variance(s, g, p)
    _calibration_jump(s, g, mx, my, mz, R, t, p, True)
    s.cal_m[0], s.cal_m[1], s.cal_m[2] = mx, my, mz
    psi = np.arctan2(mwx, mwy)
    r = wrap(psi - s.declination)
    # --- noise
    dmin2 = disturbance2(det, p)
    _environment_step(s, dmin2, t, det, p)
    rv_clean = p.mag.noise_rad**2 + p.mag.noise_uT**2 / (bh * bh)
    if p.mag.time_unc_s > 0.0:
        wx, wy, wz = s.w_gyro[0] - s.b[0], s.w_gyro[1] - s.b[1], s.w_gyro[2] - s.b[2]
        rv_clean += (np.sqrt(wx * wx + wy * wy + wz * wz) * p.mag.time_unc_s * f / bh) ** 2
    rv = rv_clean + p.mag.dist_k**2 * dmin2 / (bh * bh)
    # --- measurement row: tilt (consider states), heading, c
    bh2 = mwx * mwx + mwy * mwy
    h = np.zeros(NX)
    h[TH_X] = -p.mag.tilt_k * mwx * mwz / bh2
    h[TH_Y] = -p.mag.tilt_k * mwy * mwz / bh2
    h[TH_Z] = 1.0
    h[C_ERR] = 1.0
    if p.mag.offset_states:
        for i in range(3):
            h[OFFSET + i] = g[i]
    if s.init < 2:
        guess = flag and not det.score_absolute < 1.0
        if guess:
            rv = np.pi**2  # a guess from a disturbed field (the module docstring)
        _first_fix(s, h, r, rv, t, p)
        s.guess_w = max(_guess_weight(s, det, bh, dmin2, p), GUESS_W_NONE) if guess else 0.0
        return
    if tilt_beyond_linear(P):
        return  # a tilt this uncertain makes the linearised heading row meaningless (the module docstring)
    r = wrap(r - s.c)
    if s.fix_beyond_linear and abs(r) > LINEAR_RAD:  # a first fix beyond the linear range (module docstring)
        rotate_world(s.q_gyro, 0.0, 0.0, r)  # the gyroscope-only attitude started from that first fix too
        _set_heading(s, h, r, rv, t, t)
        return
    # χ² gate with the undisturbed noise
    S = rv_clean
    for i in range(NX):
        for m in range(NX):
            S += h[i] * P[i, m] * h[m]
    if r * r > p.mag.gate**2 * S:
        # a clean-looking field that keeps disagreeing: let the heading's variance grow
        if np.isfinite(s.t_reject):
            P[TH_Z, TH_Z] += p.mag.reject_inflate_rad**2 * min(t - s.t_reject, 1.0)
        _rejected(s, R, h, r, rv, t, p)
        return
    s.fix_beyond_linear = False
    if s.guess_w > 0.0:
        s.t_heading_set = t  # the first clean field after a guess sets the heading
    s.guess_w = 0.0
    after_run = np.isfinite(s.t_reject_start)
    s.t_reject = np.nan
    s.t_reject_start = np.nan
    dx = np.zeros(NX)
    # while the tilt is unsettled (a start in motion), the heading's changes say more about the tilt than
    # about the gyroscope; the first update after a run of rejections corrects a heading found wrong (the
    # module docstring): in either case the bias and the offset error are consider states
    update_h(s, dx, h, r, rv, True, False, tilt_unsettled(P, p) or after_run)
    inject(s, dx)
    s.t_mag_update = t
    s.mag_used = True


@njit(cache=True, error_model="numpy")
def _rejected(s, R, h, r, rv, t, p):
    """A gate rejection of a clean-looking field (innovation r): the run's statistics; re-acquisition once
    the run spans the fields behind the heading (``t_heading_set`` to ``t_mag_update``), within two of c's
    correlation times and ``mag.reacquire_s``, and its innovations agree about a line in time (a lost heading
    is off by one angle that drifts at the gyro bias's error; the module docstring)."""
    ln = s.reject_line
    if not np.isfinite(s.t_reject) or not np.isfinite(s.t_reject_start):
        s.t_reject_start = t
        s.reject_r0 = r
        for i in range(5):
            ln[i] = 0.0
    else:
        a = ew_alpha(t - s.t_reject, p.mag.reacquire_s)
        tau = t - s.t_reject_start
        x = wrap(r - s.reject_r0)
        for i, v in enumerate((tau, tau * tau, x, tau * x, x * x)):
            ln[i] += a * (v - ln[i])
    s.t_reject = t
    need = p.mag.reacquire_s
    if np.isfinite(s.t_heading_set) and np.isfinite(s.t_mag_update):
        need = min(need, max(s.t_mag_update - s.t_heading_set, 2.0 * p.mag.error_tau_s))
    if p.mag.reacquire_s <= 0.0 or t - s.t_reject_start < need:
        return
    var_t = ln[1] - ln[0] * ln[0]
    cov = ln[3] - ln[0] * ln[2]
    var_x = ln[4] - ln[2] * ln[2]
    slope = cov / var_t if var_t > 0.0 else 0.0
    P = s.P  # the bias's variance about up (R's row 2: up in device coordinates), the same quadratic form
    sb_up = np.sqrt(max(offset_heading_var(R[2], P[BIAS : BIAS + 3, BIAS : BIAS + 3]), 0.0))
    if abs(slope) > DRIFT_K * sb_up:
        slope = 0.0  # faster than the gyro can drift: a turning field, judged about its mean
    res = var_x - 2.0 * slope * cov + slope * slope * var_t
    if res > p.mag.reacquire_spread_rad**2:
        return
    jump = wrap(s.reject_r0 + ln[2] + slope * (t - s.t_reject_start - ln[0]))
    _reacquire(s, R, jump, h, rv, t, p)


@njit(cache=True, error_model="numpy")
def _reacquire(s, R, jump, h, rv, t, p):
    """Turn the attitude about up by ``jump`` onto the magnetometer's heading, the bias variance about up
    grown by the drift the jump implies (the module docstring)."""
    dt_ref = t - s.t_mag_update if np.isfinite(s.t_mag_update) else 0.0
    _set_heading(s, h, jump, rv, t, s.t_reject_start)  # the new heading rests on the run's fields
    rotation_matrix(s.q, R)
    _bias_drift_var(s, R, jump, dt_ref, p)


@njit(cache=True, error_model="numpy")
def _bias_drift_var(s, R, angle, dt, p):
    """A heading error ``angle`` (rad) found after ``dt`` (s) implies a gyro drift ``angle / dt`` about up:
    the bias variance about up (``R`` the rotation matrix, its row 2 up in device coordinates) grows by
    ``min((angle / max(dt, 10 s))², σ_b0²)`` — short runs say little about a rate, and no drift beyond
    the bias prior's."""
    vb = min((angle / max(dt, 10.0)) ** 2, bias_prior_var(s, p))
    P = s.P
    for i in range(3):
        for m in range(3):
            P[BIAS + i, BIAS + m] += vb * R[2, i] * R[2, m]


@njit(cache=True, error_model="numpy")
def _heading_gradient(R, ex, ny, g):
    """``g ← ∂ψ/∂m_d = (m_y R_x − m_x R_y) / B_h²`` (rows x, y of R; ``m_x, m_y`` the field's east and
    north components): how the heading turns with the calibrated field in the device frame."""
    bh2 = ex * ex + ny * ny
    for m in range(3):
        g[m] = (ny * R[0, m] - ex * R[1, m]) / bh2 if bh2 > 0.0 else 0.0


@njit(cache=True, error_model="numpy")
def _calibration_variance(s, g, p):
    """The heading gradient g of this sample (:func:`_heading_gradient`) kept in ``cal_g`` (the std's floor
    takes a new ``Σ_b`` or a suspected shift at once: :func:`pdr_mag.fusion.kernel.calibration_floor`), and
    without the offset states ``cal_var = g Σ_b gᵀ``, the heading variance that the
    calibration's offset uncertainty ``Σ_b`` (device frame) causes at this orientation (c's stationary
    variance then carries it, :func:`pdr_mag.fusion.gyro.magerr_var`; with them the filter carries that error
    in ``P`` and reads no ``cal_var``)."""
    for i in range(3):
        s.cal_g[i] = g[i]
    if not p.mag.offset_states:
        s.cal_var = offset_heading_var(g, s.cal_cov)


@njit(cache=True, error_model="numpy")
def offset_heading_var(g, C):
    """``g C gᵀ``: the heading variance (rad²) an offset error of covariance C (µT², device frame) causes
    where the heading's gradient is g (rad/µT)."""
    v = 0.0
    for i in range(3):
        v += g[i] * (C[i, 0] * g[0] + C[i, 1] * g[1] + C[i, 2] * g[2])
    return v


@njit(cache=True, error_model="numpy")
def _change_of(D, e, x, y, z):
    """``dm = D m + e``: how a noted calibration change moves the calibrated field ``m = (x, y, z)``."""
    return (D[0, 0] * x + D[0, 1] * y + D[0, 2] * z + e[0],
            D[1, 0] * x + D[1, 1] * y + D[1, 2] * z + e[1],
            D[2, 0] * x + D[2, 1] * y + D[2, 2] * z + e[2])  # fmt: skip


@njit(cache=True, error_model="numpy")
def _calibration_jump(s, g, mx, my, mz, R, t, p, usable):
    """A calibration change noted since the last usable sample (``dm = D m + e``, m this calibrated sample,
    :meth:`pdr_mag.fusion.FusionCore.note_calibration_change`): the heading variance grows by the square of
    the turn ``v`` the change makes, capped at π², once the heading is known: the larger of its first-order
    turn ``g · dm`` and the exact turn between the headings of the horizontal fields ``R m`` and
    ``R (m − dm)`` — a change as large as the horizontal field may turn it by anything, which the gradient
    does not see (an offset error along the field that reversed it).  With this sample not ``usable``
    (flagged, or held out by the caller: its direction is not to be trusted) the gradient is the latest
    usable sample's and m its field ``cal_m`` as the new calibration gives it (``o + D o + e`` for its old
    field o, to first order in D; the first-order turn alone before any).  The old calibration's heading
    error changed as the device turned, and the filter read those changes as gyro drift: the bias variance
    about up grows by ``min((v / max(Δt, 10 s))², σ_b0²)`` (Δt: how long the old calibration was in
    force), the drift rate that error implies, as at a re-acquisition."""
    D, e = s.cal_jump_d, s.cal_jump_e
    if not _jump_noted(D, e):
        return
    if s.init >= 2:
        dx, dy, dz = _change_of(D, e, mx, my, mz)
        v = g[0] * dx + g[1] * dy + g[2] * dz
        if not usable and np.isfinite(s.cal_m[0]):
            o = s.cal_m
            dx, dy, dz = _change_of(D, e, o[0], o[1], o[2])
            mx, my, mz = o[0] + dx, o[1] + dy, o[2] + dz
            dx, dy, dz = _change_of(D, e, mx, my, mz)
            usable = True
        if usable:
            ox, oy, oz = mx - dx, my - dy, mz - dz  # the old calibration's field, m − dm
            new_e = R[0, 0] * mx + R[0, 1] * my + R[0, 2] * mz
            new_n = R[1, 0] * mx + R[1, 1] * my + R[1, 2] * mz
            old_e = R[0, 0] * ox + R[0, 1] * oy + R[0, 2] * oz
            old_n = R[1, 0] * ox + R[1, 1] * oy + R[1, 2] * oz
            turn = wrap(np.arctan2(new_e, new_n) - np.arctan2(old_e, old_n))
            if abs(turn) > abs(v):
                v = turn
        P = s.P
        P[TH_Z, TH_Z] = min(P[TH_Z, TH_Z] + v * v, np.pi**2)
        _bias_drift_var(s, R, v, t - s.t_cal_start if np.isfinite(s.t_cal_start) else 0.0, p)
        s.t_cal_start = t
    for i in range(3):
        e[i] = 0.0
        for m in range(3):
            D[i, m] = 0.0


@njit(cache=True, error_model="numpy")
def _jump_noted(D, e):
    """Whether a calibration change is noted (``D`` or ``e`` not all zero), without a temporary array: it is
    asked at every magnetometer sample."""
    for i in range(3):
        if e[i] != 0.0:
            return True
        for m in range(3):
            if D[i, m] != 0.0:
                return True
    return False


@njit(cache=True, error_model="numpy")
def _environment_step(s, dmin2, t, det, p):
    """The environment's disturbance level: EW mean of ``d_min²`` over ``mag.env_tau_s`` (from the prior
    ``mag.env_prior_uT``: the filter's weighting) and the same over the samples seen only, normalised by
    their weight (the reported std's, :func:`pdr_mag.fusion.gyro.unmodelled_var`), and the local
    reference's horizontal strength ``B_h = F_loc cos I_loc`` (they set the stationary variance of c)."""
    if np.isfinite(s.t_env):
        a = ew_alpha(t - s.t_env, p.mag.env_tau_s)
        s.env_d2 += a * (dmin2 - s.env_d2)
        s.env_seen2, s.env_w = _ew_seen(s.env_seen2, s.env_w, dmin2, a)
    else:  # the first sample is the level seen until the next (its weight is nil)
        s.env_d2 = max(dmin2, p.mag.env_prior_uT**2)
        s.env_seen2 = dmin2
    s.t_env = t
    bh_ref = reference_horizontal(det)
    if np.isfinite(bh_ref):
        s.bh_ref = bh_ref
    s.u_var = unmodelled_var(s, p)


@njit(cache=True, error_model="numpy")
def _ew_seen(mean, w, x, a):
    """One sample x into an exponentially weighted mean of the samples seen (weight ``a`` of this one):
    ``w ← w + a (1 − w)``, ``mean ← mean + a (x − mean) / w`` — normalised by the weight seen, so it is
    not pulled towards a start value.  Returns ``(mean, w)``."""
    w = w + a * (1.0 - w)
    if w > 0.0:
        mean += a * (x - mean) / w
    return mean, w


@njit(cache=True, error_model="numpy")
def _flag_share_step(s, flag, t, det, p):
    """The share of flagged samples, EW over ``mag.env_tau_s`` and normalised by the weight of the samples
    seen (so the first seconds give the share of what was seen, not a mean pulled towards the first
    sample), and the disturbance the detectors' tolerance stands for, ``tol_F² + (F tol_I)²`` (they set
    the consider covariance's part of c, :func:`pdr_mag.fusion.gyro.unmodelled_var`)."""
    x = 1.0 if flag else 0.0
    if np.isfinite(s.t_flag):
        s.flag_share, s.flag_w = _ew_seen(s.flag_share, s.flag_w, x, ew_alpha(t - s.t_flag, p.mag.env_tau_s))
    else:  # the first sample is the share seen until the next (its weight is nil)
        s.flag_share = x
    s.t_flag = t
    s.flag_d2 = tolerance2(det)
    s.u_var = unmodelled_var(s, p)


@njit(cache=True, error_model="numpy")
def _first_fix(s, h, r, rv, t, p):
    """Set the heading from the first usable sample (residual r, noise rv; the module docstring)."""
    P = s.P
    P[C_ERR, C_ERR] = max(P[C_ERR, C_ERR], magerr_var(s, p))  # a coarse calibration's error from the start
    b = horizontal_ref(s)
    if b > 0.0:  # and the place's turning, unseen yet (the module docstring)
        place = p.mag.error_std_rad**2 + UNSEEN_SHARE * (p.mag.env_prior_uT / b) ** 2
        P[C_ERR, C_ERR] = max(P[C_ERR, C_ERR], place)
    settle_u(s)
    s.U[C_ERR, C_ERR] = max(s.U[C_ERR, C_ERR], s.u_var)  # and the place's, from the start too
    rotate_world(s.q_gyro, 0.0, 0.0, r)
    _turn_world_frame(s, r)
    _heading_from_field(P, h, rv)
    _heading_from_field(s.U, h, 0.0)
    s.init = 2
    s.fix_beyond_linear = tilt_beyond_linear(P)
    s.t_heading_set = t
    s.t_mag_update = t
    s.t_cal_start = t
    s.mag_used = True


@njit(cache=True, error_model="numpy")
def history_fix(s, r, var, span, t, p):
    """Set the heading of a filter that has none from the azimuth of many past fields (the module
    docstring, "First heading from the first fit's own samples"): the turn ``r`` (rad, onto the fields'
    heading less the declination) and the variance ``var`` of the fields' mean azimuth (rad², their c
    included: :meth:`pdr_mag.fusion.FusionCore.fix_heading_from_history`), the fields spanning ``span``
    seconds up to ``t``.  The consider part U gets c's unmodelled variance averaged over the span,
    ``k = 2τ/T (1 − τ/T (1 − e^(−T/τ)))`` of it (the variance of an Ornstein–Uhlenbeck process's mean over
    T, c's correlation time τ); the heading's error is uncorrelated with the c of the fields to come."""
    P = s.P
    U = s.U
    P[C_ERR, C_ERR] = max(P[C_ERR, C_ERR], magerr_var(s, p))
    settle_u(s)
    U[C_ERR, C_ERR] = max(U[C_ERR, C_ERR], s.u_var)
    tau = p.mag.error_tau_s
    k = 1.0
    if span > 0.0 and tau > 0.0:
        x = span / tau
        k = min(2.0 / x * (1.0 - (1.0 - np.exp(-x)) / x), 1.0)
    rotate_world(s.q_gyro, 0.0, 0.0, r)
    _turn_world_frame(s, r)
    for i in range(NX):
        P[TH_Z, i] = 0.0
        P[i, TH_Z] = 0.0
        U[TH_Z, i] = 0.0
        U[i, TH_Z] = 0.0
    P[TH_Z, TH_Z] = min(var, np.pi**2)
    U[TH_Z, TH_Z] = k * U[C_ERR, C_ERR]
    s.init = 2
    s.guess_w = 0.0
    s.t_heading_set = t - span  # the heading rests on the fields of the span
    # a mean this uncertain may be beyond the linear range as well: the first update is then a re-fix
    s.fix_beyond_linear = tilt_beyond_linear(P) or var > LINEAR_RAD**2
    s.t_mag_update = t
    s.t_cal_start = t
    s.mag_used = True


@njit(cache=True, error_model="numpy")
def _refine_guess(s, r, w, t):
    """A flagged field of weight w (:func:`_guess_weight`) while the heading is a guess (residual r): the
    guess becomes the weighted mean of the flagged fields' headings so far, ``W ← W + w``, applied as the
    attitude correction ``δθ_z = w r / W`` (:func:`pdr_mag.fusion.eskf.inject`: the world-frame quantities
    turn with it); P is left as it is, the heading's variance π² (the module docstring)."""
    if not w > 0.0:
        return
    s.guess_w += w
    dx = np.zeros(NX)
    dx[TH_Z] = w * r / s.guess_w
    inject(s, dx)
    s.t_mag_update = t


@njit(cache=True, error_model="numpy")
def _guess_weight(s, det, bh, dmin2, p):
    """Weight of a flagged field's heading in the guess (the module docstring): ``1 / (σ_h² + d² / B²)``, 0
    when ``d ≥ B``.  ``d`` is the larger of the detectors' ``d_min`` (``dmin2`` its square at this sample,
    against the local references, if learnt) and the deviation from the reference field,
    ``√((F − F_ref)² + (F (I − I_ref))²)`` (the parts known: a flagged start has learnt no local reference);
    B the expected horizontal strength — the local reference's once learnt, else the reference field's
    ``F_ref cos I_ref`` (``F_ref`` while its dip is to be learnt, the measured ``bh`` without either)."""
    x = det.x
    d2_abs = 0.0
    if np.isfinite(s.f_ref):
        d2_abs += (x.f - s.f_ref) ** 2
    if np.isfinite(s.dip_ref):
        d2_abs += (x.f * np.radians(x.dip - s.dip_ref)) ** 2
    d2 = max(dmin2, d2_abs)
    b = s.bh_ref
    if not b > 0.0:
        b = s.f_ref * np.cos(np.radians(s.dip_ref)) if np.isfinite(s.dip_ref) else s.f_ref
    if not b > 0.0:
        b = bh
    if not d2 < b * b:  # NaN (a dip not yet known at this sample) weighs nothing either
        return 0.0
    return 1.0 / (p.mag.noise_rad**2 + d2 / (b * b))


@njit(cache=True, error_model="numpy")
def _set_heading(s, h, r, rv, t, since):
    """Set the heading from the field anew (residual r: the turn, reported in ``heading_reset_deg``), as at
    the first fix: a re-acquisition (:func:`_reacquire`), and the first heading update once the tilt is
    settled that finds a first fix made through an unsettled tilt more than ``LINEAR_RAD`` off (the module
    docstring; no bias variance is added then: no heading update has taught the bias since the first fix);
    ``since``: when the fields it now rests on began (``t_heading_set``: the re-acquisition's support)."""
    _turn_world_frame(s, r)
    _heading_from_field(s.P, h, rv)
    settle_u(s)
    _heading_from_field(s.U, h, 0.0)
    s.guess_w = 0.0
    s.fix_beyond_linear = False
    s.t_reject = np.nan
    s.t_reject_start = np.nan
    s.reset_jump += r
    s.t_heading_set = since
    s.t_mag_update = t
    s.mag_used = True


@njit(cache=True, error_model="numpy")
def _turn_world_frame(s, angle):
    """Turn the attitude about up by ``angle``; the world-frame quantities the filter carries turn with it
    (the averaged specific force over both windows and their mean R) or restart (the detectors' mean field
    direction)."""
    rotate_world(s.q, 0.0, 0.0, angle)
    c, sn = np.cos(angle), np.sin(angle)
    if np.isfinite(s.acc_w[0]):
        for aw in (s.acc_w, s.acc_w_long):
            x0, y0 = aw[0], aw[1]
            aw[0], aw[1] = c * x0 - sn * y0, sn * x0 + c * y0
    Rb = s.R_bar
    for m in range(3):
        x0, y0 = Rb[0, m], Rb[1, m]
        Rb[0, m], Rb[1, m] = c * x0 - sn * y0, sn * x0 + c * y0
    restart(s.det)


@njit(cache=True, error_model="numpy")
def _heading_from_field(P, h, rv):
    """Covariance ``P`` after a heading taken from the field (row h, noise rv): the residual is then zero, so
    ``δθ_z = −(h′·δx′ + n)`` over the other states (the tilt, c and the offset error; the module docstring);
    rv = 0 for the consider covariance ``U`` (the noise the weighting leaves out is all in its c)."""
    z = TH_Z
    for i in range(NX):
        P[z, i] = 0.0
        P[i, z] = 0.0
    col = np.zeros(NX)  # P h′: the heading's row and column are zero now, so P h
    for j in range(NX):
        for k in range(NX):
            col[j] += P[j, k] * h[k]
    v = rv
    for j in range(NX):
        v += h[j] * col[j]
    P[z, z] = v
    for j in range(NX):
        if j != z:
            P[z, j] = -col[j]
            P[j, z] = -col[j]
