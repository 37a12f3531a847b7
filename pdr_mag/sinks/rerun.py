"""rerun output: a recording (``.rrd`` file or live viewer) laid out for debugging heading drift.

Entities (timeline ``time``: the recording's clock as a duration, ``round(t·1e9)`` ns; negative t is fine)
--------------------------------------------------------------------------------------------------
``heading/ours``, ``heading/truth``, ``heading/gyro_only``, ``heading/os``
    heading, deg clockwise from north (ours; ``reference("truth")``; diag ``gyro_heading_deg``;
    ``reference("os")``), drawn as points so the 0/360 wrap draws no vertical lines.
``heading_std/ours``
    1-σ heading uncertainty, deg.
``heading_error/ours``, ``heading_error/gyro_only``, ``heading_error/os``
    heading minus the truth (interpolated), wrapped to [−180, 180) deg — where drift shows directly; only
    when ``reference("truth")`` came before the series (as the replay sends it).
``field/strength``, ``field/reference``, ``field/lower``, ``field/upper``
    |calibrated field| with the detector's reference and the accepted band (reference ∓ tolerance), µT.
``dip/measured``, ``dip/reference``, ``dip/lower``, ``dip/upper``
    dip angle with the reference inclination and its band, deg.
``detector/score``, ``detector/threshold``
    interference score (≥ 1 flags) and the threshold 1.
``state/interference``, ``state/mag_used``, ``state/calibration``
    :class:`rerun.StateChange` lanes, written only where the state changes.
``coverage/online``, ``coverage/calibration``
    orientation coverage of the online buffer (diag ``coverage``) and of each calibration, [0, 1].
``mag/raw``, ``mag/calibrated``
    the 3-D cloud of raw and calibrated magnetometer samples, µT, decimated to ``cloud_rate_hz``.
``mag/fit/ellipsoid``, ``mag/fit/sphere``
    at each calibration: the fitted surface in raw space (centre = offset, axes from ``soft_iron``:
    ``|S (m − b)| = R`` ⇔ ``m = b + V diag(R/λ) u`` with ``S = V diag(λ) Vᵀ``, ``|u| = 1``) and the sphere of
    radius ``field_uT`` round the origin that the calibrated cloud should lie on.
``inputs/accel/{x,y,z}``, ``inputs/gyro/{x,y,z}``, ``inputs/mag/{x,y,z}``
    the raw inputs (a tab of their own, behind coverage).
``events``
    :class:`rerun.TextLog` — pipeline events and calibrations.

The default blueprint (:func:`drift_blueprint`) puts heading, heading error vs truth, field strength, dip
and the state lanes on the left, on a shared time axis; the 3-D cloud with the fitted surfaces (all samples
up to the time cursor), tabs for coverage / heading σ / interference score / inputs, and the event log on
the right.

Every series goes out with columnar :meth:`rerun.RecordingStream.send_columns` calls, buffered per entity
up to ``chunk_rows`` rows (bounded memory, few large sends); nothing is logged row by row.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pdr_mag.conventions import heading_deg_from_quat, wrap_deg


def _duration_ns(t: np.ndarray) -> np.ndarray:
    """Seconds → ``timedelta64[ns]``, rounded like MCAP's ``round(t·1e9)`` (rerun itself truncates)."""
    return np.round(np.asarray(t, dtype=float) * 1e9).astype(np.int64).astype("timedelta64[ns]")


WARNING_EVENTS = ("interference_start", "calibration_rejected", "recalibration_requested")

