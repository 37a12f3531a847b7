"""Magnetic interference detectors: is the calibrated field the Earth's?

Four checks, one module each, each a score that is ≥ 1 when the field fails it:

:mod:`~pdr_mag.fusion.detectors.strength`
    the strength against the local and the reference strength;
:mod:`~pdr_mag.fusion.detectors.dip`
    the dip below the horizon against the local and the reference inclination;
:mod:`~pdr_mag.fusion.detectors.variance`
    the windowed variance of the strength;
:mod:`~pdr_mag.fusion.detectors.consistency`
    the field's turn in the world frame against the gyroscope-propagated attitude.

The score is the largest of the four.  The flag uses hold-off timers so it neither flickers nor sticks: it
rises after the score has been ≥ 1 for ``hold_on_s`` and falls after the score has stayed < 1 for
``hold_off_s``.  The local references are learnt (time constant ``learn_ref_s``, a running mean of the
first samples) only from samples inside the loose bands around the references whose every check passes,
so a disturbance cannot drag them.

Two levels.  The default thresholds flag *gross* disturbances (a magnet, a steel door: ±14 µT, ±15° of
dip, 30° of turn, 100 µT² of variance) — the fusion skips those samples.  Below the thresholds the fusion
does not trust the field blindly either: it weights each sample by the smallest disturbance that explains
the deviations measured here (:mod:`pdr_mag.fusion.mag`).  Tight thresholds alone reject most of an indoor
walk (the building's field wanders by several µT and degrees) and leave the heading to the gyroscope for
too long; measured on the tyrex walks, the two levels together do better than either.

A detector is one unit
----------------------
:data:`DETECTORS` is the registry: each module there has its settings, its state, its compiled steps, its
diagnostic columns and rerun plot, its array form and its known-answer example (the parts are listed in
:mod:`~pdr_mag.fusion.detectors._unit`).  Everything else follows the registry: :class:`InterferenceSettings`
(one field per detector), :data:`DETECTOR_STATE`, :func:`detect_step` and the fusion's hooks (compiled
chains over the registry, in its order), the output's diagnostic columns (:data:`COLUMNS`,
:mod:`pdr_mag.fusion.rows`, :data:`pdr_mag.estimates.DIAG_KEYS`), the MCAP's bands and the rerun views
(:mod:`pdr_mag.sinks`), and ``tests/test_detectors.py``.  A fifth detector is a fifth module in
:data:`DETECTORS`.

The chains are numba closures over the registry's functions, built once at import: calls, not a loop over
function pointers, so the compiled fusion kernel that calls them is cached (``cache=True``) like any other.
"""

from __future__ import annotations

import sys
from dataclasses import field, make_dataclass

import numpy as np
from numba import njit

from pdr_mag import _jit_cache
from pdr_mag._records import check_numbers, settings_record
from pdr_mag.fusion import ew, quat
from pdr_mag.fusion.detectors import _unit, consistency, dip, strength, variance
from pdr_mag.fusion.detectors.consistency import ConsistencySettings
from pdr_mag.fusion.detectors.dip import DipSettings
from pdr_mag.fusion.detectors.strength import StrengthSettings
from pdr_mag.fusion.detectors.variance import VarianceSettings
from pdr_mag.fusion.ew import ew_alpha

#: the detectors, in the order their columns appear in the output and their steps run
DETECTORS = (strength, dip, variance, consistency)

__all__ = [
    "DETECTORS",
    "DETECTOR_STATE",
    "ConsistencySettings",
    "DipSettings",
    "InterferenceSettings",
    "StrengthSettings",
    "VarianceSettings",
    "detect_step",
    "forget_learnt",
    "hold_off",
    "new_detector_state",
]


# ------------------------------------------------------------------------------------------ settings
def _check_interference(self):
    check_numbers(self, positive=("learn_ref_s",))


