"""``--latitude DEG --longitude DEG [--altitude M] [--date YYYY-MM-DD]``: the place and day of a recording
that does not state them (a backend knows its building; many loggers write no position), for the commands
that use the field model (``replay``, ``calibrate`` and their ``batch`` forms; ``simulate`` has options of
the same names for its site).  They set the recording's ``meta`` keys ``latitude_deg``, ``longitude_deg``,
``altitude_m`` and ``date`` as its ``meta.json`` would, over what the recording states."""

from __future__ import annotations

import click

from replay.errors import InputError


def place_options(command):
    """The four options, for a click command (its function takes ``latitude``, ``longitude``, ``altitude``,
    ``date``; :func:`place_of` turns them into ``place``, ``date``)."""
    options = [
        click.option("--latitude", type=click.FloatRange(-90.0, 90.0), metavar="DEG",
                     help="Where the recording was made (WGS-84, with --longitude), over what it says: the "
                     "field model gives the reference field and true north."),
        click.option("--longitude", type=click.FloatRange(-180.0, 360.0), metavar="DEG",
                     help="… its longitude."),
        click.option("--altitude", type=float, metavar="M",
                     help="… its height above the WGS-84 ellipsoid, m."),
        click.option("--date", type=click.DateTime(formats=["%Y-%m-%d"]), metavar="YYYY-MM-DD",
                     help="The day the recording was made, over what it says (the field model's date)."),
    ]
    for opt in reversed(options):
        command = opt(command)
    return command


def place_of(latitude, longitude, altitude, date) -> tuple[tuple | None, str | None]:
    """``(place, day)`` from the options: ``place`` = ``(latitude, longitude, altitude or None)`` or None,
    ``day`` = ``"YYYY-MM-DD"`` or None; a usage error when latitude and longitude do not come together, or an
    altitude comes without them."""
    day = None if date is None else date.date().isoformat()
    if latitude is None and longitude is None:
        if altitude is not None:
            raise click.UsageError("--altitude needs --latitude and --longitude")
        return None, day
    if latitude is None or longitude is None:
        raise click.UsageError("--latitude and --longitude go together")
    return (latitude, longitude, altitude), day


def apply_place(meta: dict, where, place: tuple | None, day: str | None) -> None:
    """``place`` and ``day`` into a recording's ``meta`` (in place); a place for a recording that states no
    day, without one given, is an :class:`InputError` naming ``where``: the field model needs the day."""
    if day is not None:
        meta["date"] = day
    if place is None:
        return
    meta["latitude_deg"], meta["longitude_deg"] = place[0], place[1]
    if place[2] is not None:
        meta["altitude_m"] = place[2]
    if not meta.get("date"):
        raise InputError(where, "states no date: give --date YYYY-MM-DD with --latitude/--longitude "
                         "(the field model needs the day)")
