"""Shared pieces of the readers: a stream accumulator that cleans rows as they arrive, unit checks, parsing.

Every reader feeds rows one at a time (or in chunks) into a :class:`StreamBuilder`, which

* drops a row with a NaN/inf value (``"<key>:nan"``), a row whose time repeats the previous one
  (``"<key>:duplicate_t"``) and an attitude row that is no unit quaternion (``"<key>:not_unit"``,
  :data:`QUAT_NORM`), counting them in the recording's ``dropped`` counter;
* raises :class:`~replay.errors.InputError` naming the file and line when time goes backwards;
* flags (keeps, but counts as ``"<key>:saturated"``) samples with an axis at the sensor's range limit,
  when the reader knows that limit;
* stores values in compact ``array('d')`` buffers (8 bytes a number, not a Python float object each).

A garbled text row never reaches a builder as a sample: a row with more fields than the header (or the
format) defines, :data:`EXTRA_FIELDS`, or with a field anywhere in it that is not a number,
:data:`NON_NUMERIC`, is dropped whole, never read in part, and counted in the recording's ``dropped``:
every text parser (:func:`iter_table` here, the readers' own line parsers) decides and counts it with
:func:`row_values`. A row with fewer fields than the format needs is judged by :class:`ShortRows`: as the
file's last row, a file cut short (an :class:`~replay.errors.InputError`); with rows after it, a garbled
row like the others (:data:`SHORT_ROW`).

Readers stream: after every chunk (:data:`CHUNK` lines or messages) a parser hands the rows cleaned so far
on (:meth:`StreamBuilder.take`), so a builder never holds more than one chunk. A :class:`StreamSpec` says
how a stream's rows become the contract's units; its :class:`Converter` converts block by block and runs the
checks that used to look at the whole stream, in streaming form:

* the unit plausibility checks (median vector norm, µT / m/s² / rad/s, and median sample interval, s — a
  file in the wrong unit) look at the first :data:`UNIT_CHECK_SAMPLES` samples (or all, when the stream is
  shorter): blocks are held back until they have run;
* a sample with an axis beyond :data:`PHYSICAL_LIMITS` (a corrupt number: no sensor of the kind reports it)
  is dropped and counted (``"<key>:implausible"``);
* the too-few-samples check runs when the stream ends;
* where the reader does not know the sensor's range, :class:`Saturation` counts clipped samples with a
  running per-axis peak; the count is exactly :func:`flag_saturation`'s on the whole stream, and it enters
  ``dropped`` when the stream ends.

:func:`iter_table` parses numeric text in chunks (numpy fast path, exact-line errors), :class:`Bundle`
reads the files of a folder or a zip export as streams, :func:`iter_csv` reads quoted CSV.
"""

from __future__ import annotations

import csv
import io
import itertools
import math
import zipfile
import zlib
from array import array
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pdr_mag.units import time_unit_problem, unit_problem
from replay.errors import InputError

#: Rows (text lines, messages) a parser reads before it hands its cleaned rows on; tests make it tiny.
#: Three files read side by side hold three chunks of text lines at once: 8192 keeps that to a few MB, and
#: larger chunks are no faster (benchmarks/replay_memory.py: 65536 lines cost +50 MB of peak memory).
CHUNK = 8192
#: The unit check looks at the median norm of a stream's first this many samples.
UNIT_CHECK_SAMPLES = 4096

Block = tuple[np.ndarray, np.ndarray]

#: Reasons a garbled text row is dropped (``"<stream>:<reason>"`` in ``dropped``): more fields than the
#: header or the format defines, and a field (any of the row's) that is not a number.
EXTRA_FIELDS = "extra_fields"
NON_NUMERIC = "non_numeric"
#: … and a row with fewer fields than the format needs that more rows follow (:class:`ShortRows`)
SHORT_ROW = "short_row"

