"""HeadingPipeline: the streaming state machine that ties calibration, detection and fusion together.

Data flow per sample stream (accelerometer, gyroscope, magnetometer — independent, irregular rates)::

    push / push_arrays ─► per-stream buffers ─► time-ordered merge ─► blocks of ``block_s`` ─►
        calibrate mag (current MagCalibration, ``mag_to_imu``) ─► FusionCore (detectors + filter) ─►
        estimates (+ cal_state)  ─►  OnlineCalibrator (diversity buffer, refits, stale test) ─► events

Determinism (streaming == batch).  Samples are released from the per-stream buffers only when they are
older than the newest sample of *every* expected stream (so no later push can precede them; ties go
accel < gyro < mag) and fused at once (the fusion core gives the same result however its input is cut).
The calibration changes only at block boundaries (multiples of ``block_s`` in stream time): when the
released samples pass the end of a block, the online calibrator is given that block's magnetometer samples
(with the filter's up vector and the gyro rate of the latest row at or before each — causal, so
independent of the cuts) before any sample of the next block is fused.  Hence the output depends on the
data alone, not on how it was cut into pushes: sample by sample, in chunks or all at once give identical
rows.

Speed.  The filter is not called once per block: it runs ahead over a span of blocks with the calibration
in use (one call into the compiled kernel), the span's blocks are then closed by one call to
:meth:`OnlineCalibrator.update_blocks <pdr_mag.calibration.online.OnlineCalibrator.update_blocks>`, which
stops at the first block whose close changes the calibration; the filter is then put back to its latest
snapshot before that boundary (the span's start, or one taken every ``_SNAP_EVERY`` blocks inside long
spans) and re-run up to it (calibration changes are rare: a few per recording), and the next span starts
there.  The rows are those of block-by-block processing, whatever the span lengths (tested).  The
per-poll bookkeeping (merge, magnetometer context, span layout) is compiled
(:mod:`pdr_mag._pipeline_kernel`).  The one exception to streaming == batch is
:meth:`HeadingPipeline.poll`'s look-ahead bound: a stream more than ``max_lag_s`` behind the others is not
waited for (its late samples are dropped and counted), which only happens when a stream stalls.

Memory is bounded: the pending buffers hold at most about ``max_lag_s`` of data between polls (``push``
processes on its own beyond ``max_pending`` samples), the online calibrator's buffers are fixed-size, and
estimates leave at every :meth:`poll`.

Errors at the boundary, flags in the loop: a wrong shape or unknown stream name raises ``ValueError``; a
NaN row, a repeated or backward timestamp is dropped and counted in :attr:`HeadingPipeline.dropped`.
"""

from __future__ import annotations

import json
import math
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from pdr_mag import _pipeline_kernel as PK
from pdr_mag._json import state_float
from pdr_mag.calibration.model import MagCalibration
from pdr_mag.calibration.online import OnlineCalibrator, OnlineSettings
from pdr_mag.estimates import EstimateBatch, Event
from pdr_mag.field import EarthField, earth_field_from_meta

#: Stream names and their ``kind`` codes in the merged sample stream.
KINDS = {"accel": 0, "gyro": 1, "mag": 2}
_NAMES = {v: k for k, v in KINDS.items()}
STATE_VERSION = 1
#: Blocks fused in one speculative span (see :meth:`HeadingPipeline._process`): the first span after a
#: calibration change is short (changes come in runs while the calibration converges, and each one throws
#: away the span's fusion after it), each span without a change doubles the next, up to the maximum.  A
#: span of L blocks costs a fixed c ≈ 7 blocks' worth of fusion (Python per span) and, at a rate r of
#: changes per block, r·L/2 blocks thrown away per block: L ≈ √(2·7/r) ≈ 30 for the one change in 40 s of
#: the walks' later minutes (measured: 32 beats 64 by 4–5 ms on the swinging walks, ±0.5 ms elsewhere).
_SPAN_MIN = 8
_SPAN_MAX = 32
#: Blocks between the filter snapshots taken inside a span (a change re-runs the filter from the latest one).
_SNAP_EVERY = 4
_NO_OFFSET = np.zeros(3)


def _default_fusion_settings():
    from pdr_mag.attitude import FusionSettings

    return FusionSettings()


