"""rerun output: a recording (``.rrd`` file or live viewer) laid out for debugging heading drift.

Entities (timeline ``time``: the recording's clock as a duration, ``round(t·1e9)`` ns; negative t is fine)
--------------------------------------------------------------------------------------------------
``heading/ours``, ``heading/truth``, ``heading/gyro_only``, ``heading/os``
    heading, deg clockwise from north (ours; ``reference("truth")``; diag ``gyro_heading_deg``;
    ``reference("os")``), drawn as points so the 0/360 wrap draws no vertical lines.  ``heading/ours``
    holds the rows from the first magnetometer correction on (``mag_used``); the rows before it, whose
    heading is arbitrary, are ``heading/unreferenced``.
``heading_std/ours``
    1-σ heading uncertainty, deg.
``heading_error/ours``, ``heading_error/gyro_only``, ``heading_error/os``
    heading minus the truth (interpolated), wrapped to [−180, 180) deg — where drift shows directly; only
    when ``reference("truth")`` came before the series (as the replay sends it); ours and gyro only from the
    first magnetometer correction on; the phone's as points (its wraps draw no strokes).
``heading_error/{plus,minus}_{1,2}sigma``
    ±σ and ±2σ of our heading around zero (from the first correction on): the error reads against them.
one group per interference detector (:data:`pdr_mag.fusion.detectors.PLOTS`)
    ``field/strength``, ``field/reference``, ``field/lower``, ``field/upper``: |calibrated field| with the
    detector's reference and the accepted band (reference ∓ tolerance), µT; ``dip/measured``,
    ``dip/reference``, ``dip/lower``, ``dip/upper``: dip angle with the reference inclination and its band,
    deg; ``variance/strength``: the strength's windowed variance, µT²; ``consistency/angle``: the
    gyro-consistency angle, deg.
``detector/score``, ``detector/threshold``
    interference score (≥ 1 flags) and the threshold 1.
``mag_use/share``
    the magnetometer's use per second of the recording clock: corrections in the second × the fusion's
    ``MagSettings.interval_s`` (``meta["mag_interval_s"]``; else the shortest gap between corrections seen),
    over the second's covered time, at most 1; drawn at the middle of the second.
``state/drift``, ``state/interference``, ``state/mag_calibration``, ``state/magnetometer``, ``state/rotation``
    :class:`rerun.StateChange` lanes with fixed colours (:mod:`pdr_mag.sinks._rerun_layout`), in this
    (alphabetical, the viewer's) order: the drift episodes of the replay (``drift_episode`` events; where
    several overlap, the worst kind — error, then σ, then no reference), the interference flag, the
    calibration state, the magnetometer's share as ``used`` (≥ ½), ``partly``, ``not used``, the online
    calibrator's rotation episodes; written only where the state changes.
``coverage/online``, ``coverage/calibration``
    orientation coverage of the online buffer (diag ``coverage``) and of each calibration, [0, 1].
``mag/raw``, ``mag/calibrated``
    the 3-D cloud of raw and calibrated magnetometer samples, µT, decimated to ``cloud_rate_hz``.
``mag/fit/ellipsoid``, ``mag/fit/sphere``
    at each calibration: the fitted surface in raw space (centre = offset, axes from ``soft_iron``:
    ``|S (m − b)| = R`` ⇔ ``m = b + V diag(R/λ) u`` with ``S = V diag(λ) Vᵀ``, ``|u| = 1``) and the sphere of
    radius ``field_uT`` round the origin that the calibrated cloud should lie on; the 3-D view shows the
    latest at the cursor.
``inputs/accel/{x,y,z}``, ``inputs/gyro/{x,y,z}``, ``inputs/mag/{x,y,z}``
    the raw inputs (one plot per sensor).
``estimates/gyro_bias/{x,y,z}``, ``estimates/offset_error/{x,y,z}``
    what the filter has learnt that turns the heading between magnetometer corrections: its gyro bias
    estimate (°/s, device frame; diag ``gyro_bias_*``) and the calibration's offset error it found (µT,
    device frame, the field it takes being the calibrated one less it; diag ``mag_offset_error_*``).
``events``
    :class:`rerun.TextLog` — pipeline events, one line per calibration (the ``calibration_accepted`` /
    ``recalibrated`` event and the calibration itself make one line) and one per drift episode, at its
    start (clicking a line moves the time cursor there).

The default blueprint (:func:`pdr_mag.sinks._rerun_layout.drift_blueprint`) is sent when the sink closes,
with the time and y ranges fitted to what was written (:class:`pdr_mag.sinks._rerun_layout.PlotRanges`); a
live viewer gets it also at the start, without the fitted ranges.

Every series goes out with columnar :meth:`rerun.RecordingStream.send_columns` calls, buffered per entity
up to ``chunk_rows`` rows (bounded memory, few large sends); nothing is logged row by row.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import rerun as rr
from scipy.spatial.transform import Rotation

from pdr_mag.conventions import heading_deg_from_quat, wrap_deg
from pdr_mag.episodes import Episode
from pdr_mag.estimates import diag_vectors
from pdr_mag.fusion.detectors import BANDS, PLOTS
from pdr_mag.fusion.rows import GYRO_BIAS_COLUMNS, OFFSET_ERROR_COLUMNS
from pdr_mag.sinks import WARNING_EVENTS
from pdr_mag.sinks._rerun_layout import (
    BLUE,
    CAL_COLOR,
    CLOUD_RADIUS_UI,
    GREEN,
    RAW_COLOR,
    RAW_FIT_COLOR,
    RED,
    REJECTED_COLOR,
    SERIES,
    SPHERE_COLOR,
    STATE_LABELS,
    STATES,
    PlotRanges,
    drift_blueprint,
)

__all__ = ["RerunSink", "drift_blueprint", "WARNING_EVENTS"]

#: The event log's words for where a ``stream_gap`` ends.
_GAP_UNTIL = {"start": "its first sample", "end": "the recording's end"}


def _duration_ns(t: np.ndarray) -> np.ndarray:
    """Seconds → ``timedelta64[ns]``, rounded like MCAP's ``round(t·1e9)`` (rerun itself truncates)."""
    return np.round(np.asarray(t, dtype=float) * 1e9).astype(np.int64).astype("timedelta64[ns]")