_COLORS = {
    "heading/ours": (31, 119, 180),
    "heading/truth": (40, 40, 40),
    "heading/gyro_only": (255, 127, 14),
    "heading/os": (44, 160, 44),
    "heading_std/ours": (31, 119, 180),
    "heading_error/ours": (31, 119, 180),
    "heading_error/gyro_only": (255, 127, 14),
    "heading_error/os": (44, 160, 44),
    "field/strength": (31, 119, 180),
    "field/reference": (40, 40, 40),
    "field/lower": (214, 39, 40),
    "field/upper": (214, 39, 40),
    "dip/measured": (148, 103, 189),
    "dip/reference": (40, 40, 40),
    "dip/lower": (214, 39, 40),
    "dip/upper": (214, 39, 40),
    "detector/score": (140, 86, 75),
    "detector/threshold": (214, 39, 40),
    "coverage/online": (23, 190, 207),
    "coverage/calibration": (188, 189, 34),
}
_NAMES = {
    "heading/ours": "ours",
    "heading/truth": "truth",
    "heading/gyro_only": "gyro only",
    "heading/os": "phone (OS)",
    "heading_std/ours": "1σ",
    "heading_error/ours": "ours − truth",
    "heading_error/gyro_only": "gyro only − truth",
    "heading_error/os": "phone − truth",
    "field/strength": "|m_cal|",
    "field/reference": "reference",
    "field/lower": "lower threshold",
    "field/upper": "upper threshold",
    "dip/measured": "dip",
    "dip/reference": "reference",
    "dip/lower": "band lower",
    "dip/upper": "band upper",
    "detector/score": "score",
    "detector/threshold": "threshold",
    "coverage/online": "online buffer",
    "coverage/calibration": "calibration",
}
#: Entities drawn as points instead of lines.
_POINT_SERIES = ("heading/ours", "heading/truth", "heading/gyro_only", "heading/os", "coverage/calibration")


def drift_blueprint():
    """The default layout: what one needs to see to find where and why the heading drifts."""
    import rerun.blueprint as rrb

    everything_so_far = rrb.VisibleTimeRange(
        "time", start=rrb.TimeRangeBoundary.infinite(), end=rrb.TimeRangeBoundary.cursor_relative()
    )
    left = rrb.Vertical(
        rrb.TimeSeriesView(origin="/heading", name="Heading, deg (ours, truth, gyro only, phone)"),
        rrb.TimeSeriesView(origin="/heading_error", name="Heading error vs truth, deg (wrapped to ±180)"),
        rrb.TimeSeriesView(origin="/field", name="Field strength, µT (reference and thresholds)"),
        rrb.TimeSeriesView(origin="/dip", name="Dip angle, deg (reference band)"),
        rrb.StateTimelineView(origin="/state", name="Interference / magnetometer used / calibration state"),
        row_shares=[3, 2, 2, 2, 1],
    )
    right = rrb.Vertical(
        rrb.Spatial3DView(
            origin="/mag",
            name="Magnetometer cloud: raw, calibrated, fitted surfaces",
            time_ranges=everything_so_far,
        ),
        rrb.Tabs(
            rrb.TimeSeriesView(origin="/coverage", name="Coverage"),
            rrb.TimeSeriesView(origin="/heading_std", name="Heading σ, deg"),
            rrb.TimeSeriesView(origin="/detector", name="Interference score"),
            rrb.TimeSeriesView(origin="/inputs", name="Inputs"),
        ),
        rrb.TextLogView(origin="/events", name="Events"),
        row_shares=[3, 2, 2],
    )
    return rrb.Blueprint(rrb.Horizontal(left, right, column_shares=[3, 2]), collapse_panels=True)