@dataclass(frozen=True)
class PipelineSettings:
    """Settings of :class:`HeadingPipeline`.

    Attributes
    ----------
    block_s : float
        Calibration block length, s: the online calibration may change at each block boundary (the
        output latency does not depend on it: samples are fused as soon as every stream has passed them).
    max_lag_s : float
        :meth:`HeadingPipeline.poll` does not wait for a stream more than this behind the newest sample, s.
    max_pending : int
        ``push`` processes what it safely can once this many samples are pending.
    online : bool
        Run the online calibrator (refits, stale test, recalibration).  False: the given calibration only.
    online_settings : OnlineSettings
        Its settings.
    fusion : FusionSettings or None
        Settings of :class:`pdr_mag.attitude.FusionCore` (None: its defaults).
    keep_mag_calibrated : bool
        Keep the calibrated magnetometer samples for :meth:`HeadingPipeline.pop_mag_calibrated` (sinks).
    """

    block_s: float = 0.5
    max_lag_s: float = 1.0
    max_pending: int = 20000
    online: bool = True
    online_settings: OnlineSettings = field(default_factory=OnlineSettings)
    fusion: object | None = None
    keep_mag_calibrated: bool = False

    def __post_init__(self):
        if not (np.isfinite(self.block_s) and self.block_s > 0):
            raise ValueError(f"block_s: expected a positive number of seconds, got {self.block_s!r}")
        if not (np.isfinite(self.max_lag_s) and self.max_lag_s > 0):
            raise ValueError(f"max_lag_s: expected a positive number of seconds, got {self.max_lag_s!r}")
        if int(self.max_pending) < 1:
            raise ValueError(f"max_pending: expected a positive count, got {self.max_pending!r}")


class _Stream:
    """Pending samples of one input stream: rows ``[lo, hi)`` of one buffer that grows (doubling) when a
    push does not fit after moving the pending rows to its start — so a push is one copy, and the samples
    before a time are taken (and merged with the other streams') by :func:`_pipeline_kernel.take_merge3`."""

    __slots__ = ("t", "xyz", "lo", "hi", "last_t")

    def __init__(self):
        self.t = np.empty(0)
        self.xyz = np.empty((0, 3))
        self.lo = 0
        self.hi = 0
        self.last_t = -np.inf

    @property
    def n(self) -> int:
        return self.hi - self.lo

    def append(self, t: np.ndarray, xyz: np.ndarray) -> None:
        k = len(t)
        if self.hi + k > len(self.t):
            n = self.hi - self.lo
            if n + k > len(self.t):
                cap = max(2 * len(self.t), n + k, 256)
                bt, bx = np.empty(cap), np.empty((cap, 3))
            else:
                bt, bx = self.t, self.xyz
            bt[:n] = self.t[self.lo : self.hi]
            bx[:n] = self.xyz[self.lo : self.hi]
            self.t, self.xyz, self.lo, self.hi = bt, bx, 0, n
        self.t[self.hi : self.hi + k] = t
        self.xyz[self.hi : self.hi + k] = xyz
        self.hi += k
        self.last_t = float(t[-1])

    def pending(self) -> tuple[np.ndarray, np.ndarray]:
        return self.t[self.lo : self.hi].copy(), self.xyz[self.lo : self.hi].copy()