#: events that announce a calibration the sink also receives through ``calibration()``: one line for both.
_CALIBRATION_EVENTS = ("calibration_accepted", "recalibrated")
#: diagnostic column → entity: the gyro-only heading, each detector's value (and reference, for a band), the
#: score, the online buffer's coverage.
_DIAG_SERIES = (
    ("gyro_heading_deg", "heading/gyro_only"),
    *((p.column, f"{p.group}/{p.leaf}") for p in PLOTS.values()),
    *((band.reference, f"{PLOTS[name].group}/reference") for name, band in BANDS.items()),
    ("interference_score", "detector/score"),
    ("coverage", "coverage/online"),
)
#: the filter's estimates drawn per axis: entity group → (diag columns x, y, z, series label, scale to the
#: plotted unit)
_ESTIMATES = {
    "gyro_bias": (GYRO_BIAS_COLUMNS, "gyro bias", float(np.degrees(1.0))),
    "offset_error": (OFFSET_ERROR_COLUMNS, "offset error", 1.0),
}
#: drift lane priority where episodes overlap (worst first).
_DRIFT_ORDER = ("error", "sigma", "no_reference")
#: strips drawn inside the error plot (exactly on its time axis): (lane, its state, strip entity, height as a
#: fraction of the plot's half-height).
_STRIPS = (
    ("state/interference", "interference", "heading_error/strip_interference", -0.93),
    ("state/magnetometer", "not used", "heading_error/strip_no_magnetometer", -0.86),
)
_STRIP_LANES = tuple(x[0] for x in _STRIPS)
#: drift strips, one row each at the top: error, σ, no reference.
_DRIFT_STRIP_Y = (0.93, 0.86, 0.79)
#: σ histogram for the error plot's range: 0.25° bins up to 180°.
_STD_BIN_DEG = 0.25


@dataclass
class _Second:
    """The rows of one second of the recording clock, for the magnetometer's share of it."""

    second: float
    t_first: float
    t_last: float = np.nan
    rows: int = 0
    used: int = 0


