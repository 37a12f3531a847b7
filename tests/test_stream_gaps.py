"""Gaps in a recording's streams (``pdr_mag/pipeline/stream_gaps.py``): found inside, at the start and at
the end, the same however the samples are chunked, by the library's pipeline (events, summary, resumable
state), in ``replay``'s summary, on the console and to the sinks."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pdr_mag.pipeline import HeadingPipeline
from pdr_mag.pipeline.stream_gaps import MIN_GAP_S, RATE_SAMPLES, StreamGaps
from pdr_mag.sinks import QuietSink
from replay.cli import main
from replay.formats import pdrcsv
from replay.recording import Recording, Stream
from replay.run import replay
from tests.test_online import synth_walk
from tests.test_pipeline import META


def _gaps(streams: dict, chunk: int = 10**9) -> StreamGaps:
    """Feed each stream's times in chunks of ``chunk`` samples, interleaved as a replay's slices are."""
    g = StreamGaps()
    longest = max(len(t) for t in streams.values())
    for lo in range(0, longest, chunk):
        for name, t in streams.items():
            g.add(name, t[lo : lo + chunk])
    g.finish()
    return g


def test_a_gap_inside_a_stream_and_a_stream_that_ends_early_are_found():
    t = np.arange(0.0, 60.0, 0.01)
    gyro = t[(t < 20.0) | (t >= 23.0)]  # 3 s without samples
    accel = t[t < 40.0]  # stops 20 s before the others
    g = _gaps({"accel": accel, "gyro": gyro, "mag": t[::2]})
    got = {(x["stream"], x["where"]): x for x in g.gaps}
    assert set(got) == {("gyro", "inside"), ("accel", "end")}
    gap = got[("gyro", "inside")]
    assert gap["t_from"] == pytest.approx(19.99, abs=1e-6) and gap["t_to"] == pytest.approx(23.0, abs=1e-6)
    assert got[("accel", "end")]["duration_s"] == pytest.approx(60.0 - 0.01 - 39.99, abs=1e-6)
    s = g.summary()
    assert s["n"] == 2 and s["per_stream"]["gyro"] == {"n": 1, "total_s": pytest.approx(3.01, abs=1e-3)}
    assert s["threshold_s"] == {"accel": MIN_GAP_S, "gyro": MIN_GAP_S, "mag": MIN_GAP_S}


def test_a_stream_that_starts_late_and_the_threshold_follows_a_slow_stream():
    t = np.arange(0.0, 100.0, 0.01)
    mag = np.arange(8.0, 100.0, 1.0)  # 1 Hz: gaps of 1 s are its rate, not gaps; it starts 8 s late
    mag = mag[(mag < 50.0) | (mag > 53.0)]  # a 4-s interval: below 5 periods
    g = _gaps({"accel": t, "gyro": t, "mag": mag})
    assert g.threshold["mag"] == pytest.approx(5.0)
    assert [(x["stream"], x["where"], x["t_to"]) for x in g.gaps] == [("mag", "start", 8.0)]
    mag2 = mag[(mag < 60.0) | (mag > 70.0)]  # 11 s: a gap
    g = _gaps({"accel": t, "gyro": t, "mag": mag2})
    assert [(x["stream"], x["where"]) for x in g.gaps] == [("mag", "start"), ("mag", "inside")]


@pytest.mark.parametrize("chunk", [1, 7, RATE_SAMPLES, 5000])
def test_the_gaps_do_not_depend_on_how_the_samples_are_chunked(chunk):
    rng = np.random.default_rng(3)
    t = np.cumsum(rng.uniform(0.005, 0.015, 6000))
    gyro = t[(t < 0.5) | ((t > 1.9) & (t < 30.0)) | (t > 31.5)]  # a gap before the rate is known, one after
    streams = {"accel": t, "gyro": gyro, "mag": t[::3][:1500]}
    ref = _gaps(streams).summary()
    assert ref["n"] == 3  # the two gyro gaps and the magnetometer's early end
    assert _gaps(streams, chunk).summary() == ref


def test_a_short_recording_sets_its_thresholds_at_the_end():
    t = np.arange(0.0, 1.5, 0.01)  # fewer samples than RATE_SAMPLES
    g = _gaps({"accel": t, "gyro": t[(t < 0.1) | (t > 1.2)], "mag": t})
    assert [(x["stream"], x["where"]) for x in g.gaps] == [("gyro", "inside")]


class _Events(QuietSink):
    def __init__(self):
        self.events = []

    def event(self, ev) -> None:
        self.events.append(ev)


def test_replay_reports_a_gyroscope_that_stops_and_warns_the_sinks(tmp_path, capsys):
    """A gyroscope that stops at 18 s of a 30-s walk: the rows end there (they follow the gyroscope), the
    summary and the console say so, and the sinks get a ``stream_gap`` event at the gap's start."""
    d = synth_walk(duration=30.0, seed=21)
    tg, wg = d["gyro"]
    keep = tg < 18.0
    rec = Recording(mag=Stream(*d["mag"]), accel=Stream(*d["accel"]), gyro=Stream(tg[keep], wg[keep]),
                    meta=dict(META))
    sink = _Events()
    summary = replay(rec, sinks=[sink], progress=False)
    gaps = summary["stream_gaps"]
    assert gaps["n"] == 1 and gaps["per_stream"]["gyro"]["n"] == 1
    gap = gaps["gaps"][0]
    assert gap["where"] == "end" and gap["t_from"] == pytest.approx(tg[keep][-1], abs=1e-6)
    assert gap["duration_s"] == pytest.approx(12.0, abs=0.1)
    ev = [e for e in sink.events if e.kind == "stream_gap"]
    assert len(ev) == 1 and ev[0].t == pytest.approx(gap["t_from"]) and ev[0].data["stream"] == "gyro"
    assert summary["n_outputs"] < 0.65 * 30.0 * 50  # the rows stop with the gyroscope (50 Hz output)
    assert all(e["kind"] != "stream_gap" for e in summary["events"])  # the pipeline's events only

    p = tmp_path / "walk"
    pdrcsv.write(rec, p)
    out = tmp_path / "s.json"
    assert main(["replay", str(p), "--json", str(out), "--no-progress"]) == 0
    line = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("stream gaps"))
    assert "gyro 1" in line and "ends 12.0 s before the others: no output rows after 18.0 s" in line
    assert json.loads(out.read_text())["stream_gaps"] == json.loads(json.dumps(gaps))


