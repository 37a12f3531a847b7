"""A building's own field in the simulator: a magnetic field (no curl, no divergence), of the RMS and
correlation length asked for, seeded, serialisable, and added to a simulation without changing anything
else."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pdr_mag.sim import simulate
from pdr_mag.sim.building import BuildingField, FieldSum, field_from_json
from pdr_mag.sim.effects import DipoleField
from pdr_mag.sim.sensor_model import SensorModel
from replay.cli import main
from replay.formats import pdrcsv

#: buildings averaged over for the ensemble's statistics
N_BUILDINGS = 60


def _ensemble(rms, length, positions):
    """The field of N_BUILDINGS random buildings at ``positions``: (N_BUILDINGS, N, 3)."""
    rngs = [np.random.default_rng(s) for s in range(N_BUILDINGS)]
    return np.stack([BuildingField.random(rms, length, r).field_w(positions) for r in rngs])


def test_the_field_is_free_of_curl_and_divergence():
    """B = −∇Φ with Φ harmonic: the Jacobian of B is symmetric and traceless (central differences, h = 1 mm:
    truncation ~ h² |∇³B| ≈ 1e-6 of the gradient for L = 2 m)."""
    f = BuildingField.random(2.0, 2.0, np.random.default_rng(4))
    rng = np.random.default_rng(5)
    p = np.column_stack([rng.uniform(-30, 30, 200), rng.uniform(-30, 30, 200), rng.uniform(0.3, 2.5, 200)])
    h = 1e-3
    jac = np.stack([(f.field_w(p + h * e) - f.field_w(p - h * e)) / (2 * h) for e in np.eye(3)], axis=2)
    scale = np.abs(jac).max()
    assert scale > 0.1  # µT/m: a field that varies over metres
    assert np.abs(np.trace(jac, axis1=1, axis2=2)).max() < 1e-5 * scale
    assert np.abs(jac - jac.transpose(0, 2, 1)).max() < 1e-5 * scale


def test_rms_and_correlation_length_as_asked():
    """Over an ensemble of buildings, at the reference height: each horizontal component has the RMS asked
    for, the vertical √2 of it (half of each mode's energy is vertical); along a line the field decorrelates
    over about L.  Tolerances: 60 buildings × 400 points far apart (≥ 10 L) leave the RMS good to ~1.5 %
    (3σ ≈ 5 %)."""
    rms, length = 1.5, 3.0
    far = np.arange(20) * 10 * length
    grid = np.stack(np.meshgrid(far, far), axis=-1).reshape(-1, 2)
    b = _ensemble(rms, length, np.column_stack([grid, np.full(len(grid), 1.0)]))
    got = np.sqrt(np.mean(b**2, axis=(0, 1)))
    np.testing.assert_allclose(got[:2], rms, rtol=0.05)
    np.testing.assert_allclose(got[2], np.sqrt(2) * rms, rtol=0.05)
    # 20 parallel lines 20 L apart in each building: 1 200 pairs a lag, the correlation good to ~0.03
    x = np.arange(0.0, 12.0 * length, 0.25 * length)
    y = np.repeat(np.arange(20) * 20 * length, len(x))
    line = _ensemble(rms, length, np.column_stack([np.tile(x, 20), y, np.ones_like(y)]))
    line = line.reshape(N_BUILDINGS, 20, len(x), 3).reshape(-1, len(x), 3)
    corr = [np.mean(np.sum(line[:, 0] * line[:, k], axis=-1)) / np.mean(np.sum(line[:, 0] ** 2, axis=-1))
            for k in range(len(x))]  # fmt: skip
    assert corr[1] > 0.8  # a quarter of L apart: nearly the same field
    assert corr[8] < 0.5  # 2 L apart: mostly another
    assert np.all(np.abs(corr[-8:]) < 0.1)  # 10 L and more apart: independent


def test_the_field_weakens_away_from_its_sources():
    """A building whose sources are all below the floor: its field at 2 m is weaker than at 1 m (each mode
    decays as exp(−|κ| Δz)); at the reference height the RMS is the one asked for."""
    f = BuildingField.random(1.0, 2.0, np.random.default_rng(7))
    below = BuildingField(f.wavevectors, f.phases, np.ones_like(f.sides), f.amplitudes, f.z0_m)
    rng = np.random.default_rng(8)
    xy = rng.uniform(-500, 500, (4000, 2))
    at = [np.sqrt(np.mean(below.field_w(np.column_stack([xy, np.full(len(xy), z)])) ** 2))
          for z in (1.0, 2.0)]  # fmt: skip
    assert at[1] < 0.8 * at[0]


def test_seeded_serialised_and_summed():
    a = BuildingField.random(1.2, 3.0, np.random.default_rng(11))
    b = BuildingField.random(1.2, 3.0, np.random.default_rng(11))
    p = np.random.default_rng(1).uniform(-20, 20, (50, 3))
    np.testing.assert_array_equal(a.field_w(p), b.field_w(p))
    dip = DipoleField([[0.0, 0.0, -1.0]], [[0.0, 3.0, 1.0]])
    both = FieldSum((dip, a))
    np.testing.assert_allclose(both.field_w(p), dip.field_w(p) + a.field_w(p), rtol=0, atol=1e-12)
    for field in (a, both):
        back = field_from_json(json.loads(json.dumps(field.to_json())))
        np.testing.assert_array_equal(back.field_w(p), field.field_w(p))
        model = SensorModel.from_json(json.loads(json.dumps(SensorModel({"local_anomaly": field}).to_json())))
        np.testing.assert_array_equal(model.value("local_anomaly").field_w(p), field.field_w(p))
    with pytest.raises(ValueError, match="rms_uT"):
        BuildingField.random(-1.0, 3.0, np.random.default_rng(0))
    with pytest.raises(ValueError, match="length_m"):
        BuildingField.random(1.0, 0.0, np.random.default_rng(0))
    with pytest.raises(ValueError, match="sides"):
        BuildingField(a.wavevectors, a.phases, 0.5 * a.sides, a.amplitudes)
    with pytest.raises(ValueError, match="unknown field kind"):
        field_from_json({"kind": "magnet"})


def test_a_simulation_in_a_building_changes_the_field_only():
    """The building has a random stream of its own: the trajectory, the sample clocks, the noises, the
    steel and its windows are those of the same simulation without it; the magnetometer differs by the
    building's field at the phone, seen in device axes through the phone's soft iron."""
    plain = simulate("mixed", seed=3, duration_s=90.0)
    inside = simulate("mixed", seed=3, duration_s=90.0, building=(1.5, 3.0))
    for s in ("accel", "gyro"):
        np.testing.assert_array_equal(getattr(plain, s)[1], getattr(inside, s)[1])
    np.testing.assert_array_equal(plain.mag[0], inside.mag[0])
    assert plain.meta["simulation"]["anomaly_windows"] == inside.meta["simulation"]["anomaly_windows"]
    assert plain.meta["simulation"]["anomaly_windows"]  # the scenario's steel is still there
    assert inside.meta["simulation"]["building"] == {"rms_uT": 1.5, "length_m": 3.0}
    assert "building" not in plain.meta["simulation"]
    diff = inside.mag[1] - plain.mag[1]
    rms = np.sqrt(np.mean(np.sum(diff**2, axis=1)))
    assert 0.5 < rms < 6.0  # µT: a building of 1.5 µT per horizontal axis (2.1 vertical) seen along the walk


def test_cli_building_option(tmp_path, capsys):
    out = tmp_path / "rec"
    assert main(["simulate", "--scenario", "walk", "--seed", "2", "--duration", "30", "--out", str(out),
                 "--building", "1.2"]) == 0  # fmt: skip
    rec = pdrcsv.read(out)
    assert rec.meta["simulation"]["building"] == {"rms_uT": 1.2, "length_m": 3.0}
    assert rec.meta["simulation"]["effects"]["local_anomaly"]["kind"] == "building"
    capsys.readouterr()
    bad = ["simulate", "--scenario", "walk", "--out", str(tmp_path / "bad"), "--building", "1,-2"]
    assert main(bad) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--building" in err[0]
