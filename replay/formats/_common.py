"""Shared pieces of the readers: a stream accumulator that cleans rows as they arrive, unit checks, parsing.

Every reader feeds rows one at a time (or in chunks) into a :class:`StreamBuilder`, which

* drops a row with a NaN/inf value (``"<key>:nan"``) and a row whose time repeats the previous one
  (``"<key>:duplicate_t"``), counting both in the recording's ``dropped`` counter;
* raises :class:`~replay.errors.InputError` naming the file and line when time goes backwards;
* flags (keeps, but counts as ``"<key>:saturated"``) samples with an axis at the sensor's range limit,
  when the reader knows that limit;
* stores values in compact ``array('d')`` buffers (8 bytes a number, not a Python float object each).

:func:`finish` converts to a :class:`~replay.recording.Stream` in the contract's units and checks that the
median vector norm is plausible for the stream (µT, m/s², rad/s), which catches a file in the wrong unit;
where the reader does not know the sensor's range, :func:`flag_saturation` counts clipped samples.

:func:`read_table` parses numeric text in chunks (numpy fast path, exact-line errors), :class:`Bundle`
reads the files of a folder or a zip export as streams, :func:`iter_csv` reads quoted CSV.
"""

from __future__ import annotations

import math
from array import array
from collections import Counter
from pathlib import Path

import numpy as np

from replay.errors import InputError
from replay.recording import Stream

# Plausible medians of the vector norm per stream, in the contract's units; outside → wrong unit.
UNIT_RANGES = {
    "mag": (5.0, 2000.0, "µT"),
    "accel": (3.0, 30.0, "m/s²"),
    "gyro": (0.0, 20.0, "rad/s"),
}


def is_float(v: str) -> bool:
    try:
        float(v)
        return True
    except ValueError:
        return False


def floats(path, lineno: int | None, parts) -> list[float]:
    """``[float(p) for p in parts]``, or InputError naming the first cell that is not a number."""
    try:
        return [float(p) for p in parts]
    except ValueError:
        bad = next(p for p in parts if not is_float(p))
        raise InputError(path, f"not a number: {bad.strip()!r}", lineno) from None


def open_text(path: Path):
    """Open a text file for line-by-line reading, InputError if it cannot be opened."""
    try:
        return Path(path).open("r", encoding="utf-8", errors="replace", newline="")
    except OSError as exc:
        raise InputError(path, f"cannot open ({exc.strerror})") from exc


def check_units(path, key: str, xyz: np.ndarray, unit_hint: str = "") -> None:
    """InputError when the median vector norm is outside the plausible range of ``key``."""
    lo, hi, unit = UNIT_RANGES[key]
    med = float(np.median(np.linalg.norm(xyz, axis=1)))
    if not (lo <= med <= hi):
        what = f" (read as {unit_hint})" if unit_hint else ""
        raise InputError(
            path,
            f"median |{key}| is {med:.4g} {unit}{what}, outside the plausible {lo:g}–{hi:g} {unit} "
            "(wrong unit?)",
        )


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
        self._count("nan", int((~good).sum()))
        t, vals = t[good], vals[good]
        rows = np.flatnonzero(good)
        if len(t) == 0:
            return
        prev = np.concatenate([[self.last_t], t[:-1]])
        back = np.flatnonzero(t < prev)
        if len(back):
            i = back[0]
            line = None if first_line is None else first_line + int(rows[i])
            raise InputError(self.path, f"{self.key}: time goes backwards ({t[i]!r} after {prev[i]!r})", line)
        keep = t != prev
        self._count("duplicate_t", int((~keep).sum()))
        t, vals = t[keep], vals[keep]
        if self.limit is not None:
            self._count("saturated", int(np.any(np.abs(vals) >= self.limit, axis=1).sum()))
        if len(t):
            self.last_t = float(t[-1])
            self.t.frombytes(np.ascontiguousarray(t, dtype=float).tobytes())
            self.v.frombytes(np.ascontiguousarray(vals, dtype=float).tobytes())

    def _count(self, reason: str, n: int) -> None:
        if n:
            self.dropped[f"{self.key}:{reason}"] += n

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        t = np.frombuffer(self.t, dtype=float).copy()
        v = np.frombuffer(self.v, dtype=float).copy().reshape(-1, self.width)
        return t, v


#: Heuristic saturation (when the reader does not know the sensor's range): per axis, the largest |value| is
#: a clipped range limit if at least SAT_MIN_COUNT samples sit exactly on it and it is above the floor — the
#: smallest range phones use is ±2 g (19.6 m/s²) and ±250 deg/s (4.36 rad/s), so normal data never qualifies.
SAT_FLOOR = {"accel": 15.0, "gyro": 4.0}
SAT_MIN_COUNT = 3


