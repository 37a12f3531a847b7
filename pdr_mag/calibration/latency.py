"""The magnetometer's latency against the gyroscope, from how the field turns as the device turns.

A constant field seen by a turning device changes as ``ṁ = −ω × (m − b)`` (device frame: m the raw
field, b the hard-iron offset, ω the rate).  A magnetometer whose samples are stamped τ after they were
measured (a sensor's own filter delay, a logger stamping on delivery) obeys it with the gyroscope's rate at
``t − τ``::

    ṁ(t) + ω(t − τ) × m(t) = ω(t − τ) × b

which, for a trial τ, is linear in b: three equations per sample.  The latency is the τ whose least-squares
fit leaves the smallest residual; its standard error comes from the residual's curvature in τ, with the
residuals' own correlation (they are low-passed) counted.  Soft iron and a building's own field (which
changes as the walker moves, not as the device turns) are noise to this model; a latency is only reported
when the fit finds it determined (:attr:`LatencySettings.max_std_s`) and when it explains a significant share
of what lag 0 leaves (:attr:`LatencySettings.min_gain`).

The same effect is ``time_offset`` of the simulator and of ``diagnose``
(:mod:`pdr_mag.modelcheck`), whose full model fit finds it on the tyrex Nexus 5 walks at 28–33 ms; this
estimator is the fast one (a tenth of a second over a minute of a phone's data), which
``replay --mag-time-offset auto`` runs before the replay.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import butter, sosfiltfilt

from pdr_mag._records import check_numbers


@dataclass(frozen=True)
class LatencySettings:
    """Settings of :func:`estimate_mag_latency`.

    Attributes
    ----------
    max_lag_s : float
        The latencies tried: −max_lag_s … +max_lag_s, s.
    step_s : float
        Their spacing, s (the minimum is refined between its neighbours).
    cutoff_hz : float
        Both streams are low-passed at this frequency (a walker's turns and a hand's swing lie below it; the
        magnetometer's noise differentiated does not).
    min_rate : float
        Samples turning slower than this carry no timing (rad/s): left out.
    max_std_s : float
        A latency is determined when its standard error is below this, s.
    min_gain : float
        … and when it explains at least this share of the residual at lag 0 beyond what noise would.
    """

    max_lag_s: float = 0.3
    step_s: float = 0.004
    cutoff_hz: float = 3.0
    min_rate: float = 0.3
    max_std_s: float = 0.005
    min_gain: float = 0.05

    def __post_init__(self):
        check_numbers(self, positive=("max_lag_s", "step_s", "cutoff_hz", "max_std_s"))


@dataclass(frozen=True)
class Latency:
    """What :func:`estimate_mag_latency` found.

    Attributes
    ----------
    seconds : float
        The latency τ (a sample stamped t was measured at t − τ), s; NaN when nothing could be fitted.
    std_s : float
        Its standard error, s.
    gain : float
        The share of lag 0's residual that τ explains (0: none).
    n : int
        Samples used.
    determined : bool
        ``std_s`` and ``gain`` pass the settings' bounds.
    """

    seconds: float
    std_s: float
    gain: float
    n: int
    determined: bool

    def to_dict(self) -> dict:
        return {"seconds": _finite(self.seconds, 5), "std_s": _finite(self.std_s, 5),
                "gain": _finite(self.gain, 4), "n": self.n, "determined": self.determined}


NONE = Latency(float("nan"), float("nan"), 0.0, 0, False)


def estimate_mag_latency(t_gyro, gyro, t_mag, mag, settings: LatencySettings | None = None) -> Latency:
    """The magnetometer's latency against the gyroscope (module docstring).

    Parameters
    ----------
    t_gyro, gyro : arrays (N,), (N, 3)
        Gyroscope times (s) and rates (rad/s).
    t_mag, mag : arrays (M,), (M, 3)
        Magnetometer times (s) and raw field (µT), on the same clock.
    """
    s = settings or LatencySettings()
    t_gyro, gyro = np.asarray(t_gyro, float), np.asarray(gyro, float)
    t_mag, mag = np.asarray(t_mag, float), np.asarray(mag, float)
    if len(t_mag) < 50 or len(t_gyro) < 50:
        return NONE
    period = float(np.median(np.diff(t_mag)))
    if not period > 0:
        return NONE
    fs = 1.0 / period
    lo, hi = max(t_mag[0], t_gyro[0]) + s.max_lag_s, min(t_mag[-1], t_gyro[-1]) - s.max_lag_s
    if not (hi - lo > 10 * period and s.cutoff_hz < 0.45 * fs):
        return NONE
    grid = np.arange(lo, hi, period)
    sos = butter(2, s.cutoff_hz / (fs / 2), output="sos")
    m = sosfiltfilt(sos, _resample(grid, t_mag, mag), axis=0)
    dm = np.gradient(m, period, axis=0)
    lags = np.arange(-s.max_lag_s, s.max_lag_s + 0.5 * s.step_s, s.step_s)
    # the rate low-passed once on a grid of a quarter of the magnetometer's period (filtering and shifting
    # commute), then read at each trial's shifted times
    fine = np.arange(grid[0] - s.max_lag_s - period, grid[-1] + s.max_lag_s + period, period / 4)
    sos4 = butter(2, s.cutoff_hz / (2 * fs), output="sos")
    w_fine = sosfiltfilt(sos4, _resample(fine, t_gyro, gyro), axis=0)
    zero = int(np.argmin(np.abs(lags)))
    use = np.linalg.norm(_resample(grid, fine, w_fine), axis=1) >= s.min_rate
    n = int(np.count_nonzero(use))
    if n < 4 * fs:  # less than 4 s of turning
        return Latency(float("nan"), float("nan"), 0.0, n, False)
    g, mu, dmu = grid[use], m[use], dm[use]
    rss = np.array([_rss(_resample(g - lag, fine, w_fine), mu, dmu) for lag in lags])
    i = int(np.argmin(rss))
    if i in (0, len(lags) - 1):  # at the edge: not a minimum
        return Latency(float(lags[i]), float("inf"), 0.0, n, False)
    a, b, c = rss[i - 1], rss[i], rss[i + 1]
    curv = (a - 2 * b + c) / s.step_s**2  # d²RSS/dτ²
    shift = 0.5 * (a - c) / (a - 2 * b + c)
    tau = float(lags[i] + shift * s.step_s)
    rss_min = float(b - 0.125 * (a - c) ** 2 / (a - 2 * b + c))
    # the residuals are low-passed: about fs / (2 cutoff) samples carry one independent value
    n_eff = max(3 * n / (fs / (2 * s.cutoff_hz)) - 4, 1.0)
    var = rss_min / n_eff  # per independent residual
    std = float(np.sqrt(2 * var / curv)) if curv > 0 else float("inf")
    gain = float(1 - rss_min / rss[zero]) if rss[zero] > 0 else 0.0
    # what noise alone would explain: one parameter more, n_eff residuals (an F-test's 1 / n_eff)
    determined = bool(std < s.max_std_s and gain > s.min_gain + 1.0 / n_eff)
    return Latency(tau, std, gain, n, determined)


def applies(latency: Latency) -> bool:
    """Whether a latency found is one to correct: determined, and the magnetometer the later stream.

    The output rows follow the IMU's stamps.  A negative latency says the IMU is the later stream (or the
    magnetometer's own filtering leads its stamps): moving the magnetometer onto the IMU's clock leaves the
    output as late as before, and moving the IMU back did not help either — measured on six tyrex iPhone 4S
    walks (−10 to −14 ms; the walks' mean errors summed, mode a / b: 21.0 / 17.0° as they are, 22.1 / 18.2°
    with the magnetometer moved, 21.5 / 16.9° with the IMU moved) and the mall traces (−8 to −23 ms: the
    walked median 8.89 → 9.07° with the magnetometer moved) (benchmarks/NOTES.md).  A positive one is a
    magnetometer that reports late, which moving its stamps back mends on the simulator's late phones and on
    the tyrex Nexus 5 (25–33 ms; its walks 5.02 → 4.94° in mode a) — but not on BROAD's lab IMU (9–13 ms: five
    of six trials worse), which is why ``auto`` is an option of ``replay``, not its default."""
    return bool(latency.determined and latency.seconds > 0.0)


def _resample(grid, t, x):
    return np.column_stack([np.interp(grid, t, x[:, k]) for k in range(3)])


def _rss(w, m, dm) -> float:
    """The residual of ``dm + w × m = w × b`` with b fitted by least squares."""
    y = (dm + np.cross(w, m)).reshape(-1)
    z = np.zeros(len(w))
    a = np.stack([np.stack([z, -w[:, 2], w[:, 1]], 1),
                  np.stack([w[:, 2], z, -w[:, 0]], 1),
                  np.stack([-w[:, 1], w[:, 0], z], 1)], 1).reshape(-1, 3)
    b, *_ = np.linalg.lstsq(a, y, rcond=None)
    r = y - a @ b
    return float(r @ r)


def _finite(x: float, nd: int):
    return round(float(x), nd) if np.isfinite(x) else None
