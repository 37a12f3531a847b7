"""Device calibration store: what a backend learnt of each phone, for the next recording of the same phone.

A folder with one JSON file per device (the key: the recording's ``device`` model, and its ``device_id`` when
the recording has one).  Each file holds the last good magnetometer calibration of that device with its
offset covariance, the gyroscope bias with its σ, and when they were known (Unix time)::

    {"format_version": 1, "key": "OPPO PBCM10", "device": "OPPO PBCM10", "device_id": null,
     "t_unix": 1574572530.2,
     "calibration": {... the calibrate --json object ...},
     "gyro_bias_rad_s": [0.0018, 0.0021, 0.0009], "gyro_bias_std_rad_s": 0.0004}

:meth:`DeviceStore.load` gives it back as a :class:`~pdr_mag.calibration.prior.DevicePrior` aged to the new
recording's start (:func:`~pdr_mag.calibration.prior.aged`: the offset's covariance grows with the days
passed, the gyro bias gets a power-up's σ), so a stale entry weighs what it deserves and the pipeline's stale
test and online fits replace it when the data disagree; :meth:`DeviceStore.save` writes atomically (a
concurrent reader sees the old file or the new one).  A file that cannot be read is reported (``ValueError``
naming it), never silently replaced.
"""

from __future__ import annotations

import datetime
import hashlib
import json
import math
import os
import re
import tempfile
from dataclasses import replace
from pathlib import Path

from pdr_mag.calibration.model import MagCalibration
from pdr_mag.calibration.prior import DevicePrior, PriorSettings, aged

FORMAT_VERSION = 1


def _parse(p: Path) -> dict | None:
    """A store file's entry as parsed (None when there is no such file); ``ValueError`` naming the file
    when it cannot be read, is not of this format or names no device key."""
    if not p.is_file():
        return None
    try:
        d = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{p}: device store: cannot read ({exc})") from None
    if not isinstance(d, dict) or d.get("format_version") != FORMAT_VERSION:
        raise ValueError(f"{p}: device store: expected format_version {FORMAT_VERSION}")
    if not isinstance(d.get("key"), str):
        raise ValueError(f"{p}: device store: no device key")
    return d


