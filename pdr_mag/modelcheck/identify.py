"""What the recording's motion can reveal: the identifiability of each candidate effect, from the data.

A phone that only turns about one axis (a texting walk turns about the phone's up axis) shows the field
sweeping a cone in device axes: what scales or turns the field *along* that axis, or turns it *about* it,
leaves the same trace as the hard-iron offset or the unknown heading reference.  This module measures that
on the recording, effect by effect, against the model the search ended with.

Model
-----
For effect e with parameters θ_e, the Fisher information the magnetometer carries about θ_e once every
parameter of the current model is fitted along with it (the Schur complement)::

    F_e = w (J_eᵀ J_e − J_eᵀ N (NᵀN)⁻¹ Nᵀ J_e),      w = n_eff / RSS

``J_e = ∂m̂/∂θ_e`` at the fitted model (central differences for the nonlinear effects, the design columns
for the linear ones), ``N`` the Jacobian of the current model's parameters (``B_w``, hard iron, the
effects already named — or, for a named effect, the model without it) and ``w`` the weight of the
search's ΔBIC (:mod:`.select`: ``n_eff · ln(RSS_c/RSS_e) ≈ w ΔRSS``), so ``θᵀ F_e θ`` is the score an
effect θ would earn.  For ``gyro_bias`` the accelerometer's information (the drift of gravity in the gyro
frame, :class:`~pdr_mag.modelcheck.orientation.TiltBias`) is added: the two sensors see different axes.

With θ = s_e v (v a unit direction, ``s_e`` the smallest size worth naming, :data:`SMALLEST`), an effect
of that size along v changes the prediction, beyond what the model's other parameters take, by the mean
square ``q_v = s_e² vᵀ J_pᵀ J_p v / 3N`` (µT², ``J_p`` the projected Jacobian).  The direction is
*identifiable* when such an effect would pass the search's first two rules: its score
``n_eff q_v / gap² ≥ score_threshold + k_e ln n_eff`` (k_e: the effect's parameter count, its BIC
penalty) and its shrink of the gap above the white noise, ``q_v ≥ (1 − (1 − min_gap_reduction)²)
(gap² − σ_w²)``.  The directions are the eigenvectors of ``q`` (for ``gyro_bias`` the accelerometer's
information, which identifies a direction on its own when ``s_e² vᵀ I_acc v`` reaches the score rule,
is added in the same measure); its 1-σ is ``1/√(vᵀ F_e v)``.  A direction that is not identifiable is

* *not excited* when even its whole trace ``J v`` falls short of the score rule at the white noise
  (``n_eff s_e² |J v|² / 3N σ_w² <`` the rule): the motion leaves no trace of it;
* *taken* when the model's other parameters reproduce most (≥ half) of its trace: the parts that do,
  greedily, are named (e.g. the heading reference for a misalignment about the up axis);
* *masked* otherwise: its own trace is real but too small against the residual left unexplained (the
  orientation estimate's error, or an effect still missing).

Within the directions that are not identifiable the eigenvectors are arbitrary mixes, so they are
reported in a basis whose first vector is the phone's up axis when it lies among them.

Local effects (windows in time) and effects without data (temperature) are judged by their own
rules (:func:`identifiability`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from pdr_mag.modelcheck.fit import (
    BASELINE,
    FitResult,
    Problem,
    design,
    linear_layout,
    linear_ridge,
    measurement_times,
    sample_matrices,
)
from pdr_mag.modelcheck.null import above_white

#: The smallest size of each effect worth naming (the weak strengths of ``benchmarks/diagnose.py``'s
#: suites, which the search names on a calibration + walk recording): time_offset 15 ms, a misalignment of
#: 2°, a soft-iron distortion with axis ratio e^0.08 ≈ 1.08 (E in ``S⁻¹ = expm(E)``), a gyro bias of 0.3 °/s,
#: a drift of 1.2 µT/min and 0.2 µT/°C — in the fit's internal units.
SMALLEST = {"time_offset": 0.015, "mag_imu_misalignment": np.radians(2.0), "soft_iron": 0.04,
            "gyro_bias": 0.005, "bias_drift": 1.2, "temperature_offset": 0.2}
#: The smallest sizes in words.
_SIZE_TEXT = {"time_offset": "15 ms", "mag_imu_misalignment": "2°", "soft_iron": "an axis ratio of 1.08",
              "gyro_bias": "0.3 °/s", "bias_drift": "1.2 µT/min", "temperature_offset": "0.2 µT/°C"}
#: JSON unit of each effect's 1-σ and the factor from the internal unit.
_UNIT = {"time_offset": ("s", 1.0), "mag_imu_misalignment": ("deg", np.degrees(1.0)), "soft_iron": ("1", 1.0),
         "gyro_bias": ("rad/s", 1.0), "bias_drift": ("uT/min", 1.0), "temperature_offset": ("uT/degC", 1.0)}
_NL_SIZE = {"time_offset": 1, "gyro_bias": 3, "mag_imu_misalignment": 3, "soft_iron": 5}
_LOCAL = ("local_anomaly", "hard_iron_change")
_PART = {"field_w": "the heading reference (the field's direction, fitted: the orientation has no heading)",
         "hard_iron": "the hard-iron offset"}


@dataclass(frozen=True)
class Direction:
    """One direction of an effect's parameters: unit ``vector`` (device axes for the 3-vector effects;
    (E_xx, E_yy, E_xy, E_xz, E_yz) for soft_iron), its 1-σ in the effect's JSON unit, whether the
    recording identifies it, what it is, the rms trace an effect of the smallest size along it leaves
    beyond the model's other parameters (µT) and, when not identifiable, why: ``"not_excited"``,
    ``"taken"`` (by ``taken_by``) or ``"masked"`` (module docstring)."""

    vector: tuple[float, ...]
    std: float
    identifiable: bool
    text: str
    trace_uT: float
    why: str = ""
    taken_by: tuple[str, ...] = ()

    def to_dict(self) -> dict:
        return {"vector": [round(v, 3) for v in self.vector],
                "std": round(self.std, 6) if np.isfinite(self.std) else None,
                "identifiable": self.identifiable, "trace_uT": round(self.trace_uT, 4),
                "why": self.why or None, "taken_by": list(self.taken_by), "what": self.text}


@dataclass(frozen=True)
class Identifiability:
    """What the recording can tell of one effect.

    ``status``: ``named`` (a missing effect), ``not_significant`` (identifiable, and what it explains
    is not significant), ``partly_identifiable`` (so in the directions it identifies; not in the others),
    ``not_identifiable`` (no direction identifiable) or ``not_tried`` (the recording lacks what the
    candidate needs).  ``reason`` says why a direction is not identifiable, ``reveal`` which motion
    would identify it."""

    effect: str
    status: str
    reason: str = ""
    reveal: str = ""
    unit: str = ""
    directions: tuple[Direction, ...] = ()

    def to_dict(self) -> dict:
        return {"status": self.status, "reason": self.reason, "reveal": self.reveal, "unit": self.unit,
                "identifiable_directions": sum(d.identifiable for d in self.directions),
                "directions": [d.to_dict() for d in self.directions]}


# ---------------------------------------------------------------------------------------------- the motion


def motion_summary(problem: Problem, fit: FitResult) -> dict:
    """The motion as the magnetometer saw it: the phone's mean up axis and how far it tilted from it, the
    device axis the field swept least and by how much, the rms angular rate, the length."""
    up = problem.r_dw0[:, :, 2]
    mu = up.mean(axis=0)
    mu /= np.linalg.norm(mu)
    tilt = np.degrees(np.arccos(np.clip(up @ mu, -1.0, 1.0)))
    b = np.asarray(fit.linear["field_w"], dtype=float)
    h = sample_matrices(problem, fit.nonlinear) @ (b / np.linalg.norm(b))
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    lam, vec = np.linalg.eigh(np.cov(h.T))
    least = vec[:, 0] * np.sign(vec[np.argmax(np.abs(vec[:, 0])), 0])
    rate = angular_rate(problem.track.t, problem.track.quat)
    return {"up_axis_d": _round(mu), "tilt_rms_deg": round(float(np.sqrt(np.mean(tilt**2))), 2),
            "least_swept_axis_d": _round(least),
            "least_swept_deg": round(float(np.degrees(np.arcsin(min(1.0, np.sqrt(lam[0]))))), 2),
            "rate_rms_rad_per_s": round(float(np.sqrt(np.mean(rate**2))), 3),
            "duration_s": round(float(problem.t[-1] - problem.t[0]), 1)}


def angular_rate(t: np.ndarray, quat: np.ndarray) -> np.ndarray:
    """Rate (rad/s) between successive orientations ``quat`` (w-first) at times ``t`` (N − 1 values):
    the angle ``2 acos|q_i · q_{i+1}|`` over the step, blind to the sign of a quaternion."""
    dot = np.clip(np.abs(np.sum(quat[1:] * quat[:-1], axis=1)), 0.0, 1.0)
    return 2.0 * np.arccos(dot) / np.maximum(np.diff(t), 1e-9)


def _round(v) -> list[float]:
    return [round(float(x), 3) for x in np.ravel(v)]


# ---------------------------------------------------------------------------------------------- Jacobians


def _x(fit: FitResult, layout) -> np.ndarray:
    x = np.zeros(layout.size)
    for name, sl in layout.blocks.items():
        x[sl] = np.ravel(fit.linear[name]) if name in fit.linear else 0.0
    return x


def _nonlinear_jacobian(problem: Problem, nl: dict, name: str, layout, x: np.ndarray) -> np.ndarray:
    """``∂m̂/∂θ`` (3N, k) of a nonlinear effect at ``nl`` (zero when absent), linear parameters held."""
    base = np.asarray(nl.get(name, np.zeros(_NL_SIZE[name])), dtype=float)
    h = 1e-3 * SMALLEST[name]
    cols = []
    for j in range(len(base)):
        out = []
        for sign in (1.0, -1.0):
            p = base.copy()
            p[j] += sign * h
            q = {**nl, name: p}
            a = design(problem, sample_matrices(problem, q), measurement_times(problem, q), layout)
            out.append(a @ x)
        cols.append((out[0] - out[1]) / (2.0 * h))
    return np.column_stack(cols)


@dataclass(frozen=True)
class _Nuisance:
    """The current model's Jacobian N in groups (name → columns), with the factorised ``NᵀN``."""

    matrix: sp.csc_matrix
    groups: dict
    lu: object

    def project_out(self, j: np.ndarray) -> np.ndarray:
        """``J − N (NᵀN)⁻¹ NᵀJ``."""
        ntj = self.matrix.T @ j
        return j - self.matrix @ self.lu.solve(np.asarray(ntj).reshape(self.matrix.shape[1], -1))

    def share(self, s: np.ndarray, names) -> float:
        """Share of ``|s|²`` that the columns of the groups ``names`` together reproduce."""
        g = self.matrix[:, np.concatenate([np.arange(self.matrix.shape[1])[self.groups[n]] for n in names])]
        gtg = (g.T @ g).tocsc()
        gtg = gtg + sp.diags(1e-12 * max(float(gtg.diagonal().max()), 1e-300) * np.ones(gtg.shape[0]))
        c = splu(gtg.tocsc()).solve(np.asarray(g.T @ s))
        return float(s @ (g @ c)) / max(float(s @ s), 1e-300)

    def taken_by(self, s: np.ndarray, enough: float = 0.99) -> tuple[str, ...]:
        """The fewest groups that together reproduce ``enough`` of what the whole model reproduces of the
        trace ``s`` (greedily, the best single group first)."""
        target = enough * self.share(s, list(self.groups))
        chosen: list[str] = []
        left = list(self.groups)
        while left:
            best = max(left, key=lambda n: self.share(s, [*chosen, n]))
            chosen.append(best)
            left.remove(best)
            if self.share(s, chosen) >= target:
                break
        return tuple(chosen)


