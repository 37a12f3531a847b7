"""Magnetic interference detectors: is the calibrated field the Earth's?

Four checks, each a score that is ≥ 1 when the field fails it (seed 003 §4 motivates the first two: "the
modulus of the magnetometer and its variance as the criterion of magnetic interference"):

strength
    ``s_F = max(|F − F_loc| / tol_F, |F − F_ref| / (band · F_ref))`` with ``F = |m_d|`` the calibrated
    strength, ``F_ref`` the reference strength (the calibration radius when the caller gives one, else the
    World Magnetic Model), ``F_loc`` the local strength learnt from clean samples (starts at ``F_ref``,
    time constant ``learn_ref_s``; indoor fields differ from the WMM by several µT) and
    ``tol_F = max(strength_tol_uT, strength_tol_rel · F_ref)``.
variance
    ``s_V = var_τ(F) / var_max`` with ``var_τ`` an exponentially weighted variance of F over the time
    constant ``τ = var_window_s`` (irregular sampling: weight ``α = 1 − exp(−Δt/τ)`` per sample).
dip
    ``s_I = max(|I − I_loc| / dip_tol_deg, |I − I_ref| / dip_band_deg)`` with the measured dip
    ``I = asin(−(m_d · u_d) / |m_d|)`` from the calibrated field and the device-frame up direction ``u_d``
    (the filter's gravity estimate), ``I_ref`` the reference inclination (WMM) and ``I_loc`` the local
    dip learnt like ``F_loc`` (without a reference: learnt from the first clean samples).
gyro consistency
    a field fixed in the world frame stays fixed when rotated by the filter's attitude
    ``m_w = R_wd m_d``; its direction is compared with an exponentially weighted mean direction
    ``m̄_w`` (time constant ``consistency_window_s``), which the fusion rotates with every correction it
    applies to the attitude (so the angle is the field's motion against the gyro-propagated frame, not
    hidden by the filter following a disturbed field):
    ``s_G = ∠(m_w, m̄_w) / (consistency_tol_deg + k σ_b consistency_window_s)``, widened by the filter's
    bias uncertainty σ_b so that drift the filter knows it may have does not fire it.
    A field that turns in the device frame without the device turning (a passing magnet, a car) moves
    ``m_w``; the Earth's does not.

The score is ``max(s_F, s_V, s_I, s_G)``.  The flag uses hold-off timers so it neither flickers nor
sticks: it rises after the score has been ≥ 1 for ``hold_on_s`` and falls after the score has stayed < 1
for ``hold_off_s``.  The local references are learnt only from samples inside the loose bands around the
references with low variance and consistency scores, so a disturbance cannot drag them.

Two levels.  The default thresholds flag *gross* disturbances (a magnet, a steel door: ±14 µT, ±15° of
dip, 30° of turn, 100 µT² of variance) — the fusion skips those samples.  Below the thresholds the
fusion does not trust the field blindly either: it weights each sample by the smallest disturbance that
explains the deviations measured here (:mod:`pdr_mag.fusion.mag`).  Tight thresholds alone reject
most of an indoor walk (the building's field wanders by several µT and degrees) and leave the heading
to the gyroscope for too long; measured on the tyrex walks, the two levels together do better than
either.

Two forms: :func:`detect_step` (``@njit``, one sample, its state in a record of :data:`DETECTOR_STATE`),
which the fusion kernel (:mod:`pdr_mag.fusion.mag`) calls per magnetometer sample, and vectorised numpy
functions for arrays (:func:`strength_score`, :func:`dip_deg`, :func:`windowed_variance`,
:func:`consistency_angle_deg`, :func:`hold_off`) that give the same numbers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from pdr_mag._records import settings_dtype, settings_record


@dataclass(frozen=True)
class InterferenceSettings:
    """Thresholds of the interference detectors (all documented in the module docstring).

    Attributes
    ----------
    strength_tol_uT : float
        Minimum half-width of the accepted strength band, µT.
    strength_tol_rel : float
        Half-width of the strength band relative to the reference strength.
    var_window_s : float
        Time constant of the exponentially weighted strength variance, s.
    var_max_uT2 : float
        Variance of the strength above which the field is flagged, µT².
    dip_tol_deg : float
        Half-width of the accepted dip band around the reference inclination, deg.
    consistency_window_s : float
        Time constant of the mean world-frame field direction, s.
    consistency_tol_deg : float
        Angle between the current and the mean world-frame field direction above which the field is
        flagged, deg.
    hold_on_s : float
        The score must stay ≥ 1 this long before the flag rises, s.
    hold_off_s : float
        The score must stay < 1 this long before the flag falls, s.
    learn_ref_s : float
        Time constant with which the local strength and dip references are learnt from clean samples, s
        (indoor fields differ from the WMM by several µT and degrees; the learnt values start at the
        reference and follow the local field slowly).
    strength_band_rel : float
        The learnt strength may not leave ``F_ref (1 ± strength_band_rel)``: samples outside are flagged.
    dip_band_deg : float
        The learnt dip may not leave ``I_ref ± dip_band_deg``: samples outside are flagged.
    consistency_bias_k : float
        The consistency tolerance is widened by ``k · σ_b · consistency_window_s`` (σ_b the filter's gyro
        bias uncertainty), so the check cannot fire on drift the filter knows it may have.
    """

    strength_tol_uT: float = 10.0
    strength_tol_rel: float = 0.3
    var_window_s: float = 1.0
    var_max_uT2: float = 100.0
    dip_tol_deg: float = 15.0
    consistency_window_s: float = 2.0
    consistency_tol_deg: float = 30.0
    hold_on_s: float = 0.0
    hold_off_s: float = 0.5
    learn_ref_s: float = 30.0
    strength_band_rel: float = 0.4
    dip_band_deg: float = 25.0
    consistency_bias_k: float = 3.0

    def __post_init__(self):
        for name in (
            "strength_tol_uT",
            "strength_tol_rel",
            "var_window_s",
            "var_max_uT2",
            "dip_tol_deg",
            "consistency_window_s",
            "consistency_tol_deg",
            "learn_ref_s",
            "strength_band_rel",
            "dip_band_deg",
        ):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"{name}: expected a positive finite number, got {v!r}")
        for name in ("hold_on_s", "hold_off_s"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"{name}: expected a non-negative finite number, got {v!r}")

    def as_params(self) -> np.ndarray:
        """The thresholds as the compiled detectors read them: a one-element array of :data:`PARAMS`."""
        return settings_record(self)


#: the thresholds as the compiled detectors read them: one float64 field per :class:`InterferenceSettings`
#: attribute, same name and unit (:func:`pdr_mag._records.settings_dtype`)
PARAMS = settings_dtype(InterferenceSettings)


# ----------------------------------------------------------------------------------------------- scalar
@njit(cache=True, error_model="numpy")
def strength_tol(ref_uT, p):
    """Half-width of the accepted strength band, µT."""
    return max(p.strength_tol_uT, p.strength_tol_rel * ref_uT)


@njit(cache=True, error_model="numpy")
def dip_of(mx, my, mz, ux, uy, uz):
    """Dip (deg, positive below the horizon) of field m against the unit up direction u."""
    n = np.sqrt(mx * mx + my * my + mz * mz)
    if n <= 0.0:
        return np.nan
    s = -(mx * ux + my * uy + mz * uz) / n
    s = min(1.0, max(-1.0, s))
    return np.degrees(np.arcsin(s))


@njit(cache=True, error_model="numpy")
def ew_alpha(dt, tau):
    """Weight of a new sample in an exponentially weighted mean with time constant tau."""
    if dt <= 0.0:
        return 0.0
    return 1.0 - np.exp(-dt / tau)


@njit(cache=True, error_model="numpy")
def angle_deg(ax, ay, az, bx, by, bz):
    """Angle between two vectors, deg."""
    cx = ay * bz - az * by
    cy = az * bx - ax * bz
    cz = ax * by - ay * bx
    return np.degrees(np.arctan2(np.sqrt(cx * cx + cy * cy + cz * cz), ax * bx + ay * by + az * bz))


@njit(cache=True, error_model="numpy")
def hold_step(flag, since, score, t, p):
    """One step of the hold-off timer.

    ``since`` is the time the score last changed side of 1 (NaN = unknown).  Returns (flag, since).
    """
    bad = score >= 1.0
    if bad != flag:
        if not np.isfinite(since):
            since = t
        wait = p.hold_on_s if bad else p.hold_off_s
        if t - since >= wait:
            flag = bad
            since = np.nan
    else:
        since = np.nan
    return flag, since


# ------------------------------------------------------------------------------------------ detector state
#: the detectors' state for one magnetometer stream (nested in the fusion filter's state), and the figures of
#: its latest sample (the fusion's noise model and diagnostics read them)
DETECTOR_STATE = np.dtype(
    [
        ("t", np.float64),  # time of the last sample, s (NaN: none yet)
        ("f_mean", np.float64),  # EW mean of the strength F, µT (NaN: restart)
        ("f2_mean", np.float64),  # EW mean of F², µT²
        ("mw", np.float64, (3,)),  # EW mean m̄_w of the world-frame field direction (NaN in x: restart)
        ("f_loc", np.float64),  # learnt local strength F_loc, µT (NaN: nothing learnt)
        ("dip_loc", np.float64),  # learnt local dip I_loc, deg
        ("n_learn", np.int64),  # clean samples learnt from
        ("flag", np.bool_),  # interference flag, after the hold timers
        ("since", np.float64),  # hold timer: when the score changed side of 1 (NaN: no change pending)
        # the latest sample
        ("f", np.float64),  # strength F, µT
        ("dip", np.float64),  # dip I, deg
        ("tol_f", np.float64),  # half-width tol_F of the strength band, µT
        ("tol_dip", np.float64),  # half-width of the dip band, deg
        ("var", np.float64),  # var_τ(F), µT²
        ("cons", np.float64),  # gyro-consistency angle ∠(m_w, m̄_w), deg
        ("score_f", np.float64),  # strength score s_F
        ("score_dip", np.float64),  # dip score s_I
        ("score", np.float64),  # max of the four scores
    ],
    align=True,
)


def new_detector_state() -> np.void:
    """A fresh detector state (nothing learnt, flag down): one record of :data:`DETECTOR_STATE`."""
    det = np.zeros(1, dtype=DETECTOR_STATE)
    for name in DETECTOR_STATE.names:
        if DETECTOR_STATE[name].base == np.float64:
            det[name] = np.nan
    return det[0]


@njit(cache=True, error_model="numpy")
def detect_step(det, f, dip, mwx, mwy, mwz, t, fref, dipref, sigma_b_deg, ip):
    """All four checks and the hold timer for one calibrated sample (the formulas of the module docstring).

    Parameters
    ----------
    det : DETECTOR_STATE record
        Detector state, updated in place; its fields ``f`` … ``score`` receive this sample's figures.
    f, dip : float
        Strength (µT) and dip (deg) of the sample.
    mwx, mwy, mwz : float
        Its direction in the world frame (unit), rotated with the gyro-propagated attitude.
    t : float
        Time, s.
    fref, dipref : float
        Reference strength and inclination (NaN when unknown).
    sigma_b_deg : float
        Gyro bias uncertainty of the filter, deg/s (widens the consistency tolerance).
    ip : PARAMS record
        :meth:`InterferenceSettings.as_params`.

    Returns
    -------
    bool
        The interference flag.
    """
    dtm = t - det.t if np.isfinite(det.t) else np.inf
    if dtm > 5.0 * ip.var_window_s or not np.isfinite(det.f_mean):
        det.f_mean = f
        det.f2_mean = f * f
    else:
        a = ew_alpha(dtm, ip.var_window_s)
        det.f_mean += a * (f - det.f_mean)
        det.f2_mean += a * (f * f - det.f2_mean)
    var = max(det.f2_mean - det.f_mean**2, 0.0)
    mw = det.mw
    if dtm > 5.0 * ip.consistency_window_s or not np.isfinite(mw[0]):  # (re)start the mean direction
        mw[0], mw[1], mw[2] = mwx, mwy, mwz
        cons = 0.0
    else:
        cons = angle_deg(mwx, mwy, mwz, mw[0], mw[1], mw[2])
        a = ew_alpha(dtm, ip.consistency_window_s)
        mw[0] += a * (mwx - mw[0])
        mw[1] += a * (mwy - mw[1])
        mw[2] += a * (mwz - mw[2])
    det.t = t
    # strength and dip: against the learnt local values and, loosely, against the references
    band_f = abs(f - fref) / (ip.strength_band_rel * fref) if np.isfinite(fref) else 0.0
    band_d = abs(dip - dipref) / ip.dip_band_deg if np.isfinite(dipref) else 0.0
    score_v = var / ip.var_max_uT2
    score_c = cons / (ip.consistency_tol_deg + ip.consistency_bias_k * sigma_b_deg * ip.consistency_window_s)
    if max(max(band_f, band_d), max(score_v, score_c)) < 1.0:
        # learn the local references (running mean of the first samples, then time constant learn_ref_s)
        det.n_learn += 1
        a = max(ew_alpha(min(dtm, 1.0), ip.learn_ref_s), 1.0 / det.n_learn)
        if not np.isfinite(det.f_loc):
            det.f_loc = f
            det.dip_loc = dip
        else:
            det.dip_loc += a * (dip - det.dip_loc)
            det.f_loc += a * (f - det.f_loc)
    floc = det.f_loc
    diploc = det.dip_loc
    ftol = strength_tol(fref if np.isfinite(fref) else floc, ip)
    score_f = max(band_f, abs(f - floc) / ftol) if np.isfinite(floc) else band_f
    score_d = max(band_d, abs(dip - diploc) / ip.dip_tol_deg) if np.isfinite(diploc) else band_d
    score = max(max(score_f, score_d), max(score_v, score_c))
    flag, since = hold_step(det.flag, det.since, score, t, ip)
    det.flag = flag
    det.since = since
    det.f = f
    det.dip = dip
    det.tol_f = ftol
    det.tol_dip = ip.dip_tol_deg
    det.var = var
    det.cons = cons
    det.score_f = score_f
    det.score_dip = score_d
    det.score = score
    return flag


# ----------------------------------------------------------------------------------------------- arrays
def strength_score(mag_d: np.ndarray, ref_uT: float, settings: InterferenceSettings | None = None):
    """Strength F (µT), and score ``|F − F_ref| / tol_F`` for calibrated samples (N, 3)."""
    s = settings or InterferenceSettings()
    f = np.linalg.norm(np.asarray(mag_d, dtype=float), axis=-1)
    tol = max(s.strength_tol_uT, s.strength_tol_rel * float(ref_uT))
    return f, np.abs(f - ref_uT) / tol


def dip_deg(mag_d: np.ndarray, up_d: np.ndarray) -> np.ndarray:
    """Dip angle (deg, positive below the horizon) between calibrated field and device-frame up (N, 3)."""
    m = np.asarray(mag_d, dtype=float)
    u = np.asarray(up_d, dtype=float)
    u = u / np.linalg.norm(u, axis=-1, keepdims=True)
    s = -np.sum(m * u, axis=-1) / np.linalg.norm(m, axis=-1)
    return np.degrees(np.arcsin(np.clip(s, -1.0, 1.0)))


def windowed_variance(t: np.ndarray, x: np.ndarray, window_s: float) -> np.ndarray:
    """Exponentially weighted variance of x (time constant ``window_s``), sample by sample."""
    t = np.asarray(t, dtype=float)
    x = np.asarray(x, dtype=float)
    return _ew_var(t, x, float(window_s))


@njit(cache=True, error_model="numpy")
def _ew_var(t, x, tau):
    out = np.empty(len(x))
    m = np.nan
    m2 = 0.0
    for i in range(len(x)):
        if not np.isfinite(m):
            m = x[i]
            m2 = x[i] * x[i]
        else:
            a = ew_alpha(t[i] - t[i - 1], tau)
            m += a * (x[i] - m)
            m2 += a * (x[i] * x[i] - m2)
        out[i] = max(m2 - m * m, 0.0)
    return out


def consistency_angle_deg(t: np.ndarray, mag_w: np.ndarray, window_s: float) -> np.ndarray:
    """Angle (deg) between each world-frame field sample and the exponentially weighted mean direction
    of the previous samples (time constant ``window_s``)."""
    return _cons(np.asarray(t, dtype=float), np.asarray(mag_w, dtype=float), float(window_s))


@njit(cache=True, error_model="numpy")
def _cons(t, m, tau):
    n = len(t)
    out = np.empty(n)
    mx = np.nan
    my = 0.0
    mz = 0.0
    for i in range(n):
        f = np.sqrt(m[i, 0] ** 2 + m[i, 1] ** 2 + m[i, 2] ** 2)
        ux, uy, uz = m[i, 0] / f, m[i, 1] / f, m[i, 2] / f
        if not np.isfinite(mx):
            mx, my, mz = ux, uy, uz
            out[i] = 0.0
            continue
        out[i] = angle_deg(ux, uy, uz, mx, my, mz)
        a = ew_alpha(t[i] - t[i - 1], tau)
        mx += a * (ux - mx)
        my += a * (uy - my)
        mz += a * (uz - mz)
    return out


def hold_off(t: np.ndarray, score: np.ndarray, settings: InterferenceSettings | None = None) -> np.ndarray:
    """Flags (bool, N) from scores with the hold-on / hold-off timers."""
    s = settings or InterferenceSettings()
    return _hold(np.asarray(t, dtype=float), np.asarray(score, dtype=float), s.as_params()[0])


@njit(cache=True, error_model="numpy")
def _hold(t, score, p):
    out = np.empty(len(t), dtype=np.bool_)
    flag = False
    since = np.nan
    for i in range(len(t)):
        flag, since = hold_step(flag, since, score[i], t[i], p)
        out[i] = flag
    return out