class DeviceStore:
    """The store in ``folder`` (created on the first :meth:`save`).

    Parameters
    ----------
    folder : str or Path
    settings : PriorSettings, optional
        How a stored entry ages.
    """

    def __init__(self, folder, settings: PriorSettings | None = None):
        self.folder = Path(folder)
        self.settings = settings or PriorSettings()
        if self.folder.exists() and not self.folder.is_dir():
            raise ValueError(f"{self.folder}: device store: not a folder")

    @staticmethod
    def key(meta: dict) -> str | None:
        """The device's key: ``device`` and, when known, ``device_id``; None when the recording names no
        device (nothing is stored for it)."""
        model = meta.get("device")
        if not isinstance(model, str) or not model.strip():
            return None
        dev_id = meta.get("device_id")
        return f"{model.strip()}#{dev_id}" if dev_id not in (None, "") else model.strip()

    @staticmethod
    def recording_time(meta: dict) -> float | None:
        """When a recording started, Unix time, from what its metadata states: ``start_time_unix``, else
        noon UTC of its ``date`` (an entry's age then counts in days); None when it states neither (a live
        backend uses the clock)."""
        t = meta.get("start_time_unix")
        if isinstance(t, int | float) and math.isfinite(t):
            return float(t)
        d = meta.get("date")
        if isinstance(d, str):
            try:
                day = datetime.date.fromisoformat(d[:10])
            except ValueError:
                return None
            return datetime.datetime(day.year, day.month, day.day, 12, tzinfo=datetime.UTC).timestamp()
        return None

    def path(self, meta: dict) -> Path | None:
        """The file of this recording's device (None without a device): the key with every run of other
        characters than letters, digits, ``.``, ``_``, ``-`` made one ``_`` — unless that file holds another
        device whose key reads the same so (``"A B"`` and ``"A/B"``), then the same name with the key's
        hash, so that neither overwrites the other.  ``ValueError`` for a file that is not a store entry
        (:meth:`load` names it)."""
        found = self._locate(meta)
        return None if found is None else found[0]

    def _locate(self, meta: dict) -> tuple[Path, dict | None] | None:
        """This device's file (:meth:`path`) and its entry as parsed (None: no entry yet), each file read
        once; None without a device."""
        k = self.key(meta)
        if k is None:
            return None
        plain = self.folder / (re.sub(r"[^A-Za-z0-9._-]+", "_", k) + ".json")
        hashed = plain.with_name(f"{plain.stem}-{hashlib.sha1(k.encode('utf-8')).hexdigest()[:10]}.json")
        d = _parse(hashed)  # the hashed name first: it is this key's alone (the plain one may be gone since)
        if d is not None:
            if d["key"] != k:
                raise ValueError(f"{hashed}: device store: holds {d['key']!r}, not {k!r}")
            return hashed, d
        d = _parse(plain)
        return (plain, d) if d is None or d["key"] == k else (hashed, None)

    def load(self, meta: dict, t_unix: float) -> DevicePrior | None:
        """The stored prior of this recording's device, aged to ``t_unix`` (None when there is none)."""
        return self.find(meta, t_unix)[1]

    def find(self, meta: dict, t_unix: float) -> tuple[Path | None, DevicePrior | None]:
        """:meth:`path` and :meth:`load` together, the file read once."""
        found = self._locate(meta)
        if found is None:
            return None, None
        if found[1] is None:
            return found[0], None
        prior, t_saved = _entry(*found)
        return found[0], aged(prior, t_unix - t_saved, self.settings)

    def save(self, meta: dict, prior: DevicePrior, t_unix: float) -> Path | None:
        """Store what is known of this recording's device at ``t_unix`` (a part that ``prior`` lacks keeps
        the stored one: a calibration aged to ``t_unix``, a gyro bias as it was stored — a power-up's σ is
        added at each load, not at each save); returns the file, or None when the recording names no
        device."""
        found = self._locate(meta)
        if found is None:
            return None
        p, d = found
        stored = None if d is None else _entry(p, d)
        old = None if stored is None else aged(stored[0], t_unix - stored[1], self.settings)
        cal = prior.calibration if prior.calibration is not None else (old and old.calibration)
        src = stored[0] if prior.gyro_bias is None and stored is not None else prior
        gyro, std = src.gyro_bias, src.gyro_bias_std
        entry = {
            "format_version": FORMAT_VERSION,
            "key": self.key(meta),
            "device": meta.get("device"),
            "device_id": meta.get("device_id"),
            "t_unix": float(t_unix),
            "calibration": None if cal is None else cal.to_dict(),
            "gyro_bias_rad_s": None if gyro is None else [float(v) for v in gyro],
            "gyro_bias_std_rad_s": None if gyro is None else float(std),
        }
        self.folder.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=self.folder, prefix=".", suffix=".tmp")
        try:
            with os.fdopen(fd, "w", encoding="utf-8") as fh:
                json.dump(entry, fh, indent=1)
                fh.write("\n")
            os.replace(tmp, p)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        return p


def _entry(p: Path, d: dict) -> tuple[DevicePrior, float]:
    """A parsed entry (:func:`_parse`) as the device's prior as saved, and when; ``ValueError`` naming the
    file when its parts are malformed."""
    try:
        cal = None if d.get("calibration") is None else MagCalibration.from_dict(d["calibration"])
        gyro = d.get("gyro_bias_rad_s")
        gyro = None if gyro is None else tuple(float(v) for v in gyro)
        std = float(d["gyro_bias_std_rad_s"]) if gyro is not None else math.nan
        t_saved = float(d["t_unix"])
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{p}: device store: malformed entry ({exc})") from None
    if gyro is not None and (len(gyro) != 3 or not all(map(math.isfinite, (*gyro, std)))):
        raise ValueError(f"{p}: device store: gyro_bias_rad_s: expected 3 finite numbers and a σ")
    if cal is not None:
        cal = replace(cal, extra={**cal.extra, "prior": "store"})
    return DevicePrior(calibration=cal, gyro_bias=gyro, gyro_bias_std=std, source="store"), t_saved
