"""Settings of the fusion filter, grouped by concern: gyroscope, accelerometer, magnetometer, reported
uncertainty, the interference detectors, and the output rate.

Each group is a frozen dataclass; :class:`FusionSettings` holds one of each.  The compiled kernels read them
as one record built by :func:`pdr_mag._records.settings_record` (``p.gyro.noise``, ``p.mag.gate``,
``p.interference.dip.tol_deg``, …); settings in degrees reach the kernel in radians (``noise_deg`` →
``noise_rad``) and the output rate as its period (``out_dt_s``).  To change a setting::

    FusionSettings(mag=MagSettings(gate=3.0))
    dataclasses.replace(s, accel=dataclasses.replace(s.accel, range=19.6))

The model the settings belong to is in :mod:`pdr_mag.fusion` and each sensor's module.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pdr_mag._records import check_numbers, kernel_field
from pdr_mag.conventions import GRAVITY
from pdr_mag.fusion.detectors import InterferenceSettings


def _radians(name: str, default: float):
    """A setting in degrees that the kernel reads in radians as ``name``."""
    return kernel_field(default, name, np.radians)


def _period(v: float) -> float:
    return 1.0 / v if v > 0 else 0.0


@dataclass(frozen=True)
class GyroSettings:
    """The gyroscope: prediction, bias, gaps and the zero-rate update while still
    (:mod:`pdr_mag.fusion.gyro`).

    Attributes
    ----------
    noise : float
        Gyroscope angle random walk, rad/s/√Hz (phones: 0.003–0.01).
    bias_rw : float
        Gyroscope bias random walk, rad/s/√s.
    bias0_std : float
        Initial bias standard deviation per axis, rad/s.  0.1 (5.7 °/s per axis, √3 · 5.7 ≈ 10 °/s for the
        norm) covers the raw offsets of real phones (4–6 °/s, on one axis: PEERS.md) at about 1σ; a wider
        prior lets the first seconds of a disturbed, not yet flagged field teach the filter offsets no
        phone has.
    max_dt : float
        Gyro gaps up to this long are integrated with the mean rate of their ends, and their attitude
        variance grows by ``var(ω) (Δt − 0.05 s)²`` (the rate meanwhile is unknown to the recent motion
        level); longer gaps are not integrated and add ``(|ω̄|² + var(ω)) Δt²``, s.
    still_gyro : float
        Still when the RMS deviation of the gyro from its running mean is below this, rad/s…
    still_acc : float
        …and that of the accelerometer below this, m/s²…
    still_tau_s : float
        …(running statistics with this time constant, s; also the accelerometer's running variance)…
    still_min_s : float
        …for at least this long, s; then zero-rate updates of the bias.
    zupt_noise : float
        Noise density of a zero-rate update, rad/s·√s (per-sample σ = zupt_noise / √Δt: 0.02 rad/s at
        100 Hz — gyro noise plus the tremor of a hand-held "still" phone).
    """

    noise: float = 0.005
    bias_rw: float = 2e-4
    bias0_std: float = 0.1
    max_dt: float = 0.5
    still_gyro: float = 0.03
    still_acc: float = 0.3
    still_tau_s: float = 0.3
    still_min_s: float = 0.5
    zupt_noise: float = 0.002

    def __post_init__(self):
        check_numbers(self, positive=("noise", "bias0_std", "max_dt", "still_tau_s", "zupt_noise"))


@dataclass(frozen=True)
class AccelSettings:
    """The accelerometer: the tilt's start, its averaged (or per-sample) updates, clipping and the tilt
    reset (:mod:`pdr_mag.fusion.accel`).

    Attributes
    ----------
    tilt0_std : float
        Floor of the initial tilt standard deviation, rad (a start at rest; the first sample's own
        acceleration and rotation add to it, :func:`pdr_mag.fusion.accel.init_tilt`).
    tau_s : float
        Time constant of the average of the specific force in the (almost inertial) world frame, s.  The
        tilt is corrected from that average (the mean linear acceleration of a walking or swinging hand
        over the window is Δv/τ ≈ 0, whereas single samples of a swinging arm point along the arm).  All
        samples are averaged; ``gate`` applies to the average.  0 = correct from single samples
        (``noise``, ``corr_s``, ``rate_k``).
    interval_s : float
        At most one averaged-accelerometer update per this interval, s.
    tilt_reset_k, tilt_reset_tau_s, tilt_reset_min_deg : float
        Tilt reset.  The specific force is also averaged in the world frame over ``tilt_reset_tau_s``
        (several strides: a running arm's swing, which the short average passes at a quarter of its
        amplitude, cancels); once that window is full, its average has ``||ā| − g| < 0.3 g`` and it is
        farther from up than ``tilt_reset_min_deg`` and ``tilt_reset_k`` σ of the tilt error, the attitude
        is turned so that it is up (a tilt started from one sample of a running arm can be 150° off, beyond
        what a linearised update can correct, and its corrections would teach the gyro bias instead).  A
        short-window average that far off (``tilt_reset_k`` σ of the tilt error and the update's noise) is
        never an update.  ``tilt_reset_k`` 0 = neither.
    avg_noise : float
        Noise of the averaged direction, per update (≈ rad); plus ``dyn · ||ā| − g| / g``.
    noise : float
        Base noise of the normalised accelerometer direction, per sample (dimensionless ≈ rad).
    corr_s : float
        Correlation time of the linear acceleration, s: the per-sample noise grows by
        ``var(a) / g² · corr_s / Δt`` with ``var(a)`` the running variance of the accelerometer
        (time constant ``GyroSettings.still_tau_s``) and Δt the accelerometer period — the same information
        per second whatever the sample rate.
    dyn : float
        Noise added per unit of ``||a| − g| / g``.
    spread_k : float
        Dynamics term of the averaged update's noise: the direction of ``ā_w`` is off by about
        ``spread_k · s`` rad per horizontal axis, ``s`` the RMS horizontal spread of the world-frame
        specific force about its average, over g.  0.19 is the slope measured with motion-capture attitude
        on 42 walks of three phones and eight ways of carrying them (texting: s ≈ 0.08, 1–2°; running in
        the hand: s ≈ 1, 15°).  Successive updates ``interval_s`` apart share the window τ, so this
        variance counts ``τ / interval_s`` times per update: the information per second is that of one
        independent direction per window.
    range : float
        Full scale of the accelerometer, m/s² per axis (0: found in the data).  A sample with an axis at the
        range is clipped: its true value lies beyond, by an unknown amount.  Found in the data, the range is
        the largest |a_i| seen once at least ``clip_min_hits`` samples came within ``clip_band`` of it and
        it is above 1.5 g (phone ranges are 2, 4, 8 or 16 g): a sensor that clips piles its samples up at
        the range (exactly, or spread over a few per cent by the phone's own axis calibration, as on the
        iPhone 4S), one that does not reaches its largest value once.
    clip_band : float
        Samples within this fraction of the range count as clipped.
    clip_min_hits : float
        Samples near the largest value that make it a range.
    clip_k : float
        Clipped samples stay in the average ``ā_w`` — dropping them would drop the peaks of every step and
        tilt it far more (by 36° mean, 86° p95 on a real running walk) — but their missing excess, of the
        order of a g each, is unknown: the direction of ``ā_w`` may be off by about ``share · excess / g``,
        so the averaged update's noise grows by ``(clip_k · share)²`` rad² (``clip_k`` = 1: an excess of one
        g), ``share`` the weight of clipped samples in the window, counted ``τ / interval_s`` times like the
        spread.  Single-sample updates (``tau_s = 0``) skip clipped samples.
    turn_speed : float
        Walking speed assumed for the centripetal acceleration ``v · ω_up`` of a turn, m/s (0 = off: on
        the real walks it costs more than it gains, as turns are frequent and tilt then drifts): adds
        ``(v ω_up / g)² · turn_corr_s / Δt`` to the per-sample noise (ω_up the turn rate about up).
    turn_corr_s : float
        Correlation time of that acceleration (the length of a turn), s.
    rate_k : float
        Tilt error per rad/s of angular rate from centripetal / tangential acceleration, rad·s: the
        per-sample update's noise (``tau_s = 0``, bias-corrected rate) and, in every mode, part of the
        initial tilt variance (the first sample's raw rate).
    gate : float
        Accelerometer samples (or averages) with ``||a| − g| > gate · g`` are not used.
    gravity : float
        g, m/s².
    """

    tilt0_std: float = 0.2
    tau_s: float = 0.5
    interval_s: float = 0.05
    tilt_reset_k: float = 4.0
    tilt_reset_tau_s: float = 3.0
    tilt_reset_min_deg: float = _radians("tilt_reset_min_rad", 30.0)
    avg_noise: float = 0.2
    noise: float = 0.05
    corr_s: float = 0.1
    dyn: float = 2.0
    spread_k: float = 0.19
    range: float = 0.0
    clip_band: float = 0.05
    clip_min_hits: float = 5.0
    clip_k: float = 1.0
    turn_speed: float = 0.0
    turn_corr_s: float = 1.0
    rate_k: float = 0.5
    gate: float = 0.5
    gravity: float = GRAVITY

    def __post_init__(self):
        check_numbers(self, positive=("tilt0_std", "noise", "gravity"))


@dataclass(frozen=True)
class MagSettings:
    """The magnetometer: the heading update's noise and gates, the heading error state c, the recent
    environment and the re-acquisition of a lost heading (:mod:`pdr_mag.fusion.mag`).

    Attributes
    ----------
    noise_deg : float
        Heading noise of one magnetometer update, deg (calibration residual, time correlation).
    noise_uT : float
        Field noise, µT; adds ``noise_uT / B_h`` rad to the heading noise (B_h horizontal strength).
    dist_k : float
        Heading noise added per µT of the smallest disturbance that explains the detectors' deviations
        (strength and dip from their local references, the gyro-consistency angle), divided by B_h
        (``k |d|_min / B_h`` rad).
    time_unc_s : float
        Timestamp uncertainty of the magnetometer against the gyroscope, s: adds ``(|ω| τ F / B_h)²`` to
        the heading noise (a swinging phone turns at several rad/s).
    cons_k : float
        Weight (0 = off, 1 = on) of the gyro-consistency angle in that smallest disturbance
        (``F · angle``).
    tilt_k : float
        Weight (0 = off, 1 = on) of the tilt errors in the heading update: the projection of the field on
        the horizontal plane turns by ``−(m_x m_z δθ_x + m_y m_z δθ_y) / B_h²`` per tilt error; they enter
        H as consider states (in the gain and P, never corrected by the magnetometer).
    error_std_deg : float
        Standard deviation of the slowly varying magnetometer heading error c (residual calibration
        error, local anomalies of the building), deg.  Modelled as a first-order Gauss–Markov state so
        the filter does not take correlated errors for gyro bias.
    error_tau_s : float
        Correlation time of c, s.
    error_turn_deg : float
        Turn over which c decorrelates as well, deg (0 = time only): c is also a function of the device's
        heading — a calibration's offset residual δb turns the field by ``δb⊥ / B_h``, whose sign changes
        as the device turns (correlation ``cos Δψ`` between two headings) — and a walker who turns walks
        into another part of the building.  Each gyroscope step multiplies c's correlation by
        ``exp(−|ω̄_up| Δt / θ_c)``, ``ω̄_up`` the rate about the world's up averaged over a stride
        (:data:`pdr_mag.fusion.gyro.TURN_TAU_S`), so a swinging or pocketed phone's yaw back and forth
        within each stride does not count as turning.  90°: a quarter turn, where ``cos Δψ`` is 0.
        (With ``offset_states`` the offset residual is a state of its own; the turn then stands for the
        building's part of c, which a walker who turns leaves behind.)
    offset_states : bool
        The calibration's offset error as three states of the filter, ``δo`` (device frame, µT), started
        at the calibration's covariance (``M Σ_b Mᵀ``: the calibrated field's error) whenever a calibration
        comes into force, and observed by the heading row through the field's gradient ``g = ∂ψ/∂m_d``: a
        constant offset error turns the field by ``g·o``, one way at one heading and the other way at the
        opposite one, while the gyroscope says the device turned by neither — so the walker's turns tell it
        apart from the heading and from c (the body-frame magnetometer biases of ArduPilot's EKF3 and PX4's
        EKF2).  The field the filter takes is the calibrated one less the estimate ``o``.  False: the offset
        error is part of c's stationary variance (``g Σ_b gᵀ``, as noise that decorrelates) and floors the
        reported std.
    offset_rw_uT : float
        Random walk of the offset error, µT/√s: a phone's hard iron drifts with its temperature and its
        currents (0.05: 0.4 µT a minute, 3 µT an hour).
    env_k : float
        Where the recent field was disturbed, a field that looks clean may still be turned: steel that
        changes strength and dip by ``|d|`` nearby turns the horizontal field by up to ``|d| / B_h``
        elsewhere in the same place.  The stationary variance of c grows by ``(k · d_env / B_h)²``, with
        ``d_env²`` the exponentially weighted mean of ``d_min²`` (see ``dist_k``) over ``env_tau_s`` and
        ``B_h`` the reference horizontal strength (0 = off).
    env_tau_s : float
        Memory of that environment level (and of the flagged share, :class:`UncertaintySettings`), s.
    env_prior_uT : float
        The environment level before anything is known of it, µT: a walk starts where the field may already
        be turned (indoor fields deviate from the model by several µT), so ``d_env`` starts at no less than
        this and learns the place's own level over ``env_tau_s``; and the first fix's c counts the unseen
        component of a disturbance at this level, ``σ_c² + d₀² / (2 B_h²)``
        (:func:`pdr_mag.fusion.mag._first_fix`).
    interval_s : float
        At most one magnetometer update per this interval, s (the errors are correlated in time; 0 = all).
    gate : float
        χ² gate of the heading innovation, in standard deviations.
    reject_inflate_deg : float
        While an undisturbed-looking field keeps failing the gate, the heading variance grows by this
        squared per second (deg/√s) beyond the gyroscope's own uncertainty.  0 (default): a field that a
        heading the gyroscope vouches for disagrees with is kept out until re-acquisition (``reacquire_s``)
        or the stale test decides — 3 let a hard iron's shift into the heading within seconds (benchmarks/
        NOTES.md).
    reacquire_s : float
        Re-acquisition: when a field that the detectors find clean has failed the gate for this long
        without a break (or for as long as the accepted fields behind the heading span, if shorter, but no
        less than two of c's correlation times ``error_tau_s``), and the innovations agree among themselves
        (their scatter about a line in time — a lost heading drifts at the bias's error — exponentially
        weighted over this time, is below ``reacquire_spread_deg``; :mod:`pdr_mag.fusion.mag`), the filter is
        what is lost: the heading is set to the magnetometer's (a ``heading_reset`` event carries the jump),
        uncorrelated from the bias, whose variance about up grows to the drift rate the jump implies.  0 =
        off.  A field turned by steel is local: 20 s of walking (~25 m) leaves the reach of a building's
        structure, so a field that still disagrees by the same angle is right and the heading wrong; a steel
        area passed in less time is waited out — unless the heading itself rests on fields of a shorter span.
    reacquire_spread_deg : float
        Largest spread (standard deviation) of those innovations about their line, deg.
    """

    noise_deg: float = _radians("noise_rad", 5.0)
    noise_uT: float = 1.0
    dist_k: float = 2.0
    time_unc_s: float = 0.01
    cons_k: float = 1.0
    tilt_k: float = 1.0
    error_std_deg: float = _radians("error_std_rad", 6.0)
    error_tau_s: float = 5.0
    error_turn_deg: float = _radians("error_turn_rad", 90.0)
    offset_states: bool = True
    offset_rw_uT: float = 0.05
    env_k: float = 0.3
    env_tau_s: float = 30.0
    env_prior_uT: float = 5.0
    interval_s: float = 0.2
    gate: float = 4.0
    reject_inflate_deg: float = _radians("reject_inflate_rad", 0.0)
    reacquire_s: float = 20.0
    reacquire_spread_deg: float = _radians("reacquire_spread_rad", 15.0)

    def __post_init__(self):
        check_numbers(self, positive=("gate", "env_tau_s"))


@dataclass(frozen=True)
class UncertaintySettings:
    """What the reported ``heading_std_deg`` counts beyond the filter's own variance: the consider part
    (:func:`pdr_mag.fusion.gyro.unmodelled_var`).  Both 0: the filter's variance alone.

    Attributes
    ----------
    env_k : float
        The environment's turning of the horizontal field as the *reported* std counts it:
        ``(env_k · d_seen / B_h)²`` in c's stationary variance, against the filter's
        ``(MagSettings.env_k · d_env / B_h)²`` (``d_seen²`` the same mean of ``d_min²`` over the samples
        seen, without the filter's prior ``MagSettings.env_prior_uT``: a start in a disturbed place counts
        what it saw).  ``d_min`` sees the two components of a disturbance that change strength and dip; the
        third, which turns the horizontal field, is unseen, and a disturbance with no preferred direction
        has it as large as the mean of the two: ``d_min / √2`` (the default 0.71).  The filter weighs the
        field with the smaller ``MagSettings.env_k`` (a field that passes the detectors in such a place is
        still informative); the difference is noise the weighting leaves out, carried through the same
        gains in a consider covariance ``U`` and added to the reported variance,
        ``P[δθ_z, δθ_z] + U[δθ_z, δθ_z]`` (floored by the calibration's own,
        :func:`pdr_mag.fusion.kernel.calibration_floor`).  0 leaves this part out.
    flag_k : float
        Weight of the flagged share in that consider part: where a share ``s_flag`` of the recent samples
        (exponentially weighted over ``MagSettings.env_tau_s``, normalised by the weight seen, so a start
        counts what it saw) was flagged, the disturbances there are at least the detectors' tolerance
        ``d_tol² = tol_F² + (F tol_I)²``, and a field that passes between them is turned by such a
        disturbance's unseen component as often: ``flag_k · s_flag · d_tol² / 2`` is added to c's
        unmodelled variance (× 1/B_h²).  0 = off.  Together with ``env_k`` the truth lies beyond 3σ in
        at most 3.4 % of any tyrex walk's frames, at the price of a conservative std in disturbed buildings
        (median 18–20° there; the variants measured are in benchmarks/NOTES.md).
    """

    env_k: float = 0.71
    flag_k: float = 1.0

    def __post_init__(self):
        check_numbers(self)


@dataclass(frozen=True)
class FusionSettings:
    """Noise model, gates and output of the fusion filter, one group per concern.

    Attributes
    ----------
    gyro : GyroSettings
    accel : AccelSettings
    mag : MagSettings
    uncertainty : UncertaintySettings
    interference : InterferenceSettings
        The detectors' thresholds.
    output_rate_hz : float
        Output rows per second (decimated gyro samples); 0 = one row per gyro sample.  The kernel reads
        its period ``out_dt_s`` (0: every sample).
    """

    gyro: GyroSettings = field(default_factory=GyroSettings)
    accel: AccelSettings = field(default_factory=AccelSettings)
    mag: MagSettings = field(default_factory=MagSettings)
    uncertainty: UncertaintySettings = field(default_factory=UncertaintySettings)
    interference: InterferenceSettings = field(default_factory=InterferenceSettings)
    output_rate_hz: float = kernel_field(50.0, "out_dt_s", _period)

    def __post_init__(self):
        check_numbers(self)
