"""Error-state Kalman filter algebra of the fusion kernel (numba, scalar code).

The attitude error is a world-frame rotation vector: ``R_true = Exp(δθ) R``, so an estimated correction
``δθ`` is injected as ``q ← Exp(δθ) ⊗ q`` (:mod:`pdr_mag.fusion.quat`).

Measurements are processed as scalars: with ``H`` one row, ``S = H P Hᵀ + r_v``, ``K = P Hᵀ / S``,
``δx ← δx + K (r − H δx)`` (``r`` the residual before this update: several scalar updates accumulate in
one ``δx`` that is injected once) and ``P ← P − K H P``.  With *consider* states (Schmidt–Kalman) the gain
of those states is set to zero and ``P`` follows the Joseph form for that gain,
``P ← P − k cᵀ − c kᵀ + S k kᵀ`` with ``c = P Hᵀ``, valid for any gain.

Every update also carries the filter's second covariance ``U`` with the same gain,
``U ← (I − k H) U (I − k H)ᵀ`` (:func:`carry`), after the prediction pending on it (:func:`settle_u`):
``U`` is the covariance of the error that noise the filter's weighting leaves out causes
(:mod:`pdr_mag.fusion.gyro`); it never changes a gain.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from pdr_mag.fusion.detectors import turn
from pdr_mag.fusion.quat import rotate_vector, rotate_world
from pdr_mag.fusion.state import BIAS, C_ERR, NX, OFFSET, TH_X, TH_Y, TH_Z

#: the largest tilt error the linearised updates treat as small (the accelerometer's bias terms, the
#: magnetometer's heading row), rad
LINEAR_RAD = 0.35


# ------------------------------------------------------------------------------------------ scalar updates
@njit(cache=True, error_model="numpy")
def update(s, dx, j, a, r, rv):
    """Scalar update of record ``s`` with ``H = a·e_j``; r the residual before this update, rv its noise
    variance; ``U`` carried with the same gain."""
    settle_u(s)
    P = s.P
    col = np.empty(NX)
    for i in range(NX):
        col[i] = a * P[i, j]
    r = r - a * dx[j]
    S = a * col[j] + rv
    if S <= 0.0:
        return
    k = np.empty(NX)
    for i in range(NX):
        k[i] = col[i] / S
        dx[i] += k[i] * r
    for i in range(NX):
        for m in range(NX):
            P[i, m] -= k[i] * col[m]
    U = s.U
    for i in range(NX):  # col, no longer needed, takes U h
        col[i] = a * U[i, j]
    carry(U, k, col, a * col[j])


@njit(cache=True, error_model="numpy")
def carry(U, k, uh, hu):
    """``U ← (I − k hᵀ) U (I − k hᵀ)ᵀ``: the consider covariance through an update of gain k and row h,
    given ``uh = U h`` and ``hu = hᵀ U h`` (symmetric: the upper triangle, mirrored)."""
    for i in range(NX):
        for m in range(i, NX):
            v = U[i, m] + hu * k[i] * k[m] - k[i] * uh[m] - uh[i] * k[m]
            U[i, m] = v
            U[m, i] = v


@njit(cache=True, error_model="numpy")
def update_h(s, dx, h, r, rv, consider_tilt, consider_heading=False, consider_bias=False):
    """Scalar update of record ``s`` with a general ``H = h``; with ``consider_tilt`` the tilt errors
    (δθ_x, δθ_y), with ``consider_heading`` the heading errors (δθ_z and δc), with ``consider_bias`` the gyro
    bias and the calibration's offset error (the slow states that a correction of a heading found wrong
    would otherwise be taught) are consider states (zero gain, Joseph form); ``U`` carried with the same
    gain."""
    settle_u(s)
    P = s.P
    col = np.empty(NX)
    for i in range(NX):
        v = 0.0
        for m in range(NX):
            v += P[i, m] * h[m]
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
        k[TH_X] = 0.0
        k[TH_Y] = 0.0
    if consider_heading:
        k[TH_Z] = 0.0
        k[C_ERR] = 0.0
    if consider_bias:
        for i in range(3):
            k[BIAS + i] = 0.0
            k[OFFSET + i] = 0.0
    for i in range(NX):
        dx[i] += k[i] * r
    for i in range(NX):
        for m in range(NX):
            P[i, m] += S * k[i] * k[m] - k[i] * col[m] - col[i] * k[m]
    U = s.U
    hu = 0.0
    for i in range(NX):  # col, no longer needed, takes U h
        v = 0.0
        for m in range(NX):
            v += U[i, m] * h[m]
        col[i] = v
        hu += h[i] * v
    carry(U, k, col, hu)


@njit(cache=True, error_model="numpy")
def settle_u(s):
    """Bring ``U`` up to date: the prediction steps since it last was, ``Φ_k = [[I, G_k, 0], [0, I, 0],
    [0, 0, φ_k]]`` with ``G_k = −R_k Δt_k``, multiply to ``Φ = [[I, ΣG_k, 0], [0, I, 0], [0, 0, Πφ_k]]``
    exactly, and c's unmodelled noise over them sums to ``V_u (1 − Πφ_k²)``: so ``U`` is propagated once per
    update rather than per gyroscope sample (its noise enters through c alone)."""
    if not s.u_pending:
        return
    phi = s.u_phi
    G = s.u_G
    U = s.U
    for m in range(NX):  # U ← Φ U (rows of δb unchanged, so in place)
        for i in range(3):
            U[i, m] += G[i, 0] * U[3, m] + G[i, 1] * U[4, m] + G[i, 2] * U[5, m]
        U[6, m] *= phi
    for m in range(NX):  # … Φᵀ
        for i in range(3):
            U[m, i] += U[m, 3] * G[i, 0] + U[m, 4] * G[i, 1] + U[m, 5] * G[i, 2]
        U[m, 6] *= phi
    U[6, 6] += s.u_var * (1.0 - phi * phi)
    for i in range(NX):  # the row and column passes agree but for rounding: keep U exactly symmetric
        for m in range(i + 1, NX):
            U[m, i] = U[i, m]
    if U[TH_Z, TH_Z] > np.pi**2:  # an unknown heading is uniform
        fs = np.pi / np.sqrt(U[TH_Z, TH_Z])
        for i in range(NX):
            U[TH_Z, i] *= fs
            U[i, TH_Z] *= fs
    for i in range(3):
        for m in range(3):
            G[i, m] = 0.0
    s.u_phi = 1.0
    s.u_pending = False


@njit(cache=True, error_model="numpy")
def heading_var_u(s):
    """``U[δθ_z, δθ_z]`` with the pending prediction applied (for an output row; ``U`` itself untouched):
    ``U_zz + 2 g·U[δb, δθ_z] + g U_bb gᵀ``, g row z of ``ΣG_k``."""
    U = s.U
    g0, g1, g2 = s.u_G[2, 0], s.u_G[2, 1], s.u_G[2, 2]
    v = U[2, 2] + 2.0 * (g0 * U[3, 2] + g1 * U[4, 2] + g2 * U[5, 2])
    v += g0 * (g0 * U[3, 3] + g1 * U[3, 4] + g2 * U[3, 5])
    v += g1 * (g0 * U[4, 3] + g1 * U[4, 4] + g2 * U[4, 5])
    v += g2 * (g0 * U[5, 3] + g1 * U[5, 4] + g2 * U[5, 5])
    return v


@njit(cache=True, error_model="numpy")
def tilt_beyond_linear(P):
    """Whether the tilt's variance ``P_xx + P_yy`` exceeds ``2 · LINEAR_RAD²``: a tilt this uncertain may be
    tens of degrees off, beyond what a linearised heading row describes."""
    return P[TH_X, TH_X] + P[TH_Y, TH_Y] > 2.0 * LINEAR_RAD**2


@njit(cache=True, error_model="numpy")
def tilt_unsettled(P, p):
    """Whether the tilt is less certain than a start at rest (``tr P_tilt > 2 tilt0_std²``): a start in
    motion.  Then a far-off average is the tilt's, and the heading's changes are the tilt's, not the gyro
    bias's (:mod:`pdr_mag.fusion.accel`, :mod:`pdr_mag.fusion.mag`)."""
    return P[TH_X, TH_X] + P[TH_Y, TH_Y] > 2.0 * p.accel.tilt0_std**2


