"""HeadingPipeline: the streaming state machine that ties calibration, detection and fusion together.

Data flow (accelerometer, gyroscope, magnetometer: independent, irregular rates)::

    push / push_arrays ─► pending samples per stream ─► time-ordered merge ─► blocks of ``block_s`` ─►
        calibrate mag (the calibration in force) ─► FusionCore (detectors + filter) ─► estimates
    a closed block's magnetometer samples (+ up vector, gyro rate) ─► OnlineCalibrator ─► calibration, events

What the output is.  Stream time is cut into blocks ``[k·block_s, (k+1)·block_s)``, and the rows are those
of processing block by block: fuse the block's samples with the calibration in force, then close it —
give its magnetometer samples to the online calibrator, each with the up vector of the filter's latest
output row at or before it (the accelerometer's direction before the filter has an attitude) and the norm
of the latest gyro sample.  The calibration thus changes only at block ends.  When the first one comes into
force (none before it), the filter, whose heading the gyroscope alone has carried, takes its heading from the
recent fields that calibration explains (:meth:`~pdr_mag.fusion.FusionCore.fix_heading_from_history`).

Streaming == batch.  Samples leave the pending buffers only once they are older than the newest sample of
every stream (no later push can precede them; ties go accel < gyro < mag), so the merged stream does not
depend on how the input was cut into pushes; the fusion core's output does not depend on how its input is
cut, and the calibrator is given whole blocks.  Sample by sample, in chunks or all at once give identical
rows, events and calibrations (tested).  The one exception is :meth:`HeadingPipeline.poll`'s look-ahead
bound: a stream more than ``max_lag_s`` behind the others is not waited for (its late samples are dropped
and counted), which only happens when a stream stalls.

Speculative spans.  One call into the compiled filter and one into the calibrator per block would cost
more in fixed per-call work than the block's fusion itself (a block is ~100 samples).  So the filter runs
ahead over a span of blocks with the calibration in force, in one call that also keeps a copy of its state
before each block; then the span's ended blocks go to the calibrator in one call, which stops at the end
of the first block whose close changed the calibration.  Then the filter is put back to its state at that
block's end and the rows after it are dropped, and the next span starts there with the new calibration.
A change of the shift suspected of the calibration alone (the stale test's) needs no new run: the filter's
weights do not see it, so the rows after that block only get their std anew
(:meth:`~pdr_mag.fusion.FusionCore.suspect_from`) and the blocks after it go on to the calibrator.
Changes are rare (a few per recording, most while the calibration converges), so a span is short after a
change and doubles after each span without one (``_SPAN_MIN`` … ``_SPAN_MAX`` blocks), once a calibration
is in force.  The rows are those of block-by-block processing whatever the span length (tested).

Memory is bounded: the pending buffers hold at most about ``max_lag_s`` of data between polls (``push``
processes on its own beyond ``max_pending`` samples), the online calibrator's buffers are fixed-size, and
estimates leave at every :meth:`HeadingPipeline.poll`.

Errors at the boundary, flags in the loop: a wrong shape, an unknown stream name, and a stream whose first
samples are not in the contract's units (:class:`pdr_mag.units.UnitCheck`: accelerations in g, a field in
gauss, times in nanoseconds, … — judged on its first 50 samples, or on the 3 or more there are when the
pipeline first processes), and streams whose first samples lie more than ten minutes apart (two clocks,
:func:`pdr_mag.units.clock_problem`) raise ``ValueError``; a NaN row, a repeated or backward timestamp,
and a stalled sensor's value delivered a third time in a row
(:meth:`~pdr_mag.pipeline.streams.PendingStream.stale`) are dropped and counted in
:attr:`HeadingPipeline.dropped`.
"""

from __future__ import annotations

import math
from collections import Counter

import numpy as np

from pdr_mag._records import default_settings
from pdr_mag.calibration.model import MagCalibration
from pdr_mag.calibration.online import OnlineCalibrator
from pdr_mag.calibration.prior import (
    DevicePrior,
    choose,
    phone_calibration,
    phone_changes,
    phone_prior,
    prior_source,
    with_offset_error,
)
from pdr_mag.estimates import EstimateBatch, Event, diag_vectors
from pdr_mag.field import EarthField, earth_field_from_meta
from pdr_mag.fusion import FusionCore, Span, heading_reset_events
from pdr_mag.fusion.kinds import KINDS, MAG, NAMES
from pdr_mag.fusion.rows import OFFSET_ERROR_COLUMNS
from pdr_mag.pipeline import _kernel as PK
from pdr_mag.pipeline import state as state_json
from pdr_mag.pipeline.settings import PipelineSettings, fusion_settings
from pdr_mag.pipeline.stream_gaps import StreamGaps
from pdr_mag.pipeline.streams import PendingStream, take_merged
from pdr_mag.units import UnitCheck, clock_problem

