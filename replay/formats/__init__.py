"""Readers: one module per format, each converting units and axes into the contract (INTERFACE.md).

:func:`read_recording` detects the format of a path and returns a :class:`replay.recording.Recording`.
"""

from __future__ import annotations

from pathlib import Path

from replay.errors import InputError
from replay.recording import Recording


def read_recording(path) -> Recording:
    """Read any recording a reader recognises; raises :class:`InputError` otherwise."""
    from replay.formats import pdrcsv

    p = Path(path)
    if not p.exists():
        raise InputError(p, "no such file or directory")
    if pdrcsv.detect(p):
        return pdrcsv.read(p)
    raise InputError(p, "not a recording in a known format (expected a pdr-csv directory with mag.csv)")
