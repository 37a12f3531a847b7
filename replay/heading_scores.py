"""The heading scored against what a recording knows of the true heading: the direction walked between
surveyed waypoints, and orientation series to compare with (motion capture ``truth``, the phone's own
``os``).  Numbers in, numbers out: no file format; :class:`HeadingScores` gathers both while a replay
streams (a sink, so its memory does not grow with the recording's length beyond the scored windows).

Walked direction
----------------
Waypoints are ``(t, x, y)``: seconds on the estimates' clock, metres east and north of any origin on a
true-north map (the shopping-mall traces' ``TYPE_WAYPOINT``; position fixes in latitude/longitude go
through :func:`waypoints_from_fixes`).  A *segment* is every pair of consecutive waypoints a, b at least
:data:`MIN_DISTANCE_M` apart in space and :data:`MIN_DURATION_S` in time; its bearing and scoring window are

    β = atan2(x_b − x_a, y_b − y_a)  (deg, clockwise from north, in [0, 360)),
    window = [t_a + ¼ (t_b − t_a), t_a + ¾ (t_b − t_a)]  (the middle half: the turns at its ends left out).

The estimate over the window is the circular mean of the rows' ``heading_deg`` ψ_i,

    ψ̄ = atan2(Σ sin ψ_i, Σ cos ψ_i),   ε = wrap₍₋₁₈₀,₁₈₀₎(ψ̄ − β),

with σ the median of their ``heading_std_deg``; a window holding fewer than :data:`MIN_ROWS` rows scores
ε = :data:`MISSED_DEG` (σ undefined).  Pooled over segments (:func:`pooled`): median and mean of |ε|,
segments beyond 20° and 45°, the share whose |ε| ≤ 2σ (over the segments with a finite σ > 0; the walked
direction itself carries a few degrees, people do not walk straight), and the segments more than 45° off
with σ ≤ 20° (wrong and confident).  These are the definitions of ``../shared/tools/walked-direction``;
``tests/test_heading_scores.py`` checks them against that tool's own printout.

Heading error against an orientation series
-------------------------------------------
At every output epoch ``t`` inside a reference series the reference is slerp-interpolated between its two
samples around ``t`` (epochs whose two samples lie more than :data:`MAX_REF_GAP_S` apart are not scored),
and the error rotation ``e = q_est ⊗ q_ref⁻¹`` (world frame) gives the heading error as its twist about the
world Up axis,

    ε = wrap₍₋₁₈₀,₁₈₀₎( 2 · atan2(e_z, e_w) )  [deg],

the definition of the shared tyrex scorer (``../shared/benchmarks/tyrex/score.py``), which stays defined at
any pitch.  :class:`ReferenceErrors` keeps the count of |ε| beyond 45° and a :class:`Histogram` of |ε| in
bins of :data:`BIN_DEG` centred on its multiples over [0°, 180°], whose nearest-rank quantile (the
``⌈q·n⌉``-th smallest value) is exact to within half a bin.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from pdr_mag.conventions import quat_multiply, wrap_deg
from pdr_mag.sinks import QuietSink
from replay.formats._common import QUAT_NORM

#: Segment rules of the walked direction (``../shared/tools/walked-direction``).
MIN_DISTANCE_M = 4.0
MIN_DURATION_S = 3.0
WINDOW = (0.25, 0.75)
MIN_ROWS = 3
MISSED_DEG = 180.0

#: Histogram bin width, deg: quantiles are given to within half of it.
BIN_DEG = 0.01

#: Largest gap between two reference samples that an output epoch between them is scored across, s.
MAX_REF_GAP_S = 1.0

#: The reference series scored (``Recording.truth`` and the ``Recording.references`` names).
REFERENCES = ("truth", "os")

#: WGS-84 semi-major axis (m) and first eccentricity squared, for the local east/north of position fixes.
_WGS84_A = 6378137.0
_WGS84_E2 = 6.69437999014e-3


# --------------------------------------------------------------------------------------- walked direction
def walked_segments(waypoints) -> list[tuple[float, float, float]]:
    """The scored segments of a walk: ``(t_lo, t_hi, bearing_deg)`` for each pair of consecutive waypoints
    at least :data:`MIN_DISTANCE_M` and :data:`MIN_DURATION_S` apart.

    Parameters
    ----------
    waypoints : sequence of (t, x_m, y_m)
        In time order: s, metres east, metres north (true north).

    Returns
    -------
    list of (float, float, float)
        The middle half of the segment's time (s) and its bearing, deg clockwise from north in [0, 360).
    """
    wp = [(float(w[0]), float(w[1]), float(w[2])) for w in waypoints]
    out = []
    for (ta, xa, ya), (tb, xb, yb) in zip(wp[:-1], wp[1:], strict=True):
        dx, dy = xb - xa, yb - ya
        if math.hypot(dx, dy) < MIN_DISTANCE_M or tb - ta < MIN_DURATION_S:
            continue
        lo, hi = WINDOW
        out.append((ta + lo * (tb - ta), ta + hi * (tb - ta), math.degrees(math.atan2(dx, dy)) % 360))
    return out


def waypoints_from_fixes(fixes) -> list[tuple[float, float, float]]:
    """Position fixes ``(t, latitude_deg, longitude_deg, …)`` as waypoints ``(t, east_m, north_m)`` on the
    plane tangent to the WGS-84 ellipsoid at the first fix (x = N cos φ₀ Δλ, y = M Δφ with the prime-vertical
    and meridian radii N, M at φ₀: bearings within 0.01° over a building)."""
    fixes = [f for f in fixes if len(f) >= 3]
    if not fixes:
        return []
    lat0, lon0 = math.radians(float(fixes[0][1])), math.radians(float(fixes[0][2]))
    s2 = math.sin(lat0) ** 2
    n = _WGS84_A / math.sqrt(1 - _WGS84_E2 * s2)
    m = _WGS84_A * (1 - _WGS84_E2) / (1 - _WGS84_E2 * s2) ** 1.5
    return [(float(f[0]), n * math.cos(lat0) * (math.radians(float(f[2])) - lon0),
             m * (math.radians(float(f[1])) - lat0)) for f in fixes]


class SegmentScorer:
    """The walked-direction error of each segment, accumulated over chunks of estimate rows (any chunking
    gives the same sums): per segment the row count, Σ sin ψ, Σ cos ψ and the rows' σ."""

    def __init__(self, segments):
        self.segments = [(float(a), float(b), float(c)) for a, b, c in segments]
        self._lo = np.array([s[0] for s in self.segments])
        self._hi = np.array([s[1] for s in self.segments])
        n = len(self.segments)
        self.n_rows = np.zeros(n, dtype=np.int64)
        self.sum_sin = np.zeros(n)
        self.sum_cos = np.zeros(n)
        self._std: list[list[np.ndarray]] = [[] for _ in range(n)]

    def add(self, t, heading_deg, heading_std_deg=None) -> None:
        """Add estimate rows (``t`` increasing, s; deg; deg or None)."""
        t = np.asarray(t, dtype=float)
        if not len(t) or not self.segments:
            return
        r = np.radians(np.asarray(heading_deg, dtype=float))
        std = None if heading_std_deg is None else np.asarray(heading_std_deg, dtype=float)
        for k in np.flatnonzero((self._hi >= t[0]) & (self._lo <= t[-1])):
            i0 = int(np.searchsorted(t, self._lo[k], side="left"))
            i1 = int(np.searchsorted(t, self._hi[k], side="right"))
            if i1 <= i0:
                continue
            self.n_rows[k] += i1 - i0
            self.sum_sin[k] += float(np.sin(r[i0:i1]).sum())
            self.sum_cos[k] += float(np.cos(r[i0:i1]).sum())
            if std is not None:
                self._std[k].append(std[i0:i1])

    def results(self) -> list[tuple[float, float]]:
        """``(error_deg, sigma_deg)`` per segment, in order; a missed window is ``(180.0, nan)``."""
        out = []
        for k, (_, _, beta) in enumerate(self.segments):
            if self.n_rows[k] < MIN_ROWS:
                out.append((MISSED_DEG, math.nan))
                continue
            est = math.degrees(math.atan2(self.sum_sin[k], self.sum_cos[k]))
            sig = float(np.median(np.concatenate(self._std[k]))) if self._std[k] else math.nan
            out.append((float(wrap_deg(est - beta)), sig))
        return out


