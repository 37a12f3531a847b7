"""Phone-like sample times: own clock-rate error, jitter, dropped samples and gaps per stream."""

from __future__ import annotations

import numpy as np


def sample_times(
    rate_hz: float,
    t_end: float,
    rng: np.random.Generator,
    rate_error: float = 0.0,
    jitter_s: float = 0.0,
    drop_prob: float = 0.0,
    gap_rate_hz: float = 0.0,
    gap_max_s: float = 0.3,
) -> np.ndarray:
    """Strictly increasing sample times in ``[0, t_end]``, s.

    ``t_k = t_0 + k / (rate · (1 + ε)) + j_k`` with ε ~ N(0, rate_error²), t_0 ~ U(0, period), jitter
    j_k ~ N(0, jitter_s²) clipped to ±0.4 period (so times stay increasing); each sample is dropped with
    probability ``drop_prob``, and gaps of U(0.05, gap_max_s) s start as a Poisson process of rate
    ``gap_rate_hz``.
    """
    if rate_hz <= 0 or t_end <= 0:
        raise ValueError(f"rate_hz, t_end: expected positive values, got {rate_hz!r}, {t_end!r}")
    dt = 1.0 / (rate_hz * (1.0 + rate_error * rng.standard_normal()))
    t0 = rng.uniform(0.0, dt)
    n = int(np.floor((t_end - t0) / dt)) + 1
    t = t0 + dt * np.arange(n)
    if jitter_s > 0:
        t = t + np.clip(rng.standard_normal(n) * jitter_s, -0.4 * dt, 0.4 * dt)
    keep = (t >= 0.0) & (t <= t_end)
    if drop_prob > 0:
        keep &= rng.random(n) >= drop_prob
    if gap_rate_hz > 0:
        n_gaps = rng.poisson(gap_rate_hz * t_end)
        starts = rng.uniform(0.0, t_end, n_gaps)
        lengths = rng.uniform(0.05, max(gap_max_s, 0.05), n_gaps)
        for s, ln in zip(starts, lengths, strict=True):
            keep &= ~((t >= s) & (t < s + ln))
    return t[keep]
