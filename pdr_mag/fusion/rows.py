"""The filter's output rows: one structured array, its columns by name, defined here only.

The kernel (:func:`pdr_mag.fusion.kernel.run_cut`) writes one record of :data:`ROWS` per output gyroscope
sample, field by field (``row.heading_std_deg = …``; each detector writes its own columns,
:func:`pdr_mag.fusion.detectors.write`); :class:`pdr_mag.fusion.FusionCore` reads the columns by the same
names into an :class:`pdr_mag.estimates.EstimateBatch` (views, no copy).  The diagnostic columns are
:data:`DIAG_COLUMNS`: the filter's own and every registered detector's
(:data:`pdr_mag.fusion.detectors.COLUMNS`); :data:`pdr_mag.estimates.DIAG_KEYS` is built from them.
"""

from __future__ import annotations

import numpy as np

from pdr_mag.fusion.detectors import COLUMNS as DETECTOR_COLUMNS

#: diagnostic columns of the output (name → meaning), in order: the gyroscope-only heading, the detectors'
#: figures at the latest magnetometer sample and their score, the bias estimate, a re-acquisition's jump
DIAG_COLUMNS = {
    "gyro_heading_deg": "heading from gyroscope integration alone (same start), deg",
    **DETECTOR_COLUMNS,
    "interference_score": "detector score (≥ 1 means flagged)",
    "gyro_bias_x": "estimated gyroscope bias x, rad/s",
    "gyro_bias_y": "estimated gyroscope bias y, rad/s",
    "gyro_bias_z": "estimated gyroscope bias z, rad/s",
    "heading_reset_deg": "the turn of a heading re-acquisition at that row, deg (NaN at the others)",
}
#: the diagnostic columns, in order
DIAG_NAMES = tuple(DIAG_COLUMNS)
#: the columns that are not among :data:`pdr_mag.estimates.DIAG_KEYS` (so not in the MCAP's ``/pdr/diag``):
#: the jump of a re-acquisition, which the pipeline turns into ``heading_reset`` events, and the
#: gyro-consistency angle (adding it to ``/pdr/diag`` changes that message's layout, which
#: ``tests/fixtures/pdrmcap_v2_handwritten.mcap`` holds byte for byte)
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
