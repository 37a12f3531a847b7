"""Gaps in a recording's streams: stretches in which one stream has no sample while the recording goes on.

:class:`~pdr_mag.pipeline.HeadingPipeline` keeps one (``stream_gaps``): each gap is a ``stream_gap`` event of
:meth:`~pdr_mag.pipeline.HeadingPipeline.pop_events` when it ends (a gap at a stream's start or end at
:meth:`~pdr_mag.pipeline.HeadingPipeline.flush`), and the pipeline's summary counts them — so a backend that
pushes samples learns that the phone stopped delivering one sensor (an app put in the background) as
``replay`` does.  The times are those the pipeline accepted (finite, in order; the magnetometer's on the
IMU's clock when ``mag_time_offset_s`` moves it).

What a gap does to the heading (``INTERFACE.md``): the output rows follow the gyroscope, so a gyroscope gap
has no rows and the heading turns by nothing through it (its σ grows by the gyro's uncertainty over the
gap, and the magnetometer takes it back); an accelerometer gap leaves the tilt to the gyroscope alone; a
magnetometer gap leaves the heading to the gyroscope alone (a ``no_reference`` drift episode when long).
A logger that stops delivering one sensor — an app put in the background, a sensor switched off to save
power — loses the rows or the corrections of the whole stretch, which the summary would otherwise show only
as fewer ``n_outputs``.

A gap is a stretch longer than ``max(MIN_GAP_S, GAP_PERIODS × the stream's median sample interval)``
without a sample of the stream: between two of its samples (``inside``), from the recording's first sample
(of any stream) to the stream's first (``start``), or from the stream's last to the recording's last
(``end``). The median interval is that of the stream's first :data:`RATE_SAMPLES` intervals (all of them in
a shorter stream), so the gaps found do not depend on how the recording is sliced.
"""

from __future__ import annotations

import numpy as np

from pdr_mag.estimates import Event
from pdr_mag.pipeline import _kernel as PK

#: The shortest stretch without samples reported, s: shorter ones are the jitter and stalls of phone loggers,
#: which the filter bridges (a turn of 1 s at a walker's 1 rad/s is what the gyro's σ then has to cover).
MIN_GAP_S = 1.0
#: A gap is longer than this many of the stream's median sample intervals (a 1-Hz stream has no gap of 1 s).
GAP_PERIODS = 5.0
#: Intervals from the stream's start whose median sets its rate.
RATE_SAMPLES = 200
#: Gaps listed in the summary (all are counted).
MAX_LISTED = 100


class StreamGaps:
    """Find the gaps of each stream as its samples come (:meth:`add`), and at the end (:meth:`finish`); the
    recording starts at the earliest first sample of the streams added (known at :meth:`finish`, whatever
    order the streams came in)."""

    def __init__(self):
        self.finished = False  # finish() has run: the start and end gaps are in
        self.gaps: list[dict] = []
        self.threshold: dict[str, float] = {}  # per stream, s, once its rate is known
        self._head: dict[str, list[np.ndarray]] = {}  # times before the rate is known
        self.first: dict[str, float] = {}  # each stream's first sample time, s
        self._last: dict[str, float] = {}

    def add(self, name: str, t: np.ndarray) -> list[Event]:
        """The next samples' times of stream ``name`` (increasing, after the previous ones); returns a
        ``stream_gap`` event for each gap that ends among them."""
        if not len(t):
            return []
        if name not in self.first:
            self.first[name] = float(t[0])
        if name not in self.threshold:
            head = self._head.setdefault(name, [])
            head.append(np.array(t, dtype=float))  # a copy: a caller may refill its buffer
            if sum(len(h) for h in head) <= RATE_SAMPLES:
                return []
            t = self._set_threshold(name)
        events = self._inside(name, t)
        self._last[name] = float(t[-1])
        return events

    def finish(self) -> list[Event]:
        """The gaps left: inside the streams too short to have set their rate, and at each stream's start
        and end against the recording's first and last sample; returns their events (none after the first
        call: the recording has ended)."""
        if self.finished:
            return []
        self.finished = True
        events = []
        for name in list(self._head):
            t = self._set_threshold(name)
            events += self._inside(name, t)
            self._last[name] = float(t[-1])
        if not self._last:
            return events
        t_end = max(self._last.values())
        t0 = min(self.first.values())
        for name, first in self.first.items():
            if first - t0 > self.threshold[name]:
                events.append(self._gap(name, t0, first, "start"))
        for name, last in self._last.items():
            if t_end - last > self.threshold[name]:
                events.append(self._gap(name, last, t_end, "end"))
        self.gaps.sort(key=lambda g: (g["t_from"], g["stream"]))
        return events

    def summary(self) -> dict:
        """The summary's ``stream_gaps``: how many, how many and how long per stream, thresholds, gaps."""
        per = {}
        for g in self.gaps:
            n, total = per.get(g["stream"], (0, 0.0))
            per[g["stream"]] = (n + 1, total + g["duration_s"])
        return {
            "n": len(self.gaps),
            "per_stream": {k: {"n": n, "total_s": round(s, 3)} for k, (n, s) in sorted(per.items())},
            "threshold_s": {k: round(v, 3) for k, v in sorted(self.threshold.items())},
            "gaps": self.gaps[:MAX_LISTED],
        }

    def get_state(self) -> dict:
        """JSON-serialisable state (:meth:`set_state` puts it back; non-finite times cannot occur: every
        time kept is a sample's)."""
        return {"finished": self.finished, "gaps": [dict(g) for g in self.gaps],
                "threshold": dict(self.threshold),
                "head": {k: np.concatenate(v).tolist() for k, v in self._head.items()},
                "first": dict(self.first), "last": dict(self._last)}

    def set_state(self, state: dict) -> None:
        """Restore from :meth:`get_state` (KeyError, TypeError or ValueError when it is not such a state)."""
        self.finished = bool(state["finished"])
        self.gaps = [dict(g) for g in state["gaps"]]
        self.threshold = {str(k): float(v) for k, v in state["threshold"].items()}
        self._head = {str(k): [np.asarray(v, dtype=float)] for k, v in state["head"].items()}
        self.first = {str(k): float(v) for k, v in state["first"].items()}
        self._last = {str(k): float(v) for k, v in state["last"].items()}

    def _set_threshold(self, name: str) -> np.ndarray:
        """Set the stream's threshold from its first intervals; returns the times held until then."""
        t = np.concatenate(self._head.pop(name))
        dt = np.diff(t[: RATE_SAMPLES + 1])
        period = float(np.median(dt)) if len(dt) else 0.0
        self.threshold[name] = max(MIN_GAP_S, GAP_PERIODS * period)
        return t

    def _inside(self, name: str, t: np.ndarray) -> list[Event]:
        """Gaps between the stream's samples ``t`` and after its last sample before them."""
        prev = self._last.get(name)
        if PK.longest_interval(t, -np.inf if prev is None else prev) <= self.threshold[name]:
            return []  # a push's common case, answered compiled
        tt = t if prev is None else np.concatenate(([prev], t))
        at = np.flatnonzero(np.diff(tt) > self.threshold[name])
        return [self._gap(name, float(tt[i]), float(tt[i + 1]), "inside") for i in at]

    def _gap(self, name: str, t_from: float, t_to: float, where: str) -> Event:
        gap = {"stream": name, "t_from": round(t_from, 6), "t_to": round(t_to, 6),
               "duration_s": round(t_to - t_from, 6), "where": where}
        self.gaps.append(gap)
        return Event(t_from, "stream_gap", {k: v for k, v in gap.items() if k != "t_from"})
