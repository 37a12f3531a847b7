"""Named phones: the hardware (:class:`~pdr_mag.sim.sensor_model.PhoneSpec`) and its own magnetisation.

A phone here is what differs between handsets of the tyrex recordings (``../shared/datasets``) beyond the
scenario: sample rates, the accelerometer's full scale — ±2 g on the iPhone 4S and the Nexus 5, so a run
clips it many times a second (``accel_range``: samples saturate at the limit,
:func:`~pdr_mag.sim.sensor_model.digitise`) — and a hard-iron offset of the size those phones have (the day's
``pdr-mag calibrate`` fits: iPhone 4S ≈ (85, 205, −550) µT, |b| ≈ 593 µT, twelve times the Earth's field;
Nexus 5 ≈ (58, −74, 412) µT).  ``effects`` are the phone's defaults on top of the scenario's (an
``--effect`` still overrides them).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from pdr_mag.conventions import GRAVITY
from pdr_mag.sim.sensor_model import PhoneSpec

#: ±2 g, m/s² (an accelerometer's full scale is set in units of standard gravity)
TWO_G = 2.0 * GRAVITY


@dataclass(frozen=True)
class Phone:
    """A named phone: its sensors' hardware and its own default effects."""

    name: str
    description: str
    spec: PhoneSpec
    effects: dict = field(default_factory=dict)


PHONES: dict[str, Phone] = {
    p.name: p
    for p in (
        Phone("default", "a typical phone: 100/100/50 Hz, ±8 g accelerometer", PhoneSpec()),
        Phone(
            "iphone4s",
            "iPhone 4S-like: accel/gyro/mag 90/108/38 Hz, ±2 g accelerometer (clips when running), "
            "hard iron (85, 205, −550) µT (|b| ≈ 593 µT)",
            PhoneSpec(accel_rate_hz=90.0, gyro_rate_hz=108.0, mag_rate_hz=38.0, accel_range=TWO_G,
                      accel_step=0.00098),
            {"hard_iron": (85.0, 205.0, -550.0)},
        ),
        Phone(
            "nexus5",
            "Nexus 5-like: 200/200/50 Hz, ±2 g accelerometer, hard iron (58, −74, 412) µT (|b| ≈ 422 µT)",
            PhoneSpec(accel_rate_hz=200.0, gyro_rate_hz=200.0, mag_rate_hz=50.0, accel_range=TWO_G),
            {"hard_iron": (58.0, -74.0, 412.0)},
        ),
    )
}
