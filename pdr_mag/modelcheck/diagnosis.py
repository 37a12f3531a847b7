"""What :func:`pdr_mag.modelcheck.select.diagnose` reports: its settings, the records of a diagnosis (the
candidates tried, their tests against the recording's null, the models) and the per-effect estimates in the
units of INTERFACE.md (``diagnose --json``)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pdr_mag._json import rounded
from pdr_mag.modelcheck.fit import CANDIDATES, FitResult, Problem, soft_iron_distortion
from pdr_mag.modelcheck.null import NullSettings
from pdr_mag.modelcheck.orientation import OrientationSettings
from pdr_mag.modelcheck.predict import anomaly_field, offset_change

GAP_METRIC = "rms of measured minus simulated magnetometer, µT"


@dataclass(frozen=True)
class DiagnoseSettings:
    """Settings of :func:`pdr_mag.modelcheck.select.diagnose` (documented defaults).

    Attributes
    ----------
    candidates : tuple of str
        Effects that may be added (``temperature_offset`` only applies with a temperature channel).
    score_threshold : float
        Least ΔBIC for an effect to count as missing.
    min_gap_reduction : float
        Least relative shrink of the gap above the white noise for an effect to count as missing.
    anomaly_knot_s : float
        Knot spacing of the ``local_anomaly`` field, s.
    anomaly_min_uT : float
        Smallest world-frame residual (1-s mean) that can mark a local anomaly, µT.
    anomaly_max_share : float
        Largest share of the recording a *local* anomaly may cover.
    max_rounds : int
        Most effects added.
    max_nfev : int
        Evaluations per nonlinear fit.
    orientation : OrientationSettings
    null : NullSettings
        The recording's own null (:mod:`.null`): a candidate that passes the two rules above must also
        beat what it fits on surrogates of the recording with nothing missing.
    """

    candidates: tuple[str, ...] = CANDIDATES
    score_threshold: float = 10.0
    min_gap_reduction: float = 0.1
    anomaly_knot_s: float = 1.0
    anomaly_min_uT: float = 3.0
    anomaly_max_share: float = 0.5
    max_rounds: int = 6
    max_nfev: int = 60
    orientation: OrientationSettings = field(default_factory=OrientationSettings)
    null: NullSettings = field(default_factory=NullSettings)


@dataclass(frozen=True)
class NullTest:
    """A candidate against the recording's null: its statistic (a nested fit's gain
    ``ln(cost_current / cost_candidate)``, see :func:`pdr_mag.modelcheck.select._null_tests`) on the
    subsampled recording, the replicates' values and the threshold it had to beat."""

    statistic: float
    threshold: float
    replicates: tuple[float, ...]
    stride: int

    @property
    def passed(self) -> bool:
        return bool(self.statistic > self.threshold)

    def to_dict(self) -> dict:
        v = np.asarray(self.replicates, dtype=float)
        return {"statistic": rounded(self.statistic, 5), "threshold": rounded(self.threshold, 5),
                "null_mean": rounded(float(np.mean(v)), 5) if v.size else None,
                "null_max": rounded(float(np.max(v)), 5) if v.size else None,
                "replicates": int(v.size), "stride": self.stride, "passed": self.passed}


@dataclass(frozen=True)
class Candidate:
    """One candidate tried in one round: gap (µT), score (ΔBIC), its estimate (JSON units) and, when it
    passed the ΔBIC and gap rules, its test against the recording's null."""

    effect: str
    gap: float
    score: float
    estimate: dict
    round: int
    significant: bool
    null: NullTest | None = None

    def to_dict(self) -> dict:
        return {"effect": self.effect, "gap": rounded(self.gap), "score": rounded(self.score, 2),
                "estimate": self.estimate, "round": self.round, "significant": self.significant,
                "null": None if self.null is None else self.null.to_dict()}


@dataclass(frozen=True)
class ModelSummary:
    effects: tuple[str, ...]
    gap: float
    estimate: dict
    fit: FitResult
    problem: Problem

    def to_dict(self) -> dict:
        return {"effects": list(self.effects), "gap": rounded(self.gap), "estimate": self.estimate}


@dataclass(frozen=True)
class Diagnosis:
    """What :func:`pdr_mag.modelcheck.select.diagnose` found (``to_dict()`` is the ``diagnose --json`` object
    of INTERFACE.md).

    ``identifiability``: every candidate's verdict (:class:`~pdr_mag.modelcheck.identify.Identifiability`),
    ``motion`` the motion it was judged on; ``gyro_bias_from_accelerometer``: the accelerometer's part of
    the gyro bias (:class:`~pdr_mag.modelcheck.gyro.AccelerometerBias`), empty along the truth."""

    baseline: ModelSummary
    candidates: tuple[Candidate, ...]
    rounds: tuple[tuple[Candidate, ...], ...]
    missing_effects: tuple[str, ...]
    final: ModelSummary
    orientation_source: str
    duration_s: float
    n_samples: int
    n_eff: float = float("nan")
    rules: dict = field(default_factory=dict)
    identifiability: dict = field(default_factory=dict)
    motion: dict = field(default_factory=dict)
    gyro_bias_from_accelerometer: dict = field(default_factory=dict)

    @property
    def missing_effect(self) -> str | None:
        return self.missing_effects[0] if self.missing_effects else None

    def with_status(self, *status: str) -> tuple[str, ...]:
        """The candidate effects whose identifiability has one of these statuses."""
        return tuple(e for e, v in self.identifiability.items() if v.status in status)

    def to_dict(self) -> dict:
        return {
            "gap_metric": GAP_METRIC,
            "baseline": self.baseline.to_dict(),
            "candidates": [c.to_dict() for c in self.candidates],
            "missing_effect": self.missing_effect,
            "missing_effects": list(self.missing_effects),
            "final": self.final.to_dict(),
            "rounds": [[c.to_dict() for c in r] for r in self.rounds],
            "orientation": self.orientation_source,
            "duration_s": rounded(self.duration_s, 3),
            "n_samples": self.n_samples,
            "n_eff": rounded(self.n_eff, 1),
            "rules": self.rules,
            "not_identifiable": list(self.with_status("not_identifiable")),
            "partly_identifiable": list(self.with_status("partly_identifiable")),
            "identifiability": {e: v.to_dict() for e, v in self.identifiability.items()},
            "motion": self.motion,
            "gyro_bias_from_accelerometer": self.gyro_bias_from_accelerometer,
        }


