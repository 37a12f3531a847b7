"""The phone's own heading where pdr_mag knows none.

Until the first field the filter can trust, the heading's variance sits at its cap π² (a reported std of
180°, :func:`pdr_mag.fusion.kernel.calibration_floor`): before the first calibration the heading is an
arbitrary start turned by the gyroscope (a walk started in the middle of a disturbance waits tens of seconds
for its first fit), and after a start next to steel it is a guess from flagged fields
(:mod:`pdr_mag.fusion.mag`).  The phone usually knows more: its OS keeps a magnetometer calibration across
sessions and its fusion ran before the recording began (Android's ``TYPE_ROTATION_VECTOR``, iOS CoreMotion's
attitude, the IPIN logger's ``AHRS``).

:func:`fill_unknown_heading` gives those rows the phone's heading: the latest attitude sample at or before
the row's time (causal: what a backend has when the row is made), at most ``max_age_s`` older, the row's
own tilt kept — the world turned about Up by ``ψ − ψ_phone`` counter-clockwise
(:func:`pdr_mag.conventions.rotation_about_up`), which moves the heading ψ (clockwise from north) onto
ψ_phone and nothing else.  The std stays
180°: pdr_mag does not vouch for the phone's heading (a CoreMotion frame may be arbitrary in yaw; on the
tyrex walks the iPhones' fusions are 80–160° off at 20 s on 4 of 28), so a backend weighting by 1/σ² still
gives these rows no weight and no row is kept as sure that was not before; the filter never reads it.
Measured (benchmarks/NOTES.md): on the tyrex walks replayed from 20 s in without a calibration, the rows
at 180° were 82.5° off on average with the filter's own start and are 27.0° off with the phone's; a flagged
start's guess loses to the phone's heading too (the mall traces' mean 11.90 → 11.72° with it replaced,
11.90° with it kept).

The attitude must be in the north the output is in (a magnetic-north attitude turned by the declination the
pipeline uses, :attr:`HeadingPipeline.field`; the readers do so for ``Recording.references["os"]``).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from pdr_mag.conventions import heading_deg_from_quat, quat_to_rotation, rotation_about_up, rotation_to_quat
from pdr_mag.estimates import EstimateBatch

#: a row's heading is unknown when its reported std is at the cap (π² of variance, 180°), deg
UNKNOWN_STD_DEG = 180.0 - 1e-6


def fill_unknown_heading(
    batch: EstimateBatch, t_phone: np.ndarray, q_phone: np.ndarray, max_age_s: float = 1.0
) -> tuple[EstimateBatch, np.ndarray]:
    """``batch`` with its unknown-heading rows (``heading_std_deg`` at 180°) turned onto the phone's heading
    (the module docstring), and the indices of the rows that were.

    ``t_phone`` (M,) increasing times in the estimates' clock, s; ``q_phone`` (M, 4) w-first device → ENU
    attitudes in the output's north.  A row with no attitude sample at or before it within ``max_age_s``
    keeps its own heading.  The input batch is not changed.
    """
    t_phone = np.asarray(t_phone, dtype=float).reshape(-1)
    q_phone = np.asarray(q_phone, dtype=float).reshape(-1, 4)
    if len(t_phone) != len(q_phone):
        raise ValueError(f"t_phone, q_phone: {len(t_phone)} times for {len(q_phone)} attitudes")
    none = np.empty(0, dtype=np.intp)
    if not len(batch) or not len(t_phone):
        return batch, none
    rows = np.flatnonzero(batch.heading_std_deg >= UNKNOWN_STD_DEG)
    if not len(rows):
        return batch, none
    k = np.searchsorted(t_phone, batch.t[rows], side="right") - 1  # the latest sample at or before
    q_ph = q_phone[np.maximum(k, 0)]
    norm = np.linalg.norm(q_ph, axis=1)
    use = (k >= 0) & (batch.t[rows] - t_phone[np.maximum(k, 0)] <= max_age_s)
    use &= np.all(np.isfinite(q_ph), axis=1) & (norm > 0)
    rows = rows[use]
    if not len(rows):
        return batch, none
    q_ph = q_ph[use] / norm[use, None]  # heading_deg_from_quat takes unit quaternions
    turn = rotation_about_up(np.radians(batch.heading_deg[rows] - heading_deg_from_quat(q_ph)))
    q = batch.q_wd.copy()
    q[rows] = rotation_to_quat(turn * quat_to_rotation(q[rows]))  # w ≥ 0, the rows' convention
    heading = batch.heading_deg.copy()
    heading[rows] = heading_deg_from_quat(q[rows])
    return replace(batch, q_wd=q, heading_deg=heading), rows
