"""Which effect is missing: greedy forward selection by a penalised likelihood (BIC) with a threshold.

Score of adding effect e to the current model c (positive: e earns its place)::

    score_e = n_eff · ln(RSS_c / RSS_e) − (k_e − k_c) · ln(n_eff),   n_eff = 3N / τ_int(r_full)

which is ``BIC_c − BIC_e`` for white Gaussian noise of unknown σ, with the sample count cut to the number of
independent residuals: τ_int is the integrated autocorrelation time (1 for white noise) of the residual of
a *full* model (offset drift, and an anomaly field free over the whole recording) — the closest estimate
of the noise process there is, which still holds the fast correlated part that no effect explains
(orientation errors).  Taking τ_int from each
candidate's own residual would instead punish every candidate for the effects still missing besides it.

An effect is significant when three things hold:

1. ``score > score_threshold`` (10: "very strong" evidence on the Kass–Raftery scale);
2. it shrinks the gap's part above the white noise, ``√(gap² − σ_w²)``, by at least ``min_gap_reduction``
   (10 %, relative) — an effect worth naming.  σ_w is the recording's white noise (the median absolute
   first difference of the baseline residual, per axis: :func:`~pdr_mag.modelcheck.null.robust_sigma`),
   which no effect explains: measured against the whole gap, the same effect would be worth naming on a
   quiet magnetometer and not on a noisy one;
3. it beats the recording's own null (:mod:`.null`): on surrogates of the recording that have the
   current model, the recording's orientation error and noise but nothing missing, the same candidate
   fitted the same way must explain less than on the recording, at a false-alarm level of
   ``null.false_alarm`` (10⁻³ per candidate and round).

Rules 1 and 2 alone cannot tell a missing effect from the error of the gyro + accelerometer orientation,
which leaves correlated residuals (tilt errors of 0.5–5° in turns, swings and motion changes, i.e.
0.4–4 µT of field) that any flexible effect partly fits — by an amount that depends on the recording's
motion and length.  Rule 3 measures that amount on the recording itself; it is run only for candidates
that pass rules 1 and 2, so a recording with nothing near significance costs nothing more.  The best
significant effect (by score) is added and the search repeated until none is left; then every candidate gets
a verdict of what the motion can reveal of it (:mod:`.identify`).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from pdr_mag._json import rounded
from pdr_mag.modelcheck.diagnosis import (
    Candidate,
    DiagnoseSettings,
    Diagnosis,
    ModelSummary,
    NullTest,
    estimates,
)
from pdr_mag.modelcheck.fit import (
    BASELINE,
    CANDIDATES,
    FitResult,
    Problem,
    fit_along,
    fit_model,
    integrated_autocorr_time,
    make_problem,
    sample_matrices,
    with_track,
)
from pdr_mag.modelcheck.gyro import accelerometer_bias, heading_drift_start, replay
from pdr_mag.modelcheck.identify import SMALLEST, identifiability
from pdr_mag.modelcheck.null import (
    above_white,
    null_threshold,
    robust_sigma,
    stride_for,
    subsample,
    surrogate_residuals,
)
from pdr_mag.modelcheck.orientation import (
    OrientationTrack,
    estimate_orientation,
    track_from_truth,
)
from pdr_mag.modelcheck.predict import gap
from pdr_mag.modelcheck.support import anomaly_support

#: Two names for a disturbance confined in time: fixed in the world (an external field) or fixed to the
#: phone (an offset change).  They explain the same windows, so a model gets at most one of them — the one
#: that scores better (they differ only where the phone turns inside a window) — except that external
#: fields being the common case, ``hard_iron_change`` must beat ``local_anomaly``'s gap by
#: :data:`_LOCAL_MARGIN`.  The final estimate says how the other did, and ``ambiguous: true`` when the
#: two gaps are within that margin.
_LOCAL = ("local_anomaly", "hard_iron_change")
_LOCAL_MARGIN = 0.05

#: Effects that change the strength of the measured field.  An error of the orientation only turns the
#: predicted field (``B × φ``, perpendicular to it), so what these effects explain *along* the field is
#: what no orientation error can mimic: their test against the null counts the residual along the field.
#: The others (time_offset, mag_imu_misalignment, gyro_bias) turn the field too and are tested on all of it.
_STRENGTH = ("soft_iron", "bias_drift", "local_anomaly", "hard_iron_change", "temperature_offset")


# ---------------------------------------------------------------------------------------------- fitting


def _fit(problem: Problem, effects, current: FitResult, settings: DiagnoseSettings, hold=()) -> FitResult:
    init = dict(current.nonlinear)
    best = fit_model(problem, effects, init, settings.max_nfev, hold)
    if "gyro_bias" in effects and "gyro_bias" not in current.nonlinear:
        init2 = dict(init, gyro_bias=heading_drift_start(problem, current))
        alt = fit_model(problem, effects, init2, settings.max_nfev, hold)
        if alt.rss < best.rss:
            best = alt
    return best


def _score(current: FitResult, cand: FitResult, n_eff: float) -> float:
    return float(n_eff * np.log(current.rss / max(cand.rss, 1e-300)) - (cand.k - current.k) * np.log(n_eff))


def _candidate(eff: str, problem: Problem, current: FitResult, added, settings: DiagnoseSettings,
               gyro=None, accel=None):
    """The problem (with the windows of a local effect, or the orientation re-estimated with a gyro bias
    when ``gyro`` and ``accel`` are given) and the fit of one candidate added to the current model; None
    when a local effect finds no window."""
    p = problem
    if eff in _LOCAL:
        frame = "world" if eff == "local_anomaly" else "device"
        p = anomaly_support(problem, current, settings.anomaly_knot_s, settings.anomaly_min_uT,
                            max_share=settings.anomaly_max_share, frame=frame)
        if not (p.knot_free if frame == "world" else p.offset_knot_free).any():
            return None
    f = _fit(p, (*added, eff), current, settings)
    if eff == "gyro_bias" and gyro is not None:
        p, f = replay(p, f, gyro, accel, settings.orientation, settings.max_nfev)
    return p, f


def field_directions(problem: Problem, fit: FitResult) -> np.ndarray:
    """Unit direction of the field that ``fit`` predicts, per sample, in magnetometer axes (N, 3)."""
    b = np.asarray(fit.linear["field_w"], dtype=float)
    h = sample_matrices(problem, fit.nonlinear) @ (b / np.linalg.norm(b))
    return h / np.linalg.norm(h, axis=1, keepdims=True)


def _null_tests(problem: Problem, current: FitResult, added: tuple[str, ...], fits: dict,
                settings: DiagnoseSettings, rnd: int) -> tuple[str | None, dict[str, NullTest]]:
    """The effect the search adds among ``fits`` (effect → its problem, fit and gap on the recording, best
    score first) and the null tests that chose it: each candidate on the recording and on surrogates of
    it with nothing missing (a parametric bootstrap).

    :func:`_pick` asks for the tests in its order; the candidates it does not ask about are left
    untested (and not significant).

    A candidate's replicates are the current model's prediction (the null hypothesis) plus surrogates
    (:func:`~pdr_mag.modelcheck.null.surrogate_residuals`) of the residual that is left *with* the
    candidate: the residual of the fuller model holds the orientation error and the noise but not the
    effect, so a missing effect does not raise its own null (Davison & Hinkley 1997, §4.4: resample the
    residuals of the alternative, simulate under the null).  Recording and replicates are treated
    alike — subsampled to ``null.max_rate_hz``, and the statistic is a nested fit's gain
    ``ln(cost_current / cost_candidate)`` (cost: what the fit minimises, RSS plus the priors' penalty;
    the current model's nonlinear parameters held in both, only the linear ones and the candidate's
    refitted):

    * effects that change the field's strength (:data:`_STRENGTH`) are fitted to the residual's
      component along the predicted field alone (:func:`~pdr_mag.modelcheck.fit.fit_along`): what no
      orientation error reaches;
    * the others (rotations) to all of it, a gyro bias by its first-order heading drift only:
      re-estimating the orientation with a fitted bias also changes the tilt between the
      accelerometer's corrections, a knob that can trim the recording's own tilt errors (which the
      surrogates, drawn independently of the motion, cannot reproduce) — on a simulated texting walk
      with no bias it shrank the gap by 11 %;
    * a local effect is fitted in the windows found on the recording: the question is what a field in
      *those* windows explains when there is only orientation error and noise.
    """
    ns = settings.null
    stride = stride_for(problem, ns.max_rate_hz)
    sub = subsample(problem, stride)
    prediction = problem.mag - current.residual
    along = field_directions(sub, current)
    init = dict(current.nonlinear)

    def statistic(eff: str, p: Problem, p_e: Problem) -> float:
        if eff in _LOCAL:  # the recording's windows, in the recording and in every replicate alike
            q = replace(p, knots=p_e.knots, knot_free=p_e.knot_free, offset_knots=p_e.offset_knots,
                        offset_knot_free=p_e.offset_knot_free)
        else:
            q = p
        if eff in _STRENGTH:
            c0 = fit_along(p, added, along, init, 0)
            c1 = fit_along(q, (*added, eff), along, init, settings.max_nfev, hold=added)
        else:
            cur = fit_model(p, added, init, 0)
            c0, c1 = cur.cost, _fit(q, (*added, eff), cur, settings, hold=added).cost
        return float(np.log(c0 / max(c1, 1e-300)))

    out: dict[str, NullTest] = {}

    def passes(eff: str) -> bool:
        p_e, f_e, _ = fits[eff]
        rng = np.random.default_rng([ns.seed, rnd, CANDIDATES.index(eff)])
        reps = [statistic(eff, replace(sub, mag=(prediction + res)[::stride]), p_e)
                for res in surrogate_residuals(p_e, f_e, rng, ns.replicates, ns)]
        thr = null_threshold(reps, ns.false_alarm)
        out[eff] = NullTest(statistic(eff, sub, p_e), thr, tuple(reps), stride)
        return out[eff].passed

    return _pick({eff: g for eff, (_, _, g) in fits.items()}, passes), out


def _pick(ranked: dict[str, float], passes) -> str | None:
    """The effect the search adds among ``ranked`` (effect → gap, best score first): the first for which
    ``passes(effect)`` holds, except that a ``hard_iron_change`` gives way to a ``local_anomaly`` ranked
    after it that passes too and whose gap is within :data:`_LOCAL_MARGIN` of its own — external fields
    are the common case, so a body-fixed change must win clearly.  None when none passes.

    ``passes`` is asked in rank order up to the first that holds, then only about that ``local_anomaly``:
    with the null test every question costs the replicates' fits.  A ``local_anomaly`` ranked before
    the winner was asked already and did not pass.
    """
    order = list(ranked)
    for i, eff in enumerate(order):
        if not passes(eff):
            continue
        if (eff == "hard_iron_change" and "local_anomaly" in order[i + 1:] and passes("local_anomaly")
                and ranked[eff] >= ranked["local_anomaly"] * (1.0 - _LOCAL_MARGIN)):
            return "local_anomaly"
        return eff
    return None


def _why_not_tried(effect: str, in_last_round: bool, offered, has_temperature: bool, use_truth: bool,
                   settings: DiagnoseSettings) -> str:
    """Empty when the search tried ``effect`` in its last round, else why the recording could not."""
    if in_last_round:
        return ""
    if effect == "temperature_offset" and not has_temperature:
        return "the recording has no temperature channel"
    if effect == "gyro_bias" and use_truth:
        return "the orientation is the truth (use_truth): a gyro bias does not enter it"
    if effect in _LOCAL:
        frame = "world" if effect == "local_anomaly" else "device"
        return (f"no stretch where the residual ({frame} frame, 1-s mean) stands out above "
                f"{settings.anomaly_min_uT:g} µT and 4 σ")
    return "" if effect in offered else "not among the candidates of the settings"


def diagnose(
    t_mag,
    mag,
    t_gyro,
    gyro,
    t_accel,
    accel,
    *,
    truth: tuple[np.ndarray, np.ndarray] | None = None,
    use_truth: bool = False,
    temperature: tuple[np.ndarray, np.ndarray] | None = None,
    settings: DiagnoseSettings | None = None,
) -> Diagnosis:
    """Simulation vs measured: fit the baseline, find the missing effects one by one, refit.

    Parameters
    ----------
    t_mag, mag : ndarray (N,), (N, 3)
        Raw magnetometer, s and µT.
    t_gyro, gyro, t_accel, accel : ndarray
        Gyroscope (rad/s) and accelerometer (m/s²) with their times; they give the orientation.
    truth : (t, q_wxyz), optional
        True orientation; used only when ``use_truth`` (evaluation mode).
    use_truth : bool
        Predict along the true orientation instead of the gyro + accelerometer estimate.
    temperature : (t, T_degC), optional
        Sensor temperature; enables the ``temperature_offset`` candidate.
    settings : DiagnoseSettings

    Returns
    -------
    Diagnosis
    """
    settings = settings or DiagnoseSettings()
    t_mag = np.asarray(t_mag, float)
    # times relative to the first magnetometer stamp: a phone clock may read 10⁹ s (Unix time), where a
    # float64 resolves only 0.24 µs — too coarse for the finite differences of the time_offset fit
    t_origin = float(t_mag[0]) if len(t_mag) else 0.0
    gyro_pair = accel_pair = None
    if use_truth:
        if truth is None:
            raise ValueError("truth: use_truth=True needs the true orientation (t, q_wxyz)")
        track: OrientationTrack = track_from_truth(np.asarray(truth[0], float) - t_origin, truth[1])
        source = "truth"
    else:
        if gyro is None or accel is None:
            raise ValueError("gyro, accel: both are needed to estimate the orientation")
        gyro_pair = (np.asarray(t_gyro, float) - t_origin, np.asarray(gyro, float))
        accel_pair = (np.asarray(t_accel, float) - t_origin, np.asarray(accel, float))
        track = estimate_orientation(*gyro_pair, *accel_pair, settings=settings.orientation)
        source = "gyro+accel"
    temp = None
    if temperature is not None:
        temp = np.interp(t_mag, np.asarray(temperature[0], float), np.asarray(temperature[1], float))
    problem = make_problem(t_mag - t_origin, mag, track, temp, settings.anomaly_knot_s, t_origin=t_origin)
    n = problem.n

    base = fit_model(problem, (), None, settings.max_nfev)
    w = float(np.sqrt(np.mean(base.residual**2)) * np.sqrt(integrated_autocorr_time(base.residual)))
    problem = replace(problem, prior_weight=max(w, 1e-3))
    baseline = ModelSummary(BASELINE, gap(problem, base), estimates(problem, base, BASELINE), base, problem)
    white = float(np.sqrt(np.mean([robust_sigma(base.residual[:, k]) ** 2 for k in range(3)])))

    candidates = [c for c in settings.candidates if c != "temperature_offset" or temp is not None]
    if use_truth:
        candidates = [c for c in candidates if c != "gyro_bias"]
    # effective sample size from the residual of a "full" model whose world-frame field may vary everywhere
    # (anomaly knots over the whole recording) and whose offset may drift: what it leaves is the fast part
    # of the noise.  It is linear (one solve); the nonlinear effects are left out for speed — what they
    # would explain is fast only for time_offset, whose signature is strong enough anyway.
    full = [c for c in candidates if c in ("bias_drift", "temperature_offset")] + ["local_anomaly"]
    f_full = fit_model(problem, full, None, settings.max_nfev)
    tau_int = integrated_autocorr_time(f_full.residual)
    n_eff = n / tau_int

    current, cur_problem, added = base, problem, []
    notes: dict[str, dict] = {}
    rounds: list[tuple[Candidate, ...]] = []
    for rnd in range(settings.max_rounds):
        tried = []
        cur_gap = gap(cur_problem, current)
        cur_excess = above_white(cur_gap, white)
        for eff in candidates:
            if eff in added or (eff in _LOCAL and any(a in _LOCAL for a in added)):
                continue
            fitted = _candidate(eff, cur_problem, current, added, settings, gyro_pair, accel_pair)
            if fitted is None:
                continue
            p, f = fitted
            g = gap(p, f)
            s = _score(current, f, n_eff)
            shrinks = above_white(g, white) < (1.0 - settings.min_gap_reduction) * cur_excess
            rules = bool(s > settings.score_threshold and shrinks)
            tried.append((eff, g, s, estimates(p, f, [eff]).get(eff, {}), rules, f, p))
        winner: str | None = None
        tests: dict[str, NullTest] = {}
        passing = {x[0]: (x[6], x[5], x[1]) for x in sorted(tried, key=lambda x: -x[2]) if x[4]}
        if passing and settings.null.replicates > 0:
            winner, tests = _null_tests(cur_problem, current, tuple(added), passing, settings, rnd)
        elif passing:
            winner = _pick({eff: g for eff, (_, _, g) in passing.items()}, lambda eff: True)
        judged = []
        for eff, g, s, est, rules, f, p in tried:
            test = tests.get(eff)
            sig = rules and (settings.null.replicates == 0 or (test is not None and test.passed))
            judged.append((Candidate(eff, g, s, est, rnd + 1, sig, test), f, p))
        tried = judged
        rounds.append(tuple(c for c, _, _ in tried))
        if winner is None:
            break
        best = next(x for x in tried if x[0].effect == winner)
        added.append(best[0].effect)
        current, cur_problem = best[1], best[2]
        if best[0].effect in _LOCAL:  # the other name for a local disturbance: how close did it come?
            other = [c for c, _, _ in tried if c.effect in _LOCAL and c.effect != best[0].effect]
            if other:
                o = other[0]
                notes[best[0].effect] = {
                    "alternative": {"effect": o.effect, "gap": rounded(o.gap), "score": rounded(o.score, 2)},
                    "ambiguous": bool(abs(o.gap - best[0].gap) < best[0].gap * _LOCAL_MARGIN),
                }

    accel_bias = None
    if not use_truth:  # the accelerometer's part of the gyro bias, judged by the final model's gap with it
        def final_gap(tr: OrientationTrack) -> float:
            p = with_track(cur_problem, tr)
            others = tuple(e for e in added if e != "gyro_bias")
            nl = {k: v for k, v in current.nonlinear.items() if k != "gyro_bias"}
            return gap(p, fit_model(p, others, nl, 0))

        def raw_gap() -> float:
            return final_gap(estimate_orientation(*gyro_pair, *accel_pair, settings=replace(
                settings.orientation, bias_from_tilt=False)))

        accel_bias = accelerometer_bias(track.tilt_bias, final_gap(track), raw_gap, white,
                                        settings.min_gap_reduction, SMALLEST["gyro_bias"])
        if accel_bias.named and "gyro_bias" not in added:
            added.insert(0, "gyro_bias")  # named by the accelerometer, in the orientation from the start
    final_effects = (*BASELINE, *added)
    final_est = estimates(cur_problem, current, final_effects)
    for eff, note in notes.items():
        final_est[eff].update(note)
    final = ModelSummary(final_effects, gap(cur_problem, current), final_est, current, cur_problem)
    last = {c.effect for c in rounds[-1]} if rounds else set()
    why_not = {e: _why_not_tried(e, e in last, candidates, temp is not None, use_truth, settings)
               for e in settings.candidates}
    ident, motion = identifiability(cur_problem, current, tuple(added), why_not, n_eff,
                                    (settings.score_threshold, settings.min_gap_reduction), notes, white)
    return Diagnosis(
        baseline=baseline,
        candidates=rounds[0] if rounds else (),
        rounds=tuple(rounds),
        missing_effects=tuple(added),
        final=final,
        orientation_source=source,
        duration_s=float(problem.t[-1] - problem.t[0]),
        n_samples=len(problem.t),
        n_eff=float(n_eff),
        identifiability=ident,
        motion=motion,
        gyro_bias_from_accelerometer={} if accel_bias is None else accel_bias.to_dict(),
        rules={"score_threshold": settings.score_threshold, "min_gap_reduction": settings.min_gap_reduction,
               "white_noise_uT": rounded(white),
               "null_replicates": settings.null.replicates, "null_false_alarm": settings.null.false_alarm},
    )
