"""Settings of :class:`pdr_mag.pipeline.HeadingPipeline`, and the fusion settings a recording's metadata
completes."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

from pdr_mag._records import check_numbers, default_settings
from pdr_mag.calibration.online import OnlineSettings
from pdr_mag.calibration.prior import PriorSettings
from pdr_mag.fusion import FusionSettings


def fusion_settings(settings, meta: dict):
    """The fusion settings (defaults when None), with the accelerometer range the recording states
    (``meta["accel_range_m_s2"]``, per axis) unless the settings give one."""
    settings = settings or default_settings(FusionSettings)
    rng = meta.get("accel_range_m_s2")
    if settings.accel.range == 0.0 and rng is not None:
        if not (isinstance(rng, int | float) and math.isfinite(rng) and rng > 0):
            raise ValueError(f"meta: accel_range_m_s2: expected a positive number of m/s², got {rng!r}")
        settings = replace(settings, accel=replace(settings.accel, range=float(rng)))
    return settings


@dataclass(frozen=True)
class PipelineSettings:
    """Settings of :class:`HeadingPipeline`.

    Attributes
    ----------
    block_s : float
        Calibration block length, s: the online calibration may change at each block boundary (the
        output latency does not depend on it: samples are fused as soon as every stream has passed them).
    max_lag_s : float
        :meth:`HeadingPipeline.poll` does not wait for a stream more than this behind the newest sample, s.
    max_pending : int
        ``push`` processes what it safely can once this many samples are pending.
    online : bool
        Run the online calibrator (refits, stale test, recalibration).  False: the given calibration only.
    online_settings : OnlineSettings
        Its settings.
    fusion : FusionSettings or None
        Settings of :class:`pdr_mag.fusion.FusionCore` (None: its defaults).
    keep_mag_calibrated : bool
        Keep the calibrated magnetometer samples for :meth:`HeadingPipeline.pop_mag_calibrated` (sinks).
    prior : PriorSettings
        What is taken from the phone's own estimates in the metadata and how sure they are
        (:mod:`pdr_mag.calibration.prior`).
    """

    block_s: float = 0.5
    max_lag_s: float = 1.0
    max_pending: int = 20000
    online: bool = True
    online_settings: OnlineSettings = field(default_factory=OnlineSettings)
    fusion: FusionSettings | None = None
    keep_mag_calibrated: bool = False
    prior: PriorSettings = field(default_factory=PriorSettings)

    def __post_init__(self):
        # a group of another class (a dict, say) would fail deep inside a run
        check_numbers(self, positive=("block_s", "max_lag_s", "max_pending"))
