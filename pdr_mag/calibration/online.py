"""Online (streaming) hard-iron calibration, stale-calibration test and figure-8 recalibration (seed 003).

Three pieces, all with bounded memory:

1. A **diversity buffer** of raw magnetometer samples ``m`` (with the gravity direction ``u`` at that
   instant).  A new sample is rejected when a kept sample lies within ``min_sep_frac · F`` of it in raw µT
   space *and* had nearly the same gravity direction: repeated orientations add no information but would
   dominate a least-squares fit.  When full, the most redundant sample is evicted; a kept sample older
   than ``refresh_s`` may be replaced by a close new one, so the buffer follows slow drift.

2. **Refits** of the hard-iron offset ``b`` on the buffer:

   * the linear least-squares sphere fit of seed 003 (eqs. 3–16,
     :func:`pdr_mag.calibration.sphere.fit_sphere`), which needs samples over the whole sphere;
   * a **gravity-aided fit**, which does not.  Phone walks rarely cover the sphere (texting pose: mostly yaw
     turns about the vertical).  With the accelerometer's (or the attitude filter's) unit up vector ``u_i``
     in the device frame, and the Earth field of strength ``F`` and inclination ``I`` (positive down), every
     sample obeys two equations::

         |m_i − b|        = F                  (strength)
         (m_i − b) · u_i  = −F · sin I         (dip: the field points below the horizon)

     Under pure yaw the points ``m_i`` lie on a circle about the axis ``u``: the circle's centre gives the
     two components of ``b`` across ``u``, and the dip equation the component along ``u`` — so ``b`` is
     observable from yaw rotations alone.  Without the World Magnetic Model, ``F`` and ``F sin I`` are
     taken from the last accepted calibration (fitted radius and mean dip) or, failing that, estimated as two
     more unknowns (which then needs some tilt diversity).  Solved by a linear initial value (the strength
     equation written as ``2 m·b − |b|² = |m|² − F²`` with ``k = |b|²`` a free unknown, plus the dip rows)
     followed by Gauss–Newton with Huber reweighting, residuals scaled by ``sigma_strength_uT`` and
     ``F · sigma_tilt``;
   * the calibration core's full fit (``pdr_mag.calibration.calibrate``, ellipsoid / ML) once the coverage
     allows it.

   Every refit goes through the acceptance rules (the calibration core's
   :func:`pdr_mag.calibration.coverage.accept` plus the online rules of :func:`judge`) before it replaces
   the calibration.

3. A **stale-calibration test** telling a passing disturbance from an offset that moved (e.g. the phone got a
   magnetised case).  The physics: a new device-fixed offset ``δ`` adds the same vector to the calibrated
   field in the device frame whatever the orientation, so ``|m_cal| − F ≈ δ · m̂_cal`` varies with
   orientation in a fixed, repeatable way and the *gravity-aided fit of δ on recent calibrated samples*
   explains it down to the noise, with the same ``δ`` from the older and the newer half of the window.  An
   external anomaly is fixed in the world (or moves with the walker's position), so it rotates with the
   device like the Earth's field: no constant device-frame ``δ`` explains it, the two halves disagree and
   the fit residual stays large; and it passes.  A building whose field differs from the WMM is a third case:
   held in one pose, it mimics a shift along the mean up vector, so a shift counts only where the data
   determine it with the local strength and dip free (:meth:`OnlineCalibrator._device_fixed`).  Only the
   first case requests a recalibration: the provisional offset ``b + S⁻¹δ`` is used at once
   (``cal_state = "recalibrating"``), the buffer is cleared, and the next
   rotation-rich episode (a figure-8: gyro rate above ``episode_rate`` for a while) with enough coverage gives
   the new calibration (``recalibrated``).

Speed: the per-sample work (episode tracker, recent ring, admission test, diversity buffer, coverage) and
the gravity-aided fit are compiled (:mod:`pdr_mag.calibration._online_kernel`, numba); Python runs only at
the refit and stale-test instants (every ``refit_period_s`` / ``stale_check_s``), and a refit whose inputs
(buffer, calibration, episode flag) did not change since the previous one reuses its candidates.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, replace
from functools import lru_cache

import numpy as np

from pdr_mag._json import state_float
from pdr_mag.calibration import _online_kernel as K
from pdr_mag.calibration.coverage import AcceptanceSettings
from pdr_mag.calibration.coverage import accept as core_accept
from pdr_mag.calibration.coverage import coverage as core_coverage
from pdr_mag.calibration.model import _EYE, MagCalibration
from pdr_mag.calibration.select import calibrate
from pdr_mag.calibration.sphere import fit_sphere

# ---------------------------------------------------------------------------------------------- settings


@dataclass(frozen=True)
class OnlineSettings:
    """Settings of the online calibrator (defaults suit 20–200 Hz phone magnetometers).

    Attributes
    ----------
    buffer_size : int
        Maximum number of samples in the diversity buffer.
    min_sep_frac : float
        A new sample closer than ``min_sep_frac · F`` (raw µT) to a kept one with a similar gravity
        direction is redundant.
    min_sep_up_deg : float
        Gravity directions closer than this count as similar.
    refresh_s : float
        A redundant new sample replaces its kept neighbour when that one is older than this.
    refit_period_s : float
        Stream time between refit attempts (before the first acceptance: ``refit_period_s / 2``).
    refit_min_new, refit_new_frac : float
        Once calibrated (and not recalibrating), a refit attempt fits only when the buffer took in at least
        ``max(refit_min_new, refit_new_frac · n)`` samples since the last fit (n: samples in the buffer);
        otherwise the last fit's verdict stands.  The fitted offset's covariance scales as 1/n, so k new
        samples shrink its σ by ≈ k/(2n) and move it by ≈ σ·√(k/n): far less than the 20 % shrink or
        2 σ shift a new fit needs to replace the calibration (see ``_accept``).  A change of the
        calibration, a rotation episode's start or end and a cleared buffer make the next attempt fit.
    refit_backoff : float
        A buffer that stopped growing changes only by replacement (an old sample refreshed by a close new
        one, the most redundant one evicted when full): while it does not grow, each fit that leaves the
        calibration as it was multiplies the number of new samples the next fit needs by this, up to n (the
        whole buffer renewed); growth, a change of calibration or any of the events above starts over.
    min_samples : int
        Fewer samples in the buffer: no refit.
    sigma_strength_uT : float
        1-σ of the strength equation (noise + unmodelled soft iron), µT.
    sigma_tilt_deg : float
        1-σ of the gravity direction, deg (the dip equation's σ is ``F · sin(sigma_tilt)``).
    prior_strength_std_uT, prior_dip_std_deg : float
        1-σ of the WMM strength and inclination as priors of the gravity-aided fit (the local field
        indoors differs by a few µT / degrees); 0 fixes them.
    max_offset_std_uT : float
        A gravity/sphere refit is accepted only when every offset σ is below this.
    first_offset_std_uT : float
        The same bound for the very first calibration (none yet): a coarse offset early lets the filter
        align the heading and learn the gyro bias before the first disturbance; refits refine it.
    max_rms_frac : float
        Accepted only when the robust residual RMS is below ``max_rms_frac · F``.
    max_offset_uT : float
        Offsets beyond this are implausible.
    strength_tol_frac : float
        After a calibration, samples whose ``| |m_cal| − F |`` exceeds this fraction of F are not buffered
        and count as deviating in the stale test.
    add_tol_frac, add_dip_tol_deg : float
        Once calibrated, a sample enters the buffer only when its strength is within ``add_tol_frac · F`` and
        its dip within ``add_dip_tol_deg`` of the reference (no disturbed samples in the fits).
    ellipsoid_coverage : float
        Coverage from which the core's full (ellipsoid) fit is attempted.
    ellipsoid_precheck_frac : float
        The full fit is attempted only when, besides, the buffer's coverage by the core's own measure (the
        equal-area grid of :func:`pdr_mag.calibration.coverage.coverage`, on which the fit is judged) about
        the current offset estimate reaches this share of the core's ``min_coverage``: the fit is judged about
        its own centre, a few µT away, which moves a direction by a few degrees against cells of 22° × 45°.
    sphere_coverage : float
        Coverage from which the sphere LLS fit is attempted.
    stale_window_s, stale_check_s, stale_min_frac, stale_min_shift_uT : float
        Stale test: recent window length, check period, share of deviating samples in the last third of the
        window needed to run the test, and the least offset shift (also ≥ 4 σ) that counts.
    stale_rate_hz : float
        Decimation of the recent window.
    stale_confirm_s : float
        The same offset shift must be found again this much later (the deviation persisting in between)
        before a recalibration is requested.
    episode_rate : float
        Smoothed gyro rate (rad/s) above which a rotation-rich episode (figure-8) is on; off below half.
    recal_fallback_s : float
        While recalibrating without a figure-8, an accepted gravity-aided refit on the new buffer older
        than this ends the recalibration.
    """

    buffer_size: int = 400
    min_sep_frac: float = 0.12
    min_sep_up_deg: float = 6.0
    refresh_s: float = 120.0
    refit_period_s: float = 2.0
    refit_min_new: float = 2.0
    refit_new_frac: float = 0.1
    refit_backoff: float = 2.0
    min_samples: int = 8
    sigma_strength_uT: float = 1.0
    sigma_tilt_deg: float = 3.0
    prior_strength_std_uT: float = 3.0
    prior_dip_std_deg: float = 3.0
    max_offset_std_uT: float = 2.0
    first_offset_std_uT: float = 4.0
    max_rms_frac: float = 0.08
    max_offset_uT: float = 2000.0
    strength_tol_frac: float = 0.15
    add_tol_frac: float = 0.06
    add_dip_tol_deg: float = 4.0
    ellipsoid_coverage: float = 0.6
    ellipsoid_precheck_frac: float = 0.8
    sphere_coverage: float = 0.4
    stale_window_s: float = 30.0
    stale_check_s: float = 2.0
    stale_min_frac: float = 0.5
    stale_min_shift_uT: float = 6.0
    stale_confirm_s: float = 10.0
    stale_rate_hz: float = 10.0
    episode_rate: float = 1.5
    recal_fallback_s: float = 20.0


# ---------------------------------------------------------------------------------------------- the fit


def gravity_aided_offset(
    mag: np.ndarray,
    up: np.ndarray,
    strength: float | None = None,
    sin_dip: float | None = None,
    sigma_strength_uT: float = 1.0,
    sigma_tilt_deg: float = 3.0,
    iterations: int = 8,
    prior_strength_std_uT: float = 0.0,
    prior_dip_std_deg: float = 0.0,
) -> MagCalibration:
    """Hard-iron offset from strength and dip constraints (see the module docstring for the model).

    Parameters
    ----------
    mag : ndarray (N, 3)
        Raw magnetometer samples m_i, µT, device frame.
    up : ndarray (N, 3)
        Unit up vectors u_i in the device frame (normalised specific force at rest).
    strength, sin_dip : float, optional
        F (µT) and sin I of the Earth field; both estimated when omitted.
    sigma_strength_uT, sigma_tilt_deg : float
        1-σ of the two residuals (µT, and deg of tilt).
    prior_strength_std_uT, prior_dip_std_deg : float
        With F and sin I given and these > 0, F and F sin I are estimated too, with the given values as a
        Gaussian prior of these 1-σ (the local field indoors differs from the WMM by a few µT and degrees;
        a hard constraint would push that error into the offset).  0: F and sin I fixed.

    Returns
    -------
    MagCalibration
        ``method="gravity"``, identity soft iron, ``field_uT`` = F, offset covariance, ``extra`` with
        ``sin_dip`` and ``dip_rms_uT``.  Acceptance is not judged here.
    """
    m = np.asarray(mag, dtype=float)
    u = np.asarray(up, dtype=float)
    if m.ndim != 2 or m.shape[1] != 3 or u.shape != m.shape:
        raise ValueError(f"mag, up: expected two (N, 3) arrays, got {m.shape} and {u.shape}")
    if len(m) < 5:
        raise ValueError(f"mag: need at least 5 samples, got {len(m)}")
    code, b, f, s, cov_b, free, rms, dip_rms = _gravity_numbers(
        m, u, strength, sin_dip, sigma_strength_uT, sigma_tilt_deg, iterations, prior_strength_std_uT,
        prior_dip_std_deg,
    )  # fmt: skip
    if code == K.FIT_BAD_INPUT:
        raise ValueError("mag, up: contain NaN, infinite or zero vectors")
    if code != K.FIT_OK:
        raise ValueError("mag, up: offset not observable from these samples (degenerate geometry)")
    n = len(m)
    return MagCalibration.from_arrays(
        b,
        None,
        field_uT=f,
        method="gravity",
        residual_rms_uT=float(rms),
        offset_std_uT=np.sqrt(np.maximum(np.diag(cov_b), 0)),
        n_samples=n,
        covariance=cov_b,
        extra={
            "covariance_params": ["offset_x", "offset_y", "offset_z"],
            "sin_dip": s / f if f > 0 else float("nan"),
            "dip_rms_uT": float(dip_rms),
            "strength_estimated": bool(free),
        },
    )


def _gravity_numbers(
    m,
    u,
    strength,
    sin_dip,
    sigma_strength_uT,
    sigma_tilt_deg,
    iterations,
    prior_strength_std_uT,
    prior_dip_std_deg,
):
    """:func:`gravity_aided_offset` without the checks of its arguments and without building the result:
    ``(code, offset, F, F sin I, offset covariance, strength estimated, rms, dip rms)``."""
    free = strength is None or sin_dip is None
    f_guess = float(strength) if strength is not None else 50.0
    s_ref = 0.0 if free else float(strength) * float(sin_dip)
    prior = not free and prior_strength_std_uT > 0 and prior_dip_std_deg > 0
    sig2, sig_f, sig_s = _gravity_scales(
        f_guess, float(sigma_tilt_deg), prior, float(prior_strength_std_uT), float(sin_dip or 0.0),
        float(prior_dip_std_deg),
    )  # fmt: skip
    try:
        code, b, f, s, cov, est, rms, dip_rms = K.gravity_fit(
            np.ascontiguousarray(m, dtype=float), np.ascontiguousarray(u, dtype=float), f_guess,
            0.0 if free else float(strength), s_ref, free, float(sigma_strength_uT), sig2, int(iterations),
            prior, sig_f, sig_s,
        )  # fmt: skip
    except np.linalg.LinAlgError as exc:
        raise ValueError("mag, up: singular normal equations") from exc
    return code, b, float(f), float(s), cov[:3, :3].copy(), bool(est), float(rms), float(dip_rms)


@lru_cache(maxsize=64)
def _gravity_scales(f_guess, sigma_tilt_deg, prior, prior_strength_std_uT, sin_dip, prior_dip_std_deg):
    """``(σ_dip, σ_F, σ_{F sin I})`` of :func:`_gravity_numbers` (memoised: the same settings each fit)."""
    sig2 = max(f_guess * np.sin(np.radians(sigma_tilt_deg)), 1e-3)
    sig_f = sig_s = 1.0
    if prior:
        sig_f = float(prior_strength_std_uT)
        sig_s = float(f_guess * np.cos(np.arcsin(np.clip(sin_dip, -1, 1))) * np.radians(prior_dip_std_deg))
    return sig2, sig_f, sig_s


# ---------------------------------------------------------------------------------------------- coverage

_N_DIRS = 64
_GOLD = np.pi * (3.0 - np.sqrt(5.0))
_zs = 1.0 - 2.0 * (np.arange(_N_DIRS) + 0.5) / _N_DIRS
_DIRS = np.column_stack(
    [
        np.sqrt(1 - _zs**2) * np.cos(_GOLD * np.arange(_N_DIRS)),
        np.sqrt(1 - _zs**2) * np.sin(_GOLD * np.arange(_N_DIRS)),
        _zs,
    ]
)


_ZERO3 = np.zeros(3)
_COS30 = float(np.cos(np.radians(30.0)))
_EV_NAMES = {K.EV_EPISODE_START: "rotation_episode_start", K.EV_EPISODE_END: "rotation_episode_end"}


def direction_coverage(mag_cal: np.ndarray) -> float:
    """Share of 64 near-uniform directions with a calibrated sample direction within 30°, in [0, 1].

    The online trigger for the sphere and ellipsoid refits (``sphere_coverage``, ``ellipsoid_coverage``)
    is set on this measure; the calibration core's equal-area :func:`pdr_mag.calibration.coverage.coverage`
    is what the full fit reports and judges.
    """
    m = np.ascontiguousarray(mag_cal, dtype=float).reshape(-1, 3)
    return float(K.coverage(m, len(m), _ZERO3, _DIRS, _COS30))


def judge(
    cal: MagCalibration,
    settings: OnlineSettings,
    field_ref: float | None,
    first: bool = False,
    coverage: float | None = None,
) -> MagCalibration:
    """Acceptance verdict for an online refit (returns a copy with ``accepted``/``reasons`` set).

    The calibration core's rules (:func:`pdr_mag.calibration.coverage.accept`: sample count, radius against
    the reference, residual, offset σ and range, soft-iron spread, conditioning — the coverage rules apply
    where the fit recorded its coverage) are applied to every refit but the gravity-aided one, whose
    geometry they do not describe; the online rules below are applied in any case: offset σ, residual RMS
    relative to F, offset magnitude, radius against the reference strength.  ``coverage`` given: the copy
    also gets it (for the gravity-aided refit, whose rules do not read it).
    """
    reasons: list[str] = []
    if cal.method != "gravity":
        reasons += list(core_accept(cal, field=field_ref).reasons)
    f = cal.field_uT
    bound = (
        settings.max_offset_std_uT
        if not first
        else max(settings.first_offset_std_uT, settings.max_offset_std_uT)
    )
    if not all(map(math.isfinite, cal.offset_std_uT)) or max(cal.offset_std_uT) > bound:
        std = np.asarray(cal.offset_std_uT, dtype=float)
        reasons.append(f"offset σ {np.nanmax(std):.2f} µT above {bound:g} µT")
    if not np.isfinite(f) or f <= 0:
        reasons.append("no finite field radius")
    elif cal.residual_rms_uT > settings.max_rms_frac * f:
        reasons.append(f"residual RMS {cal.residual_rms_uT:.2f} µT above {settings.max_rms_frac:.0%} of F")
    if np.linalg.norm(cal.offset_array) > settings.max_offset_uT:
        reasons.append(f"offset {np.linalg.norm(cal.offset_array):.0f} µT implausible")
    if field_ref is not None and np.isfinite(f) and abs(f / field_ref - 1) > 0.25:
        reasons.append(f"radius {f:.1f} µT far from the reference {field_ref:.1f} µT")
    if coverage is not None:
        return replace(cal, coverage=coverage, accepted=not reasons, reasons=tuple(reasons))
    return cal.with_acceptance(not reasons, reasons)


def _full_fit(mag: np.ndarray, field_ref: float | None) -> MagCalibration:
    """The calibration core's fit (model chosen by BIC, geometric ML; seeds 000/001/004)."""
    return calibrate(mag, method="auto", field=field_ref)


