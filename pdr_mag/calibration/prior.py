"""What is known of a device before its first sample: a prior with its uncertainty, never a fact.

Two sources feed it, besides a calibration file given by the user (``replay --calibration``, which the
pipeline keeps as the calibration in force until the stale test says otherwise):

the phone itself
    A phone's OS calibrates its sensors all the time and many loggers record what it knows (the recording's
    ``meta``, keys of ``INTERFACE.md``): Android's uncalibrated magnetometer carries the OS's hard-iron
    estimate (``mag_os_bias_uT``), its uncalibrated gyroscope the OS's drift estimate
    (``gyro_os_bias_rad_s``); a stream the OS has already corrected (``mag_os_calibrated``,
    ``gyro_os_calibrated``) is the same knowledge with a zero bias left.
a backend's device store
    The last good calibration of the same device from an earlier recording
    (:class:`pdr_mag.calibration.store.DeviceStore`), with its covariance grown by its age.

Uncertainty, from measured figures (the defaults of :class:`PriorSettings`):

* the OS's hard-iron estimate against that day's figure-8 calibration on five Nexus 5 walks of
  ``../shared/datasets/tyrex-attitude`` was off by 1, 2, 4, 7 and 20 µT: 6 µT per axis is its σ, and the
  20-µT case (3σ) is what the online fits and the stale test are for;
* the OS's gyro drift estimate of the same walks agreed with the static recordings of the day within
  0.2 °/s per axis;
* hard iron moves between sessions: the day-to-day change of the figure-8 calibrations of the three tyrex
  phones was 2, 4, 4, 5, 21 and 50 µT (a random walk of σ ≈ 13 µT per √day per axis matches their
  variance; the large ones are jumps, which the stale test catches);
* a MEMS gyro's offset changes with each power-up: the tyrex static recordings of the same phone on
  different days differ by 0.1–0.4 °/s per axis (0.25 °/s as σ).

The phone's current estimate and a store's older one are both priors of the same offset; the pipeline takes
the one with the smaller covariance (:func:`choose`), so a fresh store entry from a figure-8 fit wins over the
OS's coarse estimate, and a day-old one does not.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from pdr_mag._records import check_numbers
from pdr_mag.calibration.model import MagCalibration

#: Seconds in a day (the store's random-walk rates are per √day).
DAY_S = 86400.0


@dataclass(frozen=True)
class PriorSettings:
    """Uncertainties of prior knowledge (the figures behind them: the module docstring).

    Attributes
    ----------
    phone_offset_std_uT : float
        1σ per axis of the OS's hard-iron estimate, µT.
    phone_gyro_bias_std : float
        1σ per axis of the OS's gyro drift estimate (or of the residual of an OS-calibrated gyro), rad/s.
    offset_drift_uT_per_sqrt_day : float
        Random walk of a stored hard-iron offset with its age, µT per √day per axis.
    gyro_turn_on_std : float
        1σ per axis of a gyro offset's change from one power-up to the next, rad/s (added to a stored bias).
    use_phone : bool
        Take the phone's own estimates from the recording's metadata (False: ignore them).
    """

    phone_offset_std_uT: float = 6.0
    phone_gyro_bias_std: float = math.radians(0.2)
    offset_drift_uT_per_sqrt_day: float = 13.0
    gyro_turn_on_std: float = math.radians(0.25)
    use_phone: bool = True

    def __post_init__(self):
        positive = ("phone_offset_std_uT", "phone_gyro_bias_std", "offset_drift_uT_per_sqrt_day",
                    "gyro_turn_on_std")  # fmt: skip
        check_numbers(self, positive=positive)


@dataclass(frozen=True)
class DevicePrior:
    """Prior knowledge of one device.

    Attributes
    ----------
    calibration : MagCalibration or None
        The magnetometer calibration known before the first sample, with its offset covariance
        (``offset_std_uT`` or ``covariance``); None when the magnetometer is unknown.
    gyro_bias : tuple of 3 float or None
        Gyroscope bias, rad/s, device frame (None: unknown).
    gyro_bias_std : float
        Its 1σ per axis, rad/s (NaN when ``gyro_bias`` is None).
    source : str
        ``"phone"``, ``"store"`` or, when each part came from another, ``"phone+store"``.
    age_s : float
        Age of the stored knowledge at the recording's start, s (0 for the phone's own).
    """

    calibration: MagCalibration | None = None
    gyro_bias: tuple[float, float, float] | None = None
    gyro_bias_std: float = float("nan")
    source: str = "phone"
    age_s: float = 0.0

    def to_dict(self) -> dict:
        """The prior for a run's summary (JSON)."""
        cal = self.calibration
        return {
            "source": self.source,
            "age_s": round(float(self.age_s), 1),
            "offset_uT": None if cal is None else [round(float(v), 3) for v in cal.offset],
            "offset_std_uT": None if cal is None else _stds(cal),
            "gyro_bias_rad_s": None if self.gyro_bias is None else [float(v) for v in self.gyro_bias],
            "gyro_bias_std_rad_s": None if self.gyro_bias is None else float(self.gyro_bias_std),
        }


