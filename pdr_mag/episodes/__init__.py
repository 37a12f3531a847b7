"""Drift episodes of a run: estimate rows + events (+ truth) → the stretches where the heading went wrong,
with the detectors that noticed them and how late.

:mod:`~pdr_mag.episodes.finder`
    :class:`EpisodeFinder` (streaming), :class:`Episode`, :class:`EpisodeSettings`, :func:`worst`; the
    definitions are in its docstring;
:mod:`~pdr_mag.episodes._kernel`
    the compiled row scan (stretches, gaps, detector changes).
"""

from pdr_mag.episodes.finder import DETECTORS, KINDS, Episode, EpisodeFinder, EpisodeSettings, worst

__all__ = ["DETECTORS", "KINDS", "Episode", "EpisodeFinder", "EpisodeSettings", "worst"]
