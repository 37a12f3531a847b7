"""The recordings a batch names: explicit recordings, folders searched recursively, manifests.

Each INPUT is, in this order of tests,

* a **manifest** — a file named ``*.manifest``: one recording a line, optionally followed by its
  calibration file (``calibrate --json``, for ``replay``); blank lines and ``#`` comments are skipped,
  a path with spaces is quoted (shell-like: :func:`shlex.split`); relative paths are relative to the
  manifest's folder;
* a **recording** — a path a reader of :mod:`replay.formats` recognises (:func:`replay.formats.detect`);
* a **folder** — searched recursively (sorted by name; hidden entries and the output folder skipped,
  symbolic links followed once) for folders and files a reader recognises; a recording's own folder is
  not searched further. Folders holding no recording are passed over;
* anything else — a file no reader recognises, a path that does not exist, a folder that cannot be
  listed — is an :class:`Item` with an ``error``: a row with status ``error`` in the fleet table.

Each recording comes once (the first time it is named, by its real path), in a stable order: the inputs
in the order given, a folder's recordings in sorted order.

Output folders mirror the input tree under ``--out``: a recording named explicitly goes to
``DIR/<its name>``, one found in folder ``F`` to ``DIR/<F's name>/<its path under F>``, a manifest's line
to ``DIR/<its path under the manifest's folder>`` (``DIR/<its name>`` when it lies elsewhere). Two
recordings that would share a folder: the second is an error row naming the first.
"""

from __future__ import annotations

import os
import shlex
from dataclasses import dataclass
from pathlib import Path

from replay.errors import InputError
from replay.formats import detect, open_recording

#: File-name suffix of a manifest.
MANIFEST_SUFFIX = ".manifest"


@dataclass(frozen=True)
class Item:
    """One recording a batch names.

    Attributes
    ----------
    label : str
        Its path as given (or as found under a given folder): the fleet table's ``recording`` and the
        ``source`` its outputs name.
    path : str
        The same, absolute: what a worker opens (workers of a remote cluster share the path, not the
        client's working folder).
    key : str
        Its output folder under ``--out`` (POSIX relative path; empty for an error).
    calibration : str or None
        A calibration file given for it by a manifest (as written there, joined to the manifest's folder).
    error : str or None
        Why it cannot be processed (the one line of the fleet table), or None.
    """

    label: str
    path: str
    key: str = ""
    calibration: str | None = None
    error: str | None = None


def _unrecognised(path: Path) -> str:
    """The one-line message the single commands give for a path no reader recognises."""
    try:
        open_recording(path)
    except InputError as exc:
        return str(exc)
    except OSError as exc:
        return f"{path}: cannot read ({exc.strerror})"
    return f"{path}: not a recording"  # pragma: no cover - detect said no, a reader said yes


def _search(folder: Path, label: str, key: str, skip: set[str], seen: set[str]):
    """Recordings under ``folder`` (sorted, recursively); yields Items (errors for unlistable folders)."""
    real = os.path.realpath(folder)
    if real in seen:  # a symbolic-link loop
        return
    seen.add(real)
    try:
        entries = sorted(os.scandir(folder), key=lambda e: e.name)
    except OSError as exc:
        yield Item(label, os.path.abspath(folder), error=f"{label}: cannot list the folder ({exc.strerror})")
        return
    for e in entries:
        if e.name.startswith("."):
            continue
        path = Path(e.path)
        sub_label, sub_key = os.path.join(label, e.name), f"{key}/{e.name}" if key else e.name
        try:
            is_dir = e.is_dir()
        except OSError:
            continue
        if is_dir and os.path.realpath(path) in skip:
            continue
        if detect(path) is not None:
            yield Item(sub_label, os.path.abspath(path), sub_key)
        elif is_dir:
            yield from _search(path, sub_label, sub_key, skip, seen)


def _manifest(path: Path, label: str):
    """The recordings a manifest lists (errors for lines it cannot parse)."""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        why = exc.strerror if isinstance(exc, OSError) else "not UTF-8 text"
        yield Item(label, os.path.abspath(path), error=f"{label}: cannot read the manifest ({why})")
        return
    base_label = os.path.dirname(label)
    base = os.path.dirname(os.path.abspath(path))
    for lineno, line in enumerate(text.splitlines(), start=1):
        try:
            fields = shlex.split(line, comments=True)
        except ValueError as exc:
            yield Item(f"{label}:{lineno}", os.path.abspath(path), error=f"{label}:{lineno}: {exc}")
            continue
        if not fields:
            continue
        if len(fields) > 2:
            yield Item(f"{label}:{lineno}", os.path.abspath(path),
                       error=f"{label}:{lineno}: expected RECORDING [CALIBRATION], got {len(fields)} fields")
            continue
        rec = fields[0]
        rec_label = rec if os.path.isabs(rec) else os.path.normpath(os.path.join(base_label, rec))
        rec_path = os.path.normpath(os.path.join(base, rec))
        rel = os.path.relpath(rec_path, base)
        key = Path(rel).as_posix() if not rel.startswith("..") else Path(rec_path).name
        cal = None
        if len(fields) == 2:
            c = fields[1]
            cal = c if os.path.isabs(c) else os.path.normpath(os.path.join(base_label, c))
        yield _named(Path(rec_path), rec_label, key, cal)


def _named(path: Path, label: str, key: str, calibration: str | None = None) -> Item:
    """A recording named explicitly (on the command line or in a manifest)."""
    if not path.exists():
        return Item(label, str(path), error=f"{label}: no such file or directory")
    if detect(path) is None:
        msg = _unrecognised(path)
        return Item(label, str(path), error=msg.replace(str(path), label))
    return Item(label, str(path), key, calibration)


def find_recordings(inputs, skip=()) -> list[Item]:
    """Every recording the inputs name, once each, in a stable order (see the module docstring).

    Parameters
    ----------
    inputs : sequence of path
        Recordings, folders and manifests.
    skip : sequence of path
        Folders not to search (the batch's own output folder).
    """
    skip_real = {os.path.realpath(p) for p in skip}
    items: list[Item] = []
    for given in inputs:
        label = str(given)
        p = Path(given)
        absolute = Path(os.path.abspath(p))
        if p.is_file() and p.name.endswith(MANIFEST_SUFFIX):
            items.extend(_manifest(p, label))
        elif not p.exists() or detect(p) is not None or not p.is_dir():
            items.append(_named(absolute, label, absolute.name))
        else:
            items.extend(_search(p, label, absolute.name, skip_real, set()))
    return _once(items)


def _once(items: list[Item]) -> list[Item]:
    """Each recording once (by real path); a second recording for an output folder is an error."""
    out: list[Item] = []
    seen: set[str] = set()
    keys: dict[str, str] = {}
    for it in items:
        if it.error is not None:
            out.append(it)
            continue
        real = os.path.realpath(it.path)
        if real in seen:
            continue
        seen.add(real)
        first = keys.setdefault(it.key, it.label)
        if first != it.label:
            why = f"{it.label}: its output folder {it.key} is already that of {first}"
            it = Item(it.label, it.path, error=why)
        out.append(it)
    return out