#: An attitude row (``width=4``: truth, the phone's own) is a quaternion of norm 1 up to its rounding; one
#: outside this band (an all-zero row, a logging glitch) is no attitude: dropped (``"<key>:not_unit"``).
QUAT_NORM = (0.5, 1.5)
#: Largest |axis| a sample of each stream may hold, in the contract's units: about twice the widest range any
#: MEMS sensor of the kind offers (magnetometers ±4.9 mT, accelerometers ±400 g, gyroscopes ±4000 °/s).
#: Beyond it a number is corrupt, not a measurement: the sample is dropped (``"<key>:implausible"``).
PHYSICAL_LIMITS = {"mag": 1.0e4, "accel": 1.0e4, "gyro": 150.0}


def is_float(v: str) -> bool:
    try:
        float(v)
        return True
    except ValueError:
        return False


class ShortRows:
    """The rows of a text file with fewer fields than its format needs.

    The last row of a file is short when the logger stopped in the middle of writing it: the file is cut
    short, an :class:`~replay.errors.InputError` naming that row (raised by :meth:`end`, when the file ends
    there).  A short row that more rows follow is a garbled row inside a good file (a write interrupted and
    resumed): dropped and counted under ``"<key>:short_row"`` (:data:`SHORT_ROW`) for each stream it would
    have fed, as :func:`row_values` counts the others.  A parser calls :meth:`found` for a short row,
    :meth:`follows` for every other row (a cheap test while nothing is pending) and :meth:`end` at the end
    of the file."""

    __slots__ = ("path", "dropped", "pending")

    def __init__(self, path, dropped: Counter):
        self.path = path
        self.dropped = dropped
        self.pending: tuple | None = None  # (line number, message, stream keys) of the last short row

    def found(self, lineno: int, message: str, keys=()) -> None:
        """Row ``lineno`` is short (``message`` says how, for the error if it is the last)."""
        self.follows()
        self.pending = (lineno, message, tuple(keys))

    def follows(self) -> None:
        """Another row was read: a short row before it was inside the file."""
        if self.pending is not None:
            for key in self.pending[2]:
                self.dropped[f"{key}:{SHORT_ROW}"] += 1
            self.pending = None

    def end(self) -> None:
        """The file ended: a short row pending was its last, the file is cut short."""
        if self.pending is not None:
            lineno, message, _ = self.pending
            raise InputError(self.path, message, lineno)


def row_values(
    parts, most: int, *, dropped: Counter | None = None, keys=(), numeric: int | None = None
) -> list[float] | None:
    """The fields of a text row as floats, or None for a garbled row: the one rule of every text reader.

    A row is garbled when it has more than ``most`` fields (:data:`EXTRA_FIELDS`, the reason given when it is
    both) or a field that is not a number (:data:`NON_NUMERIC`) among its first ``numeric`` fields (default
    all of them; the fields after those are the caller's, e.g. a name that may be text, and are not
    returned). A garbled row is dropped whole, never read in part, and counted once in ``dropped`` under
    ``"<key>:<reason>"`` for each of ``keys``, the streams it would have fed (no keys: not counted, for a
    pass whose rows another pass counts). Fewer fields than the format needs are the caller's to judge (a
    truncated file, or a value missing).
    """
    if len(parts) > most:
        why = EXTRA_FIELDS
    else:
        try:
            return [float(p) for p in (parts if numeric is None else parts[:numeric])]
        except ValueError:
            why = NON_NUMERIC
    for key in keys:
        dropped[f"{key}:{why}"] += 1
    return None


#: The UTF-8 byte-order mark a spreadsheet or a Windows tool may write at a text file's start: skipped.
BOM = b"\xef\xbb\xbf"


def read_text(path: Path) -> str:
    """A whole small text file (metadata, a header file), UTF-8, a byte-order mark skipped."""
    return Path(path).read_text(encoding="utf-8-sig", errors="replace")


def head_bytes(path: Path, n: int) -> bytes:
    """A file's first ``n`` bytes, a byte-order mark skipped (a format's sniffer reads them)."""
    with Path(path).open("rb") as fh:
        return fh.read(n).removeprefix(BOM)


def open_text(path: Path):
    """Open a text file for line-by-line reading (UTF-8, a byte-order mark that a spreadsheet or a Windows
    tool wrote skipped), InputError if it cannot be opened."""
    try:
        return Path(path).open("r", encoding="utf-8-sig", errors="replace", newline="")
    except OSError as exc:
        raise InputError(path, f"cannot open ({exc.strerror})") from exc


