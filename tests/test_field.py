import numpy as np
import pytest

from pdr_mag.field import EarthField, decimal_year, earth_field, earth_field_from_meta


def test_wmm_grenoble_2016_matches_published_model_values():
    # WMM-2015v2 values for the tyrex site (Grenoble, 2016-05-31) as computed by NOAA's model: D 1.499°,
    # I 61.047°, F 47.064 µT (the dataset's own trial.json lists the same).
    f = earth_field(45.187778, 5.726945, 200.0, "2016-05-31")
    assert f.model == "WMM-2015v2" and not f.extrapolated
    assert f.declination_deg == pytest.approx(1.499, abs=0.005)
    assert f.inclination_deg == pytest.approx(61.047, abs=0.005)
    assert f.strength == pytest.approx(47.064, abs=0.01)
    v = f.field_w_array
    assert np.linalg.norm(v) == pytest.approx(f.strength, rel=1e-9)
    assert v[2] < 0  # northern hemisphere: field points down


def test_from_vector_inverts_angles():
    f = earth_field(-33.9, 151.2, 0.0, "2024-03-01")
    g = EarthField.from_vector(f.field_w)
    assert g.inclination_deg == pytest.approx(f.inclination_deg, abs=1e-9)
    assert g.declination_deg == pytest.approx(f.declination_deg, abs=1e-9)
    assert f.inclination_deg < 0  # southern hemisphere: field points up


def test_epoch_choice_and_bad_input():
    assert earth_field(0, 0, 0, "2026-11-21").model == "WMM-2025"
    assert earth_field(0, 0, 0, "2009-01-01").extrapolated
    assert decimal_year("2020-01-01") == pytest.approx(2020.0 + 0.5 / 366)
    with pytest.raises(ValueError, match="latitude_deg"):
        earth_field(91, 0, 0, "2020-01-01")
    with pytest.raises(ValueError, match="date"):
        earth_field(0, 0, 0, "31/05/2016")
    assert earth_field_from_meta({"device": "x"}) is None