def _nuisance(problem: Problem, fit: FitResult, effects: tuple[str, ...]) -> _Nuisance:
    layout = linear_layout(problem, effects)
    nl = {k: v for k, v in fit.nonlinear.items() if k in effects}
    a = design(problem, sample_matrices(problem, nl), measurement_times(problem, nl), layout)
    cols, groups, at = [a], dict(layout.blocks), layout.size
    full_layout = linear_layout(problem, fit.effects)
    x = _x(fit, full_layout)
    for name in nl:
        j = _nonlinear_jacobian(problem, nl, name, full_layout, x)
        cols.append(sp.csr_matrix(j))
        groups[name] = slice(at, at + j.shape[1])
        at += j.shape[1]
    n = sp.hstack(cols).tocsc()
    ntn = (n.T @ n).tocsc()
    ridge = np.concatenate([linear_ridge(problem, layout, ntn.diagonal()[:layout.size]),
                            1e-9 * np.mean(ntn.diagonal()) * np.ones(at - layout.size)])
    return _Nuisance(n, groups, splu((ntn + sp.diags(ridge)).tocsc()))


def effect_jacobian(problem: Problem, fit: FitResult, effect: str) -> np.ndarray:
    """``∂m̂/∂θ_e`` (3N, k) at the fitted model (zero parameters when the effect is not in it)."""
    layout = linear_layout(problem, fit.effects)
    x = _x(fit, layout)
    if effect in _NL_SIZE:
        return _nonlinear_jacobian(problem, fit.nonlinear, effect, layout, x)
    lay = linear_layout(problem, (*fit.effects, effect))
    nl = fit.nonlinear
    a = design(problem, sample_matrices(problem, nl), measurement_times(problem, nl), lay)
    return a[:, lay.blocks[effect]].toarray()


