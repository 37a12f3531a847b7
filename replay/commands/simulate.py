"""``pdr-mag simulate``: write a simulated pdr-csv recording (+ truth.csv, truth_position.csv).

    pdr-mag simulate --scenario NAME --seed N --out DIR [--effect NAME=VALUE ...] [--duration S]
    pdr-mag simulate --list

Options beyond the contract: ``--phone NAME`` (a named phone of ``--list``: rates, accelerometer range,
its own hard iron), ``--imu-rate``/``--mag-rate`` (Hz), the site (``--latitude``, ``--longitude``,
``--altitude``, ``--date``) or a plain ``--field E,N,U`` (µT) instead of the WMM, and ``--building
RMS[,LENGTH]``: a building's own weak field everywhere along the walk (:class:`pdr_mag.sim.building.
BuildingField`), on top of the scenario's steel.

Effect values: a number, comma-separated numbers, or ``off`` (see ``--list``).  The same arguments give
byte-identical files.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import click
import numpy as np

from pdr_mag.field import EarthField, decimal_year
from pdr_mag.sim import DEFAULT_EFFECTS, DEFAULT_SITE, PHONES, SCENARIOS, simulate
from pdr_mag.sim.sensor_model import EFFECTS, PhoneSpec, parse_effect_value
from replay.commands._output import writable_dir
from replay.errors import InputError
from replay.formats import pdrcsv
from replay.recording import Recording, Stream

#: Correlation length of ``--building``'s field when not given, m: what the tyrex room shows
#: (benchmarks/NOTES.md, "A building's own field").
BUILDING_LENGTH_M = 3.0

#: Value format of mag.csv and accel.csv (0.1 mµT / 0.1 mm/s² — finer than the sensors' resolution).
VALUE_FMT = "%.4f"


def _fmt_default(v) -> str:
    a = np.asarray(v, dtype=float)
    return ",".join(f"{x:g}" for x in a.reshape(-1))


def _listing() -> str:
    """``--list``: the scenarios, effects and phones, each table's columns as wide as its longest entry."""
    scenarios = [
        (s.name, f"{s.default_duration_s:.0f} s",
         s.description + "".join(f"; default {k}={_fmt_default(v)}" for k, v in s.default_effects.items()))
        for s in SCENARIOS.values()
    ]
    effects = []
    for e in EFFECTS.values():
        d = DEFAULT_EFFECTS.get(e.name)
        dflt = f"  [default {_fmt_default(d)}]" if d is not None else ""
        effects.append((e.name, e.unit, f"{e.description}; values: {e.cli}{dflt}"))
    ph = PhoneSpec()
    lines = ["scenarios:", *_columns(scenarios, right=(1,)), "effects (NAME=VALUE, NAME=off):",
             *_columns(effects)]
    lines.append(
        f"phone: accel/gyro {ph.accel_rate_hz:g} Hz, mag {ph.mag_rate_hz:g} Hz (own jittered clocks, "
        f"{ph.drop_prob:.1%} dropped, gaps), noise accel {ph.accel_noise:g} m/s² "
        f"gyro {ph.gyro_noise:g} rad/s, "
        f"resolution {ph.accel_step:g} m/s² {ph.gyro_step:g} rad/s {ph.mag_step:g} µT, "
        f"range ±{ph.accel_range:g} m/s² ±{ph.gyro_range:g} rad/s ±{ph.mag_range:g} µT"
    )
    lines.append("phones (--phone NAME; its effects are defaults under --effect):")
    lines.extend(_columns([(p.name, p.description) for p in PHONES.values()]))
    lines.append(
        f"site: lat {DEFAULT_SITE['latitude_deg']}, lon {DEFAULT_SITE['longitude_deg']}, "
        f"{DEFAULT_SITE['date']} (WMM field; truth is device→ENU, true north)"
    )
    return "\n".join(lines)


def _columns(rows: list[tuple[str, ...]], right: tuple[int, ...] = ()) -> list[str]:
    """Rows of cells as indented lines, every column but the last padded to its widest cell (the columns in
    ``right`` aligned right), so that each column starts at the same place on every line."""
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]) - 1)]
    lines = []
    for r in rows:
        padded = zip(r[:-1], widths, strict=True)
        cells = [c.rjust(w) if i in right else c.ljust(w) for i, (c, w) in enumerate(padded)]
        lines.append("  " + "  ".join([*cells, r[-1]]))
    return lines


def _parse_building(text: str) -> tuple[float, float]:
    """``--building RMS[,LENGTH]``: (µT ≥ 0, m > 0), the length :data:`BUILDING_LENGTH_M` when omitted."""
    try:
        vals = [float(x) for x in text.split(",")]
    except ValueError:
        vals = []
    if len(vals) == 1:
        vals.append(BUILDING_LENGTH_M)
    if len(vals) != 2 or not (np.isfinite(vals[0]) and vals[0] >= 0 and np.isfinite(vals[1]) and vals[1] > 0):
        raise click.BadParameter(
            f"expected RMS[,LENGTH]: an RMS ≥ 0 in µT and a length > 0 in m, got {text!r}",
            param_hint="--building",
        )
    return vals[0], vals[1]


