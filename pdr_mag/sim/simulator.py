"""``simulate()``: a scenario's trajectory through the sensor model into phone-like sample streams.

Random streams are independent children of ``SeedSequence(seed)`` (trajectory, steel layout, the three
sample clocks, the three noises, the building's field), so switching an effect on or off changes nothing
else: the trajectory, the sample times and the noise draws stay the same.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass

import numpy as np

from pdr_mag.field import EarthField, earth_field
from pdr_mag.sim.building import BuildingField, FieldSum
from pdr_mag.sim.phones import PHONES, Phone
from pdr_mag.sim.sampling import sample_times
from pdr_mag.sim.scenarios import DEFAULT_EFFECTS, SCENARIOS, Plan, layout_dipoles
from pdr_mag.sim.sensor_model import (
    EFFECTS,
    PhoneSpec,
    SensorModel,
    measure_accel,
    measure_gyro,
    measure_mag,
)
from pdr_mag.sim.trajectory import Trajectory

#: Where the simulated phone is (Zürich) and when: sets the WMM field of the simulation.
DEFAULT_SITE = {"latitude_deg": 47.3769, "longitude_deg": 8.5417, "altitude_m": 410.0, "date": "2026-06-15"}


@dataclass(frozen=True, eq=False)
class SimResult:
    """A simulated recording with its truth and the exact model that made it.

    Streams are ``(t (N,), xyz (N, 3))`` in the contract's units and device frame; ``truth`` is
    ``(t, q_wd)`` (w-first, device → ENU true north), ``truth_position`` ``(t, p_w)`` (m, ENU, walker at
    the origin at t = 0).
    """

    scenario: str
    seed: int
    duration_s: float
    accel: tuple[np.ndarray, np.ndarray]
    gyro: tuple[np.ndarray, np.ndarray]
    mag: tuple[np.ndarray, np.ndarray]
    truth: tuple[np.ndarray, np.ndarray]
    truth_position: tuple[np.ndarray, np.ndarray]
    model: SensorModel
    phone: PhoneSpec
    field: EarthField
    plan: Plan
    meta: dict

    @property
    def trajectory(self) -> Trajectory:
        return self.plan.trajectory

    @property
    def n_samples(self) -> int:
        return len(self.accel[0]) + len(self.gyro[0]) + len(self.mag[0])


def resolve_effects(
    scenario: str, overrides: Mapping[str, object] | None = None, defaults: bool = True
) -> dict[str, object]:
    """The scenario's default effects updated with ``overrides`` (a value of None switches one off)."""
    if scenario not in SCENARIOS:
        raise ValueError(f"scenario: unknown {scenario!r}; known: {', '.join(SCENARIOS)}")
    eff: dict[str, object] = {}
    if defaults:
        eff.update(DEFAULT_EFFECTS)
        eff.update(SCENARIOS[scenario].default_effects)
    for k, v in (overrides or {}).items():
        if k not in EFFECTS:
            raise ValueError(f"unknown effect {k!r}; known: {', '.join(EFFECTS)}")
        eff[k] = v
    return {k: v for k, v in eff.items() if v is not None}


def _json_safe(x):
    if isinstance(x, float) and not np.isfinite(x):
        return None
    return x


#: |local anomaly| above which a time counts as inside an anomaly window, µT.
ANOMALY_THRESHOLD_UT = 1.0


def _anomaly_windows(anomaly, traj: Trajectory, duration: float) -> list[dict]:
    """Time intervals (10 Hz grid) where the local anomaly at the phone (a field object; None: none)
    exceeds ANOMALY_THRESHOLD_UT, with the peak |B| in each."""
    if anomaly is None:
        return []
    t = np.arange(0.0, duration + 1e-9, 0.1)
    b = np.linalg.norm(anomaly.field_w(traj.position(t)), axis=1)
    inside = np.concatenate([[False], b > ANOMALY_THRESHOLD_UT, [False]])
    edges = np.flatnonzero(np.diff(inside.astype(int)))
    out = []
    for i0, i1 in zip(edges[::2], edges[1::2], strict=True):
        out.append(
            {
                "t0": round(float(t[i0]), 3),
                "t1": round(float(t[i1 - 1]), 3),
                "peak_uT": round(float(b[i0:i1].max()), 3),
            }
        )
    return out