# ---------------------------------------------------------------------------------------------- calibrator


def _ks_prop(i: int, kind):
    """An attribute stored in ``self._ks[i]`` (the compiled loop's state vector)."""

    def get(self):
        return kind(self._ks[i])

    def set_(self, v) -> None:
        self._ks[i] = float(v)

    return property(get, set_)


class OnlineCalibrator:
    """The streaming calibration state machine: ``none`` → ``offset``/``ellipsoid`` ⇄ ``recalibrating``.

    Feed it magnetometer samples in time order with :meth:`update`; read :attr:`calibration` and
    :attr:`cal_state`; it returns :class:`pdr_mag.estimates.Event`-ready ``(t, kind, data)`` tuples.

    Parameters
    ----------
    settings : OnlineSettings
    calibration : MagCalibration, optional
        A device calibration to start from (``cal_state`` ``offset`` or ``ellipsoid``).
    strength, sin_dip : float, optional
        Earth field strength F (µT) and sin of the inclination from the WMM; None when unknown.
    """

    def __init__(
        self,
        settings: OnlineSettings | None = None,
        calibration: MagCalibration | None = None,
        strength: float | None = None,
        sin_dip: float | None = None,
    ):
        self.settings = settings or OnlineSettings()
        self.strength_wmm = None if strength is None else float(strength)
        self.sin_dip_wmm = None if sin_dip is None else float(sin_dip)
        s = self.settings
        self._ks = np.zeros(K.N_KS)  # scalar state of the compiled loop (K_* indices)
        self._ks[K.K_LAST_REC_T] = -np.inf
        self._ks[K.K_NEXT_REFIT_T] = -np.inf
        self._ks[K.K_NEXT_STALE_T] = -np.inf
        self._ks[K.K_COV_VERSION] = -1.0
        self._ks[K.K_FIT_SCALE] = 1.0
        self._cp = np.zeros(K.N_CP)
        self._cp[K.C_REFRESH_S] = s.refresh_s
        self._cp[K.C_REC_DT] = 1.0 / s.stale_rate_hz
        self._cp[K.C_EP_RATE] = s.episode_rate
        self._cp[K.C_SIZE] = s.buffer_size
        self._cp[K.C_COS_COV] = _COS30
        self._cos_up = float(np.cos(np.radians(s.min_sep_up_deg)))
        self._cal: MagCalibration | None = None
        self.calibration = calibration
        self.cal_state = "none" if calibration is None else _state_of(calibration)
        self.provided = calibration is not None
        self._buf = np.full((s.buffer_size, 7), np.nan)  # t, m(3), u(3)
        self._buf0 = np.empty_like(self._buf)  # the buffer at the start of the open block
        self._old0 = np.zeros(s.buffer_size, dtype=np.int64)  # its samples that may be old enough to refresh
        nrec = int(s.stale_window_s * s.stale_rate_hz) + 1
        self._rec = np.full((nrec, 7), np.nan)  # ring of recent samples
        self._recal_t = np.nan
        self._stale_cand: list | None = None
        self._n_refits = 0
        self._last_reject_t = -np.inf
        self._refit_memo: tuple | None = None
        self._bp_memo: tuple | None = None
        self._centre_memo: tuple | None = None
        self._dp_memo: tuple | None = None

    # scalar state kept in the compiled loop's vector
    _rate_ema = _ks_prop(K.K_RATE_EMA, float)
    _episode = _ks_prop(K.K_EPISODE, bool)
    _episode_seen = _ks_prop(K.K_EPISODE_SEEN, bool)
    _last_rec_t = _ks_prop(K.K_LAST_REC_T, float)
    _rec_i = _ks_prop(K.K_REC_I, int)
    _nbuf = _ks_prop(K.K_NBUF, int)
    _next_refit_t = _ks_prop(K.K_NEXT_REFIT_T, float)
    _next_stale_t = _ks_prop(K.K_NEXT_STALE_T, float)

    @property
    def calibration(self) -> MagCalibration | None:
        """The calibration in use (None before the first accepted fit)."""
        return self._cal

    @calibration.setter
    def calibration(self, cal: MagCalibration | None) -> None:
        self._cal = cal
        self._ks[K.K_COV_VERSION] = -1.0  # the coverage is taken about the calibration's offset
        self._ks[K.K_FIT_NEW] = np.inf  # the next refit attempt fits

    # ------------------------------------------------------------------ reference field
    @property
    def field_ref(self) -> float | None:
        """F, µT: the WMM strength, else the radius of the current calibration."""
        if self.strength_wmm is not None:
            return self.strength_wmm
        if self.calibration is not None and np.isfinite(self.calibration.field_uT):
            return float(self.calibration.field_uT)
        return None

    @property
    def sin_dip_ref(self) -> float | None:
        if self.sin_dip_wmm is not None:
            return self.sin_dip_wmm
        if self.calibration is not None:
            v = self.calibration.extra.get("sin_dip") if isinstance(self.calibration.extra, dict) else None
            if v is not None and np.isfinite(v):
                return float(v)
        return None

    def _prior(self) -> dict:
        s = self.settings
        return {"prior_strength_std_uT": s.prior_strength_std_uT, "prior_dip_std_deg": s.prior_dip_std_deg}

    @property
    def episode(self) -> bool:
        """Whether a rotation-rich episode (figure-8) is on."""
        return self._episode

    @property
    def buffer(self) -> np.ndarray:
        """The diversity buffer's raw samples, (n, 3) µT (a copy)."""
        return self._buf[: self._nbuf, 1:4].copy()

    def coverage(self) -> float:
        """Direction coverage of the buffer about the calibration's offset (the buffer mean without one)."""
        return float(K.cached_coverage(self._buf, self._ks, self._centre(), _DIRS, _COS30))

    def _centre(self) -> np.ndarray:
        """``(flag, offset)`` of the calibration in use for the coverage (the same array while it stays the
        same — read-only)."""
        memo = self._centre_memo
        if memo is not None and memo[0] is self._cal:
            return memo[1]
        c = np.zeros(4)
        if self._cal is not None:
            c[0] = 1.0
            c[1:4] = self._cal.offset_array
        self._centre_memo = (self._cal, c)
        return c

    def _block_params(self) -> np.ndarray:
        """Admission-test parameters for a block starting now (the calibration in use; the same array until
        the calibration or its state changes — read-only)."""
        memo = self._bp_memo
        if memo is not None and memo[0] is self._cal and memo[1] == self.cal_state:
            return memo[2]
        bp = self._new_block_params()
        self._bp_memo = (self._cal, self.cal_state, bp)
        return bp

    def _new_block_params(self) -> np.ndarray:
        s = self.settings
        bp = np.zeros(K.N_BP)
        f = self.field_ref
        bp[K.B_SEP2] = (s.min_sep_frac * (f or 50.0)) ** 2
        bp[K.B_COS_UP] = self._cos_up
        cal = self._cal
        if cal is None or f is None or self.cal_state in ("none", "recalibrating"):
            return bp
        a = cal.soft_iron_array
        if cal.mag_to_imu is not None:
            a = np.asarray(cal.mag_to_imu, dtype=float) @ a
        bp[K.B_CHECK] = 1.0
        bp[K.B_M : K.B_M + 9] = a.reshape(-1)
        bp[K.B_OFF : K.B_OFF + 3] = cal.offset_array
        bp[K.B_F] = f
        bp[K.B_TOL_F] = s.add_tol_frac * f
        sd = self.sin_dip_ref
        if sd is not None:
            bp[K.B_DIP_CHECK] = 1.0
            bp[K.B_DIP_DEG] = np.degrees(np.arcsin(sd))
            bp[K.B_DIP_TOL] = s.add_dip_tol_deg
        return bp

    # ------------------------------------------------------------------ the loop
    def update(self, t: np.ndarray, mag: np.ndarray, up: np.ndarray, rate: np.ndarray) -> list:
        """Take raw magnetometer samples (time-ordered) with up vectors and gyro rates; return events.

        The samples are one block: the admission test of every sample (consistency with the calibration,
        redundancy against the buffer) is against the calibration and the buffer at the block start.
        Never raises on odd data: samples with NaN are skipped.
        """
        t = np.asarray(t, dtype=float).reshape(-1)
        ends = np.zeros(len(t), dtype=np.bool_)
        if len(t):
            ends[-1] = True
        events, _, _ = self.update_blocks(t, mag, up, rate, ends, stop_on_change=False)
        return [e for _, e in events]

    def update_blocks(
        self,
        t: np.ndarray,
        mag: np.ndarray,
        up: np.ndarray,
        rate: np.ndarray,
        block_end: np.ndarray,
        stop_on_change: bool = True,
    ) -> tuple[list, int, np.ndarray]:
        """:meth:`update` for several blocks at once; ``block_end`` (N,) bool marks the last sample of each.

        Returns ``(events, n, coverage)``: events as ``(row, (t, kind, data))`` with the row that raised
        them, the number of rows taken in (all, or with ``stop_on_change`` up to the end of the first block
        in which the calibration changed), and the buffer's coverage after each block end (NaN elsewhere).
        """
        events: list = []
        t = np.asarray(t, dtype=float).reshape(-1)
        n_all = len(t)
        if not n_all:
            return events, 0, np.empty(0)
        mag = np.asarray(mag, dtype=float)
        up = np.asarray(up, dtype=float)
        rate = np.asarray(rate, dtype=float)
        block_end = np.asarray(block_end, dtype=np.bool_)
        rows = None
        ok, t_c, mag_c, up_c, rate_c = K.contiguous_rows(t, mag, up, rate)
        if ok:
            t, mag, up, rate = t_c, mag_c, up_c, rate_c
        else:
            cov = np.full(n_all, np.nan)
            good = np.isfinite(t) & np.all(np.isfinite(mag), axis=1) & np.all(np.isfinite(up), axis=1)
            # a block whose last sample is dropped ends at its last good one
            blk = np.cumsum(np.r_[False, block_end[:-1]])
            rows = np.flatnonzero(good)
            t, mag, up, rate, blk = t[rows], mag[rows], up[rows], rate[rows], blk[rows]
            block_end = np.r_[blk[1:] != blk[:-1], True] if len(rows) else block_end[:0]
            if not len(rows):
                return events, n_all, cov
            rate = np.where(np.isfinite(rate), rate, 0.0)
            t = np.ascontiguousarray(t)
            mag = np.ascontiguousarray(mag)
            up = np.ascontiguousarray(up)
        events, stop_at, cov_g = self._update_rows(t, mag, up, rate, block_end, stop_on_change)
        if rows is None:
            cov = cov_g
            n_done = stop_at if stop_at < len(t) else n_all
        else:
            cov[rows] = cov_g
            events = [(int(rows[r]), e) for r, e in events]
            n_done = int(rows[stop_at - 1]) + 1 if stop_at < len(t) else n_all
        return events, n_done, cov

    def _update_rows(
        self,
        t: np.ndarray,
        mag: np.ndarray,
        up: np.ndarray,
        rate: np.ndarray,
        block_end: np.ndarray,
        stop_on_change: bool = True,
    ) -> tuple[list, int, np.ndarray]:
        """:meth:`update_blocks` on rows already contiguous and finite (non-finite rates set to 0): returns
        ``(events, n, coverage)`` as it does, ``n`` the rows taken in."""
        events: list = []
        cov_g = np.full(len(t), np.nan)
        ev_i = np.zeros(len(t) * 2 + 2, dtype=np.int64)
        ev_k = np.zeros(len(t) * 2 + 2, dtype=np.int64)
        s = self.settings
        bp = self._block_params()
        i = 0
        changed = False
        stop_at = len(t)
        cal_of = False  # the calibration the separation and the coverage centre below were taken from
        while i < len(t):
            if self._cal is not cal_of:
                cal_of = self._cal
                sep2 = (s.min_sep_frac * (self.field_ref or 50.0)) ** 2
                centre = self._centre()
                dp = self._decide_params()
            self._ks[K.K_STALE_ON] = self._cal is not None and self.cal_state != "recalibrating"
            dp[K.D_CAND_NONE] = self._stale_cand is None
            code, j, n_ev = K.scan(
                t, mag, up, rate, block_end, i, self._ks, bp, self._cp, self._buf, self._buf0, self._old0,
                self._rec, sep2, centre, _DIRS, cov_g, changed, ev_i, ev_k, dp,
            )  # fmt: skip
            for e in range(n_ev):
                ie = int(ev_i[e])
                events.append((ie, (float(t[ie]), _EV_NAMES[int(ev_k[e])], {})))
            if code == K.DONE:
                break
            if code == K.DECIDE:
                before = self._cal
                ti = float(t[j])
                out: list = []
                if ti >= self._next_refit_t:
                    period = s.refit_period_s if self._cal is not None else 0.5 * s.refit_period_s
                    self._next_refit_t = ti + period
                    self._refit(ti, out)
                if ti >= self._next_stale_t and self._cal is not None and self.cal_state != "recalibrating":
                    self._next_stale_t = ti + s.stale_check_s
                    self._stale_check(ti, out)
                events += [(j, e) for e in out]
                changed = changed or self._cal is not before
                if not block_end[j]:
                    i = j + 1
                    continue
            # a block ended at j (its coverage is in cov_g[j] unless the calibration changed since)
            if changed:
                cov_g[j] = self.coverage()
                if stop_on_change:
                    stop_at = j + 1
                    break
                changed = False
                bp = self._block_params()
            i = j + 1
        return events, stop_at, cov_g

    def _decide_params(self) -> np.ndarray:
        """``dp`` of :func:`_online_kernel.scan` for the calibration in use (the same array while it stays
        the same; the caller sets the candidate flag before each call)."""
        memo = self._dp_memo
        if memo is not None and memo[0] is self._cal:
            return memo[1]
        s = self.settings
        f = self.field_ref
        dp = np.zeros(K.N_DP)
        dp[K.D_PERIOD] = s.refit_period_s if self._cal is not None else 0.5 * s.refit_period_s
        dp[K.D_MIN_SAMPLES] = s.min_samples
        dp[K.D_MIN_NEW] = s.refit_min_new
        dp[K.D_NEW_FRAC] = s.refit_new_frac
        dp[K.D_STALE_DT] = s.stale_check_s
        dp[K.D_STALE_OK] = f is not None and self.sin_dip_ref is not None
        dp[K.D_WINDOW] = s.stale_window_s
        if f is not None:
            dp[K.D_F] = f
            dp[K.D_TOL] = s.strength_tol_frac * f * 0.5
        dp[K.D_MIN_FRAC] = s.stale_min_frac
        self._dp_memo = (self._cal, dp)
        return dp

    # ------------------------------------------------------------------ diversity buffer
    def _add(self, t: float, m: np.ndarray, u: np.ndarray) -> None:
        s = self.settings
        K.add(
            float(t), np.asarray(m, dtype=float), np.asarray(u, dtype=float), self._buf, self._ks,
            (s.min_sep_frac * (self.field_ref or 50.0)) ** 2, self._cos_up, s.refresh_s, s.buffer_size,
        )  # fmt: skip

    def clear_buffer(self) -> None:
        self._buf[:] = np.nan
        self._nbuf = 0
        self._ks[K.K_VERSION] += 1.0
        self._ks[K.K_FIT_NEW] = np.inf

    # ------------------------------------------------------------------ refits
    def _refit(self, t: float, events: list) -> None:
        s = self.settings
        n = self._nbuf
        if n < s.min_samples:
            return
        ks = self._ks
        if ks[K.K_FIT_NEW] == np.inf or n > ks[K.K_FIT_N]:
            ks[K.K_FIT_SCALE] = 1.0  # an event, or the buffer grew since the last fit: no back-off
        need = min(max(s.refit_min_new, s.refit_new_frac * n) * ks[K.K_FIT_SCALE], n)
        if self._cal is not None and self.cal_state != "recalibrating" and ks[K.K_FIT_NEW] < need:
            return  # too few new samples since the last fit to change its verdict (refit_min_new)
        ks[K.K_FIT_NEW] = 0.0
        ks[K.K_FIT_N] = n
        ks[K.K_FIT_SCALE] *= s.refit_backoff  # reset above by the change of calibration, if this makes one
        # the candidates and their verdicts depend on the buffer, the calibration in use and the episode
        # flag only: when none of them changed since the last refit, they are the same
        key = (float(self._ks[K.K_VERSION]), self._episode_seen, self.cal_state)
        memo = self._refit_memo
        if memo is not None and memo[0] == key and memo[1] is self._cal:
            judged = memo[2]
        else:
            judged = self._candidates(n)
            self._refit_memo = (key, self._cal, judged)
        good = [c for c in judged if c.accepted]
        if not good:
            if judged and self.calibration is None and t - self._last_reject_t > 30.0:
                self._last_reject_t = t
                best = judged[-1]
                events.append(
                    (t, "calibration_rejected", {"method": best.method, "reasons": list(best.reasons)})
                )
            return
        # prefer the richest model that passed: ellipsoid/ml > sphere > gravity
        rank = {"gravity": 0, "sphere": 1}
        best = max(good, key=lambda c: (rank.get(c.method, 2), -float(max(c.offset_std_uT))))  # finite σ
        self._accept(t, copy.copy(best), events)

    def _candidates(self, n: int) -> list[MagCalibration]:
        """Every refit of the buffer's ``n`` samples, judged (see :func:`judge`)."""
        s = self.settings
        m = self._buf[:n, 1:4]
        u = self._buf[:n, 4:7]
        f_ref = self.field_ref
        cands: list[MagCalibration] = []
        centre = self.calibration.offset_array if self.calibration is not None else None
        try:
            g = self._gravity_fit(m, u, f_ref)
            cands.append(g)
            centre = g.offset_array
        except ValueError:
            pass
        cov = direction_coverage(m - (centre if centre is not None else m.mean(axis=0)))
        if cov >= s.sphere_coverage:
            try:
                sp = fit_sphere(m)
                sp = replace(sp, coverage=cov)
                cands.append(sp)
            except (ValueError, ArithmeticError):
                pass
        if (
            cov >= s.ellipsoid_coverage
            and (self._episode_seen or self.cal_state == "none")
            and core_coverage(m - (centre if centre is not None else m.mean(axis=0)))
            >= s.ellipsoid_precheck_frac * AcceptanceSettings().min_coverage
        ):
            try:
                full = _full_fit(m, f_ref)
                full = replace(full, coverage=cov if not np.isfinite(full.coverage) else full.coverage)
                cands.append(full)
            except Exception:  # the core's fit failing on odd data is a failed refit, never a crash
                pass
        first = self.calibration is None
        # the gravity verdict does not read its coverage: judged, the coverage set in the same copy
        return [
            judge(c, s, f_ref, first, coverage=cov) if c.method == "gravity" else judge(c, s, f_ref, first)
            for c in cands
        ]

    def _gravity_fit(self, m: np.ndarray, u: np.ndarray, f_ref: float | None) -> MagCalibration:
        """Gravity-aided offset fit that keeps the shape (soft iron, ``mag_to_imu``) of the current
        calibration: the hard iron moves (a magnet, a case), the sensor's scale and axes do not.

        With ``M = R·A`` (R = mag_to_imu or I, A = soft iron), ``y = M m`` is the field in the device frame
        up to a constant ``c = M b``; the fit on ``(y, u)`` gives ``c``, hence ``b = M⁻¹ c``.
        """
        s = self.settings
        cur = self.calibration
        a = cur.soft_iron_array if cur is not None else np.eye(3)
        r = (
            np.asarray(cur.mag_to_imu, dtype=float)
            if cur is not None and cur.mag_to_imu is not None
            else None
        )
        mm = a if r is None else r @ a
        shaped = not _is_identity(mm, 1e-12)
        y = m @ mm.T if shaped else m
        g = gravity_aided_offset(
            y,
            u,
            f_ref,
            self.sin_dip_ref if f_ref is not None else None,
            s.sigma_strength_uT,
            s.sigma_tilt_deg,
            **self._prior(),
        )
        if not shaped:
            return g
        mi = np.linalg.inv(mm)
        cov_b = mi @ np.asarray(g.covariance, dtype=float) @ mi.T
        return MagCalibration.from_arrays(
            mi @ g.offset_array,
            a,
            field_uT=g.field_uT,
            method="gravity",
            residual_rms_uT=g.residual_rms_uT,
            offset_std_uT=np.sqrt(np.maximum(np.diag(cov_b), 0)),
            n_samples=g.n_samples,
            covariance=cov_b,
            mag_to_imu=cur.mag_to_imu,
            extra={**g.extra, "shape_from": cur.method},
        )

    def _with_dip(self, cal: MagCalibration) -> MagCalibration:
        """A sphere or full refit taken into use gets ``extra["sin_dip"]``: the median dip of the buffer's
        samples under it (the buffer the refit was made on; computed only for the refit taken)."""
        if cal.method == "gravity":
            return cal
        n = self._nbuf
        sin_dip = _mean_sin_dip(self._buf[:n, 1:4], self._buf[:n, 4:7], cal)
        return replace(cal, extra={**cal.extra, "sin_dip": sin_dip})

    def _accept(self, t: float, cal: MagCalibration, events: list) -> None:
        s = self.settings
        old = self.calibration
        if self.cal_state == "recalibrating":
            cal = self._with_dip(cal)
            rich = cal.method != "gravity" and self._episode_seen
            waited = np.isfinite(self._recal_t) and t - self._recal_t > s.recal_fallback_s
            if not (rich or waited):
                # provisional: keep refining the offset, stay in "recalibrating"
                self.calibration = cal
                return
            self.calibration = cal
            self.cal_state = _state_of(cal)
            self._recal_t = np.nan
            events.append((t, "recalibrated", {**_cal_summary(cal), "figure8": bool(rich)}))
            return
        if old is not None:
            # do not replace a richer calibration by a poorer one, nor churn on noise
            if _state_of(old) == "ellipsoid" and _state_of(cal) == "offset":
                return  # never trade a soft-iron shape for an offset-only fit
            if self.provided and cal.method in ("gravity", "sphere"):
                return
            shift = np.linalg.norm(cal.offset_array - old.offset_array)
            std_new = float(max(cal.offset_std_uT))  # finite: an accepted refit
            std_old = float(max(old.offset_std_uT)) if all(map(math.isfinite, old.offset_std_uT)) else np.inf
            upgrade = _state_of(cal) == "ellipsoid" and _state_of(old) != "ellipsoid"
            rms_old = old.residual_rms_uT if np.isfinite(old.residual_rms_uT) else np.inf
            if not upgrade and cal.residual_rms_uT > 1.5 * rms_old + 0.3:
                return  # the buffer got worse (disturbed samples): keep the calibration
            if not upgrade and shift < 2 * max(std_new, 0.2) and std_new > 0.8 * std_old:
                return
        cal = self._with_dip(cal)
        self.calibration = cal
        self.cal_state = _state_of(cal)
        self._n_refits += 1
        events.append((t, "calibration_accepted", _cal_summary(cal)))

    # ------------------------------------------------------------------ stale test
    def _recent(self, t: float) -> np.ndarray:
        """The ring's samples of the last ``stale_window_s``, oldest first."""
        return K.recent(self._rec, self._ks[K.K_REC_I], t - self.settings.stale_window_s)

    def _stale_check(self, t: float, events: list) -> None:
        s = self.settings
        cal = self.calibration
        f = self.field_ref
        sd = self.sin_dip_ref
        if cal is None or f is None or sd is None:
            return
        bp = np.zeros(K.N_BP)
        a = cal.soft_iron_array
        if cal.mag_to_imu is not None:
            a = np.asarray(cal.mag_to_imu, dtype=float) @ a
        bp[K.B_M : K.B_M + 9] = a.reshape(-1)
        bp[K.B_OFF : K.B_OFF + 3] = cal.offset_array
        tol = s.strength_tol_frac * f * 0.5
        pre = K.stale_precheck(self._rec, t, s.stale_window_s, bp, f, tol, s.stale_min_frac)
        if pre == K.STALE_SKIP:
            return
        if pre == K.STALE_CLEAR:
            self._stale_cand = None
            return
        # deviating (the precheck's share test passed): fit a device-fixed offset shift on the window
        r = self._recent(t)
        mc = cal.apply(r[:, 1:4])
        half = len(r) // 2
        fits = []
        for lo, hi in ((0, len(r)), (0, half), (half, len(r))):
            try:
                code, off, _, _, cov_b, _, rms, _ = _gravity_numbers(
                    mc[lo:hi], r[lo:hi, 4:7], f, sd, s.sigma_strength_uT, s.sigma_tilt_deg, 8,
                    s.prior_strength_std_uT, s.prior_dip_std_deg,
                )  # fmt: skip
            except ValueError:
                return
            if code != K.FIT_OK:
                return
            fits.append((off, np.sqrt(np.maximum(np.diag(cov_b), 0)), rms))
            if lo == 0 and hi == len(r) and self._stale_cand is None:
                # speed only: with no candidate pending, a whole-window fit that fails the tests below
                # ends the check as the halves would (a failed half returns, leaving the candidate None)
                d, sg, w_rms = fits[0]
                sh = float(np.linalg.norm(d))
                if not (
                    w_rms < 0.5 * s.strength_tol_frac * f
                    and sh > s.stale_min_shift_uT
                    and sh > 4 * float(np.linalg.norm(sg))
                    and float(np.max(sg)) < 2 * s.max_offset_std_uT
                ):
                    return
        (delta, sig, whole_rms), (a_off, a_std, _), (b_off, b_std, _) = fits
        whole_n = len(r)
        sig_ab = np.sqrt(a_std**2 + b_std**2)
        shift = float(np.linalg.norm(delta))
        consistent = bool(np.all(np.abs(a_off - b_off) < np.maximum(3 * sig_ab, 3.0)))
        explained = whole_rms < 0.5 * s.strength_tol_frac * f
        significant = shift > s.stale_min_shift_uT and shift > 4 * float(np.linalg.norm(sig))
        well_posed = float(np.max(sig)) < 2 * s.max_offset_std_uT
        if not (consistent and explained and significant and well_posed and self._device_fixed(mc, r)):
            self._stale_cand = None
            return
        # persistence: a magnetised case stays, a disturbed area is walked out of — the same δ must be
        # found again at least stale_confirm_s later (with the strength still deviating in between)
        cand = self._stale_cand
        if cand is None or not np.all(np.abs(np.asarray(cand[1:4]) - delta) < np.maximum(3 * sig, 3.0)):
            self._stale_cand = [t, *map(float, delta)]
            return
        if t - cand[0] < s.stale_confirm_s:
            return
        self._stale_cand = None
        a_inv = np.linalg.inv(cal.soft_iron_array)
        if cal.mag_to_imu is not None:
            a_inv = a_inv @ np.asarray(cal.mag_to_imu, dtype=float).T
        new_offset = cal.offset_array + a_inv @ delta
        provisional = MagCalibration.from_arrays(
            new_offset,
            cal.soft_iron_array,
            field_uT=cal.field_uT,
            method="gravity",
            residual_rms_uT=whole_rms,
            offset_std_uT=sig,
            n_samples=whole_n,
            mag_to_imu=cal.mag_to_imu,
            extra={"sin_dip": sd, "provisional": True},
        )
        events.append(
            (
                t,
                "recalibration_requested",
                {
                    "reason": "offset moved: orientation-dependent, time-stable strength residual",
                    "offset_shift_uT": [float(v) for v in a_inv @ delta],
                    "residual_rms_uT": float(whole_rms),
                },
            )
        )
        self.calibration = provisional
        self.cal_state = "recalibrating"
        self.provided = False
        self._recal_t = t
        self._episode_seen = self._episode
        self.clear_buffer()
        self._rec[:] = np.nan

    def _device_fixed(self, mc: np.ndarray, r: np.ndarray) -> bool:
        """Whether the window's deviation needs a *device-fixed* offset shift, whatever the local field.

        The stale test's fits hold the local field near the WMM (priors of a few µT / degrees), so a
        building whose vertical field differs by several µT is, for a phone held in one pose (texting:
        device z ≈ up, only yaw turns), indistinguishable from an offset shift along the mean up vector
        ``ū``: ``|m_cal|`` and the dip deviate the same way, orientation-dependently only through the tilt.
        Such a shift is not evidence of a moved offset, and taking it as one puts its across-``ū`` part
        into the horizontal field (tyrex iPhone 5 NoDist: a local field 8 µT weaker vertically read as an
        offset shift of (−2.5, −3.4, 7.1) µT; heading 1.7° → 3.0°).  Here F and F sin I are free (the
        alternative hypothesis "the local field differs" gets its own two unknowns): a shift counts only
        where the data determine it: its components along the covariance's eigen-directions that exceed
        4 σ each must together exceed ``stale_min_shift_uT`` (a shift along an ill-determined direction, even
        at 3 σ, is what a few µT of local field error and the walk's tilt errors make of the ambiguity).
        """
        s = self.settings
        try:
            code, off, _, _, cov_b, _, _, _ = _gravity_numbers(
                mc, r[:, 4:7], None, None, s.sigma_strength_uT, s.sigma_tilt_deg, 8, 0.0, 0.0
            )
        except ValueError:
            return False
        if code != K.FIT_OK or not np.all(np.isfinite(cov_b)):
            return False
        w, v = np.linalg.eigh(0.5 * (cov_b + cov_b.T))
        c = v.T @ off  # the shift along the covariance's eigen-directions
        sig = np.sqrt(np.clip(w, 0.0, None))
        c = c[np.abs(c) > 4.0 * sig]  # the components the data determine
        return bool(np.linalg.norm(c) > s.stale_min_shift_uT)

    # ------------------------------------------------------------------ state
    def get_state(self) -> dict:
        return {
            "calibration": None if self.calibration is None else self.calibration.to_dict(),
            "cal_state": self.cal_state,
            "provided": self.provided,
            "buf": _arr(self._buf[: self._nbuf]),
            "rec": _arr(self._rec),
            "rec_i": self._rec_i,
            "last_rec_t": state_float(self._last_rec_t),
            "next_refit_t": state_float(self._next_refit_t),
            "next_stale_t": state_float(self._next_stale_t),
            "rate_ema": self._rate_ema,
            "episode": self._episode,
            "episode_seen": self._episode_seen,
            "recal_t": state_float(self._recal_t),
            "stale_cand": self._stale_cand,
            "n_refits": self._n_refits,
            "last_reject_t": state_float(self._last_reject_t),
            "fit_new": state_float(self._ks[K.K_FIT_NEW]),
            "fit_scale": state_float(self._ks[K.K_FIT_SCALE]),
            "fit_n": int(self._ks[K.K_FIT_N]),
        }

    def set_state(self, st: dict) -> None:
        self.calibration = None if st["calibration"] is None else MagCalibration.from_dict(st["calibration"])
        self.cal_state = st["cal_state"]
        self.provided = bool(st["provided"])
        buf = _unarr(st["buf"], 7)
        self._buf[:] = np.nan
        self._buf[: len(buf)] = buf
        self._nbuf = len(buf)
        self._rec = np.ascontiguousarray(_unarr(st["rec"], 7))
        self._rec_i = int(st["rec_i"])
        self._last_rec_t = _uf(st["last_rec_t"])
        self._next_refit_t = _uf(st["next_refit_t"])
        self._next_stale_t = _uf(st["next_stale_t"])
        self._rate_ema = float(st["rate_ema"])
        self._episode = bool(st["episode"])
        self._episode_seen = bool(st["episode_seen"])
        self._recal_t = _uf(st["recal_t"])
        self._stale_cand = None if st.get("stale_cand") is None else [float(v) for v in st["stale_cand"]]
        self._n_refits = int(st["n_refits"])
        self._last_reject_t = _uf(st["last_reject_t"])
        self._ks[K.K_FIT_NEW] = _uf(st.get("fit_new", "inf"))
        self._ks[K.K_FIT_SCALE] = _uf(st.get("fit_scale", 1.0))
        self._ks[K.K_FIT_N] = int(st.get("fit_n", 0))
        self._ks[K.K_IN_BLOCK] = 0.0
        self._ks[K.K_VERSION] += 1.0
        self._refit_memo = None
        self._bp_memo = None
        self._centre_memo = None
        self._dp_memo = None


