"""Online (streaming) hard-iron calibration, stale-calibration test and figure-8 recalibration ([Liu2018]).

:class:`OnlineCalibrator` is a state machine over the calibration in force::

    none ──accepted refit──► offset / ellipsoid ──offset moved──► recalibrating ──figure-8 refit──► offset / …
                                   ▲   │ accepted refit that improves it          │ provisional refits
                                   └───┘                                          └─(stay recalibrating)

It is fed magnetometer samples block by block, each with the device-frame up vector and the gyro rate at
that instant, and works with bounded memory:

* the compiled per-sample loop (:mod:`pdr_mag.calibration._online_kernel`) tracks rotation episodes,
  keeps a ring of recent samples, admits samples to the **diversity buffer**
  (:mod:`pdr_mag.calibration.diversity`) and keeps the schedule of refits and stale tests;
* a **refit** fits the buffer (the gravity-aided fit of :mod:`pdr_mag.calibration.gravity`, which works from
  yaw turns alone; [Liu2018]'s sphere fit and the core's full fit once the coverage allows) and judges the
  candidates (:mod:`pdr_mag.calibration.refit`).  A first calibration may be accepted under a looser
  offset σ than a later one; while it is that uncertain (:func:`pdr_mag.calibration.refit.provisional`) it
  does not judge which samples enter the buffer, and refits are judged as first ones, so a wrong first fit
  (a few samples, a start in motion) gives way to the next — as does a prior that knows less than a first
  fit would;
* at a rotation episode's end with an offset-only calibration in force, the full fit of the recent samples
  (the ring, every sample: a figure-8's stretched fields, which a soft iron the offset does not model keeps
  out of the buffer, :meth:`OnlineCalibrator._figure8_fit`) is a candidate too;
* the **stale-calibration test** (:mod:`pdr_mag.calibration.stale`) tells an offset that moved from a passing
  disturbance.  A shift found (a candidate) is suspected of the calibration in force until the test
  confirms or drops it (:attr:`OnlineCalibrator.suspected_shift`: the heading's std counts at once the turn
  the shift would make); found again ``stale_confirm_s`` later it requests a recalibration: the provisional
  offset ``b + M⁻¹δ`` is used at once (``cal_state = "recalibrating"``), the buffer is cleared, and the next
  rotation-rich episode (a figure-8) with enough coverage gives the new calibration (``recalibrated``) —
  or, without one, the first refit accepted ``recal_fallback_s`` after the request.

Its state is JSON-serialisable (:meth:`OnlineCalibrator.get_state` / :meth:`~OnlineCalibrator.set_state`).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from pdr_mag._json import state_float
from pdr_mag._records import settings_record
from pdr_mag.calibration import _online_kernel as K
from pdr_mag.calibration import diversity, refit, stale, turned
from pdr_mag.calibration.gravity import fit_model, gravity_aided_offset
from pdr_mag.calibration.model import MagCalibration
from pdr_mag.calibration.online_settings import OnlineSettings
from pdr_mag.calibration.prior import is_prior, offset_sigma, prior_source
from pdr_mag.calibration.sphere import fit_sphere
from pdr_mag.field import plausible_strength

__all__ = ["OnlineCalibrator", "OnlineSettings", "gravity_aided_offset"]

_EPISODE_EVENTS = {K.EPISODE_START: "rotation_episode_start", K.EPISODE_END: "rotation_episode_end"}

#: Fields of the compiled loop's state that belong to the open block, with the block-start copies of the
#: calibration and the buffer (``hint`` only speeds up the redundancy search), and the buffer's direction
#: counts (counted afresh from the buffer when not ``cover_ok``): they are not saved, and a restored
#: calibrator starts a new block at its next sample.
_BLOCK_FIELDS = ("in_block", "cal_changed", "n_buf0", "n_old0", "hint", "cover_ok", "cover")
_SAVED_FIELDS = tuple(name for name in K.STATE.names if name not in _BLOCK_FIELDS)


def deviating_fields(fields, up, strength: float, tol_uT: float, dip_deg: float | None = None,
                     dip_tol_deg: float = 0.0) -> np.ndarray:
    """Which calibrated fields (N × 3, µT, device frame, each with its up vector, N × 3) deviate from a
    reference field: a strength more than ``tol_uT`` from ``strength``, or, with a reference dip
    ``dip_deg``, a dip ``asin(−f·u / |f||u|)`` more than ``dip_tol_deg`` from it — the test the buffer's
    admission and the stale test apply with their own bands, here with the caller's (the fusion filter's
    detectors: :meth:`pdr_mag.fusion.FusionCore.seed_flag_share`).  Boolean array (N,)."""
    return K.deviating(np.ascontiguousarray(fields, dtype=float), np.ascontiguousarray(up, dtype=float),
                       float(strength), float(tol_uT), dip_deg is not None,
                       0.0 if dip_deg is None else float(dip_deg), float(dip_tol_deg))  # fmt: skip


class OnlineCalibrator:
    """The streaming calibration state machine (see the module docstring).

    Feed it magnetometer samples in time order with :meth:`update` (one block) or :meth:`update_blocks`;
    read :attr:`calibration` and :attr:`cal_state`; they return :class:`pdr_mag.estimates.Event`-ready
    ``(t, kind, data)`` tuples.

    Parameters
    ----------
    settings : OnlineSettings
    calibration : MagCalibration, optional
        A device calibration to start from (``cal_state`` ``offset`` or ``ellipsoid``).  A prior (the phone's
        own estimate, a device store's: ``extra["prior"]``, :mod:`.prior`) rather than a calibration the user
        gave is replaced by an online fit that improves on its covariance
        (:func:`pdr_mag.calibration.refit.replaces`), as an earlier fit is.
    strength, sin_dip : float, optional
        Earth field strength F (µT) and sin of the inclination from the WMM; None when unknown.

    Attributes
    ----------
    calibration : MagCalibration or None
        The calibration in force (None before the first accepted fit).
    cal_state : str
        ``none``, ``offset``, ``ellipsoid`` or ``recalibrating``.
    provided : bool
        The calibration in force is the one the user gave (gravity and sphere refits do not replace it).
    """

    def __init__(
        self,
        settings: OnlineSettings | None = None,
        calibration: MagCalibration | None = None,
        strength: float | None = None,
        sin_dip: float | None = None,
    ):
        s = self.settings = settings or OnlineSettings()
        self.strength_wmm = None if strength is None else float(strength)
        self.sin_dip_wmm = None if sin_dip is None else float(sin_dip)
        self.provided = calibration is not None and not is_prior(calibration)
        self._recal_t = np.nan  # when the recalibration was requested
        self._n_refits = 0
        self._last_reject_t = -np.inf  # last calibration_rejected event (at most one per 30 s)
        # since when the filter's heading is the gyroscope's alone (no calibration in force: the turned-field
        # test's frame); a calibration in force: not until it is refused
        self._gyro_heading_t = -np.inf if calibration is None else np.inf
        # the compiled loop's records (one-element structured arrays) and sample arrays
        self._params = settings_record(s)
        self._state = np.zeros(1, K.STATE)
        st = self._state[0]
        st["ring_last_t"] = -np.inf
        st["rate_t"] = np.nan
        st["next_refit_t"] = -np.inf
        st["next_stale_t"] = -np.inf
        st["fit_scale"] = 1.0
        st["episode_t1"] = np.nan
        self._cal = np.zeros(1, K.CAL)  # the calibration in force, as the loop reads it
        self._cal0 = np.zeros(1, K.CAL)  # … at the start of the open block
        self._buf = diversity.empty(s.buffer_size)
        self._buf0 = diversity.empty(s.buffer_size)  # the buffer at the start of the open block
        self._old0 = np.zeros(s.buffer_size, dtype=np.int64)
        self._ring = diversity.empty(int(s.stale_window_s * s.stale_rate_hz) + 1)  # recent samples
        # the same arrays as the compiled loop takes them (written in place from here on)
        self._loop = K.Loop(
            self._state, self._cal, self._cal0, self._params, self._buf, self._buf0, self._old0, self._ring
        )
        # the stale test's fits: F and sin I free, and (set by _use) the references in force with priors
        self._free_model = fit_model(None, None, s.sigma_strength_uT, s.sigma_tilt_deg)
        self._use(calibration, "none" if calibration is None else refit.state_of(calibration))

    # ------------------------------------------------------------------ reading
    @property
    def field_ref(self) -> float | None:
        """F, µT: the WMM strength, else the radius of the calibration in force (unless it is a
        ``horizontal_only`` fit, whose radius traded against its undetermined offset along up)."""
        if self.strength_wmm is not None:
            return self.strength_wmm
        cal = self.calibration
        if cal is not None and np.isfinite(cal.field_uT) and not refit.horizontal_only(cal):
            return float(cal.field_uT)
        return None

    @property
    def sin_dip_ref(self) -> float | None:
        """sin I: the WMM's, else the calibration's ``extra["sin_dip"]``."""
        if self.sin_dip_wmm is not None:
            return self.sin_dip_wmm
        if self.calibration is not None and not refit.horizontal_only(self.calibration):
            v = self.calibration.extra.get("sin_dip")
            if v is not None and np.isfinite(v):
                return float(v)
        return None

    @property
    def best_estimate(self) -> MagCalibration | None:
        """The device's calibration as this session's data say it best: the latest accepted refit that may
        stand for the calibration in force (:func:`pdr_mag.calibration.refit.may_stand_for`) but did not
        replace it — it said nothing the filter had to act on, a shift within 2 σ or a σ less than 20 %
        smaller (:func:`pdr_mag.calibration.refit.replaces`) — else the calibration in force.  The filter
        keeps its calibration against such a refit, as each change turns the heading; a device store keeps
        the refit, which rests on the buffer as the session left it — more samples, a longer time base, the
        building's field averaged over more of its places — where the calibration in force rests on the
        buffer of when it was taken (the first fits after a hard-iron jump: ten seconds of one corridor).
        None before any calibration, and during a recalibration (its provisional offset is not yet a
        calibration); a prior in force (the phone's, a store's) is returned as it is unless a refit of this
        session may stand for it."""
        if self.calibration is None or self.cal_state == "recalibrating":
            return None
        return self._latest_fit if self._latest_fit is not None else self.calibration

    @property
    def suspected_shift(self) -> np.ndarray | None:
        """The offset shift a stale test found and has yet to confirm or drop, in the raw field's frame
        (``M⁻¹δ``, µT, as a recalibration would move the offset), or None."""
        st = self._state[0]
        if not st["has_candidate"] or self.calibration is None:
            return None
        return np.linalg.solve(self.calibration.matrix, st["candidate_shift"])

    @property
    def suspect_key(self) -> float | None:
        """When the pending candidate was found (None: none): it tells one suspected shift from another."""
        st = self._state[0]
        return float(st["candidate_t"]) if st["has_candidate"] else None

    @property
    def episode(self) -> bool:
        """Whether a rotation-rich episode (figure-8) is on."""
        return bool(self._state[0]["episode"])

    @property
    def buffer(self) -> np.ndarray:
        """The diversity buffer's raw samples, (n, 3) µT (a copy)."""
        return self._buf["m"][: self._n_buf].copy()

    @property
    def _n_buf(self) -> int:
        return int(self._state[0]["n_buf"])

    def coverage(self) -> float:
        """Direction coverage of the buffer about the calibration's offset (the buffer mean without one)."""
        return float(K.coverage_now(self._loop))

    # ------------------------------------------------------------------ feeding
    def update(
        self,
        t: np.ndarray,
        mag: np.ndarray,
        up: np.ndarray,
        rate: np.ndarray,
        north: np.ndarray | None = None,
    ) -> list:
        """Take one block of raw magnetometer samples (time-ordered) with up vectors and gyro rates; return
        the events.  ``north`` (N, 3): the device-frame world y axis of the attitude the up vectors come
        from (the heading the gyroscope carries; None: unknown, and the turned-field test does not run).

        Every sample of the block is admitted to the buffer against the calibration and the buffer of the
        block's start.  Never raises on odd data: samples with NaN are skipped.
        """
        t = np.asarray(t, dtype=float).reshape(-1)
        ends = np.zeros(len(t), dtype=np.bool_)
        if len(t):
            ends[-1] = True
        events, _, _ = self.update_blocks(t, mag, up, rate, ends, north)
        return [e for _, e in events]

    def update_blocks(
        self,
        t: np.ndarray,
        mag: np.ndarray,
        up: np.ndarray,
        rate: np.ndarray,
        block_end: np.ndarray,
        north: np.ndarray | None = None,
    ) -> tuple[list, int, np.ndarray]:
        """:meth:`update` for whole blocks, ``block_end`` (N,) bool marking the last sample of each; stops at
        the end of the first block in which the calibration, or the shift suspected of it
        (:attr:`suspected_shift`), changed.

        Returns ``(events, n, coverage)``: the events as ``(row, (t, kind, data))`` with the row that raised
        them, the number of rows taken in, and the buffer's coverage at each block end taken in (NaN
        elsewhere).  Rows with a NaN time, field or up vector are skipped (a NaN rate counts as 0).
        """
        t = np.asarray(t, dtype=float).reshape(-1)
        mag = np.asarray(mag, dtype=float)
        up = np.asarray(up, dtype=float)
        rate = np.asarray(rate, dtype=float)
        block_end = np.asarray(block_end, dtype=np.bool_)
        n = len(t)
        north = np.full((n, 3), np.nan) if north is None else np.asarray(north, dtype=float)
        blocks = K.Blocks(t, mag, up, north, rate, block_end)
        # at most one episode event per sample
        found = K.Found(np.full(n, np.nan), np.empty(n, dtype=np.int64), np.empty(n, dtype=np.int64))
        events: list = []
        i, resumed = 0, False
        st = self._state[0]
        while True:
            suspected = self.suspected_shift
            code, j, n_ev = K.scan(blocks, i, resumed, self._loop, found)
            for k in range(n_ev):
                r = int(found.ev_index[k])
                events.append((r, (float(t[r]), _EPISODE_EVENTS[int(found.ev_kind[k])], {})))
            if suspected is not None and not st["has_candidate"]:  # the field no longer deviates
                t_drop = float(st["candidate_t"])
                r = min(int(np.searchsorted(t, t_drop)), n - 1)
                events.append((r, (t_drop, "suspicion_dropped", _shift_data(suspected))))
                events.sort(key=lambda e: e[0])  # among this scan's episode events, in time order
            if code == K.DONE:
                return events, n, found.coverage
            if code == K.BLOCK_END:  # the calibration or its suspected shift changed in the block ended at j
                return events, j + 1, found.coverage
            ti = float(t[j])
            decided: list = []
            if code == K.REFIT:
                self._refit(ti, decided)
                if K.stale_now(ti, self._loop) == K.STALE_TEST:
                    self._stale_test(ti, decided)
            else:
                self._stale_test(ti, decided)
            events += [(j, e) for e in decided]
            i, resumed = j, True

    # ------------------------------------------------------------------ transitions
    def renew_prior(self, cal: MagCalibration) -> bool:
        """A newer estimate from the source of the prior in force (the phone's OS changed its hard-iron
        estimate mid-recording: ``cal.extra["prior"]`` names the source): it becomes the calibration in
        force when that is still the prior from the same source — not an online fit that replaced it, nor a
        recalibration under way.  Returns whether it did."""
        source = prior_source(cal)
        if source is None or self.cal_state == "recalibrating" or prior_source(self.calibration) != source:
            return False
        self._use(cal, refit.state_of(cal))
        return True

    def _use(self, cal: MagCalibration | None, cal_state: str) -> None:
        """Put ``cal`` in force with state ``cal_state``, and its parameters where the compiled loop reads
        them (:data:`pdr_mag.calibration._online_kernel.CAL`); the next refit fits."""
        s = self.settings
        self.calibration = cal
        self.cal_state = cal_state
        self._latest_fit = None  # a later refit that may stand for cal (not in force: it said nothing new)
        f = self.field_ref
        sd = self.sin_dip_ref
        c = self._cal[0]
        # a prior is not yet the data's: every sample may enter the buffer, as before any calibration, so
        # that a wrong one is seen to be wrong (the refit's plausibility test) and a fit can replace it
        c["check"] = (cal is not None and f is not None and cal_state not in ("none", "recalibrating")
                      and not is_prior(cal) and not refit.provisional(cal, s))  # fmt: skip
        if cal is not None:
            c["matrix"] = cal.matrix
            c["offset"] = cal.offset_array
        c["strength"] = np.nan if f is None else f
        c["strength_tol"] = np.nan if f is None else s.add_tol_frac * f
        c["dip_check"] = sd is not None
        c["dip_deg"] = np.nan if sd is None else np.degrees(np.arcsin(sd))
        c["dip_tol_deg"] = s.add_dip_tol_deg
        c["sep2"] = separation(s, f, sd) ** 2
        c["has_offset"] = cal is not None
        c["stale_on"] = cal is not None and cal_state != "recalibrating"
        c["stale_ok"] = f is not None and sd is not None
        c["stale_tol"] = np.nan if f is None else s.stale_band_uT(f)
        c["refit_period"] = s.refit_period_s if cal is not None else 0.5 * s.refit_period_s
        self._stale_model = fit_model(
            f, sd, s.sigma_strength_uT, s.sigma_tilt_deg, s.prior_strength_std_uT, s.prior_dip_std_deg
        )
        st = self._state[0]
        st["coverage_stale"] = True  # the coverage is taken about the offset
        st["cover_ok"] = False
        st["fit_new"] = np.inf
        st["cal_changed"] = True

    def _refit(self, t: float, events: list) -> None:
        """A refit the schedule made due: fit the buffer, judge, take the best if it improves on the
        calibration in force (:func:`pdr_mag.calibration.refit.replaces`)."""
        n = self._n_buf
        if is_prior(self.calibration) and n >= self.settings.prior_min_samples:
            self._check_prior(t, n, events)
        full_fit_allowed = (
            bool(self._state[0]["episode_seen"]) or self.cal_state == "none" or is_prior(self.calibration)
        )
        judged = refit.candidates(
            self._buf["m"][:n], self._buf["u"][:n], self.calibration, full_fit_allowed, self.field_ref,
            self.sin_dip_ref, self.settings, times=self._buf["t"][:n],
        )  # fmt: skip
        # the refit that a rotation episode's end made due (at that very sample)
        if self._state[0]["episode_t1"] == t and self.cal_state == "offset":
            judged += self._figure8_fit(t)
        if self.calibration is None and self.field_ref is None:
            judged = [self._turned_field(c, n) for c in judged]
        chosen = refit.best(judged)
        if chosen is None:
            if judged and self.calibration is None and t - self._last_reject_t > 30.0:
                self._last_reject_t = t
                last = judged[-1]
                data = {"method": last.method, "reasons": list(last.reasons)}
                events.append((t, "calibration_rejected", data))
            return
        recalibrating = self.cal_state == "recalibrating"
        buf = self._buf["m"][:n]
        if not recalibrating and not refit.replaces(chosen, self.calibration, self.provided, buf):
            if refit.may_stand_for(chosen, self.calibration, self.provided, buf):
                self._latest_fit = refit.with_dip(chosen, buf, self._buf["u"][:n])
            return
        cal = refit.with_dip(chosen, buf, self._buf["u"][:n])
        if recalibrating:
            rich = cal.method != "gravity" and bool(self._state[0]["episode_seen"])
            waited = np.isfinite(self._recal_t) and t - self._recal_t > self.settings.recal_fallback_s
            if not (rich or waited):
                self._use(cal, "recalibrating")  # provisional: keep refining the offset
                return
            self._use(cal, refit.state_of(cal))
            self._recal_t = np.nan
            events.append((t, "recalibrated", {**refit.summary(cal), "figure8": bool(rich)}))
            return
        self._use(cal, refit.state_of(cal))
        self._n_refits += 1
        events.append((t, "calibration_accepted", refit.summary(cal)))

    def _turned_field(self, cal: MagCalibration, n: int) -> MagCalibration:
        """A first calibration without a reference field (no place known) refused when, about it, the
        buffer's field turned against the gyroscope (:mod:`pdr_mag.calibration.turned`: the azimuth's spread
        above ``turned.bound_deg`` at the fit's own dip).  Judged on the samples taken since the filter's
        heading has been the gyroscope's alone (``_gyro_heading_t``)."""
        if not cal.accepted:
            return cal
        b = self._buf[:n]
        mc = cal.apply(b["m"])
        k = b["t"] >= self._gyro_heading_t
        spread = turned.azimuth_spread_deg(mc[k], b["u"][k], b["n"][k], b["t"][k])
        bound = turned.bound_deg(self.settings.turned_field_deg, refit.median_sin_dip(mc, b["u"]))
        if not spread > bound:
            return cal
        reason = f"the field turned {spread:.0f}° against the gyroscope (above {bound:.0f}°)"
        return cal.with_acceptance(False, (*cal.reasons, reason))

    def gyro_heading_fields(self, cal: MagCalibration) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The recent samples (the stale test's ring: the last ``stale_window_s``, at up to
        ``stale_rate_hz``) taken while the filter's heading was the gyroscope's alone (since
        ``_gyro_heading_t``), every one of them, calibrated with ``cal``: their times, fields (N × 3, µT) and
        up vectors (N × 3), device frame — what the place was like before any calibrated field reached the
        filter's detectors (:meth:`pdr_mag.fusion.FusionCore.seed_flag_share`)."""
        r = self._gyro_heading_ring()
        return r["t"], cal.apply(r["m"]), r["u"]

    def _gyro_heading_ring(self) -> np.ndarray:
        """The ring's samples since ``_gyro_heading_t`` with the filter's north known."""
        ring = self._ring
        if not np.isfinite(ring["t"]).any():
            return ring[:0]
        r = self._recent(float(np.nanmax(ring["t"])))
        return r[(r["t"] >= self._gyro_heading_t) & np.all(np.isfinite(r["n"]), axis=1)]

    def gyro_heading_azimuths(self, cal: MagCalibration) -> tuple[np.ndarray, ...]:
        """The recent samples (the stale test's ring: the last ``stale_window_s``, at up to ``stale_rate_hz``)
        taken while the filter's heading was the gyroscope's alone (since ``_gyro_heading_t``), calibrated
        with ``cal``: their times, the azimuths ``α_k`` of their fields in the filter's frame
        (:func:`pdr_mag.calibration.turned.azimuths`), the azimuths' gradients with respect to the field
        (:func:`~pdr_mag.calibration.turned.azimuth_gradients`: how ``cal``'s offset error turns them) and
        the calibrated fields (N × 3, µT), for the first heading of a filter that had none
        (:meth:`pdr_mag.fusion.FusionCore.fix_heading_from_history`).  Only the samples the buffer would
        admit under ``cal`` count — the strength within ``add_tol_frac`` of the fit's field and, with a
        reference dip, the dip within ``add_dip_tol_deg`` of it: a disturbance turns the field as it
        changes its strength."""
        r = self._gyro_heading_ring()
        if not len(r):
            return np.empty(0), np.empty(0), np.empty((0, 3)), np.empty((0, 3))
        s = self.settings
        mc = cal.apply(r["m"])
        f = cal.field_uT if np.isfinite(cal.field_uT) else self.field_ref
        sd = self.sin_dip_ref
        if f is None:
            ok = np.ones(len(r), dtype=bool)
        else:
            dip_deg = None if sd is None else float(np.degrees(np.arcsin(sd)))
            ok = ~deviating_fields(mc, r["u"], f, s.add_tol_frac * f, dip_deg, s.add_dip_tol_deg)
        mc, u, n = mc[ok], r["u"][ok], r["n"][ok]
        return r["t"][ok], turned.azimuths(mc, u, n), turned.azimuth_gradients(mc, u, n), mc

    def _figure8_fit(self, t: float) -> list:
        """At a rotation episode's end, while an offset-only calibration is in force: the full fit of the
        recent samples (the stale test's ring: the last ``stale_window_s``, every sample at up to
        ``stale_rate_hz``).  The buffer admits only fields within ``add_tol_frac`` of F under that
        calibration, and a phone's soft iron (real phones' axis scales differ by 7–16 %) leaves more, so the
        samples of a figure-8 that reveal it never reach the buffer's full fit; the ring's all do, as a
        requested recalibration's buffer does.  Gated by the ring's coverage as the buffer's full fit is, and
        judged by the calibration core's rules (a swinging arm's episode does not cover the sphere; a
        disturbed place's samples do not fit an ellipsoid), and tried only where a sphere fits the samples
        within the residual every online refit must meet (``max_rms_frac`` of F: a soft iron's stretch
        leaves 3–7 %, a walk past magnets 65–145 %).  ``[]`` when no fit was made."""
        m = self._recent(t)["m"]
        f = self.field_ref
        if f is None or len(m) < 10:
            return []
        try:  # a disturbed place first (the core's full fit would refuse it, at ~0.1 s a fit)
            if fit_sphere(m).residual_rms_uT > self.settings.max_rms_frac * f:
                return []
        except (ValueError, ArithmeticError):
            return []
        found = refit.full_fit(m, self.calibration.offset_array, f, self.settings)
        if found is None:
            return []
        return [refit.judge(replace(found, extra={**found.extra, "figure8": True}), self.settings, f)]

    def _check_prior(self, t: float, n: int, events: list) -> None:
        """Refuse the prior in force when the field it calibrates cannot be the Earth's (OnlineSettings
        ``prior_band_frac``): a store's entry of another phone of the same model, an OS estimate gone
        stale.  A ``prior_refused`` event; nothing is in force then, and the refit that follows is judged as
        a first calibration."""
        s = self.settings
        cal = self.calibration
        mc = cal.apply(self._buf["m"][:n])
        norm = np.linalg.norm(mc, axis=1)
        strength = float(np.median(norm))
        margin = 3.0 * offset_sigma(cal, unknown=0.0)
        f = self.field_ref
        dip = float(np.degrees(np.arcsin(np.clip(refit.median_sin_dip(mc, self._buf["u"][:n]), -1.0, 1.0))))
        c = self._cal[0]
        dip_ok = not c["dip_check"] or abs(dip - c["dip_deg"]) <= s.prior_band_dip_deg + np.degrees(
            margin / max(strength, 1.0))
        if dip_ok and plausible_strength(strength, f, s.prior_band_frac, margin):
            return
        data = {"source": prior_source(cal), "offset_uT": [round(float(v), 3) for v in cal.offset],
                "median_strength_uT": round(strength, 3), "reference_uT": None if f is None else round(f, 3),
                "median_dip_deg": round(dip, 2)}
        events.append((t, "prior_refused", data))
        self._use(None, "none")
        self._gyro_heading_t = t  # the filter's heading had this prior's updates until now

    def _stale_test(self, t: float, events: list) -> None:
        """The stale test's fits on the recent window (its first part found the strength or the dip
        deviating); the same shift found again ``stale_confirm_s`` later requests a recalibration.  A
        candidate found, replaced or dropped ends the block (the filter takes the shift suspected of the
        calibration anew)."""
        s = self.settings
        st = self._state[0]
        cal = self.calibration
        window = self._recent(t)
        mc = cal.apply(window["m"])
        pending = bool(st["has_candidate"])
        found = stale.window_shift(mc, window["u"], self._stale_model, self._free_model, s, pending)
        if found is stale.INCONCLUSIVE:
            return
        if found is None:
            if pending:
                events.append((t, "suspicion_dropped", _shift_data(self.suspected_shift)))
                st["has_candidate"] = False
                st["cal_changed"] = True
            return
        same = pending and np.all(
            np.abs(st["candidate_shift"] - found.delta) < np.maximum(3 * found.sigma, 3.0)
        )
        if not same:
            st["cal_changed"] = True
            st["has_candidate"] = True
            st["candidate_t"] = t
            st["candidate_shift"] = found.delta
            data = {**_shift_data(self.suspected_shift), "residual_rms_uT": round(float(found.rms), 3)}
            events.append((t, "calibration_suspected", data))
            return
        if t - st["candidate_t"] < s.stale_confirm_s:
            return
        st["has_candidate"] = False
        self._request_recalibration(t, found, len(window), events)

    def _request_recalibration(self, t: float, found: stale.Shift, n: int, events: list) -> None:
        """Use the provisional offset ``b + M⁻¹δ`` (M = :attr:`MagCalibration.matrix`), clear the buffer and
        the ring, and wait for a figure-8."""
        cal = self.calibration
        shift = np.linalg.inv(cal.matrix) @ found.delta
        provisional = MagCalibration.from_arrays(
            cal.offset_array + shift,
            cal.soft_iron_array,
            field_uT=cal.field_uT,
            method="gravity",
            residual_rms_uT=found.rms,
            offset_std_uT=found.sigma,
            n_samples=n,
            mag_to_imu=cal.mag_to_imu,
            extra={"sin_dip": self.sin_dip_ref, "provisional": True},
        )
        events.append(
            (
                t,
                "recalibration_requested",
                {
                    "reason": "offset moved: orientation-dependent, time-stable strength residual",
                    "offset_shift_uT": [float(v) for v in shift],
                    "residual_rms_uT": float(found.rms),
                },
            )
        )
        self._use(provisional, "recalibrating")
        self.provided = False
        self._recal_t = t
        st = self._state[0]
        st["episode_seen"] = st["episode"]
        self.clear_buffer()
        self._ring.view(np.float64)[:] = np.nan

    def clear_buffer(self) -> None:
        """Empty the diversity buffer (the next refit fits)."""
        self._buf.view(np.float64)[:] = np.nan
        st = self._state[0]
        st["n_buf"] = 0
        st["coverage_stale"] = True
        st["cover_ok"] = False
        st["fit_new"] = np.inf

    def _recent(self, t: float) -> np.ndarray:
        """The ring's samples of the last ``stale_window_s``, oldest first."""
        return K.recent(self._ring, self._state[0]["ring_next"], t - self.settings.stale_window_s)

    # ------------------------------------------------------------------ state
    def get_state(self) -> dict:
        """JSON-serialisable state (:meth:`set_state` on a calibrator with the same settings resumes).

        The open block's fields (:data:`_BLOCK_FIELDS`) are left out, as are the block-start copies.
        """
        return {
            "calibration": None if self.calibration is None else self.calibration.to_dict(),
            "cal_state": self.cal_state,
            "provided": self.provided,
            "recal_t": state_float(self._recal_t),
            "n_refits": self._n_refits,
            "latest_fit": None if self._latest_fit is None else self._latest_fit.to_dict(),
            "last_reject_t": state_float(self._last_reject_t),
            "gyro_heading_t": state_float(self._gyro_heading_t),
            "loop": {name: _to_json(self._state[0][name]) for name in _SAVED_FIELDS},
            "buffer": _to_json(self._buf[: self._n_buf].view(np.float64)),
            "ring": _to_json(self._ring.view(np.float64)),
        }

    def set_state(self, st: dict) -> None:
        """Restore a :meth:`get_state` dict; the next sample starts a new block.  The open block's fields
        are reset; a state that includes them is accepted and their values are not read."""
        cal = None if st["calibration"] is None else MagCalibration.from_dict(st["calibration"])
        self._use(cal, st["cal_state"])
        self.provided = bool(st["provided"])
        self._recal_t = float(st["recal_t"])
        self._n_refits = int(st["n_refits"])
        self._latest_fit = None if st["latest_fit"] is None else MagCalibration.from_dict(st["latest_fit"])
        self._last_reject_t = float(st["last_reject_t"])
        self._gyro_heading_t = float(st["gyro_heading_t"])
        loop = self._state[0]
        for name in _BLOCK_FIELDS:
            loop[name] = 0  # False for the flags
        for name in _SAVED_FIELDS:
            v = st["loop"][name]
            loop[name] = [float(x) for x in v] if isinstance(v, list) else v if type(v) is bool else float(v)
        buf = self._buf.view(np.float64)
        buf[:] = np.nan
        buf[: len(st["buffer"])] = [float(x) for x in st["buffer"]]
        self._ring.view(np.float64)[:] = [float(x) for x in st["ring"]]


def separation(s: OnlineSettings, strength: float | None, sin_dip: float | None) -> float:
    """The diversity buffer's neighbourhood, raw µT: ``min_sep_frac · F`` (F 50 µT when unknown), or
    ``min_sep_yaw · F cos I`` where the horizontal field makes that less (:class:`OnlineSettings`)."""
    f = 50.0 if strength is None else strength
    if sin_dip is None:
        return s.min_sep_frac * f
    return f * min(s.min_sep_frac, s.min_sep_yaw * float(np.sqrt(max(1.0 - sin_dip * sin_dip, 0.0))))


def _shift_data(shift: np.ndarray) -> dict:
    """The ``calibration_suspected`` / ``suspicion_dropped`` events' data: the suspected offset shift."""
    return {"offset_shift_uT": [round(float(v), 3) for v in shift]}


def _to_json(v):
    """A record field or a float array for the state JSON (non-finite floats as strings)."""
    if isinstance(v, np.ndarray):
        return [state_float(x) for x in v.ravel()]
    if isinstance(v, bool | np.bool_):
        return bool(v)
    if isinstance(v, int | np.integer):
        return int(v)
    return state_float(v)
