"""Fit the magnetometer model along an estimated orientation: baseline plus any set of candidate effects.

The prediction is the one of :mod:`pdr_mag.sim.sensor_model` (same symbols)::

    m_i = S⁻¹ Mᵀ R_dw(t_i − Δt) Rz(ψ_i) (B_w + ΔB(t_i − Δt)) + b + d (t_i − t_ref)/60 + c (T_i − T_ref)

with ``R_dw`` the gyro + accelerometer orientation (:mod:`.orientation`, heading reference arbitrary),
``B_w`` the field in that frame (fitted, so the heading reference comes from the fit itself), ``b`` the
hard-iron offset at ``t_ref``, and the candidate effects:

=========================  ==========================================================  ===============
effect                     parameters                                                  kind
=========================  ==========================================================  ===============
``soft_iron``              ``S⁻¹ = expm(E)``, E symmetric, trace-free (5; the scale    nonlinear
                           trades with ``|B_w|``)
``time_offset``            Δt, s (1)                                                   nonlinear
``mag_imu_misalignment``   ``M = exp([μ]×)``, μ rotation vector (3)                    nonlinear
``gyro_bias``              heading drift ``ψ_i = δ·∫up_d dt`` of a bias δ left in      nonlinear
                           the gyro (3; first order, then replayed, see below)
``bias_drift``             d, µT/min (3)                                               linear
``local_anomaly``          ΔB(t): world-frame field, piecewise linear in time with     linear
                           knots every ``anomaly_knot_s`` (3 per knot; time stands
                           in for position, which a recording does not give)
``temperature_offset``     c, µT/°C (3), when the recording has a temperature channel  linear
``hard_iron_change``       Δb(t): a *body-fixed* offset change (a magnet on the phone,  linear
                           a magnetised part), piecewise linear in time, confined to
                           windows like ``local_anomaly`` (3 per knot)
=========================  ==========================================================  ===============

The linear parameters are solved exactly for given nonlinear ones (variable projection: a sparse normal
equation per evaluation) and the nonlinear ones by trust-region least squares on the projected residual.
The noise is white Gaussian with σ estimated from the residual (profile likelihood).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import scipy.sparse as sp
from scipy.optimize import least_squares
from scipy.sparse.linalg import splu

from pdr_mag.conventions import quat_slerp, rotvec_to_matrix
from pdr_mag.modelcheck.orientation import OrientationTrack

#: Effects every model has ([Liu2018]'s sphere: hard-iron offset and white noise).
BASELINE = ("hard_iron", "noise")
#: Candidate effects, in the order they are tried.
CANDIDATES = (
    "time_offset",
    "mag_imu_misalignment",
    "soft_iron",
    "bias_drift",
    "gyro_bias",
    "local_anomaly",
    "hard_iron_change",
    "temperature_offset",
)
_NONLINEAR = {"time_offset": 1, "gyro_bias": 3, "mag_imu_misalignment": 3, "soft_iron": 5}
_NL_ORDER = ("time_offset", "gyro_bias", "mag_imu_misalignment", "soft_iron")
_NL_SCALE = {"time_offset": 0.01, "gyro_bias": 0.005, "mag_imu_misalignment": 0.01, "soft_iron": 0.01}
#: Weak Gaussian priors (σ, internal units) on the nonlinear parameters: they keep directions the motion
#: does not observe (e.g. gyro bias about a horizontal axis in a level walk) at zero, and cost < 1 µT².
_NL_PRIOR = {"time_offset": 1.0, "gyro_bias": 0.05, "mag_imu_misalignment": 0.1, "soft_iron": 0.2}
_NL_BOUND = {"time_offset": 0.5, "gyro_bias": 0.5, "mag_imu_misalignment": 0.5, "soft_iron": 0.6}


@dataclass(frozen=True)
class Problem:
    """The data of one fit: magnetometer samples and the orientation track they are predicted along.

    Attributes
    ----------
    t, mag : ndarray (N,), (N, 3)
        Magnetometer stamps (s) and raw samples (µT).
    track : OrientationTrack
        Orientation (IMU clock) and ``∫up_d dt``.
    t_ref : float
        Reference time of the hard-iron offset and of ``bias_drift``, s.
    temperature : ndarray (N,) or None
        Sensor temperature at the magnetometer stamps, °C.
    temp_ref : float
        Reference temperature, °C.
    knots : ndarray (K,)
        Knot times of the ``local_anomaly`` field, s.
    knot_free : ndarray (K,) of bool
        Knots whose value is fitted; the others are held at zero, so the anomaly is confined to the
        windows :func:`anomaly_support` found (it is *local*).
    offset_knots, offset_knot_free : ndarray
        The same for ``hard_iron_change`` (device frame).
    t_origin : float
        The recording's clock at time zero of the problem, s: every time above is relative to it (the
        estimates report times on the recording's clock).
    prior_weight : float
        Weight of the priors on the nonlinear parameters, µT: the residual's σ × √τ_int, so that a prior
        counts as much against correlated residuals as it should against independent ones.
    anomaly_prior_uT : float
        Prior σ of a knot of the anomaly field (a weak ridge that fixes the split between ``B_w`` and the
        anomaly), µT.
    """

    t: np.ndarray
    mag: np.ndarray
    track: OrientationTrack
    t_ref: float
    temperature: np.ndarray | None = None
    temp_ref: float = 0.0
    knots: np.ndarray = field(default_factory=lambda: np.zeros(0))
    knot_free: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    offset_knots: np.ndarray = field(default_factory=lambda: np.zeros(0))
    offset_knot_free: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    anomaly_prior_uT: float = 100.0
    prior_weight: float = 1.0
    r_dw0: np.ndarray | None = None
    t_origin: float = 0.0

    @property
    def n(self) -> int:
        return 3 * len(self.t)


def make_problem(t, mag, track: OrientationTrack, temperature=None, anomaly_knot_s: float = 1.0,
                 t_origin: float = 0.0) -> Problem:
    """A :class:`Problem` on the samples inside the track's time span (``t`` and the track's times
    relative to ``t_origin``)."""
    t = np.asarray(t, dtype=float)
    m = np.asarray(mag, dtype=float)
    keep = (t >= track.t[0]) & (t <= track.t[-1])
    t, m = t[keep], m[keep]
    if len(t) < 20:
        raise ValueError(f"mag: need at least 20 samples inside the gyro's time span, got {len(t)}")
    temp = None
    temp_ref = 0.0
    if temperature is not None:
        temp = np.asarray(temperature, dtype=float)[keep]
        temp_ref = float(np.mean(temp))
    span = t[-1] - t[0]
    nk = max(2, int(np.ceil(span / anomaly_knot_s)) + 1)
    knots = np.linspace(t[0], t[-1], nk)
    prob = Problem(t=t, mag=m, track=track, t_ref=float(np.mean(t)), temperature=temp, temp_ref=temp_ref,
                   knots=knots, knot_free=np.ones(len(knots), dtype=bool), t_origin=float(t_origin))
    return with_track(prob, track)


def with_track(problem: Problem, track: OrientationTrack) -> Problem:
    """The problem along another orientation track (caches ``R_dw`` at the stamps)."""
    q = quat_slerp(track.t, track.quat, problem.t)
    return replace(problem, track=track, r_dw0=np.swapaxes(_quat_to_matrix(q), 1, 2))


def soft_iron_distortion(e: np.ndarray) -> np.ndarray:
    """``S⁻¹ = expm(E)`` from the 5 parameters (E_xx, E_yy, E_xy, E_xz, E_yz), E_zz = −E_xx − E_yy.

    E symmetric and trace-free, so ``S⁻¹`` is symmetric positive definite with determinant 1 (the scale
    of the distortion trades with ``|B_w|`` and is not fitted).
    """
    exx, eyy, exy, exz, eyz = e
    m = np.array([[exx, exy, exz], [exy, eyy, eyz], [exz, eyz, -exx - eyy]])
    w, v = np.linalg.eigh(m)
    return (v * np.exp(w)) @ v.T


def _quat_to_matrix(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], axis=-1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], axis=-1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=-1),
        ],
        axis=-2,
    )


def split_nonlinear(effects, p: np.ndarray) -> dict[str, np.ndarray]:
    """Nonlinear parameter vector → per-effect arrays (in :data:`_NL_ORDER`)."""
    out, i = {}, 0
    for name in _NL_ORDER:
        if name in effects:
            out[name] = np.asarray(p[i : i + _NONLINEAR[name]], dtype=float)
            i += _NONLINEAR[name]
    return out


def sample_matrices(problem: Problem, nl: dict[str, np.ndarray]) -> np.ndarray:
    """Per-sample maps ``M_i = S⁻¹ Mᵀ R_dw(t_i − Δt) Rz(ψ_i)`` (N, 3, 3) from world field to raw mag."""
    tau = measurement_times(problem, nl)
    if "time_offset" not in nl and problem.r_dw0 is not None:
        r_dw = problem.r_dw0
    else:
        q = quat_slerp(problem.track.t, problem.track.quat, tau)
        r_dw = np.swapaxes(_quat_to_matrix(q), 1, 2)
    if "gyro_bias" in nl:
        psi = problem.track.up_integral(tau) @ nl["gyro_bias"]
        c, s = np.cos(psi), np.sin(psi)
        rz = np.zeros((len(psi), 3, 3))
        rz[:, 0, 0], rz[:, 0, 1], rz[:, 1, 0], rz[:, 1, 1], rz[:, 2, 2] = c, -s, s, c, 1.0
        r_dw = r_dw @ rz
    left = np.eye(3)
    if "mag_imu_misalignment" in nl:
        left = rotvec_to_matrix(nl["mag_imu_misalignment"]).T
    if "soft_iron" in nl:
        left = soft_iron_distortion(nl["soft_iron"]) @ left
    if "mag_imu_misalignment" in nl or "soft_iron" in nl:
        r_dw = left @ r_dw
    return r_dw


@dataclass(frozen=True)
class Layout:
    """Where each linear block sits in the linear parameter vector."""

    blocks: dict[str, slice]
    size: int


def linear_layout(problem: Problem, effects) -> Layout:
    blocks, i = {}, 0
    for name, size in (
        ("field_w", 3),
        ("hard_iron", 3),
        ("bias_drift", 3),
        ("temperature_offset", 3),
        ("hard_iron_change", 3 * int(np.count_nonzero(problem.offset_knot_free))),
        ("local_anomaly", 3 * int(np.count_nonzero(problem.knot_free))),
    ):
        if name in ("field_w", "hard_iron") or name in effects:
            blocks[name] = slice(i, i + size)
            i += size
    return Layout(blocks, i)


def design(problem: Problem, mats: np.ndarray, tau: np.ndarray, layout: Layout) -> sp.csr_matrix:
    """Sparse design matrix (3N, L) of the linear parameters given the per-sample maps and the true
    measurement times ``tau`` (where the anomaly field is evaluated)."""
    n = len(problem.t)
    rows3 = 3 * np.arange(n)[:, None] + np.arange(3)[None, :]  # (N, 3)
    r_parts, c_parts, v_parts = [], [], []

    def add(rows, cols, vals):
        r_parts.append(np.broadcast_to(rows, vals.shape).ravel())
        c_parts.append(np.broadcast_to(cols, vals.shape).ravel())
        v_parts.append(vals.ravel())

    s = layout.blocks["field_w"].start
    add(rows3[:, :, None], s + np.arange(3)[None, None, :], mats)
    s = layout.blocks["hard_iron"].start
    add(rows3, s + np.arange(3)[None, :], np.ones((n, 3)))
    if "bias_drift" in layout.blocks:
        s = layout.blocks["bias_drift"].start
        add(rows3, s + np.arange(3)[None, :], np.repeat(((problem.t - problem.t_ref) / 60.0)[:, None], 3, 1))
    if "temperature_offset" in layout.blocks:
        s = layout.blocks["temperature_offset"].start
        add(rows3, s + np.arange(3)[None, :],
            np.repeat((problem.temperature - problem.temp_ref)[:, None], 3, 1))
    if "hard_iron_change" in layout.blocks:
        s = layout.blocks["hard_iron_change"].start
        for kk, w, sel, idx in _hat_weights(problem.offset_knots, problem.offset_knot_free, problem.t):
            add(rows3[sel], s + 3 * idx[kk[sel]][:, None] + np.arange(3)[None, :],
                np.repeat(w[sel][:, None], 3, axis=1))
    if "local_anomaly" in layout.blocks:
        s = layout.blocks["local_anomaly"].start
        kn = problem.knots
        free = problem.knot_free
        idx = np.cumsum(free) - 1  # column of each free knot
        k = np.clip(np.searchsorted(kn, tau, side="right") - 1, 0, len(kn) - 2)
        u = np.clip((tau - kn[k]) / (kn[k + 1] - kn[k]), 0.0, 1.0)
        cols = np.arange(3)[None, None, :]
        for kk, w in ((k, 1.0 - u), (k + 1, u)):
            sel = free[kk]
            add(rows3[sel][:, :, None], s + 3 * idx[kk[sel]][:, None, None] + cols,
                mats[sel] * w[sel][:, None, None])
    rows = np.concatenate(r_parts)
    cols = np.concatenate(c_parts)
    vals = np.concatenate(v_parts)
    return sp.csr_matrix((vals, (rows, cols)), shape=(3 * n, layout.size))


def _hat_weights(kn: np.ndarray, free: np.ndarray, t: np.ndarray):
    """Piecewise-linear interpolation weights of times t on knots: ((knot, weight, free?, column) × 2)."""
    idx = np.cumsum(free) - 1
    k = np.clip(np.searchsorted(kn, t, side="right") - 1, 0, len(kn) - 2)
    u = np.clip((t - kn[k]) / (kn[k + 1] - kn[k]), 0.0, 1.0)
    return [(kk, w, free[kk], idx) for kk, w in ((k, 1.0 - u), (k + 1, u))]


def measurement_times(problem: Problem, nl: dict[str, np.ndarray]) -> np.ndarray:
    """``τ = t − time_offset`` (IMU clock)."""
    return problem.t - (float(nl["time_offset"][0]) if "time_offset" in nl else 0.0)


def linear_ridge(problem: Problem, layout: Layout, diag: np.ndarray) -> np.ndarray:
    """The ridge added to the normal matrix ``AᵀA`` (diagonal ``diag``) of the linear parameters: a
    vanishing one everywhere (a motion that leaves a combination undetermined gets its minimum-norm value)
    and the weak prior ``1/anomaly_prior_uT²`` on the knots of the local effects (σ_noise ~ 1 µT)."""
    ridge = 1e-9 * (diag.mean() if diag.size else 1.0) * np.ones(layout.size)
    for name in ("local_anomaly", "hard_iron_change"):
        if name in layout.blocks:
            ridge[layout.blocks[name]] += 1.0 / problem.anomaly_prior_uT**2
    return ridge


def solve_linear(problem: Problem, nl: dict, mats: np.ndarray, layout: Layout, with_normal: bool = False,
                 along: np.ndarray | None = None):
    """Linear parameters x̂ and the residual ``y − A x̂`` (3N,) for given per-sample maps
    (and the regularised normal matrix ``AᵀA`` with ``with_normal``).

    ``along`` (N, 3) unit vectors: fit and return only the residual's component along them, per sample
    (``h_iᵀ(y_i − A_i x̂)``, (N,)).
    """
    a = design(problem, mats, measurement_times(problem, nl), layout)
    y = problem.mag.ravel()
    if along is not None:
        n = len(problem.t)
        proj = sp.csr_matrix((np.asarray(along, dtype=float).ravel(),
                              (np.repeat(np.arange(n), 3), np.arange(3 * n))), shape=(n, 3 * n))
        a, y = proj @ a, proj @ y
    ata = (a.T @ a).tocsc()
    aty = a.T @ y
    ata = (ata + sp.diags(linear_ridge(problem, layout, ata.diagonal()))).tocsc()
    # sparse LU (SuperLU): the normal matrix is banded (anomaly knots) with a small dense border, and
    # unlike dense LAPACK it does not slow down when BLAS threads compete for the two cores
    try:
        lu = splu(ata)
        x = lu.solve(aty)
    except RuntimeError:  # exactly singular
        lu = None
        x = np.linalg.lstsq(ata.toarray(), aty, rcond=None)[0]
    if with_normal:
        return x, y - a @ x, (ata, lu)
    return x, y - a @ x


@dataclass(frozen=True)
class FitResult:
    """One fitted model.

    Attributes
    ----------
    effects : tuple of str
        Baseline plus the candidate effects in it.
    nonlinear : dict name → ndarray
        Fitted nonlinear parameters (internal units: s, rad/s, rad, distortion terms).
    linear : dict name → ndarray
        Fitted linear blocks (``field_w``, ``hard_iron``, ``bias_drift``, …).
    residual : ndarray (N, 3)
        Measured minus predicted, µT.
    rss : float
        Residual sum of squares, µT².
    k : int
        Number of fitted parameters (σ not counted; it is in every model).
    penalty : float
        The priors' share of the minimised cost, µT² (``cost = rss + penalty``).
    """

    effects: tuple[str, ...]
    nonlinear: dict
    linear: dict
    residual: np.ndarray
    rss: float
    k: int
    nfev: int = 1
    std: dict = field(default_factory=dict)
    penalty: float = 0.0

    @property
    def cost(self) -> float:
        """What the fit minimises: residual sum of squares plus the priors' penalty, µT²."""
        return self.rss + self.penalty

    @property
    def gap(self) -> float:
        return float(np.sqrt(np.mean(self.residual**2)))