def _state_of(cal: MagCalibration) -> str:
    if cal.soft_iron is _EYE:
        return "offset"  # the identity of from_arrays(soft_iron=None)
    return "offset" if _is_identity(cal.soft_iron, 1e-9) else "ellipsoid"


def _is_identity(a, atol: float) -> bool:
    """``np.allclose(a, np.eye(3), atol=atol)`` for a 3×3 nested sequence, without numpy's overhead."""
    for i in range(3):
        for j in range(3):
            e = 1.0 if i == j else 0.0
            if not abs(float(a[i][j]) - e) <= atol + 1e-5 * e:
                return False
    return True


def _mean_sin_dip(m: np.ndarray, u: np.ndarray, cal: MagCalibration) -> float:
    mc = cal.apply(m)
    nm = np.linalg.norm(mc, axis=1)
    v = -np.einsum("ij,ij->i", mc, u) / np.maximum(nm, 1e-9)
    return float(np.median(v))


def _cal_summary(cal: MagCalibration) -> dict:
    return {
        "method": cal.method,
        "offset_uT": [round(float(v), 3) for v in cal.offset],
        "offset_std_uT": [round(float(v), 3) if np.isfinite(v) else None for v in cal.offset_std_uT],
        "field_uT": round(float(cal.field_uT), 3) if np.isfinite(cal.field_uT) else None,
        "residual_rms_uT": round(float(cal.residual_rms_uT), 3) if np.isfinite(cal.residual_rms_uT) else None,
        "coverage": round(float(cal.coverage), 3) if np.isfinite(cal.coverage) else None,
        "n_samples": int(cal.n_samples),
    }


def _uf(v) -> float:
    return float(v)


def _arr(a: np.ndarray) -> list:
    return [[state_float(x) for x in row] for row in np.asarray(a, dtype=float)]


def _unarr(rows: list, ncol: int) -> np.ndarray:
    if not rows:
        return np.empty((0, ncol))
    return np.asarray([[float(x) for x in row] for row in rows], dtype=float)
