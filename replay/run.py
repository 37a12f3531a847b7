"""Drive a recording through :class:`pdr_mag.pipeline.HeadingPipeline` and into the sinks.

The recording streams (:mod:`replay.source`): its samples are read a chunk at a time and pushed in slices
of ``slice_s`` seconds of stream time (:data:`SLICE_S`), so memory does not grow with the recording's
length; the pipeline is polled after each slice, and everything it gives out — estimates,
events, calibrations, calibrated magnetometer samples — goes to every sink through the
:class:`pdr_mag.sinks.Sink` protocol.  The CSV output of ``replay --out-csv`` is one such sink; another,
:class:`replay.heading_scores.HeadingScores`, is in every run and gives the summary's heading figures
against the walked direction and the reference series.
"""

from __future__ import annotations

import errno
import sys
import time
from collections import Counter
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from pdr_mag.calibration.latency import NONE as NO_LATENCY
from pdr_mag.calibration.latency import Latency, estimate_mag_latency
from pdr_mag.calibration.model import MagCalibration
from pdr_mag.calibration.store import DeviceStore
from pdr_mag.episodes import EpisodeFinder, EpisodeSettings
from pdr_mag.estimates import CSV_COLUMNS, EstimateBatch
from pdr_mag.pipeline import HeadingPipeline, PipelineSettings, fill_unknown_heading
from pdr_mag.sinks import QuietSink
from pdr_mag.units import clock_problem
from replay.compiling import CompileWatch
from replay.errors import InputError
from replay.formats import open_recording
from replay.heading_scores import HeadingScores, attitude_series
from replay.recording import Recording
from replay.source import Merge, RecordingSource

#: Stream time pushed between polls, s. A file needs no phone-like delivery (an app pushes every second or
#: two); a poll has a fixed cost (≈ 0.13 ms: the filter's and the calibrator's calls for the slice's last
#: span, the episode finder's batch) against ≈ 0.1–0.25 ms per second of 100–200 Hz data, so 30 s keeps it
#: to a few per cent, and a slice in memory stays ≈ 15 000 samples at 200 Hz.
SLICE_S = 30.0

#: Recordings of more input bytes than this get a progress bar (≈ 200 000 samples of text).
PROGRESS_MIN_BYTES = 8_000_000


class CsvSink(QuietSink):
    """``replay --out-csv``: one row per output epoch, columns exactly :data:`CSV_COLUMNS`."""

    def __init__(self, path):
        self.path = Path(path)
        self._fh = None

    def open(self, meta: dict) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fh = self.path.open("w", encoding="utf-8", newline="\n")
        self._fh.write(",".join(CSV_COLUMNS) + "\n")

    def estimates(self, batch: EstimateBatch) -> None:
        if not len(batch):
            return
        q = batch.q_wd
        lines = [
            f"{t:.6f},{a:.9f},{b:.9f},{c:.9f},{d:.9f},{h:.4f},{s:.4f},{int(m)},{int(i)},{cs}\n"
            for t, a, b, c, d, h, s, m, i, cs in zip(
                batch.t.tolist(),
                q[:, 0].tolist(),
                q[:, 1].tolist(),
                q[:, 2].tolist(),
                q[:, 3].tolist(),
                batch.heading_deg.tolist(),
                batch.heading_std_deg.tolist(),
                batch.mag_used.tolist(),
                batch.interference.tolist(),
                batch.cal_state.tolist(),
                strict=True,
            )
        ]
        self._fh.writelines(lines)

    def close(self) -> None:
        if self._fh is not None:
            self._fh.close()
            self._fh = None


class _SinkFile:
    """A sink that writes a file (it has a ``path``), whose write errors name that file: a full disk, a
    device gone, as ``OSError(filename=path)`` — ``pdr-mag: FILE: cannot write (…)``, exit 2 — where the
    writer's own error names none (Python's file objects; the rerun SDK's I/O errors, a ``RuntimeError``
    ending ``(os error N)``).  Everything else is the sink's."""

    def __init__(self, sink):
        self._sink = sink

    def __getattr__(self, name):
        attr = getattr(self._sink, name)
        if not callable(attr):
            return attr

        def call(*args, **kwargs):
            try:
                return attr(*args, **kwargs)
            except OSError as exc:
                if exc.filename is not None:
                    raise
                why = f"cannot write ({exc.strerror or exc})"
                raise OSError(exc.errno or errno.EIO, why, str(self._sink.path)) from None
            except RuntimeError as exc:
                if "os error" not in str(exc):
                    raise
                raise OSError(errno.EIO, f"cannot write ({exc})", str(self._sink.path)) from None

        return call


