"""Output paths checked before a command does its work: bad ones are an :class:`InputError`, not a traceback.

A command that writes files (``--json``, ``--out-csv``, ``--mcap``, ``--rrd``, ``--out``, ``--report``)
asks here first, so that an unwritable path ends the command at once with exit code 2 and one line naming
the path, instead of after a long run (or with an ``OSError`` deep inside a sink).
"""

from __future__ import annotations

import os
from pathlib import Path

from replay.errors import InputError


def _make_parent(path: Path) -> None:
    parent = path.parent
    if parent.exists() and not parent.is_dir():
        raise InputError(path, f"cannot write: {parent} is not a directory")
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(path, f"cannot create the folder {parent} ({exc.strerror})") from None


def writable_file(path) -> Path:
    """Check that ``path`` can be written as a file (its folder made if missing); returns it as a Path.

    The check opens the file for appending (nothing is truncated) and removes it again if it did not exist,
    so it also catches what permission bits cannot tell (a read-only file system, a path under ``/proc``).
    """
    p = Path(path)
    if p.is_dir():
        raise InputError(p, "cannot write: is a directory")
    _make_parent(p)
    existed = p.exists()
    try:
        with p.open("a"):
            pass
    except OSError as exc:
        raise InputError(p, f"cannot write ({exc.strerror})") from None
    if not existed:
        os.unlink(p)
    return p


def writable_dir(path) -> Path:
    """Check that ``path`` is, or can be made, a writable directory (it is created); returns it as a Path."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise InputError(p, "cannot write: exists and is not a directory")
    _make_parent(p)
    try:
        p.mkdir(exist_ok=True)
    except OSError as exc:
        raise InputError(p, f"cannot create the folder ({exc.strerror})") from None
    if not os.access(p, os.W_OK | os.X_OK):
        raise InputError(p, "cannot write: no write permission")
    return p