class HeadingPipeline:
    """Calibrated, interference-aware heading from streaming accelerometer, gyroscope and magnetometer.

    Parameters
    ----------
    settings : PipelineSettings, optional
    calibration : MagCalibration, optional
        A device calibration (from ``pdr-mag calibrate``); None starts uncalibrated (online only).
    meta : dict, optional
        Recording metadata (``latitude_deg``, ``longitude_deg``, ``altitude_m``, ``date``): with position
        and date, the WMM gives the reference field and the heading is true north.
    fusion : object, optional
        A fusion core to use instead of :class:`pdr_mag.attitude.FusionCore` (same interface; for tests).

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
    ):
        if calibration is not None and not isinstance(calibration, MagCalibration):
            raise ValueError(
                f"calibration: expected a MagCalibration or None, got {type(calibration).__name__}"
            )
        if meta is not None and not isinstance(meta, dict):
            raise ValueError(f"meta: expected a dict or None, got {type(meta).__name__}")
        self.settings = settings or PipelineSettings()
        self.meta = dict(meta or {})
        try:
            self.field: EarthField | None = earth_field_from_meta(self.meta)
        except ValueError as exc:
            raise ValueError(f"meta: {exc}") from exc
        from pdr_mag.attitude import FusionCore

        if fusion is None:
            fusion = FusionCore(self.settings.fusion or _default_fusion_settings(), self.field)
        self.fusion = fusion
        # a FusionCore's entry for checked input (the rows get the calibration state too); else process()
        self._fusion_run = fusion._run if type(fusion) is FusionCore else None
        f = self.field
        self.online = OnlineCalibrator(
            self.settings.online_settings,
            calibration,
            strength=None if f is None else f.strength,
            sin_dip=None if f is None else float(np.sin(np.radians(f.inclination_deg))),
        )
        self._streams = {k: _Stream() for k in KINDS}
        self._stream_list = tuple(self._streams.values())  # in kind order
        self._done_t = -np.inf  # everything before this time has been processed
        self._cur_blk: float | None = None  # index of the block the last fused piece belonged to
        self._span = (
            _SPAN_MIN  # blocks in the next speculative span (speed only: results do not depend on it)
        )
        self._pend: list[np.ndarray] = []  # magnetometer rows (t, raw, up, rate) of the open block
        self._coverage = 0.0
        self._up_acc = np.full(3, np.nan)
        self._rate = np.zeros(1)
        self.dropped: Counter = Counter()
        self._out: list[EstimateBatch] = []
        self._events: list[Event] = []
        self._magcal: list[tuple[np.ndarray, np.ndarray]] = []
        self._interf = False
        self._up = np.array([np.nan, np.nan, np.nan])
        self._calibrations: list[tuple[float, MagCalibration]] = []
        self._cal_mats: tuple = (None,)  # (calibration, offset, matrix transposed) of _apply
        self._n_out = 0
        self._t_first = np.nan
        self._t_last = np.nan
        self._sync_fusion_reference()

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
        self.push_arrays(kind, np.array([t], dtype=float), np.asarray(xyz, dtype=float).reshape(1, 3))

    def push_arrays(self, kind, t, xyz) -> None:
        """Push a chunk of one stream: times (N,) s and values (N, 3) in the contract's units.

        Rows with NaN, and times not after the stream's previous sample, are dropped and counted.
        """
        name = kind if type(kind) is str and kind in KINDS else _kind_name(kind)
        t = np.asarray(t, dtype=float).reshape(-1)
        xyz = np.asarray(xyz, dtype=float)
        if xyz.ndim != 2 or xyz.shape != (len(t), 3):
            raise ValueError(f"xyz: expected shape ({len(t)}, 3) for {len(t)} times, got {xyz.shape}")
        if not len(t):
            return
        s = self._streams[name]
        # the common case: finite, strictly increasing, after everything pushed and processed (copied in
        # place when the buffer has room)
        code = PK.append_in_order(s.t, s.xyz, s.hi, t, xyz, s.last_t, self._done_t)
        if code:
            if code == 1:
                s.hi += len(t)
                s.last_t = float(t[-1])
            else:
                s.append(t, xyz)
            if self._n_pending() > self.settings.max_pending:
                self._process(self._safe_horizon())
            return
        good = np.isfinite(t) & np.all(np.isfinite(xyz), axis=1)
        if not np.all(good):
            self.dropped[f"{name}:nan"] += int(np.count_nonzero(~good))
            t, xyz = t[good], xyz[good]
        if len(t):
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
            s.append(t, xyz)
        if self._n_pending() > self.settings.max_pending:
            self._process(self._safe_horizon())

    def _n_pending(self) -> int:
        a, g, m = self._stream_list
        return a.hi - a.lo + g.hi - g.lo + m.hi - m.lo

    # ------------------------------------------------------------------ output
    def poll(self) -> EstimateBatch:
        """Process what can be processed and return the estimates produced since the last poll."""
        self._process(self._poll_horizon())
        return self._take_out()

    def _poll_horizon(self) -> float:
        a, g, m = self._stream_list
        h = min(a.last_t, g.last_t, m.last_t)
        newest = max(a.last_t, g.last_t, m.last_t)
        if math.isfinite(newest):
            h = max(h, newest - self.settings.max_lag_s)
        return h

    def flush(self) -> EstimateBatch:
        """Process everything pending (end of stream) and return the remaining estimates."""
        self._process(np.inf, final=True)
        return self._take_out()

    def pop_events(self) -> list[Event]:
        """Events since the last call (interference_start/_end, calibration_accepted/_rejected,
        recalibration_requested, recalibrated, rotation_episode_start/_end)."""
        ev, self._events = self._events, []
        return ev

    def pop_mag_calibrated(self) -> tuple[np.ndarray, np.ndarray]:
        """Calibrated magnetometer samples (t, xyz) since the last call (``keep_mag_calibrated``)."""
        if not self._magcal:
            return np.empty(0), np.empty((0, 3))
        t = np.concatenate([a for a, _ in self._magcal])
        x = np.concatenate([b for _, b in self._magcal])
        self._magcal = []
        return t, x

    def run(self, streams: dict) -> EstimateBatch:
        """Batch convenience: ``{"accel": (t, xyz), ...}`` all at once → every estimate (a loop over push)."""
        for name, (t, xyz) in streams.items():
            self.push_arrays(name, t, xyz)
        self._process(self._poll_horizon())  # poll, then flush: the rows of both concatenated once
        self._process(np.inf, final=True)
        out, self._out = self._out, []
        return EstimateBatch.concat(out)

    def _take_out(self) -> EstimateBatch:
        out, self._out = self._out, []
        return EstimateBatch.concat(out) if len(out) != 1 else out[0]

    # ------------------------------------------------------------------ merge + blocks
    def _safe_horizon(self) -> float:
        return min(s.last_t for s in self._streams.values())

    def _process(self, horizon: float, final: bool = False) -> None:
        """Fuse every pending sample before ``horizon`` (all of them when ``final``); a block whose end the
        horizon has passed is closed (online calibration update).

        Fusion runs speculatively over spans of ``_SPAN_MIN`` … ``_SPAN_MAX`` blocks with the calibration in
        use at
        the span's start (one call into the compiled filter instead of one per block).  The blocks are then
        closed in order; when a close changes the calibration, the filter is put back to its state at the
        span's start and re-run up to that block boundary (the same rows: the filter's output does not
        depend on how its input is cut), and a new span starts there with the new calibration.  The result
        is that of fusing block by block.
        """
        b = self.settings.block_s
        if final:
            t_end = np.inf
        else:
            if not np.isfinite(horizon) or horizon <= self._done_t:
                return
            t_end = horizon
        # each stream's samples before t_end, merged in time order, ties in kind order: accel < gyro < mag
        sa, sg, sm = self._stream_list
        sa.lo, sg.lo, sm.lo, kind, t, xyz, blk = PK.take_merge3(
            sa.t, sa.xyz, sa.lo, sa.hi, sg.t, sg.xyz, sg.lo, sg.hi, sm.t, sm.xyz, sm.lo, sm.hi, t_end, b
        )
        if not final:
            self._done_t = t_end
        if len(t):
            if final:
                self._done_t = max(self._done_t, float(t[-1]))
            i, n = 0, len(t)
            while i < n:
                if self._cur_blk is not None and blk[i] > self._cur_blk:
                    self._close_block()
                self._cur_blk = float(blk[i])
                i += self._fuse_span(kind[i:], t[i:], xyz[i:], blk[i:])
        if self._cur_blk is not None and (final or (self._cur_blk + 1) * b <= t_end):
            self._close_block()

    def _fuse_span(self, kind: np.ndarray, t: np.ndarray, xyz: np.ndarray, blk: np.ndarray) -> int:
        """Fuse a span starting at the first of these samples (see :meth:`_process`), closing the blocks
        inside it; returns the number of samples fused for good."""
        cal = self.online.calibration
        state = self.online.cal_state
        off = self._offset_only(cal)
        e, lo, hi, mag_lo, mag_hi, data, allowed, n_gyro = PK.span_start(
            blk, kind, xyz, self._span, off if off is not None else _NO_OFFSET, cal is not None
        )
        kind, t, xyz, blk = kind[:e], t[:e], xyz[:e], blk[:e]
        if cal is not None and off is None:
            data = self._calibrated(cal, kind, xyz)
        n_p = len(lo)
        # filter snapshots at the span's start and (long spans) every _SNAP_EVERY pieces: what a calibration
        # change inside the span puts back before re-running the filter up to the change
        snap_at = lo[_SNAP_EVERY::_SNAP_EVERY] if n_p > 2 * _SNAP_EVERY else lo[:0]
        snap = self.fusion._snapshot() if n_p > 1 else None
        if self._fusion_run is not None:  # FusionCore: the input is checked, the rows get the state
            batch = self._fusion_run(kind, t, data, allowed, snap_at, n_gyro, state)
        else:
            batch = (
                self.fusion.process(kind, t, data, allowed, snapshot_at=snap_at)
                if len(snap_at)
                else self.fusion.process(kind, t, data, allowed)
            )
        snaps = self.fusion.snapshots if len(snap_at) else []
        # rows (one per output gyro sample) of each block-piece
        piece_ev: list = []  # (piece, source, Event): the order of block-by-block processing
        covs = np.full(n_p, self._coverage)
        n_pieces = n_p
        if self.settings.online:
            row_hi, ctx = PK.span_context(
                kind, t, xyz, hi, batch.t, batch.q_wd, self._up, self._up_acc, self._rate
            )
        else:
            row_hi, ctx = PK.rows_before(batch.t, t, hi), None
        if ctx is not None and n_p > 1:
            # close every block but the last: the open block's earlier samples, then the span's
            pre = np.concatenate(self._pend) if self._pend else np.empty((0, PK.N_CTX))
            self._pend = []
            n_rows_c, last, has, ends, piece_of_row, ok, r_t, r_mag, r_up, r_rate = PK.close_span(
                pre, ctx, mag_lo, mag_hi
            )
            before = self.online.calibration
            if ok:  # the common case: contiguous and finite, as update_blocks would make them
                events, n_done, cov = self.online.update_blocks(r_t, r_mag, r_up, r_rate, ends)
            else:
                rows = np.concatenate([pre, ctx[: mag_hi[-2]]]) if len(pre) else ctx[: mag_hi[-2]]
                r_t = rows[:, 0]
                events, n_done, cov = self.online.update_blocks(
                    rows[:, 0], rows[:, 1:4], rows[:, 4:7], rows[:, 7], ends
                )
            if n_rows_c:
                for r, (te, k, d) in events:
                    piece_ev.append((int(piece_of_row[r]), 1, Event(te, k, d)))
                # coverage after each closed block with samples, carried over the pieces without
                covs = PK.piece_coverage(cov, last, has, self._coverage)
                if self.online.calibration is not before:
                    q = int(piece_of_row[n_done - 1])
                    n_pieces = q + 1
                    self._coverage = float(covs[q + 1])
                    if self.online.calibration is not None:
                        self._calibrations.append((float(r_t[n_done - 1]), self.online.calibration))
                else:
                    self._coverage = float(covs[-1])
            self._cur_blk = float(blk[lo[n_pieces]] if n_pieces < n_p else blk[lo[-1]])
        elif n_p > 1:
            self._cur_blk = float(blk[lo[-1]])
        end = int(hi[n_pieces - 1])
        if end < e:
            # the calibration changed at a block boundary inside the span: redo the filter up to there from
            # the latest snapshot before it
            j = int(np.searchsorted(snap_at, end, side="right"))
            start = int(snap_at[j - 1]) if j else 0
            self.fusion._restore(snaps[j - 1] if j else snap)
            if end > start:
                self.fusion.process(kind[start:end], t[start:end], data[start:end], allowed[start:end])
            self._sync_fusion_reference()
            self._span = _SPAN_MIN
        else:
            if ctx is not None and mag_hi[-1] > mag_lo[-1]:
                self._pend.append(ctx[mag_lo[-1] : mag_hi[-1]])
            if n_p == self._span:
                self._span = min(2 * self._span, _SPAN_MAX)
        n_rows = int(row_hi[n_pieces - 1])
        if ctx is not None:
            PK.carry_context(kind, xyz, end, batch.q_wd, n_rows, self._up, self._up_acc, self._rate)
        if n_rows:
            if n_rows < len(batch):
                batch = _head(batch, n_rows)
            # the calibration (hence cal_state) is the span start's in every piece kept
            if self._fusion_run is None:
                batch.cal_state = np.full(n_rows, state, dtype="<U13")
            batch.diag["coverage"] = PK.rows_coverage(covs, row_hi, n_pieces)
            for r, ev in self._interference_events(batch):
                piece_ev.append((int(np.searchsorted(row_hi, r, side="right")), 0, ev))
            self._n_out += n_rows
            self._out.append(batch)
        if piece_ev:
            piece_ev.sort(key=lambda x: (x[0], x[1]))
            self._events += [ev for _, _, ev in piece_ev]
        if not math.isfinite(self._t_first):
            self._t_first = float(t[0])
        self._t_last = float(t[end - 1])
        if self.settings.keep_mag_calibrated and cal is not None:
            m = kind[:end] == 2
            if np.any(m):
                self._magcal.append((t[:end][m].copy(), data[:end][m].copy()))
        return end

    def _close_block(self) -> None:
        """End of a block: the online calibrator sees the block's magnetometer samples."""
        if self._pend:
            p = np.concatenate(self._pend)
            self._pend = []
            before = self.online.calibration
            for te, k, d in self.online.update(p[:, 0], p[:, 1:4], p[:, 4:7], p[:, 7]):
                self._events.append(Event(te, k, d))
            self._coverage = self.online.coverage()
            if self.online.calibration is not before and self.online.calibration is not None:
                self._calibrations.append((float(p[-1, 0]), self.online.calibration))
                self._sync_fusion_reference()

    def _calibrated(self, cal: MagCalibration | None, kind: np.ndarray, xyz: np.ndarray) -> np.ndarray:
        """The merged samples with the magnetometer's calibrated by :meth:`MagCalibration.apply` (NaN
        without a calibration); the calibration's matrices are kept while it stays the same."""
        if cal is None:
            data = xyz.copy()
            data[kind == 2] = np.nan
            return data
        _, off, a_t, eye = self._cal_matrices(cal)
        if eye:
            return PK.minus_offset(kind, xyz, off)
        data = xyz.copy()
        is_mag = kind == 2
        data[is_mag] = (xyz[is_mag] - off) @ a_t
        return data

    def _cal_matrices(self, cal: MagCalibration) -> tuple:
        """``(cal, offset, matrix transposed, whether it is the identity)``, kept while ``cal`` stays."""
        if self._cal_mats[0] is not cal:
            a = cal.soft_iron_array
            if cal.mag_to_imu is not None:
                a = np.asarray(cal.mag_to_imu, dtype=float) @ a
            eye = bool(np.all(a == np.eye(3)))  # offset only: (m − b) @ I is m − b
            self._cal_mats = (cal, cal.offset_array, a.T, eye)
        return self._cal_mats

    def _offset_only(self, cal: MagCalibration | None) -> np.ndarray | None:
        """The offset of an offset-only calibration (None without one or with a matrix)."""
        if cal is None:
            return None
        _, off, _, eye = self._cal_matrices(cal)
        return off if eye else None

    def _interference_events(self, batch: EstimateBatch) -> list[tuple[int, Event]]:
        """Flag changes in these rows, as (row, event)."""
        out = []
        flags = np.asarray(batch.interference, dtype=bool)
        if PK.all_equal(flags, self._interf):
            return out  # no change (the common case)
        prev = np.empty_like(flags)
        prev[0] = self._interf
        prev[1:] = flags[:-1]
        for i in np.flatnonzero(flags != prev):
            kind = "interference_start" if flags[i] else "interference_end"
            data = {}
            for key in ("field_strength_uT", "dip_deg", "interference_score"):
                v = batch.diag.get(key)
                if v is not None and np.isfinite(v[i]):
                    data[key] = round(float(v[i]), 3)
            out.append((int(i), Event(float(batch.t[i]), kind, data)))
        self._interf = bool(flags[-1])
        return out

    def _sync_fusion_reference(self) -> None:
        cal = self.online.calibration
        if cal is not None and np.isfinite(cal.field_uT) and cal.field_uT > 0:
            if not self._calibrations:
                self._calibrations.append((-np.inf, cal))
            self.fusion.set_reference_strength(float(cal.field_uT))

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
        polled are not — poll them first."""
        pend = {}
        for name, s in self._streams.items():
            t, x = s.pending()
            pend[name] = {"t": t.tolist(), "xyz": x.tolist(), "last_t": state_float(s.last_t)}
        st = {
            "version": STATE_VERSION,
            "pending": pend,
            "done_t": state_float(self._done_t),
            "dropped": dict(self.dropped),
            "interf": self._interf,
            "up": [state_float(v) for v in self._up],
            "up_acc": [state_float(v) for v in self._up_acc],
            "rate": state_float(self._rate[0]),
            "cur_blk": None if self._cur_blk is None else self._cur_blk,
            "pend": [
                [state_float(v) for v in row] for row in (np.concatenate(self._pend) if self._pend else [])
            ],
            "coverage": self._coverage,
            "n_out": self._n_out,
            "t_first": state_float(self._t_first),
            "t_last": state_float(self._t_last),
            "calibrations": [[state_float(t), c.to_dict()] for t, c in self._calibrations],
            "fusion": self.fusion.get_state(),
            "online": self.online.get_state(),
        }
        json.dumps(st)  # fail here, not at the caller's, if something is not serialisable
        return st

    def set_state(self, state: dict) -> None:
        """Restore from :meth:`get_state` (ValueError when the dict is not such a state)."""
        if not isinstance(state, dict) or state.get("version") != STATE_VERSION:
            raise ValueError(f"state: expected a HeadingPipeline state of version {STATE_VERSION}")
        try:
            for name, s in self._streams.items():
                p = state["pending"][name]
                t = np.asarray(p["t"], dtype=float)
                x = np.asarray(p["xyz"], dtype=float).reshape(-1, 3)
                s.t, s.xyz, s.lo, s.hi = t, x, 0, len(t)
                s.last_t = float(p["last_t"])
            self._done_t = float(state["done_t"])
            self.dropped = Counter(state["dropped"])
            self._interf = bool(state["interf"])
            self._up = np.asarray([float(v) for v in state["up"]])
            self._up_acc = np.asarray([float(v) for v in state["up_acc"]])
            self._rate = np.array([float(state["rate"])])
            self._cur_blk = None if state["cur_blk"] is None else float(state["cur_blk"])
            pend = np.asarray([[float(v) for v in row] for row in state["pend"]], dtype=float)
            self._pend = [pend.reshape(-1, 8)] if len(pend) else []
            self._coverage = float(state["coverage"])
            self._n_out = int(state["n_out"])
            self._t_first = float(state["t_first"])
            self._t_last = float(state["t_last"])
            self._calibrations = [(float(t), MagCalibration.from_dict(c)) for t, c in state["calibrations"]]
            self.fusion.set_state(state["fusion"])
            self.online.set_state(state["online"])
        except (KeyError, TypeError) as exc:
            raise ValueError(f"state: malformed ({exc!r})") from exc
        self._out, self._events, self._magcal = [], [], []


def _head(batch: EstimateBatch, n: int) -> EstimateBatch:
    """The first ``n`` rows of a batch."""
    return EstimateBatch(
        t=batch.t[:n],
        q_wd=batch.q_wd[:n],
        heading_deg=batch.heading_deg[:n],
        heading_std_deg=batch.heading_std_deg[:n],
        mag_used=batch.mag_used[:n],
        interference=batch.interference[:n],
        cal_state=batch.cal_state[:n],
        diag={k: v[:n] for k, v in batch.diag.items()},
    )


def _kind_name(kind) -> str:
    if isinstance(kind, str):
        if kind not in KINDS:
            raise ValueError(f"kind: expected one of {sorted(KINDS)}, got {kind!r}")
        return kind
    try:
        return _NAMES[int(kind)]
    except (KeyError, TypeError, ValueError):
        raise ValueError(f"kind: expected 'accel', 'gyro', 'mag' or 0/1/2, got {kind!r}") from None


