"""The fusion filter, behind one door: its settings, state, process, snapshots and interference detectors.

The public API (what :class:`pdr_mag.pipeline.HeadingPipeline` uses; nothing outside this package reaches
into its modules' private parts):

:class:`FusionCore`
    ``process(kind, t, xyz, mag_allowed)`` (checked input) or ``advance(Span, snapshot_before)`` (the
    pipeline's: rows and :class:`Snapshot` s), ``snapshot()`` / ``restore()``, ``get_state()`` /
    ``set_state()`` (JSON), ``use_calibration()`` (a calibration in force: reference strength, offset
    covariance, a change noted), ``set_field()``;
:class:`FusionSettings`
    grouped by concern: :class:`GyroSettings`, :class:`AccelSettings`, :class:`MagSettings`,
    :class:`UncertaintySettings`, :class:`InterferenceSettings`;
:mod:`~pdr_mag.fusion.kinds`
    the codes of the merged stream's samples (``ACCEL``, ``GYRO``, ``MAG``);
:func:`heading_reset_events`
    the ``heading_reset`` events of a batch of rows.

Model: an error-state (multiplicative) extended Kalman filter.

nominal state
    ``q`` attitude, device → ENU (true north when a declination is given), w-first; ``b`` gyroscope bias,
    device frame, rad/s; ``c`` the slowly varying error of the magnetometer heading, rad; ``o`` the error
    of the calibration's offset that the filter has found, device frame, µT (the field it takes is the
    calibrated one less ``o``; ``mag.offset_states``).
error state ``δx = (δθ, δb, δc, δo)``, 10 values
    ``R_true = Exp(δθ) R`` with ``δθ`` in the world frame (so ``δθ_z`` is the heading error and
    ``heading_std = √max((P + U)[δθ_z, δθ_z], g ΔΔᵀ gᵀ)``, ``U`` the consider covariance below, the
    floor an offset shift Δ the stale test suspects, seen in the heading,
    :func:`~pdr_mag.fusion.kernel.calibration_floor`), ``b_true = b + δb``, ``c_true = c + δc``,
    ``o_true = o + δo``.
prediction (:mod:`~pdr_mag.fusion.gyro`)
    ``q ← q ⊗ Exp((ω̄ − b) Δt)``; ``Φ = [[I, −R Δt, 0, 0], [0, I, 0, 0], [0, 0, φ, 0], [0, 0, 0, I]]``,
    ``φ = exp(−Δt/τ_c − |ω̄_up| Δt/θ_c)`` (c decorrelates in time and as the walker turns);
    ``Q = diag(σ_g² Δt I, σ_b² Δt I, σ_c² (1 − φ²), σ_o² Δt I)``; ``c ← φ c`` (first-order Gauss–Markov),
    ``o`` constant but for a slow random walk; gaps add their unknown rotation to ``P``; a zero-rate
    update ``ω_m = b + δb + n`` while the device is still.
accelerometer (:mod:`~pdr_mag.fusion.accel`)
    tilt only: the direction of the specific force averaged in the world frame observes the window's mean
    ``(−δθ_y, δθ_x)`` (hence also ``δb``); its noise grows with the measured dynamics and with clipped
    samples; gated on ``||ā| − g|``; the tilt starts only once the gyroscope streams.
magnetometer (:mod:`~pdr_mag.fusion.mag`)
    heading only: ``r = wrap(atan2(m_w,x, m_w,y) − D − c)`` of the field ``m − o`` observes
    ``h_t·δθ_xy + δθ_z + δc + g·δo`` (``g = ∂ψ/∂m_d``) with the tilt errors as consider states; noise
    from the field's horizontal strength and the smallest disturbance that explains the detectors'
    deviations; skipped while the interference flag (:mod:`pdr_mag.fusion.detectors`) is up, when the
    caller disallows it or beyond a χ² gate.  The stationary variance of ``c`` grows with the recent
    environment's disturbance level; a calibration in force sets ``δo``'s covariance (and ``o`` to zero);
    a field that stays clean but keeps failing
    the gate for ``mag.reacquire_s`` (or as long as the fields behind the heading span, if shorter, but two
    of c's correlation times at least) re-acquires the heading (``heading_reset``).
consider covariance ``U`` (:mod:`~pdr_mag.fusion.eskf`, :mod:`~pdr_mag.fusion.gyro`)
    the same Φ and the same gains as ``P`` (Joseph form), driven only by the part of c's stationary
    variance that the weighting leaves out,
    ``V_u = [max(k_u² d_seen² − k_e² d_env², 0) + k_f s_flag d_tol² / 2] / B_h²``
    (``k_u, k_f`` the ``uncertainty`` settings, ``k_e`` ``mag.env_k``: the unseen turning
    component of the detectors' deviations and of the disturbances behind the recent flagged share
    ``s_flag``, which a first calibration's recent fields set where the detectors judged none:
    :meth:`FusionCore.seed_flag_share`); it never changes the estimate, only the reported std.

Modules
-------
:mod:`~pdr_mag.fusion.core`
    :class:`FusionCore`, the Python face: settings, input checks, spans, snapshots, state round trip;
:mod:`~pdr_mag.fusion.settings`
    the settings groups (the kernel reads them as one record, :mod:`pdr_mag._records`);
:mod:`~pdr_mag.fusion.detectors`
    the interference detectors (strength, variance, dip, gyro consistency) and their hold-off timer;
:mod:`~pdr_mag.fusion.state`
    the state and parameter layouts (numpy records with named fields) and their JSON form;
:mod:`~pdr_mag.fusion.rows`, :mod:`~pdr_mag.fusion.kinds`
    the output rows' columns and the stream kinds, by name;
:mod:`~pdr_mag.fusion.eskf`
    the scalar Kalman updates and the injection of the error estimate;
:mod:`~pdr_mag.fusion.quat`, :mod:`~pdr_mag.fusion.ew`
    quaternion helpers and the exponential-weighting factor (leaf modules the detectors use too);
:mod:`~pdr_mag.fusion.gyro`, :mod:`~pdr_mag.fusion.accel`, :mod:`~pdr_mag.fusion.mag`
    one sensor each, with its equations in the module docstring;
:mod:`~pdr_mag.fusion.kernel`
    the run loop over a merged chunk of samples and the output rows.

To change a measurement model, edit its sensor module; a setting is a field of its group in
:mod:`~pdr_mag.fusion.settings` (the kernel's record follows); to add an interference detector, write
its module and add it to :data:`pdr_mag.fusion.detectors.DETECTORS`; to carry a
new quantity from sample to sample, add a field to :data:`~pdr_mag.fusion.state.STATE` (the JSON state
follows; bump :data:`pdr_mag.fusion.core.STATE_VERSION`).  The kernels' numba cache is refreshed when any of
these modules changes (:mod:`pdr_mag._jit_cache`).
"""

