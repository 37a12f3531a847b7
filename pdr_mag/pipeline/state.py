"""What :meth:`pdr_mag.pipeline.HeadingPipeline.get_state` keeps, as JSON, and how
:meth:`~pdr_mag.pipeline.HeadingPipeline.set_state` puts it back: each stream's pending samples and its
stalled-sensor check, how far the merge has gone, the calibrator's open block (its magnetometer rows and
the context the next chunk needs), the calibrations in force so far, the output counters, the streams' gaps
found so far, and the filter's and the calibrator's own states.  Non-finite floats go through
:func:`pdr_mag._json.state_float`, so the round trip is exact."""

from __future__ import annotations

import json
from collections import Counter

import numpy as np

from pdr_mag._json import state_float
from pdr_mag.calibration.model import MagCalibration
from pdr_mag.pipeline import _kernel as PK

#: format of :meth:`HeadingPipeline.get_state` (it nests the filter's, :data:`pdr_mag.fusion.STATE_VERSION`)
STATE_VERSION = 15


def to_json(pipe) -> dict:
    """The state of ``pipe`` (a :class:`~pdr_mag.pipeline.HeadingPipeline`) as a JSON-serialisable dict."""
    pend = {}
    for name, s in pipe._streams.items():
        t, x = s.pending()
        pend[name] = {"t": t.tolist(), "xyz": x.tolist(), "last_t": state_float(s.last_t),
                      "last_xyz": [state_float(v) for v in s.last_xyz], "repeats": s.repeats}
    st = {
        "version": STATE_VERSION,
        "pending": pend,
        "done_t": state_float(pipe._done_t),
        "dropped": dict(pipe.dropped),
        "mag_rows": [state_float(v) for v in pipe._pend.view(np.float64)],
        "carry": [state_float(v) for v in pipe._carry.view(np.float64)],
        "coverage": pipe._coverage,
        "interf": pipe._interf,
        "calibrations": [[state_float(t), c.to_dict()] for t, c in pipe._calibrations],
        "n_out": pipe._n_out,
        "t_first": state_float(pipe._t_first),
        "t_last": state_float(pipe._t_last),
        "fusion": pipe.fusion.get_state(),
        "online": pipe.online.get_state(),
        "phone_changes": [[t, list(b)] for t, b in pipe._phone_changes],
        "stream_gaps": pipe.stream_gaps.get_state(),
    }
    json.dumps(st)  # fail here, not at the caller's, if something is not serialisable
    return st


def from_json(pipe, state: dict) -> None:
    """Put :func:`to_json`'s ``state`` back into ``pipe`` (ValueError when the dict is not such a state);
    the caller then takes the calibration in force into use."""
    if not isinstance(state, dict) or state.get("version") != STATE_VERSION:
        raise ValueError(f"state: expected a HeadingPipeline state of version {STATE_VERSION}")
    try:
        for name, s in pipe._streams.items():
            p = state["pending"][name]
            t = np.asarray(p["t"], dtype=float)
            x = np.asarray(p["xyz"], dtype=float).reshape(-1, 3)
            s.t, s.xyz, s.lo, s.hi = t, x, 0, len(t)
            s.last_t = float(p["last_t"])
            s.last_xyz = np.array([float(v) for v in p["last_xyz"]])
            s.repeats = int(p["repeats"])
        pipe._done_t = float(state["done_t"])
        pipe.dropped = Counter(state["dropped"])
        pipe._pend = np.array([float(v) for v in state["mag_rows"]]).view(PK.MAG_ROW)
        pipe._carry.view(np.float64)[:] = [float(v) for v in state["carry"]]
        pipe._coverage = float(state["coverage"])
        pipe._interf = bool(state["interf"])
        pipe._calibrations = [(float(t), MagCalibration.from_dict(c)) for t, c in state["calibrations"]]
        pipe._n_out = int(state["n_out"])
        pipe._t_first = float(state["t_first"])
        pipe._t_last = float(state["t_last"])
        pipe.fusion.set_state(state["fusion"])  # with its reference strength
        pipe.online.set_state(state["online"])
        pipe._phone_changes = [(float(t), tuple(float(v) for v in b)) for t, b in state["phone_changes"]]
        pipe.stream_gaps.set_state(state["stream_gaps"])
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"state: malformed ({exc!r})") from exc
