"""The calibration result: ``m_cal = soft_iron @ (m_raw - offset)``, with its quality and JSON form.

The JSON object is the one of ``../shared/INTERFACE.md`` (``calibrate --json``), which is also the
calibration file that ``replay --calibration`` reads.  Keys beyond the contract are added, never renamed.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from pdr_mag._json import jsonable

FORMAT_VERSION = 1
#: the soft iron of an offset-only calibration (:meth:`MagCalibration.from_arrays` without one): code that
#: asks whether a calibration has a shape may test for this object first, then for an identity by value
IDENTITY_SOFT_IRON = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))


#: ``extra`` key of the offset error a fit's model leaves out, µT² (3 × 3 nested lists): an offset-only fit's
#: unseen soft iron; the fusion filter counts it with the fit's covariance (``offset_error_covariance``).
SHAPE_COVARIANCE = "shape_offset_cov_uT2"


@dataclass(frozen=True)
class MagCalibration:
    """A magnetometer calibration.

    Model: ``m_cal = soft_iron @ (m_raw - offset)``; ``soft_iron`` symmetric positive definite,
    ``|m_cal| ≈ field_uT``.

    Attributes
    ----------
    offset : tuple of 3 float
        Hard-iron offset b, µT, device (magnetometer) frame.
    soft_iron : tuple of 3 tuples of 3 float
        Symmetric positive-definite correction matrix (identity for an offset-only fit).
    field_uT : float
        Radius of the calibrated sphere, µT (the local field strength as the fit sees it).
    method : str
        ``sphere``, ``ellipsoid``, ``als``, ``ml``, … — which estimator produced it.
    residual_rms_uT : float
        RMS of ``|m_cal| − field_uT`` over the samples used, µT.
    offset_std_uT : tuple of 3 float
        1-σ uncertainty of the offset, µT (from the parameter covariance).
    n_samples : int
        Number of samples the fit used.
    coverage : float
        Share of orientation space covered by the samples, in [0, 1].
    accepted : bool
        Whether the acceptance rules passed; ``reasons`` say why not.
    reasons : tuple of str
        Human-readable reasons for refusal (empty when accepted).
    covariance : tuple or None
        Covariance of the estimated parameters (row-major nested tuples), in the order given by
        ``extra["covariance_params"]`` when present.
    mag_to_imu : tuple or None
        Rotation matrix from magnetometer to IMU axes when estimated (alignment); None = identity.
    extra : dict
        Further method-specific figures (iterations, noise estimate, information criteria, …).
    """

    offset: tuple[float, float, float]
    soft_iron: tuple[tuple[float, float, float], ...] = IDENTITY_SOFT_IRON
    field_uT: float = float("nan")
    method: str = "sphere"
    residual_rms_uT: float = float("nan")
    offset_std_uT: tuple[float, float, float] = (float("nan"),) * 3
    n_samples: int = 0
    coverage: float = float("nan")
    accepted: bool = True
    reasons: tuple[str, ...] = ()
    covariance: tuple | None = None
    mag_to_imu: tuple | None = None
    extra: dict = field(default_factory=dict)

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_arrays(cls, offset, soft_iron=None, **kwargs) -> MagCalibration:
        """Build from numpy arrays, validating shapes and symmetry."""
        b = np.asarray(offset, dtype=float)
        if b.shape != (3,) or not np.isfinite(b).all():
            raise ValueError(f"offset: expected 3 finite values in µT, got {offset!r}")
        if soft_iron is None:
            soft = IDENTITY_SOFT_IRON  # 0.5 (I + Iᵀ) = I
        else:
            a = np.asarray(soft_iron, dtype=float)
            if a.shape != (3, 3):
                raise ValueError(f"soft_iron: expected a finite 3×3 matrix, got shape {a.shape}")
            if not np.all(np.isfinite(a)):
                raise ValueError("soft_iron: expected a finite 3×3 matrix, got NaN or infinite values")
            soft = _tuplify(0.5 * (a + a.T))
        for key in ("offset_std_uT",):
            if key in kwargs and kwargs[key] is not None:
                kwargs[key] = tuple(np.asarray(kwargs[key], dtype=float).ravel().tolist())
        if kwargs.get("covariance") is not None:
            kwargs["covariance"] = _tuplify(np.asarray(kwargs["covariance"], dtype=float))
        if kwargs.get("mag_to_imu") is not None:
            kwargs["mag_to_imu"] = _tuplify(np.asarray(kwargs["mag_to_imu"], dtype=float))
        if "reasons" in kwargs:
            kwargs["reasons"] = tuple(kwargs["reasons"])
        return cls(offset=tuple(b.tolist()), soft_iron=soft, **kwargs)

    def with_acceptance(self, accepted: bool, reasons) -> MagCalibration:
        """A copy with the acceptance verdict replaced."""
        return replace(self, accepted=bool(accepted), reasons=tuple(reasons))

    # ------------------------------------------------------------------ use
    @property
    def offset_array(self) -> np.ndarray:
        return np.asarray(self.offset, dtype=float)

    @property
    def soft_iron_array(self) -> np.ndarray:
        return np.asarray(self.soft_iron, dtype=float)

    @property
    def matrix(self) -> np.ndarray:
        """The 3×3 matrix ``M`` taking an offset-corrected raw sample ``m_raw − offset`` into the device (IMU)
        frame: ``mag_to_imu @ soft_iron``, or ``soft_iron`` when ``mag_to_imu`` is None (a new array)."""
        a = self.soft_iron_array
        if self.mag_to_imu is not None:
            a = np.asarray(self.mag_to_imu, dtype=float) @ a
        return a

    @property
    def offset_error_covariance(self) -> np.ndarray | None:
        """The offset's error as the fusion filter counts it, 3×3 µT²: :attr:`offset_covariance` plus what
        the fit's model leaves out, ``extra[SHAPE_COVARIANCE]`` (an offset-only fit's unseen soft iron,
        :func:`pdr_mag.calibration.gravity.soft_iron_offset_covariance`)."""
        cov = self.offset_covariance
        shape = self.extra.get(SHAPE_COVARIANCE)
        if cov is None or shape is None:
            return cov
        return cov + np.asarray(shape, dtype=float)

    @property
    def offset_covariance(self) -> np.ndarray | None:
        """Covariance of the offset, 3×3 µT²: the offset block of ``covariance`` (every fit puts the offset
        first), else ``diag(offset_std_uT²)``; None when neither is known."""
        if self.covariance is not None:
            c = np.asarray(self.covariance, dtype=float)
            if c.ndim == 2 and c.shape[0] >= 3 and np.all(np.isfinite(c[:3, :3])):
                return c[:3, :3].copy()
        s = np.asarray(self.offset_std_uT, dtype=float)
        return np.diag(s * s) if np.all(np.isfinite(s)) else None

    def apply(self, mag_raw: np.ndarray) -> np.ndarray:
        """Calibrated field ``soft_iron @ (m_raw − offset)`` for samples of shape (3,) or (N, 3), µT.

        When ``mag_to_imu`` is set, the result is also rotated into the IMU axes.
        """
        m = np.asarray(mag_raw, dtype=float)
        if m.shape[-1] != 3:
            raise ValueError(f"mag_raw: expected shape (…, 3) in µT, got {m.shape}")
        return (m - self.offset_array) @ self.matrix.T

    # ------------------------------------------------------------------ JSON
    def to_dict(self) -> dict:
        """The ``calibrate --json`` object (INTERFACE.md), plus extra keys."""
        out = {
            "format_version": FORMAT_VERSION,
            "method": self.method,
            "offset_uT": list(self.offset),
            "soft_iron": [list(r) for r in self.soft_iron],
            "field_uT": _num(self.field_uT),
            "residual_rms_uT": _num(self.residual_rms_uT),
            "offset_std_uT": [_num(v) for v in self.offset_std_uT],
            "n_samples": int(self.n_samples),
            "coverage": _num(self.coverage),
            "accepted": bool(self.accepted),
            "reasons": list(self.reasons),
        }
        if self.covariance is not None:
            out["covariance"] = [list(r) for r in self.covariance]
        if self.mag_to_imu is not None:
            out["mag_to_imu"] = [list(r) for r in self.mag_to_imu]
        if self.extra:
            out["extra"] = jsonable(self.extra)
        return out

    def to_json(self, path: str | Path | None = None) -> str:
        text = json.dumps(self.to_dict(), indent=1)
        if path is not None:
            Path(path).write_text(text + "\n")
        return text

    @classmethod
    def from_dict(cls, d: dict) -> MagCalibration:
        """Parse a ``calibrate --json`` object; raises ValueError naming the bad key."""
        if not isinstance(d, dict):
            raise ValueError("calibration: expected a JSON object")
        version = d.get("format_version")
        if version != FORMAT_VERSION:
            raise ValueError(f"calibration: format_version {version!r} is not supported (expected 1)")
        for key in ("offset_uT", "soft_iron"):
            if key not in d:
                raise ValueError(f"calibration: missing key {key!r}")
        try:
            cal = cls.from_arrays(
                d["offset_uT"],
                d["soft_iron"],
                field_uT=float(d.get("field_uT") if d.get("field_uT") is not None else float("nan")),
                method=str(d.get("method", "unknown")),
                residual_rms_uT=_float(d.get("residual_rms_uT")),
                offset_std_uT=[_float(v) for v in d.get("offset_std_uT", [None] * 3)],
                n_samples=int(d.get("n_samples", 0)),
                coverage=_float(d.get("coverage")),
                accepted=bool(d.get("accepted", True)),
                reasons=d.get("reasons", []),
                covariance=d.get("covariance"),
                mag_to_imu=d.get("mag_to_imu"),
                extra=dict(d.get("extra", {})),
            )
        except (TypeError, ValueError) as exc:
            raise ValueError(f"calibration: {exc}") from exc
        _check_physical(cal)
        return cal

    @classmethod
    def from_json(cls, path: str | Path) -> MagCalibration:
        try:
            d = json.loads(Path(path).read_text())
        except json.JSONDecodeError as exc:
            raise ValueError(f"{path}: not valid JSON (line {exc.lineno}: {exc.msg})") from exc
        return cls.from_dict(d)


def _tuplify(a: np.ndarray) -> tuple:
    return tuple(map(tuple, np.asarray(a, dtype=float).tolist()))


def _num(v: float):
    v = float(v)
    return v if np.isfinite(v) else None


def _float(v) -> float:
    return float("nan") if v is None else float(v)


def _check_physical(cal: MagCalibration) -> None:
    """What a calibration file must state to be a calibration (the model of the class docstring): a soft-iron
    matrix that is positive definite (a singular one maps the field onto a plane, a negative eigenvalue
    mirrors it), a field strength that is positive (or unknown) and offset σ that are not negative (or
    unknown); ValueError naming the key."""
    eig = np.linalg.eigvalsh(cal.soft_iron_array)
    if not eig.min() > 1e-9 * max(eig.max(), 1e-300):
        got = np.round(eig, 6).tolist()
        raise ValueError(f"calibration: soft_iron: expected a positive-definite matrix, eigenvalues {got}")
    if np.isfinite(cal.field_uT) and not cal.field_uT > 0:
        raise ValueError(f"calibration: field_uT: expected a positive strength in µT, got {cal.field_uT!r}")
    std = np.asarray(cal.offset_std_uT, dtype=float)
    if np.any(std[np.isfinite(std)] < 0):
        raise ValueError(f"calibration: offset_std_uT: expected σ ≥ 0 in µT, got {list(cal.offset_std_uT)!r}")
