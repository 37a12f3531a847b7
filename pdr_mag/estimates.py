"""What the heading pipeline gives out: per-epoch estimates (single and columnar) and events.

These types are the boundary between :class:`pdr_mag.pipeline.HeadingPipeline` and its callers / sinks.
The ``replay --out-csv`` columns of INTERFACE.md are exactly :data:`CSV_COLUMNS`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pdr_mag.fusion.rows import DIAG_COLUMNS, INTERNAL_DIAG

#: ``replay --out-csv`` columns (INTERFACE.md); more may follow, none renamed.
CSV_COLUMNS = (
    "t", "qw", "qx", "qy", "qz", "heading_deg", "heading_std_deg", "mag_used", "interference", "cal_state",
)

#: Calibration states written in ``cal_state``.
CAL_STATES = ("none", "offset", "ellipsoid", "recalibrating")

#: Optional diagnostic columns an :class:`EstimateBatch` may carry in ``diag`` (all float arrays, NaN when
#: not available at that epoch): the fusion filter's (:data:`pdr_mag.fusion.rows.DIAG_COLUMNS`, with every
#: registered interference detector's) and the online calibrator's ``coverage``.  Sinks draw them when
#: present.
DIAG_KEYS = {}
for _name, _doc in DIAG_COLUMNS.items():
    if _name not in INTERNAL_DIAG:
        DIAG_KEYS[_name] = _doc
    if _name == "interference_score":
        DIAG_KEYS["coverage"] = "orientation coverage of the online calibration buffer, [0, 1]"


@dataclass(frozen=True)
class HeadingEstimate:
    """One output epoch.

    Attributes
    ----------
    t : float
        Time, s (the recording's clock).
    q_wd : tuple of 4 float
        Orientation, w-first quaternion, device → ENU (true north when the declination is known).
    heading_deg : float
        In [0, 360), clockwise from north, of the device +y axis.
    heading_std_deg : float
        1-σ heading uncertainty, deg.
    mag_used : bool
        Whether the magnetometer corrected the heading since the previous epoch.
    interference : bool
        Whether the interference detector flags the field at this epoch.
    cal_state : str
        One of :data:`CAL_STATES`.
    """

    t: float
    q_wd: tuple[float, float, float, float]
    heading_deg: float
    heading_std_deg: float
    mag_used: bool
    interference: bool
    cal_state: str


@dataclass(frozen=True)
class Event:
    """Something that happened: ``interference_start``/``_end``, ``calibration_accepted``,
    ``calibration_rejected``, ``recalibration_requested``, ``recalibrated``, … with details in ``data``."""

    t: float
    kind: str
    data: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"t": float(self.t), "kind": self.kind, **self.data}


@dataclass
class EstimateBatch:
    """Columnar estimates for a run of epochs (N rows); the fast path for sinks and CSV.

    ``diag`` holds optional float columns named in :data:`DIAG_KEYS`.
    """

    t: np.ndarray
    q_wd: np.ndarray
    heading_deg: np.ndarray
    heading_std_deg: np.ndarray
    mag_used: np.ndarray
    interference: np.ndarray
    cal_state: np.ndarray
    diag: dict[str, np.ndarray] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.t)

    @classmethod
    def empty(cls) -> EstimateBatch:
        return cls(
            t=np.empty(0),
            q_wd=np.empty((0, 4)),
            heading_deg=np.empty(0),
            heading_std_deg=np.empty(0),
            mag_used=np.empty(0, dtype=bool),
            interference=np.empty(0, dtype=bool),
            cal_state=np.empty(0, dtype="<U13"),
        )

    @classmethod
    def concat(cls, batches: list[EstimateBatch]) -> EstimateBatch:
        batches = [b for b in batches if len(b)]
        if not batches:
            return cls.empty()
        keys = set().union(*(b.diag.keys() for b in batches))
        diag = {
            k: np.concatenate([b.diag[k] if k in b.diag else np.full(len(b), np.nan) for b in batches])
            for k in sorted(keys)
        }
        return cls(
            t=np.concatenate([b.t for b in batches]),
            q_wd=np.concatenate([b.q_wd for b in batches]),
            heading_deg=np.concatenate([b.heading_deg for b in batches]),
            heading_std_deg=np.concatenate([b.heading_std_deg for b in batches]),
            mag_used=np.concatenate([b.mag_used for b in batches]),
            interference=np.concatenate([b.interference for b in batches]),
            cal_state=np.concatenate([b.cal_state for b in batches]),
            diag=diag,
        )

    def head(self, n: int) -> EstimateBatch:
        """The first ``n`` rows (views)."""
        return EstimateBatch(
            t=self.t[:n],
            q_wd=self.q_wd[:n],
            heading_deg=self.heading_deg[:n],
            heading_std_deg=self.heading_std_deg[:n],
            mag_used=self.mag_used[:n],
            interference=self.interference[:n],
            cal_state=self.cal_state[:n],
            diag={k: v[:n] for k, v in self.diag.items()},
        )

    def rows(self):
        """Iterate as :class:`HeadingEstimate` objects (slow path, for the API's single-epoch users)."""
        for i in range(len(self.t)):
            yield HeadingEstimate(
                t=float(self.t[i]),
                q_wd=tuple(float(v) for v in self.q_wd[i]),
                heading_deg=float(self.heading_deg[i]),
                heading_std_deg=float(self.heading_std_deg[i]),
                mag_used=bool(self.mag_used[i]),
                interference=bool(self.interference[i]),
                cal_state=str(self.cal_state[i]),
            )


def diag_vectors(batch: EstimateBatch, columns: tuple[str, str, str]) -> np.ndarray | None:
    """Three diag columns of ``batch`` (x, y, z: :data:`pdr_mag.fusion.rows.GYRO_BIAS_COLUMNS`,
    :data:`~pdr_mag.fusion.rows.OFFSET_ERROR_COLUMNS`) as one N × 3 array; None when the batch lacks one."""
    cols = [batch.diag.get(c) for c in columns] if batch.diag else [None]
    if any(c is None for c in cols):
        return None
    return np.column_stack([np.asarray(c, dtype=float) for c in cols])
