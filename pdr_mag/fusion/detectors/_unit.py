"""What every interference detector is made of, and the defaults of the parts a detector may leave out.

A detector is one module of :mod:`pdr_mag.fusion.detectors` with:

``NAME``
    its name: its settings' field in :class:`~pdr_mag.fusion.detectors.InterferenceSettings`, its state's
    field in :data:`~pdr_mag.fusion.detectors.DETECTOR_STATE`, its rerun entities;
``Settings``
    its thresholds, a frozen dataclass (the compiled record follows, :mod:`pdr_mag._records`);
``STATE``
    its state, a numpy record dtype with at least ``score`` (its latest score; ≥ 1 fails the check);
``ABSOLUTE``
    whether it compares the field with an absolute reference (then a first heading fix may trust a
    sample it passes while another detector flags it);
``LEARNT``
    the fields of its state learnt from the calibrated field (its local reference): a change of the
    calibration in force makes them stale, and they are learnt anew (:func:`~pdr_mag.fusion.detectors.
    forget_learnt`); ``()`` when it learns nothing;
``COLUMNS``, ``BAND``, ``PLOT``
    the diagnostic columns it writes (name → meaning), its band in them (:class:`Band`, or None) and how
    the rerun sink draws it (:class:`Plot`);
compiled steps (numba), each given the detectors' state ``det`` (the sample in ``det.x``) and settings ``ip``
    ``observe(det, ip)`` updates its running statistics and returns its score against the references'
    loose bands (all below 1: the sample is clean, the references are learnt from it);
    ``learn(det, a, ip)`` learns its local reference from a clean sample with weight ``a``;
    ``score(det, ip)`` returns its score (and keeps it in its ``score``);
    ``disturbance2(det, p)`` its part of ``d_min²``, the smallest disturbance that explains the deviations
    (µT², ``p`` the fusion's settings record);
    ``tolerance2(det)`` its tolerance as a disturbance (µT²);
    ``write(det, out, n, col)`` its diagnostic columns into row ``n`` of the output's float block ``out``
    (its column ``c`` is ``out[col.c, n]``, :data:`pdr_mag.fusion.rows.COL`);
    ``turn(det, ex, ey, ez)`` / ``restart(det)`` what a world-frame correction / a jump of the filter's
    attitude (a heading re-acquisition, a tilt reset) does to its state;
``example()``
    its known-answer case (:class:`Example`): a field it flags, run by ``tests/test_detectors.py``;
an array form
    its quantity for arrays, a numpy twin the tests compare with (e.g.
    :func:`~pdr_mag.fusion.detectors.dip.dip_deg`; for variance and consistency the score itself).

The parts a detector has no use for are these module's defaults (``learn = no_learn``).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit


class Band(NamedTuple):
    """A detector's band in its diagnostic columns: ``value`` against ``reference ± tolerance``; ``unit``
    names the band's columns in the MCAP (``<detector>_lower_<unit>``)."""

    value: str
    reference: str
    tolerance: str
    unit: str


class Plot(NamedTuple):
    """How the rerun sink draws a detector: its diagnostic column ``column`` as entity ``<group>/<leaf>``
    (named ``label``, in ``colour``), with its band when it has one (``<group>/reference``, ``lower``,
    ``upper``), in a view titled ``title``; ``main``: in the left column (with the heading), else a tab on
    the right."""

    group: str
    leaf: str
    column: str
    label: str
    colour: str
    title: str
    main: bool


class Example(NamedTuple):
    """A known-answer case: world-frame field samples ``m_w`` (N, 3, µT) at times ``t`` (s) seen by a
    correctly tilted filter (the dip follows from them), the references ``f_ref`` (µT) and ``dip_ref``
    (deg); the detector's score is ≥ 1 on every sample in ``[t_on, t_off)`` and no detector flags a sample
    before ``t_clean``."""

    t: np.ndarray
    m_w: np.ndarray
    f_ref: float
    dip_ref: float
    t_on: float
    t_off: float
    t_clean: float


@njit(cache=True, error_model="numpy")
def no_learn(det, a, ip):
    """No local reference to learn."""


@njit(cache=True, error_model="numpy")
def no_disturbance2(det, p):
    """No part in the smallest disturbance."""
    return 0.0


@njit(cache=True, error_model="numpy")
def no_tolerance2(det):
    """No tolerance that stands for a disturbance."""
    return 0.0


@njit(cache=True, error_model="numpy")
def no_turn(det, ex, ey, ez):
    """No world-frame quantity to turn."""


@njit(cache=True, error_model="numpy")
def no_restart(det):
    """Nothing to restart on a jump of the attitude."""


def field_example(t: np.ndarray, strength: np.ndarray, dip_deg: np.ndarray, azimuth_deg: np.ndarray):
    """World-frame field samples of the given strength (µT), dip (deg, below the horizon) and azimuth
    (deg, clockwise from north) at times ``t``: the raw material of the examples."""
    dip = np.radians(dip_deg)
    az = np.radians(azimuth_deg)
    h = strength * np.cos(dip)
    return np.column_stack([h * np.sin(az), h * np.cos(az), -strength * np.sin(dip)])