# ---------------------------------------------------------------------------------------------- words


def _axis(v) -> str:
    return "(" + ", ".join(f"{x:.2f}" for x in np.ravel(v)) + ")"


def _relation(v: np.ndarray, motion: dict) -> str:
    c = abs(float(np.dot(v, motion["up_axis_d"])))
    return " (the phone's up axis)" if c > np.cos(np.radians(25.0)) else (
        " (across the up axis)" if c < np.cos(np.radians(65.0)) else "")


def _what(effect: str, v: np.ndarray, motion: dict) -> str:
    if effect == "time_offset":
        return "a lag of the magnetometer's clock"
    if effect == "soft_iron":
        w, vec = np.linalg.eigh(_e_matrix(v))
        a = vec[:, np.argmax(np.abs(w))]
        a = a * np.sign(a[np.argmax(np.abs(a))])
        return f"soft iron scaling device axis {_axis(a)}{_relation(a, motion)} against the others"
    a = v * np.sign(v[np.argmax(np.abs(v))])
    kind = {"mag_imu_misalignment": "a rotation of the magnetometer about", "gyro_bias": "a gyro bias about",
            "bias_drift": "an offset drift along", "temperature_offset": "a temperature coefficient along"}
    return f"{kind[effect]} device axis {_axis(a)}{_relation(a, motion)}"


