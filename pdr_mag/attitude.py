"""Attitude fusion: gyroscope + accelerometer + calibrated magnetometer → orientation, heading, uncertainty.

An error-state (multiplicative) extended Kalman filter with seven error states — world-frame attitude
error ``δθ``, gyroscope bias error ``δb`` and a Gauss–Markov magnetometer heading error ``c`` — whose
recursion is compiled in :mod:`pdr_mag.fusion` (the model there, each sensor's equations in its module).
In short:

* gyroscope: propagates ``q`` (device → ENU) with the bias-corrected rate (across gaps up to ``max_dt``,
  whose unknown rotation is added to ``P``); ``P`` grows with the gyro noise and the bias uncertainty,
  so ``heading_std_deg`` grows while the magnetometer is rejected;
* accelerometer: corrects tilt only, from the specific force averaged over ``acc_tau_s`` in the
  almost-inertial world frame (the mean linear acceleration of a walking, swinging or pocketed phone over
  the window is ≈ 0); its noise grows with ``||ā| − g|``, the horizontal spread and the clipped share, and
  the window's lag puts ``τ R̄`` on the bias in H; the average is gated beyond ``acc_gate``; a tilt farther
  off than a linearised update holds is turned onto a longer average instead (``tilt_reset_*``);
* magnetometer: corrects heading only, so a disturbed field can never corrupt the tilt; the tilt errors
  enter its H as consider states (Schmidt), so a tilt error (× tan I in the field's horizontal
  projection) is not taken for a heading error.  Gross disturbances are rejected by
  :mod:`pdr_mag.interference` (flag with hold-off timers); moderate ones are down-weighted by the
  smallest disturbance that explains the deviations of strength, dip and gyro consistency; the
  innovation must pass a χ² gate; the caller may veto (``mag_allowed``);
* gyroscope bias: observable through the heading (magnetometer) and tilt (accelerometer) corrections as
  the device turns, plus a zero-rate update whenever the device is still (low gyro and accel variance for
  ``still_min_s``).  The initial bias standard deviation (``bias0_std``, 5.7 °/s per axis) covers the raw
  offsets of real phone gyroscopes (4–6 °/s);
* magnetometer heading error ``c``: the errors of a calibrated magnetometer indoors are correlated over
  seconds (residual calibration, the building's field); modelling them keeps the bias estimate from
  absorbing them;
* reported uncertainty: ``heading_std_deg = degrees(sqrt(P[δθ_z, δθ_z] + U[δθ_z, δθ_z]))``.  ``U`` is a
  consider covariance propagated and updated with the filter's own gains: the place's disturbance that the
  weighting leaves out (``std_env_k``, ``std_flag_k``: the unseen, heading-turning component of the
  deviations the detectors measure, and of the disturbances that raise their flag) — a field that passes
  the detectors in a steel-heavy place is still weighed as informative, and the std still says how far it
  may be turned.  Measured on the 42 tyrex walks (benchmarks/RESULTS.md): no walk with more than 10 % of
  its frames beyond 3σ; conservative on most frames (truth within 1σ in ≈ 95 %).

Interface for :class:`pdr_mag.pipeline.HeadingPipeline`
-------------------------------------------------------
``FusionCore(settings, field)``; ``process(kind, t, xyz, mag_allowed) -> EstimateBatch``:

``kind`` int8 (N,)
    0 accelerometer (m/s²), 1 gyroscope (rad/s), 2 magnetometer (µT, **already calibrated**, device frame;
    a row of NaN = no usable calibration yet: the detectors and the heading update skip it).
``t`` float64 (N,)
    Merged, time-ordered (non-decreasing) times, s.
``xyz`` float64 (N, 3).
``mag_allowed`` bool (N,) or None
    Per-row permission to use a magnetometer row for the heading (the pipeline's recalibration state
    machine); ignored for other kinds.  The detectors run on every finite magnetometer row regardless.

Output: one row per gyroscope sample, decimated to ``settings.output_rate_hz`` on a grid anchored at the
first gyroscope sample after the tilt has been initialised (a row at the first gyro sample at or after
each grid time; ``output_rate_hz = 0`` gives every gyro sample).  No rows before the first accelerometer
sample (the tilt is unknown).  Columns: ``t`` (gyro time), ``q_wd``, ``heading_deg``, ``heading_std_deg``,
``mag_used`` (the magnetometer corrected the heading since the previous row), ``interference`` (flag up
at, or since, the previous row), ``cal_state`` (placeholder ``"none"``; the pipeline overwrites it), and
``diag`` with the :data:`pdr_mag.estimates.DIAG_KEYS` the core knows (all but ``coverage``) plus
``consistency_deg`` and ``heading_reset_deg`` (the jump of a heading re-acquisition at that row, deg; NaN
at the other rows).  Before the first usable magnetometer sample the heading is arbitrary (device +y to
north) with ``heading_std_deg = 180``.

North: with a field that has a declination, the output is referenced to true north (the magnetometer
residual is taken against the declination); with ``field=None`` to magnetic north.  The strength
reference of the detectors is, in this order: the value passed to :meth:`FusionCore.set_reference_strength`
(the pipeline passes its calibration radius, which is in the calibrated data's own scale), else the
field's WMM strength, else none (the strength check is off).  The dip reference is the field's
inclination, else learnt from clean samples.

State: everything the filter carries from one sample to the next is one record of
:data:`pdr_mag.fusion.state.STATE` (named fields), so splitting a stream into any chunks gives identical
results; :meth:`get_state` / :meth:`set_state` round-trip it exactly as a JSON-serialisable dict of those
fields.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np

from pdr_mag.estimates import EstimateBatch, Event
from pdr_mag.field import EarthField
from pdr_mag.fusion import kernel
from pdr_mag.fusion.state import (
    DIAG_NAMES,
    FLAG_COLS,
    FLOAT_COLS,
    PARAMS,
    STATE,
    new_rows,
    new_state,
    state_from_json,
    state_to_json,
)
from pdr_mag.interference import InterferenceSettings

#: format of :meth:`FusionCore.get_state`
STATE_VERSION = 6
_NO_CUTS = np.empty(0, dtype=np.intp)
_NO_SNAPS = np.empty(0, dtype=STATE)


@dataclass(frozen=True)
class FusionSettings:
    """Noise model and gates of the fusion filter.

    Attributes
    ----------
    gyro_noise : float
        Gyroscope angle random walk, rad/s/√Hz (phones: 0.003–0.01).
    bias_rw : float
        Gyroscope bias random walk, rad/s/√s.
    bias0_std : float
        Initial bias standard deviation per axis, rad/s.  0.1 (5.7 °/s per axis, √3 · 5.7 ≈ 10 °/s for the
        norm) covers the raw offsets of real phones (4–6 °/s, on one axis: PEERS.md) at about 1σ; a wider
        prior lets the first seconds of a disturbed, not yet flagged field teach the filter offsets no
        phone has.
    tilt0_std : float
        Initial tilt standard deviation, rad.
    acc_tau_s : float
        Time constant of the average of the specific force in the (almost inertial) world frame, s.  The
        tilt is corrected from that average (the mean linear acceleration of a walking or swinging hand
        over the window is Δv/τ ≈ 0, whereas single samples of a swinging arm point along the arm).  All
        samples are averaged; ``acc_gate`` applies to the average.  0 = correct from single samples
        (``acc_noise``, ``acc_corr_s``, ``acc_gyro``).
    acc_interval_s : float
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
    acc_avg_noise : float
        Noise of the averaged direction, per update (≈ rad); plus ``acc_dyn · ||ā| − g| / g``.
    acc_noise : float
        Base noise of the normalised accelerometer direction, per sample (dimensionless ≈ rad).
    acc_corr_s : float
        Correlation time of the linear acceleration, s: the per-sample noise grows by
        ``var(a) / g² · acc_corr_s / Δt`` with ``var(a)`` the running variance of the accelerometer
        (time constant ``still_tau_s``) and Δt the accelerometer period — the same information per second
        whatever the sample rate.
    turn_speed : float
        Walking speed assumed for the centripetal acceleration ``v · ω_up`` of a turn, m/s (0 = off: on
        the real walks it costs more than it gains, as turns are frequent and tilt then drifts): adds
        ``(v ω_up / g)² · turn_corr_s / Δt`` to the accelerometer noise (ω_up the turn rate about up).
    turn_corr_s : float
        Correlation time of that acceleration (the length of a turn), s.
    acc_dyn : float
        Noise added per unit of ``||a| − g| / g``.
    acc_spread_k : float
        Dynamics term of the averaged update's noise: the direction of ``ā_w`` is off by about
        ``acc_spread_k · s`` rad per horizontal axis, ``s`` the RMS horizontal spread of the world-frame
        specific force about its average, over g.  0.19 is the slope measured with motion-capture attitude
        on 42 walks of three phones and eight ways of carrying them (texting: s ≈ 0.08, 1–2°; running in
        the hand: s ≈ 1, 15°).  Successive updates ``acc_interval_s`` apart share the window τ, so this
        variance counts ``τ / acc_interval_s`` times per update: the information per second is that of one
        independent direction per window.
    acc_range : float
        Full scale of the accelerometer, m/s² per axis (0: found in the data).  A sample with an axis at the
        range is clipped: its true value lies beyond, by an unknown amount.  Found in the data, the range is
        the largest |a_i| seen once at least ``acc_clip_min_hits`` samples came within ``acc_clip_band`` of
        it and it is above 1.5 g (phone ranges are 2, 4, 8 or 16 g): a sensor that clips piles its samples
        up at the range (exactly, or spread over a few per cent by the phone's own axis calibration, as on
        the iPhone 4S), one that does not reaches its largest value once.
    acc_clip_band : float
        Samples within this fraction of the range count as clipped.
    acc_clip_min_hits : float
        Samples near the largest value that make it a range.
    acc_clip_k : float
        Clipped samples stay in the average ``ā_w`` — dropping them would drop the peaks of every step and
        tilt it far more (by 36° mean, 86° p95 on a real running walk) — but their missing excess, of the
        order of a g each, is unknown: the direction of ``ā_w`` may be off by about ``share · excess / g``,
        so the averaged update's noise grows by ``(acc_clip_k · share)²`` rad² (``acc_clip_k`` = 1: an
        excess of one g), ``share`` the weight of clipped samples in the window,
        counted ``τ / acc_interval_s`` times like the spread.  Single-sample updates (``acc_tau_s = 0``) skip
        clipped samples.
    acc_gyro : float
        Noise added per rad/s of bias-corrected angular rate (centripetal / tangential acceleration).
    acc_gate : float
        Accelerometer samples with ``||a| − g| > acc_gate · g`` are not used.
    mag_noise_deg : float
        Heading noise of one magnetometer update, deg (calibration residual, time correlation).
    mag_noise_uT : float
        Field noise, µT; adds ``mag_noise_uT / B_h`` rad to the heading noise (B_h horizontal strength).
    mag_time_unc_s : float
        Timestamp uncertainty of the magnetometer against the gyroscope, s: adds ``(|ω| τ F / B_h)²`` to
        the heading noise (a swinging phone turns at several rad/s).
    mag_dist_k : float
        Heading noise added per µT of the smallest disturbance that explains the deviation of strength
        and dip from their local references, divided by B_h (``k |d|_min / B_h`` rad).
    mag_cons_k : float
        Weight (0 = off, 1 = on) of the gyro-consistency angle in that smallest disturbance
        (``F · angle``).
    mag_tilt_k : float
        Weight (0 = off, 1 = on) of the tilt errors in the heading update: the projection of the field on
        the horizontal plane turns by ``−(m_x m_z δθ_x + m_y m_z δθ_y) / B_h²`` per tilt error; they enter
        H as consider states (in the gain and P, never corrected by the magnetometer).
    mag_error_std_deg : float
        Standard deviation of the slowly varying magnetometer heading error c (residual calibration
        error, local anomalies of the building), deg.  Modelled as a first-order Gauss–Markov state so
        the filter does not take correlated errors for gyro bias.
    mag_error_tau_s : float
        Correlation time of c, s.
    mag_env_k : float
        Where the recent field was disturbed, a field that looks clean may still be turned: steel that
        changes strength and dip by ``|d|`` nearby turns the horizontal field by up to ``|d| / B_h``
        elsewhere in the same place.  The stationary variance of c grows by ``(k · d_env / B_h)²``, with
        ``d_env²`` the exponentially weighted mean of ``d_min²`` (see ``mag_dist_k``) over
        ``mag_env_tau_s`` and ``B_h`` the reference horizontal strength (0 = off).
    mag_env_tau_s : float
        Memory of that environment level, s.
    mag_env_prior_uT : float
        The environment level before anything is known of it, µT: a walk starts where the field may already
        be turned (indoor fields deviate from the model by several µT), so ``d_env`` starts at no less than
        this and learns the place's own level over ``mag_env_tau_s``.
    std_env_k : float
        The environment's turning of the horizontal field as the *reported* ``heading_std_deg`` counts it:
        ``(std_env_k · d_seen / B_h)²`` in c's stationary variance, against the filter's
        ``(mag_env_k · d_env / B_h)²`` (``d_seen²`` the same mean of ``d_min²`` over the samples seen, without
        the filter's prior ``mag_env_prior_uT``: a start in a disturbed place counts what it saw).
        ``d_min`` sees the two components of a disturbance that change strength and dip; the third, which
        turns the horizontal field, is unseen, and a disturbance with no preferred direction has it as
        large as the mean of the two: ``d_min / √2`` (the default 0.71).  The filter weighs the field with
        the smaller ``mag_env_k`` (a field that passes the detectors in such a place is still informative);
        the difference is noise the weighting leaves out, carried through the same gains in a consider
        covariance ``U`` and added to the reported variance, ``P[δθ_z, δθ_z] + U[δθ_z, δθ_z]``.  0 leaves
        this part out.
    std_flag_k : float
        Weight of the flagged share in that consider part: where a share ``s_flag`` of the recent samples
        (exponentially weighted over ``mag_env_tau_s``, normalised by the weight seen, so a start counts
        what it saw) was flagged, the disturbances there are at least the detectors' tolerance
        ``d_tol² = tol_F² + (F tol_I)²``, and a field that passes between them is turned by such a
        disturbance's unseen component as often: ``std_flag_k · s_flag · d_tol² / 2`` is added to c's
        unmodelled variance (× 1/B_h²).  0 = off.  Together with ``std_env_k`` the truth lies beyond 3σ in
        at most 3.4 % of any tyrex walk's frames, at the price of a conservative std in disturbed buildings
        (median 18–20° there; the variants measured are in benchmarks/NOTES.md).
    mag_interval_s : float
        At most one magnetometer update per this interval, s (the errors are correlated in time; 0 = all).
    mag_gate : float
        χ² gate of the heading innovation, in standard deviations.
    reject_inflate_deg : float
        While an undisturbed-looking field keeps failing the gate, the heading variance grows by this
        squared per second (deg/√s), so a wrong heading (a disturbed start) is not kept forever.
    reacquire_s : float
        Re-acquisition: when a field that the detectors find clean has failed the gate for this long
        without a break, and the innovations agree among themselves (their circular spread, exponentially
        weighted over this time, is below ``reacquire_spread_deg``), the filter is what is lost: the
        heading is set to the magnetometer's (a ``heading_reset`` event carries the jump), uncorrelated
        from the bias, whose variance about up grows to the drift rate the jump implies.  0 = off.  A field
        turned by steel is local: 20 s of walking (~25 m) leaves the reach of a building's structure, so a
        field that still disagrees by the same angle is right and the heading wrong; a steel area passed in
        less time is waited out.
    reacquire_spread_deg : float
        Largest circular spread of those innovations, deg.
    still_gyro : float
        Still when the RMS deviation of the gyro from its running mean is below this, rad/s…
    still_acc : float
        …and that of the accelerometer below this, m/s²…
    still_tau_s : float
        …(running statistics with this time constant, s)…
    still_min_s : float
        …for at least this long, s; then zero-rate updates of the bias.
    zupt_noise : float
        Noise density of a zero-rate update, rad/s·√s (per-sample σ = zupt_noise / √Δt: 0.02 rad/s at
        100 Hz — gyro noise plus the tremor of a hand-held "still" phone).
    output_rate_hz : float
        Output rows per second (decimated gyro samples); 0 = one row per gyro sample.
    gravity : float
        m/s².
    max_dt : float
        Gyro gaps up to this long are integrated with the mean rate of their ends, and their attitude
        variance grows by ``var(ω) (Δt − 0.05 s)²`` (the rate meanwhile is unknown to the recent motion
        level); longer gaps are not integrated and add ``(|ω̄|² + var(ω)) Δt²``, s.
    interference : InterferenceSettings
        Detector thresholds.
    """

    gyro_noise: float = 0.005
    bias_rw: float = 2e-4
    bias0_std: float = 0.1
    tilt0_std: float = 0.2
    acc_tau_s: float = 0.5
    acc_interval_s: float = 0.05
    tilt_reset_k: float = 4.0
    tilt_reset_tau_s: float = 3.0
    tilt_reset_min_deg: float = 30.0
    acc_avg_noise: float = 0.2
    acc_noise: float = 0.05
    acc_corr_s: float = 0.1
    acc_dyn: float = 2.0
    acc_spread_k: float = 0.19
    acc_range: float = 0.0
    acc_clip_band: float = 0.05
    acc_clip_min_hits: float = 5.0
    acc_clip_k: float = 1.0
    turn_speed: float = 0.0
    turn_corr_s: float = 1.0
    acc_gyro: float = 0.5
    acc_gate: float = 0.5
    mag_noise_deg: float = 5.0
    mag_noise_uT: float = 1.0
    mag_dist_k: float = 2.0
    mag_time_unc_s: float = 0.01
    mag_cons_k: float = 1.0
    mag_tilt_k: float = 1.0
    mag_error_std_deg: float = 6.0
    mag_error_tau_s: float = 5.0
    mag_env_k: float = 0.3
    mag_env_tau_s: float = 30.0
    mag_env_prior_uT: float = 5.0
    std_env_k: float = 0.71
    std_flag_k: float = 1.0
    mag_interval_s: float = 0.2
    mag_gate: float = 4.0
    reject_inflate_deg: float = 3.0
    reacquire_s: float = 20.0
    reacquire_spread_deg: float = 15.0
    still_gyro: float = 0.03
    still_acc: float = 0.3
    still_tau_s: float = 0.3
    still_min_s: float = 0.5
    zupt_noise: float = 0.002
    output_rate_hz: float = 50.0
    gravity: float = 9.80665
    max_dt: float = 0.5
    interference: InterferenceSettings = field(default_factory=InterferenceSettings)

    def __post_init__(self):
        for f in fields(self):  # not asdict(): it deep-copies the nested settings at every construction
            if f.name == "interference":
                continue
            name, v = f.name, getattr(self, f.name)
            if not np.isfinite(v) or v < 0:
                raise ValueError(f"{name}: expected a non-negative finite number, got {v!r}")
        for name in (
            "gyro_noise",
            "bias0_std",
            "tilt0_std",
            "acc_noise",
            "mag_gate",
            "still_tau_s",
            "mag_env_tau_s",
            "gravity",
            "max_dt",
            "zupt_noise",
        ):
            if getattr(self, name) <= 0:
                raise ValueError(f"{name}: expected a positive number, got {getattr(self, name)!r}")

    def as_params(self) -> np.ndarray:
        """The settings in the compiled kernel's units: a one-element array of
        :data:`pdr_mag.fusion.state.PARAMS` (``*_deg`` → ``*_rad``, ``output_rate_hz`` → ``out_dt_s``)."""
        p = np.zeros(1, dtype=PARAMS)
        for f in fields(self):
            name, v = f.name, getattr(self, f.name)
            if name == "interference":
                continue
            if name == "output_rate_hz":
                p["out_dt_s"] = 1.0 / v if v > 0 else 0.0
            elif name.endswith("_deg"):
                p[name[:-4] + "_rad"] = np.radians(v)
            else:
                p[name] = v
        return p


class FusionCore:
    """The streaming fusion filter (see the module docstring for the interface).

    Parameters
    ----------
    settings : FusionSettings, optional
    field : EarthField or None
        Reference field (declination → true north, inclination → dip check, strength → strength check).
    """

    def __init__(self, settings: FusionSettings | None = None, field: EarthField | None = None):
        self.settings = settings or FusionSettings()
        self._p = self.settings.as_params()
        self._ip = self.settings.interference.as_params()
        self._st = new_state()
        self._raw = self._st.view(np.uint8)  # its bytes: snapshots are plain copies of them
        self._ref_strength: float | None = None
        self._snaps = (_NO_SNAPS, None)  # the states kept by the last run, and the reference strength
        self.field: EarthField | None = None
        self.set_field(field)

    # ------------------------------------------------------------------ configuration
    def set_field(self, field: EarthField | None) -> None:
        """Set (or clear) the reference Earth field."""
        self.field = field
        self._st["declination"] = np.radians(field.declination_deg) if field is not None else 0.0
        self._st["dip_ref"] = field.inclination_deg if field is not None else np.nan
        self._apply_strength()

    def set_reference_strength(self, strength_uT: float | None) -> None:
        """Strength the detectors compare with (e.g. the calibration radius), µT; None = the field's."""
        if strength_uT is not None and not (np.isfinite(strength_uT) and strength_uT > 0):
            raise ValueError(f"strength_uT: expected a positive finite value in µT, got {strength_uT!r}")
        self._ref_strength = None if strength_uT is None else float(strength_uT)
        self._apply_strength()

    def set_calibration_covariance(self, cov_uT2) -> None:
        """Covariance of the calibration's offset (3×3, device frame, µT²; None = exact).  The heading error
        it causes, ``g Σ_b gᵀ`` at each sample's orientation, joins the stationary variance of the
        magnetometer error state c: a coarse early calibration (σ of a few µT against a horizontal field of
        ~20 µT: ~10°) then weighs as little as it deserves, and the std says so."""
        if cov_uT2 is None:
            self._st["cal_cov"] = 0.0
            return
        c = np.asarray(cov_uT2, dtype=float)
        if c.shape != (3, 3) or not np.all(np.isfinite(c)):
            raise ValueError(f"cov_uT2: expected a finite 3×3 covariance in µT², got {cov_uT2!r}")
        self._st["cal_cov"] = 0.5 * (c + c.T)

    def note_calibration_change(self, matrix_old, offset_old, matrix_new, offset_new) -> None:
        """The calibration in force changed from ``m = M_old (r − b_old)`` to ``m = M_new (r − b_new)`` (r the
        raw field).  A field calibrated with the new one, ``m``, was ``m − dm`` with the old, where
        ``dm = D m + e``, ``D = I − M_old M_new⁻¹``, ``e = M_old (b_old − b_new)``.  The heading so far was
        taken from the old fields, so it carries the heading error ``g · dm`` that the change removes
        (``g = ∂ψ/∂m_d``): at the next usable magnetometer sample that variance joins the heading's, and a
        field the new calibration turns by tens of degrees is then within the gate rather than rejected until
        a re-acquisition.  Changes before that sample add up (to first order)."""
        arrays = []
        for name, v, shape in (("matrix_old", matrix_old, (3, 3)), ("offset_old", offset_old, (3,)),
                               ("matrix_new", matrix_new, (3, 3)), ("offset_new", offset_new, (3,))):
            a = np.asarray(v, dtype=float)
            if a.shape != shape or not np.all(np.isfinite(a)):
                raise ValueError(f"{name}: expected finite values of shape {shape}, got {v!r}")
            arrays.append(a)
        m_old, b_old, m_new, b_new = arrays
        st = self._st[0]
        st["cal_jump_d"] += np.eye(3) - m_old @ np.linalg.inv(m_new)
        st["cal_jump_e"] += m_old @ (b_old - b_new)

    def _apply_strength(self) -> None:
        if self._ref_strength is not None:
            self._st["f_ref"] = self._ref_strength
        elif self.field is not None:
            self._st["f_ref"] = self.field.strength
        else:
            self._st["f_ref"] = np.nan

    @property
    def north(self) -> str:
        """``"true"`` when a declination is applied, else ``"magnetic"``."""
        return "true" if self.field is not None else "magnetic"

    # ------------------------------------------------------------------ processing
    def process(self, kind, t, xyz, mag_allowed=None, snapshot_at=None) -> EstimateBatch:
        """Run a merged, time-ordered chunk through the filter; returns its output rows.

        ``snapshot_at``: increasing sample indices before each of which a :meth:`_snapshot` is kept in
        ``self.snapshots`` (same rows: the filter's output does not depend on how its input is cut).
        """
        kind = np.ascontiguousarray(kind, dtype=np.int8)
        t = np.ascontiguousarray(t, dtype=np.float64)
        xyz = np.ascontiguousarray(xyz, dtype=np.float64)
        n = len(t)
        if kind.shape != (n,) or xyz.shape != (n, 3):
            raise ValueError(
                f"kind, t, xyz: expected shapes (N,), (N,), (N, 3); got {kind.shape}, {t.shape}, {xyz.shape}"
            )
        if mag_allowed is None:
            allowed = np.ones(n, dtype=np.bool_)
        else:
            allowed = np.ascontiguousarray(mag_allowed, dtype=np.bool_)
            if allowed.shape != (n,):
                raise ValueError(f"mag_allowed: expected shape ({n},), got {allowed.shape}")
        m = int(np.count_nonzero(kind == 1))
        cuts = _NO_CUTS if snapshot_at is None else np.asarray(snapshot_at, dtype=np.intp)
        return self._run(kind, t, xyz, allowed, cuts, m)

    def _run(self, kind, t, xyz, allowed, cuts, m, cal_state: str = "none") -> EstimateBatch:
        """:meth:`process` on checked input: contiguous ``kind`` (int8), ``t``, ``xyz`` (float64),
        ``allowed`` (bool), ``cuts`` (intp, the ``snapshot_at``), ``m`` ≥ the number of gyro samples; the
        rows' ``cal_state`` is ``cal_state``."""
        floats, q, flags = new_rows(m)
        snaps = np.empty(len(cuts), dtype=STATE) if len(cuts) else _NO_SNAPS
        # the filter, a copy of its state before each cut, the quaternion sign and the heading's arctan2
        # arguments in one compiled call
        k = kernel.run_cut(kind, t, xyz, allowed, self._st, self._p, self._ip, cuts, snaps, floats, q, flags)
        self._snaps = (snaps, self._ref_strength)
        col = dict(zip(FLOAT_COLS, floats[:, :k], strict=True)) | dict(
            zip(FLAG_COLS, flags[:, :k], strict=True)
        )
        heading = np.arctan2(col["h_y"], col["h_x"])
        np.degrees(heading, out=heading)
        np.mod(heading, 360.0, out=heading)
        return EstimateBatch(
            t=col["t"],
            q_wd=q[:k],
            heading_deg=heading,
            heading_std_deg=col["heading_std_deg"],
            mag_used=col["mag_used"],
            interference=col["interference"],
            cal_state=np.full(k, cal_state, dtype="<U13"),
            diag={name: col[name] for name in DIAG_NAMES},
        )

    # ------------------------------------------------------------------ state
    @property
    def bias(self) -> np.ndarray:
        """Current gyroscope bias estimate, rad/s (device frame)."""
        return self._st["b"][0].copy()

    @property
    def interference_flag(self) -> bool:
        return bool(self._st["det"]["flag"][0])

    def get_state(self) -> dict:
        """JSON-serialisable state: the fields of :data:`pdr_mag.fusion.state.STATE` by name."""
        return {
            "version": STATE_VERSION,
            "state": state_to_json(self._st[0]),
            "reference_strength_uT": self._ref_strength,
        }

    @property
    def snapshots(self) -> list:
        """The :meth:`_snapshot` s kept by the last :meth:`process` (``snapshot_at``), in order."""
        snaps, ref = self._snaps
        return [(raw, ref) for raw in snaps.view(np.uint8).reshape(len(snaps), -1)] if len(snaps) else []

    def _snapshot(self) -> tuple:
        """Cheap in-process snapshot for :meth:`_restore` (a copy of the state's bytes; not serialisable)."""
        return self._raw.copy(), self._ref_strength

    def _restore(self, snap: tuple) -> None:
        """Put back a :meth:`_snapshot` (as :meth:`set_state` does for a :meth:`get_state` dict: the
        reference field of this object wins)."""
        raw, self._ref_strength = snap
        self._raw[:] = raw
        self.set_field(self.field)

    def set_state(self, state: dict) -> None:
        """Restore a state from :meth:`get_state` (the settings and field stay those of this object,
        except the strength reference, which is restored)."""
        if not isinstance(state, dict) or state.get("version") != STATE_VERSION:
            raise ValueError(f"state: expected a FusionCore state dict of version {STATE_VERSION}")
        self._st[:] = state_from_json(STATE, state.get("state"), "state['state']")
        self._ref_strength = state.get("reference_strength_uT")
        # the reference field of this object wins over the saved one
        self.set_field(self.field)


def heading_reset_events(batch: EstimateBatch) -> list[Event]:
    """The heading re-acquisitions in these rows (``diag["heading_reset_deg"]``): ``heading_reset`` events
    with ``jump_deg`` (the turn onto the magnetometer's heading, counter-clockwise seen from above) and the
    ``heading_std_deg`` it left."""
    jumps = batch.diag.get("heading_reset_deg") if batch.diag else None
    if jumps is None:
        return []
    out = []
    for i in np.flatnonzero(np.isfinite(jumps)):
        std = float(batch.heading_std_deg[i])
        data = {"jump_deg": round(float(jumps[i]), 3), "heading_std_deg": round(std, 3)}
        out.append(Event(float(batch.t[i]), "heading_reset", data))
    return out
