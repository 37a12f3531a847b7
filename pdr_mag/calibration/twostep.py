"""Two-step initial value: offset and norm without a prior range, then the shape ([Zhong2017] §2.3,
[Long2013]).

Step 1 ([Zhong2017] §2.3, eqs. 10–13): ignore misalignment and sensitivity errors, so ``|m − b|² = F²`` is
linear in ``β = (2b, F² − |b|²)``: ``|m_i|² = [m_iᵀ, 1] β``, solved by linear least squares
(:func:`pdr_mag.calibration.sphere.sphere_lls`).  This gives the offset ``b₀`` and the norm ``F₀`` in the
sensor's own units, whatever they are — which is what lets the iterative fits start without knowing the
range of the parameters ([Zhong2017] §2.3; the paper shows LM diverging from a fixed guess).

Step 2 (the linear "二步法" step [Long2013] starts its Newton iterations from, Alonso & Shuster's centred
estimate): in the coordinates ``(m − b₀)/F₀`` of step 1 the full quadric is fitted linearly with the
ellipsoid constraint (:func:`pdr_mag.calibration.ellipsoid.ellipsoid_specific_solve`), giving offset and
SPD shape ``L``.  If the data cannot support it (not an ellipsoid, or axis ratio beyond
``max_axis_ratio``) the sphere of step 1 (``L = F₀ I``) is used.
"""

from __future__ import annotations

import numpy as np

from pdr_mag.calibration.ellipsoid import ellipsoid_specific_solve
from pdr_mag.calibration.geometry import build_calibration, monomials, quadric_to_ellipsoid
from pdr_mag.calibration.model import MagCalibration
from pdr_mag.calibration.sphere import _check_mag, sphere_lls


def initial_ellipsoid(mag: np.ndarray, max_axis_ratio: float = 3.0) -> tuple[np.ndarray, np.ndarray, str]:
    """``(b, L, source)`` — the two-step initial value; ``source`` is ``"ellipsoid"`` or ``"sphere"``."""
    m = _check_mag(mag)
    b0, r0, _ = sphere_lls(m)
    if len(m) >= 10:
        xs = (m - b0) / r0
        z = monomials(xs)
        try:
            b, L = quadric_to_ellipsoid(ellipsoid_specific_solve(z.T @ z / len(z)))
            ax = np.linalg.eigvalsh(L)
            if ax[-1] / ax[0] <= max_axis_ratio:
                return b0 + r0 * b, r0 * L, "ellipsoid"
        except ValueError:
            pass
    return b0, r0 * np.eye(3), "sphere"


def fit_twostep(mag: np.ndarray) -> MagCalibration:
    """The two-step estimate itself as a calibration (``method='twostep'``); see the module docstring."""
    m = _check_mag(mag)
    b, L, source = initial_ellipsoid(m)
    return build_calibration(m, b, L, "twostep", extra={"twostep_source": source})
