"""The kinds of sample in the merged stream the filter takes: one int8 code each, named here only.

The pipeline's merge writes them (ties in this order: an accelerometer sample before a gyroscope sample
before a magnetometer sample of the same time), the filter's run loop dispatches on them, and numba reads
them as compile-time constants.
"""

from __future__ import annotations

import numpy as np

#: accelerometer, m/s² (specific force, device frame)
ACCEL = 0
#: gyroscope, rad/s (device frame)
GYRO = 1
#: magnetometer, µT (device frame; calibrated when the filter takes it)
MAG = 2

#: stream name → kind, in the merge's tie order
KINDS = {"accel": ACCEL, "gyro": GYRO, "mag": MAG}
#: kind → stream name
NAMES = {v: k for k, v in KINDS.items()}


def check_kinds(kind: np.ndarray) -> None:
    """``ValueError`` unless every value of ``kind`` is one of :data:`KINDS`."""
    if len(kind) and not (kind.min() >= min(NAMES) and kind.max() <= max(NAMES)):
        bad = sorted(set(np.unique(kind).tolist()) - set(NAMES))
        raise ValueError(f"kind: expected codes {KINDS}, got {bad}")
