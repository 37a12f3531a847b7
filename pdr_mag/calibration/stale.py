"""Stale-calibration test: has the hard-iron offset moved (a magnetised case), or is it a passing disturbance?

The physics.  A new device-fixed offset ``δ`` adds the same vector to the calibrated field in the device
frame whatever the orientation, so ``|m_cal| − F ≈ δ · m̂_cal`` varies with orientation in a fixed,
repeatable way: the gravity-aided fit of ``δ`` (:mod:`pdr_mag.calibration.gravity`) on recent calibrated
samples explains it down to the noise, with the same ``δ`` from the older and the newer half of the window.
An external anomaly is fixed in the world (or moves with the walker's position): it rotates with the device
like the Earth's field, no constant device-frame ``δ`` explains it, the two halves disagree and the fit
residual stays large; and it passes.  A building whose field differs from the WMM is a third case: held in
one pose, it mimics a shift along the mean up vector, so a shift counts only where the data determine it
with the local strength and dip free (:func:`device_fixed`).

A shift that happens inside the window — the usual way: a case's magnet clasped, the phone's OS replacing
its hard-iron estimate in a stream it calibrates — leaves the older samples explained by the calibration in
force and the newer ones by the shifted one.  From that moment the field deviates from the reference (its
strength from F by ``δ · m̂``, and its dip, in proportions the pose sets: a phone held flat and a shift
across the field move the dip alone).  The window is cut where the share of deviating samples steps up
(:func:`step_start`) and the segment after the cut is tested on its own as a window first
(:func:`window_shift`), so the shift is found once that segment determines it (7–15 s after a 25-µT shift
on simulated walks, phone in hand, in a pocket or swinging) rather than when a window half lies wholly after
it (10–25 s).  Without such a step, a window whose halves disagree has its newer half tested on its own.

The test runs on the recent window when its cheap first part found the strength or the dip deviating
(:func:`pdr_mag.calibration._online_kernel.stale_precheck`); what follows a found shift (confirmation a
while later, the recalibration request) is the calibrator's state machine
(:class:`pdr_mag.calibration.online.OnlineCalibrator`).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from pdr_mag.calibration._online_kernel import STALE_DIP_FACTOR, step_start_index
from pdr_mag.calibration.gravity import FitModel, fit_offset
from pdr_mag.calibration.online_settings import OnlineSettings


class Shift(NamedTuple):
    """A device-fixed offset shift found on the window: ``δ`` of the calibrated field, its 1-σ and the
    whole-window fit's residual RMS (µT)."""

    delta: np.ndarray
    sigma: np.ndarray
    rms: float


#: :func:`window_shift`'s verdict when a fit failed: the test says nothing (a pending candidate stays).
INCONCLUSIVE = "inconclusive"


def window_shift(
    mag_cal: np.ndarray,
    up: np.ndarray,
    model: FitModel,
    free_model: FitModel,
    settings: OnlineSettings,
    candidate_pending: bool,
) -> Shift | None | str:
    """Fit a device-fixed shift ``δ`` of the calibrated field on the window (oldest first).

    ``model``: the fit's references (F, sin I: the WMM's or the calibration's) with their priors;
    ``free_model``: F and sin I free (for :func:`device_fixed`).

    Fits on the whole window and on each half; the shift counts when the halves agree (within 3 σ of their
    difference, at least 3 µT), the whole-window fit explains the deviation (RMS below half of
    ``strength_tol_frac · F``), the shift is significant (above ``stale_min_shift_uT`` and 4 σ), well
    posed (σ below twice ``max_offset_std_uT``) and :func:`device_fixed`.

    The segment after a step in the field's deviation (:func:`step_start`) is tested first, the same way
    on its own: it is the shifted calibration's alone.  Where the whole-window fit explains the deviation but
    its halves disagree — the signature of a shift that happened inside the window — the newer half (at
    least :data:`MIN_NEWER` samples) is tested on its own too, unless the step's segment was longer.

    Returns the :class:`Shift`, None when there is none, or :data:`INCONCLUSIVE` when a fit failed.  With
    no candidate pending, a whole-window fit that fails the tests ends the test at once (None).
    """
    start = step_start(mag_cal, up, model, settings)
    if start is not None:
        newer, _ = _stationary_shift(mag_cal[start:], up[start:], model, free_model, settings, False)
        if isinstance(newer, Shift):
            return newer
    found, newer_fit = _stationary_shift(mag_cal, up, model, free_model, settings, candidate_pending)
    half = len(mag_cal) // 2
    if newer_fit is not None and (start is None or start > half) and len(mag_cal) - half >= MIN_NEWER:
        newer, _ = _stationary_shift(mag_cal[half:], up[half:], model, free_model, settings, False, newer_fit)
        if isinstance(newer, Shift):
            return newer
    return found