class RerunSink:
    """Write a replay to a rerun ``.rrd`` file and/or a live viewer, with the :func:`drift_blueprint`.

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
        self._cloud_bin: dict[str, float] = {}
        self._truth: tuple[list, list] | None = None  # (t chunks, heading chunks) for the error curves
        self._truth_unwrapped: tuple[np.ndarray, np.ndarray] | None = None
        self.rows_sent: dict[str, int] = {}

    # ------------------------------------------------------------------ Sink protocol
    def open(self, meta: dict) -> None:
        import rerun as rr

        bp = drift_blueprint()
        rec = rr.RecordingStream(self.application_id)
        if self.spawn and self.path is not None:
            rec.spawn(connect=False)
            self.path.parent.mkdir(parents=True, exist_ok=True)
            rec.set_sinks(rr.FileSink(str(self.path)), rr.GrpcSink(), default_blueprint=bp)
        elif self.spawn:
            rec.spawn(default_blueprint=bp)
        else:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            rec.save(self.path, default_blueprint=bp)
        self._rec = rec
        meta = dict(meta or {})
        name = meta.get("source") or (self.path.stem if self.path else "pdr_mag replay")
        rec.send_recording_name(Path(str(name)).name or str(name))
        props = {str(k): str(v) for k, v in meta.items() if v is not None}
        if props:
            rec.send_property("recording", rr.AnyValues(**props))
        # static styling: names, colours, lines or points
        for entity, color in _COLORS.items():
            style = rr.SeriesPoints if entity in _POINT_SERIES else rr.SeriesLines
            if style is rr.SeriesPoints:
                rec.log(
                    entity, style(colors=[color], names=[_NAMES[entity]], marker_sizes=[1.5]), static=True
                )
            else:
                rec.log(entity, style(colors=[color], names=[_NAMES[entity]], widths=[1.5]), static=True)
        for kind in ("accel", "gyro", "mag"):
            for axis, color in zip("xyz", ((214, 39, 40), (44, 160, 44), (31, 119, 180)), strict=True):
                style = rr.SeriesLines(colors=[color], names=[f"{kind} {axis}"])
                rec.log(f"inputs/{kind}/{axis}", style, static=True)
        rec.log("mag/raw", rr.Points3D.from_fields(colors=[(160, 160, 160)], radii=[0.4]), static=True)
        rec.log("mag/calibrated", rr.Points3D.from_fields(colors=[(31, 119, 180)], radii=[0.4]), static=True)

    def inputs(self, kind: str, t: np.ndarray, xyz: np.ndarray) -> None:
        if kind not in ("accel", "gyro", "mag"):
            raise ValueError(f"kind: expected 'accel', 'gyro' or 'mag', got {kind!r}")
        t = np.asarray(t, dtype=float)
        xyz = np.asarray(xyz, dtype=float).reshape(len(t), 3)
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
        self._push_scalar("heading/ours", t, batch.heading_deg)
        self._push_scalar("heading_std/ours", t, batch.heading_std_deg)
        d = batch.diag
        self._push_error("heading_error/ours", t, batch.heading_deg)
        if "gyro_heading_deg" in d:
            self._push_error("heading_error/gyro_only", t, d["gyro_heading_deg"])
        for key, entity in (
            ("gyro_heading_deg", "heading/gyro_only"),
            ("field_strength_uT", "field/strength"),
            ("field_ref_uT", "field/reference"),
            ("dip_deg", "dip/measured"),
            ("dip_ref_deg", "dip/reference"),
            ("interference_score", "detector/score"),
            ("coverage", "coverage/online"),
        ):
            if key in d:
                self._push_scalar(entity, t, d[key])
        for ref, tol, name in (
            ("field_ref_uT", "strength_tol_uT", "field"),
            ("dip_ref_deg", "dip_tol_deg", "dip"),
        ):
            if ref in d and tol in d:
                r, w = np.asarray(d[ref], dtype=float), np.asarray(d[tol], dtype=float)
                self._push_scalar(f"{name}/lower", t, r - w)
                self._push_scalar(f"{name}/upper", t, r + w)
        if "interference_score" in d:
            self._push_scalar("detector/threshold", t[[0, -1]], np.ones(2))
        self._push_states("state/interference", t, np.where(batch.interference, "interference", "clean"))
        self._push_states("state/mag_used", t, np.where(batch.mag_used, "mag used", "gyro only"))
        self._push_states("state/calibration", t, np.asarray(batch.cal_state).astype(str))

    def reference(self, name: str, t: np.ndarray, q_wd: np.ndarray) -> None:
        t = np.asarray(t, dtype=float)
        if len(t) == 0:
            return
        q = np.asarray(q_wd, dtype=float).reshape(len(t), 4)
        entity = f"heading/{name}"
        if entity not in _COLORS and self._rec is not None:
            import rerun as rr

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

    def _push_error(self, entity: str, t: np.ndarray, heading_deg) -> None:
        """``heading − truth`` wrapped to [−180, 180) where the truth covers ``t`` (truth interpolated
        linearly on its unwrapped heading).  Needs the truth before the series it is compared with — the
        replay sends references first; a series that arrives before any truth gets no error curve."""
        if self._truth is None or len(t) == 0:
            return
        if len(self._truth[0]) > 1:  # truth given in several calls: join once, keep the joined arrays
            tt, hh = np.concatenate(self._truth[0]), np.concatenate(self._truth[1])
            order = np.argsort(tt, kind="stable")
            self._truth = ([tt[order]], [hh[order]])
        tt = self._truth[0][0]
        if self._truth_unwrapped is None or self._truth_unwrapped[0] is not tt:
            self._truth_unwrapped = (tt, np.unwrap(self._truth[1][0], period=360.0))
        hu = self._truth_unwrapped[1]
        inside = (t >= tt[0]) & (t <= tt[-1])
        err = wrap_deg(np.asarray(heading_deg, dtype=float) - np.interp(t, tt, hu))
        self._push_scalar(entity, t[inside], err[inside])

    def event(self, ev) -> None:
        details = {k: v for k, v in ev.to_dict().items() if k not in ("t", "kind")}
        text = ev.kind + ("" if not details else " " + ", ".join(f"{k}={v}" for k, v in details.items()))
        level = "WARN" if ev.kind in WARNING_EVENTS else "INFO"
        self._push("events", "text", np.array([float(ev.t)]), np.array([(text, level)], dtype=object))

    def calibration(self, t: float, cal) -> None:
        import rerun as rr
        from scipy.spatial.transform import Rotation

        t = float(t)
        rec = self._require()
        time = [rr.TimeColumn("time", duration=_duration_ns(np.array([t])))]
        r = float(cal.field_uT)
        color = (44, 160, 44) if cal.accepted else (214, 39, 40)
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
                        centers=[cal.offset], half_sizes=[r / lam], quaternions=[quat], colors=[color]
                    ),
                )
            rec.send_columns(
                "mag/fit/sphere",
                indexes=time,
                columns=rr.Ellipsoids3D.columns(
                    centers=[(0.0, 0.0, 0.0)], half_sizes=[(r, r, r)], colors=[color]
                ),
            )
        if np.isfinite(cal.coverage):
            self._push_scalar("coverage/calibration", np.array([t]), np.array([float(cal.coverage)]))
        text = (
            f"calibration {cal.method} {'accepted' if cal.accepted else 'rejected'}: "
            f"offset {np.round(cal.offset, 2).tolist()} µT, field {r:.2f} µT, "
            f"residual {cal.residual_rms_uT:.3g} µT, coverage {cal.coverage:.2f}, n {cal.n_samples}"
            + ("" if cal.accepted else f"; reasons: {'; '.join(cal.reasons)}")
        )
        level = "INFO" if cal.accepted else "WARN"
        self._push("events", "text", np.array([t]), np.array([(text, level)], dtype=object))

    def close(self) -> None:
        if self._rec is None:
            return
        for entity in list(self._buf):
            self._flush(entity)
        rec, self._rec = self._rec, None
        try:
            rec.flush()
        except RuntimeError as exc:  # a live viewer that is gone must not cost the replay its outputs
            if not self.spawn:
                raise
            import warnings

            warnings.warn(f"rerun viewer unreachable ({exc}); the data it missed is not shown", stacklevel=2)
        rec.disconnect()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # ------------------------------------------------------------------ buffering
    def _require(self):
        if self._rec is None:
            raise RuntimeError("RerunSink: open() must be called before writing (and not after close())")
        return self._rec

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
        import rerun as rr

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
