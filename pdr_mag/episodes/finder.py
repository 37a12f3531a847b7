"""Drift episodes: the stretches of a run where the heading went wrong, and what noticed it.

Numbers in, numbers out: the rows of :class:`pdr_mag.estimates.EstimateBatch` (in time order, in any
chunks), the pipeline's events and, when the recording has one, the true orientation → a list of
:class:`Episode`.  :class:`EpisodeFinder` streams: it keeps only the open stretches and the detector
transitions of the last few seconds, so its memory does not grow with the recording.

Kinds (each with its threshold in :class:`EpisodeSettings`)
---------------------------------------------------------
``error``
    ``|e|`` with ``e = wrap(ψ − ψ_true)`` (heading minus the true heading interpolated at the row, wrapped to
    [−180, 180) deg) exceeded ``error_deg``.  The episode is the stretch around it in which ``|e|`` stays
    above ``error_onset_deg`` — from where the error began to grow to where it came back.  Needs the truth.
``sigma``
    the filter's own 1-σ ``heading_std_deg`` exceeded ``std_deg`` (the stretch where it stays above).
``no_reference``
    no magnetometer correction (``mag_used``) for longer than ``no_reference_s``: the episode runs from the
    last correction (or the first row) to the next one (or the last row); the heading is the gyroscope's.

``error`` and ``sigma`` count only rows from the first magnetometer correction on (before it the heading is
arbitrary and σ is 180° by construction — that start is a ``no_reference`` stretch when it is long).
Stretches of one kind less than ``merge_s`` apart are one episode; ``error`` and ``sigma`` stretches shorter
than ``min_duration_s`` are none.

What noticed it
---------------
For the window ``[t_lo, t_end]`` — ``t_lo`` is ``t_start − lookback_s`` or the interference flag's last fall
before ``t_start``, whichever is later (a disturbance flagged and over is not this one's) — an episode
lists the first time each detector fired:
``interference`` (the flag rose), ``strength`` / ``dip`` (the field strength / dip angle left the
detector's band ``ref ± tol``, the ``field_ref_uT ± strength_tol_uT`` and ``dip_ref_deg ± dip_tol_deg``
columns) and the events ``calibration_suspected``, ``recalibration_requested`` and ``calibration_rejected``.

Detection latency: ``t_flag`` is the first rise of the interference flag in the window;
``t_field_out`` is when the field left its inner band — its deviation ``d = max(|F − F_ref| / tol_F,
|I − I_ref| / tol_I)`` reached ``field_band_frac`` (half way to the detector's threshold by default) for the
first time after ``t_lo`` or the flag's previous fall, whichever is later (that time itself when the field
was already out then); ``latency_s = t_flag − t_field_out``.  A disturbance the filter follows
before the flag rises shows as a positive latency with a large ``error_at_flag_deg``.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import NamedTuple

import numpy as np

from pdr_mag._records import check_numbers, default_settings
from pdr_mag.conventions import heading_deg_from_quat, wrap_deg
from pdr_mag.episodes import _kernel as K
from pdr_mag.estimates import Event
from pdr_mag.fusion.detectors import BANDS

#: Episode kinds, with the unit of their threshold and peak.
KINDS = {"error": "deg", "sigma": "deg", "no_reference": "s"}

#: The detectors that are events of the pipeline.
_EVENT_DETECTORS = ("calibration_suspected", "recalibration_requested", "calibration_rejected")
#: Detectors an episode can name (see the module docstring).
DETECTORS = ("strength", "dip", "interference", *_EVENT_DETECTORS)


@dataclass(frozen=True)
class EpisodeSettings:
    """Thresholds of the episode finder.

    Attributes
    ----------
    error_deg : float
        ``|heading − truth|`` above which an ``error`` episode is found, deg.
    error_onset_deg : float
        An ``error`` episode extends on both sides while ``|heading − truth|`` stays above this, deg.
    std_deg : float
        ``heading_std_deg`` above which a ``sigma`` episode is found, deg.
    no_reference_s : float
        Time without a magnetometer correction above which a ``no_reference`` episode is found, s.
    merge_s : float
        Stretches of one kind closer than this are one episode, s.
    min_duration_s : float
        ``error`` and ``sigma`` stretches shorter than this are not episodes (the filter's start-up
        transient, a single outlier), s.
    field_band_frac : float
        The field counts as out of its inner band when its strength or dip deviation reaches this fraction
        of the detector's tolerance (for the detection latency).
    lookback_s : float
        Detectors that fired up to this long before an episode's start are its detectors, s.
    max_truth_gap_s : float
        Rows farther than this from a valid truth sample have no error, s.
    """

    error_deg: float = 10.0
    error_onset_deg: float = 5.0
    std_deg: float = 10.0
    no_reference_s: float = 10.0
    merge_s: float = 2.0
    min_duration_s: float = 1.0
    field_band_frac: float = 0.5
    lookback_s: float = 5.0
    max_truth_gap_s: float = 0.5

    def __post_init__(self):
        check_numbers(self)
        if self.error_onset_deg > self.error_deg:
            raise ValueError(
                f"error_onset_deg: expected ≤ error_deg ({self.error_deg}), got {self.error_onset_deg}"
            )

    def threshold(self, kind: str) -> float:
        """The threshold of ``kind`` in its unit (:data:`KINDS`)."""
        return {"error": self.error_deg, "sigma": self.std_deg, "no_reference": self.no_reference_s}[kind]


@dataclass(frozen=True)
class Episode:
    """One drift episode (times on the recording's clock, s).

    Attributes
    ----------
    kind : str
        ``"error"``, ``"sigma"`` or ``"no_reference"``.
    t_start, t_end : float
        The stretch.
    threshold : float
        The kind's threshold (deg, deg, s).
    peak : float
        The kind's quantity at its worst: max ``|error|`` (deg), max σ (deg), the gap (s).
    t_peak : float
        When it peaked (for ``no_reference`` the gap's end).
    peak_error_deg : float or None
        The signed error of largest magnitude inside the stretch (None without truth).
    peak_std_deg : float
        The largest ``heading_std_deg`` inside the stretch (NaN when no row of it had one).
    detectors : tuple of (str, float)
        ``(detector, first time)`` in the window ``[t_lo, t_end]``, in time order.
    t_flag, t_field_out, latency_s : float or None
        The detection latency (module docstring).
    error_at_flag_deg : float or None
        The error at ``t_flag`` (None without truth or flag).
    """

    kind: str
    t_start: float
    t_end: float
    threshold: float
    peak: float
    t_peak: float
    peak_error_deg: float | None = None
    peak_std_deg: float = float("nan")
    detectors: tuple = ()
    t_flag: float | None = None
    t_field_out: float | None = None
    latency_s: float | None = None
    error_at_flag_deg: float | None = None

    @property
    def severity(self) -> float:
        """How far past its threshold: ``peak / threshold`` (the console ranks episodes by it)."""
        return self.peak / self.threshold if self.threshold > 0 else float("inf")

    def describe(self) -> str:
        """One line for people: the stretch, how bad, what noticed it and how late."""
        err = "" if self.peak_error_deg is None else f"error {self.peak_error_deg:+.1f}°"
        std = "" if not np.isfinite(self.peak_std_deg) else f"σ {self.peak_std_deg:.1f}°"
        if self.kind == "error":
            what = f"peak {err}" + (f" ({std})" if std else "")
        elif self.kind == "sigma":
            what = f"peak {std}" + (f" ({err})" if err else "")
        else:
            also = ", ".join(x for x in (err, std) if x)
            what = f"{self.peak:.1f} s on the gyroscope alone" + (f" ({also})" if also else "")
        text = f"{self.kind} {self.t_start:.1f}–{self.t_end:.1f} s: {what}; "
        if self.t_flag is None:
            text += "no interference flag"
        else:
            text += f"flag at {self.t_flag:.1f} s"
            if self.latency_s is not None:
                text += f", {self.latency_s:.1f} s after the field left its band"
            if self.error_at_flag_deg is not None:
                text += f", error then {self.error_at_flag_deg:+.1f}°"
        others = [n for n, _ in self.detectors if n not in ("interference", "strength", "dip")]
        return text + ("; " + ", ".join(others) if others else "")

    def to_event(self) -> Event:
        """The ``drift_episode`` :class:`pdr_mag.estimates.Event` at ``t_start`` that sinks draw (its
        ``data``: ``episode`` = the kind, the other fields of :meth:`to_dict`)."""
        d = self.to_dict()
        d.pop("t_start")
        return Event(self.t_start, "drift_episode", {"episode": d.pop("kind"), **d})

    @classmethod
    def from_dict(cls, d: dict) -> Episode:
        """Back from :meth:`to_dict` (a ``replay --json`` entry; JSON null → NaN for ``peak_std_deg``)."""
        kw = {f.name: d[f.name] for f in fields(cls) if f.name in d}
        kw["detectors"] = tuple((x["detector"], x["t"]) for x in d.get("detectors", ()))
        if kw.get("peak_std_deg") is None:
            kw["peak_std_deg"] = float("nan")
        return cls(**kw)

    def to_dict(self) -> dict:
        """The ``replay --json`` form (``duration_s`` and ``unit`` added, detectors as objects)."""
        d = {f.name: getattr(self, f.name) for f in fields(self)}  # (the values are immutable)
        d["duration_s"] = self.t_end - self.t_start
        d["unit"] = KINDS[self.kind]
        d["detectors"] = [{"detector": n, "t": t} for n, t in self.detectors]
        return d


class _Change(NamedTuple):
    """A transition of a binary signal: when, to which state, and the error then (deg, NaN if unknown)."""

    t: float
    up: bool
    err: float


class _Closed(NamedTuple):
    """A closed stretch waiting to become an :class:`Episode`."""

    kind: str
    t_start: float
    t_end: float
    peak: float
    t_peak: float
    err: float
    std: float


class EpisodeFinder:
    """Find drift episodes in a run's rows, streaming.

    Parameters
    ----------
    settings : EpisodeSettings, optional
    truth : (t, q_wd) or None
        True orientation (w-first quaternions, device → ENU), rows with NaN ignored.

    ``update(batch, events)`` with every batch and event of the run, in time order, returns the episodes
    closed so far; ``finish()`` the rest (sorted by start).  The rows go through a compiled scan
    (:mod:`pdr_mag.episodes._kernel`) that keeps the open stretches and the detectors' states; the
    transitions of each detector are kept here, pruned to those a window still to come can need.
    """

    def __init__(self, settings: EpisodeSettings | None = None, truth=None):
        self.settings = settings or default_settings(EpisodeSettings)
        self._truth = None
        if truth is not None:
            t_tr = np.asarray(truth[0], dtype=float)
            q = np.asarray(truth[1], dtype=float).reshape(len(t_tr), 4)
            ok = np.isfinite(t_tr)
            for component in q.T:  # (np.all(…, axis=1) over 4 columns is much slower)
                ok &= np.isfinite(component)
            if ok.sum() >= 2:
                if not ok.all():
                    t_tr, q = t_tr[ok], q[ok]
                if np.any(t_tr[1:] < t_tr[:-1]):
                    order = np.argsort(t_tr, kind="stable")
                    t_tr, q = t_tr[order], q[order]
                self._truth = (t_tr, np.unwrap(heading_deg_from_quat(q), period=360.0))
                wide = t_tr[1:] - t_tr[:-1] > self.settings.max_truth_gap_s
                self._truth_holes = (t_tr[:-1][wide], t_tr[1:][wide])
        self._scan = K.new_scan()
        self._levels = np.zeros(1, dtype=K.LEVELS)
        for name in K.LEVELS.names:
            self._levels[name] = getattr(self.settings, name)
        self._t_now = np.nan
        self._trans: dict[str, list[_Change]] = {name: [] for name in (*DETECTORS, "field_out")}
        self._pending: list[_Closed] = []
        self._done: list[Episode] = []

    @property
    def has_truth(self) -> bool:
        return self._truth is not None

    # ------------------------------------------------------------------ input
    def error_deg(self, t: np.ndarray, heading_deg: np.ndarray) -> np.ndarray:
        """``wrap(heading − truth)`` at ``t``, deg; NaN without truth within ``max_truth_gap_s``."""
        t = np.asarray(t, dtype=float)
        if self._truth is None:
            return np.full(len(t), np.nan)
        tt, hh = self._truth
        err = wrap_deg(np.asarray(heading_deg, dtype=float) - np.interp(t, tt, hh))
        if len(t) and not self._may_lack_truth(float(t.min()), float(t.max())):
            return err
        j = np.minimum(np.maximum(np.searchsorted(tt, t), 1), len(tt) - 1)
        near = np.minimum(np.abs(t - tt[j - 1]), np.abs(tt[j] - t))
        err[(near > self.settings.max_truth_gap_s) | (t < tt[0]) | (t > tt[-1])] = np.nan
        return err

    def _may_lack_truth(self, t_min: float, t_max: float) -> bool:
        """Whether a row in ``[t_min, t_max]`` may be farther than ``max_truth_gap_s`` from every truth
        sample: the span leaves the truth's, or meets a hole (truth samples ``a < b`` more than
        ``max_truth_gap_s`` apart, ``a < t_max`` and ``b ≥ t_min``).  A row ``t`` between truth samples
        ``a < t ≤ b`` closer than that is within ``t − a ≤ b − a`` of one (NaN: True)."""
        tt = self._truth[0]
        if not (tt[0] <= t_min and t_max <= tt[-1]):
            return True
        starts, ends = self._truth_holes
        k = int(np.searchsorted(ends, t_min))  # the first hole that ends at or after t_min
        return k < len(ends) and starts[k] < t_max

    def update(self, batch, events=()) -> list[Episode]:
        """Take the next rows (an ``EstimateBatch``) and the events up to them; return the episodes closed."""
        for ev in events:
            d = ev if isinstance(ev, dict) else ev.to_dict()
            if d["kind"] in _EVENT_DETECTORS:
                self._trans[d["kind"]].append(_Change(float(d["t"]), True, np.nan))
        if len(batch) == 0:
            return self._release()
        t = np.asarray(batch.t, dtype=float)
        closed, changes = K.scan(
            t,
            self.error_deg(t, batch.heading_deg),
            np.asarray(batch.heading_std_deg, dtype=float),
            np.asarray(batch.mag_used, dtype=bool),
            np.asarray(batch.interference, dtype=bool),
            _band(batch.diag, BANDS["strength"][:3], len(t)),  # (value, reference, tolerance) columns
            _band(batch.diag, BANDS["dip"][:3], len(t)),
            self._scan,
            self._levels,
        )
        self._take(closed)
        for signal, t_change, up, err in changes.tolist():
            self._trans[K.ROW_SIGNALS[signal]].append(_Change(t_change, up, err))
        self._t_now = float(t[-1])
        return self._release()

    def finish(self) -> list[Episode]:
        """Close what is open at the end of the run; return the remaining episodes."""
        self._take(K.close_open(self._scan, self._levels))
        if np.isfinite(self._t_now):
            s = self._scan[0]
            start = float(s["last_used"] if np.isfinite(s["last_used"]) else s["t_first"])
            if self._t_now - start > self.settings.no_reference_s:
                self._pending.append(
                    _Closed("no_reference", start, self._t_now, self._t_now - start, self._t_now,
                            float(s["gap_err"]), float(s["gap_std"]))
                )  # fmt: skip
        return self._release()

    def _take(self, closed: np.ndarray) -> None:
        """The scan's closed stretches (:data:`pdr_mag.episodes._kernel.CLOSED`) to the pending ones."""
        for kind, *rest in closed.tolist():
            self._pending.append(_Closed(K.KIND_NAMES[kind], *rest))

    def _release(self) -> list[Episode]:
        """The episodes closed since the last call (their windows end at their ends, all seen); prune."""
        out = [self._episode(p) for p in self._pending]
        self._pending = []
        # transitions older than any window still to come are not needed (keep the last one for the state)
        s = self._scan[0]
        starts = [float(s[kind]["t_start"]) for kind in ("error", "sigma") if s[kind]["open"]]
        starts.append(float(s["last_used"] if np.isfinite(s["last_used"]) else s["t_first"]))
        horizon = min([*starts, self._t_now]) - self.settings.lookback_s - self.settings.merge_s
        if np.isfinite(horizon):
            for trans in self._trans.values():
                k = 0
                while k + 1 < len(trans) and trans[k + 1].t < horizon:
                    k += 1
                if k:
                    del trans[:k]
        out.sort(key=lambda e: (e.t_start, e.kind))
        self._done += out
        return out

    def _episode(self, c: _Closed) -> Episode:
        s = self.settings
        kind, t_start, t_end = c.kind, c.t_start, c.t_end
        interference = self._trans["interference"]
        lo = max([t_start - s.lookback_s] + [c.t for c in interference if not c.up and c.t <= t_start])
        found = []
        for name in DETECTORS:
            first = _first_rise(self._trans[name], lo, t_end)
            if first is not None:
                found.append((name, first.t))
        found.sort(key=lambda x: x[1])
        flag = _first_rise(interference, lo, t_end)
        t_flag = err_flag = t_out = latency = None
        if flag is not None:
            t_flag = flag.t
            err_flag = None if not np.isfinite(flag.err) else flag.err
            since = max([lo] + [c.t for c in interference if not c.up and c.t < t_flag])
            t_out = _first_up(self._trans["field_out"], since, t_flag)
            if t_out is not None:
                latency = t_flag - t_out
        else:
            t_out = _first_up(self._trans["field_out"], lo, t_end)
        return Episode(
            kind=kind,
            t_start=float(t_start),
            t_end=float(t_end),
            threshold=s.threshold(kind),
            peak=float(c.peak),
            t_peak=float(c.t_peak),
            peak_error_deg=None if not np.isfinite(c.err) else float(c.err),
            peak_std_deg=float(c.std),
            detectors=tuple(found),
            t_flag=t_flag,
            t_field_out=t_out,
            latency_s=latency,
            error_at_flag_deg=err_flag,
        )

    @property
    def episodes(self) -> list[Episode]:
        """Every episode released so far, by start."""
        return sorted(self._done, key=lambda e: (e.t_start, e.kind))


def worst(episodes, n: int = 3) -> list[Episode]:
    """The ``n`` episodes furthest past their thresholds (:attr:`Episode.severity`), worst first."""
    return sorted(episodes, key=lambda e: -e.severity)[:n]


def _band(d: dict, keys: tuple[str, str, str], n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A detector's value, reference and tolerance columns from diag (the scan's deviation ``|value − ref| /
    tol``, 0 where one is NaN); NaN columns when one is missing (a deviation of 0 throughout)."""
    if not all(k in d for k in keys):
        return (np.full(n, np.nan),) * 3
    return tuple(np.ascontiguousarray(d[k], dtype=float) for k in keys)


def _first_rise(trans: list, lo: float, hi: float) -> _Change | None:
    """The first rise in ``[lo, hi]``, or None."""
    for c in trans:
        if c.t > hi:
            break
        if c.up and c.t >= lo:
            return c
    return None


def _first_up(trans: list, lo: float, hi: float) -> float | None:
    """When the signal is first up in ``[lo, hi]``: ``lo`` itself if it was up then, else its first rise."""
    state = False
    for c in trans:
        if c.t > lo:
            break
        state = c.up
    if state:
        return lo
    hit = _first_rise(trans, lo, hi)
    return None if hit is None else hit.t