def _vec(v, nd: int = 4) -> list:
    return [round(float(x), nd) for x in np.ravel(v)]


# ---------------------------------------------------------------------------------------------- estimates


def estimates(problem: Problem, fit: FitResult, effects) -> dict:
    """Per-effect estimates in the units of INTERFACE.md, for the given effect names."""
    out: dict = {}
    nl, lin, sd = fit.nonlinear, fit.linear, fit.std
    for e in effects:
        if e == "hard_iron":
            out[e] = {"uT": _vec(lin["hard_iron"], 3), "std": _vec(sd["hard_iron"], 3),
                      "t_ref": rounded(problem.t_origin + problem.t_ref, 3)}
        elif e == "noise":
            out[e] = {"uT": _vec(np.sqrt(np.mean(fit.residual**2, axis=0)), 4)}
        elif e == "time_offset":
            out[e] = {"seconds": rounded(nl[e][0], 5), "std": rounded(sd[e][0], 5)}
        elif e == "mag_imu_misalignment":
            deg = np.degrees(nl[e])
            out[e] = {"degrees": rounded(np.linalg.norm(deg), 3), "rotvec_deg": _vec(deg, 3),
                      "std_deg": _vec(np.degrees(sd[e]), 3)}
        elif e == "soft_iron":
            s = np.linalg.inv(soft_iron_distortion(nl[e]))
            s = 0.5 * (s + s.T)
            s = s / np.cbrt(np.linalg.det(s))
            ev = np.linalg.eigvalsh(s)
            out[e] = {"matrix": [_vec(row, 5) for row in s], "axis_ratio": rounded(ev[-1] / ev[0], 5),
                      "std": rounded(float(np.max(sd[e])), 5)}
        elif e == "bias_drift":
            out[e] = {"uT_per_min": _vec(lin[e], 4), "std": _vec(sd[e], 4)}
        elif e == "temperature_offset":
            out[e] = {"uT_per_degC": _vec(lin[e], 4), "std": _vec(sd[e], 4),
                      "t_ref_degC": rounded(problem.temp_ref, 2)}
        elif e == "gyro_bias":  # δ absent: named by the accelerometer alone (in the track's bias)
            delta = nl.get(e, np.zeros(3))
            total = problem.track.gyro_bias + delta
            up = np.mean(problem.r_dw0[:, :, 2], axis=0)  # mean up direction in device axes
            up /= np.linalg.norm(up)
            cov = fit.std.get("_cov_nonlinear")
            i0 = 1 if "time_offset" in nl else 0
            up_std = (float(np.sqrt(up @ cov[i0:i0 + 3, i0:i0 + 3] @ up)) if cov is not None and e in nl
                      else float("nan"))
            out[e] = {"rad_per_s": _vec(total, 5), "residual_rad_per_s": _vec(delta, 5),
                      "from_accelerometer_rad_per_s": _vec(problem.track.tilt_bias.correction, 5),
                      "std": _vec(sd.get(e, np.full(3, np.nan)), 5), "mean_up_d": _vec(up, 4),
                      "along_up_rad_per_s": rounded(up @ total, 5),
                      "along_up_std": rounded(up_std, 5)}
        elif e == "hard_iron_change":
            db = offset_change(problem, fit)
            mags = np.linalg.norm(db, axis=1)
            i = int(np.argmax(mags))
            kn, free = problem.offset_knots, problem.offset_knot_free
            edges = np.flatnonzero(np.diff(np.concatenate([[0], free.astype(np.int8), [0]])))
            t0 = problem.t_origin
            win = [[rounded(t0 + kn[a], 2), rounded(t0 + kn[b - 1], 2)]
                   for a, b in zip(edges[::2], edges[1::2], strict=True)]
            share = float(np.mean(np.interp(problem.t, kn, free.astype(float)) > 0))
            out[e] = {"uT": rounded(mags[i], 3), "t_peak": rounded(t0 + problem.t[i], 2), "windows_s": win,
                      "share": rounded(share, 3)}
        elif e == "local_anomaly":
            fld = anomaly_field(problem, fit)
            mags = np.linalg.norm(fld.values_w, axis=1)
            i = int(np.argmax(mags))
            free = problem.knot_free
            edges = np.flatnonzero(np.diff(np.concatenate([[0], free.astype(np.int8), [0]])))
            t0 = problem.t_origin
            win = [[rounded(t0 + problem.knots[a], 2), rounded(t0 + problem.knots[b - 1], 2)] for a, b in
                   zip(edges[::2], edges[1::2], strict=True)]
            share = float(np.mean(np.interp(problem.t, problem.knots, free.astype(float)) > 0))
            out[e] = {"uT": rounded(mags[i], 3), "t_peak": rounded(t0 + problem.knots[i], 2),
                      "windows_s": win, "share": rounded(share, 3)}
    return out