def score_segments(t, heading_deg, heading_std_deg, segments) -> list[tuple[float, float]]:
    """``(error_deg, sigma_deg)`` of each segment of :func:`walked_segments` for estimate rows ``t`` (s,
    increasing), ``heading_deg`` and ``heading_std_deg`` (or None: σ is then NaN)."""
    scorer = SegmentScorer(segments)
    scorer.add(t, heading_deg, heading_std_deg)
    return scorer.results()


def pooled(results) -> dict:
    """The pooled figures of ``(error_deg, sigma_deg)`` pairs: ``n_segments``, ``median_deg`` and
    ``mean_deg`` of |ε|, ``p95_deg`` (nearest rank), ``n_over_20``, ``n_over_45``, ``within_2sigma_share``
    (None without a finite σ > 0) and ``n_over_45_sigma_le_20``; the figures are None without segments."""
    e = np.abs(np.array([r[0] for r in results], dtype=float))
    s = np.array([r[1] for r in results], dtype=float)
    if not len(e):
        return {"n_segments": 0, "median_deg": None, "mean_deg": None, "p95_deg": None, "n_over_20": 0,
                "n_over_45": 0, "within_2sigma_share": None, "n_over_45_sigma_le_20": 0}
    has = np.isfinite(s) & (s > 0)
    return {
        "n_segments": len(e),
        "median_deg": float(np.median(e)),
        "mean_deg": float(e.mean()),
        "p95_deg": float(np.sort(e)[math.ceil(0.95 * len(e)) - 1]),
        "n_over_20": int((e > 20).sum()),
        "n_over_45": int((e > 45).sum()),
        "within_2sigma_share": float(np.mean(e[has] / s[has] <= 2)) if has.any() else None,
        "n_over_45_sigma_le_20": int(((e > 45) & np.isfinite(s) & (s <= 20)).sum()),
    }