def prior_source(cal: MagCalibration | None) -> str | None:
    """The source a prior calibration came from (``extra["prior"]``: ``"phone"``, ``"store"``), or None
    for a fit of this recording's data, a calibration the user gave, or none."""
    if cal is None or not isinstance(cal.extra, dict):
        return None
    return cal.extra.get("prior") or None


def is_prior(cal: MagCalibration | None) -> bool:
    """Whether ``cal`` is a prior (the phone's estimate, a store's entry) rather than a fit of this
    recording's data or a calibration the user gave."""
    return prior_source(cal) is not None


def phone_calibration(offset, offset_std_uT) -> MagCalibration:
    """The phone's hard-iron estimate ``offset`` (µT) as a prior calibration with ``offset_std_uT``."""
    return MagCalibration.from_arrays(offset, method="phone", offset_std_uT=offset_std_uT,
                                      extra={"prior": "phone"})  # fmt: skip


def phone_changes(meta: dict) -> list[tuple[float, tuple]]:
    """The phone's later hard-iron estimates stated by the metadata (``mag_os_bias_changes``: ``[[t, x, y,
    z], …]``), in time order; ``ValueError`` naming the key when malformed."""
    rows = meta.get("mag_os_bias_changes") or []
    out = []
    try:
        for r in rows:
            t, x, y, z = (float(v) for v in r)
            if not all(map(math.isfinite, (t, x, y, z))):
                raise ValueError(r)
            out.append((t, (x, y, z)))
    except (TypeError, ValueError):
        raise ValueError(f"meta: mag_os_bias_changes: expected [[t, x, y, z], …], got {rows!r}") from None
    return sorted(out)


def _stated(v: np.ndarray | None) -> np.ndarray | None:
    """An OS estimate, None for (0, 0, 0): no estimate stated."""
    return None if v is None or not np.any(v != 0.0) else v


def phone_prior(meta: dict, settings: PriorSettings | None = None) -> DevicePrior | None:
    """The phone's own calibration as the recording's ``meta`` states it (None when it states none).

    ``mag_os_bias_uT`` gives the offset, ``mag_os_calibrated`` a zero offset (the stream is already
    corrected), each with ``phone_offset_std_uT``; ``gyro_os_bias_rad_s`` / ``gyro_os_calibrated`` the gyro
    bias with ``phone_gyro_bias_std``.  An estimate of exactly (0, 0, 0) is an OS that states none
    (INTERFACE.md; :mod:`replay.formats._phone`), as if the key were absent.  A malformed value is a
    ``ValueError`` naming the key."""
    s = settings or PriorSettings()
    if not s.use_phone:
        return None
    cal = None
    bias = _stated(_vector(meta, "mag_os_bias_uT"))
    if bias is None and meta.get("mag_os_calibrated") is True:
        bias = np.zeros(3)
    if bias is not None:
        sd = s.phone_offset_std_uT
        cal = phone_calibration(bias, (sd, sd, sd))
    gyro = _stated(_vector(meta, "gyro_os_bias_rad_s"))
    if gyro is None and meta.get("gyro_os_calibrated") is True:
        gyro = np.zeros(3)
    if cal is None and gyro is None:
        return None
    return DevicePrior(
        calibration=cal,
        gyro_bias=None if gyro is None else tuple(float(v) for v in gyro),
        gyro_bias_std=s.phone_gyro_bias_std if gyro is not None else float("nan"),
        source="phone",
    )


