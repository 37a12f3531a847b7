"""The recording's own null: what a candidate effect fits when nothing is missing but the orientation error.

The magnetometer is predicted along an orientation estimated from the gyroscope and accelerometer
(:mod:`.orientation`).  Its error — tilt from walking accelerations that do not average out, turns'
centripetal acceleration, heading wander — leaves a correlated residual that any flexible candidate can
partly fit, by an amount that depends on the recording (its motion, its length, the field's direction).
A fixed threshold on ΔBIC or on the gap cannot know that amount; this module measures it by a parametric
bootstrap: the current model's prediction plus a *surrogate* residual that has the orientation error's
statistics but none of a missing effect's structure, fitted exactly like the recording.

Surrogate residual
------------------
A small error ``φ`` (world frame) of the orientation changes the predicted field by ``B × φ``: it moves
the residual perpendicular to the field ``B`` (first order) and along it only by ``|B|(1 − cos φ)``.
So, with the residual taken back to the world frame of the track through the current model's own map
(``r_w = A⁻¹ r``, ``A = S⁻¹ Mᵀ R_dw(t − Δt) Rz(ψ)`` of :func:`~pdr_mag.modelcheck.fit.sample_matrices`,
which is ``R_dw`` for the baseline) and ``u = B / |B|``:

* along ``u``: white noise of the recording's own σ (median absolute first difference / √2 · 1.4826 —
  insensitive to anything slow, which is what a missing effect would put there), and the second-order
  shortening ``−|B|(1 − cos φ) ≈ −|s|² / 2|B|`` of the field that the error ``s`` across it implies;
* perpendicular to ``u`` (2 components): the residual itself, re-drawn with random Fourier phases
  (phases shared by the two components, so their cross-spectrum is kept: Theiler et al. 1992, Prichard
  & Theiler 1994), in two parts:

  - the band ``band_hz`` (periods of 0.5–20 s), where the tilt errors of turns and motion changes are:
    ``a(t) · PR(band / a)`` with ``a(t)`` its moving RMS over ``envelope_s``.  Tilt errors come in
    bursts, and a local candidate fits a burst better than the same power spread evenly; the envelope
    keeps each burst's size and place, the phases its shape;
  - the rest, stationary: the slow part (its power stays, its timing does not, so a trend or a drift —
    gyro bias, bias drift — is not copied into the null) and the fast part (noise);

  and ``|s|`` is clipped at ``|B| sin(max_error_deg)``: with nothing missing, the estimate errs in tilt
  by a few degrees at most (the accelerometer bounds it) and in heading only as much as the gyro's
  noise lets it wander — a heading drift is the ``gyro_bias`` candidate, and a larger burst across the
  field is no orientation error (e.g. what a local candidate's windows could not hold).

The search draws the surrogates from the residual that is left *with* the candidate under test, so what
the candidate explains is not copied into its own null (:func:`pdr_mag.modelcheck.select._null_tests`).

Decision
--------
The statistic of a candidate is a nested fit's gain ``L = ln(cost_current / cost_candidate)`` (ΔBIC
without the penalty), taken alike on the recording and on each replicate — for an effect that changes
the field's strength on the residual's component along the field alone, which no orientation error
reaches (:func:`pdr_mag.modelcheck.select._null_tests`).  The candidate beats the null when its ``L``
exceeds the ``1 − false_alarm`` prediction bound of the replicates (:func:`null_threshold`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy import stats

from pdr_mag.modelcheck.fit import FitResult, Problem, sample_matrices
from pdr_mag.modelcheck.orientation import window_mean


@dataclass(frozen=True)
class NullSettings:
    """Settings of the recording's null (see the module docstring).

    Attributes
    ----------
    replicates : int
        Surrogate recordings per round (0: no null, the fixed ΔBIC and gap rules decide alone).
    false_alarm : float
        Probability that a candidate with nothing missing beats the null, per candidate and round.
        10⁻³: a recording is tried with at most 8 candidates a round, so one with nothing missing is
        named something with probability below 1 % — and in practice far less, since only candidates
        that already pass the ΔBIC and gap rules are tested.  A user running ``diagnose`` over a
        hundred recordings then meets a false name about once, not on every second recording.
    max_rate_hz : float
        The null runs on every k-th magnetometer sample so that its rate is at most this (cost ∝ 1/k);
        the recording's own statistic is taken on the same samples, so the level holds — fewer samples
        cost power, not false alarms.
    band_hz : (float, float)
        Frequency band of the bursts of orientation error across the field, Hz.
    envelope_s : float
        Moving-RMS length of the band's envelope, s.
    max_error_deg : float
        Largest orientation error (other than a heading drift, which is the ``gyro_bias`` candidate) of
        a gyro + accelerometer estimate, degrees: the accelerometer bounds its tilt error.
    seed : int
        Seed of the surrogates' phases (a diagnosis is reproducible).
    """

    replicates: int = 12
    false_alarm: float = 1e-3
    max_rate_hz: float = 12.5
    band_hz: tuple[float, float] = (0.05, 2.0)
    envelope_s: float = 4.0
    max_error_deg: float = 10.0
    seed: int = 0


def _band(t: np.ndarray, x: np.ndarray, lo_hz: float, hi_hz: float) -> np.ndarray:
    """The part of ``x`` (N, d) between ``lo_hz`` and ``hi_hz`` (an ideal band-pass on the FFT of the
    samples taken as uniform at their mean rate; the rest, ``x`` minus it, is orthogonal to it)."""
    n = len(x)
    rate = (n - 1) / max(float(t[-1] - t[0]), 1e-9)
    f = np.fft.rfftfreq(n, 1.0 / rate)
    spec = np.fft.rfft(x, axis=0)
    spec[(f < lo_hz) | (f > hi_hz)] = 0.0
    return np.fft.irfft(spec, n, axis=0)


def _random_phases(x: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """``x`` (N, d) with the same amplitude spectrum and random Fourier phases shared by its columns."""
    n = len(x)
    f = np.fft.rfft(x, axis=0)
    ph = np.exp(2j * np.pi * rng.random(len(f)))
    ph[0] = 1.0  # the mean stays
    if n % 2 == 0:
        ph[-1] = np.sign(rng.standard_normal())  # the Nyquist term is real
    return np.fft.irfft(f * ph[:, None], n, axis=0)


def _perpendicular_basis(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    e1 = np.cross(u, [0.0, 0.0, 1.0])
    if np.linalg.norm(e1) < 1e-6:  # a vertical field
        e1 = np.cross(u, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(u, e1)


def above_white(g: float, white: float) -> float:
    """The part of a gap ``g`` above the white noise ``white`` (rms, µT): ``√(g² − σ_w²)``, ≥ 0."""
    return float(np.sqrt(max(g * g - white * white, 0.0)))


def robust_sigma(x: np.ndarray) -> float:
    """White-noise σ of a series from its first differences (median absolute deviation), robust to any
    slow part."""
    d = np.diff(np.asarray(x, dtype=float))
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / np.sqrt(2.0))


def surrogate_residuals(problem: Problem, fit: FitResult, rng: np.random.Generator, n: int,
                        settings: NullSettings = NullSettings()) -> list[np.ndarray]:
    """``n`` surrogate residuals (N, 3), µT, magnetometer axes: the orientation error and noise of
    ``fit``'s residual without its structure (module docstring)."""
    maps = sample_matrices(problem, fit.nonlinear)  # world → raw magnetometer axes, per sample
    r_w = np.linalg.solve(maps, fit.residual[:, :, None])[:, :, 0]
    b = np.asarray(fit.linear["field_w"], dtype=float)
    u = b / np.linalg.norm(b)
    e1, e2 = _perpendicular_basis(u)
    perp = np.column_stack([r_w @ e1, r_w @ e2])
    sigma = robust_sigma(r_w @ u)
    mid = _band(problem.t, perp, *settings.band_hz)
    rest = perp - mid
    power = np.sum(mid**2, axis=1, keepdims=True)
    env = np.sqrt(window_mean(problem.t, power, 0.5 * settings.envelope_s))[:, 0]  # RMS over envelope_s
    env = np.maximum(env, 1e-6 * max(float(env.max()), 1e-12))
    s_max = np.linalg.norm(b) * np.sin(np.radians(settings.max_error_deg))
    out = []
    for _ in range(n):
        s = env[:, None] * _random_phases(mid / env[:, None], rng) + _random_phases(rest, rng)
        s *= np.minimum(1.0, s_max / np.maximum(np.linalg.norm(s, axis=1), 1e-12))[:, None]
        along = sigma * rng.standard_normal(len(s)) - np.sum(s**2, axis=1) / (2.0 * np.linalg.norm(b))
        w = np.outer(along, u) + np.outer(s[:, 0], e1) + np.outer(s[:, 1], e2)
        out.append(np.einsum("nij,nj->ni", maps, w))
    return out