# ---------------------------------------------------------------------------------- reference series
class Histogram:
    """Counts of angles in [0°, 180°], in bins of :data:`BIN_DEG` centred on its multiples."""

    def __init__(self, top_deg: float = 180.0):
        self.n_bins = int(round(top_deg / BIN_DEG)) + 1
        self.counts = np.zeros(self.n_bins, dtype=np.int64)

    def add(self, values_deg: np.ndarray) -> None:
        """Count the finite values (clipped into the range)."""
        v = np.asarray(values_deg, dtype=float)
        v = v[np.isfinite(v)]
        if len(v):
            idx = np.clip(np.rint(v / BIN_DEG), 0, self.n_bins - 1).astype(np.int64)
            self.counts += np.bincount(idx, minlength=self.n_bins)

    @property
    def n(self) -> int:
        return int(self.counts.sum())

    def quantile(self, q: float) -> float | None:
        """Nearest-rank ``q`` quantile (the ``⌈q·n⌉``-th smallest value) to within ``BIN_DEG / 2``, or None
        without values."""
        return self.quantiles(q)[0]

    def quantiles(self, *qs: float) -> list[float | None]:
        """:meth:`quantile` of each of ``qs`` (the counts summed once)."""
        cum = np.cumsum(self.counts)
        n = int(cum[-1])
        if n == 0:
            return [None] * len(qs)
        return [round(int(np.searchsorted(cum, max(1, math.ceil(q * n)))) * BIN_DEG, 2) for q in qs]


def heading_error_deg(q_est: np.ndarray, q_ref: np.ndarray) -> np.ndarray:
    """Signed heading error, deg: the twist about Up of ``e = q_est ⊗ q_ref⁻¹`` (w-first), in [-180, 180);
    the definition the compiled :func:`_score` computes in one pass (tested against each other)."""
    conj = np.asarray(q_ref, dtype=float) * np.array([1.0, -1.0, -1.0, -1.0])
    e = quat_multiply(q_est, conj)
    return wrap_deg(np.degrees(2.0 * np.arctan2(e[:, 3], e[:, 0])))


