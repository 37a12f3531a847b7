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


#: The largest magnetometer latency :class:`PipelineSettings` takes, s: a sensor's filter delays its samples
#: by tens of milliseconds, a logger stamping on delivery by up to a few hundred; a second is another clock.
MAX_MAG_TIME_OFFSET_S = 1.0


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
    mag_time_offset_s : float
        The magnetometer's latency against the IMU, s: a magnetometer sample stamped t was measured at IMU
        time t − ``mag_time_offset_s`` (the simulator's and ``diagnose``'s ``time_offset``: a sensor's own
        filter delay, a logger stamping on delivery). The pipeline moves the magnetometer's stamps (and the
        phone's estimate changes, stamped on them) back by it. A field measured 30 ms before its stamp is
        turned by 30 ms of rotation: 3.4° at a swinging hand's 2 rad/s. At most ``MAX_MAG_TIME_OFFSET_S``
        either way.
    check_inputs : bool
        Judge each stream's unit on its first samples and the streams' clocks on their first sample times
        (:mod:`pdr_mag.units`), raising ``ValueError``.  ``replay`` turns it off: its readers judged the same
        rules on more samples (4096 a stream) and name the file.
    """

    block_s: float = 0.5
    max_lag_s: float = 1.0
    max_pending: int = 20000
    online: bool = True
    online_settings: OnlineSettings = field(default_factory=OnlineSettings)
    fusion: FusionSettings | None = None
    keep_mag_calibrated: bool = False
    prior: PriorSettings = field(default_factory=PriorSettings)
    mag_time_offset_s: float = 0.0
    check_inputs: bool = True

    def __post_init__(self):
        # a group of another class (a dict, say) would fail deep inside a run
        check_numbers(self, positive=("block_s", "max_lag_s", "max_pending"), signed=("mag_time_offset_s",))
        if abs(self.mag_time_offset_s) > MAX_MAG_TIME_OFFSET_S:
            raise ValueError(f"PipelineSettings.mag_time_offset_s: {self.mag_time_offset_s!r} s is beyond "
                             f"±{MAX_MAG_TIME_OFFSET_S} s (a clock problem, not a sensor's latency)")
