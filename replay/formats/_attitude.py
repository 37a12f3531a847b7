"""The phone's own fused attitude as a reference series (``Recording.references["os"]``): for evaluation, and
the heading of the rows whose heading pdr_mag does not know (:func:`pdr_mag.pipeline.fill_unknown_heading`).

Android's ``TYPE_ROTATION_VECTOR`` gives the vector part (x, y, z) = sin(θ/2)·axis of the unit quaternion
of the device → world rotation, the world being east, north (magnetic), up; the scalar part, when not
logged, is w = √max(0, 1 − x² − y² − z²) (Android's ``getQuaternionFromVector``: w ≥ 0).

The pipeline's heading is referenced to true north when the recording's metadata give position and date
(the WMM declination D, positive east), else to magnetic north.  The reference is put in the same north: with
the field known, a heading ψ_mag from magnetic north is ψ_mag + D from true north, i.e. the world turned by
−D about Up,

    q_true = q_z(−D) ⊗ q_mag,   q_z(α) = (cos α/2, 0, 0, sin α/2),

and without it the reference stays magnetic, as the pipeline's output then is.
"""

from __future__ import annotations

import numpy as np

from pdr_mag.conventions import quat_multiply
from pdr_mag.field import earth_field_from_meta


def rotation_vector_quat(xyz: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """w-first unit quaternions (N, 4) from rotation-vector components ``xyz`` (N, 3) and, when logged, the
    scalar part ``w`` (N,)."""
    v = np.asarray(xyz, dtype=float).reshape(-1, 3)
    if w is None:
        w = np.sqrt(np.clip(1.0 - np.sum(v * v, axis=1), 0.0, None))
    q = np.column_stack([np.asarray(w, dtype=float), v])
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def in_output_north(q_mag: np.ndarray, meta: dict) -> np.ndarray:
    """A magnetic-north attitude ``q_mag`` (N, 4) in the north the pipeline gives for ``meta``: turned by
    the WMM declination when position and date are known, unchanged otherwise."""
    field = earth_field_from_meta(meta)
    if field is None:
        return np.asarray(q_mag, dtype=float)
    a = -np.radians(field.declination_deg)
    turn = np.array([[np.cos(a / 2), 0.0, 0.0, np.sin(a / 2)]])
    return quat_multiply(np.broadcast_to(turn, np.shape(q_mag)), np.asarray(q_mag, dtype=float))
