"""JSON helpers shared by the library's serialisers (calibration files, pipeline state, MCAP metadata).

Two conventions, for two purposes:

* :func:`jsonable` — for *outputs* (``calibrate --json``, MCAP metadata and events): numpy scalars and arrays
  become plain numbers and lists, a non-finite float becomes ``null`` (:func:`rounded`: one float so,
  rounded);
* :func:`state_float` — for the pipeline's *state* (``get_state``/``set_state``), which must round-trip
  exactly: a non-finite float is kept as the string ``"nan"``, ``"inf"`` or ``"-inf"`` (``float()`` reads
  them back).
"""

from __future__ import annotations

import math

import numpy as np


def jsonable(obj):
    """``obj`` with numpy types converted, non-finite floats as None and unknown objects as ``str``."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    if obj is None or isinstance(obj, (int, str)):
        return obj
    return str(obj)


def rounded(v: float, nd: int = 4):
    """A float for an output JSON, rounded to ``nd`` decimals; a non-finite one as None (``null``)."""
    v = float(v)
    return round(v, nd) if math.isfinite(v) else None


def state_float(v: float):
    """A float for the state JSON: the number, or ``"nan"`` / ``"inf"`` / ``"-inf"`` (exact round trip)."""
    v = float(v)
    if math.isnan(v):
        return "nan"
    if math.isinf(v):
        return "inf" if v > 0 else "-inf"
    return v