def check_units(path, key: str, xyz: np.ndarray, unit_hint: str = "") -> None:
    """InputError when the median vector norm is outside the plausible range of ``key``
    (:func:`pdr_mag.units.unit_problem`)."""
    problem = unit_problem(key, xyz, unit_hint)
    if problem is not None:
        raise InputError(path, problem)


def check_time_unit(path, key: str, t: np.ndarray) -> None:
    """InputError when the median interval between the (cleaned, increasing) times ``t`` of a sensor stream is
    outside :data:`pdr_mag.units.SAMPLE_INTERVAL_S` (time not in seconds)."""
    problem = time_unit_problem(key, t)
    if problem is not None:
        raise InputError(path, problem)


class StreamBuilder:
    """Accumulate (t, x, y, z) rows of one stream, cleaning as they come.

    Parameters
    ----------
    path : path-like
        File named in errors.
    key : str
        ``"mag"``, ``"accel"``, ``"gyro"`` (or ``"truth"``, with ``width=4``).
    dropped : Counter
        The recording's counter of odd samples.
    width : int
        Number of values after the time (3 for vectors, 4 for quaternions).
    limit : float, optional
        Sensor range in the *source* units: a sample with any ``|axis| >= limit`` is counted as saturated.
    """

    def __init__(self, path, key: str, dropped: Counter, width: int = 3, limit: float | None = None):
        self.path = path
        self.key = key
        self.dropped = dropped
        self.width = width
        self.limit = limit
        self.t = array("d")
        self.v = array("d")
        self.last_t = -math.inf
        self.last_line: int | None = None

    def __len__(self) -> int:
        return len(self.t)

    def add(self, lineno: int | None, t: float, vals) -> bool:
        """Add one row; returns False when it was dropped (NaN, duplicate time)."""
        if not math.isfinite(t) or not all(math.isfinite(v) for v in vals):
            self.dropped[f"{self.key}:nan"] += 1
            return False
        if self.width == 4 and not QUAT_NORM[0] <= math.sqrt(sum(v * v for v in vals)) <= QUAT_NORM[1]:
            self.dropped[f"{self.key}:not_unit"] += 1
            return False
        if t == self.last_t:
            self.dropped[f"{self.key}:duplicate_t"] += 1
            return False
        if t < self.last_t:
            raise InputError(
                self.path, f"{self.key}: time goes backwards ({t!r} after {self.last_t!r})", lineno
            )
        if self.limit is not None and any(abs(v) >= self.limit for v in vals):
            self.dropped[f"{self.key}:saturated"] += 1
        self.last_t = t
        self.last_line = lineno
        self.t.append(t)
        self.v.extend(vals)
        return True

    def add_block(self, t: np.ndarray, vals: np.ndarray, first_line: int | None = None) -> None:
        """Add many rows at once (arrays already in memory, e.g. from a MATLAB file), same cleaning."""
        t = np.asarray(t, dtype=float)
        vals = np.asarray(vals, dtype=float).reshape(len(t), self.width)
        good = np.isfinite(t) & np.all(np.isfinite(vals), axis=1)
        self.count("nan", int((~good).sum()))
        if self.width == 4:
            norm = np.linalg.norm(vals, axis=1)
            unit = good & (norm >= QUAT_NORM[0]) & (norm <= QUAT_NORM[1])
            self.count("not_unit", int((good & ~unit).sum()))
            good = unit
        t, vals = t[good], vals[good]
        rows = np.flatnonzero(good)
        if len(t) == 0:
            return
        prev = np.concatenate([[self.last_t], t[:-1]])
        back = np.flatnonzero(t < prev)
        if len(back):
            i = back[0]
            line = None if first_line is None else first_line + int(rows[i])
            back, last = float(t[i]), float(prev[i])
            raise InputError(self.path, f"{self.key}: time goes backwards ({back!r} after {last!r})", line)
        keep = t != prev
        self.count("duplicate_t", int((~keep).sum()))
        t, vals = t[keep], vals[keep]
        if self.limit is not None:
            self.count("saturated", int(np.any(np.abs(vals) >= self.limit, axis=1).sum()))
        if len(t):
            self.last_t = float(t[-1])
            self.t.frombytes(np.ascontiguousarray(t, dtype=float).tobytes())
            self.v.frombytes(np.ascontiguousarray(vals, dtype=float).tobytes())

    def count(self, reason: str, n: int = 1) -> None:
        """Count ``n`` odd samples of this stream under ``"<key>:<reason>"``."""
        if n:
            self.dropped[f"{self.key}:{reason}"] += n

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        t = np.frombuffer(self.t, dtype=float).copy()
        v = np.frombuffer(self.v, dtype=float).copy().reshape(-1, self.width)
        return t, v

    def take(self) -> Block:
        """The rows added since the last ``take()`` (as :meth:`arrays`), and forget them (the cleaning state —
        last time, counters — carries on)."""
        out = self.arrays()
        self.t = array("d")
        self.v = array("d")
        return out