@njit(cache=True)
def _score(tr, qr, ts, qs, max_gap, bin_deg, counts):
    """Each estimate ``qs[k]`` at ``ts[k]`` inside ``[tr[0], tr[-1]]`` with a finite attitude (the others are
    not scored) against the reference ``qr`` slerped there (the shorter arc;
    :func:`pdr_mag.conventions.quat_slerp`'s formula), where the two reference samples around it are at most
    ``max_gap`` apart: |heading error| (:func:`heading_error_deg`) counted into ``counts`` (bins of
    ``bin_deg``, as :meth:`Histogram.add`).  Returns how many exceed 45°.  One pass in compiled code: the
    series is scored at every output epoch, 100–200 a second.  An epoch on a reference sample (``u = 0``:
    the phone's own attitude is often stamped with the gyroscope's times, as the rows are) takes the
    formula's weights there, exactly 1 and 0, without the arc's trigonometry.  The reference sample at or
    before each epoch is found by walking forward from the previous epoch's (rows come in time order; a row
    earlier than the one before starts the walk over)."""
    m = len(tr)
    nb = len(counts)
    n45 = 0
    j = 0  # the last reference sample at or before the previous scored row
    for k in range(len(ts)):
        if not (ts[k] >= tr[0] and ts[k] <= tr[m - 1]):
            continue
        if not (np.isfinite(qs[k, 0]) and np.isfinite(qs[k, 1])):
            continue
        if not (np.isfinite(qs[k, 2]) and np.isfinite(qs[k, 3])):
            continue
        if tr[j] > ts[k]:
            j = 0
        while j + 1 < m and tr[j + 1] <= ts[k]:
            j += 1
        i = min(j, m - 2)
        if tr[i + 1] - tr[i] > max_gap:
            continue
        u = min(max((ts[k] - tr[i]) / (tr[i + 1] - tr[i]), 0.0), 1.0)
        d = 0.0
        for c in range(4):
            d += qr[i, c] * qr[i + 1, c]
        sgn = -1.0 if d < 0.0 else 1.0
        if u == 0.0:
            w0, w1 = 1.0, 0.0  # sin(ang) / sin(ang) and sin(0) / sin(ang), or 1 − u and u
        else:
            d = abs(d)
            ang = np.arccos(min(max(d, -1.0), 1.0))
            s = np.sin(ang)
            if s < 1e-9:
                w0, w1 = 1.0 - u, u
            else:
                w0, w1 = np.sin((1.0 - u) * ang) / s, np.sin(u * ang) / s
        q0 = w0 * qr[i, 0] + w1 * sgn * qr[i + 1, 0]
        q1 = w0 * qr[i, 1] + w1 * sgn * qr[i + 1, 1]
        q2 = w0 * qr[i, 2] + w1 * sgn * qr[i + 1, 2]
        q3 = w0 * qr[i, 3] + w1 * sgn * qr[i + 1, 3]
        nq = np.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
        # e = q_est ⊗ conj(q_ref): its w and z parts give the twist about Up
        pw, px, py, pz = qs[k, 0], qs[k, 1], qs[k, 2], qs[k, 3]
        rw, rx, ry, rz = q0 / nq, -q1 / nq, -q2 / nq, -q3 / nq
        ew = pw * rw - px * rx - py * ry - pz * rz
        ez = pw * rz + px * ry - py * rx + pz * rw
        e = abs((np.degrees(2.0 * np.arctan2(ez, ew)) + 180.0) % 360.0 - 180.0)  # |wrap_deg(…)|
        counts[min(max(int(np.rint(e / bin_deg)), 0), nb - 1)] += 1
        if e > 45.0:
            n45 += 1
    return n45