def n_params(problem: Problem, effects) -> int:
    k = linear_layout(problem, effects).size
    return k + sum(_NONLINEAR[e] for e in _NL_ORDER if e in effects)


def _start(problem: Problem, effects, init: dict | None, hold=()):
    """Start values, scales, the priors' residual rows (a function of the parameters) and the
    free-parameter mask of the nonlinear parameters of ``effects`` (those of the effects in ``hold`` are
    held at ``init``).

    Priors, each weighted by ``prior_weight`` so that it counts against the magnetometer's residual as a
    χ² term: the weak Gaussians of :data:`_NL_PRIOR`, and for ``gyro_bias`` what the accelerometer says of
    it (``δᵀ I_acc δ``, ``I_acc`` the information of :class:`~pdr_mag.modelcheck.orientation.TiltBias`
    within the directions it estimated; the track's bias already holds that estimate, so δ's prior is
    centred at zero).
    """
    nl_names = [e for e in _NL_ORDER if e in effects]
    p0, scale, lo, hi, free = [], [], [], [], []
    for name in nl_names:
        size = _NONLINEAR[name]
        v = np.zeros(size) if init is None or name not in init else np.asarray(init[name], float)
        p0.extend(v)
        scale.extend([_NL_SCALE[name]] * size)
        lo.extend([-_NL_BOUND[name]] * size)
        hi.extend([_NL_BOUND[name]] * size)
        free.extend([name not in hold] * size)
    p0 = np.clip(np.asarray(p0, float), np.asarray(lo), np.asarray(hi))
    diag = problem.prior_weight * np.asarray(
        [1.0 / _NL_PRIOR[name] for name in nl_names for _ in range(_NONLINEAR[name])]
    )
    accel = None
    info = problem.track.tilt_bias.prior_information
    if "gyro_bias" in nl_names and np.any(info):
        i0 = 1 if "time_offset" in nl_names else 0
        lam, vec = np.linalg.eigh(info)
        accel = (slice(i0, i0 + 3), problem.prior_weight * np.sqrt(np.clip(lam, 0.0, None))[:, None] * vec.T)

    def prior_rows(p: np.ndarray) -> np.ndarray:
        rows = p * diag
        return rows if accel is None else np.concatenate([rows, accel[1] @ p[accel[0]]])

    return p0, np.asarray(scale), prior_rows, np.asarray(free, dtype=bool)


