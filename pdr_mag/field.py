"""Reference Earth magnetic field from the World Magnetic Model (WMM).

The WMM coefficients come with the maintained ``pygeomag`` package (WMM2010, WMM2015v2, WMM2020,
WMM2025), so nothing is downloaded at run time.  The model epoch is chosen by date; dates outside
2010–2030 use the nearest epoch (``EarthField.model`` says which, ``extrapolated`` flags it).

Output in the library's units and world frame (ENU, µT):
``field_w = F · (cos I · sin D, cos I · cos D, −sin I)`` with F the total intensity, I the inclination
(positive downward) and D the declination (positive east of true north).
"""

from __future__ import annotations

import datetime as _dt
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from pygeomag import GeoMag

from pdr_mag.conventions import NT_PER_UT

#: The Earth's total intensity at its surface, µT: over the WMM's epochs 2010–2025 it runs from 22.1 µT (the
#: South Atlantic anomaly, 27° S 60° W) to 66.9 µT (59° S 136° E), read off a 2° × 4° grid.  No calibration
#: whose radius lies far outside this range describes the Earth's field.
EARTH_STRENGTH_RANGE_UT = (22.0, 67.0)

_EPOCHS = (
    (2010.0, "WMM_2010.COF", "WMM-2010"),
    (2015.0, "WMM_2015v2.COF", "WMM-2015v2"),
    (2020.0, "WMM_2020.COF", "WMM-2020"),
    (2025.0, "WMM_2025.COF", "WMM-2025"),
)


@dataclass(frozen=True)
class EarthField:
    """The Earth's field at one place and date.

    Attributes
    ----------
    field_w : tuple of float
        Field vector in ENU, µT.
    strength : float
        Total intensity F, µT.
    inclination_deg : float
        Dip angle, positive when the field points below the horizon.
    declination_deg : float
        Angle from true north to magnetic north, positive east.
    model : str
        Which model produced it (``"WMM-2015v2"``, … or ``"vector"`` for a user override).
    extrapolated : bool
        True when the date lies outside the model's five-year lifespan.
    """

    field_w: tuple[float, float, float]
    strength: float
    inclination_deg: float
    declination_deg: float
    model: str
    extrapolated: bool = False

    @classmethod
    def from_vector(cls, field_w) -> EarthField:
        """An override from a plain ENU field vector (µT)."""
        f = np.asarray(field_w, dtype=float)
        if f.shape != (3,) or not np.all(np.isfinite(f)) or np.linalg.norm(f) <= 0:
            raise ValueError(f"field_w: expected 3 finite ENU components in µT, got {field_w!r}")
        strength = float(np.linalg.norm(f))
        horiz = float(np.hypot(f[0], f[1]))
        return cls(
            field_w=(float(f[0]), float(f[1]), float(f[2])),
            strength=strength,
            inclination_deg=float(np.degrees(np.arctan2(-f[2], horiz))),
            declination_deg=float(np.degrees(np.arctan2(f[0], f[1]))) if horiz > 0 else 0.0,
            model="vector",
        )

    @property
    def field_w_array(self) -> np.ndarray:
        return np.asarray(self.field_w, dtype=float)


def decimal_year(date: _dt.date | str) -> float:
    """Decimal year of a ``datetime.date`` or ``"YYYY-MM-DD"`` string (noon of that day)."""
    if isinstance(date, str):
        try:
            date = _dt.date.fromisoformat(date)
        except ValueError as exc:
            raise ValueError(f"date: expected 'YYYY-MM-DD', got {date!r}") from exc
    start = _dt.date(date.year, 1, 1)
    days = (_dt.date(date.year + 1, 1, 1) - start).days
    return date.year + ((date - start).days + 0.5) / days


@lru_cache(maxsize=8)
def _geomag(filename: str):
    return GeoMag(coefficients_file=f"wmm/{filename}")


def earth_field(
    latitude_deg: float, longitude_deg: float, altitude_m: float = 0.0, date: _dt.date | str | None = None
) -> EarthField:
    """Earth field from the WMM at a geodetic position and date.

    Parameters
    ----------
    latitude_deg, longitude_deg : float
        WGS-84 geodetic position, degrees.
    altitude_m : float
        Height above the WGS-84 ellipsoid, metres.
    date : datetime.date or str, optional
        Date (``"YYYY-MM-DD"``); today when omitted.
    """
    if not (-90.0 <= float(latitude_deg) <= 90.0):
        raise ValueError(f"latitude_deg: expected -90..90, got {latitude_deg!r}")
    if not (-180.0 <= float(longitude_deg) <= 360.0):
        raise ValueError(f"longitude_deg: expected -180..360, got {longitude_deg!r}")
    year = decimal_year(date if date is not None else _dt.date.today())
    chosen = _EPOCHS[0]
    for epoch in _EPOCHS:
        if year >= epoch[0]:
            chosen = epoch
    alt_km = float(altitude_m) / 1000.0
    return _wmm(chosen, float(latitude_deg), float(longitude_deg), alt_km, year)


@lru_cache(maxsize=64)
def _wmm(epoch: tuple, glat: float, glon: float, alt_km: float, year: float):
    """The WMM field of :func:`earth_field` (cached: the recordings of a batch, or of a building, share their
    place and day)."""
    res = _geomag(epoch[1]).calculate(
        glat=glat, glon=glon, alt=alt_km, time=year, allow_date_outside_lifespan=True
    )
    # pygeomag: x north, y east, z down, nT
    field_w = (res.y / NT_PER_UT, res.x / NT_PER_UT, -res.z / NT_PER_UT)
    return EarthField(
        field_w=tuple(float(v) for v in field_w),
        strength=float(res.f / NT_PER_UT),
        inclination_deg=float(res.i),
        declination_deg=float(res.d),
        model=epoch[2],
        extrapolated=not (epoch[0] <= year < epoch[0] + 5.0),
    )


def earth_field_from_meta(meta: dict) -> EarthField | None:
    """The WMM field for a recording's ``meta.json`` dict, or None when position or date is missing."""
    try:
        lat = meta["latitude_deg"]
        lon = meta["longitude_deg"]
        date = meta["date"]
    except (KeyError, TypeError):
        return None
    return earth_field(lat, lon, meta.get("altitude_m", 0.0) or 0.0, date)


def plausible_strength(strength_uT: float, reference_uT: float | None, rel_tol: float,
                       margin_uT: float = 0.0) -> bool:
    """Whether a field strength can be the Earth's: within ``rel_tol`` (indoors the local field departs from
    the model by up to tens of per cent) of the reference strength when one is known (the WMM's for the
    place and date), else within :data:`EARTH_STRENGTH_RANGE_UT` widened by the same share; either band
    widened by ``margin_uT`` more (what the uncertainty of the calibration that gave the strength can do)."""
    if not np.isfinite(strength_uT) or strength_uT <= 0:
        return False
    if reference_uT is not None and np.isfinite(reference_uT):
        return abs(strength_uT - reference_uT) <= rel_tol * reference_uT + margin_uT
    lo, hi = EARTH_STRENGTH_RANGE_UT
    return lo * (1.0 - rel_tol) - margin_uT <= strength_uT <= hi * (1.0 + rel_tol) + margin_uT