class RerunSink:
    """Write a replay to a rerun ``.rrd`` file and/or a live viewer, with the drift blueprint.

    Parameters
    ----------
    path : str or Path or None
        The ``.rrd`` file; None for a live viewer only.
    spawn : bool
        Start (or connect to) a rerun viewer and stream to it; with ``path`` too, both receive the data.
    chunk_rows : int
        Rows buffered per entity before a columnar send.
    cloud_rate_hz : float
        Rate at which magnetometer samples enter the 3-D cloud (decimation), Hz.
    application_id : str
        The rerun application id.
    """

    def __init__(
        self,
        path=None,
        *,
        spawn: bool = False,
        chunk_rows: int = 20_000,
        cloud_rate_hz: float = 5.0,
        application_id: str = "pdr_mag",
    ):
        if path is None and not spawn:
            raise ValueError("path: give an .rrd file to write, or spawn=True for a live viewer")
        if int(chunk_rows) < 1:
            raise ValueError(f"chunk_rows: expected a positive row count, got {chunk_rows!r}")
        if not cloud_rate_hz > 0:
            raise ValueError(f"cloud_rate_hz: expected a positive rate in Hz, got {cloud_rate_hz!r}")
        self.path = None if path is None else Path(path)
        self.spawn = bool(spawn)
        self.chunk_rows = int(chunk_rows)
        self.cloud_rate_hz = float(cloud_rate_hz)
        self.application_id = application_id
        self._rec = None
        self._buf: dict[str, list] = {}  # entity → [kind, [t arrays], [value arrays], rows]
        self._last_state: dict[str, str] = {}
        self._changes: dict[str, list] = {e: [] for e in _STRIP_LANES}  # lane → [(t, state)] for the strips
        self._cloud_bin: dict[str, float] = {}
        self._truth: tuple[list, list] | None = None  # (t chunks, heading chunks) for the error curves
        self._truth_unwrapped: tuple[np.ndarray, np.ndarray] | None = None
        self._referenced = False  # a magnetometer correction has been seen
        self._mag_interval = np.nan  # the fusion's MagSettings.interval_s (meta), else inferred
        self._min_used_gap = np.inf
        self._last_used_t = np.nan
        self._second: _Second | None = None  # the second whose magnetometer share is being counted
        self._pending_cal_event = None
        self._episodes: list[tuple[float, float, str]] = []
        # what the blueprint's axes are fitted to
        self._t_span = [np.inf, -np.inf]
        self._err_max = 0.0
        self._std_hist = np.zeros(int(180.0 / _STD_BIN_DEG) + 1, dtype=np.int64)
        self._band_span = {p.group: [np.inf, -np.inf] for name, p in PLOTS.items() if name in BANDS}
        self.rows_sent: dict[str, int] = {}

    # ------------------------------------------------------------------ Sink protocol
    def open(self, meta: dict) -> None:
        rec = rr.RecordingStream(self.application_id)
        if self.spawn and self.path is not None:
            rec.spawn(connect=False)
            self.path.parent.mkdir(parents=True, exist_ok=True)
            rec.set_sinks(rr.FileSink(str(self.path)), rr.GrpcSink(), default_blueprint=drift_blueprint())
        elif self.spawn:
            rec.spawn(default_blueprint=drift_blueprint())
        else:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            rec.save(self.path)  # the blueprint goes out at close, fitted to the data
        self._rec = rec
        meta = dict(meta or {})
        interval = meta.get("mag_interval_s")
        if isinstance(interval, (int, float)) and interval > 0:
            self._mag_interval = float(interval)
        name = meta.get("source") or (self.path.stem if self.path else "pdr_mag replay")
        rec.send_recording_name(Path(str(name)).name or str(name))
        props = {str(k): str(v) for k, v in meta.items() if v is not None}
        if props:
            rec.send_property("recording", rr.AnyValues(**props))
        for entity, (label, color, points, size) in SERIES.items():
            if points:
                style = rr.SeriesPoints(colors=[color], names=[label], marker_sizes=[size])
            else:
                style = rr.SeriesLines(colors=[color], names=[label], widths=[size])
            rec.log(entity, style, static=True)
        for entity, colors in STATES.items():
            values = list(colors)
            rec.log(
                entity,
                rr.StateConfiguration(
                    values=values,
                    labels=[STATE_LABELS.get(v, v) for v in values],
                    colors=[colors[v] for v in values],
                ),
                static=True,
            )
        for kind in ("accel", "gyro", "mag"):
            for axis, color in zip("xyz", (RED, GREEN, BLUE), strict=True):
                style = rr.SeriesLines(colors=[color], names=[f"{kind} {axis}"])
                rec.log(f"inputs/{kind}/{axis}", style, static=True)
        for group, (_, label, _) in _ESTIMATES.items():
            for axis, color in zip("xyz", (RED, GREEN, BLUE), strict=True):
                style = rr.SeriesLines(colors=[color], names=[f"{label} {axis}"])
                rec.log(f"estimates/{group}/{axis}", style, static=True)
        radius = rr.Radius.ui_points(CLOUD_RADIUS_UI)
        rec.log("mag/raw", rr.Points3D.from_fields(colors=[RAW_COLOR], radii=[radius]), static=True)
        rec.log("mag/calibrated", rr.Points3D.from_fields(colors=[CAL_COLOR], radii=[radius]), static=True)

    def inputs(self, kind: str, t: np.ndarray, xyz: np.ndarray) -> None:
        if kind not in ("accel", "gyro", "mag"):
            raise ValueError(f"kind: expected 'accel', 'gyro' or 'mag', got {kind!r}")
        t = np.asarray(t, dtype=float)
        xyz = np.asarray(xyz, dtype=float).reshape(len(t), 3)
        self._span(t)
        for i, axis in enumerate("xyz"):
            self._push_scalar(f"inputs/{kind}/{axis}", t, xyz[:, i])
        if kind == "mag":
            self._push_cloud("mag/raw", t, xyz)

    def mag_calibrated(self, t: np.ndarray, xyz: np.ndarray) -> None:
        t = np.asarray(t, dtype=float)
        self._push_cloud("mag/calibrated", t, np.asarray(xyz, dtype=float).reshape(len(t), 3))

    def estimates(self, batch) -> None:
        if len(batch) == 0:
            return
        t = np.asarray(batch.t, dtype=float)
        self._span(t)
        used = np.asarray(batch.mag_used, dtype=bool)
        ref = np.full(len(t), self._referenced)
        if not self._referenced and used.any():
            ref[int(np.argmax(used)) :] = True
            self._referenced = True
        heading = np.asarray(batch.heading_deg, dtype=float)
        std = np.asarray(batch.heading_std_deg, dtype=float)
        self._push_scalar("heading/ours", t[ref], heading[ref])
        self._push_scalar("heading/unreferenced", t[~ref], heading[~ref])
        self._push_scalar("heading_std/ours", t, std)
        tr, sr = t[ref], std[ref]
        for k in (1, 2):
            self._push_scalar(f"heading_error/plus_{k}sigma", tr, k * sr)
            self._push_scalar(f"heading_error/minus_{k}sigma", tr, -k * sr)
        ok = np.isfinite(sr)
        np.add.at(self._std_hist, np.minimum(sr[ok] / _STD_BIN_DEG, len(self._std_hist) - 1).astype(int), 1)
        err = self._push_error("heading_error/ours", tr, heading[ref])
        if len(err):
            self._err_max = max(self._err_max, float(np.max(np.abs(err))))
        d = batch.diag
        if "gyro_heading_deg" in d:
            self._push_error("heading_error/gyro_only", tr, np.asarray(d["gyro_heading_deg"])[ref])
        for key, entity in _DIAG_SERIES:
            if key in d:
                self._push_scalar(entity, t, d[key])
        for group, (columns, _, scale) in _ESTIMATES.items():
            xyz = diag_vectors(batch, columns)
            if xyz is not None:
                for i, axis in enumerate("xyz"):
                    self._push_scalar(f"estimates/{group}/{axis}", t, scale * xyz[:, i])
        for name, band in BANDS.items():
            if band.reference in d and band.tolerance in d:
                group = PLOTS[name].group
                span = self._band_span[group]
                r, w = np.asarray(d[band.reference], dtype=float), np.asarray(d[band.tolerance], dtype=float)
                self._push_scalar(f"{group}/lower", t, r - w)
                self._push_scalar(f"{group}/upper", t, r + w)
                lo, hi = r - 2 * w, r + 2 * w  # the plot shows excursions up to twice the band
                if np.isfinite(lo).any():
                    span[0] = min(span[0], float(np.nanmin(lo)))
                    span[1] = max(span[1], float(np.nanmax(hi)))
        if "interference_score" in d:
            self._push_scalar("detector/threshold", t[[0, -1]], np.ones(2))
        self._push_states("state/interference", t, np.where(batch.interference, "interference", "clean"))
        self._push_states("state/mag_calibration", t, np.asarray(batch.cal_state).astype(str))
        self._mag_share(t, used)

    def reference(self, name: str, t: np.ndarray, q_wd: np.ndarray) -> None:
        t = np.asarray(t, dtype=float)
        if len(t) == 0:
            return
        q = np.asarray(q_wd, dtype=float).reshape(len(t), 4)
        entity = f"heading/{name}"
        if entity not in SERIES and self._rec is not None:
            self._rec.log(entity, rr.SeriesPoints(names=[name], marker_sizes=[1.5]), static=True)
        heading = heading_deg_from_quat(q)
        self._push_scalar(entity, t, heading)
        if name == "truth":
            if self._truth is None:
                self._truth = ([], [])
            self._truth[0].append(t)
            self._truth[1].append(heading)
        else:
            self._push_error(f"heading_error/{name}", t, heading)

    def _push_error(self, entity: str, t: np.ndarray, heading_deg) -> np.ndarray:
        """``heading − truth`` wrapped to [−180, 180) where the truth covers ``t`` (truth interpolated
        linearly on its unwrapped heading); returns what was drawn.  Needs the truth before the series it is
        compared with — the replay sends references first; a series before any truth gets no error curve."""
        if self._truth is None or len(t) == 0:
            return np.empty(0)
        if len(self._truth[0]) > 1:  # truth given in several calls: join once, keep the joined arrays
            tt, hh = np.concatenate(self._truth[0]), np.concatenate(self._truth[1])
            order = np.argsort(tt, kind="stable")
            self._truth = ([tt[order]], [hh[order]])
        tt = self._truth[0][0]
        if self._truth_unwrapped is None or self._truth_unwrapped[0] is not tt:
            self._truth_unwrapped = (tt, np.unwrap(self._truth[1][0], period=360.0))
        hu = self._truth_unwrapped[1]
        inside = (t >= tt[0]) & (t <= tt[-1])
        t = t[inside]
        err = wrap_deg(np.asarray(heading_deg, dtype=float)[inside] - np.interp(t, tt, hu))
        self._push_scalar(entity, t, err)
        return err[np.isfinite(err)]

    def event(self, ev) -> None:
        kind = ev.kind
        if kind in _CALIBRATION_EVENTS:
            self._flush_cal_event()
            self._pending_cal_event = ev  # written with the calibration that follows it
            return
        if kind in ("rotation_episode_start", "rotation_episode_end"):
            state = "rotating" if kind.endswith("start") else ""
            self._push("state/rotation", "state", np.array([float(ev.t)]), np.array([state]))
        if kind == "drift_episode":
            d = ev.to_dict()
            ep = Episode.from_dict({**d, "kind": d["episode"], "t_start": d["t"]})
            self._episodes.append((ep.t_start, ep.t_end, ep.kind))
            text = "drift episode: " + ep.describe()
        elif kind == "stream_gap":
            d = ev.data
            until = _GAP_UNTIL.get(d["where"], "its next sample")
            text = f"stream gap: no {d['stream']} sample for {d['duration_s']:.1f} s, until {until}"
        else:
            details = {k: v for k, v in ev.to_dict().items() if k not in ("t", "kind")}
            text = kind + ("" if not details else " " + ", ".join(f"{k}={v}" for k, v in details.items()))
        self._log_text(float(ev.t), text, "WARN" if kind in WARNING_EVENTS else "INFO")

    def calibration(self, t: float, cal) -> None:
        t = float(t)
        rec = self._require()
        time = [rr.TimeColumn("time", duration=_duration_ns(np.array([t])))]
        r = float(cal.field_uT)
        if np.isfinite(r) and r > 0:
            lam, v = np.linalg.eigh(np.asarray(cal.soft_iron, dtype=float))
            if np.linalg.det(v) < 0:
                v[:, 2] = -v[:, 2]
            if np.all(lam > 0):
                quat = Rotation.from_matrix(v).as_quat()  # x, y, z, w
                rec.send_columns(
                    "mag/fit/ellipsoid",
                    indexes=time,
                    columns=rr.Ellipsoids3D.columns(
                        centers=[cal.offset],
                        half_sizes=[r / lam],
                        quaternions=[quat],
                        colors=[RAW_FIT_COLOR if cal.accepted else REJECTED_COLOR],
                    ),
                )
            rec.send_columns(
                "mag/fit/sphere",
                indexes=time,
                columns=rr.Ellipsoids3D.columns(
                    centers=[(0.0, 0.0, 0.0)],
                    half_sizes=[(r, r, r)],
                    colors=[SPHERE_COLOR if cal.accepted else REJECTED_COLOR],
                ),
            )
        if np.isfinite(cal.coverage):
            self._push_scalar("coverage/calibration", np.array([t]), np.array([float(cal.coverage)]))
        ev, self._pending_cal_event = self._pending_cal_event, None
        head = "calibration" if ev is None or ev.kind == "calibration_accepted" else ev.kind
        if ev is not None and ev.kind == "recalibrated":
            head += " (after a figure-8)" if ev.data.get("figure8") else " (fallback)"
        text = (
            f"{head}: {cal.method} {'accepted' if cal.accepted else 'rejected'}, "
            f"offset {np.round(cal.offset, 2).tolist()} µT, field {r:.2f} µT, "
            f"residual {cal.residual_rms_uT:.3g} µT, coverage {cal.coverage:.2f}, n {cal.n_samples}"
            + ("" if cal.accepted else f"; reasons: {'; '.join(cal.reasons)}")
        )
        self._log_text(t, text, "INFO" if cal.accepted else "WARN")

    def close(self) -> None:
        if self._rec is None:
            return
        self._flush_cal_event()
        self._mag_share(np.empty(0), np.empty(0, dtype=bool), final=True)
        self._drift_lane()
        self._strips()
        for entity in list(self._buf):
            self._flush(entity)
        rec, self._rec = self._rec, None
        rec.send_blueprint(self.blueprint(), make_active=True, make_default=True)
        try:
            rec.flush()
        except RuntimeError as exc:  # a live viewer that is gone must not cost the replay its outputs
            if not self.spawn:
                raise
            warnings.warn(f"rerun viewer unreachable ({exc}); the data it missed is not shown", stacklevel=2)
        rec.disconnect()

    def blueprint(self):
        """The drift blueprint fitted to what this sink has written so far (:meth:`plot_ranges`)."""
        return drift_blueprint(self.plot_ranges())

    def plot_ranges(self) -> PlotRanges:
        """Time span of everything written; the error plot's half-height ``1.2 · max(max |ours − truth|,
        2 σ₉₀)`` (σ₉₀ the 90th percentile of σ after the first correction), at least 5°, at most 180°; the
        detectors with a band (field strength, dip): their bands widened to twice their tolerance."""
        t = tuple(self._t_span) if np.isfinite(self._t_span).all() else None
        n = self._std_hist.sum()
        s90 = 0.0
        if n:
            s90 = (int(np.searchsorted(np.cumsum(self._std_hist), 0.9 * n)) + 1) * _STD_BIN_DEG
        err = float(np.clip(1.2 * max(self._err_max if self._truth else 0.0, 2 * s90), 5.0, 180.0))
        bands = {group: tuple(span) for group, span in self._band_span.items() if np.isfinite(span).all()}
        return PlotRanges(t=t, error=err, bands=bands, truth=self._truth is not None)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # ------------------------------------------------------------------ derived lanes
    def _mag_share(self, t: np.ndarray, used: np.ndarray, final: bool = False) -> None:
        """The magnetometer's share of each second (``mag_use/share`` and the ``state/magnetometer``
        lane), a second at a time as its rows complete."""
        tu = t[used]
        if len(tu):
            gaps = np.diff(np.r_[self._last_used_t, tu])
            gaps = gaps[np.isfinite(gaps) & (gaps > 0)]
            if len(gaps):
                self._min_used_gap = min(self._min_used_gap, float(gaps.min()))
            self._last_used_t = float(tu[-1])
        sec = np.floor(t)
        out_t, out_share = [], []
        start = 0
        for k in np.flatnonzero(np.diff(sec)) + 1 if len(sec) else []:
            self._share_add(sec[start], t[start:k], used[start:k], out_t, out_share)
            start = k
        if len(sec):
            self._share_add(sec[start], t[start:], used[start:], out_t, out_share, keep_open=True)
        if final and self._second is not None:
            self._share_close(out_t, out_share)
        if out_t:
            ts, share = np.array(out_t), np.array(out_share)
            self._push_scalar("mag_use/share", ts + 0.5, share)
            labels = np.where(share >= 0.5, "used", np.where(share > 0, "partly", "not used"))
            self._push_states("state/magnetometer", ts, labels)

    def _share_add(self, second, t, used, out_t, out_share, keep_open=False) -> None:
        b = self._second
        if b is not None and b.second != second:
            self._share_close(out_t, out_share)
            b = None
        if b is None:
            b = self._second = _Second(float(second), t_first=float(t[0]))
        b.rows += len(t)
        b.used += int(np.count_nonzero(used))
        b.t_last = float(t[-1])
        if not keep_open:
            self._share_close(out_t, out_share)

    def _share_close(self, out_t, out_share) -> None:
        b, self._second = self._second, None
        interval = self._mag_interval if np.isfinite(self._mag_interval) else self._min_used_gap
        if not np.isfinite(interval):
            interval = 0.0
        n = b.rows
        covered = (b.t_last - b.t_first) * n / (n - 1) if n > 1 else 1.0  # rows' span plus one row period
        out_t.append(b.second)
        out_share.append(min(1.0, b.used * interval / max(covered, interval, 1e-9)))

    def _drift_lane(self) -> None:
        """``state/drift`` from the episodes seen: at each time the worst kind of those open, else none."""
        if not self._episodes:
            return
        edges = sorted({x for a, b, _ in self._episodes for x in (a, b)})
        ts, states = [], []
        for lo, hi in zip(edges[:-1], edges[1:], strict=True):
            mid = 0.5 * (lo + hi)
            open_kinds = {k for a, b, k in self._episodes if a <= mid <= b}
            state = next((k for k in _DRIFT_ORDER if k in open_kinds), "")
            if not states or states[-1] != state:
                ts.append(lo)
                states.append(state)
        ts.append(edges[-1])
        states.append("")
        self._push("state/drift", "state", np.array(ts), np.array(states))

    def _strips(self) -> None:
        """Thick segments along the top and bottom of the error plot where a drift episode, the interference
        flag or a second without the magnetometer was, so they share the error's time axis exactly (NaN
        breaks a line: one point at each end of a stretch, a NaN just after it)."""
        half = self.plot_ranges().error
        end = self._t_span[1]
        for lane, state, entity, frac in _STRIPS:
            ch = self._changes[lane]
            spans = [
                (a, ch[i + 1][0] if i + 1 < len(ch) else end) for i, (a, s) in enumerate(ch) if s == state
            ]
            self._push_spans(entity, spans, frac * half)
        for kind, frac in zip(_DRIFT_ORDER, _DRIFT_STRIP_Y, strict=True):
            spans = [(a, b) for a, b, k in self._episodes if k == kind]
            self._push_spans(f"heading_error/strip_drift_{kind}", spans, frac * half)

    def _push_spans(self, entity: str, spans: list, y: float) -> None:
        if not spans:
            return
        t = np.array([[a, b, b + 1e-6] for a, b in spans]).ravel()
        v = np.tile([y, y, np.nan], len(spans))
        self._push(entity, "scalar", t, v)

    def _flush_cal_event(self) -> None:
        """A calibration event whose calibration never came: its own line."""
        ev, self._pending_cal_event = self._pending_cal_event, None
        if ev is not None:
            details = {k: v for k, v in ev.to_dict().items() if k not in ("t", "kind")}
            text = ev.kind + " " + ", ".join(f"{k}={v}" for k, v in details.items())
            self._log_text(float(ev.t), text, "INFO")

    # ------------------------------------------------------------------ buffering
    def _require(self):
        if self._rec is None:
            raise RuntimeError("RerunSink: open() must be called before writing (and not after close())")
        return self._rec

    def _span(self, t: np.ndarray) -> None:
        if len(t):
            self._t_span[0] = min(self._t_span[0], float(t[0]))
            self._t_span[1] = max(self._t_span[1], float(t[-1]))

    def _log_text(self, t: float, text: str, level: str) -> None:
        self._push("events", "text", np.array([t]), np.array([(text, level)], dtype=object))

    def _push_scalar(self, entity: str, t: np.ndarray, values) -> None:
        v = np.asarray(values, dtype=float)
        ok = np.isfinite(v)
        if not ok.all():
            t, v = t[ok], v[ok]
        self._push(entity, "scalar", t, v)

    def _push_states(self, entity: str, t: np.ndarray, states: np.ndarray) -> None:
        """Keep only the rows where the state changes (also across batches)."""
        if len(states) == 0:
            return
        change = np.empty(len(states), dtype=bool)
        change[0] = states[0] != self._last_state.get(entity)
        change[1:] = states[1:] != states[:-1]
        self._last_state[entity] = str(states[-1])
        if change.any():
            self._push(entity, "state", t[change], states[change])
            if entity in self._changes:
                self._changes[entity] += zip(t[change].tolist(), states[change].tolist(), strict=True)

    def _push_cloud(self, entity: str, t: np.ndarray, xyz: np.ndarray) -> None:
        """Decimate to at most one sample per ``1/cloud_rate_hz`` seconds (bins of the time axis)."""
        if len(t) == 0:
            return
        bins = np.floor(t * self.cloud_rate_hz)
        keep = np.empty(len(t), dtype=bool)
        keep[0] = bins[0] != self._cloud_bin.get(entity)
        keep[1:] = bins[1:] != bins[:-1]
        self._cloud_bin[entity] = float(bins[-1])
        if keep.any():
            self._push(entity, "points", t[keep], xyz[keep])

    def _push(self, entity: str, kind: str, t: np.ndarray, values: np.ndarray) -> None:
        self._require()
        if len(t) == 0:
            return
        entry = self._buf.get(entity)
        if entry is None:
            entry = self._buf[entity] = [kind, [], [], 0]
        entry[1].append(np.array(t, dtype=float))
        entry[2].append(values)
        entry[3] += len(t)
        if entry[3] >= self.chunk_rows:
            self._flush(entity)

    def _flush(self, entity: str) -> None:
        kind, ts, vs, n = self._buf.pop(entity)
        if n == 0:
            return
        t = np.concatenate(ts)
        v = np.concatenate(vs)
        for i in range(0, n, self.chunk_rows):  # one send per chunk_rows, however much arrived at once
            self._send(entity, kind, t[i : i + self.chunk_rows], v[i : i + self.chunk_rows])
        self.rows_sent[entity] = self.rows_sent.get(entity, 0) + n

    def _send(self, entity: str, kind: str, t: np.ndarray, v: np.ndarray) -> None:
        index = [rr.TimeColumn("time", duration=_duration_ns(t))]
        if kind == "scalar":
            columns = rr.Scalars.columns(scalars=v)
        elif kind == "state":
            columns = rr.StateChange.columns(state=v.tolist())
        elif kind == "points":
            columns = rr.Points3D.columns(positions=v)
        else:  # text
            columns = rr.TextLog.columns(text=[str(x) for x in v[:, 0]], level=[str(x) for x in v[:, 1]])
        self._rec.send_columns(entity, indexes=index, columns=columns)