class MemorySink(QuietSink):
    """Keeps the estimate batches in memory (``batches``, in order) and writes nothing: what a backend or a
    benchmark embedding :func:`replay` collects.  Like :class:`CsvSink` it does not want the calibrated
    magnetometer samples, so :func:`replay` runs the pipeline with the same settings and the batches hold
    the rows ``--out-csv`` writes."""

    def __init__(self):
        self.batches: list[EstimateBatch] = []

    def estimates(self, batch: EstimateBatch) -> None:
        self.batches.append(batch)


#: Stream time the magnetometer's latency is estimated on before a run (``--mag-time-offset auto``), s.
LATENCY_SPAN_S = 60.0


def estimate_latency(rec_path, span_s: float = LATENCY_SPAN_S) -> Latency:
    """The magnetometer's latency against the gyroscope over the recording's first ``span_s`` seconds
    (:func:`pdr_mag.calibration.latency.estimate_mag_latency`): a pass of its own over the start of the file,
    before the run (``replay --mag-time-offset auto``). ``rec_path``: a path or a :class:`Recording`."""
    if isinstance(rec_path, RecordingSource):
        raise ValueError("estimate_latency: a RecordingSource streams once; give the path (or a Recording)")
    if isinstance(rec_path, Recording):
        src = RecordingSource.from_recording(rec_path)
    else:
        src = open_recording(rec_path)
    merge = Merge(src)
    if "gyro" not in merge.present or "mag" not in merge.present:
        return NO_LATENCY
    # the first slice holds the samples before t0 + span_s (all of them in a shorter recording)
    _, blocks = next(merge.slices(span_s))
    if blocks.get("gyro") is None or blocks.get("mag") is None:
        return NO_LATENCY
    return estimate_mag_latency(*blocks["gyro"], *blocks["mag"])


def load_calibration(path) -> MagCalibration:
    """Read a ``calibrate --json`` file; any problem is an :class:`InputError` naming the file."""
    p = Path(path)
    if not p.is_file():
        raise InputError(p, "no such calibration file")
    try:
        return MagCalibration.from_json(p)
    except ValueError as exc:
        msg = str(exc)
        prefix = f"{p}: "
        raise InputError(p, msg[len(prefix) :] if msg.startswith(prefix) else msg) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(p, f"cannot read ({exc})") from None


def make_sink(kind: str, path, *, spawn: bool = False, rate_hz: float | None = None):
    """An MCAP or rerun sink (``spawn``: rerun also streams to a live viewer it starts; ``path`` may then be
    None; ``rate_hz``: the MCAP sink's rate limit)."""
    # imported here, when the output is asked for: the sink modules import mcap / rerun, heavy libraries that
    # the other outputs never need (optional outputs, house style 9)
    if kind == "mcap":
        from pdr_mag.sinks.mcap import McapSink

        return McapSink(path, rate_hz=rate_hz)
    from pdr_mag.sinks.rerun import RerunSink

    return RerunSink(path, spawn=spawn)


def os_reference(rec: Recording | RecordingSource):
    """The phone's own orientation (``os``) when the reader found one, else None."""
    return rec.references.get("os")


