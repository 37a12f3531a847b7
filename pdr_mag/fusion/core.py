""":class:`FusionCore`, the fusion filter's face: gyroscope + accelerometer + calibrated magnetometer →
orientation, heading, uncertainty.

An error-state (multiplicative) extended Kalman filter with seven error states — world-frame attitude
error ``δθ``, gyroscope bias error ``δb`` and a Gauss–Markov magnetometer heading error ``c`` — whose
recursion is compiled in :mod:`pdr_mag.fusion.kernel` (the model in :mod:`pdr_mag.fusion`, each sensor's
equations in its module).  In short:

* gyroscope: propagates ``q`` (device → ENU) with the bias-corrected rate (across gaps up to ``gyro.max_dt``,
  whose unknown rotation is added to ``P``); ``P`` grows with the gyro noise and the bias uncertainty,
  so ``heading_std_deg`` grows while the magnetometer is rejected;
* accelerometer: corrects tilt only, from the specific force averaged over ``accel.tau_s`` in the
  almost-inertial world frame (the mean linear acceleration of a walking, swinging or pocketed phone over
  the window is ≈ 0); its noise grows with ``||ā| − g|``, the horizontal spread and the clipped share, and
  the window's lag puts ``τ R̄`` on the bias in H; the average is gated beyond ``accel.gate``; a tilt farther
  off than a linearised update holds is turned onto a longer average instead (``tilt_reset_*``);
* magnetometer: corrects heading only, so a disturbed field can never corrupt the tilt; the tilt errors
  enter its H as consider states (Schmidt), so a tilt error (× tan I in the field's horizontal
  projection) is not taken for a heading error.  Gross disturbances are rejected by
  :mod:`pdr_mag.fusion.detectors` (flag with hold-off timers); moderate ones are down-weighted by the
  smallest disturbance that explains the deviations of strength, dip and gyro consistency; the
  innovation must pass a χ² gate; the caller may veto (``mag_allowed``);
* gyroscope bias: observable through the heading (magnetometer) and tilt (accelerometer) corrections as
  the device turns, plus a zero-rate update whenever the device is still (low gyro and accel variance for
  ``gyro.still_min_s``).  The initial bias standard deviation (``gyro.bias0_std``, 5.7 °/s per axis) covers
  the raw offsets of real phone gyroscopes (4–6 °/s);
* magnetometer heading error ``c``: the errors of a calibrated magnetometer indoors are correlated over
  seconds (residual calibration, the building's field); modelling them keeps the bias estimate from
  absorbing them;
* reported uncertainty: ``heading_std_deg = degrees(sqrt(max(P[δθ_z, δθ_z] + U[δθ_z, δθ_z], g Σ_b gᵀ)))``,
  the last the heading error the calibration's offset covariance causes at this orientation, which does not
  average out while the orientation holds (:func:`pdr_mag.fusion.kernel.calibration_floor`).  ``U`` is a
  consider covariance propagated and updated with the filter's own gains: the place's disturbance that the
  weighting leaves out (``uncertainty.env_k``, ``uncertainty.flag_k``: the unseen, heading-turning component
  of the deviations the detectors measure, and of the disturbances that raise their flag) — a field that
  passes the detectors in a steel-heavy place is still weighed as informative, and the std still says how far
  it may be turned.  Measured on the 42 tyrex walks (benchmarks/RESULTS.md): no walk with more than 10 % of
  its frames beyond 3σ; conservative on most frames (truth within 1σ in ≈ 95 %).

Interface
---------
``FusionCore(settings, field)``; ``process(kind, t, xyz, mag_allowed) -> EstimateBatch`` (checked input),
or, for a caller that made the input itself, ``advance(Span(...), snapshot_before) -> Advanced`` (the rows,
a :class:`Snapshot` before each given sample, for :meth:`FusionCore.restore`, and the columns the rows are
views of, for :meth:`FusionCore.suspect_from`; what the pipeline uses):

``kind`` int8 (N,)
    :data:`~pdr_mag.fusion.kinds.ACCEL` (m/s²), :data:`~pdr_mag.fusion.kinds.GYRO` (rad/s),
    :data:`~pdr_mag.fusion.kinds.MAG` (µT, **already calibrated**, device frame; a row of NaN = no usable
    calibration yet: the detectors and the heading update skip it).
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
at, or since, the previous row), ``cal_state`` (``"none"`` unless the caller of :meth:`FusionCore.advance`
names it), and
``diag`` with the :data:`pdr_mag.estimates.DIAG_KEYS` the core knows (all but ``coverage``) plus
``consistency_deg`` and ``heading_reset_deg`` (the jump of a heading re-acquisition at that row, deg; NaN
at the other rows).  Before the first usable magnetometer sample the heading is arbitrary (device +y to
north) with ``heading_std_deg = 180``.

North: with a field that has a declination, the output is referenced to true north (the magnetometer
residual is taken against the declination); with ``field=None`` to magnetic north.  The strength
reference of the detectors is, in this order: the value passed to :meth:`FusionCore.set_reference_strength`
(:meth:`FusionCore.use_calibration` passes the calibration radius, which is in the calibrated data's own
scale), else the
field's WMM strength, else none (the strength check is off).  The dip reference is the field's
inclination, else learnt from clean samples.

State: everything the filter carries from one sample to the next is one record of
:data:`pdr_mag.fusion.state.STATE` (named fields), so splitting a stream into any chunks gives identical
results; :meth:`get_state` / :meth:`set_state` round-trip it exactly as a JSON-serialisable dict of those
fields, and a :class:`Snapshot` is a copy of its bytes.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import scipy.linalg

from pdr_mag._records import settings_record
from pdr_mag.calibration.model import MagCalibration
from pdr_mag.calibration.online import deviating_fields
from pdr_mag.calibration.refit import horizontal_only, robust_spread
from pdr_mag.estimates import EstimateBatch, Event
from pdr_mag.field import EARTH_STRENGTH_RANGE_UT, EarthField
from pdr_mag.fusion import kernel
from pdr_mag.fusion.detectors import forget_learnt
from pdr_mag.fusion.kinds import GYRO, check_kinds
from pdr_mag.fusion.mag import offset_heading_var
from pdr_mag.fusion.quat import rotation_matrix
from pdr_mag.fusion.rows import DIAG_NAMES, Rows, columns, new_rows
from pdr_mag.fusion.settings import FusionSettings
from pdr_mag.fusion.state import BIAS, OFFSET, STATE, TH_Z, new_state, state_from_json, state_to_json

#: format of :meth:`FusionCore.get_state`
STATE_VERSION = 16
_NO_CUTS = np.empty(0, dtype=np.intp)
_NO_SNAPS = np.empty(0, dtype=STATE)


class Span(NamedTuple):
    """A merged, time-ordered chunk of samples as the filter takes it (the module docstring's input), made
    by the caller and not checked again: contiguous arrays of these dtypes.

    Attributes
    ----------
    kind : int8 (N,)
        :mod:`pdr_mag.fusion.kinds` codes.
    t : float64 (N,)
        Times, s, non-decreasing.
    xyz : float64 (N, 3)
        Samples; magnetometer rows calibrated (NaN: no usable calibration).
    mag_allowed : bool (N,)
        Per-row permission to use a magnetometer row for the heading.
    n_gyro : int
        At least the number of gyroscope rows (the most output rows the span can give).
    """

    kind: np.ndarray
    t: np.ndarray
    xyz: np.ndarray
    mag_allowed: np.ndarray
    n_gyro: int


@dataclass(frozen=True, eq=False)
class Snapshot:
    """The filter at one instant, for :meth:`FusionCore.restore` in the same process: a copy of its state's
    bytes and the reference strength in force (not serialisable: :meth:`FusionCore.get_state` is)."""

    raw: np.ndarray
    reference_strength: float | None


#: the fewest fields :meth:`FusionCore.fix_heading_from_history` takes a heading from
HISTORY_MIN = 10


class HistoryFix(NamedTuple):
    """A heading taken from past fields (:meth:`FusionCore.fix_heading_from_history`): when (s), from how
    many fields over how many seconds, the turn it made (deg, counter-clockwise seen from above: the world
    frame turned onto the fields' heading) and the std it left (deg)."""

    t: float
    fields: int
    span_s: float
    turn_deg: float
    std_deg: float


class Snapshots(Sequence):
    """The :class:`Snapshot` s an :meth:`FusionCore.advance` kept, in order (made on access)."""

    def __init__(self, states: np.ndarray, reference_strength: float | None):
        self._raw = states.view(np.uint8).reshape(len(states), -1) if len(states) else states
        self._ref = reference_strength

    def __len__(self) -> int:
        return len(self._raw)

    def __getitem__(self, i: int) -> Snapshot:
        return Snapshot(self._raw[i], self._ref)


class Advanced(NamedTuple):
    """What :meth:`FusionCore.advance` gives: the output rows, the snapshots asked for and the columns the
    rows are views of (:class:`~pdr_mag.fusion.rows.Rows`, with the variance's parts: for
    :meth:`FusionCore.suspect_from`)."""

    rows: EstimateBatch
    snapshots: Snapshots
    columns: Rows


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
        self._p = settings_record(self.settings)
        self._st = new_state()
        self._raw = self._st.view(np.uint8)  # its bytes: snapshots are plain copies of them
        self._ref_strength: float | None = None
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
        """Covariance of the error the calibration's offset makes in the calibrated field (3×3, device frame,
        µT²; None = exact): ``M Σ_b Mᵀ`` for an offset covariance ``Σ_b`` and the calibration's matrix M.  A
        coarse early calibration (σ of a few µT against a horizontal field of ~20 µT: ~10°) then weighs as
        little as it deserves.  With the offset states (``mag.offset_states``) it is the offset error's
        covariance when a calibration comes into force (:meth:`use_calibration`) and the first heading's
        from history; without them the heading error it causes, ``g Σ_b gᵀ`` at each sample's orientation,
        joins the stationary variance of the magnetometer error state c (from the next usable sample on), and
        the std says so at once (its floor, :func:`pdr_mag.fusion.kernel.calibration_floor`, is the new
        covariance at the latest usable sample's orientation: a flagged stretch may be long)."""
        if cov_uT2 is None:
            self._st["cal_cov"] = 0.0
            return
        c = np.asarray(cov_uT2, dtype=float)
        if c.shape != (3, 3) or not np.all(np.isfinite(c)):
            raise ValueError(f"cov_uT2: expected a finite 3×3 covariance in µT², got {cov_uT2!r}")
        self._st["cal_cov"] = 0.5 * (c + c.T)

    def set_suspected_shift(self, shift_uT) -> None:
        """An offset shift ``shift_uT`` (3, µT, device frame) that the calibration in force is suspected of —
        the stale test found it and has yet to confirm or drop it — or None (none): the reported std counts
        the heading turn it would make, ``g ΔΔᵀ gᵀ`` (:func:`pdr_mag.fusion.kernel.calibration_floor`), from
        the next row on; the filter's weights do not change."""
        if shift_uT is None:
            self._st["suspect_cov"] = 0.0
            return
        d = np.asarray(shift_uT, dtype=float)
        if d.shape != (3,) or not np.all(np.isfinite(d)):
            raise ValueError(f"shift_uT: expected 3 finite values in µT, got {shift_uT!r}")
        self._st["suspect_cov"] = np.outer(d, d)

    def note_calibration_change(self, matrix_old, offset_old, matrix_new, offset_new) -> None:
        """The calibration in force changed from ``m = M_old (r − b_old)`` to ``m = M_new (r − b_new)`` (r the
        raw field).  A field calibrated with the new one, ``m``, was ``m − dm`` with the old, where
        ``dm = D m + e``, ``D = I − M_old M_new⁻¹``, ``e = M_old (b_old − b_new)``.  The heading so far was
        taken from the old fields, so it carries the heading error ``g · dm`` that the change removes
        (``g = ∂ψ/∂m_d``): at the next magnetometer sample (a flagged one too) that variance joins the
        heading's, and a field the new calibration turns by tens of degrees is then within the gate rather
        than rejected until a re-acquisition.  Changes before that sample add up (to first order).  The
        detectors' local references were learnt from the old fields: a change that moves the calibrated field
        by more than the strength detector's tolerance (``|D|·F + |e| > max(tol_uT, tol_rel·F)``, F the
        reference strength, or the Earth's smallest, 22 µT, without one) leaves them wrong by more than they
        tolerate — every field of the new calibration would be flagged against them — so they are learnt
        anew; a smaller change (a refit's refinement) leaves them to follow the new fields at their own pace
        (relearning them at every change cost the tyrex walks more than it gained)."""
        arrays = []
        for name, v, shape in (("matrix_old", matrix_old, (3, 3)), ("offset_old", offset_old, (3,)),
                               ("matrix_new", matrix_new, (3, 3)), ("offset_new", offset_new, (3,))):
            a = np.asarray(v, dtype=float)
            if a.shape != shape or not np.isfinite(a).all():
                raise ValueError(f"{name}: expected finite values of shape {shape}, got {v!r}")
            arrays.append(a)
        m_old, b_old, m_new, b_new = arrays
        st = self._st[0]
        if (m_old == m_new).all():  # the shape kept (every gravity refit): D = I − M·M⁻¹ = 0 exactly
            d, d_norm = np.zeros((3, 3)), 0.0
        else:
            d = np.eye(3) - m_old @ np.linalg.inv(m_new)
            d_norm = np.linalg.norm(d, 2)
        e = m_old @ (b_old - b_new)
        st["cal_jump_d"] += d
        st["cal_jump_e"] += e
        f = float(st["f_ref"]) if np.isfinite(st["f_ref"]) else EARTH_STRENGTH_RANGE_UT[0]
        tol = self.settings.interference.strength
        if d_norm * f + np.linalg.norm(e) > max(tol.tol_uT, tol.tol_rel * f):
            forget_learnt(st["det"])

    def use_calibration(self, cal: MagCalibration | None, previous: MagCalibration | None = None) -> None:
        """The magnetometer calibration in force is now ``cal`` (the samples the filter takes are calibrated
        with it; None: none yet), ``previous`` the one before it (None: none).  Where a calibration meets
        the filter — a given one (the phone's own, a backend's store), an online fit, a recalibration:

        * a change is noted (:meth:`note_calibration_change`), so the heading taken from the old fields
          gets the variance of what the change removes;
        * its radius becomes the detectors' reference strength (:meth:`set_reference_strength`; a
          calibration without a radius leaves the reference as it was, as does a ``horizontal_only`` fit,
          whose radius traded against its undetermined offset along up:
          :func:`pdr_mag.calibration.refit.judge`);
        * its offset's error (:attr:`~pdr_mag.calibration.MagCalibration.offset_error_covariance`: the fit's
          covariance and, for an offset-only fit, the soft iron it cannot see) becomes a source of heading
          error (:meth:`set_calibration_covariance`), with the offset states the covariance of their error,
          anew (:meth:`_reset_offset_states`);
        * none after one (a prior refused): the heading it gave is forgotten (:meth:`forget_heading`).
        """
        changed = cal is not previous
        if changed and cal is not None and previous is not None:
            self.note_calibration_change(previous.matrix, previous.offset_array, cal.matrix, cal.offset_array)
        if cal is None and previous is not None:
            self.forget_heading()
        if cal is not None and np.isfinite(cal.field_uT) and cal.field_uT > 0 and not horizontal_only(cal):
            self.set_reference_strength(float(cal.field_uT))
        cov = None if cal is None else cal.offset_error_covariance
        if cov is not None:
            m = cal.matrix
            cov = m @ cov @ m.T  # the offset's error as it moves the calibrated field
        self.set_calibration_covariance(cov)
        if changed and self.settings.mag.offset_states:
            self._reset_offset_states()

    def _reset_offset_states(self) -> None:
        """A new calibration in force: the offset error found under the old one is dropped — the field the
        filter takes moves by it, a change of the calibrated field that :meth:`note_calibration_change`
        counts with the calibrations' own — and the offset error's covariance is the new calibration's,
        uncorrelated with the rest (a refit's offset rests on the same samples as the heading, but its
        errors are the fit's, not the filter's)."""
        st = self._st[0]
        st["cal_jump_e"] += st["offset"]
        st["offset"] = 0.0
        o = slice(OFFSET, OFFSET + 3)
        for m in (st["P"], st["U"]):
            m[o, :] = 0.0
            m[:, o] = 0.0
        if st["init"] >= 1:
            st["P"][o, o] = st["cal_cov"]

    def seed_flag_share(self, t, field, up) -> float | None:
        """The share of flagged samples (the consider part's weight of the detectors' tolerance,
        :func:`pdr_mag.fusion.gyro.unmodelled_var`) from the fields the filter had no calibration for: the
        recent ones a first calibration now calibrates — times ``t`` (s), fields (N × 3, µT) and up vectors
        (N × 3), device frame (:meth:`pdr_mag.calibration.OnlineCalibrator.gyro_heading_fields`).

        The detectors judge calibrated fields only, so a filter started without a calibration has seen none
        when its first comes: its first heading was weighed as if the place were clean, and next to steel it
        could be 120° off at σ 10° (a tyrex walk restarted 30 s in).  Each field is flagged here as the
        detectors' reference bands would (strength beyond ``max(tol_uT, tol_rel F_ref)`` of the reference
        ``F_ref``, dip beyond ``tol_deg`` of the reference dip where one is known: the calibrator's
        :func:`~pdr_mag.calibration.online.deviating_fields` with those bands), the share weighted as
        the span's worth of ``mag.env_tau_s``; the next samples carry it on.  Only for a filter whose
        detectors have seen no field; returns the share set, or None."""
        st = self._st[0]
        t = np.asarray(t, dtype=float).reshape(-1)
        f = np.asarray(field, dtype=float).reshape(-1, 3)
        u = np.asarray(up, dtype=float).reshape(-1, 3)
        ok = np.isfinite(t) & np.all(np.isfinite(f), axis=1) & np.all(np.isfinite(u), axis=1)
        t, f, u = t[ok], f[ok], u[ok]
        f_ref, dip_ref = float(st["f_ref"]), float(st["dip_ref"])
        if np.isfinite(st["t_flag"]) or not len(t) or not f_ref > 0.0:
            return None
        det = self.settings.interference
        tol_f = max(det.strength.tol_uT, det.strength.tol_rel * f_ref)
        tol_dip = det.dip.tol_deg if np.isfinite(dip_ref) else 0.0
        flagged = deviating_fields(f, u, f_ref, tol_f, dip_ref if np.isfinite(dip_ref) else None, tol_dip)
        share = float(np.mean(flagged))
        st["flag_share"] = share
        st["flag_w"] = -np.expm1(-(t.max() - t.min()) / self.settings.mag.env_tau_s)
        st["t_flag"] = t.max()
        st["flag_d2"] = tol_f**2 + (f_ref * np.radians(tol_dip)) ** 2
        kernel.refresh_unmodelled(self._st, self._p)
        return share

    def fix_heading_from_history(self, t, azimuth, gradient=None, field=None) -> HistoryFix | None:
        """The first heading of a filter that has none (no magnetometer update since the start, or since
        :meth:`forget_heading`), from the fields of the calibration just found: ``azimuth`` (rad) of each
        field at time ``t`` (s) in the filter's frame, which the gyroscope alone has carried, its gradient
        with respect to the calibrated field (N × 3, rad/µT; None: the calibration counted exact) and the
        calibrated field itself (N × 3, µT, device frame; None: unknown) — the pipeline gives the first fit's
        own recent samples (:meth:`pdr_mag.calibration.OnlineCalibrator.gyro_heading_azimuths`).  The
        latest field and its gradient are then the latest usable sample's, which a calibration change before
        the next usable one is judged by (:mod:`pdr_mag.fusion.mag`).

        The Earth's field keeps one azimuth ``a`` in that frame, so each ``α_k = a + ε_k``, the errors
        correlated through four causes, each with the filter's own model of it (the covariance ``Σ``):
        white noise ``σ_h²`` (``mag.noise_deg``); the field's own error c, an Ornstein–Uhlenbeck process
        ``σ_c² e^(−|t_k − t_l| / τ_c)`` (``mag.error_std_deg``, ``mag.error_tau_s``; c's decorrelation by
        turning, ``mag.error_turn_deg``, left out: the fields count as more alike than the filter counts
        them, the safe side); the frame's drift since the sample, ``(t_now − t_k) ḃ`` with ``ḃ`` the gyro
        bias about up, of the filter's variance ``σ_ḃ²``; and the calibration's offset error,
        ``g_k Σ_b g_lᵀ`` (its covariance in force; with the offset states the heading's error is then
        correlated with theirs through the fields' weighted mean gradient ``ḡ``, ``P[δθ_z, δo] = −Σ_b ḡ``).
        ``a`` is the generalised least-squares mean, ``â = 1ᵀΣ⁻¹α / 1ᵀΣ⁻¹1``, of variance ``1 / 1ᵀΣ⁻¹1`` —
        scaled up where the fields scatter more than the model says (a field that turned, a calibration
        worse than its covariance), by the larger of the residuals' ``χ² / (N − 1)`` and their robust
        spread's square over one field's ``σ_h² + σ_c²``.  Taken from :data:`HISTORY_MIN` fields or more
        spanning two of c's correlation times or more; a first fix from the next field would take that one
        field's error — or, when it is disturbed, only a guess — and the next clean field now updates the
        heading instead, the two weighed by their variances.
        Returns the :class:`HistoryFix` made, or None when the heading was not set."""
        st = self._st[0]
        if st["init"] != 1:
            return None
        t = np.asarray(t, dtype=float).reshape(-1)
        a = np.asarray(azimuth, dtype=float).reshape(-1)
        g = np.zeros((len(t), 3)) if gradient is None else np.asarray(gradient, dtype=float).reshape(-1, 3)
        f = np.full((len(t), 3), np.nan) if field is None else np.asarray(field, dtype=float).reshape(-1, 3)
        ok = np.isfinite(t) & np.isfinite(a) & np.all(np.isfinite(g), axis=1)
        t, a, g, f = t[ok], a[ok], g[ok], f[ok]
        m = self.settings.mag
        tau = m.error_tau_s
        t_now = float(max(st["t_gyro"], st["t_acc"]))
        if len(t) < HISTORY_MIN or not np.isfinite(t_now) or t.max() - t.min() < 2.0 * tau:
            return None
        white, corr = np.radians(m.noise_deg) ** 2, np.radians(m.error_std_deg) ** 2
        R = np.empty((3, 3))
        rotation_matrix(st["q"], R)
        up = R[2]  # the world's up in device coordinates
        drift = t_now - t
        cov = white * np.eye(len(t)) + corr * np.exp(-np.abs(t[:, None] - t[None, :]) / tau)
        cov += float(up @ st["P"][BIAS : BIAS + 3, BIAS : BIAS + 3] @ up) * np.outer(drift, drift)
        cov += g @ st["cal_cov"] @ g.T
        centre = float(np.angle(np.mean(np.exp(1j * a))))
        e = np.angle(np.exp(1j * (a - centre)))
        factor = scipy.linalg.cho_factor(cov)
        w = scipy.linalg.cho_solve(factor, np.ones(len(t)))
        var = 1.0 / w.sum()
        mean = var * float(w @ e)
        res = e - mean
        spread = robust_spread(e)
        chi2 = float(res @ scipy.linalg.cho_solve(factor, res))
        var *= max(1.0, chi2 / (len(t) - 1), spread**2 / (white + corr))
        latest = int(np.argmax(t))
        r = float(np.angle(np.exp(1j * (centre + mean - st["declination"]))))
        st["cal_g"] = g[latest]
        st["cal_m"] = f[latest]
        if not m.offset_states:  # c's stationary variance reads it (mag._calibration_variance)
            st["cal_var"] = offset_heading_var(g[latest], st["cal_cov"])
        span = float(t_now - t.min())
        kernel.fix_from_history(self._st, self._p, r, var, span, t_now)
        if m.offset_states:  # the fields' mean azimuth errs by ḡ·o (ḡ their weighted mean gradient)
            g_bar = (w @ g) / w.sum()
            o = slice(OFFSET, OFFSET + 3)
            c = -st["P"][o, o] @ g_bar
            st["P"][TH_Z, o] = c
            st["P"][o, TH_Z] = c
        std = float(np.degrees(np.sqrt(min(var, np.pi**2))))
        return HistoryFix(t_now, len(t), span, float(np.degrees(r)), std)

    def forget_heading(self) -> None:
        """The heading so far came from a calibration found wrong and withdrawn (a prior refused): it is
        unknown again (``heading_std_deg`` 180°, its covariance with the rest dropped), the detectors learn
        their local references anew, and the next usable magnetometer sample fixes it as the first did."""
        st = self._st[0]
        if st["init"] < 2:
            return
        st["init"] = 1
        for m in (st["P"], st["U"]):
            m[TH_Z, :] = 0.0
            m[:, TH_Z] = 0.0
        st["P"][TH_Z, TH_Z] = np.pi**2
        forget_learnt(st["det"])

    def set_gyro_prior(self, bias, std: float) -> None:
        """What is known of the gyroscope bias before the first sample: ``bias`` (3, rad/s, device frame)
        with ``std`` (rad/s per axis) — the phone's own drift estimate, a device store's
        (:mod:`pdr_mag.calibration.prior`) — instead of a zero bias with ``gyro.bias0_std``.  Only before the
        filter has started (``ValueError`` after)."""
        b = np.asarray(bias, dtype=float)
        if b.shape != (3,) or not np.all(np.isfinite(b)):
            raise ValueError(f"bias: expected 3 finite values in rad/s, got {bias!r}")
        if not (np.isfinite(std) and std > 0):
            raise ValueError(f"std: expected a positive number of rad/s, got {std!r}")
        if self._st["init"][0] != 0:
            raise ValueError("gyro prior: the filter has already started")
        self._st["b"] = b
        self._st["bias0_var"] = float(std) ** 2

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
    def process(self, kind, t, xyz, mag_allowed=None) -> EstimateBatch:
        """Run a merged, time-ordered chunk through the filter (the module docstring's input, checked);
        returns its output rows."""
        kind = np.ascontiguousarray(kind, dtype=np.int8)
        t = np.ascontiguousarray(t, dtype=np.float64)
        xyz = np.ascontiguousarray(xyz, dtype=np.float64)
        n = len(t)
        if kind.shape != (n,) or xyz.shape != (n, 3):
            raise ValueError(
                f"kind, t, xyz: expected shapes (N,), (N,), (N, 3); got {kind.shape}, {t.shape}, {xyz.shape}"
            )
        check_kinds(kind)
        if mag_allowed is None:
            allowed = np.ones(n, dtype=np.bool_)
        else:
            allowed = np.ascontiguousarray(mag_allowed, dtype=np.bool_)
            if allowed.shape != (n,):
                raise ValueError(f"mag_allowed: expected shape ({n},), got {allowed.shape}")
        return self.advance(Span(kind, t, xyz, allowed, int(np.count_nonzero(kind == GYRO)))).rows

    def advance(self, span: Span, snapshot_before=None, cal_state: str = "none") -> Advanced:
        """Run ``span`` through the filter; keep a :class:`Snapshot` before each sample index of
        ``snapshot_before`` (increasing, intp; the rows do not depend on where the input is cut).

        The rows' ``cal_state`` is ``cal_state``: the state of the calibration the span's magnetometer
        samples were calibrated with, which the caller knows (the pipeline: its online calibrator's)."""
        cuts = _NO_CUTS if snapshot_before is None else snapshot_before
        out = new_rows(span.n_gyro)
        snaps = np.empty(len(cuts), dtype=STATE) if len(cuts) else _NO_SNAPS
        # the filter, a copy of its state before each cut, the quaternion sign and the heading's arctan2
        # arguments in one compiled call
        k = kernel.run_cut(span, self._st, self._p, cuts, snaps, out)
        col = columns(out, k)
        heading = np.mod(np.degrees(np.arctan2(col["h_y"], col["h_x"])), 360.0)
        rows = EstimateBatch(
            t=col["t"],
            q_wd=col["q"],
            heading_deg=heading,
            heading_std_deg=col["heading_std_deg"],
            mag_used=col["mag_used"],
            interference=col["interference"],
            cal_state=np.full(k, cal_state, dtype="<U13"),
            diag={name: col[name] for name in DIAG_NAMES},
        )
        return Advanced(rows, Snapshots(snaps, self._ref_strength), out)

    def suspect_from(self, advanced: Advanced, first: int, shift_uT) -> None:
        """:meth:`set_suspected_shift` as if it had been set before row ``first`` of ``advanced`` (the latest
        :meth:`advance`'s): that row's and the later rows' ``heading_std_deg`` count the new shift (in place),
        and the state goes on with it.  The suspected shift is in the std only, so these are the rows a run
        from a snapshot before that row with the shift set would give, without running the filter again."""
        self.set_suspected_shift(shift_uT)
        kernel.rewrite_std(self._st, advanced.columns, first, len(advanced.rows))

    # ------------------------------------------------------------------ state
    @property
    def bias(self) -> np.ndarray:
        """Current gyroscope bias estimate, rad/s (device frame)."""
        return self._st["b"][0].copy()

    def offset_error(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The calibration's offset error the filter has found, in the calibrated field (µT, device frame:
        the field it takes is the calibrated one less it), and its covariance (µT²); None without the offset
        states or before the filter has started."""
        st = self._st[0]
        if not self.settings.mag.offset_states or st["init"] == 0:
            return None
        o = slice(OFFSET, OFFSET + 3)
        return st["offset"].copy(), st["P"][o, o].copy()

    def gyro_bias(self) -> tuple[np.ndarray, np.ndarray]:
        """The gyroscope bias estimate (rad/s, device frame) and its variance per axis, (rad/s)² — NaN before
        the filter has started (no accelerometer sample yet)."""
        st = self._st[0]
        if st["init"] == 0:
            return np.full(3, np.nan), np.full(3, np.nan)
        return st["b"].copy(), np.diag(st["P"])[BIAS : BIAS + 3].copy()

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

    def snapshot(self) -> Snapshot:
        """The filter as it is now, for :meth:`restore` (a copy of the state's bytes)."""
        return Snapshot(self._raw.copy(), self._ref_strength)

    def restore(self, snap: Snapshot) -> None:
        """Put back a :class:`Snapshot` (as :meth:`set_state` does for a :meth:`get_state` dict: the
        reference field of this object wins)."""
        self._raw[:] = snap.raw
        self._ref_strength = snap.reference_strength
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