def _e_matrix(e: np.ndarray) -> np.ndarray:
    exx, eyy, exy, exz, eyz = e
    return np.array([[exx, exy, exz], [exy, eyy, eyz], [exz, eyz, -exx - eyy]])


def _reveal(effect: str, motion: dict) -> str:
    w, spread = _axis(motion["least_swept_axis_d"]), motion["least_swept_deg"]
    if effect in ("mag_imu_misalignment", "soft_iron"):
        return (f"rotations about axes across device axis {w} by tens of degrees (a figure-8, or turning the "
                f"phone over): here the field's direction varied by only {spread}° along it")
    if effect == "gyro_bias":
        return (f"tilting the phone so that its up axis (here {_axis(motion['up_axis_d'])}, tilted by "
                f"{motion['tilt_rms_deg']}° rms) also points along the axes named")
    if effect == "time_offset":
        return f"faster turns (here {motion['rate_rms_rad_per_s']} rad/s rms)"
    if effect == "bias_drift":
        return f"a longer recording (here {motion['duration_s']} s)"
    return "a change of the sensor's temperature that does not follow time linearly"


def _why_text(d: Direction, effect: str, motion: dict) -> str:
    size = _SIZE_TEXT[effect]
    if d.why == "masked":
        excess = above_white(motion["gap_uT"], motion["white_noise_uT"])
        return (f"at {size} it leaves a trace of {d.trace_uT:.3f} µT rms beyond what the rest of the model "
                f"takes, too little against the residual left unexplained ({excess:.3f} µT above a white "
                f"noise of {motion['white_noise_uT']} µT)")
    if d.why == "not_excited":
        extra = {"time_offset": f", rms angular rate {motion['rate_rms_rad_per_s']} rad/s",
                 "bias_drift": f", the recording lasts {motion['duration_s']} s"}.get(effect, "")
        return (f"the motion does not excite it (at {size} it changes the field by {d.trace_uT:.3f} µT "
                f"rms{extra})")
    return "its trace is that of " + " and ".join(_PART.get(g, g) for g in d.taken_by)