def replay(
    rec_path,
    calibration=None,
    sinks=(),
    settings: PipelineSettings | None = None,
    progress: bool | None = None,
    slice_s: float | None = None,
    episode_settings: EpisodeSettings | None = None,
    device_store: DeviceStore | None = None,
) -> dict:
    """Replay a recording; return the run summary (the ``replay --json`` object).

    Three steps: :meth:`ReplayRun.start` opens the recording, the pipeline and the sinks;
    :meth:`ReplayRun.stream` pushes the recording through them slice by slice; :meth:`ReplayRun.summary`
    sums the run up. The time the numba kernels took to compile (a cold cache: the first run only) is
    reported apart (``compile_s``), not counted as the run's work (``elapsed_s``, ``samples_per_s``).

    Parameters
    ----------
    rec_path : path, RecordingSource or Recording
        A recording (any format a reader recognises: streamed, a chunk at a time), one opened with
        :func:`replay.formats.open_recording`, or one already read (pushed from memory, same slices).
    calibration : MagCalibration, path or None
        The device calibration (a path is read as the ``calibrate --json`` file); None = online only.
    sinks : sequence of Sink
        Opened, fed and closed here.
    settings : PipelineSettings, optional
    progress : bool or None
        Progress bar on stderr, over the input bytes read (the number of samples is not known before the
        end); None = only for recordings of at least :data:`PROGRESS_MIN_BYTES` on a terminal.
    slice_s : float, optional
        Stream time pushed between polls, s (default :data:`SLICE_S`). The outputs do not depend on it (the
        pipeline gives the same rows, events and calibrations however its input is chunked).
    episode_settings : EpisodeSettings, optional
        Thresholds of the drift episodes (:mod:`pdr_mag.episodes`) in the summary's ``episodes``; each
        episode also goes to the sinks as a ``drift_episode`` event when it closes.
    device_store : DeviceStore, optional
        A backend's store of its devices' calibrations (``replay --device-store DIR``): the run starts from
        the entry of the recording's device (a prior, aged to the recording's start) and leaves what it
        learnt there at the end (:meth:`ReplayRun.keep`); the summary's ``device_store`` says what was read
        and written.
    """
    with CompileWatch() as compiling:
        run = ReplayRun.start(rec_path, calibration, sinks, settings, episode_settings, device_store)
        if progress is None:
            progress = run.src.size >= PROGRESS_MIN_BYTES and sys.stderr.isatty()
        t_start, compiled_before = time.perf_counter(), compiling.seconds
        run.stream(SLICE_S if slice_s is None else slice_s, progress)
        run.keep()
        elapsed = time.perf_counter() - t_start - (compiling.seconds - compiled_before)
    return run.summary(elapsed, compiling.seconds)


