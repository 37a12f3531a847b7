"""Online refits: the candidate fits of the diversity buffer, their verdicts, and when one is taken into use.

Candidates (:func:`candidates`), on the buffer's raw samples ``m_i`` and up vectors ``u_i``:

* the gravity-aided fit (:mod:`pdr_mag.calibration.gravity`), always: it needs yaw turns only.  It keeps the
  shape of the calibration in force (:func:`gravity_fit_keeping_shape`): a magnet or a case moves the hard
  iron, not the sensor's scale and axes;
* when no fit of the whole buffer is accepted, the references F and I are known and nothing better than a
  first fit is in force (:func:`_consensus_wanted`), the consensus fit of
  :mod:`pdr_mag.calibration.consensus`: the gravity-aided fit of the samples that agree with the best of the
  offsets that time windows and pairs of samples give (a start next to steel leaves a buffer mostly of
  disturbed samples);
* [Liu2018]'s linear least-squares sphere fit (eqs. 7–16, :func:`pdr_mag.calibration.sphere.fit_sphere`) once
  the buffer's direction coverage about the gravity fit's offset reaches ``sphere_coverage``;
* the calibration core's full fit (:func:`pdr_mag.calibration.select.calibrate`: model by BIC, geometric
  ML; [Long2013]/[Zhong2017]/[Huang2018]) once the coverage reaches ``ellipsoid_coverage``, the buffer's
  coverage on the core's equal-area grid reaches ``ellipsoid_precheck_frac`` of
  ``AcceptanceSettings.min_coverage`` (a cheap gate that spares full fits on a sparse buffer; it is not the
  acceptance rule, which is the heading bound of :func:`pdr_mag.calibration.coverage.accept` and may pass fits
  the gate skips), and a figure-8 was seen (or nothing is calibrated yet).

Each is judged (:func:`judge`); the richest accepted one (full > sphere > gravity, then the smallest offset
σ) is the refit's result.  Whether it replaces the calibration in force is :func:`replaces`.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from pdr_mag.calibration.consensus import consensus_offset, with_consensus
from pdr_mag.calibration.coverage import AcceptanceSettings
from pdr_mag.calibration.coverage import accept as core_accept
from pdr_mag.calibration.coverage import coverage as core_coverage
from pdr_mag.calibration.diversity import direction_coverage
from pdr_mag.calibration.gravity import fit_model, gravity_aided_offset, soft_iron_offset_covariance
from pdr_mag.calibration.model import IDENTITY_SOFT_IRON, SHAPE_COVARIANCE, MagCalibration
from pdr_mag.calibration.online_settings import OnlineSettings
from pdr_mag.calibration.prior import is_prior
from pdr_mag.calibration.select import calibrate
from pdr_mag.calibration.sphere import fit_sphere
from pdr_mag.field import EARTH_STRENGTH_RANGE_UT, plausible_strength

#: An online fit's radius may differ from the reference strength (or, without one, from the Earth's range)
#: by this share: indoors the local field departs from the model by up to tens of per cent.
RADIUS_REL_TOL = 0.25

#: Preference among accepted refits: the full fit's methods (ellipsoid, ml, …) rank 2.
_RANK = {"gravity": 0, "sphere": 1}

#: χ²₃ at 99.9 %: two offsets further apart than this in their combined covariance contradict each other —
#: one of them was fitted on a field that was not the Earth's, which neither σ can tell.
CONTRADICTION_CHI2 = 16.27
#: … and the refit then replaces the fit in force only with at least this share of its independent samples
#: (:func:`contradicts_with_less_evidence`: "clearly less evidence" is less than half)
EVIDENCE_SHARE = 0.5


def candidates(
    m: np.ndarray,
    u: np.ndarray,
    current: MagCalibration | None,
    full_fit_allowed: bool,
    field_ref: float | None,
    sin_dip_ref: float | None,
    settings: OnlineSettings,
    times: np.ndarray | None = None,
) -> list[MagCalibration]:
    """Every refit of the buffer (raw ``m``, up ``u``, sample ``times``), judged; ``full_fit_allowed``: a
    figure-8 was seen or nothing is calibrated yet."""
    s = settings
    cands: list[MagCalibration] = []
    centre = current.offset_array if current is not None else None
    try:
        g = gravity_fit_keeping_shape(m, u, current, field_ref, sin_dip_ref, s)
        if times is not None:
            g = with_correlated_errors(g, times, s.field_corr_s)
        cands.append(g)
        centre = g.offset_array
    except ValueError:
        pass
    centred = m - (centre if centre is not None else m.mean(axis=0))
    cov = direction_coverage(centred)
    if cov >= s.sphere_coverage:
        try:
            cands.append(replace(fit_sphere(m), coverage=cov))
        except (ValueError, ArithmeticError):
            pass
    if full_fit_allowed:
        full = full_fit(m, centre, field_ref, s)
        if full is not None:
            cands.append(full)
    first = current is None or provisional(current, s, vague_prior=True)
    # the gravity verdict does not read its coverage: judged, the coverage set in the same copy
    judged = [
        judge(c, s, field_ref, first, coverage=cov if c.method == "gravity" else None, up=u) for c in cands
    ]
    if _consensus_wanted(judged, current, field_ref, sin_dip_ref, times, s):
        found = consensus_offset(m, u, times, current, field_ref, sin_dip_ref, s)
        if found is not None:
            mask, best_n = found
            try:
                g = gravity_fit_keeping_shape(m[mask], u[mask], current, field_ref, sin_dip_ref, s)
            except ValueError:
                return judged
            g = with_consensus(with_correlated_errors(g, times[mask], s.field_corr_s), mask, best_n)
            # its coverage: the inliers' directions about its own offset, not the polluted buffer's
            inl = direction_coverage(g.apply(m[mask]))
            judged.append(judge(g, s, field_ref, first, coverage=inl, up=u[mask]))
    return judged


def full_fit(m: np.ndarray, centre, field_ref: float | None, s: OnlineSettings) -> MagCalibration | None:
    """The calibration core's full fit of raw samples ``m`` (model by BIC, geometric ML), not judged; None
    when their directions about ``centre`` (the offset estimate; their mean without one) cover less than
    ``ellipsoid_coverage`` or the core's grid less than ``ellipsoid_precheck_frac`` of its minimum, or when
    the fit fails."""
    if len(m) == 0:
        return None
    centred = m - (centre if centre is not None else m.mean(axis=0))
    cov = direction_coverage(centred)
    if cov < s.ellipsoid_coverage or core_coverage(centred) < (
        s.ellipsoid_precheck_frac * AcceptanceSettings().min_coverage
    ):
        return None
    try:
        full = calibrate(m, method="auto", field=field_ref)
    except Exception:  # the core's fit failing on odd data is a failed refit, never a crash
        return None
    return replace(full, coverage=cov if not np.isfinite(full.coverage) else full.coverage)


def _consensus_wanted(judged, current, field_ref, sin_dip_ref, times, s: OnlineSettings) -> bool:
    """Whether to try the consensus fit: the references are known, no fit of the whole buffer is accepted,
    and nothing better than a first fit is in force — neither a calibration that judges the samples
    entering the buffer (its buffer is clean) nor a prior (the phone's, a store's: a consensus of a few
    seconds must not outvote it; the prior check refuses a wrong one)."""
    if times is None or field_ref is None or sin_dip_ref is None or any(c.accepted for c in judged):
        return False
    return current is None or (not is_prior(current) and provisional(current, s))


def provisional(cal: MagCalibration, s: OnlineSettings, vague_prior: bool = False) -> bool:
    """Whether ``cal`` holds only under the first calibration's looser bound: a fit with its offset σ above
    ``max_offset_std_uT``, what a later refit must reach.  Its strength errors reach that σ and more, so
    it cannot judge samples by the admission band; they enter as before any calibration, and the refit
    that fits them replaces it.  A prior (the phone's, a store's) is provisional for the refits' judgement
    (``vague_prior``) only when it knows less than a first fit would (σ above ``first_offset_std_uT``: a
    store's entry aged by days), so that a first fit may replace it."""
    std = cal.offset_std_uT
    finite = all(map(math.isfinite, std))
    if is_prior(cal):  # a prior without its σ knows nothing sure (prior.offset_sigma: unknown is infinite)
        sd = float(max(std)) if finite else math.inf
        return vague_prior and sd > max(s.first_offset_std_uT, s.max_offset_std_uT)
    if not finite:
        return False  # a calibration given without its σ (a file): as sure as the user says
    return float(max(std)) > s.max_offset_std_uT


def with_correlated_errors(cal: MagCalibration, times: np.ndarray, corr_s: float) -> MagCalibration:
    """The offset covariance of a fit whose residuals are correlated in time, scaled by ``N / N_eff``.

    The fit's covariance treats its N samples' errors as independent.  They are not: the local field
    (steel, the building's own field) and the strength and dip priors' errors are the same for samples taken
    within ``corr_s`` of each other, so the samples hold about ``N_eff = min(N, 1 + span / corr_s)``
    independent errors, ``span`` the time the buffer covers.  A buffer of a few seconds — the first fit of
    a walk — then claims what a few samples can tell, not what a dozen could.
    """
    n = len(times)
    if n < 2 or corr_s <= 0 or cal.covariance is None:
        return cal
    span = float(times.max() - times.min())
    k = n / min(n, 1.0 + span / corr_s)
    if k <= 1.0:
        return cal
    cov = np.asarray(cal.covariance, dtype=float) * k
    return replace(
        cal,
        covariance=tuple(map(tuple, cov.tolist())),
        offset_std_uT=tuple(np.sqrt(np.maximum(np.diag(cov)[:3], 0.0)).tolist()),
        extra={**cal.extra, "correlation_inflation": k},
    )


def best(judged: list[MagCalibration]) -> MagCalibration | None:
    """The richest accepted refit (full > sphere > gravity), then the one with the smallest offset σ."""
    good = [c for c in judged if c.accepted]
    if not good:
        return None
    return max(good, key=lambda c: (_RANK.get(c.method, 2), -float(max(c.offset_std_uT))))  # finite σ


def gravity_fit_keeping_shape(
    m: np.ndarray,
    u: np.ndarray,
    current: MagCalibration | None,
    field_ref: float | None,
    sin_dip_ref: float | None,
    settings: OnlineSettings,
) -> MagCalibration:
    """Gravity-aided offset fit keeping the soft iron and ``mag_to_imu`` of ``current``.

    With ``M = R·A`` (R = mag_to_imu or I, A = soft iron), ``y = M m`` is the field in the device frame up
    to a constant ``c = M b``; the fit on ``(y, u)`` gives ``c``, hence ``b = M⁻¹ c`` and its covariance
    ``M⁻¹ Σ_c M⁻ᵀ``.
    """
    s = settings
    # an offset-only calibration (the identity soft iron of from_arrays, no mag_to_imu) has no shape to keep
    plain = current is None or (current.soft_iron is IDENTITY_SOFT_IRON and current.mag_to_imu is None)
    mm = None if plain else current.matrix
    shaped = not plain and not is_identity(mm.tolist(), 1e-12)
    sin_dip = sin_dip_ref if field_ref is not None else None
    g = gravity_aided_offset(
        m @ mm.T if shaped else m, u, field_ref, sin_dip, s.sigma_strength_uT, s.sigma_tilt_deg,
        prior_strength_std_uT=s.prior_strength_std_uT, prior_dip_std_deg=s.prior_dip_std_deg,
    )  # fmt: skip
    # no shape known, and no sure fit of the walk's own in force yet: the soft iron the fit cannot see
    first = current is None or is_prior(current) or provisional(current, s)
    if not shaped and first and s.soft_iron_std > 0:
        model = fit_model(field_ref, sin_dip, s.sigma_strength_uT, s.sigma_tilt_deg, s.prior_strength_std_uT,
                          s.prior_dip_std_deg)  # fmt: skip
        shape_cov = soft_iron_offset_covariance(m, u, g, model, s.soft_iron_std)
        g = replace(g, extra={**g.extra, SHAPE_COVARIANCE: shape_cov.tolist()})
    if not shaped:
        return g
    a = current.soft_iron_array
    mi = np.linalg.inv(mm)
    cov_b = mi @ np.asarray(g.covariance, dtype=float) @ mi.T
    return MagCalibration.from_arrays(
        mi @ g.offset_array,
        a,
        field_uT=g.field_uT,
        method="gravity",
        residual_rms_uT=g.residual_rms_uT,
        offset_std_uT=np.sqrt(np.maximum(np.diag(cov_b), 0)),
        n_samples=g.n_samples,
        covariance=cov_b,
        mag_to_imu=current.mag_to_imu,
        extra={**g.extra, "shape_from": current.method},
    )


def judge(
    cal: MagCalibration,
    settings: OnlineSettings,
    field_ref: float | None,
    first: bool = False,
    coverage: float | None = None,
    up: np.ndarray | None = None,
) -> MagCalibration:
    """Acceptance verdict for an online refit (returns a copy with ``accepted``/``reasons`` set).

    The calibration core's rules (:func:`pdr_mag.calibration.coverage.accept` with its default settings and
    ``field_ref`` as the reference strength) are applied to every refit but the gravity-aided one, whose
    geometry they do not describe: enough samples, a finite radius and a positive-definite soft iron, a
    residual RMS within the larger of a share of the field and a magnetometer's noise, a heading error that
    the fit's uncertainty allows within the tolerance, a plausible offset, and, where the samples determine
    them, a plausible soft-iron eigenvalue spread and a radius near the reference (coverage only explains a
    heading refusal).  The online rules below are applied to every refit: offset σ below
    ``max_offset_std_uT`` (for the very first calibration, ``first_offset_std_uT`` when larger), a finite
    radius, residual RMS relative to F, offset magnitude, radius within :data:`RADIUS_REL_TOL` of the
    reference strength (without one, of the Earth's range, 22–67 µT: no Earth field has 14 µT); the
    residual and the radius are named once, by the core's rules when they named them (theirs are tighter).
    ``coverage`` given: the copy also gets it (for the gravity-aided refit, whose rules do not read it).

    Without a reference field (no place known) a gravity-aided fit estimates F and the dip itself, and from
    yaw turns alone (a phone held flat) the offset along the device's up is not determined: F, the dip and
    that component trade against each other.  A heading needs only the offset across up, so a first such
    fit is judged by the σ its offset has across the up vector of any of the buffer's poses
    (:func:`horizontal_std`, ``up`` the buffer's up vectors) and, accepted so, marked ``horizontal_only``
    in its ``extra``: its radius and dip are not the place's (they traded against that component), so
    neither the detectors nor the next fits take them as references
    (:meth:`pdr_mag.fusion.FusionCore.use_calibration`, :attr:`.online.OnlineCalibrator.field_ref`); its
    covariance goes to the fusion as it is, whose calibration floor ``g Σ_b gᵀ`` counts the undetermined part
    at every pose the device takes.
    """
    reasons: list[str] = []
    if cal.method != "gravity":
        reasons += list(core_accept(cal, field=field_ref).reasons)
    # a subject the core's rules named already (their bounds are the tighter) is not named twice
    named = {subject for subject in ("residual RMS", "radius") if any(r.startswith(subject) for r in reasons)}
    f = cal.field_uT
    s = settings
    bound = s.max_offset_std_uT if not first else max(s.first_offset_std_uT, s.max_offset_std_uT)
    across_up = first and field_ref is None and cal.method == "gravity" and up is not None
    if across_up and cal.offset_covariance is not None and np.all(np.isfinite(cal.offset_covariance)):
        std_h = horizontal_std(cal.offset_covariance, up)
        if std_h > bound:
            reasons.append(f"offset σ across up {std_h:.2f} µT above {bound:g} µT")
        elif max(cal.offset_std_uT) > bound:
            cal = replace(cal, extra={**cal.extra, "horizontal_only": True})
    elif not all(map(math.isfinite, cal.offset_std_uT)) or max(cal.offset_std_uT) > bound:
        std = np.asarray(cal.offset_std_uT, dtype=float)
        reasons.append(f"offset σ {np.nanmax(std):.2f} µT above {bound:g} µT")
    if not np.isfinite(f) or f <= 0:
        reasons.append("no finite field radius")
    elif cal.residual_rms_uT > s.max_rms_frac * f and "residual RMS" not in named:
        reasons.append(f"residual RMS {cal.residual_rms_uT:.2f} µT above {s.max_rms_frac:.0%} of F")
    if np.linalg.norm(cal.offset) > s.max_offset_uT:
        reasons.append(f"offset {np.linalg.norm(cal.offset):.0f} µT implausible")
    radius_open = "radius" not in named and np.isfinite(f)
    if radius_open and field_ref is not None and abs(f / field_ref - 1) > RADIUS_REL_TOL:
        reasons.append(f"radius {f:.1f} µT far from the reference {field_ref:.1f} µT")
    elif radius_open and field_ref is None and cal.method == "gravity" \
            and not plausible_strength(f, None, RADIUS_REL_TOL):  # fmt: skip
        # (the core's rules, applied to every other refit above, hold its radius to the Earth's range)
        lo, hi = EARTH_STRENGTH_RANGE_UT
        reasons.append(f"radius {f:.1f} µT: the Earth's field is {lo:g}–{hi:g} µT everywhere "
                       f"(± {RADIUS_REL_TOL:.0%} indoors)")
    if coverage is not None:
        return replace(cal, coverage=coverage, accepted=not reasons, reasons=tuple(reasons))
    return cal.with_acceptance(not reasons, reasons)


def horizontal_only(cal: MagCalibration | None) -> bool:
    """Whether ``cal`` is a fit judged by its offset across up alone (:func:`judge`, no place known): its
    radius and dip traded against its undetermined offset along up and are no reference."""
    return cal is not None and bool(cal.extra.get("horizontal_only"))


def horizontal_std(cov: np.ndarray, up: np.ndarray) -> float:
    """The largest σ (µT) of an offset error of covariance ``cov`` (device frame) across the up vector of
    any of the poses ``up`` (N × 3, unit): ``max_i √λ_max(P_i C P_i)``, ``P_i = I − u_i u_iᵀ`` — what a
    heading reads of the offset's error at those poses (its part along up leaves the horizontal field)."""
    u = np.asarray(up, dtype=float).reshape(-1, 3)
    u = u[np.all(np.isfinite(u), axis=1)]
    if not len(u):
        return math.inf
    eye = np.eye(3)
    proj = eye[None, :, :] - u[:, :, None] * u[:, None, :]
    return float(np.sqrt(max(np.linalg.eigvalsh(proj @ cov @ proj).max(), 0.0)))


def replaces(new: MagCalibration, old: MagCalibration | None, provided: bool, m: np.ndarray) -> bool:
    """Whether an accepted refit replaces the calibration in force (outside a recalibration): it may stand
    for the device (:func:`may_stand_for`) and it is not noise — the offset must move by 2 σ (σ at least
    0.2 µT) or its σ shrink by 20 %; an upgrade to a soft-iron shape passes that rule.  The filter changes
    its calibration only for a fit that says something new: each change turns the heading."""
    if old is None:
        return True
    if not may_stand_for(new, old, provided, m):
        return False
    shift = np.linalg.norm(new.offset_array - old.offset_array)
    std_new = float(max(new.offset_std_uT))  # finite: an accepted refit
    std_old = float(max(old.offset_std_uT)) if all(map(math.isfinite, old.offset_std_uT)) else np.inf
    return _upgrade(new, old) or not (shift < 2 * max(std_new, 0.2) and std_new > 0.8 * std_old)


def may_stand_for(new: MagCalibration, old: MagCalibration, provided: bool, m: np.ndarray) -> bool:
    """Whether an accepted refit ``new`` may stand for the device in place of the calibration in force
    ``old`` — every rule of :func:`replaces` but the one against noise.

    Never a soft-iron shape by an offset-only fit, nor a calibration given by the user by a gravity or
    sphere fit, nor a fit that contradicts an online fit on clearly less evidence
    (:func:`contradicts_with_less_evidence`); not when the residual got worse (``> 1.5 · old + 0.3`` µT:
    disturbed samples in the buffer).  The old calibration's residual is the larger of its own and the
    spread (:func:`robust_spread`) of the strength it gives ``m``, the buffer's raw samples the refit
    fitted — a calibration fitted on a few samples and wrong by tens of µT explains the buffer worse than the
    refit that replaces it, whatever its own small residual said, while one sample of a disturbance in the
    buffer makes no calibration look bad (the spread is computed only when the old residual alone would
    refuse the refit).
    """
    if state_of(old) == "ellipsoid" and state_of(new) == "offset":
        return False
    if provided and new.method in ("gravity", "sphere"):
        return False
    if contradicts_with_less_evidence(new, old):
        return False
    rms_old = old.residual_rms_uT if np.isfinite(old.residual_rms_uT) else np.inf
    if not _upgrade(new, old) and new.residual_rms_uT > 1.5 * rms_old + 0.3:
        f = np.linalg.norm(old.apply(m), axis=1)
        if new.residual_rms_uT > 1.5 * robust_spread(f) + 0.3:
            return False
    return True


def _upgrade(new: MagCalibration, old: MagCalibration) -> bool:
    """A soft-iron shape where an offset-only calibration was in force."""
    return state_of(new) == "ellipsoid" and state_of(old) != "ellipsoid"


def robust_spread(x: np.ndarray) -> float:
    """The spread of ``x`` as a Gaussian's σ, from its median absolute deviation (``1.4826 · MAD``): a few
    samples of a disturbance in the buffer do not make it large, a calibration wrong for every sample
    does."""
    return 1.4826 * float(np.median(np.abs(x - np.median(x))))


def independent_samples(cal: MagCalibration) -> float:
    """``N_eff`` of a gravity-aided fit: its samples over the inflation :func:`with_correlated_errors` gave
    its covariance (errors correlated within ``field_corr_s``), its sample count when none was needed."""
    return cal.n_samples / max(float(cal.extra.get("correlation_inflation", 1.0)), 1.0)


def contradicts_with_less_evidence(new: MagCalibration, old: MagCalibration) -> bool:
    """Whether an online refit ``new`` contradicts the online fit ``old`` in force (their offsets
    :data:`CONTRADICTION_CHI2` apart in ``Σ_old + Σ_new``) on clearly less evidence: fewer than half its
    independent samples (:func:`independent_samples`).  Two offsets that far apart cannot both be the
    device's: one was fitted where the field was not the Earth's — a disturbance, which is local: a few
    seconds of samples that happen to have the reference strength and dip (a consensus from one pass by
    steel), or a first fit made next to it.  Neither σ can tell which (each is computed as if the field were
    the Earth's); a much longer time base can, as the Earth's field is the one that holds everywhere.  With
    comparable evidence the usual rules decide (a moved offset is the stale test's to find).  Applied between
    gravity-aided fits (a consensus is one), whose independent samples are counted alike — a full fit's
    covariance is not scaled for correlated errors, so its sample count is not comparable — and not to a
    prior (the phone's, a store's: :meth:`pdr_mag.calibration.online.OnlineCalibrator._check_prior` judges
    those) or without both covariances."""
    if is_prior(old) or not new.method == old.method == "gravity":
        return False
    if independent_samples(new) >= EVIDENCE_SHARE * independent_samples(old):
        return False  # (the evidence first: most refits rest on as much as the fit they would replace)
    c_old, c_new = old.offset_covariance, new.offset_covariance
    if c_old is None or c_new is None:
        return False
    d = new.offset_array - old.offset_array
    try:
        return float(d @ np.linalg.solve(c_old + c_new, d)) > CONTRADICTION_CHI2
    except np.linalg.LinAlgError:
        return False


def with_dip(cal: MagCalibration, m: np.ndarray, u: np.ndarray) -> MagCalibration:
    """A sphere or full refit taken into use gets ``extra["sin_dip"]``: the median of ``−m̂_cal · u`` over the
    samples it was fitted on (a gravity fit has its own)."""
    if cal.method == "gravity":
        return cal
    return replace(cal, extra={**cal.extra, "sin_dip": median_sin_dip(cal.apply(m), u)})


def median_sin_dip(m_cal: np.ndarray, u: np.ndarray) -> float:
    """The median of ``−m̂_cal · u``: sin of the dip of calibrated fields ``m_cal`` (N, 3) against the up
    vectors ``u`` (N, 3)."""
    nm = np.linalg.norm(m_cal, axis=1)
    return float(np.median(-np.einsum("ij,ij->i", m_cal, u) / np.maximum(nm, 1e-9)))


def state_of(cal: MagCalibration) -> str:
    """``"offset"`` for an identity soft iron, else ``"ellipsoid"``."""
    if cal.soft_iron is IDENTITY_SOFT_IRON:
        return "offset"  # the identity of from_arrays(soft_iron=None)
    return "offset" if is_identity(cal.soft_iron, 1e-9) else "ellipsoid"


def is_identity(a, atol: float) -> bool:
    """``np.allclose(a, np.eye(3), atol=atol)`` for a 3×3 nested sequence, without numpy's overhead."""
    for i in range(3):
        for j in range(3):
            e = 1.0 if i == j else 0.0
            if not abs(float(a[i][j]) - e) <= atol + 1e-5 * e:
                return False
    return True


def summary(cal: MagCalibration) -> dict:
    """The figures of a calibration for an event's data (with the consensus fit's inlier count and share,
    :mod:`pdr_mag.calibration.consensus`, when it is one; ``figure8``: a full fit of an unasked figure-8's
    recent samples, :meth:`pdr_mag.calibration.online.OnlineCalibrator._figure8_fit`; ``horizontal_only``: a
    fit without a place judged by its offset across up, :func:`judge`)."""
    return {
        "method": cal.method,
        "offset_uT": [round(float(v), 3) for v in cal.offset],
        "offset_std_uT": [round(float(v), 3) if np.isfinite(v) else None for v in cal.offset_std_uT],
        "field_uT": round(float(cal.field_uT), 3) if np.isfinite(cal.field_uT) else None,
        "residual_rms_uT": round(float(cal.residual_rms_uT), 3) if np.isfinite(cal.residual_rms_uT) else None,
        "coverage": round(float(cal.coverage), 3) if np.isfinite(cal.coverage) else None,
        "n_samples": int(cal.n_samples),
        **({"consensus": {k: cal.extra["consensus"][k] for k in ("inliers", "share")}}
           if "consensus" in cal.extra else {}),
        **({"figure8": True} if cal.extra.get("figure8") else {}),
        **({"horizontal_only": True} if horizontal_only(cal) else {}),
    }