def take_all(builders: dict) -> dict[str, Block]:
    """``{key: builder.take()}`` of the builders that hold rows: what a parser yields after a chunk."""
    return {k: b.take() for k, b in builders.items() if len(b)}


#: Heuristic saturation (when the reader does not know the sensor's range): per axis, the largest |value| is
#: a clipped range limit if at least SAT_MIN_COUNT samples sit exactly on it and it is above the floor — the
#: smallest range phones use is ±2 g (19.6 m/s²) and ±250 deg/s (4.36 rad/s), so normal data never qualifies.
SAT_FLOOR = {"accel": 15.0, "gyro": 4.0}
SAT_MIN_COUNT = 3
_BITS = np.array([1, 2, 4])


class Saturation:
    """:func:`flag_saturation`'s count, streaming: a running per-axis peak of ``|value|``.

    Each sample is filed under the set of axes (a 3-bit pattern) at which it equals the running peak; when an
    axis's peak rises, the earlier samples lose that axis's bit. At the end, axis ``a`` qualifies when its
    peak is ≥ :data:`SAT_FLOOR` and at least :data:`SAT_MIN_COUNT` samples sit on it, and the count is the
    number of samples whose pattern holds a qualifying axis: exactly the whole-array count, from 8 counters.
    """

    def __init__(self, key: str):
        self.floor = SAT_FLOOR.get(key)
        self.peak = np.full(3, -np.inf)
        self.patterns = np.zeros(8, dtype=np.int64)

    def update(self, xyz: np.ndarray) -> None:
        if self.floor is None or len(xyz) == 0:
            return
        a = np.abs(xyz)
        peak = np.maximum(self.peak, a.max(axis=0))
        for axis in np.flatnonzero(peak > self.peak):
            bit = 1 << int(axis)
            for pat in range(8):
                if pat & bit and self.patterns[pat]:
                    self.patterns[pat & ~bit] += self.patterns[pat]
                    self.patterns[pat] = 0
        self.peak = peak
        self.patterns += np.bincount((a == peak) @ _BITS, minlength=8)

    def count(self) -> int:
        if self.floor is None:
            return 0
        per_axis = [int(self.patterns[[p for p in range(8) if p & (1 << a)]].sum()) for a in range(3)]
        hit = sum(1 << a for a in range(3) if self.peak[a] >= self.floor and per_axis[a] >= SAT_MIN_COUNT)
        return int(sum(self.patterns[p] for p in range(8) if p & hit))


def flag_saturation(key: str, xyz: np.ndarray, dropped: Counter) -> int:
    """Count (``<key>:saturated``) samples with an axis exactly at a clipped range limit; returns the count.

    Only for ``accel`` and ``gyro``, in the contract's units (see :data:`SAT_FLOOR`). Samples are kept.
    """
    sat = Saturation(key)
    sat.update(np.asarray(xyz, dtype=float).reshape(-1, 3))
    n = sat.count()
    if n:
        dropped[f"{key}:saturated"] += n
    return n