InterferenceSettings = make_dataclass(
    "InterferenceSettings",
    [(d.NAME, d.Settings, field(default_factory=d.Settings)) for d in DETECTORS]
    + [("hold_on_s", float, 0.0), ("hold_off_s", float, 0.5), ("learn_ref_s", float, 30.0)],
    frozen=True,
    namespace={"__post_init__": _check_interference, "__module__": __name__},
)
InterferenceSettings.__doc__ = f"""Thresholds of the interference detectors (the module docstring).

    Attributes
    ----------
    {", ".join(d.NAME for d in DETECTORS)} : {", ".join(d.Settings.__name__ for d in DETECTORS)}
        Each detector's thresholds (its module).
    hold_on_s : float
        The score must stay ≥ 1 this long before the flag rises, s.
    hold_off_s : float
        The score must stay < 1 this long before the flag falls, s.
    learn_ref_s : float
        Time constant with which the local references (strength, dip) are learnt from clean samples, s
        (indoor fields differ from the WMM by several µT and degrees; the learnt values start at the first
        clean sample and follow the local field slowly).
    """

# ------------------------------------------------------------------------------------------ state
#: one magnetometer sample as the detectors see it (filled by the caller of :func:`detect_step`)
SAMPLE = np.dtype(
    [
        ("t", np.float64),  # time, s
        ("dt", np.float64),  # since the previous sample, s (inf: none)
        ("f", np.float64),  # strength F of the calibrated field, µT
        ("dip", np.float64),  # its dip below the horizon, deg
        ("mw", np.float64, (3,)),  # its direction in the world frame (unit; the gyro-propagated attitude)
        ("f_ref", np.float64),  # reference strength, µT (NaN: unknown)
        ("dip_ref", np.float64),  # reference inclination, deg (NaN: unknown)
        ("sigma_b_deg", np.float64),  # the filter's gyro-bias uncertainty, deg/s (widens the consistency)
    ],
    align=True,
)

#: the detectors' state for one magnetometer stream (nested in the fusion filter's state): the latest
#: sample, what they share (the learning count, the hold timer and the flag), and one record per detector
DETECTOR_STATE = np.dtype(
    [
        ("x", SAMPLE),  # the latest sample
        ("t", np.float64),  # time of the sample before it, s (NaN: none)
        ("n_learn", np.int64),  # clean samples learnt from
        ("flag", np.bool_),  # interference flag, after the hold timers
        ("since", np.float64),  # hold timer: when the score changed side of 1 (NaN: no change pending)
        ("score", np.float64),  # the largest score of the latest sample
        ("score_absolute", np.float64),  # … of the detectors against an absolute reference (ABSOLUTE)
        *((d.NAME, d.STATE) for d in DETECTORS),
    ],
    align=True,
)

#: every detector's diagnostic columns (name → meaning), in registry order
COLUMNS = {name: doc for d in DETECTORS for name, doc in d.COLUMNS.items()}
#: the detectors with a band in their columns: name → :class:`~pdr_mag.fusion.detectors._unit.Band`
BANDS = {d.NAME: d.BAND for d in DETECTORS if d.BAND is not None}
#: how the rerun sink draws each detector: name → :class:`~pdr_mag.fusion.detectors._unit.Plot`
PLOTS = {d.NAME: d.PLOT for d in DETECTORS}


def _check_units() -> None:
    for d in DETECTORS:
        if "score" not in d.STATE.names:
            raise ImportError(f"detector {d.NAME}: its STATE has no 'score'")
        for part in ("observe", "learn", "score", "disturbance2", "tolerance2", "write", "turn", "restart",
                     "example", "Settings", "COLUMNS", "BAND", "PLOT", "ABSOLUTE", "LEARNT"):  # fmt: skip
            if not hasattr(d, part):
                raise ImportError(f"detector {d.NAME}: no {part} (pdr_mag.fusion.detectors._unit)")


_check_units()