# ---------------------------------------------------------------------------------------------- the verdict


def _fisher(problem: Problem, fit: FitResult, effect: str, nuis: _Nuisance, n_eff: float, rules: tuple,
            motion: dict) -> tuple[Direction, ...]:
    """The directions of one effect's parameters and what the recording tells of each (module docstring).
    ``rules``: the search's ``(score_threshold, min_gap_reduction)``."""
    score_threshold, min_gap_reduction = rules
    n3, gap2, white2 = fit.residual.size, fit.gap**2, motion["white_noise_uT"] ** 2
    j = effect_jacobian(problem, fit, effect)
    jp = nuis.project_out(j)
    s = SMALLEST[effect]
    thr = score_threshold + j.shape[1] * np.log(max(n_eff, 2.0))
    # mean square traces (µT² per sample) of the smallest effect, projected and whole
    q_proj, q_raw = s * s * (jp.T @ jp) / n3, s * s * (j.T @ j) / n3
    need = max(thr * gap2 / n_eff, (1.0 - (1.0 - min_gap_reduction) ** 2) * max(gap2 - white2, 0.0))
    fisher = (n_eff / max(fit.rss, 1e-300)) * (jp.T @ jp)
    acc = np.zeros_like(q_proj)
    if effect == "gyro_bias":
        fisher = fisher + problem.track.tilt_bias.information
        acc = s * s * problem.track.tilt_bias.information
    g = q_proj / max(need, 1e-300) + acc / thr
    lam, vec = np.linalg.eigh(0.5 * (g + g.T))
    ok = lam >= 1.0
    basis = [(vec[:, i], True) for i in np.flatnonzero(ok)]
    basis += [(v, False) for v in _open_basis(effect, vec[:, ~ok], motion)]
    out = []
    for v, ident in basis:
        fv = float(v @ fisher @ v)
        std = float(_UNIT[effect][1] / np.sqrt(fv)) if fv > 0 else float("inf")
        qp, qr = float(v @ q_proj @ v), float(v @ q_raw @ v)
        why, taken = "", ()
        if not ident:
            if n_eff * qr / max(white2, 1e-300) + float(v @ acc @ v) < thr:
                why = "not_excited"
            elif qp < 0.5 * qr:
                why, taken = "taken", nuis.taken_by(j @ v)
            else:
                why = "masked"
        trace = np.sqrt(qr if why == "not_excited" else qp)
        out.append(Direction(tuple(float(x) for x in v), std, ident, _what(effect, v, motion), float(trace),
                             why, taken))
    return tuple(sorted(out, key=lambda d: d.identifiable))