def _parse_effects(items: tuple[str, ...]) -> dict:
    out: dict = {}
    for item in items:
        if "=" not in item:
            raise click.BadParameter(f"expected NAME=VALUE, got {item!r}", param_hint="--effect")
        name, text = (s.strip() for s in item.split("=", 1))
        try:
            out[name] = parse_effect_value(name, text)
        except ValueError as exc:
            raise click.BadParameter(str(exc), param_hint="--effect") from None
    return out


@click.command(help="Write a simulated pdr-csv recording (+ truth.csv, truth_position.csv).")
@click.option("--scenario", help="scenario name (see --list)")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True, help="random seed")
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), help="output directory")
@click.option(
    "--effect", "effects", multiple=True, metavar="NAME=VALUE", help="set or switch off (=off) an effect"
)
@click.option(
    "--duration",
    type=click.FloatRange(min=1.0, max=86400.0),
    default=None,
    help="length in seconds (default: the scenario's)",
)
@click.option(
    "--imu-rate",
    type=click.FloatRange(min=1.0, max=2000.0),
    default=None,
    help="accelerometer and gyroscope rate, Hz (default 100)",
)
@click.option(
    "--mag-rate",
    type=click.FloatRange(min=1.0, max=1000.0),
    default=None,
    help="magnetometer rate, Hz (default 50)",
)
@click.option(
    "--phone",
    "phone_name",
    type=click.Choice(list(PHONES)),
    default=None,
    help="a named phone (see --list): rates, accelerometer range, its own hard iron",
)
@click.option("--latitude", type=click.FloatRange(-90.0, 90.0), default=None, help="site latitude, deg")
@click.option("--longitude", type=click.FloatRange(-180.0, 180.0), default=None, help="site longitude, deg")
@click.option("--altitude", type=float, default=None, help="site altitude, m")
@click.option("--date", default=None, help="date YYYY-MM-DD (sets the WMM field)")
@click.option(
    "--field",
    "field_text",
    default=None,
    metavar="E,N,U",
    help="plain ENU field vector in µT instead of the WMM",
)
@click.option(
    "--building",
    "building_text",
    default=None,
    metavar="RMS[,LENGTH]",
    help="a building's own field everywhere along the walk: horizontal RMS in µT, correlation length in m"
    f" (default {BUILDING_LENGTH_M:g})",
)
@click.option("--list", "list_", is_flag=True, help="list scenarios and effects with their units")
def command(
    scenario,
    seed,
    out,
    effects,
    duration,
    imu_rate,
    mag_rate,
    phone_name,
    latitude,
    longitude,
    altitude,
    date,
    field_text,
    building_text,
    list_,
) -> int:
    if list_:
        click.echo(_listing())
        return 0
    if scenario is None:
        raise click.UsageError("--scenario is required (see --list)")
    if scenario not in SCENARIOS:
        raise click.BadParameter(
            f"unknown scenario {scenario!r}; known: {', '.join(SCENARIOS)}", param_hint="--scenario"
        )
    if out is None:
        raise click.UsageError("--out DIR is required")
    overrides = _parse_effects(effects)
    site = dict(DEFAULT_SITE)
    for key, val in (("latitude_deg", latitude), ("longitude_deg", longitude), ("altitude_m", altitude)):
        if val is not None:
            site[key] = val
    if date is not None:
        try:
            decimal_year(date)
        except ValueError as exc:
            raise click.BadParameter(str(exc), param_hint="--date") from None
        site["date"] = date
    field_w = None
    if field_text is not None:
        try:
            field_w = EarthField.from_vector([float(x) for x in field_text.split(",")]).field_w
        except ValueError as exc:
            raise click.BadParameter(
                f"expected 3 comma-separated numbers in µT ({exc})", param_hint="--field"
            ) from None
    building = None if building_text is None else _parse_building(building_text)
    spec = PhoneSpec() if phone_name is None else PHONES[phone_name].spec
    if imu_rate is not None:
        spec = replace(spec, accel_rate_hz=imu_rate, gyro_rate_hz=imu_rate)
    if mag_rate is not None:
        spec = replace(spec, mag_rate_hz=mag_rate)
    phone = spec if phone_name is None else replace(PHONES[phone_name], spec=spec)
    writable_dir(out)
    res = simulate(
        scenario, seed=seed, duration_s=duration, effects=overrides, phone=phone, site=site, field_w=field_w,
        building=building,
    )  # fmt: skip
    rec = Recording(
        mag=Stream(*res.mag),
        accel=Stream(*res.accel),
        gyro=Stream(*res.gyro),
        meta=res.meta,
        truth=res.truth,
        source="pdr-mag simulate",
        format=pdrcsv.NAME,
    )
    try:
        pdrcsv.write(rec, out, value_fmt=VALUE_FMT)
        tp, pp = res.truth_position
        with (out / "truth_position.csv").open("w", encoding="utf-8", newline="\n") as fh:
            fh.write("t,x,y,z\n")
            np.savetxt(fh, np.column_stack([tp, pp]), fmt=["%.6f", "%.3f", "%.3f", "%.3f"], delimiter=",")
    except OSError as exc:
        raise InputError(exc.filename or out, f"cannot write ({exc.strerror})") from None
    click.echo(
        f"{scenario} seed {seed}: {res.duration_s:g} s, mag {len(res.mag[0])}, accel {len(res.accel[0])}, "
        f"gyro {len(res.gyro[0])} samples; effects {', '.join(res.model.active) or 'none'} → {out}"
    )
    return 0
