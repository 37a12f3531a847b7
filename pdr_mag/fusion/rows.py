"""The filter's output rows: one structured array, its columns by name, defined and checked here only.

The kernel (:func:`pdr_mag.fusion.kernel.run_cut`) writes one record of :data:`ROWS` per output gyroscope
sample, field by field (``row.heading_std_deg = …``); :class:`pdr_mag.fusion.FusionCore` reads the columns
by the same names into an :class:`pdr_mag.estimates.EstimateBatch` (views, no copy).  The diagnostic
columns are :data:`DIAG_NAMES`: every one of them is either a documented diagnostic of the pipeline's
output (:data:`pdr_mag.estimates.DIAG_KEYS`) or one of :data:`INTERNAL_DIAG` (checked at import).
"""

from __future__ import annotations

import numpy as np

from pdr_mag.estimates import DIAG_KEYS

#: diagnostic columns of the output, in order: the gyroscope-only heading, the detectors' figures at the
#: latest magnetometer sample, the bias estimate, the consistency angle and a re-acquisition's jump
DIAG_NAMES = (
    "gyro_heading_deg",
    "field_strength_uT",
    "field_ref_uT",
    "strength_tol_uT",
    "dip_deg",
    "dip_ref_deg",
    "dip_tol_deg",
    "strength_var_uT2",
    "interference_score",
    "gyro_bias_x",
    "gyro_bias_y",
    "gyro_bias_z",
    "consistency_deg",
    "heading_reset_deg",
)

#: diagnostic columns the filter gives that are not among DIAG_KEYS: the jump of a heading
#: re-acquisition at that row (deg; NaN elsewhere; the pipeline turns it into ``heading_reset`` events) and
#: the gyro-consistency angle (deg)
INTERNAL_DIAG = ("consistency_deg", "heading_reset_deg")

#: one output row: time (the gyroscope sample's, s), attitude ``q`` (w-first, w ≥ 0), heading std (deg),
#: the arguments ``h_y = 2 (x y − w z)``, ``h_x = 1 − 2 (x² + z²)`` of the heading's ``arctan2``, whether
#: the magnetometer corrected the heading and whether the interference flag was up since the previous row,
#: and the diagnostics
ROWS = np.dtype(
    [
        ("t", np.float64),
        ("q", np.float64, (4,)),
        ("heading_std_deg", np.float64),
        ("h_y", np.float64),
        ("h_x", np.float64),
        ("mag_used", np.bool_),
        ("interference", np.bool_),
        *((name, np.float64) for name in DIAG_NAMES),
    ],
    align=True,
)


def new_rows(m: int) -> np.ndarray:
    """Room for ``m`` output rows."""
    return np.empty(m, dtype=ROWS)


def _check() -> None:
    unknown = [n for n in DIAG_NAMES if n not in DIAG_KEYS and n not in INTERNAL_DIAG]
    missing = [k for k in DIAG_KEYS if k not in DIAG_NAMES and k != "coverage"]
    if unknown or missing:
        raise ImportError(f"fusion rows and DIAG_KEYS disagree: unknown {unknown}, missing {missing}")


_check()
