"""Device calibration store: what a backend learnt of each phone, for the next recording of the same phone.

A folder with one JSON file per device (the key: the recording's ``device`` model, and its ``device_id`` when
the recording has one).  Each file holds the last good magnetometer calibration of that device (refined by
the sessions that agreed with it) with its offset covariance, the gyroscope's mean power-up bias over its
sessions with the σ of that mean, and when they were known (Unix time)::

    {"format_version": 1, "key": "OPPO PBCM10", "device": "OPPO PBCM10", "device_id": null,
     "t_unix": 1574572530.2,
     "calibration": {... the calibrate --json object ...}, "mag_stream": "raw",
     "gyro_bias_rad_s": [0.0018, 0.0021, 0.0009], "gyro_bias_std_rad_s": 0.0004, "gyro_stream": "raw"}

Each part names the stream it was learnt on (``raw``, ``os_calibrated``: the recording's
``<sensor>_os_calibrated``; null when it did not say) and serves only recordings of that stream
(:func:`_for_streams`).

:meth:`DeviceStore.load` gives it back as a :class:`~pdr_mag.calibration.prior.DevicePrior` aged to the new
recording's start (:func:`~pdr_mag.calibration.prior.aged`: the offset's covariance grows with the days
passed, the gyro bias gets a power-up's σ), so a stale entry weighs what it deserves and the pipeline's stale
test and online fits replace it when the data disagree; :meth:`DeviceStore.save` writes atomically (a
concurrent reader sees the old file or the new one). A session's fit that agrees with the entry refines it
(:func:`accumulate`), and each session's gyro bias is averaged into the device's (:func:`device_gyro_bias`):
the device's sessions add up, as a phone's OS keeps refining its own estimate. A file
that cannot be read is reported (``ValueError`` naming it), never silently replaced.
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

import numpy as np
import scipy.stats

from pdr_mag.calibration.model import MagCalibration
from pdr_mag.calibration.prior import DevicePrior, PriorSettings, aged, is_prior
from pdr_mag.calibration.refit import CONTRADICTION_CHI2

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
        """The stored prior of this recording's device, aged to ``t_unix``, without the parts learnt on
        another stream than the recording's (None when nothing is left)."""
        return self.find(meta, t_unix)[1]

    def find(self, meta: dict, t_unix: float) -> tuple[Path | None, DevicePrior | None]:
        """:meth:`path` and :meth:`load` together, the file read once."""
        found = self._locate(meta)
        if found is None:
            return None, None
        if found[1] is None:
            return found[0], None
        prior, t_saved = _entry(*found)
        prior = _for_streams(prior, _streams(found[1]), meta)
        if prior.calibration is None and prior.gyro_bias is None:
            return found[0], None
        return found[0], aged(prior, t_unix - t_saved, self.settings)

    def save(self, meta: dict, prior: DevicePrior, t_unix: float) -> Path | None:
        """Store what is known of this recording's device at ``t_unix`` (a part that ``prior`` lacks keeps
        the stored one: a calibration aged to ``t_unix``, a gyro bias as it was stored — a power-up's σ is
        added at each load, not at each save; a calibration that agrees with the stored one refines it,
        :func:`accumulate`; a gyro bias is averaged into the device's, :func:`device_gyro_bias` — each only
        when learnt on the same stream, else the new part replaces the stored one); returns the file, or
        None when the recording names no device."""
        found = self._locate(meta)
        if found is None:
            return None
        p, d = found
        stored = None if d is None else _entry(p, d)
        old = None if stored is None else aged(stored[0], t_unix - stored[1], self.settings)
        streams = {"mag": None, "gyro": None} if d is None else _streams(d)
        now = {sensor: stream_kind(meta, sensor) for sensor in streams}
        # a stored part of another stream than this recording's is another quantity: replaced, never refined
        same = {sensor: _same_stream(streams[sensor], now[sensor]) for sensor in streams}
        cal = prior.calibration if prior.calibration is not None else (old and old.calibration)
        if prior.calibration is not None and old is not None and old.calibration is not None and same["mag"]:
            cal = accumulate(old.calibration, prior.calibration)
        tau = self.settings.gyro_turn_on_std
        earlier = None if stored is None or (prior.gyro_bias is not None and not same["gyro"]) else stored[0]
        gyro, std = device_gyro_bias(earlier, prior, tau)
        entry = {
            "format_version": FORMAT_VERSION,
            "key": self.key(meta),
            "device": meta.get("device"),
            "device_id": meta.get("device_id"),
            "t_unix": float(t_unix),
            "calibration": None if cal is None else cal.to_dict(),
            "mag_stream": now["mag"] if prior.calibration is not None and now["mag"] else streams["mag"],
            "gyro_bias_rad_s": None if gyro is None else [float(v) for v in gyro],
            "gyro_bias_std_rad_s": None if gyro is None else float(std),
            "gyro_stream": now["gyro"] if prior.gyro_bias is not None and now["gyro"] else streams["gyro"],
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


#: χ²₃ at 99 %: a session's offset farther than this from the stored one (in the Mahalanobis distance of
#: their summed covariances) is a changed device (a case's magnet, a repair), not a refinement
AGREE_CHI2 = float(scipy.stats.chi2.ppf(0.99, 3))


def accumulate(stored: MagCalibration, new: MagCalibration) -> MagCalibration:
    """What the store keeps when a session ends with calibration ``new`` and the entry (aged to now) is
    ``stored``: ``new`` with its offset the information-weighted mean ``(Σ_s⁻¹ + Σ_n⁻¹)⁻¹ (Σ_s⁻¹ b_s +
    Σ_n⁻¹ b_n)`` when the two agree (``d² = Δᵀ(Σ_s + Σ_n)⁻¹Δ`` within :data:`AGREE_CHI2`) and share the
    soft-iron shape; otherwise ``new`` as it is.  Its covariance stays ``new``'s: successive sessions' fits of
    a phone held alike in the same buildings share part of their error (the building's field along the
    device's axes, NOTES), so the mean is no surer than the latest fit — it only averages what differs between
    sessions.  A prior (the phone's estimate, this entry itself left standing) brings nothing new."""
    so, sn = stored.offset_covariance, new.offset_covariance
    if is_prior(new) or so is None or sn is None or not np.array_equal(stored.matrix, new.matrix):
        return new
    b_s, b_n = stored.offset_array, new.offset_array
    d = b_n - b_s
    if not np.any(d) or float(d @ np.linalg.solve(so + sn, d)) > AGREE_CHI2:
        return new
    info_s, info_n = np.linalg.inv(so), np.linalg.inv(sn)
    b = np.linalg.solve(info_s + info_n, info_s @ b_s + info_n @ b_n)
    return replace(new, offset=tuple(float(v) for v in b))


def device_gyro_bias(stored: DevicePrior | None, session: DevicePrior, turn_on_std: float) -> tuple:
    """The device's gyro offset the store keeps, ``(bias, σ)``: the offset the device powers up with on
    average, ``b_dev``, and the σ of that estimate.

    A MEMS gyro's offset is ``b_dev + ε`` at each power-up, ``ε`` of σ ``turn_on_std`` drawn anew
    (:class:`~pdr_mag.calibration.prior.PriorSettings`); a session's filter estimates that session's offset
    ``b_k`` with σ_k — in a building its heading corrections teach the bias part of the field's turning
    too, tenths of a °/s, of either sign from one walk to the next.  Each session is then an estimate of
    ``b_dev`` of variance ``σ_k² + turn_on_std²``, and the sessions that agree add up as independent
    measurements: ``b_dev = V (Σ b_k / (σ_k² + τ²))``, ``V = (Σ 1 / (σ_k² + τ²))⁻¹`` — the stored σ is √V,
    and :func:`~pdr_mag.calibration.prior.aged` adds ``τ²`` again at the next load (the next power-up).  A
    session whose offset is farther from the stored one than their variances allow (χ²₃ at 99.9 %,
    :data:`~pdr_mag.calibration.refit.CONTRADICTION_CHI2`: two estimates that cannot both be the device's;
    stricter than the offsets' 99 %, as the mean is worth many sessions and at 99 % one session in a hundred
    would end it by chance) starts the estimate afresh: another gyro under the same key.  A ``session``
    without a gyro bias leaves the stored one as it was; ``ValueError`` for one that is not finite."""
    if session.gyro_bias is None:
        return (None, float("nan")) if stored is None else (stored.gyro_bias, stored.gyro_bias_std)
    b_n = np.asarray(session.gyro_bias, dtype=float)
    if b_n.shape != (3,) or not np.all(np.isfinite(b_n)) or not math.isfinite(session.gyro_bias_std):
        raise ValueError("device store: a gyro bias to save needs 3 finite numbers and a finite σ")
    var_n = session.gyro_bias_std**2 + turn_on_std**2
    if stored is None or stored.gyro_bias is None:
        return session.gyro_bias, math.sqrt(var_n)
    b_s = np.asarray(stored.gyro_bias, dtype=float)
    var_s = stored.gyro_bias_std**2
    d = b_n - b_s
    if float(d @ d) / (var_s + var_n) > CONTRADICTION_CHI2:
        return session.gyro_bias, math.sqrt(var_n)
    if var_s == 0.0:  # an entry that states its bias exactly (a σ of 0 written by hand) stays as it is
        return stored.gyro_bias, 0.0
    var = 1.0 / (1.0 / var_s + 1.0 / var_n)
    b = var * (b_s / var_s + b_n / var_n)
    return tuple(float(v) for v in b), math.sqrt(var)


#: The kinds of stream a stored part may belong to (``meta["<sensor>_os_calibrated"]`` False / True)
STREAM_KINDS = ("raw", "os_calibrated")


def stream_kind(meta: dict, sensor: str) -> str | None:
    """Which stream of ``sensor`` (``"mag"``, ``"gyro"``) a recording gives: ``"raw"`` or
    ``"os_calibrated"`` as its ``<sensor>_os_calibrated`` says (INTERFACE.md), None when it does not say."""
    v = meta.get(f"{sensor}_os_calibrated")
    return None if not isinstance(v, bool) else STREAM_KINDS[int(v)]


def _same_stream(stored: str | None, recording: str | None) -> bool:
    """Whether a part learnt on stream ``stored`` belongs to a recording of stream ``recording``: the same
    kind, or either not stated."""
    return stored is None or recording is None or stored == recording


def _streams(d: dict) -> dict:
    """The streams an entry's parts were learnt on (``mag_stream``, ``gyro_stream``; None: not stated, as
    in entries written before the store kept them — such a part serves every stream)."""
    out = {}
    for sensor in ("mag", "gyro"):
        v = d.get(f"{sensor}_stream")
        out[sensor] = v if v in STREAM_KINDS else None
    return out


def _for_streams(prior: DevicePrior, streams: dict, meta: dict) -> DevicePrior:
    """``prior`` without the parts learnt on another stream than the recording's: a raw magnetometer's
    hard-iron offset (hundreds of µT) is not the residual offset of the field the OS has already corrected,
    nor a raw gyro's power-up offset the residual of an OS-calibrated rate — a backend whose app changes
    which stream it logs would otherwise start the phone from a prior that is sure and wrong.  A part
    whose stream or whose recording's stream is not stated is kept."""
    drop = {sensor for sensor, kind in streams.items() if not _same_stream(kind, stream_kind(meta, sensor))}
    if "mag" in drop:
        prior = replace(prior, calibration=None)
    if "gyro" in drop:
        prior = replace(prior, gyro_bias=None, gyro_bias_std=float("nan"))
    return prior


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
