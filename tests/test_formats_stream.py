"""Streaming readers (issue 5): every reader gives the same samples read in tiny chunks as read whole, the
merge cuts the same slices as ``np.arange`` edges, holds a bounded number of samples, and a late error still
names its line; replay from a path equals replay from a Recording."""

from __future__ import annotations

import itertools
import shutil
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from replay.cli import main
from replay.errors import InputError
from replay.formats import _common, open_recording, read_recording
from replay.recording import Recording, Stream
from replay.run import CsvSink, replay
from replay.source import KEYS, Merge, RecordingSource
from tests.conftest import dataset
from tests.test_formats_detect import FIX, FIXTURES, REAL
from tests.test_formats_mcap import _rec, _write
from tests.test_formats_ros2 import write_bag

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture
def tiny(monkeypatch):
    """Chunks of 7 rows and a unit check on the first 5 samples: many blocks in every stream."""
    monkeypatch.setattr(_common, "CHUNK", 7)
    monkeypatch.setattr(_common, "UNIT_CHECK_SAMPLES", 5)


def _same(a: Recording, b: Recording) -> None:
    for key in KEYS:
        sa, sb = getattr(a, key), getattr(b, key)
        assert (sa is None) == (sb is None), key
        if sa is not None:
            np.testing.assert_array_equal(sa.t, sb.t)
            np.testing.assert_array_equal(sa.xyz, sb.xyz)
    assert a.dropped == b.dropped
    assert a.meta == b.meta


def _merged(src: RecordingSource, slice_s: float = 2.0) -> Recording:
    """The source's samples as the merge yields them, concatenated."""
    m = Merge(src)
    parts: dict[str, list] = {k: [] for k in m.present}
    for _, blocks in m.slices(slice_s):
        for k, b in blocks.items():
            if b is not None:
                parts[k].append(b)
    streams = {k: Stream(*map(np.concatenate, zip(*p, strict=True))) for k, p in parts.items()}
    return Recording(
        mag=streams["mag"], accel=streams.get("accel"), gyro=streams.get("gyro"), meta=src.meta,
        dropped=src.dropped,
    )


def _mcap(tmp_path: Path) -> Path:
    return _write(_rec(n=300), tmp_path / "rec.mcap")


def _paths(tmp_path):
    """The fixtures of every reader (always here); the real recordings are :func:`_real_paths`."""
    yield from (FIX / name for name in sorted(FIXTURES))
    yield Path(shutil.make_archive(str(tmp_path / "ios"), "zip", FIX / "sensorlogger_ios"))  # a zip export
    yield _mcap(tmp_path)
    yield write_bag(tmp_path / "bag.mcap", n=120)


def _real_paths(tmp_path):
    for parts in sorted(REAL):
        yield dataset(*parts)


@pytest.mark.parametrize("paths", [_paths, _real_paths], ids=["fixtures", "real"])
def test_every_reader_streams_the_same_samples(tmp_path, monkeypatch, paths):
    whole = {p: read_recording(p) for p in paths(tmp_path)}
    monkeypatch.setattr(_common, "CHUNK", 7)
    monkeypatch.setattr(_common, "UNIT_CHECK_SAMPLES", 5)
    for p, rec in whole.items():
        _same(read_recording(p), rec)
        _same(_merged(open_recording(p)), rec)


def test_saturation_running_count_equals_whole_count():
    rng = np.random.default_rng(4)
    xyz = rng.normal(0.0, 6.0, (3000, 3))
    xyz[100:110, 0] = 19.6  # clipped early …
    xyz[2000:2004, 0] = -39.2  # … then at a larger range: the first ones no longer count
    xyz[2500:2503, 2] = 29.4
    xyz[2500, 0] = 39.2  # a row at two peaks counts once
    whole = Counter()
    n = _common.flag_saturation("accel", xyz, whole)
    assert n == 4 + 1 + 3 - 1 and whole == {"accel:saturated": n}
    for cut in ([1, 2, 105, 2001, 2999], list(range(0, 3000, 7))):
        sat = _common.Saturation("accel")
        for a, b in zip([0, *cut], [*cut, 3000], strict=True):
            sat.update(xyz[a:b])
        assert sat.count() == n


def test_slices_are_the_arange_edges():
    """Each slice holds the samples between two consecutive ``np.arange`` edges (the last: everything after
    the last edge); a slice in which no stream has a sample is not yielded."""
    rng = np.random.default_rng(5)
    n_empty = 0
    for _ in range(20):
        t0 = rng.uniform(-1e4, 1e9)
        t = {k: np.sort(t0 + rng.uniform(0.0, 37.0, 5 + i)) for i, k in enumerate(KEYS)}
        t["mag"][0] = t0
        rec = Recording(**{k: Stream(v, np.ones((len(v), 3))) for k, v in t.items()})
        edges = np.arange(rec.t0 + 2.0, rec.t1 + 2.0, 2.0)
        slices = list(Merge(RecordingSource.from_recording(rec)).slices(2.0))
        assert slices[-1][0] and not any(final for final, _ in slices[:-1])
        seen = []
        for final, blocks in slices:
            where = {int(np.searchsorted(edges, x, side="right")) for b in blocks.values() if b is not None
                     for x in b[0]}
            assert len(where) == 1 or (final and not where)  # one interval between edges per slice
            seen += list(where)
        assert seen == sorted(seen)
        n_empty += len(edges) + 1 - len(slices)
        n = sum(len(b[0]) for _, bl in slices for b in bl.values() if b is not None)
        assert n == sum(map(len, t.values()))
    assert n_empty > 0  # the sparse streams leave slices empty: they were skipped