_NO_OFFSET = np.zeros(3)
_EYE3 = np.eye(3)
#: Blocks fused in one speculative span (see the module docstring): the first after a change of calibration,
#: doubled after each span without one, up to the most.  A span costs ~0.1 ms of calls beside its fusion,
#: and a change wastes the fusion of the span's blocks after it: on the tyrex walks a first span of 12
#: blocks (6 s) makes fewer spans than 4 for about the same waste (1 ms less on a swinging walk).
_SPAN_MIN = 12
_SPAN_MAX = 32


class HeadingPipeline:
    """Calibrated, interference-aware heading from streaming accelerometer, gyroscope and magnetometer.

    Parameters
    ----------
    settings : PipelineSettings, optional
    calibration : MagCalibration, optional
        A device calibration (from ``pdr-mag calibrate``); None starts uncalibrated (online only).
    meta : dict, optional
        Recording metadata (``latitude_deg``, ``longitude_deg``, ``altitude_m``, ``date``): with position
        and date, the WMM gives the reference field and the heading is true north.  What the phone knows of
        itself (``mag_os_bias_uT`` and its ``mag_os_bias_changes``, ``mag_os_calibrated``,
        ``gyro_os_bias_rad_s``, ``gyro_os_calibrated``: ``INTERFACE.md``) is a prior
        (:func:`pdr_mag.calibration.prior.phone_prior`, unless ``settings.prior.use_phone`` is False).
    prior : DevicePrior, optional
        What a backend knows of the device (its device store, :class:`pdr_mag.calibration.store.DeviceStore`).
        With the phone's own estimates, each part (magnetometer, gyro) comes from the surer source
        (:func:`pdr_mag.calibration.prior.choose`).  A prior calibration is in force from the first sample,
        never as a fact: the stale test and the online fits replace it when the data disagree.  A
        ``calibration`` given is used instead of the prior's magnetometer part.
    fusion : FusionCore, optional
        The filter to use instead of a new :class:`pdr_mag.fusion.FusionCore` (for tests; the pipeline uses
        its public API: ``advance``, ``restore``, ``use_calibration``, ``get_state``/``set_state``).

    Examples
    --------
    >>> pipe = HeadingPipeline(meta={"latitude_deg": 45.2, "longitude_deg": 5.7, "date": "2016-05-31"})
    >>> pipe.push_arrays("gyro", t_g, gyro); pipe.push_arrays("accel", t_a, acc)   # doctest: +SKIP
    >>> pipe.push_arrays("mag", t_m, mag); out = pipe.poll(); events = pipe.pop_events()  # doctest: +SKIP
    """

    def __init__(
        self,
        settings: PipelineSettings | None = None,
        calibration: MagCalibration | None = None,
        meta: dict | None = None,
        fusion=None,
        prior: DevicePrior | None = None,
    ):
        if calibration is not None and not isinstance(calibration, MagCalibration):
            raise ValueError(
                f"calibration: expected a MagCalibration or None, got {type(calibration).__name__}"
            )
        if meta is not None and not isinstance(meta, dict):
            raise ValueError(f"meta: expected a dict or None, got {type(meta).__name__}")
        if prior is not None and not isinstance(prior, DevicePrior):
            raise ValueError(f"prior: expected a DevicePrior or None, got {type(prior).__name__}")
        self.settings = settings or default_settings(PipelineSettings)
        self.meta = dict(meta or {})
        try:
            self.field: EarthField | None = earth_field_from_meta(self.meta)
        except ValueError as exc:
            raise ValueError(f"meta: {exc}") from exc
        if fusion is None:
            fusion = FusionCore(fusion_settings(self.settings.fusion, self.meta), self.field)
        self.fusion = fusion
        try:
            phone = phone_prior(self.meta, self.settings.prior)
        except ValueError as exc:
            raise ValueError(f"meta: {exc}") from exc
        #: the prior knowledge the run started from (None: nothing known)
        self.prior: DevicePrior | None = choose(phone, prior)
        p = self.prior
        start = calibration if calibration is not None else (p.calibration if p is not None else None)
        f = self.field
        self.online = OnlineCalibrator(
            self.settings.online_settings,
            start,
            strength=None if f is None else f.strength,
            sin_dip=None if f is None else float(np.sin(np.radians(f.inclination_deg))),
        )
        if p is not None and p.gyro_bias is not None:
            self.fusion.set_gyro_prior(p.gyro_bias, p.gyro_bias_std)
        # the phone's later hard-iron estimates, while its first is the calibration in force: (t, offset)
        self._phone_changes: list[tuple[float, tuple]] = []
        if start is not None and start is (phone.calibration if phone is not None else None):
            lag = self.settings.mag_time_offset_s  # the changes are stamped on the magnetometer's clock
            self._phone_changes = [(t - lag, b) for t, b in phone_changes(self.meta)]
        self.dropped: Counter = Counter()
        #: stretches in which one stream delivered no sample (a ``stream_gap`` event each; the summary's
        #: ``stream_gaps``)
        self.stream_gaps = StreamGaps()
        self._streams = {k: PendingStream() for k in KINDS}
        # each stream's unit, judged on its first samples (none when the caller judged them)
        self._units = {k: UnitCheck(k) for k in KINDS} if self.settings.check_inputs else {}
        self._done_t = -np.inf  # every sample before this time has been processed
        self._span = _SPAN_MIN  # blocks in the next span (speed only: the results do not depend on it)
        self._pend = np.empty(0, dtype=PK.MAG_ROW)  # magnetometer rows of the open block, not yet closed
        self._carry = np.zeros(1, dtype=PK.CARRY)  # the magnetometer context from before (see mag_context)
        self._carry[0]["q"] = np.nan
        self._carry[0]["accel"] = np.nan
        self._coverage = 0.0  # the calibrator's buffer coverage after the last closed block
        self._interf = False  # the interference flag of the last output row
        self._calibrations: list[tuple[float, MagCalibration]] = []
        self._cal_in_use: MagCalibration | None = None  # the calibration the filter's input was made with
        self._n_out = 0
        self._t_first = np.nan
        self._t_last = np.nan
        self._out: list[EstimateBatch] = []
        self._events: list[Event] = []
        self._magcal: list[tuple[np.ndarray, np.ndarray]] = []
        self._use_calibration()

    # ------------------------------------------------------------------ properties
    @property
    def calibration(self) -> MagCalibration | None:
        """The magnetometer calibration in use (None before the first accepted online fit)."""
        return self.online.calibration

    @property
    def cal_state(self) -> str:
        return self.online.cal_state

    @property
    def north(self) -> str:
        """``"true"`` when the WMM declination is applied, else ``"magnetic"``."""
        return "true" if self.field is not None else "magnetic"

    @property
    def calibrations(self) -> list[tuple[float, MagCalibration]]:
        """Every calibration taken into use, with the stream time it started (the given one at -inf)."""
        return list(self._calibrations)

    @property
    def n_outputs(self) -> int:
        return self._n_out

    def save_calibration(self, path) -> None:
        """Write the current calibration as the ``calibrate --json`` file (ValueError when there is none)."""
        if self.calibration is None:
            raise ValueError("calibration: none yet (no accepted fit)")
        self.calibration.to_json(path)

    @staticmethod
    def load_calibration(path) -> MagCalibration:
        """Read a ``calibrate --json`` file (raises ValueError naming the file and the problem)."""
        return MagCalibration.from_json(path)

    # ------------------------------------------------------------------ input
    def push(self, kind, t: float, xyz) -> None:
        """Push one sample of stream ``kind`` (``"accel"``, ``"gyro"``, ``"mag"`` or 0/1/2)."""
        v = np.asarray(xyz, dtype=float).reshape(-1)
        if v.shape != (3,):
            raise ValueError(f"xyz: expected 3 values (x, y, z), got {v.size}")
        self.push_arrays(kind, np.array([t], dtype=float), v.reshape(1, 3))

    def push_arrays(self, kind, t, xyz) -> None:
        """Push a chunk of one stream: times (N,) s and values (N, 3) in the contract's units.

        Rows with NaN, times not after the stream's previous sample or before what has been processed, and
        a stalled sensor's repeated values (:meth:`~pdr_mag.pipeline.streams.PendingStream.stale`) are
        dropped and counted (``<stream>:nan``, ``:non_monotonic``, ``:late``, ``:repeated``).  A stretch
        without samples (before the repeated values are dropped: a stalled sensor still delivers) longer than
        :class:`~pdr_mag.pipeline.stream_gaps.StreamGaps`' threshold is a ``stream_gap`` event.  Raises
        ``ValueError`` when the stream's first samples are not in the contract's units
        (:class:`pdr_mag.units.UnitCheck`).
        """
        name = kind if type(kind) is str and kind in KINDS else _kind_name(kind)
        t = np.asarray(t, dtype=float).reshape(-1)
        xyz = np.asarray(xyz, dtype=float)
        if xyz.ndim != 2 or xyz.shape != (len(t), 3):
            raise ValueError(f"xyz: expected shape ({len(t)}, 3) for {len(t)} times, got {xyz.shape}")
        if not len(t):
            return
        if name == "mag" and self.settings.mag_time_offset_s:
            t = t - self.settings.mag_time_offset_s  # onto the IMU's time (PipelineSettings)
        s = self._streams[name]
        if not (
            t[0] >= self._done_t and PK.in_order(t, xyz, s.last_t)
        ):  # drop (and count) what cannot be used
            good = np.isfinite(t) & np.all(np.isfinite(xyz), axis=1)
            if not np.all(good):
                self.dropped[f"{name}:nan"] += int(np.count_nonzero(~good))
                t, xyz = t[good], xyz[good]
            # strictly increasing after the previous sample, and not before what has been processed
            prev = np.maximum.accumulate(np.concatenate([[s.last_t], t]))[:-1]
            ok = t > prev
            late = ok & (t < self._done_t)
            if np.any(~ok):
                self.dropped[f"{name}:non_monotonic"] += int(np.count_nonzero(~ok))
            if np.any(late):
                self.dropped[f"{name}:late"] += int(np.count_nonzero(late))
            keep = ok & ~late
            t, xyz = t[keep], xyz[keep]
        if len(t):
            first = name not in self.stream_gaps.first
            self._events += self.stream_gaps.add(name, t)
            if self._units:
                self._check_inputs(name, t, xyz, first)
            stale = s.stale(xyz)
            if stale.any():
                self.dropped[f"{name}:repeated"] += int(np.count_nonzero(stale))
                t, xyz = t[~stale], xyz[~stale]
        if len(t):
            s.append(t, xyz)
        a, g, m = self._streams.values()
        if a.n + g.n + m.n > self.settings.max_pending:
            self._process(min(a.last_t, g.last_t, m.last_t))

    def _check_inputs(self, name: str, t: np.ndarray, xyz: np.ndarray, first: bool) -> None:
        """The stream's unit on its first samples; once the last stream's first sample is in, the clocks
        (the streams' first samples, which the gap finder keeps) — after the units, so that times in
        nanoseconds, which also start far apart, are named as such."""
        self._units[name].add(t, xyz)
        starts = self.stream_gaps.first
        if first and len(starts) == len(KINDS) and (problem := clock_problem(starts)) is not None:
            for check in self._units.values():
                check.settle()
            raise ValueError(problem)

    def push_phone_calibration(self, t: float, offset_uT) -> None:
        """The phone's OS changed its hard-iron estimate at stream time ``t`` (Android's uncalibrated
        magnetometer carries it in its bias columns): while the phone's first estimate is the calibration in
        force (no online fit has replaced it), the new one replaces it at the end of the block ``t`` falls in.
        Changes must come in time order, before the samples after them are polled."""
        b = np.asarray(offset_uT, dtype=float)
        if b.shape != (3,) or not np.all(np.isfinite(b)) or not math.isfinite(t):
            raise ValueError(
                f"phone calibration: expected a finite time and 3 finite µT, got {t!r}, {offset_uT!r}"
            )
        t_imu = float(t) - self.settings.mag_time_offset_s  # stamped on the magnetometer's clock
        self._phone_changes.append((t_imu, tuple(float(v) for v in b)))
        self._phone_changes.sort()

    # ------------------------------------------------------------------ output
    def poll(self) -> EstimateBatch:
        """Process what can be processed and return the estimates produced since the last poll."""
        self._process(self._poll_horizon())
        return self._take_out()

    def _poll_horizon(self) -> float:
        """The oldest of the streams' latest samples, but not more than ``max_lag_s`` behind the newest."""
        last = [s.last_t for s in self._streams.values()]
        newest = max(last)
        return max(min(last), newest - self.settings.max_lag_s) if math.isfinite(newest) else min(last)

    def flush(self) -> EstimateBatch:
        """Process everything pending (end of stream) and return the remaining estimates; the streams'
        gaps at their start and end become events."""
        self._process(np.inf, final=True)
        self._events += self.stream_gaps.finish()
        return self._take_out()

    def pop_events(self) -> list[Event]:
        """Events since the last call (interference_start/_end, calibration_accepted/_rejected,
        recalibration_requested, recalibrated, rotation_episode_start/_end, stream_gap)."""
        ev, self._events = self._events, []
        return ev

    def pop_mag_calibrated(self) -> tuple[np.ndarray, np.ndarray]:
        """Calibrated magnetometer samples (t, xyz) since the last call (``keep_mag_calibrated``): the field
        the filter takes — the calibration in force applied, less the offset error the filter has found
        (:meth:`pdr_mag.fusion.FusionCore.offset_error`, as of the latest output row at or before each
        sample)."""
        if not self._magcal:
            return np.empty(0), np.empty((0, 3))
        t = np.concatenate([a for a, _ in self._magcal])
        x = np.concatenate([b for _, b in self._magcal])
        self._magcal = []
        return t, x

    def run(self, streams: dict) -> EstimateBatch:
        """Batch convenience: ``{"accel": (t, xyz), ...}`` all at once → every estimate (a loop over push)."""
        for name, pair in streams.items():
            if not (isinstance(pair, tuple | list) and len(pair) == 2):
                raise ValueError(f"streams[{name!r}]: expected a (t, xyz) pair, got {type(pair).__name__}")
            self.push_arrays(name, *pair)
        self._process(self._poll_horizon())
        return self.flush()

    def _take_out(self) -> EstimateBatch:
        out, self._out = self._out, []
        return EstimateBatch.concat(out) if len(out) != 1 else out[0]

    # ------------------------------------------------------------------ processing
    def _process(self, horizon: float, final: bool = False) -> None:
        """Fuse every pending sample before ``horizon`` (all of them when ``final``), span by span, and close
        the blocks that ended; the phone's later hard-iron estimates (:meth:`push_phone_calibration`) take
        effect at the end of the block they fall in, as a calibration found by the online calibrator does."""
        for check in self._units.values():  # a stream's unit judged before its samples are used
            check.settle()
        b = self.settings.block_s
        while self._phone_changes:
            t_change, offset = self._phone_changes[0]
            t_block_end = (math.floor(t_change / b) + 1) * b
            if not final and t_block_end > horizon:
                break  # its block has not ended yet
            self._fuse_until(t_block_end)
            self._phone_changes.pop(0)
            self._renew_phone_calibration(t_change, max(t_block_end, self._done_t), offset)
        self._fuse_until(horizon, final)

    def _renew_phone_calibration(self, t_change: float, t_use: float, offset: tuple) -> None:
        """The phone's OS changed its hard-iron estimate at ``t_change``: while its first one is still the
        calibration in force, the new one replaces it (from ``t_use``, a block end); a
        ``phone_calibration_changed`` event says which."""
        old = self.online.calibration
        std = old.offset_std_uT if old is not None else None
        cal = phone_calibration(offset, std)
        used = self.online.renew_prior(cal)
        if used:
            self._calibrations.append((t_use, cal))
            self._use_calibration()
        data = {"offset_uT": [round(float(v), 3) for v in offset], "in_force": used}
        self._events.append(Event(float(t_change), "phone_calibration_changed", data))

    def _fuse_until(self, horizon: float, final: bool = False) -> None:
        """:meth:`_process` without the phone's changes."""
        if final:
            t_end = np.inf
        elif not np.isfinite(horizon) or horizon <= self._done_t:
            return
        else:
            t_end = horizon
        kind, t, xyz = take_merged(self._streams, t_end)
        if not final:
            self._done_t = t_end
        elif len(t):
            self._done_t = max(self._done_t, float(t[-1]))
        b = self.settings.block_s
        blk = np.floor(t / b)
        i = 0
        while i < len(t):
            i = self._fuse_span(kind, t, xyz, blk, i, t_end)
        pend = self._pend
        if len(pend) and (math.floor(pend["t"][-1] / b) + 1) * b <= t_end:
            # no later sample, but the horizon passed the end of the open block
            self._pend = pend[:0]
            before = self._in_force()
            events, _, _, cov = self._close_blocks(pend, np.floor(pend["t"] / b))
            self._events += [ev for _, _, ev in events]
            self._coverage = float(cov[-1]) if len(cov) else self._coverage
            if self._in_force_changed(before):
                fixed = self._use_calibration()
                if fixed is not None:  # after the calibrator's events of its block
                    self._events.append(fixed)

    def _fuse_span(self, kind, t, xyz, blk, i: int, t_end: float) -> int:
        """Fuse the span of blocks that starts at sample ``i`` (see the module docstring); returns the index
        of the first sample not fused for good."""
        e = int(blk.searchsorted(blk[i] + self._span))
        # the span's last block has ended when a later sample is here or the horizon passed its end
        last_ended = e < len(t) or (blk[e - 1] + 1) * self.settings.block_s <= t_end
        n = self._fuse_and_close(kind[i:e], t[i:e], xyz[i:e], blk[i:e], last_ended)
        if n == e - i and e < len(t) and self.online.calibration is not None:
            # (while none is in force, the first calibration is near: refits come twice as often)
            self._span = min(2 * self._span, _SPAN_MAX)
        return i + n

    def _fuse_and_close(self, kind, t, xyz, blk, last_ended: bool) -> int:
        """Fuse these samples with the calibration in force and close their ended blocks; returns how many
        are fused for good: all, or those up to the end of the block whose close changed the calibration."""
        b = self.settings.block_s
        cal = self.online.calibration
        in_force = self._in_force()
        cal_state = self.online.cal_state
        # the magnetometer calibrated as MagCalibration.apply does: (m − b) @ Mᵀ
        data, allowed, n_gyro, starts = PK.filter_input(kind, xyz, blk, self._mag_offset, cal is not None)
        if cal is not None and self._mag_matrix_t is not None:
            is_mag = kind == MAG
            data[is_mag] = data[is_mag] @ self._mag_matrix_t
        # the filter over the span, keeping its state before each block (``starts``: each one's first sample)
        o_start = self.fusion.offset_error() if self.settings.keep_mag_calibrated else None
        advanced = self.fusion.advance(Span(kind, t, data, allowed, n_gyro), starts, cal_state)
        batch, snapshots = advanced.rows, advanced.snapshots
        end = len(t)
        events: list = []  # (block, 0: the filter's / 1: the calibrator's, Event)
        closed_blk = closed_cov = np.empty(0)  # the blocks closed here, the coverage after each
        if self.settings.online:
            # the open block's magnetometer rows, then these samples'
            rows, row_blk = PK.mag_context(kind, t, xyz, batch.t, batch.q_wd, self._carry, self._pend, b)
            n_ended = len(rows) if last_ended else int(row_blk.searchsorted(blk[-1]))
            events, n_taken, closed_blk, closed_cov = self._close_blocks(rows[:n_ended], row_blk[:n_ended])
            while self._only_suspicion_changed(in_force):
                # the filter's weights do not see the suspected shift: the rows after the block whose close
                # changed it keep all but their std, and the blocks after it go on to the calibrator
                after = int(blk.searchsorted(row_blk[n_taken - 1], side="right"))
                first = len(batch) if after == len(t) else int(batch.t.searchsorted(t[after]))
                self.fusion.suspect_from(advanced, first, self.online.suspected_shift)
                in_force = self._in_force()
                rest = slice(n_taken, n_ended)
                more, n_more, more_blk, more_cov = self._close_blocks(rows[rest], row_blk[rest])
                events += more
                n_taken += n_more
                closed_blk, closed_cov = np.r_[closed_blk, more_blk], np.r_[closed_cov, more_cov]
            self._pend = rows[n_ended:]
            if self._in_force_changed(in_force):
                # the blocks after the one whose close changed the calibration (or the shift suspected of it)
                # are to be fused with the new one: the filter goes back to its state at that block's end,
                # and their rows are dropped (a block's samples are all later than the previous block's)
                self._span = _SPAN_MIN
                self._pend = rows[:0]
                end = int(blk.searchsorted(row_blk[n_taken - 1], side="right"))
                if end < len(t):
                    self.fusion.restore(snapshots[int(starts.searchsorted(end))])
                    batch = batch.head(int(batch.t.searchsorted(t[end])))
                # after the filter's state (with its reference strength) is put back; the history's heading
                # after the calibrator's events of its block
                fixed = self._use_calibration()
                if fixed is not None:
                    events.append((math.floor(fixed.t / b), 2, fixed))
            PK.carry_over(kind[:end], xyz[:end], batch.q_wd, self._carry)
        if len(batch):
            batch.diag["coverage"] = PK.rows_coverage(batch.t, b, closed_blk, closed_cov, self._coverage)
            events += [(math.floor(ev.t / b), 0, ev) for ev in self._interference_events(batch)]
            events += [(math.floor(ev.t / b), 0, ev) for ev in heading_reset_events(batch)]
            self._n_out += len(batch)
            self._out.append(batch)
        if len(closed_cov):
            self._coverage = float(closed_cov[-1])
        events.sort(key=lambda x: x[:2])  # block by block: the filter's events, then the calibrator's
        self._events += [ev for _, _, ev in events]
        if end:
            if not math.isfinite(self._t_first):
                self._t_first = float(t[0])
            self._t_last = float(t[end - 1])
            if self.settings.keep_mag_calibrated and cal is not None:
                m = kind[:end] == MAG
                tm = t[:end][m]
                o = _offset_error_at(tm, batch, None if o_start is None else o_start[0])
                self._magcal.append((tm, data[:end][m] - o))
        return end

    def _close_blocks(
        self, rows: np.ndarray, row_blk: np.ndarray
    ) -> tuple[list, int, np.ndarray, np.ndarray]:
        """Give the calibrator the magnetometer rows of ended blocks (``row_blk``: each row's block); it
        stops after the first block whose close changed the calibration.  Returns the events as ``(block,
        1, Event)``, the rows taken, and the blocks closed with the coverage after each."""
        if not len(rows):
            return [], 0, np.empty(0), np.empty(0)
        ends = np.empty(len(rows), dtype=np.bool_)
        ends[:-1] = row_blk[1:] != row_blk[:-1]
        ends[-1] = True
        before = self.online.calibration
        got, n, cov = self.online.update_blocks(
            rows["t"], rows["m"], rows["up"], rows["rate"], ends, rows["north"]
        )
        if self.online.calibration is not before and self.online.calibration is not None:
            self._calibrations.append((float(rows["t"][n - 1]), self.online.calibration))
        closed = np.isfinite(cov[:n])
        events = [(row_blk[r], 1, Event(te, k, d)) for r, (te, k, d) in got]
        return events, n, row_blk[:n][closed], cov[:n][closed]

    def _in_force(self) -> tuple:
        """What the filter takes from the calibrator: the calibration in force and the shift suspected of it
        (by when it was found)."""
        return self.online.calibration, self.online.suspect_key

    def _in_force_changed(self, before: tuple) -> bool:
        """Whether :meth:`_in_force` differs from ``before`` (the calibration by identity)."""
        cal, key = self._in_force()
        return cal is not before[0] or key != before[1]

    def _only_suspicion_changed(self, before: tuple) -> bool:
        """Whether the shift suspected of the calibration in force changed since ``before`` (an
        :meth:`_in_force`) and the calibration did not."""
        cal, key = self._in_force()
        return cal is before[0] and key != before[1]

    def _use_calibration(self, restored: bool = False) -> Event | None:
        """Take the calibration in force into use: its ``b`` and ``Mᵀ`` (``M`` = ``cal.matrix``; None
        for the identity) for the filter's input, and (unless ``restored`` with the filter's state) the
        filter's :meth:`~pdr_mag.fusion.FusionCore.use_calibration` and the shift the stale test suspects of
        it (:attr:`OnlineCalibrator.suspected_shift`, :meth:`~pdr_mag.fusion.FusionCore.set_suspected_shift`):
        until the test confirms or drops it, the heading's std counts the turn it would make.  A first
        calibration (none before it) also gives the filter its heading from the calibration's recent fields
        (:meth:`~pdr_mag.fusion.FusionCore.fix_heading_from_history`); the ``heading_from_history`` event of
        that is returned, for the caller to put after the calibrator's events of the block (None: none)."""
        cal = self.online.calibration
        old = self._cal_in_use
        self._cal_in_use = cal
        self._mag_offset = _NO_OFFSET if cal is None else cal.offset_array
        self._mag_matrix_t = None
        if cal is not None:
            a = cal.matrix
            self._mag_matrix_t = None if (a == _EYE3).all() else a.T
        if restored:
            return None
        if cal is not None and not self._calibrations:
            self._calibrations.append((-np.inf, cal))
        self.fusion.use_calibration(cal, old)
        fix = None
        if cal is not None and old is None:
            # a first calibration: the place its recent fields show, and the heading from them at once (a
            # filter that has one keeps it)
            self.fusion.seed_flag_share(*self.online.gyro_heading_fields(cal))
            fix = self.fusion.fix_heading_from_history(*self.online.gyro_heading_azimuths(cal))
        self.fusion.set_suspected_shift(self.online.suspected_shift)
        if fix is None:
            return None
        data = {"fields": fix.fields, "span_s": round(fix.span_s, 3), "jump_deg": round(fix.turn_deg, 3),
                "heading_std_deg": round(fix.std_deg, 3)}  # fmt: skip
        return Event(fix.t, "heading_from_history", data)

    def _interference_events(self, batch: EstimateBatch) -> list[Event]:
        """The changes of the interference flag in these rows."""
        flags = batch.interference
        if flags.all() if self._interf else not flags.any():
            return []  # no change (the common case)
        prev = np.empty_like(flags)
        prev[0] = self._interf
        prev[1:] = flags[:-1]
        out = []
        for i in np.flatnonzero(flags != prev):
            kind = "interference_start" if flags[i] else "interference_end"
            data = {}
            for key in ("field_strength_uT", "dip_deg", "interference_score"):
                v = batch.diag.get(key)
                if v is not None and np.isfinite(v[i]):
                    data[key] = round(float(v[i]), 3)
            out.append(Event(float(batch.t[i]), kind, data))
        self._interf = bool(flags[-1])
        return out

    def device_knowledge(self) -> DevicePrior:
        """What this run knows of the device now, for a device store (:class:`~pdr_mag.calibration.store.
        DeviceStore`): the calibration the session's data support best
        (:attr:`~pdr_mag.calibration.online.OnlineCalibrator.best_estimate`: the latest accepted refit that
        may stand for the calibration in force, else that calibration — an accepted fit, or the given /
        prior one the stale test let stand — with the offset error the filter found under it,
        :meth:`~pdr_mag.fusion.FusionCore.offset_error`) — but not the phone's own estimate (the phone states
        it again next time), nor a provisional one during a recalibration; and the filter's gyro bias with its
        σ (the larger of the three axes').  A part not known is None."""
        cal = self.online.best_estimate  # None before a calibration and during a recalibration
        if cal is not None and (prior_source(cal) == "phone" or not cal.accepted):
            cal = None
        found = self.fusion.offset_error()
        if cal is not None and cal is self.online.calibration and found is not None and (
            cal.offset_covariance is not None  # a calibration as sure as its user says stays so
        ):
            cal = with_offset_error(cal, *found)
        b, var = self.fusion.gyro_bias()
        ok = bool(np.all(np.isfinite(b)) and np.all(np.isfinite(var)))
        return DevicePrior(
            calibration=cal,
            gyro_bias=tuple(float(v) for v in b) if ok else None,
            gyro_bias_std=float(np.sqrt(np.max(var))) if ok else float("nan"),
            source="run",
        )

    # ------------------------------------------------------------------ summary
    def summary(self) -> dict:
        """The run's summary for ``replay --json`` (INTERFACE.md keys and a few more)."""
        dur = self._t_last - self._t_first if np.isfinite(self._t_first) else 0.0
        return {
            "n_outputs": int(self._n_out),
            "duration_s": float(dur),
            "t_start": float(self._t_first) if np.isfinite(self._t_first) else None,
            "north": self.north,
            "cal_state": self.cal_state,
            "calibrations": [
                {"t": None if not np.isfinite(t) else float(t), **c.to_dict()} for t, c in self._calibrations
            ],
            "dropped_samples": dict(sorted(self.dropped.items())),
            "prior": None if self.prior is None else self.prior.to_dict(),
            "mag_time_offset_s": self.settings.mag_time_offset_s,
            "stream_gaps": self.stream_gaps.summary(),
            "field": None
            if self.field is None
            else {
                "model": self.field.model,
                "strength_uT": self.field.strength,
                "inclination_deg": self.field.inclination_deg,
                "declination_deg": self.field.declination_deg,
            },
        }

    # ------------------------------------------------------------------ state
    def get_state(self) -> dict:
        """JSON-serialisable state (resume after a restart with :meth:`set_state` on a pipeline built with
        the same settings and meta).  Pending samples are included; estimates and events not yet
        polled are not — poll them first (:func:`pdr_mag.pipeline.state.to_json`)."""
        return state_json.to_json(self)

    def set_state(self, state: dict) -> None:
        """Restore from :meth:`get_state` (ValueError when the dict is not such a state)."""
        state_json.from_json(self, state)
        self._use_calibration(restored=True)
        self._out, self._events, self._magcal = [], [], []


def _kind_name(kind) -> str:
    if isinstance(kind, str):
        if kind not in KINDS:
            raise ValueError(f"kind: expected one of {sorted(KINDS)}, got {kind!r}")
        return kind
    try:
        return NAMES[int(kind)]
    except (KeyError, TypeError, ValueError):
        raise ValueError(f"kind: expected 'accel', 'gyro', 'mag' or 0/1/2, got {kind!r}") from None


def _offset_error_at(t: np.ndarray, rows: EstimateBatch, before: np.ndarray | None) -> np.ndarray:
    """The filter's offset error (N × 3, µT) at times ``t``: the latest of ``rows`` at or before each (their
    ``mag_offset_error_*`` columns), ``before`` (the filter's at the rows' start; None: none found) ahead of
    the first row."""
    out = np.zeros((len(t), 3)) if before is None else np.tile(np.asarray(before, dtype=float), (len(t), 1))
    o = diag_vectors(rows, OFFSET_ERROR_COLUMNS) if len(rows) else None
    if o is None or not len(t):
        return out
    k = np.searchsorted(rows.t, t, side="right") - 1
    after = k >= 0
    out[after] = o[k[after]]
    return out