@dataclass(frozen=True)
class StreamSpec:
    """How the rows of one stream become the contract's: ``xyz = scale * (axes @ v)``,
    ``t = t_raw + t_offset``.

    Attributes
    ----------
    path : file named in errors.
    key : ``"mag"``, ``"accel"``, ``"gyro"``.
    scale, axes, t_offset : the conversion (``axes``: 3×3, source frame → Android device frame, a signed
        permutation for the devices here).
    unit_hint : the source unit, named in the unit-check error.
    check : run the unit plausibility check.
    limit_known : the reader counts saturation against the sensor's range (``StreamBuilder(limit=…)``), else
        the :class:`Saturation` heuristic counts it.
    min_samples : fewer valid samples is an error (``empty stream``)…
    optional : …unless the stream has none at all and is optional (a format where it may be absent): then
        the recording has no such stream.
    """

    path: object
    key: str
    scale: float = 1.0
    axes: np.ndarray | None = None
    t_offset: float = 0.0
    unit_hint: str = ""
    check: bool = True
    limit_known: bool = False
    min_samples: int = 2
    optional: bool = False

    def converter(self, dropped: Counter) -> Converter:
        return Converter(self, dropped)


class Converter:
    """Blocks of cleaned rows in, blocks in the contract's units out, with the stream's checks (module doc).

    :meth:`push` returns the blocks ready to go on (none until the unit check has run), :meth:`end` the rest;
    ``n`` counts the samples.
    """

    def __init__(self, spec: StreamSpec, dropped: Counter):
        self.spec = spec
        self.dropped = dropped
        self.n = 0
        self.n_kept = 0  # … of them, the ones that went on (not implausible)
        self.held: list[Block] | None = [] if spec.check else None
        self.sat = None if spec.limit_known else Saturation(spec.key)

    def push(self, t: np.ndarray, v: np.ndarray) -> list[Block]:
        if len(t) == 0:
            return []
        sp = self.spec
        if sp.axes is not None:
            v = v @ np.asarray(sp.axes, dtype=float).T
        if sp.scale != 1.0:
            v *= sp.scale
        if sp.t_offset:
            t += sp.t_offset
        self.n += len(t)
        if self.held is None:
            return self._plausible([(t, v)])
        self.held.append((t, v))
        return self._release() if self.n >= UNIT_CHECK_SAMPLES else []

    def _release(self) -> list[Block]:
        held, self.held = self.held, None
        if held:
            head = np.concatenate([v for _, v in held])[:UNIT_CHECK_SAMPLES]
            check_units(self.spec.path, self.spec.key, head, self.spec.unit_hint)
            times = np.concatenate([t for t, _ in held])[:UNIT_CHECK_SAMPLES]
            check_time_unit(self.spec.path, self.spec.key, times)
        return self._plausible(held)

    def _plausible(self, blocks: list[Block]) -> list[Block]:
        """The blocks without their samples beyond :data:`PHYSICAL_LIMITS` (counted; after the unit check,
        so a file in the wrong unit is named as such, not emptied sample by sample), the saturation
        heuristic fed with the rest."""
        limit = PHYSICAL_LIMITS.get(self.spec.key)
        out = []
        for t, v in blocks:
            # the whole block first: one reduction, where a per-row test along the short axis costs ~15×
            # more (a NaN fails both, so such a block takes the per-row test)
            if limit is not None and not np.abs(v).max(initial=0.0) < limit:
                ok = np.all(np.abs(v) < limit, axis=1)
                if not ok.all():
                    n_bad = int(np.count_nonzero(~ok))
                    self.dropped[f"{self.spec.key}:implausible"] += n_bad
                    sat = f"{self.spec.key}:saturated"
                    if self.spec.limit_known and self.dropped.get(sat):  # beyond any sensor's range is beyond
                        self.dropped[sat] -= min(n_bad, self.dropped[sat])  # this one's: the builder counted
                        if not self.dropped[sat]:  # it saturated (a kept sample); it is dropped instead
                            del self.dropped[sat]
                    t, v = t[ok], v[ok]
            self.n_kept += len(t)
            if len(t):
                if self.sat is not None:
                    self.sat.update(v)
                out.append((t, v))
        return out

    def _enough(self, n: int) -> None:
        """InputError when ``n`` samples are too few for the stream (none at all: fine if it is optional)."""
        sp = self.spec
        if n < sp.min_samples and not (sp.optional and n == 0):
            what = "no valid samples" if n == 0 else f"only {n} valid sample(s)"
            prefix = f"{sp.key}:"
            odd = [f"{k[len(prefix):]} {c}" for k, c in sorted(self.dropped.items()) if k.startswith(prefix)]
            if odd:
                what += f"; dropped: {', '.join(odd)}"
            raise InputError(sp.path, f"{sp.key}: empty stream ({what})")

    def end(self) -> list[Block]:
        """The blocks still held; InputError for a stream too short (or an implausible unit)."""
        self._enough(self.n)
        out = self._release() if self.held is not None else []
        self._enough(self.n_kept)  # the implausible ones left out
        if self.sat is not None:
            n = self.sat.count()
            if n:
                self.dropped[f"{self.spec.key}:saturated"] += n
        return out


