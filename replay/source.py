"""A recording as it streams: metadata up front, sensor samples in time slices, never the whole file.

Every reader returns a :class:`RecordingSource` (``replay.formats.open_recording``); ``read_recording``
collects one into a :class:`~replay.recording.Recording` (:meth:`RecordingSource.collect`), so there is
one code path.  A source has

* metadata, known when it is opened: ``meta``, ``source``, ``format``; ``dropped`` (odd samples, by
  ``"stream:reason"``) is complete once the samples have been read;
* evaluation-only series — ``truth``, ``references``, ``temperature`` — loaded whole when the source is
  opened (or, for ``temperature``, when first asked for): they are small and only for sinks and scoring,
  never read by the pipeline;
* the sensor streams, as :class:`Feed` s: one per file, or one for an interleaved file that holds every
  stream (demultiplexed in one pass), each a parser advanced a chunk at a time, with a
  :class:`~replay.formats._common.StreamSpec` per stream that converts the chunks into the contract's units.

:class:`Merge` drives the feeds lazily and cuts time slices for the pipeline: a feed is advanced only when
one of its streams has no sample at or after the next slice edge, so it holds about one chunk per stream
(plus the first :data:`~replay.formats._common.UNIT_CHECK_SAMPLES` of a stream until its unit check has
run) — memory independent of the recording's length. (One interleaved file whose streams lie far apart in
time at the same place in the file — e.g. very different IPIN clock shifts — makes the merge hold that
lag's worth of the leading streams.)
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from replay.formats._common import Block, StreamSpec
from replay.recording import Recording, Stream

KEYS = ("accel", "gyro", "mag")  # the order streams are pushed in (and the summary's n_samples)


@dataclass
class Feed:
    """One pass of a parser.

    ``chunks()`` starts the pass and yields ``(bytes_consumed, {key: (t, v)})`` after each chunk: the rows
    cleaned since the previous chunk (:class:`~replay.formats._common.StreamBuilder`), in the file's units,
    for streams among ``keys``. ``size`` is the bytes the pass reads in all (for progress; 0 = unknown).
    """

    keys: tuple[str, ...]
    chunks: Callable[[], Iterator[tuple[int, dict[str, Block]]]]
    size: int = 0


class RecordingSource:
    """A recording opened for streaming (see the module docstring).

    Parameters
    ----------
    specs : dict
        ``{key: StreamSpec}`` of the streams the recording may have (``mag`` always).
    feeds : list of Feed
        Together they feed every key of ``specs``, each key from one feed.
    meta, source, format, dropped, truth, references :
        As in :class:`~replay.recording.Recording`.
    temperature : (t, °C) or a callable returning it (read when first asked for), or None.
    """

    def __init__(
        self,
        specs: dict[str, StreamSpec],
        feeds: list[Feed],
        *,
        meta: dict | None = None,
        source: str = "",
        format: str = "",  # noqa: A002 — the Recording's attribute name
        dropped: Counter | None = None,
        truth=None,
        references: dict | None = None,
        temperature=None,
    ):
        self.specs = specs
        self.feeds = feeds
        self.meta = meta if meta is not None else {}
        self.source = source
        self.format = format
        self.dropped = dropped if dropped is not None else Counter()
        self.truth = truth
        self.references = references or {}
        self._temperature = temperature

    @property
    def temperature(self):
        if callable(self._temperature):
            self._temperature = self._temperature()
        return self._temperature

    @property
    def size(self) -> int:
        return sum(f.size for f in self.feeds)

    @classmethod
    def from_recording(cls, rec: Recording) -> RecordingSource:
        """A recording already in memory, as a source (its streams pass through, one block each; a sample
        beyond :data:`~replay.formats._common.PHYSICAL_LIMITS` is dropped, as any reader drops it)."""
        specs, feeds = {}, []
        for key in KEYS:
            s = getattr(rec, key)
            if s is None:
                continue
            specs[key] = StreamSpec(
                rec.source, key, check=False, limit_known=True, min_samples=0, optional=True
            )
            feeds.append(Feed((key,), lambda key=key, s=s: iter([(0, {key: (s.t, s.xyz)})])))
        return cls(
            specs, feeds, meta=rec.meta, source=rec.source, format=rec.format, dropped=Counter(rec.dropped),
            truth=rec.truth, references=rec.references, temperature=rec.temperature,
        )

    def collect(self) -> Recording:
        """Read every stream whole into a :class:`Recording` (feed after feed)."""
        conv = {k: spec.converter(self.dropped) for k, spec in self.specs.items()}
        parts: dict[str, list[Block]] = {k: [] for k in self.specs}
        for feed in self.feeds:
            for _, chunk in feed.chunks():
                for k, (t, v) in chunk.items():
                    if k in conv:
                        parts[k].extend(conv[k].push(t, v))
            for k in feed.keys:
                parts[k].extend(conv[k].end())
        streams = {
            k: Stream(np.concatenate([t for t, _ in p]), np.concatenate([v for _, v in p]))
            for k, p in parts.items()
            if p
        }
        return Recording(
            mag=streams["mag"],
            accel=streams.get("accel"),
            gyro=streams.get("gyro"),
            meta=self.meta,
            truth=self.truth,
            temperature=self.temperature,
            references=self.references,
            source=self.source,
            format=self.format,
            dropped=self.dropped,
        )


class Merge:
    """The streams of a source, merged by time into slices (reads the first chunk of every stream).

    Attributes
    ----------
    t0 : float
        The first sample time of any stream.
    starts : dict
        The first sample time of each stream present, s.
    present : tuple of str
        The streams with samples, in push order (:data:`KEYS`).
    max_pending : dict
        The most samples of each stream held here at once (converted, not yet yielded).
    """

    def __init__(self, src: RecordingSource):
        self.src = src
        self.conv = {k: spec.converter(src.dropped) for k, spec in src.specs.items()}
        self.pending: dict[str, list[Block]] = {k: [] for k in src.specs}
        self.done = dict.fromkeys(src.specs, False)
        self.t_last = dict.fromkeys(src.specs, -np.inf)
        self.max_pending = dict.fromkeys(src.specs, 0)
        self.feed_of = {k: i for i, f in enumerate(src.feeds) for k in f.keys}
        self.iters: list = [None] * len(src.feeds)
        self.positions = [0] * len(src.feeds)
        for k in src.specs:
            self._ensure(k, -np.inf)
        self.present = tuple(k for k in KEYS if k in src.specs and self.pending[k])
        self.starts = {k: float(self.pending[k][0][0][0]) for k in self.present}
        self.t0 = min(self.starts.values())

    @property
    def position(self) -> int:
        """Bytes of input consumed so far (for progress against ``src.size``)."""
        return sum(self.positions)

    def _pull(self, i: int) -> None:
        feed = self.src.feeds[i]
        if self.iters[i] is None:
            self.iters[i] = feed.chunks()
        try:
            self.positions[i], chunk = next(self.iters[i])
        except StopIteration:
            for k in feed.keys:
                self._add(k, self.conv[k].end())
                self.done[k] = True
            return
        for k, (t, v) in chunk.items():
            if k in self.conv:
                self._add(k, self.conv[k].push(t, v))

    def _add(self, k: str, blocks: list[Block]) -> None:
        if blocks:
            self.pending[k].extend(blocks)
            self.t_last[k] = float(blocks[-1][0][-1])
            self.max_pending[k] = max(self.max_pending[k], sum(len(t) for t, _ in self.pending[k]))

    def _ensure(self, k: str, edge: float) -> None:
        """Advance ``k``'s feed until ``k`` has a sample at or after ``edge``, or has ended."""
        while not self.done[k] and (not self.pending[k] or self.pending[k][-1][0][-1] < edge):
            self._pull(self.feed_of[k])

    def _cut(self, k: str, edge: float) -> Block | None:
        """The pending samples of ``k`` with ``t < edge`` (removed from pending), or None."""
        out, blocks = [], self.pending[k]
        while blocks:
            t, v = blocks[0]
            if t[-1] < edge:
                out.append(blocks.pop(0))
                continue
            j = int(np.searchsorted(t, edge, side="left"))
            if j:
                out.append((t[:j], v[:j]))
                blocks[0] = (t[j:], v[j:])
            break
        if len(out) <= 1:
            return out[0] if out else None
        return np.concatenate([t for t, _ in out]), np.concatenate([v for _, v in out])

    @staticmethod
    def _edge(k: int, start: float, slice_s: float, delta: float) -> float:
        """Edge ``k`` of :meth:`slices`, by numpy's ``arange`` formula (``delta``: see there)."""
        return start if k == 0 else start + slice_s if k == 1 else start + k * delta

    def _next_edge(self, k: int, start: float, slice_s: float, delta: float) -> int:
        """``k``, or the index of the first edge after the earliest pending sample when that sample lies at or
        beyond edge ``k`` (a gap in every stream: its empty slices are skipped, however long the gap)."""
        first = min((blocks[0][0][0] for blocks in (self.pending[key] for key in self.present) if blocks),
                    default=-np.inf)
        if first < self._edge(k, start, slice_s, delta):
            return k
        i = max(k, int((first - start) // delta))
        while self._edge(i, start, slice_s, delta) <= first:
            i += 1
        return i

    def slices(self, slice_s: float) -> Iterator[tuple[bool, dict[str, Block]]]:
        """Yield ``(final, {key: (t, xyz)})``: each stream's samples before the next edge, then the rest.

        The edges are ``np.arange(t0 + slice_s, t1 + slice_s, slice_s)`` (``t1``: the last sample time of
        any stream), computed one at a time with numpy's own formula — ``start``, ``start + slice_s``, then
        ``start + k·((start + slice_s) − start)`` — so they are bit-identical without knowing ``t1`` before
        the streams end. A slice is cut once every stream has a sample at or after its edge, or has ended.
        The last item (``final``) holds everything after the last edge.  A slice in which no stream has a
        sample (a gap in the recording) is not yielded.
        """
        start = self.t0 + slice_s
        delta = (start + slice_s) - start
        n_edges = None
        k = 0
        while True:
            edge = self._edge(k, start, slice_s, delta)
            if n_edges is None:
                for key in self.present:
                    self._ensure(key, edge)
                if all(self.done.values()):
                    t1 = max(self.t_last[key] for key in self.present)
                    n_edges = len(np.arange(start, t1 + slice_s, slice_s))
            if n_edges is not None and k >= n_edges:
                break
            after = self._next_edge(k, start, slice_s, delta)
            if after > k:  # no stream has a sample before this edge: on to the first edge after one
                k = after
                continue
            yield False, {key: self._cut(key, edge) for key in self.present}
            k += 1
        yield True, {key: self._cut(key, np.inf) for key in self.present}