def _fill_nan(rec: np.ndarray) -> None:
    for name in rec.dtype.names:
        sub = rec[name]
        if sub.dtype.names is not None:
            _fill_nan(sub)
        elif sub.dtype.base == np.float64:
            rec[name] = np.nan


def forget_learnt(det: np.ndarray) -> None:
    """The detectors' local references (each detector's ``LEARNT`` fields) forgotten, to be learnt anew from
    the next clean samples (a running mean, then ``learn_ref_s``): what they learnt was the field calibrated
    by a calibration no longer in force.  ``det``: the detectors' state (a record of :data:`DETECTOR_STATE`,
    or a one-element array of it)."""
    for d in DETECTORS:
        for name in d.LEARNT:
            det[d.NAME][name] = np.nan
    det["n_learn"] = 0


def new_detector_state() -> np.void:
    """A fresh detector state (nothing learnt, no sample yet, flag down): one record of
    :data:`DETECTOR_STATE` (every float NaN)."""
    det = np.zeros(1, dtype=DETECTOR_STATE)
    _fill_nan(det)
    return det[0]


# ------------------------------------------------------------------------------------------ chains
def _each(fns):
    """``f(*args)`` for each f, in order."""
    head = fns[0]
    if len(fns) == 1:
        return head
    rest = _each(fns[1:])

    @njit(error_model="numpy")
    def chain(*args):
        head(*args)
        rest(*args)

    return chain


def _max(fns):
    """The largest of ``f(*args)``, each called in order."""
    head = fns[0]
    if len(fns) == 1:
        return head
    rest = _max(fns[1:])

    @njit(error_model="numpy")
    def chain(*args):
        a = head(*args)
        return max(a, rest(*args))

    return chain


def _sum(fns):
    """``((acc + f₁(*args)) + f₂(*args)) + …``, summed in order (so the rounding is that of a loop)."""
    head = fns[0]
    if len(fns) == 1:

        @njit(error_model="numpy")
        def last(acc, *args):
            return acc + head(*args)

        return last
    rest = _sum(fns[1:])

    @njit(error_model="numpy")
    def chain(acc, *args):
        return rest(acc + head(*args), *args)

    return chain


def _scores(units):
    """``(max of all scores, max of the ABSOLUTE detectors' scores or 0)``, each score computed once."""
    head = units[0].score
    absolute = units[0].ABSOLUTE
    if len(units) == 1:

        @njit(error_model="numpy")
        def last(det, ip):
            s = head(det, ip)
            return s, s if absolute else 0.0

        return last
    rest = _scores(units[1:])

    @njit(error_model="numpy")
    def chain(det, ip):
        s = head(det, ip)
        a, b = rest(det, ip)
        return max(s, a), max(s, b) if absolute else b

    return chain


_observe = _max([d.observe for d in DETECTORS])
_learn = _each([d.learn for d in DETECTORS])
_score = _scores(DETECTORS)
_disturbance2 = _sum([d.disturbance2 for d in DETECTORS])
_tolerance2 = _sum([d.tolerance2 for d in DETECTORS])
_write = _each([d.write for d in DETECTORS])
_turn = _each([d.turn for d in DETECTORS])
_restart = _each([d.restart for d in DETECTORS])


# ------------------------------------------------------------------------------------------ steps
@njit(cache=True, error_model="numpy")
def hold_step(flag, since, score, t, ip):
    """One step of the hold-off timer.

    ``since`` is the time the score last changed side of 1 (NaN = unknown).  Returns (flag, since).
    """
    bad = score >= 1.0
    if bad != flag:
        if not np.isfinite(since):
            since = t
        wait = ip.hold_on_s if bad else ip.hold_off_s
        if t - since >= wait:
            flag = bad
            since = np.nan
    else:
        since = np.nan
    return flag, since