def subsample(problem: Problem, stride: int) -> Problem:
    """Every ``stride``-th sample of a problem (the knots, the track and the settings unchanged)."""
    if stride <= 1:
        return problem
    sl = slice(None, None, stride)
    temp = None if problem.temperature is None else problem.temperature[sl]
    return replace(problem, t=problem.t[sl], mag=problem.mag[sl], temperature=temp, r_dw0=problem.r_dw0[sl])


def stride_for(problem: Problem, max_rate_hz: float) -> int:
    """The subsampling step that brings the magnetometer rate to at most ``max_rate_hz``."""
    span = float(problem.t[-1] - problem.t[0])
    rate = (len(problem.t) - 1) / span if span > 0 else 1.0
    return max(1, int(np.ceil(rate / max_rate_hz - 1e-9)))


def null_threshold(values, false_alarm: float, cube_root: bool = True) -> float:
    """The threshold that a candidate's statistic must exceed: the upper ``1 − false_alarm`` prediction
    bound of one more draw from the distribution of the null statistics ``values``.

    For m Gaussian draws with mean x̄ and standard deviation s, one more draw exceeds
    ``x̄ + t_{m−1}(1 − α) · s · √(1 + 1/m)`` with probability exactly α (Student's t with m − 1 degrees of
    freedom): the replicates' own randomness is included, so few replicates give a higher threshold, not
    a higher false-alarm rate.  ``cube_root``: the bound is taken on the cube roots — a statistic that is
    χ²-like (a nested least-squares fit's gain on correlated Gaussian noise, ≥ 0) has a nearly Gaussian
    cube root (Wilson & Hilferty 1931); without it, on the values themselves.
    """
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    m = len(v)
    if m < 2:
        return float("inf")
    x = np.cbrt(v) if cube_root else v
    bound = float(np.mean(x)) + stats.t.ppf(1.0 - false_alarm, m - 1) * float(np.std(x, ddof=1)) \
        * np.sqrt(1.0 + 1.0 / m)
    return float(bound**3) if cube_root else bound