class ReplayRun:
    """One recording on its way through the pipeline into the sinks: what :func:`replay` sets up, streams
    and sums up.

    Attributes
    ----------
    src : RecordingSource
        The recording, streamed.
    merge : Merge
        Its streams merged into time slices.
    pipe : HeadingPipeline
    sinks : list of Sink
        Opened by :meth:`start`, closed by :meth:`stream`: the sinks given and :attr:`scores`.
    scores : HeadingScores
        The heading against the walked direction and the references (the summary's ``heading_error`` and
        ``walked_direction``), a sink of every run.
    calibration : MagCalibration or None
        The device calibration given (None: online calibration only).
    finder : EpisodeFinder
        The drift episodes, found as the output rows come.
    events : list of dict
        The pipeline's events so far, in order (the summary's ``events``).
    state_counts : Counter
        Output rows per ``cal_state`` so far.
    n_pushed : dict
        Samples pushed so far, per stream.
    n_cal_seen : int
        The pipeline's calibrations already sent to the sinks.
    store : DeviceStore or None
        The device store the run started from and leaves its knowledge in.
    store_use : dict
        What was read from and written to the store (the summary's ``device_store``).
    """

    def __init__(self, src: RecordingSource, merge: Merge, pipe: HeadingPipeline, sinks: list,
                 scores: HeadingScores, calibration: MagCalibration | None, finder: EpisodeFinder,
                 store: DeviceStore | None = None, store_use: dict | None = None):
        self.src = src
        self.merge = merge
        self.pipe = pipe
        self.sinks = sinks
        self.scores = scores
        self.calibration = calibration
        self.finder = finder
        self.events: list = []
        self.state_counts: Counter = Counter()
        self.n_pushed = dict.fromkeys(merge.present, 0)
        self.n_cal_seen = len(pipe.calibrations)
        self.store = store
        self.store_use = store_use
        # the phone's own attitude, for the rows whose heading pdr_mag does not know (fill_unknown_heading);
        # not with --ignore-phone-calibration, whose runs start from nothing the phone knows
        osref = os_reference(src) if pipe.settings.prior.use_phone else None
        self.phone_attitude = None if osref is None else attitude_series(*osref)
        self.n_phone_heading = 0

    @classmethod
    def start(cls, rec_path, calibration=None, sinks=(), settings: PipelineSettings | None = None,
              episode_settings: EpisodeSettings | None = None,
              device_store: DeviceStore | None = None) -> ReplayRun:
        """Open the recording (its first chunk read: a stream missing is an :class:`InputError` now), the
        pipeline (from the device store's entry, when there is one) and the sinks (given the run's metadata,
        the references and the calibration given)."""
        if isinstance(rec_path, RecordingSource):
            src = rec_path
        elif isinstance(rec_path, Recording):
            src = RecordingSource.from_recording(rec_path)
        else:
            src = open_recording(rec_path)
        where = src.source or rec_path
        merge = Merge(src)  # reads the first chunk of every stream
        for key in ("accel", "gyro"):
            if key not in merge.present:
                raise InputError(where, f"no {key} stream (heading needs accel, gyro and mag)")
        problem = clock_problem(merge.starts)
        if problem is not None:
            raise InputError(where, problem)
        if calibration is not None and not isinstance(calibration, MagCalibration):
            calibration = load_calibration(calibration)
        scores = HeadingScores()  # against the walked direction and the references: the summary's figures
        sinks = [*(_SinkFile(s) if getattr(s, "path", None) is not None else s for s in sinks), scores]
        # the readers judged each stream's unit and the clocks (above) on more samples than the pipeline would
        settings = replace(settings or PipelineSettings(), check_inputs=False)
        if any(getattr(s, "wants_mag_calibrated", True) for s in sinks):
            # the heavy sinks draw the calibrated field
            settings = replace(settings, keep_mag_calibrated=True)
        prior, store_use = None, None
        if device_store is not None:
            prior, store_use = _load_device(device_store, src.meta)
        try:
            pipe = HeadingPipeline(settings=settings, calibration=calibration, meta=src.meta, prior=prior)
        except ValueError as exc:
            raise InputError(where, str(exc)) from None
        run = cls(src, merge, pipe, sinks, scores, calibration,
                  EpisodeFinder(episode_settings, truth=src.truth), device_store, store_use)
        run._open_sinks()
        return run

    def _open_sinks(self) -> None:
        src, pipe = self.src, self.pipe
        meta = {
            **src.meta,
            "source": src.source,
            "format": src.format,
            "north": pipe.north,
            "t0": self.merge.t0,
            "mag_interval_s": pipe.fusion.settings.mag.interval_s,
        }
        if pipe.field is not None:
            meta["field"] = {
                "model": pipe.field.model,
                "strength_uT": pipe.field.strength,
                "inclination_deg": pipe.field.inclination_deg,
                "declination_deg": pipe.field.declination_deg,
            }
        for s in self.sinks:
            s.open(meta)
        if src.truth is not None:
            for s in self.sinks:
                s.reference("truth", src.truth[0], src.truth[1])
        osref = os_reference(src)
        if osref is not None:
            for s in self.sinks:
                s.reference("os", osref[0], osref[1])
        if self.calibration is not None:
            for s in self.sinks:
                s.calibration(self.merge.t0, self.calibration)

    def stream(self, slice_s: float, progress: bool) -> None:
        """Push the recording through the pipeline in slices of ``slice_s`` s of stream time, polling after
        each (flushing after the last) and handing everything out to the sinks; close the sinks at the end
        (also on an error). ``progress``: a bar on stderr over the input bytes read."""
        bar = None
        if progress:
            bar = tqdm(total=self.src.size or None, unit="B", unit_scale=True, desc="replay", leave=False)
        try:
            for final, blocks in self.merge.slices(slice_s):
                self._push(blocks)
                self._emit(self.pipe.flush() if final else self.pipe.poll())
                if bar is not None:
                    bar.update(self.merge.position - bar.n)
            _emit_episodes(self.finder.finish(), self.sinks)
        finally:
            if bar is not None:
                bar.close()
            for s in self.sinks:
                s.close()

    def _push(self, blocks: dict) -> None:
        """One slice's samples, per stream, into the pipeline and the sinks."""
        for name, block in blocks.items():
            if block is not None:
                t, xyz = block
                self.pipe.push_arrays(name, t, xyz)
                for s in self.sinks:
                    s.inputs(name, t, xyz)
                self.n_pushed[name] += len(t)

    def _emit(self, batch: EstimateBatch) -> None:
        """What a poll gave out — calibrated magnetometer samples, output rows, events, the drift episodes
        they close and new calibrations — to the sinks, counted for the summary."""
        pipe, sinks = self.pipe, self.sinks
        evs = pipe.pop_events()
        if pipe.settings.keep_mag_calibrated:
            tm, xm = pipe.pop_mag_calibrated()
            if len(tm):
                for s in sinks:
                    s.mag_calibrated(tm, xm)
        phone_rows = None
        if len(batch) and self.phone_attitude is not None:
            batch, phone_rows = fill_unknown_heading(batch, *self.phone_attitude)
            self.n_phone_heading += len(phone_rows)
        if len(batch):
            _count_states(batch.cal_state, self.state_counts)
            for s in sinks:
                if s is self.scores:
                    s.estimates(batch, phone_rows)
                else:
                    s.estimates(batch)
        for ev in evs:
            if ev.kind != "stream_gap":  # the summary's own ``stream_gaps`` lists those
                self.events.append(ev.to_dict())
            for s in sinks:
                s.event(ev)
        _emit_episodes(self.finder.update(batch, evs), sinks)
        cals = pipe.calibrations
        for t_cal, cal in cals[self.n_cal_seen :]:
            for s in sinks:
                s.calibration(t_cal, cal)
        self.n_cal_seen = len(cals)

    def keep(self) -> None:
        """Leave what the run learnt of the device in the device store (nothing without one, or when the
        recording names no device): the calibration the data supported and the gyro bias
        (:meth:`~pdr_mag.pipeline.HeadingPipeline.device_knowledge`), stamped with the recording's end."""
        if self.store is None or self.store_use is None or self.store_use["file"] is None:
            return
        end = self.store_use["t_unix"] + (self.pipe.summary()["duration_s"] or 0.0)
        try:
            self.store.save(self.src.meta, self.pipe.device_knowledge(), end)
        except (OSError, ValueError) as exc:
            raise InputError(self.store.folder, f"device store: cannot write ({exc})") from None
        self.store_use["saved"] = True

    def summary(self, elapsed_s: float, compile_s: float) -> dict:
        """The run summary (the ``replay --json`` object): the pipeline's own summary and what the run
        counted. ``elapsed_s``: the work's wall time (reading, pipeline, sinks), s; ``compile_s``: the time
        spent compiling the numba kernels during the run, s (0 when they came from the cache)."""
        n_samples = sum(self.n_pushed.values())
        summary = self.pipe.summary()
        dropped = Counter(self.src.dropped)
        dropped.update(self.pipe.dropped)
        summary.update(
            {
                "source": self.src.source,
                "format": self.src.format,
                "events": self.events,
                "dropped_samples": dict(sorted(dropped.items())),
                "n_samples": self.n_pushed,
                "cal_state_rows": dict(sorted(self.state_counts.items())),
                "phone_heading_rows": self.n_phone_heading,
                "calibration_given": self.calibration is not None,
                "device_store": None if self.store_use is None else {
                    k: v for k, v in self.store_use.items() if k != "t_unix"},
                "episodes": [ep.to_dict() for ep in self.finder.episodes],
                "episode_settings": {"truth": self.finder.has_truth, **asdict(self.finder.settings)},
                **self.scores.summary(),
                "elapsed_s": elapsed_s,
                "compile_s": compile_s,
                "samples_per_s": n_samples / elapsed_s if elapsed_s > 0 else None,
            }
        )
        return summary