def aged(prior: DevicePrior, age_s: float, settings: PriorSettings | None = None) -> DevicePrior:
    """A stored prior ``age_s`` seconds later: the offset covariance grows by
    ``offset_drift² · age / 1 day`` per axis, the gyro bias variance by ``gyro_turn_on_std²`` (a new
    power-up, whatever the age)."""
    s = settings or PriorSettings()
    age = max(float(age_s), 0.0)
    cal = prior.calibration
    if cal is not None and cal.offset_covariance is not None:  # an unknown covariance stays unknown
        cal = _with_offset_covariance(
            cal, cal.offset_covariance + np.eye(3) * s.offset_drift_uT_per_sqrt_day**2 * age / DAY_S
        )
    std = prior.gyro_bias_std
    if prior.gyro_bias is not None:
        std = math.hypot(std, s.gyro_turn_on_std)
    return replace(prior, calibration=cal, gyro_bias_std=std, age_s=age)


def choose(*priors: DevicePrior | None) -> DevicePrior | None:
    """One prior from several of the same device: for each part (magnetometer, gyro) the one with the
    smaller uncertainty (largest offset σ; gyro σ), so a part known to one source only is kept.  An
    unknown covariance counts as infinite."""
    have = [p for p in priors if p is not None]
    if not have:
        return None
    mag = min((p for p in have if p.calibration is not None), key=lambda p: offset_sigma(p.calibration),
              default=None)  # fmt: skip
    gyro = min((p for p in have if p.gyro_bias is not None), key=lambda p: _nan_inf(p.gyro_bias_std),
               default=None)  # fmt: skip
    sources = {p.source for p in (mag, gyro) if p is not None}
    return DevicePrior(
        calibration=None if mag is None else mag.calibration,
        gyro_bias=None if gyro is None else gyro.gyro_bias,
        gyro_bias_std=float("nan") if gyro is None else gyro.gyro_bias_std,
        source="+".join(sorted(sources)) if sources else "phone",
        age_s=max((p.age_s for p in (mag, gyro) if p is not None), default=0.0),
    )


# ------------------------------------------------------------------------------------------ helpers
def _vector(meta: dict, key: str) -> np.ndarray | None:
    v = meta.get(key)
    if v is None:
        return None
    try:
        a = np.asarray(v, dtype=float)
    except (TypeError, ValueError):
        a = np.empty(0)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ValueError(f"meta: {key}: expected 3 finite numbers, got {v!r}")
    return a


def offset_sigma(cal: MagCalibration, unknown: float = math.inf) -> float:
    """The largest offset σ of a calibration, µT; ``unknown`` when it carries no offset covariance."""
    cov = cal.offset_covariance
    return unknown if cov is None else float(np.sqrt(max(np.max(np.diag(cov)), 0.0)))


def _nan_inf(v: float) -> float:
    return v if math.isfinite(v) else math.inf


def _stds(cal: MagCalibration) -> list | None:
    cov = cal.offset_covariance
    if cov is None:
        return None
    return [round(float(np.sqrt(max(v, 0.0))), 3) for v in np.diag(cov)]


def with_offset_error(cal: MagCalibration, o: np.ndarray, cov_o: np.ndarray) -> MagCalibration:
    """``cal`` corrected by an offset error ``o`` found in its calibrated field (µT, device frame, of
    covariance ``cov_o``: :meth:`pdr_mag.fusion.FusionCore.offset_error`): the field ``M (r − b) − o`` is
    ``M (r − b − M⁻¹ o)``, so the offset becomes ``b + M⁻¹ o`` at the covariance ``M⁻¹ cov_o M⁻ᵀ`` (its other
    parameters' rows kept), and ``extra["filter_offset_uT"]`` says what was added."""
    m_inv = np.linalg.inv(cal.matrix)
    cov = m_inv @ cov_o @ m_inv.T
    extra = {**cal.extra, "filter_offset_uT": [round(float(v), 3) for v in o]}
    moved = replace(cal, offset=tuple((cal.offset_array + m_inv @ o).tolist()), extra=extra)
    return _with_offset_covariance(moved, 0.5 * (cov + cov.T))


def _with_offset_covariance(cal: MagCalibration, cov: np.ndarray) -> MagCalibration:
    """``cal`` with its offset covariance replaced (in a full-parameter covariance, its offset block; the
    other rows are kept; without one, the offset's own)."""
    std = tuple(float(np.sqrt(max(v, 0.0))) if np.isfinite(v) else float("nan") for v in np.diag(cov))
    if cal.covariance is not None:
        c = np.asarray(cal.covariance, dtype=float)
        if c.ndim == 2 and c.shape[0] >= 3:
            c = c.copy()
            c[:3, :3] = cov
            return replace(cal, offset_std_uT=std, covariance=tuple(map(tuple, c.tolist())))
    return replace(cal, offset_std_uT=std, covariance=tuple(map(tuple, np.asarray(cov, float).tolist())))