def simulate(
    scenario: str,
    seed: int = 0,
    duration_s: float | None = None,
    effects: Mapping[str, object] | None = None,
    defaults: bool = True,
    phone: PhoneSpec | Phone | str | None = None,
    site: Mapping[str, object] | None = None,
    field_w=None,
    truth_rate_hz: float = 25.0,
    building: tuple[float, float] | None = None,
) -> SimResult:
    """Simulate a phone recording.

    Parameters
    ----------
    scenario : str
        A name of :data:`~pdr_mag.sim.scenarios.SCENARIOS`.
    seed : int
        Seed of every random choice; same seed, same result (bit for bit).
    duration_s : float, optional
        Length, s (the scenario's default when omitted).
    effects : mapping, optional
        Effect overrides on top of the defaults (:data:`~pdr_mag.sim.sensor_model.EFFECTS` names; None = off).
        ``local_anomaly`` may be a peak strength in µT (laid out as dipoles by the scenario) or a field
        object.
    defaults : bool
        Start from the documented default effects (True) or from none.
    phone : PhoneSpec, Phone or str, optional
        Rates, noise, resolution, ranges, drops (:class:`PhoneSpec` defaults); or a named
        :class:`~pdr_mag.sim.phones.Phone` (or its name in :data:`~pdr_mag.sim.phones.PHONES`): its
        hardware, and its own effects (e.g. the hard iron) under ``effects``.
    site : mapping, optional
        ``latitude_deg``, ``longitude_deg``, ``altitude_m``, ``date`` of the WMM field (:data:`DEFAULT_SITE`).
    field_w : array-like (3,), optional
        A plain ENU field vector, µT, overriding the WMM; ``meta`` then carries no site (position and date
        would imply another field) and north is the world +y axis.
    truth_rate_hz : float
        Rate of the (uniform) truth samples.
    building : (rms_uT, length_m), optional
        A building's own field everywhere along the walk (:class:`~pdr_mag.sim.building.BuildingField`:
        horizontal RMS µT at 1 m above the floor, correlation length m), added to ``local_anomaly``'s steel;
        ``meta["simulation"]["anomaly_windows"]`` stay the steel's.
    """
    if scenario not in SCENARIOS:
        raise ValueError(f"scenario: unknown {scenario!r}; known: {', '.join(SCENARIOS)}")
    sc = SCENARIOS[scenario]
    duration = float(sc.default_duration_s if duration_s is None else duration_s)
    if not (np.isfinite(duration) and 1.0 <= duration <= 86400.0):
        raise ValueError(f"duration_s: expected 1..86400 s, got {duration_s!r}")
    if not (isinstance(seed, int | np.integer) and seed >= 0):
        raise ValueError(f"seed: expected an integer ≥ 0, got {seed!r}")
    phone_name = None
    if isinstance(phone, str):
        if phone not in PHONES:
            raise ValueError(f"phone: unknown {phone!r}; known: {', '.join(PHONES)}")
        phone = PHONES[phone]
    if isinstance(phone, Phone):
        phone_name, phone, effects = phone.name, phone.spec, {**phone.effects, **(effects or {})}
    phone = phone or PhoneSpec()
    site = dict(DEFAULT_SITE if site is None else site)
    rngs = [np.random.default_rng(s) for s in np.random.SeedSequence(int(seed)).spawn(9)]
    r_traj, r_steel, r_ta, r_tg, r_tm, r_na, r_ng, r_nm, r_building = rngs

    plan = sc.build(duration, r_traj)
    traj = plan.trajectory
    eff = resolve_effects(scenario, effects, defaults)
    anomaly_layout = None
    if "local_anomaly" in eff and not hasattr(eff["local_anomaly"], "field_w"):
        peak = float(np.asarray(eff["local_anomaly"], dtype=float).reshape(-1)[0])
        anomaly_layout = layout_dipoles(plan, peak, r_steel)
        eff["local_anomaly"] = anomaly_layout
    steel = eff.get("local_anomaly")
    if building is not None:
        rms, length = (float(v) for v in building)
        own = BuildingField.random(rms, length, r_building)
        eff["local_anomaly"] = own if steel is None else FieldSum((steel, own))
    model = SensorModel(eff)

    if field_w is not None:
        fld = EarthField.from_vector(field_w)
    else:
        fld = earth_field(
            site["latitude_deg"], site["longitude_deg"], site.get("altitude_m", 0.0), site["date"]
        )

    def times(rate: float, jitter: float, rng: np.random.Generator) -> np.ndarray:
        return sample_times(
            rate, duration, rng, phone.rate_error, jitter, phone.drop_prob, phone.gap_rate_hz, phone.gap_max_s
        )

    t_acc = times(phone.accel_rate_hz, phone.imu_jitter_s, r_ta)
    t_gyr = times(phone.gyro_rate_hz, phone.imu_jitter_s, r_tg)
    tau_mag = times(phone.mag_rate_hz, phone.mag_jitter_s, r_tm)
    t_mag = tau_mag + float(model.value("time_offset"))
    t_mag = t_mag[(t_mag >= 0.0) & (t_mag <= duration)]

    q_acc = traj.orientation(t_acc)
    accel = measure_accel(q_acc, traj.accel_w(t_acc), r_na, phone)
    gyro = measure_gyro(model, traj.omega_d(t_gyr), r_ng, phone)
    mag = measure_mag(model, t_mag, traj, fld, r_nm, phone)

    t_truth = np.arange(0.0, duration + 1e-9, 1.0 / truth_rate_hz)
    q_truth = traj.orientation(t_truth)
    q_truth = q_truth * np.where(q_truth[:, :1] < 0, -1.0, 1.0)
    p_truth = traj.position(t_truth)

    sim_meta = {
        "scenario": scenario,
        "seed": int(seed),
        "duration_s": duration,
        "effects": model.to_json(),
        "t_ref": model.t_ref,
        "field_w_uT": [round(v, 6) for v in fld.field_w],
        "field_model": fld.model,
        "declination_deg": round(fld.declination_deg, 6),
        "inclination_deg": round(fld.inclination_deg, 6),
        "phone": {k: _json_safe(v) for k, v in asdict(phone).items()},
        **({"phone_name": phone_name} if phone_name else {}),
        "segments": [{"mode": m, "t0": a, "t1": b} for m, a, b in plan.segments],
        "steel_windows": [{"t0": a, "t1": b} for a, b in plan.anomaly_windows] if anomaly_layout else [],
        "anomaly_windows": _anomaly_windows(steel, traj, duration),
        "north": "true",
    }
    if building is not None:
        sim_meta["building"] = {"rms_uT": rms, "length_m": length}
    meta = {"device": "simulated phone (pdr-mag simulate)"}
    if field_w is None:  # with a plain field vector the site would imply a different (WMM) field: left out
        meta.update(
            latitude_deg=site["latitude_deg"],
            longitude_deg=site["longitude_deg"],
            altitude_m=site.get("altitude_m", 0.0),
            date=site["date"],
        )
    meta["simulation"] = sim_meta
    return SimResult(
        scenario=scenario,
        seed=int(seed),
        duration_s=duration,
        accel=(t_acc, accel),
        gyro=(t_gyr, gyro),
        mag=(t_mag, mag),
        truth=(t_truth, q_truth),
        truth_position=(t_truth, p_truth),
        model=model,
        phone=phone,
        field=fld,
        plan=plan,
        meta=meta,
    )
