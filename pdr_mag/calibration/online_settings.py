"""Settings of the online calibrator (:class:`pdr_mag.calibration.online.OnlineCalibrator`).

Apart from the calibrator so that the modules it is built from (:mod:`~pdr_mag.calibration.refit`,
:mod:`~pdr_mag.calibration.stale`, the compiled loop :mod:`~pdr_mag.calibration._online_kernel`) read them
without importing the calibrator itself.  The compiled loop reads them as the record
:func:`pdr_mag._records.settings_record` builds (``min_sep_up_deg`` as its cosine ``cos_up``,
``stale_rate_hz`` as its period ``ring_dt``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pdr_mag._records import kernel_field


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
    min_sep_yaw : float
        … or closer than ``min_sep_yaw · B_h`` where that is less (``B_h = F cos I``, the reference's
        horizontal field; rad): a walker's turns sweep the field round a circle of radius ``B_h``, so a
        neighbourhood spans at most this much turn (0.3 rad, 17°: what ``min_sep_frac`` spans at a dip of
        66°; below that dip, as everywhere the shared data were recorded, ``min_sep_frac`` is the smaller).
        Near the magnetic poles ``B_h`` is a quarter of F and less; a turn there would otherwise need 27°
        (dip 75°) to give a new sample, and a walk of 120 s with few turns no first calibration.
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
        2 σ shift a new fit needs to replace the calibration (:func:`pdr_mag.calibration.refit.replaces`).
        A change of the calibration, a rotation episode's start or end and a cleared buffer make the next
        attempt fit.
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
        A refit (gravity-aided, sphere or full) is accepted only when every offset σ is below this.
    first_offset_std_uT : float
        The same bound for the very first calibration (none yet): a coarse offset early lets the filter
        align the heading and learn the gyro bias before the first disturbance; refits refine it.  Its σ
        (scaled for correlated errors, ``field_corr_s``) goes with it to the fusion filter, which weighs the
        field by it: 8 µT against a horizontal field of ~20 µT is a ~20° heading, better than none.
    max_rms_frac : float
        Accepted only when the robust residual RMS is below ``max_rms_frac · F``.
    max_offset_uT : float
        Offsets beyond this are implausible.
    turned_field_deg : float
        Without a reference field (no place known: F and the dip are the fit's own), a first calibration
        (none in force) is refused when, about it, the buffer's field azimuth in the gyroscope's frame
        spreads more than this (1.4826 × MAD, a linear drift removed:
        :mod:`pdr_mag.calibration.turned`) — the Earth's field does not turn against the device.  The bound
        holds up to a dip of 63.4° and grows as tan|I| beyond (a tilt error's share of the azimuth:
        :func:`~pdr_mag.calibration.turned.bound_deg`).  Right first fits spread
        0.4–6.4° on the simulator and 1.5–22° on the tyrex walks (dip 61°; the filter's tilt while running),
        fits into a pass by steel 38–95°, the one wrong tyrex first fit 24°.
    strength_tol_frac : float
        After a calibration, samples whose ``| |m_cal| − F |`` exceeds this fraction of F are not buffered;
        half of it is the stale test's band (a sample beyond it, or whose dip is more than twice
        ``add_dip_tol_deg`` off the reference, counts as deviating).
    add_tol_frac, add_dip_tol_deg : float
        Once calibrated, a sample enters the buffer only when its strength is within ``add_tol_frac · F`` and
        its dip within ``add_dip_tol_deg`` of the reference (no disturbed samples in the fits).
    ellipsoid_coverage : float
        Coverage from which the core's full (ellipsoid) fit is attempted.
    ellipsoid_precheck_frac : float
        The full fit is attempted only when, besides, the buffer's coverage on the equal-area grid of
        :func:`pdr_mag.calibration.coverage.coverage`, about the current offset estimate, reaches this share
        of ``AcceptanceSettings.min_coverage``: a cheap gate that spares full fits on a sparse buffer.  It is
        not the acceptance rule: the fit is judged by the heading error its uncertainty allows
        (:func:`pdr_mag.calibration.coverage.accept`), which well-spread samples can meet below the gate.
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
    episode_tau_s : float
        Time constant (s) of that smoothing, an exponential average over time: each magnetometer sample
        ``Δt`` after the one before moves it by ``1 − exp(−Δt / τ)`` of the way to the sample's gyro rate,
        so an episode means the same turning at any magnetometer rate (5–100 Hz).
    recal_fallback_s : float
        While recalibrating without a figure-8, an accepted gravity-aided refit on the new buffer older
        than this ends the recalibration.
    field_corr_s : float
        Time over which the errors of buffered samples stay correlated (the local field of the place, the
        priors' error), s: a gravity-aided fit's offset covariance is scaled by ``N / N_eff``,
        ``N_eff = min(N, 1 + span / field_corr_s)`` (:func:`.refit.with_correlated_errors`).
    soft_iron_std : float
        The soft iron an offset-only fit cannot see, per element of ``A − I`` (1-σ).  The offset error it
        leaves (:func:`pdr_mag.calibration.gravity.soft_iron_offset_covariance`) goes with a gravity-aided
        fit made while no sure fit of the walk's own is in force (nothing, a prior, a first fit above
        ``max_offset_std_uT``) to the fusion filter, whose offset states start from it
        (``extra["shape_offset_cov_uT2"]``,
        :attr:`~pdr_mag.calibration.model.MagCalibration.offset_error_covariance`); acceptance and
        replacement are judged on the fit's own covariance, as every fit's.  Later refits are not given it:
        each resets the offset states, and a shape term there reopens them to any change of the field (a
        25-µT hard-iron jump then let into the heading, benchmarks/NOTES.md).  0.03: the shared phones'
        (the tyrex iPhones' figure-8 fits, the mall phone's 1.07 horizontal axis ratio); 0 = off.
    prior_band_frac, prior_band_dip_deg, prior_min_samples : float, float, int
        A prior calibration (the phone's, a store's: :mod:`.prior`) is refused when, over at least
        ``prior_min_samples`` buffered samples, the median strength of the field it calibrates is farther
        from the reference than ``prior_band_frac · F``, or its median dip farther than
        ``prior_band_dip_deg`` from the reference inclination, each widened by what 3σ of the prior's offset
        can do (the interference detectors' loose bands: no place indoors departs that far for long);
        without a reference, when the strength is outside the Earth's range widened by that share.  Ten
        samples: their median holds with four of them disturbed, and a store's entry of another phone
        (70–90 µT off) is refused one or two refits sooner than with twenty (the mall traces: up to 22 s
        of a wrong prior in force), while none of the phone's own estimates there is refused.
    consensus_window, consensus_min_inliers : int
        The consensus fit (:mod:`.consensus`), tried when no fit of the whole buffer is accepted: the
        hypotheses come from windows of this many consecutive samples (ten: 2–5 s of a walk, enough yaw for
        the gravity-aided fit, short enough to lie between two disturbances), and a result needs this many
        inliers (a window and a half: one window's own samples do not make a consensus).
    consensus_pairs : int
        Hypotheses from pairs of samples solved exactly (strength and dip are linear in ``(b, |b|²)``), half
        of them neighbours in time (a disturbance comes in runs, so do the clean samples between), beside the
        windows'; drawn with a generator seeded by the buffer's size (a run repeats itself).
    consensus_strength_frac, consensus_dip_deg : float
        A sample agrees with a hypothesis when the field it gives is within this share of F (as far as a
        whole fit's residual RMS may reach, ``max_rms_frac``: a sample further off is not of that fit) and
        this angle of the reference dip (twice the admission band ``add_dip_tol_deg``: the tilt of a walking
        phone is known to a few degrees).
    """

    buffer_size: int = 400
    min_sep_frac: float = 0.12
    min_sep_yaw: float = 0.3
    min_sep_up_deg: float = kernel_field(6.0, "cos_up", lambda v: np.cos(np.radians(v)))
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
    max_offset_std_uT: float = 3.0
    first_offset_std_uT: float = 8.0
    max_rms_frac: float = 0.08
    max_offset_uT: float = 2000.0
    turned_field_deg: float = 20.0
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
    stale_rate_hz: float = kernel_field(10.0, "ring_dt", lambda v: 1.0 / v)
    episode_rate: float = 1.5
    episode_tau_s: float = 1.0
    recal_fallback_s: float = 20.0
    field_corr_s: float = 2.0
    soft_iron_std: float = 0.03
    prior_band_frac: float = 0.4
    prior_band_dip_deg: float = 25.0
    prior_min_samples: int = 10
    consensus_window: int = 10
    consensus_min_inliers: int = 15
    consensus_pairs: int = 300
    consensus_strength_frac: float = 0.08
    consensus_dip_deg: float = 8.0

    def stale_band_uT(self, strength: float) -> float:
        """The stale test's strength band, µT: half ``strength_tol_frac`` of F (a sample beyond it deviates;
        a whole-window fit explains the deviation with a residual RMS below it)."""
        return 0.5 * self.strength_tol_frac * strength
