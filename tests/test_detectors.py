"""Every registered interference detector (pdr_mag.fusion.detectors.DETECTORS) on its own known-answer
example: it flags the field its module says it flags, and nothing flags the clean field before it.  A new
detector is tested here by being registered."""

from __future__ import annotations

import numpy as np
import pytest

from pdr_mag._records import settings_record
from pdr_mag.estimates import DIAG_KEYS
from pdr_mag.fusion.detectors import (
    DETECTOR_STATE,
    DETECTORS,
    InterferenceSettings,
    detect_step,
    new_detector_state,
)
from pdr_mag.fusion.rows import DIAG_COLUMNS, FLOAT_COLUMNS, INTERNAL_DIAG


def _run(unit):
    """The detectors over the unit's example: (its score, the largest score, the flag) per sample."""
    ex = unit.example()
    det = new_detector_state()
    ip = settings_record(InterferenceSettings())[0]
    f = np.linalg.norm(ex.m_w, axis=1)
    u = ex.m_w / f[:, None]
    dip = np.degrees(np.arcsin(-u[:, 2]))  # a correctly tilted filter sees the world-frame dip
    out = np.empty((len(ex.t), 3))
    for i in range(len(ex.t)):
        x = det["x"]
        x["t"], x["f"], x["dip"], x["mw"] = ex.t[i], f[i], dip[i], u[i]
        x["f_ref"], x["dip_ref"], x["sigma_b_deg"] = ex.f_ref, ex.dip_ref, 0.0
        flag = detect_step(det, ip)
        out[i] = det[unit.NAME]["score"], det["score"], flag
    return ex, out


@pytest.mark.parametrize("unit", DETECTORS, ids=lambda u: u.NAME)
def test_each_detector_flags_its_example(unit):
    ex, out = _run(unit)
    on = (ex.t >= ex.t_on) & (ex.t < ex.t_off)
    assert on.sum() >= 25  # at least half a second of samples
    assert np.all(out[on, 0] >= 1.0), f"{unit.NAME}: below 1 on {np.mean(out[on, 0] < 1.0):.0%} of the span"
    assert np.all(out[on, 2] == 1.0)  # the flag is up (hold_on_s = 0)
    clean = ex.t < ex.t_clean
    assert np.all(out[clean, 1] < 1.0) and not np.any(out[clean, 2])


@pytest.mark.parametrize("unit", DETECTORS, ids=lambda u: u.NAME)
def test_each_detector_reaches_settings_state_and_outputs(unit):
    """Its settings are a field of InterferenceSettings (and of the compiled record), its state a field of
    DETECTOR_STATE, its columns are output rows' fields and diagnostic keys (or internal ones)."""
    assert isinstance(getattr(InterferenceSettings(), unit.NAME), unit.Settings)
    assert unit.NAME in settings_record(InterferenceSettings()).dtype.names
    assert DETECTOR_STATE[unit.NAME] == unit.STATE
    for column, meaning in unit.COLUMNS.items():
        assert column in FLOAT_COLUMNS and DIAG_COLUMNS[column] == meaning
        assert column in DIAG_KEYS or column in INTERNAL_DIAG
    if unit.BAND is not None:
        assert set(unit.BAND[:3]) <= set(unit.COLUMNS)
    assert unit.PLOT.group not in {d.PLOT.group for d in DETECTORS if d is not unit}


def test_a_number_where_a_group_of_settings_belongs_is_refused():
    """A detector's settings group given as a number would be spread over every field of its record: it is
    refused by name, as a wrong group of the filter's settings is."""
    from pdr_mag.fusion.detectors import InterferenceSettings
    from pdr_mag.fusion.settings import FusionSettings

    with pytest.raises(ValueError, match="InterferenceSettings.strength: expected a StrengthSettings"):
        InterferenceSettings(strength=5.0)
    with pytest.raises(ValueError, match="FusionSettings.gyro: expected a GyroSettings"):
        FusionSettings(gyro=3)