def test_a_gap_of_years_in_every_stream_is_crossed_at_once():
    """Streams that stop and go on 10⁹ s later (a logger's clock re-based; time read in the wrong unit is the
    readers' error) give the slices on either side of the gap, not the 5·10⁸ empty slices in between."""
    t = np.arange(0.0, 10.0, 0.01)
    t = np.concatenate([t, t + 1e9])
    rec = Recording(**{k: Stream(t, np.ones((len(t), 3))) for k in KEYS})
    slices = list(itertools.islice(Merge(RecordingSource.from_recording(rec)).slices(2.0), 100))
    assert len(slices) == 11 and slices[-1][0]  # 5 before the gap, 5 after it, the final one
    assert sum(len(b[0]) for _, bl in slices for b in bl.values() if b is not None) == len(KEYS) * len(t)


def _pdrcsv(path: Path, seconds: float, rate: float = 100.0) -> Path:
    rng = np.random.default_rng(6)
    path.mkdir()
    for name, centre in (("mag", [20.0, 0.0, -40.0]), ("accel", [0.0, 0.0, 9.81]), ("gyro", [0.0, 0.0, 0.0])):
        t = np.arange(int(seconds * rate)) / rate
        v = np.asarray(centre) + rng.normal(0.0, 0.05, (len(t), 3))
        rows = "\n".join(f"{a:.3f},{x:.5f},{y:.5f},{z:.5f}" for a, (x, y, z) in zip(t, v, strict=True))
        (path / f"{name}.csv").write_text("t,x,y,z\n" + rows + "\n")
    return path


def _xio(path: Path, seconds: float, rate: float = 100.0) -> Path:
    """An x-io CSV (one interleaved file for the three streams), deg/s, g, µT."""
    rng = np.random.default_rng(7)
    sensors = (("Gyroscope", "deg/s"), ("Accelerometer", "g"), ("Magnetometer", "uT"))
    cols = [f"{s} {a} ({u})" for s, u in sensors for a in "XYZ"]
    t = np.arange(int(seconds * rate)) / rate
    v = np.asarray([0, 0, 0, 0, 0, 1, 20, 0, -40.0]) + rng.normal(0.0, 0.05, (len(t), 9))
    rows = "\n".join(",".join(f"{x:.5f}" for x in (a, *r)) for a, r in zip(t, v, strict=True))
    path.write_text("Time (s)," + ",".join(cols) + "\n" + rows + "\n")
    return path


@pytest.mark.parametrize("write,name", [(_pdrcsv, "r"), (_xio, "r.csv")])
def test_merge_holds_a_bounded_number_of_samples(tmp_path, tiny, write, name):
    held = {}
    for seconds in (20.0, 80.0):
        src = open_recording(write(tmp_path / f"{seconds:g}{name}", seconds))
        m = Merge(src)
        n = sum(len(b[0]) for _, blocks in m.slices(2.0) for b in blocks.values() if b is not None)
        assert n == 3 * int(seconds * 100) and m.position == src.size  # progress: every byte read
        held[seconds] = max(m.max_pending.values())
    # one slice (2 s at 100 Hz) plus one chunk, whatever the length
    assert held[20.0] == held[80.0] <= 200 + _common.CHUNK


def test_late_error_names_its_line_after_slices_went_through(tmp_path, tiny, capsys):
    rec = _pdrcsv(tmp_path / "r", 30.0)
    lines = (rec / "gyro.csv").read_text().splitlines(keepends=True)
    # line 2501, in the 358th chunk: a row cut short, where the file ends (inside it, it would be dropped)
    (rec / "gyro.csv").write_text("".join(lines[:2500]) + "25.0,0,0\n")
    m = Merge(open_recording(rec))
    done = 0
    with pytest.raises(InputError) as err:
        for _ in m.slices(2.0):
            done += 1
    problem = "expected at least 4 columns, got 3 (truncated file?)"
    assert done >= 10 and str(err.value) == f"{rec / 'gyro.csv'}:2501: {problem}"
    assert main(["replay", str(rec), "-q"]) == 2
    out = capsys.readouterr()
    assert out.err.strip().splitlines() == [f"pdr-mag: {rec / 'gyro.csv'}:2501: {problem}"]
    lines[2500] = "1.0,0,0,0\n"  # time going backwards, across chunk boundaries
    (rec / "gyro.csv").write_text("".join(lines))
    assert main(["replay", str(rec), "-q"]) == 2
    err = capsys.readouterr().err
    assert err == f"pdr-mag: {rec / 'gyro.csv'}:2501: gyro: time goes backwards (1.0 after 24.98)\n"


def test_unit_check_on_the_first_samples(tmp_path, tiny):
    rec = _pdrcsv(tmp_path / "r", 1.0)
    text = (rec / "mag.csv").read_text().replace("20.", "20000.")  # nT read as µT
    (rec / "mag.csv").write_text(text)
    with pytest.raises(InputError, match=r"median \|mag\| is .* outside the plausible"):
        Merge(open_recording(rec))


@pytest.mark.parametrize("name", ["walk", "mixed"])
def test_replay_from_path_equals_replay_from_recording(tmp_path, tiny, name):
    path = ROOT / "recordings" / name
    a, b = tmp_path / "path.csv", tmp_path / "rec.csv"
    sa = replay(path, sinks=[CsvSink(a)], progress=True)  # a bar over the bytes read
    sb = replay(read_recording(path), sinks=[CsvSink(b)], progress=True)  # a bar without a total
    assert a.read_bytes() == b.read_bytes() and a.stat().st_size > 1000
    for s in (sa, sb):
        s.pop("elapsed_s"), s.pop("samples_per_s"), s.pop("compile_s")
    assert sa == sb
