"""The filter's output rows: their columns by name, defined here only.

The kernel (:func:`pdr_mag.fusion.kernel.run_cut`) writes the rows into :class:`Rows`: a block of float
columns (one row of the block per column, so each column is contiguous), the attitudes and a block of flag
columns.  It addresses a column by its name only, ``out.floats[COL.heading_std_deg, n]``: :data:`COL` and
:data:`FLAG` name each column's row in its block (numba reads them as constants), and each detector writes
its own columns the same way (:func:`pdr_mag.fusion.detectors.write`).  :class:`pdr_mag.fusion.FusionCore`
reads the columns by the same names into an :class:`pdr_mag.estimates.EstimateBatch` (views, no copy).

The diagnostic columns are :data:`DIAG_COLUMNS`: the filter's own and every registered detector's
(:data:`pdr_mag.fusion.detectors.COLUMNS`); :data:`pdr_mag.estimates.DIAG_KEYS` is built from them.
"""

from __future__ import annotations

from collections import namedtuple
from typing import NamedTuple

import numpy as np

from pdr_mag.fusion.detectors import COLUMNS as DETECTOR_COLUMNS

#: the three columns (x, y, z, device frame) of the filter's gyro bias estimate, rad/s, and of the
#: calibration's offset error ``o`` it carries, µT (``MagSettings.offset_states``: the field it takes is the
#: calibrated one less ``o``; 0 without those states)
GYRO_BIAS_COLUMNS = ("gyro_bias_x", "gyro_bias_y", "gyro_bias_z")
OFFSET_ERROR_COLUMNS = ("mag_offset_error_x", "mag_offset_error_y", "mag_offset_error_z")

#: diagnostic columns of the output (name → meaning), in order: the gyroscope-only heading, the detectors'
#: figures at the latest magnetometer sample and their score, the bias estimate, a re-acquisition's jump, the
#: offset error
DIAG_COLUMNS = {
    "gyro_heading_deg": "heading from gyroscope integration alone (same start), deg",
    **DETECTOR_COLUMNS,
    "interference_score": "detector score (≥ 1 means flagged)",
    **{c: f"estimated gyroscope bias {c[-1]}, rad/s" for c in GYRO_BIAS_COLUMNS},
    "heading_reset_deg": "the turn of a heading re-acquisition at that row, deg (NaN at the others)",
    **{c: f"the filter's estimate of the calibration's offset error, {c[-1]}, µT (device frame)"
       for c in OFFSET_ERROR_COLUMNS},
}
#: the diagnostic columns, in order
DIAG_NAMES = tuple(DIAG_COLUMNS)
#: the columns that are not among :data:`pdr_mag.estimates.DIAG_KEYS` (so not in the MCAP's ``/pdr/diag``):
#: the jump of a re-acquisition, which the pipeline turns into ``heading_reset`` events, the offset error,
#: which the pipeline takes out of the calibrated field it gives the sinks
#: (:meth:`pdr_mag.pipeline.HeadingPipeline.pop_mag_calibrated`), and the gyro-consistency angle (adding
#: them to ``/pdr/diag`` changes that message's layout, which ``tests/fixtures/pdrmcap_v2_handwritten.mcap``
#: holds byte for byte)
INTERNAL_DIAG = ("consistency_deg", "heading_reset_deg", *OFFSET_ERROR_COLUMNS)

#: the parts of a row's reported variance (:func:`pdr_mag.fusion.kernel.calibration_floor`): the filter's
#: ``(P + U)[δθ_z, δθ_z]``, the calibration's ``g Σ_b gᵀ`` (0 with the offset states, which carry it in P)
#: and the heading gradient g (rad/µT) it was taken at (both 0 before the first heading: no floor) — what
#: the std is made of besides the suspected shift ``ΔΔᵀ``, which the filter's weights do not see, so that a
#: shift suspected after the rows were made can be put into their std
#: (:meth:`pdr_mag.fusion.FusionCore.suspect_from`)
VAR_PARTS = ("var_filter", "var_cal", "cal_gx", "cal_gy", "cal_gz")
#: the float columns: time (the gyroscope sample's, s), heading std (deg), the arguments
#: ``h_y = 2 (x y − w z)``, ``h_x = 1 − 2 (x² + z²)`` of the heading's ``arctan2``, the variance's parts and
#: the diagnostics
FLOAT_COLUMNS = ("t", "heading_std_deg", "h_y", "h_x", *VAR_PARTS, *DIAG_NAMES)
#: the flag columns: the magnetometer corrected the heading / the interference flag was up, since the
#: previous row
FLAG_COLUMNS = ("mag_used", "interference")
#: each float column's row in :attr:`Rows.floats`, by name
COL = namedtuple("FloatColumns", FLOAT_COLUMNS)(*range(len(FLOAT_COLUMNS)))
#: each flag column's row in :attr:`Rows.flags`, by name
FLAG = namedtuple("FlagColumns", FLAG_COLUMNS)(*range(len(FLAG_COLUMNS)))


class Rows(NamedTuple):
    """Room for ``m`` output rows: ``floats`` (len(FLOAT_COLUMNS), m), the attitudes ``q`` (m, 4; w-first,
    w ≥ 0) and ``flags`` (len(FLAG_COLUMNS), m) bool."""

    floats: np.ndarray
    q: np.ndarray
    flags: np.ndarray


def new_rows(m: int) -> Rows:
    """Room for ``m`` output rows."""
    return Rows(
        np.empty((len(FLOAT_COLUMNS), m)), np.empty((m, 4)), np.empty((len(FLAG_COLUMNS), m), dtype=np.bool_)
    )


def columns(rows: Rows, k: int) -> dict:
    """The first ``k`` rows' columns by name (views): every float and flag column, and ``q``."""
    out = dict(zip(FLOAT_COLUMNS, rows.floats[:, :k], strict=True))
    out.update(zip(FLAG_COLUMNS, rows.flags[:, :k], strict=True))
    out["q"] = rows.q[:k]
    return out