def chunks_of(fh, builders: dict, steps) -> Iterator[tuple[int, dict[str, Block]]]:
    """After each step of a parser (``steps``: an iterator run for its effect on ``builders``), yield the
    bytes of ``fh`` consumed and the rows the builders took in since the last step
    (:meth:`StreamBuilder.take`) — the ``chunks()`` of a :class:`replay.source.Feed`."""
    for _ in steps:
        yield tell(fh), take_all(builders)
    yield tell(fh), take_all(builders)


def every(rows, n_lines: int | None = None) -> Iterator[None]:
    """Run a line-by-line parser (``rows``: its per-line iterator) and yield after every ``n_lines``
    (default :data:`CHUNK`)."""
    n = n_lines or CHUNK
    for i, _ in enumerate(rows, start=1):
        if i % n == 0:
            yield None


def tell(fh) -> int:
    """Bytes of a file consumed so far (text or binary stream; a zip member: uncompressed), for progress.

    ``fh`` may also be a list that a parser appends its file to once it has opened it."""
    if isinstance(fh, list):
        if not fh:
            return 0
        fh = fh[0]
    try:
        return int(getattr(fh, "buffer", fh).tell())
    except (OSError, ValueError, AttributeError):
        return 0


def require(path: Path, what: str) -> Path:
    """``path`` if it is a file, else InputError (a stream missing)."""
    if not path.is_file():
        raise InputError(path, f"missing ({what})")
    return path


class Bundle:
    """Named files in a directory or a ``.zip`` archive (phone apps export either), read as text streams.

    ``names()`` lists the files (relative POSIX paths), ``open(name)`` returns a text stream read line by line
    (from a zip: decompressed as it is read, never whole), ``where(name)`` is the path to name in errors.
    """

    def __init__(self, path: Path):
        self.path = Path(path)
        self.zip = None
        if self.path.is_file():
            try:
                self.zip = zipfile.ZipFile(self.path)
            except (zipfile.BadZipFile, OSError) as exc:
                raise InputError(self.path, f"not a readable zip archive ({exc})") from None

    @staticmethod
    def is_zip(path: Path) -> bool:
        if not path.is_file():
            return False
        with path.open("rb") as fh:
            return fh.read(4) == b"PK\x03\x04"

    def names(self) -> list[str]:
        if self.zip is not None:
            return [n for n in self.zip.namelist() if not n.endswith("/")]
        out = []  # the export's files and one level of sub-folders (phyphox's meta/), never a deep walk
        for p in self.path.iterdir():
            if p.is_file():
                out.append(p.name)
            elif p.is_dir():
                out.extend(f"{p.name}/{q.name}" for q in p.iterdir() if q.is_file())
        return sorted(out)

    def find(self, basename: str) -> str | None:
        """The member whose file name (any folder) is ``basename`` (case-insensitive), shallowest first."""
        hits = [n for n in self.names() if n.rsplit("/", 1)[-1].lower() == basename.lower()]
        return min(hits, key=lambda n: (n.count("/"), n)) if hits else None

    def size(self, name: str) -> int:
        """Bytes of ``name`` (uncompressed), for progress."""
        if self.zip is not None:
            return self.zip.getinfo(name).file_size
        return (self.path / name).stat().st_size

    def where(self, name: str) -> str:
        return f"{self.path}!{name}" if self.zip is not None else str(self.path / name)

    def open(self, name: str):
        if self.zip is None:
            return open_text(self.path / name)
        try:
            raw = self.zip.open(name)
        except (KeyError, OSError) as exc:
            raise InputError(self.where(name), f"cannot open ({exc})") from None
        return io.TextIOWrapper(raw, encoding="utf-8-sig", errors="replace", newline="")

    def close(self) -> None:
        if self.zip is not None:
            self.zip.close()