def _load_device(store: DeviceStore, meta: dict) -> tuple:
    """The store's prior for this recording's device, aged to its start (the clock when the recording
    states no time), and what the summary says of it: ``file``, ``loaded``, ``age_s``, ``saved``."""
    t_unix = DeviceStore.recording_time(meta)
    if t_unix is None:
        t_unix = time.time()
    try:
        path, prior = store.find(meta, t_unix)
    except ValueError as exc:  # "<file>: device store: …", the file the store could not use
        where, _, why = str(exc).partition(": ")
        raise InputError(where or store.folder, why or str(exc)) from None
    use = {"file": None if path is None else str(path), "loaded": prior is not None,
           "age_s": None if prior is None else round(prior.age_s, 1), "saved": False, "t_unix": t_unix}
    return prior, use


def _count_states(cal_state: np.ndarray, counts: Counter) -> None:
    """Add the rows of each ``cal_state`` to ``counts``, run by run (a state holds for many rows; sorting
    the strings, as ``np.unique`` does, would cost more than the rest of a poll's bookkeeping)."""
    edges = [0, *(np.flatnonzero(cal_state[1:] != cal_state[:-1]) + 1).tolist(), len(cal_state)]
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        counts[str(cal_state[lo])] += hi - lo


def _emit_episodes(episodes, sinks) -> None:
    """Each closed drift episode to every sink, as a ``drift_episode`` event at its start."""
    for ep in episodes:
        ev = ep.to_event()
        for s in sinks:
            s.event(ev)