import importlib as _importlib

#: public name → module that defines it (imported on first use, so the detectors and the settings load
#: without the filter's compiled kernel, and :mod:`pdr_mag.estimates` can read the detectors' columns)
_EXPORTS = {
    "STATE_VERSION": "pdr_mag.fusion.core",
    "Advanced": "pdr_mag.fusion.core",
    "FusionCore": "pdr_mag.fusion.core",
    "Snapshot": "pdr_mag.fusion.core",
    "Span": "pdr_mag.fusion.core",
    "heading_reset_events": "pdr_mag.fusion.core",
    "InterferenceSettings": "pdr_mag.fusion.detectors",
    "StrengthSettings": "pdr_mag.fusion.detectors",
    "DipSettings": "pdr_mag.fusion.detectors",
    "VarianceSettings": "pdr_mag.fusion.detectors",
    "ConsistencySettings": "pdr_mag.fusion.detectors",
    "AccelSettings": "pdr_mag.fusion.settings",
    "FusionSettings": "pdr_mag.fusion.settings",
    "GyroSettings": "pdr_mag.fusion.settings",
    "MagSettings": "pdr_mag.fusion.settings",
    "UncertaintySettings": "pdr_mag.fusion.settings",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'pdr_mag.fusion' has no attribute {name!r}")
    value = getattr(_importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__))
