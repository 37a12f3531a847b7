"""The row scan of :class:`pdr_mag.episodes.EpisodeFinder` (numba, ``cache=True``).

One pass over a batch's rows, in time order, carrying everything from one batch to the next in a record of
:data:`SCAN` (so the rows may come in any chunks):

* the open ``error`` and ``sigma`` stretches (:data:`RUN`): a row above the onset level extends the open
  stretch, or closes it and opens a new one when the previous row above was more than ``merge_s`` earlier;
  a stretch is kept when a row of it was above the kind's threshold and it lasted ``min_duration_s``;
* the gap since the last magnetometer correction and the peaks of its rows: at the next correction a gap
  longer than ``no_reference_s`` is a ``no_reference`` stretch;
* the states of the row signals (:data:`ROW_SIGNALS`), whose changes are given out as :data:`CHANGE` s.

The closed stretches come out as :data:`CLOSED` records (``kind`` an index into :data:`KIND_NAMES`); the
episode finder turns them into episodes.  Definitions (thresholds, which rows count) are those of the
:mod:`pdr_mag.episodes.finder` docstring.  A loop, because the hysteresis, the merging across short gaps and
the running peaks take a dozen numpy calls per kind and batch, which on a replay's 10-s batches cost as much
as the pipeline's own bookkeeping.
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: ``kind`` of a :data:`CLOSED` record → the episode kind
KIND_NAMES = ("error", "sigma", "no_reference")
ERROR, SIGMA, NO_REFERENCE = 0, 1, 2

#: the signals taken from the rows (``CHANGE.signal`` indexes this; ``SCAN`` has a field of each)
ROW_SIGNALS = ("interference", "strength", "dip", "field_out")
INTERFERENCE, STRENGTH, DIP, FIELD_OUT = 0, 1, 2, 3

#: an open ``error`` or ``sigma`` stretch and its peaks so far
RUN = np.dtype(
    [
        ("open", np.bool_),
        ("t_start", np.float64),  # its first row, s
        ("t_last", np.float64),  # its last row above the onset level, s
        ("reached", np.bool_),  # a row of it was above the kind's threshold
        ("peak", np.float64),  # the largest value (|error| or σ), deg
        ("t_peak", np.float64),  # when, s
        ("err", np.float64),  # the signed error of largest magnitude, deg (NaN: none)
        ("std", np.float64),  # the largest heading_std_deg, deg (NaN: none)
    ]
)

#: what the scan carries from one batch to the next
SCAN = np.dtype(
    [
        ("referenced", np.bool_),  # a magnetometer correction has been seen
        ("t_first", np.float64),  # the first row, s (NaN: none yet)
        ("last_used", np.float64),  # the last magnetometer correction, s (NaN: none yet)
        ("gap_err", np.float64),  # signed error of largest magnitude since then, deg (NaN: none)
        ("gap_std", np.float64),  # largest heading_std_deg since then, deg (NaN: none)
        ("error", RUN),
        ("sigma", RUN),
        # the row signals at the last row: the interference flag, the field strength / dip beyond the
        # detector's band, either beyond the inner band (field_band_frac of it)
        ("interference", np.bool_),
        ("strength", np.bool_),
        ("dip", np.bool_),
        ("field_out", np.bool_),
    ]
)

#: the thresholds the scan applies (:class:`pdr_mag.episodes.EpisodeSettings`)
LEVELS = np.dtype(
    [
        ("error_onset_deg", np.float64),
        ("error_deg", np.float64),
        ("std_deg", np.float64),
        ("no_reference_s", np.float64),
        ("merge_s", np.float64),
        ("min_duration_s", np.float64),
        ("field_band_frac", np.float64),
    ]
)

#: a closed stretch: its kind, start and end (s), peak (deg, or the gap in s) and when, signed error and σ
#: peaks (deg, NaN: none)
CLOSED = np.dtype(
    [
        ("kind", np.int64),
        ("t_start", np.float64),
        ("t_end", np.float64),
        ("peak", np.float64),
        ("t_peak", np.float64),
        ("err", np.float64),
        ("std", np.float64),
    ]
)

#: a change of a row signal: which (index into :data:`ROW_SIGNALS`), when, to which state, the error then
CHANGE = np.dtype([("signal", np.int64), ("t", np.float64), ("up", np.bool_), ("err", np.float64)])


def new_scan() -> np.ndarray:
    """A scan that has seen no row: a one-element array of :data:`SCAN` (the kernel takes its record)."""
    s = np.zeros(1, dtype=SCAN)
    for name in ("t_first", "last_used", "gap_err", "gap_std"):
        s[name] = np.nan
    return s


@njit(cache=True, error_model="numpy")
def scan(t, err, std, used, interference, strength, dip, state, levels):
    """Scan the rows (times t, error and σ in deg, magnetometer used, interference flag, the strength and
    dip detectors' value, reference and tolerance columns: :func:`_deviation`) with the one-element arrays
    ``state`` (:data:`SCAN`) and ``levels`` (:data:`LEVELS`); returns the stretches closed (:data:`CLOSED`)
    and the signal changes (:data:`CHANGE`), each in time order."""
    s = state[0]
    lv = levels[0]
    n = len(t)
    closed = np.empty(3 * n, dtype=CLOSED)  # a row closes at most an error, a sigma and a gap stretch
    changes = np.empty(len(ROW_SIGNALS) * n, dtype=CHANGE)
    n_closed = 0
    n_changes = 0
    for i in range(n):
        ti, e, sd = t[i], err[i], std[i]
        dev_f = _deviation(strength, i)
        dev_i = _deviation(dip, i)
        if not np.isfinite(s.t_first):
            s.t_first = ti
        if used[i]:
            s.referenced = True
        if s.referenced:  # before the first correction the heading is arbitrary and σ 180° by construction
            n_closed = _extend(s.error, ERROR, ti, abs(e), lv.error_onset_deg, lv.error_deg, e, sd, lv,
                               closed, n_closed)  # fmt: skip
            n_closed = _extend(s.sigma, SIGMA, ti, sd, lv.std_deg, lv.std_deg, e, sd, lv, closed, n_closed)
        s.gap_err = _signed_max(s.gap_err, e)
        s.gap_std = _nanmax(s.gap_std, sd)
        if used[i]:
            start = s.last_used if np.isfinite(s.last_used) else s.t_first
            if ti - start > lv.no_reference_s:
                _put(closed, n_closed, NO_REFERENCE, start, ti, ti - start, ti, s.gap_err, s.gap_std)
                n_closed += 1
            s.last_used = ti
            s.gap_err = np.nan
            s.gap_std = np.nan
        if interference[i] != s.interference:
            s.interference = interference[i]
            n_changes = _put_change(changes, n_changes, INTERFERENCE, ti, s.interference, e)
        if (dev_f >= 1.0) != s.strength:
            s.strength = not s.strength
            n_changes = _put_change(changes, n_changes, STRENGTH, ti, s.strength, e)
        if (dev_i >= 1.0) != s.dip:
            s.dip = not s.dip
            n_changes = _put_change(changes, n_changes, DIP, ti, s.dip, e)
        if (max(dev_f, dev_i) >= lv.field_band_frac) != s.field_out:
            s.field_out = not s.field_out
            n_changes = _put_change(changes, n_changes, FIELD_OUT, ti, s.field_out, e)
    if n:  # stretches whose last row above is more than merge_s before the batch's last row are over
        if s.error.open and t[n - 1] - s.error.t_last > lv.merge_s:
            n_closed = _close(s.error, ERROR, lv, closed, n_closed)
        if s.sigma.open and t[n - 1] - s.sigma.t_last > lv.merge_s:
            n_closed = _close(s.sigma, SIGMA, lv, closed, n_closed)
    return closed[:n_closed], changes[:n_changes]


@njit(cache=True, error_model="numpy")
def _deviation(band, i):
    """Row ``i``'s deviation ``|value − reference| / tolerance`` of a detector's ``(value, reference,
    tolerance)`` columns, in units of the tolerance; 0 where it is not finite (a column NaN there)."""
    value, ref, tol = band
    dev = abs(value[i] - ref[i]) / tol[i]
    return dev if np.isfinite(dev) else 0.0


@njit(cache=True, error_model="numpy")
def close_open(state, levels):
    """Close the open ``error`` and ``sigma`` stretches (the end of the run); returns those kept
    (:data:`CLOSED`)."""
    s = state[0]
    lv = levels[0]
    closed = np.empty(2, dtype=CLOSED)
    n = 0
    if s.error.open:
        n = _close(s.error, ERROR, lv, closed, n)
    if s.sigma.open:
        n = _close(s.sigma, SIGMA, lv, closed, n)
    return closed[:n]


@njit(cache=True, error_model="numpy")
def _extend(run, kind, t, value, onset, level, e, sd, lv, closed, n_closed):
    """A row with ``value`` (NaN: none) into the stretch ``run`` of ``kind`` (above ``onset``, reaching
    ``level``); returns the number of closed records."""
    if not value > onset:
        return n_closed
    if run.open and t - run.t_last > lv.merge_s:
        n_closed = _close(run, kind, lv, closed, n_closed)
    if not run.open:
        run.open = True
        run.t_start = t
        run.reached = False
        run.peak = -np.inf
        run.t_peak = np.nan
        run.err = np.nan
        run.std = np.nan
    run.t_last = t
    run.reached = run.reached or value > level
    if value > run.peak:
        run.peak = value
        run.t_peak = t
    run.err = _signed_max(run.err, e)
    run.std = _nanmax(run.std, sd)
    return n_closed


@njit(cache=True, error_model="numpy")
def _close(run, kind, lv, closed, n_closed):
    """Close ``run``; it is a stretch (written to ``closed``) when it reached the threshold and lasted
    ``min_duration_s``."""
    run.open = False
    if run.reached and run.t_last - run.t_start >= lv.min_duration_s:
        _put(closed, n_closed, kind, run.t_start, run.t_last, run.peak, run.t_peak, run.err, run.std)
        n_closed += 1
    return n_closed


@njit(cache=True, error_model="numpy")
def _put(closed, j, kind, t_start, t_end, peak, t_peak, err, std):
    c = closed[j]
    c.kind, c.t_start, c.t_end, c.peak, c.t_peak, c.err, c.std = kind, t_start, t_end, peak, t_peak, err, std


@njit(cache=True, error_model="numpy")
def _put_change(changes, j, signal, t, up, err):
    c = changes[j]
    c.signal, c.t, c.up, c.err = signal, t, up, err
    return j + 1


@njit(cache=True, error_model="numpy")
def _signed_max(current, v):
    """The value of larger magnitude of ``current`` and ``v``, NaN ignored (a tie keeps ``current``)."""
    if np.isfinite(v) and (not np.isfinite(current) or abs(v) > abs(current)):
        return v
    return current


@njit(cache=True, error_model="numpy")
def _nanmax(current, v):
    """The larger of ``current`` and ``v``, NaN ignored."""
    if np.isfinite(v) and (not np.isfinite(current) or v > current):
        return v
    return current
