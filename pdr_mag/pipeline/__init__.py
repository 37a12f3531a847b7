"""The heading pipeline: streaming samples in, calibrated and interference-aware heading out.

:mod:`~pdr_mag.pipeline.heading`
    :class:`HeadingPipeline` (the streaming state machine: merge → calibrate → fuse → online calibration
    → events);
:mod:`~pdr_mag.pipeline.settings`
    :class:`PipelineSettings`;
:mod:`~pdr_mag.pipeline.state`
    the pipeline's resumable state as JSON;
:mod:`~pdr_mag.pipeline.phone_heading`
    :func:`fill_unknown_heading`: the phone's own heading on the rows whose heading pdr_mag does not know;
:mod:`~pdr_mag.pipeline.streams`
    each stream's pending samples and their merge in time order;
:mod:`~pdr_mag.pipeline._kernel`
    the compiled helpers: the merge, the filter's input, the magnetometer context of the calibrator.

The filter it drives is :mod:`pdr_mag.fusion` (through its public API), the calibrator
:mod:`pdr_mag.calibration.online`.
"""

from pdr_mag.fusion.kinds import KINDS
from pdr_mag.pipeline.heading import HeadingPipeline
from pdr_mag.pipeline.phone_heading import fill_unknown_heading
from pdr_mag.pipeline.settings import PipelineSettings
from pdr_mag.pipeline.state import STATE_VERSION

__all__ = ["KINDS", "STATE_VERSION", "HeadingPipeline", "PipelineSettings", "fill_unknown_heading"]