def flag_saturation(key: str, xyz: np.ndarray, dropped: Counter) -> int:
    """Count (``<key>:saturated``) samples with an axis exactly at a clipped range limit; returns the count.

    Only for ``accel`` and ``gyro``, in the contract's units (see :data:`SAT_FLOOR`). Samples are kept.
    """
    floor = SAT_FLOOR.get(key)
    if floor is None or len(xyz) == 0:
        return 0
    a = np.abs(xyz)
    peak = a.max(axis=0)
    at = (a == peak) & (peak >= floor)
    counts = at.sum(axis=0)
    hit = np.any(at[:, counts >= SAT_MIN_COUNT], axis=1)
    n = int(hit.sum())
    if n:
        dropped[f"{key}:saturated"] += n
    return n


def finish(
    b: StreamBuilder,
    scale: float = 1.0,
    axes: np.ndarray | None = None,
    t_offset: float = 0.0,
    unit_hint: str = "",
    check: bool = True,
    min_samples: int = 2,
) -> Stream:
    """Convert a builder to a Stream in the contract: ``xyz = scale * (axes @ v)``, ``t = t_raw + t_offset``.

    ``axes`` is the 3×3 matrix taking a source-frame vector into the Android device frame (a signed
    permutation for the devices here). Raises InputError for an empty/too short stream or an implausible unit.
    """
    if len(b) < min_samples:
        what = "no valid samples" if len(b) == 0 else f"only {len(b)} valid sample(s)"
        raise InputError(b.path, f"{b.key}: empty stream ({what})")
    t, v = b.arrays()
    if axes is not None:
        v = v @ np.asarray(axes, dtype=float).T
    if scale != 1.0:
        v *= scale
    if t_offset:
        t += t_offset
    if check:
        check_units(b.path, b.key, v, unit_hint)
    if b.limit is None:
        flag_saturation(b.key, v, b.dropped)
    return Stream(t=t, xyz=v)


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
        import zipfile

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

    def where(self, name: str) -> str:
        return f"{self.path}!{name}" if self.zip is not None else str(self.path / name)

    def open(self, name: str):
        import io

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
    import csv
    import zlib
    from zipfile import BadZipFile

    reader = csv.reader(fh, delimiter=delimiter)
    try:
        for cells in reader:
            yield reader.line_num, cells
    except (BadZipFile, EOFError, zlib.error) as exc:
        raise InputError(where, f"truncated or damaged archive member ({exc})", reader.line_num + 1) from None
    except csv.Error as exc:
        raise InputError(where, f"bad CSV ({exc})", reader.line_num) from None


def read_table(
    fh,
    path,
    targets,
    ncol: int,
    first_line: int = 1,
    delimiter: str | None = None,
    tcol: int = 0,
    t_scale: float = 1.0,
    chunk: int = 65536,
) -> None:
    """Parse numeric rows ``t, v…`` of a text stream in chunks into builders, with exact errors.

    Parameters
    ----------
    fh : text stream, positioned after any header.
    path : file named in errors.
    targets : list of (StreamBuilder, column indices of x, y, z).
    ncol : the number of leading columns every row must have.
    first_line : line number of the stream's next line.
    delimiter : None for whitespace, else e.g. ``","``.
    tcol, t_scale : the time column and its factor to seconds.

    The fast path parses a chunk with :func:`numpy.loadtxt` and cleans it with
    :meth:`StreamBuilder.add_block`; a chunk that does not parse (text in a number column, a short row, a
    blank line) is re-read line by line so that the error names the exact line.
    """
    import itertools

    lineno = first_line
    cols = list(range(ncol))
    while True:
        lines = list(itertools.islice(fh, chunk))
        if not lines:
            return
        arr = None
        if all(ln.strip() for ln in lines):
            try:
                arr = np.loadtxt(
                    lines, delimiter=delimiter, usecols=cols, ndmin=2, dtype=float, comments=None
                )
            except ValueError:
                arr = None
        if arr is not None and arr.shape == (len(lines), ncol):
            t = arr[:, tcol] * t_scale if t_scale != 1.0 else arr[:, tcol]
            for b, ix in targets:
                b.add_block(t, arr[:, ix], first_line=lineno)
        else:
            for i, line in enumerate(lines):
                parts = line.split(delimiter)
                if not line.strip():
                    continue
                if len(parts) < ncol:
                    raise InputError(
                        path,
                        f"expected at least {ncol} columns, got {len(parts)} (truncated file?)",
                        lineno + i,
                    )
                vals = floats(path, lineno + i, parts[:ncol])
                for b, ix in targets:
                    b.add(lineno + i, vals[tcol] * t_scale, [vals[j] for j in ix])
        lineno += len(lines)