@njit(cache=True, error_model="numpy")
def inject(s, dx):
    """Apply the error estimate ``dx`` to the nominal state of record ``s`` and zero it.

    The world-frame quantities the filter carries — the averaged specific force ``acc_w`` and
    ``acc_w_long`` and the detectors' world-frame state (:func:`pdr_mag.fusion.detectors.turn`) — turn with
    the attitude correction, so they stay in the corrected frame (the consistency check then measures the
    field's motion against the gyro-propagated frame, whatever the filter concluded from it).
    """
    ex, ey, ez = dx[TH_X], dx[TH_Y], dx[TH_Z]
    rotate_world(s.q, ex, ey, ez)
    if np.isfinite(s.acc_w[0]):
        rotate_vector(s.acc_w, ex, ey, ez)
        rotate_vector(s.acc_w_long, ex, ey, ez)
    turn(s.det, ex, ey, ez)
    for i in range(3):
        s.b[i] += dx[BIAS + i]
    s.c += dx[C_ERR]
    for i in range(3):
        s.offset[i] += dx[OFFSET + i]
    for i in range(NX):
        dx[i] = 0.0
    P = s.P
    for i in range(NX):  # keep P symmetric (U is kept so by carry and settle_u)
        for m in range(i + 1, NX):
            v = 0.5 * (P[i, m] + P[m, i])
            P[i, m] = v
            P[m, i] = v