def test_a_recording_without_gaps_says_none():
    d = synth_walk(duration=20.0, seed=4)
    rec = Recording(**{k: Stream(*d[k]) for k in ("mag", "accel", "gyro")}, meta=dict(META))
    summary = replay(rec, progress=False)
    assert summary["stream_gaps"]["n"] == 0 and summary["stream_gaps"]["gaps"] == []


def _gappy_walk() -> dict:
    """A 40-s simulated walk whose gyroscope pauses 3 s at 15 s and whose magnetometer stops at 30 s."""
    d = synth_walk(duration=40.0, seed=5)
    tg, wg = d["gyro"]
    keep = (tg < 15.0) | (tg >= 18.0)
    tm, xm = d["mag"]
    return {"accel": d["accel"], "gyro": (tg[keep], wg[keep]), "mag": (tm[tm < 30.0], xm[tm < 30.0])}


def _push_in_slices(pipe: HeadingPipeline, streams: dict, t_from: float, t_to: float, step: float) -> list:
    """Push the streams' samples in [t_from, t_to) in slices of ``step`` s, polling after each; the events."""
    events = []
    for lo in np.arange(t_from, t_to, step):
        for name, (t, x) in streams.items():
            m = (t >= lo) & (t < min(lo + step, t_to))
            pipe.push_arrays(name, t[m], x[m])
        pipe.poll()
        events += pipe.pop_events()
    return events


def test_the_library_pipeline_reports_gaps_as_events_and_in_its_summary():
    """A backend pushing samples learns of a paused gyroscope when it resumes and of a magnetometer that
    stopped at the end, as ``stream_gap`` events, and its summary counts them however it pushed."""
    walk = _gappy_walk()
    pipe = HeadingPipeline(meta=dict(META))
    events = _push_in_slices(pipe, walk, 0.0, 40.0, 0.7)
    inside = [e for e in events if e.kind == "stream_gap"]
    assert [(e.data["stream"], e.data["where"]) for e in inside] == [("gyro", "inside")]
    assert inside[0].t == pytest.approx(15.0, abs=0.02)
    assert inside[0].data["t_to"] == pytest.approx(18.0, abs=0.02)
    pipe.flush()
    end = [e for e in pipe.pop_events() if e.kind == "stream_gap"]
    assert [(e.data["stream"], e.data["where"]) for e in end] == [("mag", "end")]
    assert end[0].t == pytest.approx(30.0, abs=0.03)
    assert end[0].data["duration_s"] == pytest.approx(10.0, abs=0.05)
    summary = pipe.summary()["stream_gaps"]
    assert summary["n"] == 2 and set(summary["per_stream"]) == {"gyro", "mag"}

    once = HeadingPipeline(meta=dict(META))
    once.run(walk)
    assert once.summary()["stream_gaps"] == summary
    assert sorted((e.t, e.data["stream"]) for e in once.pop_events() if e.kind == "stream_gap") == sorted(
        (e.t, e.data["stream"]) for e in inside + end)


def test_a_pipeline_resumed_from_its_state_inside_a_gap_finds_the_same_gaps():
    """The gap tracker is part of the resumable state: a pipeline stopped during the gyroscope's pause and
    resumed from its JSON state reports the same gaps as one that ran through."""
    walk = _gappy_walk()
    through = HeadingPipeline(meta=dict(META))
    _push_in_slices(through, walk, 0.0, 40.0, 1.0)
    through.flush()
    first = HeadingPipeline(meta=dict(META))
    _push_in_slices(first, walk, 0.0, 16.0, 1.0)
    state = json.loads(json.dumps(first.get_state()))
    resumed = HeadingPipeline(meta=dict(META))
    resumed.set_state(state)
    events = _push_in_slices(resumed, walk, 16.0, 40.0, 1.0)
    resumed.flush()
    events += resumed.pop_events()
    assert [e.data["stream"] for e in events if e.kind == "stream_gap"] == ["gyro", "mag"]
    assert resumed.summary()["stream_gaps"] == through.summary()["stream_gaps"]