def iter_csv(fh, where: str, delimiter: str = ","):
    """Yield ``(lineno, cells)`` of a CSV text stream; a damaged/truncated compressed member → InputError."""
    reader = csv.reader(fh, delimiter=delimiter)
    try:
        for cells in reader:
            yield reader.line_num, cells
    except (zipfile.BadZipFile, EOFError, zlib.error) as exc:
        raise InputError(where, f"truncated or damaged archive member ({exc})", reader.line_num + 1) from None
    except csv.Error as exc:
        raise InputError(where, f"bad CSV ({exc})", reader.line_num) from None


def read_table(fh, path, targets, ncol: int, **kw) -> None:
    """Parse a whole text stream into builders (:func:`iter_table` run to the end)."""
    for _ in iter_table(fh, path, targets, ncol, **kw):
        pass


def iter_table(
    fh,
    path,
    targets,
    ncol: int,
    first_line: int = 1,
    delimiter: str | None = None,
    tcol: int = 0,
    t_scale: float = 1.0,
    chunk: int | None = None,
    most: int | None = None,
) -> Iterator[int]:
    """Parse numeric rows ``t, v…`` of a text stream in chunks into builders, with exact errors.

    Parameters
    ----------
    fh : text stream, positioned after any header.
    path : file named in errors.
    targets : list of (StreamBuilder, column indices of x, y, z), builders of one recording (one
        ``dropped`` counter).
    ncol : the number of leading columns every row must have (fewer: :class:`ShortRows`).
    first_line : line number of the stream's next line.
    delimiter : None for whitespace, else e.g. ``","``.
    tcol, t_scale : the time column and its factor to seconds.
    chunk : lines a chunk, default :data:`CHUNK`.
    most : the most fields a row may have (the header's or the format's count), default ``ncol``; a row
        with more (:data:`EXTRA_FIELDS`) or with any field that is not a number (:data:`NON_NUMERIC`) is
        dropped and counted in every target's stream (:func:`row_values`).

    Yields the number of lines read so far after each chunk (the builders then hold that chunk's rows).
    The fast path parses a chunk, every field of it, with :func:`numpy.loadtxt` and cleans it with
    :meth:`StreamBuilder.add_block`; a chunk that does not parse that way (text in a field, a short or long
    row, a blank line) is re-read line by line, so that an error names its exact line and only the garbled
    rows are dropped.
    """
    chunk = chunk or CHUNK
    most = ncol if most is None else most
    keys = [b.key for b, _ in targets]
    dropped = targets[0][0].dropped  # the recording's counter, which every target counts into
    short = ShortRows(path, dropped)
    lineno = first_line
    while True:
        lines = list(itertools.islice(fh, chunk))
        if not lines:
            short.end()
            return
        arr = None
        if all(ln.strip() for ln in lines):
            try:
                arr = np.loadtxt(lines, delimiter=delimiter, ndmin=2, dtype=float, comments=None)
            except ValueError:
                arr = None
        if arr is not None and len(arr) == len(lines) and ncol <= arr.shape[1] <= most:
            short.follows()
            t = arr[:, tcol] * t_scale if t_scale != 1.0 else arr[:, tcol]
            for b, ix in targets:
                b.add_block(t, arr[:, ix], first_line=lineno)
        else:
            for i, line in enumerate(lines):
                parts = line.split(delimiter)
                if not line.strip():
                    continue
                if len(parts) < ncol:
                    why = f"expected at least {ncol} columns, got {len(parts)} (truncated file?)"
                    short.found(lineno + i, why, keys)
                    continue
                short.follows()
                vals = row_values(parts, most, dropped=dropped, keys=keys)
                if vals is None:
                    continue
                for b, ix in targets:
                    b.add(lineno + i, vals[tcol] * t_scale, [vals[j] for j in ix])
        lineno += len(lines)
        yield lineno - first_line