def identifiability(problem: Problem, fit: FitResult, added: tuple[str, ...], tried: dict[str, str],
                    n_eff: float, rules: tuple[float, float], local_notes: dict,
                    white: float) -> tuple[dict, dict]:
    """Per candidate effect, what this recording can tell of it (module docstring), and the motion.

    Parameters
    ----------
    problem, fit : the final model's problem and fit
    added : effects the search named, in order
    tried : every candidate → ``""`` when the search tried it in its last round, else why not (the
        recording lacks what it needs)
    n_eff : the search's effective sample count
    rules : the search's ``(score_threshold, min_gap_reduction)``
    local_notes : the named local effect's ``{"alternative", "ambiguous"}`` note, if any
    white : the recording's white noise, µT rms (:func:`~pdr_mag.modelcheck.null.robust_sigma`)

    Returns
    -------
    (dict effect → Identifiability, motion summary dict)
    """
    motion = motion_summary(problem, fit)
    motion.update(gap_uT=round(fit.gap, 3), white_noise_uT=round(white, 3))
    shared = _nuisance(problem, fit, (*BASELINE, *added))
    out: dict[str, Identifiability] = {}
    for e, why_not in tried.items():
        if e in _LOCAL:
            out[e] = _local(e, added, why_not, local_notes)
            continue
        if why_not and e not in added:
            out[e] = Identifiability(e, "not_tried", why_not)
            continue
        nuis = shared if e not in added else _nuisance(problem, fit, tuple(x for x in (*BASELINE, *added)
                                                                           if x != e))
        dirs = _fisher(problem, fit, e, nuis, n_eff, rules, motion)
        bad = [d for d in dirs if not d.identifiable]
        if e in added:  # named: found above the smallest size; what stays open is what the motion leaves
            bad = [d for d in bad if d.why != "masked"]
            status = "named"
        elif not bad:
            status = "not_significant"
        else:
            status = "not_identifiable" if len(bad) == len(dirs) else "partly_identifiable"
        reason = "; ".join(f"{d.text}: {_why_text(d, e, motion)}" for d in bad)
        reveal = _reveal(e, motion) if any(d.why != "masked" for d in bad) else ""
        out[e] = Identifiability(e, status, reason, reveal, _UNIT[e][0], dirs)
    return out, motion


def _open_basis(effect: str, space: np.ndarray, motion: dict) -> list[np.ndarray]:
    """An orthonormal basis of ``space`` (columns) whose first vector is the phone's up axis (for soft
    iron: the scaling along it) when that lies within 25° of the space."""
    if space.shape[1] == 0:
        return []
    mu = np.asarray(motion["up_axis_d"], dtype=float)
    if effect == "soft_iron":
        e = np.outer(mu, mu) - np.eye(3) / 3.0
        mu = np.array([e[0, 0], e[1, 1], e[0, 1], e[0, 2], e[1, 2]])
    elif effect == "time_offset":
        return [space[:, 0]]
    mu = mu / np.linalg.norm(mu)
    proj = space @ (space.T @ mu)
    if np.linalg.norm(proj) < np.cos(np.radians(25.0)):
        return list(space.T)
    first = proj / np.linalg.norm(proj)
    rest = space - np.outer(first, first @ space)
    u, sv, _ = np.linalg.svd(rest, full_matrices=False)
    return [first, *u[:, : space.shape[1] - 1].T]


def _local(e: str, added: tuple[str, ...], why_not: str, notes: dict) -> Identifiability:
    """``local_anomaly`` / ``hard_iron_change``: named, tried, not tried (no window), or the other name
    of a named local disturbance — not identifiable when the two fit within the search's margin."""
    if e in added:
        return Identifiability(e, "named")
    other = next((a for a in added if a in _LOCAL), None)
    if other is not None:
        note = notes.get(other, {})
        if note.get("ambiguous"):
            return Identifiability(
                e, "not_identifiable",
                f"inside the windows of {other} the phone turned too little to tell a field fixed in the "
                "world from an offset fixed to the phone (their gaps are within 5 %)",
                "turning the phone inside the disturbed stretch")
        return Identifiability(e, "not_significant", f"{other} explains the same windows better")
    if why_not:
        return Identifiability(e, "not_tried", why_not)
    return Identifiability(e, "not_significant")