def _minimise(resid, p0: np.ndarray, scale: np.ndarray, max_nfev: int, free: np.ndarray):
    """Levenberg–Marquardt (MINPACK, QR) over the ``free`` parameters from ``p0``: the priors keep the
    parameters sane, no bounds needed; ``max_nfev`` counts Jacobian evaluations too, so it is per
    iteration × (n + 1).  No free parameters or ``max_nfev=0``: ``p0`` itself.  Returns (p, nfev,
    Jacobian of the free parameters or None)."""
    if not free.any() or max_nfev <= 0:
        return p0, 1, None

    def resid_free(q):
        p = p0.copy()
        p[free] = q
        return resid(p)

    sol = least_squares(resid_free, p0[free], x_scale=scale[free], method="lm", diff_step=1e-6, xtol=1e-8,
                        ftol=1e-10, gtol=1e-10, max_nfev=max_nfev * (int(free.sum()) + 1) // 4)
    p = p0.copy()
    p[free] = sol.x
    return p, int(sol.nfev), sol.jac


def fit_model(problem: Problem, effects, init: dict | None = None, max_nfev: int = 60, hold=()) -> FitResult:
    """Fit baseline + ``effects`` by variable projection; ``init`` warm-starts nonlinear parameters
    (``max_nfev=0``: they are held at ``init`` and only the linear ones are solved; ``hold``: those of
    these effects are).  Uncertainties of the nonlinear parameters (and ``std["_cov_nonlinear"]``) come
    from the Jacobian of a fit of all of them: with any held, or ``max_nfev=0``, ``std`` has the linear
    ones' only."""
    effects = tuple(dict.fromkeys([*BASELINE, *effects]))
    layout = linear_layout(problem, effects)
    p0, scale, prior_rows, free = _start(problem, effects, init, hold)

    def resid(p):
        nl = split_nonlinear(effects, p)
        r = solve_linear(problem, nl, sample_matrices(problem, nl), layout)[1]
        return np.concatenate([r, prior_rows(p)])

    p, nfev, jac = _minimise(resid, p0, scale, max_nfev, free)
    if not free.all():
        jac = None
    nl = split_nonlinear(effects, p)
    mats = sample_matrices(problem, nl)
    x, r, ata = solve_linear(problem, nl, mats, layout, with_normal=True)
    linear = {name: x[sl].copy() for name, sl in layout.blocks.items()}
    for name in ("local_anomaly", "hard_iron_change"):
        if name in linear:
            linear[name] = linear[name].reshape(-1, 3)
    res = r.reshape(-1, 3)
    k = layout.size + len(p)
    # 1-σ uncertainties: Gauss–Newton covariance × σ² × τ_int (correlated residuals count less)
    s2 = float(r @ r) / max(len(r) - k, 1) * integrated_autocorr_time(res)
    std = {}
    ata_sp, lu = ata
    anom = layout.blocks.get("local_anomaly")
    n_glob = layout.size if anom is None else anom.start
    if lu is not None:  # the global blocks' variances: columns of the inverse normal matrix
        cov_glob = lu.solve(np.eye(layout.size)[:, :n_glob])[:n_glob]
    else:
        cov_glob = np.linalg.pinv(ata_sp.toarray())[:n_glob, :n_glob]
    var = np.full(layout.size, np.nan)
    var[:n_glob] = np.diag(cov_glob)
    for name, sl in layout.blocks.items():
        std[name] = np.sqrt(np.clip(var[sl] * s2, 0, None))
    if jac is not None:
        cov_nl = np.linalg.pinv(jac.T @ jac)
        std.update(split_nonlinear(effects, np.sqrt(np.clip(np.diag(cov_nl) * s2, 0, None))))
        std["_cov_nonlinear"] = cov_nl * s2
    return FitResult(effects=effects, nonlinear=nl, linear=linear, residual=res, rss=float(r @ r),
                     k=k, nfev=nfev, std=std, penalty=float(np.sum(prior_rows(p) ** 2)))


def fit_along(problem: Problem, effects, along: np.ndarray, init: dict | None = None,
              max_nfev: int = 60, hold=()) -> float:
    """The least cost that baseline + ``effects`` reach on the residual's component along the unit
    vectors ``along`` (N, 3) alone: ``Σ (h_iᵀ r_i)²`` plus the priors' penalty, µT² (the nonlinear
    parameters of the effects in ``hold`` held at ``init``).

    What an effect explains of the measured field's *strength* (``along`` = the predicted field's
    direction): nested models give nested costs, whatever the effect does across the field.
    """
    effects = tuple(dict.fromkeys([*BASELINE, *effects]))
    layout = linear_layout(problem, effects)
    p0, scale, prior_rows, free = _start(problem, effects, init, hold)

    def resid(p):
        nl = split_nonlinear(effects, p)
        r = solve_linear(problem, nl, sample_matrices(problem, nl), layout, along=along)[1]
        return np.concatenate([r, prior_rows(p)])

    p, _, _ = _minimise(resid, p0, scale, max_nfev, free)
    r = resid(p)
    return float(r @ r)


def integrated_autocorr_time(res: np.ndarray, max_lag: int | None = None) -> float:
    """Integrated autocorrelation time of residuals (N, 3), averaged over axes (Sokal's window c = 5).

    1 for white noise; n / τ is the effective number of independent samples.
    """
    x = np.asarray(res, dtype=float)
    x = x - x.mean(axis=0)
    n = len(x)
    nfft = 1 << int(np.ceil(np.log2(2 * n)))
    f = np.fft.rfft(x, nfft, axis=0)
    acf = np.fft.irfft(f * np.conj(f), nfft, axis=0)[:n].sum(axis=1)
    if acf[0] <= 0:
        return 1.0
    rho = acf / acf[0]
    max_lag = max_lag or n // 4
    taus = 1.0 + 2.0 * np.cumsum(rho[1 : max_lag + 1])
    m = np.arange(1, len(taus) + 1)
    ok = m >= 5.0 * taus
    tau = taus[np.argmax(ok)] if ok.any() else taus[-1]
    return float(np.clip(tau, 1.0, n / 10.0))
