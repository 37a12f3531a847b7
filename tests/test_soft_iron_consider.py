"""The soft iron an offset-only fit cannot see: its first-order effect on the gravity-aided fit's offset, and
which fits hand it to the fusion filter."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pdr_mag.calibration.gravity import fit_model, gravity_aided_offset, soft_iron_offset_covariance
from pdr_mag.calibration.model import SHAPE_COVARIANCE, MagCalibration
from pdr_mag.calibration.online_settings import OnlineSettings
from pdr_mag.calibration.refit import gravity_fit_keeping_shape

F = 47.0
SIN_I = np.sin(np.radians(61.0))
FIELD_W = F * np.array([0.0, np.sqrt(1.0 - SIN_I**2), -SIN_I])
B = np.array([58.0, -74.0, 412.0])
#: the six elements of a symmetric L, in soft_iron_offset_covariance's order
PAIRS = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))


def _poses(tilt_deg: float, n: int = 240, seed: int = 4):
    """A walk's poses: yaw over 300°, tilt about the device's x axis with a little jitter; up in the device
    frame, and the Earth's field there (noise-free)."""
    rng = np.random.default_rng(seed)
    yaw = np.linspace(0.0, np.radians(300.0), n)
    rot = Rotation.from_euler("ZX", np.column_stack([yaw, np.radians(tilt_deg + rng.normal(0.0, 2.0, n))]))
    return rot.inv().apply([0.0, 0.0, 1.0]), rot.inv().apply(FIELD_W)


def _fit(m, u, s: OnlineSettings):
    return gravity_aided_offset(
        m, u, F, SIN_I, s.sigma_strength_uT, s.sigma_tilt_deg,
        prior_strength_std_uT=s.prior_strength_std_uT, prior_dip_std_deg=s.prior_dip_std_deg,
    )  # fmt: skip


@pytest.mark.parametrize("tilt_deg", [20.0, 50.0])
def test_the_fit_moves_with_the_soft_iron_as_its_sensitivity_says(tilt_deg):
    """Raw samples of a phone with soft iron ``A = I + ε E_k`` (``m = A⁻¹ h + b``), refitted: the offset's
    change over ε (central differences, ε = 1e-3: second-order terms ~1e-6 of the first) is the column k of
    D, and ``σ_L² D Dᵀ`` is what ``soft_iron_offset_covariance`` gives (within 1 %: the fit converges to
    1e-6 µT, 1e-3 of a column's µT per unit)."""
    s = OnlineSettings()
    u, h = _poses(tilt_deg)
    m0 = h + B
    cal = _fit(m0, u, s)
    np.testing.assert_allclose(cal.offset_array, B, atol=1e-4)  # noise-free: the fit is exact
    eps = 1e-3
    cols = []
    for i, j in PAIRS:
        e = np.zeros((3, 3))
        e[i, j] = e[j, i] = 1.0
        raw = [h @ np.linalg.inv(np.eye(3) + sgn * eps * e).T + B for sgn in (1, -1)]
        moved = [_fit(r, u, s).offset_array for r in raw]
        cols.append((moved[0] - moved[1]) / (2 * eps))
    d = np.column_stack(cols)
    model = fit_model(F, SIN_I, s.sigma_strength_uT, s.sigma_tilt_deg, s.prior_strength_std_uT,
                      s.prior_dip_std_deg)  # fmt: skip
    got = soft_iron_offset_covariance(m0, u, cal, model, 0.03)
    np.testing.assert_allclose(got, 0.03**2 * d @ d.T, rtol=0.01, atol=1e-3 * np.abs(got).max())


def test_held_flat_the_vertical_scale_moves_the_offset_along_up_by_the_vertical_field():
    """Yaw turns of a phone held flat: a vertical scale error ε makes the field's vertical component
    ``−F sin I / (1 + ε)``, which the dip equation reads as an offset ε F sin I along up (the prior on
    F sin I, 2.2 µT, does not take it: nothing else in a flat ring moves s); horizontally the ring's centre
    stays put."""
    s = OnlineSettings()
    u, h = _poses(0.0)
    base = _fit(h + B, u, s).offset_array
    e = np.diag([0.0, 0.0, 1e-3])
    moved = _fit(h @ np.linalg.inv(np.eye(3) + e).T + B, u, s).offset_array
    up = u.mean(axis=0) / np.linalg.norm(u.mean(axis=0))
    shift = (moved - base) / 1e-3
    assert shift @ up == pytest.approx(F * SIN_I, rel=0.1)  # µT per unit of L_zz
    assert np.linalg.norm(shift - (shift @ up) * up) < 0.1 * F * SIN_I


def test_only_a_fit_made_before_a_sure_one_carries_it():
    """The first fit of a walk (nothing in force, a prior, a fit above ``max_offset_std_uT``) hands the
    filter its covariance plus the unseen soft iron's; a refit replacing a sure offset-only fit hands its
    own, as does any fit that keeps a known shape; ``soft_iron_std`` 0 turns it off."""
    s = OnlineSettings()
    u, h = _poses(20.0)
    rng = np.random.default_rng(1)
    m = h + B + rng.normal(0.0, 0.4, h.shape)
    first = gravity_fit_keeping_shape(m, u, None, F, SIN_I, s)
    shape = np.asarray(first.extra[SHAPE_COVARIANCE])
    assert np.all(np.linalg.eigvalsh(shape) >= -1e-12) and np.trace(shape) > 0.1  # µT²: a few tenths at least
    np.testing.assert_allclose(first.offset_error_covariance, first.offset_covariance + shape, rtol=1e-12)
    prior = MagCalibration.from_arrays(B + 5.0, offset_std_uT=(6.0,) * 3, extra={"prior": "phone"})
    unsure = MagCalibration.from_arrays(B + 5.0, method="gravity", offset_std_uT=(5.0,) * 3)
    sure = MagCalibration.from_arrays(B, method="gravity", offset_std_uT=(1.0,) * 3)
    shaped = MagCalibration.from_arrays(B, np.diag([1.03, 0.98, 1.0]), method="ml", offset_std_uT=(0.3,) * 3)
    for current, carries in ((prior, True), (unsure, True), (sure, False), (shaped, False)):
        fit = gravity_fit_keeping_shape(m, u, current, F, SIN_I, s)
        assert (SHAPE_COVARIANCE in fit.extra) == carries, current
    off = gravity_fit_keeping_shape(m, u, None, F, SIN_I, OnlineSettings(soft_iron_std=0.0))
    assert SHAPE_COVARIANCE not in off.extra
    np.testing.assert_array_equal(off.offset_error_covariance, off.offset_covariance)
    np.testing.assert_array_equal(first.offset_covariance, off.offset_covariance)  # judged as before