def step_start(mag_cal: np.ndarray, up: np.ndarray, model: FitModel, settings: OnlineSettings) -> int | None:
    """Where the window's field starts to deviate and keeps deviating: the sample ``j`` that maximises the
    share of samples deviating as the precheck counts them (strength beyond half ``strength_tol_frac`` of F,
    or dip beyond twice ``add_dip_tol_deg`` of the reference) after it less the share before it, when after it
    the share reaches ``stale_min_frac`` and before it stays below half of that; None when there is no step.

    A device-fixed shift adds ``δ`` to the calibrated field from the moment it happens, whatever the pose:
    a step in that share.  The segment after it is the shifted calibration's alone, so it is tested as a
    window of its own (:func:`window_shift`) as soon as it holds :data:`MIN_NEWER` samples, instead of
    waiting for a window half to lie wholly after the shift."""
    if model.strength is None:
        return None
    s = settings
    tol = s.stale_band_uT(model.strength)
    dip_check = model.sin_dip is not None
    dip_deg = float(np.degrees(np.arcsin(model.sin_dip))) if dip_check else 0.0
    j = step_start_index(np.ascontiguousarray(mag_cal, dtype=np.float64),
                         np.ascontiguousarray(up, dtype=np.float64), model.strength, tol, dip_check, dip_deg,
                         STALE_DIP_FACTOR * s.add_dip_tol_deg, s.stale_min_frac, MIN_NEWER)
    return None if j < 0 else int(j)


#: Fewest samples in a segment tested on its own (a step's, or the newer half), and before a step (4 s at
#: ``stale_rate_hz``).
MIN_NEWER = 40


def _stationary_shift(mag_cal, up, model, free_model, settings, candidate_pending, whole=None) -> tuple:
    """One shift over the whole of ``mag_cal`` (:func:`window_shift`'s tests, without its newer half):
    ``(verdict, newer)``, ``newer`` the newer half's fit when the whole fit explains the deviation and the
    halves disagree (else None): the whole-window fit of that half's own test.  ``whole``: the whole-window
    fit when it is known already."""
    s = settings
    n = len(mag_cal)
    half = n // 2
    fits = []
    for lo, hi in ((0, n), (0, half), (half, n)):
        if lo == 0 and hi == n and whole is not None:
            fits.append(whole)
        else:
            try:
                fit = fit_offset(mag_cal[lo:hi], up[lo:hi], model)
            except ValueError:
                return INCONCLUSIVE, None
            if not fit.ok:
                return INCONCLUSIVE, None
            fits.append(Shift(fit.offset, np.sqrt(np.maximum(fit.offset_cov.diagonal(), 0)), fit.rms))
        if hi == n and lo == 0 and not candidate_pending and not _explains(fits[0], model.strength, s):
            return None, None
    whole, a, b = fits
    sig_ab = np.sqrt(a.sigma**2 + b.sigma**2)
    consistent = bool(np.all(np.abs(a.delta - b.delta) < np.maximum(3 * sig_ab, 3.0)))
    explains = _explains(whole, model.strength, s)
    if not (consistent and explains and device_fixed(mag_cal, up, free_model, s)):
        return None, b if explains and not consistent else None
    return whole, None


def _explains(fit: Shift, strength: float, s: OnlineSettings) -> bool:
    """The whole-window tests: explained, significant and well posed."""
    shift = np.linalg.norm(fit.delta)
    return bool(
        fit.rms < s.stale_band_uT(strength)
        and shift > s.stale_min_shift_uT
        and shift > 4 * np.linalg.norm(fit.sigma)
        and float(fit.sigma.max()) < 2 * s.max_offset_std_uT
    )


def device_fixed(mag_cal: np.ndarray, up: np.ndarray, free_model: FitModel, settings: OnlineSettings) -> bool:
    """Whether the window's deviation needs a *device-fixed* offset shift, whatever the local field.

    The window fits hold the local field near the WMM (priors of a few µT / degrees), so a building whose
    vertical field differs by several µT is, for a phone held in one pose (texting: device z ≈ up, only yaw
    turns), indistinguishable from an offset shift along the mean up vector ``ū``: ``|m_cal|`` and the dip
    deviate the same way, orientation-dependently only through the tilt.  Such a shift is not evidence of a
    moved offset, and taking it as one puts its across-``ū`` part into the horizontal field (tyrex iPhone 5
    NoDist: a local field 8 µT weaker vertically read as a shift of (−2.5, −3.4, 7.1) µT; heading 1.7° →
    3.0°).  Here F and F sin I are free (the alternative "the local field differs" gets its own two
    unknowns): a shift counts only where the data determine it — its components along the covariance's
    eigen-directions that exceed 4 σ each must together exceed ``stale_min_shift_uT`` (a shift along an
    ill-determined direction, even at 3 σ, is what a few µT of local field error and the walk's tilt
    errors make of the ambiguity).  ``free_model``: the fit's σ, F and sin I not given.
    """
    try:
        fit = fit_offset(mag_cal, up, free_model)
    except ValueError:
        return False
    cov = fit.offset_cov
    if not fit.ok or not np.all(np.isfinite(cov)):
        return False
    w, v = np.linalg.eigh(0.5 * (cov + cov.T))
    c = v.T @ fit.offset  # the shift along the covariance's eigen-directions
    sig = np.sqrt(np.clip(w, 0.0, None))
    c = c[np.abs(c) > 4.0 * sig]  # the components the data determine
    return bool(np.linalg.norm(c) > settings.stale_min_shift_uT)