@njit(cache=True, error_model="numpy")
def detect_step(det, ip):
    """Every detector and the hold timer for the sample in ``det.x`` (its fields ``t``, ``f``, ``dip``,
    ``mw``, ``f_ref``, ``dip_ref``, ``sigma_b_deg`` set by the caller); returns the interference flag.

    ``det`` is a record of :data:`DETECTOR_STATE`, updated in place; ``ip`` the record of
    :class:`InterferenceSettings` (:func:`pdr_mag._records.settings_record`).  Each detector observes the
    sample; when every one passes it against the references' loose bands, the local references learn from
    it (weight ``max(α(min(Δt, 1 s), learn_ref_s), 1/n)``: a running mean of the first samples); then each
    scores it, and the largest score drives the hold timer.
    """
    x = det.x
    x.dt = x.t - det.t if np.isfinite(det.t) else np.inf
    clean = _observe(det, ip) < 1.0
    det.t = x.t
    if clean:
        det.n_learn += 1
        _learn(det, max(ew_alpha(min(x.dt, 1.0), ip.learn_ref_s), 1.0 / det.n_learn), ip)
    det.score, det.score_absolute = _score(det, ip)
    det.flag, det.since = hold_step(det.flag, det.since, det.score, x.t, ip)
    return det.flag


@njit(cache=True, error_model="numpy")
def disturbance2(det, p):
    """``d_min²``, µT²: the smallest disturbance that explains the detectors' deviations at the latest
    sample (each detector's part, summed in registry order; ``p`` the fusion's settings record)."""
    return _disturbance2(0.0, det, p)


@njit(cache=True, error_model="numpy")
def tolerance2(det):
    """The detectors' tolerance as a disturbance, µT² (e.g. ``tol_F² + (F tol_I)²``)."""
    return _tolerance2(0.0, det)


@njit(cache=True, error_model="numpy")
def reference_horizontal(det):
    """Horizontal strength of the local reference field the strength and dip detectors learnt,
    ``B_h = F_loc cos I_loc``, µT (NaN until both have learnt)."""
    f_loc = det.strength.loc
    dip_loc = det.dip.loc
    if np.isfinite(f_loc) and np.isfinite(dip_loc):
        return f_loc * np.cos(np.radians(dip_loc))
    return np.nan


@njit(cache=True, error_model="numpy")
def write(det, out, n, col):
    """Each detector's diagnostic columns into row ``n`` of the output's float block ``out``, column
    ``col.<name>`` (:data:`pdr_mag.fusion.rows.COL`)."""
    _write(det, out, n, col)


@njit(cache=True, error_model="numpy")
def turn(det, ex, ey, ez):
    """The filter corrected its attitude by ``Exp(e)`` (world frame): each detector's world-frame state
    turns with it."""
    _turn(det, ex, ey, ez)


@njit(cache=True, error_model="numpy")
def restart(det):
    """The filter's attitude jumped (a heading re-acquisition, a tilt reset): each detector restarts what
    depends on the world frame."""
    _restart(det)


# ------------------------------------------------------------------------------------------ arrays
def hold_off(t: np.ndarray, score: np.ndarray, settings=None) -> np.ndarray:
    """Flags (bool, N) from scores with the hold-on / hold-off timers."""
    ip = settings_record(settings or InterferenceSettings())[0]
    return _hold(np.asarray(t, dtype=float), np.asarray(score, dtype=float), ip)


@njit(cache=True, error_model="numpy")
def _hold(t, score, ip):
    out = np.empty(len(t), dtype=np.bool_)
    flag = False
    since = np.nan
    for i in range(len(t)):
        flag, since = hold_step(flag, since, score[i], t[i], ip)
        out[i] = flag
    return out


#: The modules the detectors' compiled code is built from, this one first (its ``__pycache__`` holds the
#: digest): a kernel that calls the detectors lists these among its own.
SOURCES = (sys.modules[__name__], *DETECTORS, _unit, ew, quat)
# numba checks a cached function against its own file only: empty the caches when any part changed
_jit_cache.refresh_if_changed(SOURCES, "detectors")