def attitude_series(t: np.ndarray, q_wd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """An orientation series (``t`` (N,), w-first ``q_wd`` (N, 4)) as the scores and the phone's heading
    (:func:`pdr_mag.pipeline.fill_unknown_heading`) take it: samples that are no attitude (a non-finite time
    or value, a quaternion far from norm 1: an all-zero row) left out, by the readers' rule — the slerp
    between two unit quaternions is never zero — and the rest in time order, a repeated time holding its
    first sample.  Contiguous arrays."""
    t = np.asarray(t, dtype=float).reshape(-1)
    q = np.asarray(q_wd, dtype=float).reshape(-1, 4)
    # (the norm summed column by column: np.linalg.norm's sum along rows of 4 gives the same bits, ~4× slower)
    w, x, y, z = q.T
    norm = np.sqrt(w * w + x * x + y * y + z * z)
    ok = np.isfinite(t) & (norm >= QUAT_NORM[0]) & (norm <= QUAT_NORM[1])
    if not ok.all():
        t, q = t[ok], q[ok]
    if np.any(np.diff(t) <= 0):  # (a series in time order, as recorded, needs neither)
        order = np.argsort(t, kind="stable")
        t, q = t[order], q[order]
        keep = np.r_[True, np.diff(t) > 0]
        t, q = t[keep], q[keep]
    return np.ascontiguousarray(t), np.ascontiguousarray(q)


class ReferenceErrors:
    """One reference series (``t`` (N,), w-first device → world ``q_wd`` (N, 4); :func:`attitude_series`)
    and the |heading error| of the estimates against it: a :class:`Histogram` and the count beyond 45°."""

    def __init__(self, t: np.ndarray, q_wd: np.ndarray):
        self.t, self.q = attitude_series(t, q_wd)
        self.errors = Histogram()
        self.n_over_45 = 0

    def add(self, t: np.ndarray, q_est: np.ndarray) -> None:
        """Score estimate rows (``t`` s, ``q_est`` w-first) that the series covers."""
        if len(self.t) < 2:
            return
        ts = np.ascontiguousarray(t, dtype=float)
        qs = np.ascontiguousarray(q_est, dtype=float)
        self.n_over_45 += _score(self.t, self.q, ts, qs, MAX_REF_GAP_S, BIN_DEG, self.errors.counts)

    def summary(self) -> dict:
        """``n_epochs`` scored; ``median_deg``, ``p90_deg``, ``p95_deg`` of |ε| (±``BIN_DEG``/2) and
        ``share_over_45`` (None without scored epochs)."""
        n = self.errors.n
        median, p90, p95 = self.errors.quantiles(0.5, 0.9, 0.95)
        return {"n_epochs": n, "median_deg": median, "p90_deg": p90, "p95_deg": p95,
                "share_over_45": self.n_over_45 / n if n else None}


# ------------------------------------------------------------------------------------------ the sink
class HeadingScores(QuietSink):
    """A replay sink scoring the estimates against what the recording knows: the walked direction between
    the waypoints in its metadata (``waypoints`` as ``[t, x_m, y_m]``, or position ``fixes`` as ``[t,
    latitude_deg, longitude_deg, …]``) and each reference series of :data:`REFERENCES` it is given.
    :meth:`summary` is the ``replay --json`` summary's ``heading_error`` and ``walked_direction``."""

    def __init__(self):
        self.references: dict[str, ReferenceErrors] = {}
        self.walked: SegmentScorer | None = None
        self.walked_from: str | None = None
        self.north: str | None = None

    def open(self, meta: dict) -> None:
        self.north = meta.get("north")
        if meta.get("waypoints"):
            self.walked, self.walked_from = SegmentScorer(walked_segments(meta["waypoints"])), "waypoints"
        elif meta.get("positions"):
            self.walked = SegmentScorer(walked_segments(waypoints_from_fixes(meta["positions"])))
            self.walked_from = "positions"

    def reference(self, name, t, q_wd) -> None:
        if name in REFERENCES:
            self.references[name] = ReferenceErrors(t, q_wd)

    def estimates(self, batch, phone_rows: np.ndarray | None = None) -> None:
        """Score the rows; ``phone_rows``: the indices of those that took the phone's own heading
        (:func:`pdr_mag.pipeline.fill_unknown_heading`), left out of the ``os`` score — they agree with it
        by construction."""
        if not len(batch):
            return
        t = np.asarray(batch.t, dtype=float)
        q = np.asarray(batch.q_wd, dtype=float)
        for name, ref in self.references.items():
            if name == "os" and phone_rows is not None and len(phone_rows):
                own = np.ones(len(t), dtype=bool)
                own[phone_rows] = False
                ref.add(t[own], q[own])
            else:
                ref.add(t, q)
        if self.walked is not None:
            self.walked.add(t, batch.heading_deg, batch.heading_std_deg)

    def summary(self) -> dict:
        """``{"heading_error": {name: ReferenceErrors.summary()}, "walked_direction": {...} or None}``."""
        walked = None
        if self.walked is not None:
            res = self.walked.results()
            walked = {
                "from": self.walked_from,
                "north": self.north,
                **pooled(res),
                "segments": [{"t_lo": lo, "t_hi": hi, "bearing_deg": b, "error_deg": e,
                              "sigma_deg": s if math.isfinite(s) else None}
                             for (lo, hi, b), (e, s) in zip(self.walked.segments, res, strict=True)],
                "rules": {"min_distance_m": MIN_DISTANCE_M, "min_duration_s": MIN_DURATION_S,
                          "window": list(WINDOW), "min_rows": MIN_ROWS, "missed_deg": MISSED_DEG},
            }
        return {"heading_error": {k: v.summary() for k, v in sorted(self.references.items())},
                "walked_direction": walked}
