"""The fusion filter's state and parameters, each in named fields.

The compiled kernels (:mod:`pdr_mag.fusion.kernel` and the modules it calls) read and write one record of
:data:`STATE`, read one record of :data:`PARAMS` (the :class:`~pdr_mag.fusion.settings.FusionSettings` in
the kernel's units, the detectors' thresholds nested in it), and write their output into the named columns of
:class:`pdr_mag.fusion.rows.Rows`.  A numpy record is what numba compiles against with ``cache=True``: its
fields are read by name at native speed, a copy of the record is a snapshot, and :func:`state_to_json` /
:func:`state_from_json` turn it into a JSON dict and back exactly.

Error state (the rows and columns of ``P`` and ``U``): ``δθ`` (3, world frame; ``δθ_z`` is the heading
error), ``δb`` (3, device frame, rad/s), ``δc`` (1, rad), ``δo`` (3, device frame, µT) — see
:mod:`pdr_mag.fusion` for the model.
"""

from __future__ import annotations

import functools

import numpy as np

from pdr_mag._json import state_float
from pdr_mag._records import copy_record, settings_dtype
from pdr_mag.fusion.detectors import DETECTOR_STATE, new_detector_state
from pdr_mag.fusion.settings import FusionSettings

#: size of the error state (δθ, δb, δc, δo)
NX = 10
#: rows of ``P``: attitude error about east, north, up (world frame), the first of the three gyro-bias errors
#: (device x, y, z), the magnetometer heading error c, the first of the three offset errors (device frame, µT)
TH_X, TH_Y, TH_Z, BIAS, C_ERR, OFFSET = 0, 1, 2, 3, 6, 7

#: exponentially weighted mean and mean square deviation of a 3-vector stream (the still detector)
EW_STATS = np.dtype([("mean", np.float64, (3,)), ("var", np.float64)], align=True)

#: everything the filter carries from one sample to the next
STATE = np.dtype(
    [
        # the filter: nominal state and covariance of the error state
        ("q", np.float64, (4,)),  # attitude, device → ENU (true north with a declination), w-first
        ("b", np.float64, (3,)),  # gyroscope bias, device frame, rad/s
        ("bias0_var", np.float64),  # variance per axis of the bias prior, (rad/s)² (NaN: gyro.bias0_std²)
        ("c", np.float64),  # magnetometer heading error (Gauss–Markov), rad
        ("offset", np.float64, (3,)),  # the calibration's offset error o: the field taken is m − o, µT
        ("turn_rate", np.float64),  # rate about the world's up, averaged over a stride (c's turn), rad/s
        ("P", np.float64, (NX, NX)),  # covariance of (δθ, δb, δc, δo)
        ("U", np.float64, (NX, NX)),  # consider covariance: the part of the error the weighting leaves out
        ("u_G", np.float64, (3, 3)),  # prediction not yet applied to U: −Σ R Δt over the steps since
        ("u_phi", np.float64),  # … and Π φ over them (pdr_mag.fusion.eskf.settle_u)
        ("u_pending", np.bool_),  # such steps exist
        ("u_var", np.float64),  # V_u, the part of c's stationary variance the weighting leaves out, rad²
        ("init", np.int64),  # 0 nothing yet, 1 tilt from the accelerometer, 2 heading from the magnetometer
        ("q_gyro", np.float64, (4,)),  # gyroscope-only attitude from the same start (diagnostics)
        # gyroscope
        ("have_gyro", np.bool_),
        ("t_gyro", np.float64),  # time of the last gyroscope sample, s
        ("w_gyro", np.float64, (3,)),  # last raw rate, rad/s
        # still detector (zero-rate updates)
        ("gyro_stats", EW_STATS),  # of the rate, rad/s
        ("acc_stats", EW_STATS),  # of the specific force, m/s²
        ("still_since", np.float64),  # start of the current still period, s (NaN: moving)
        # accelerometer
        ("have_acc", np.bool_),
        ("t_acc", np.float64),  # time of the last accelerometer sample, s
        ("t_acc_prev", np.float64),  # time of the one before, s
        ("acc_w", np.float64, (3,)),  # EW mean ā_w of the world-frame specific force, m/s² (NaN: restart)
        ("acc_peak", np.float64),  # largest |a_i| of any axis seen, m/s² (the range, if it clips)
        ("acc_peak_hits", np.int64),  # samples that reached within accel.clip_band of acc_peak
        ("clip_share", np.float64),  # EW share of clipped samples in the window of ā_w
        ("acc_spread", np.float64),  # EW mean of |a_w,h − ā_w,h|², the horizontal spread about ā_w, (m/s²)²
        ("R_bar", np.float64, (3, 3)),  # EW mean of R (device → world) over the same window
        ("t_acc_update", np.float64),  # time of the last averaged-accelerometer update, s
        ("t_acc_w0", np.float64),  # time the average ā_w (re)started, s
        ("acc_w_long", np.float64, (3,)),  # the same average over accel.tilt_reset_tau_s (strides), m/s²
        ("tilt_resets", np.int64),  # tilt resets so far (the average far outside the tilt's uncertainty)
        # magnetometer
        ("declination", np.float64),  # D, rad (0: magnetic north)
        ("f_ref", np.float64),  # reference strength of the detectors, µT (NaN: unknown)
        ("dip_ref", np.float64),  # reference inclination, deg (NaN: learnt)
        ("t_mag_update", np.float64),  # time of the last heading update, s
        ("t_reject", np.float64),  # last gate rejection of a clean-looking field, s (NaN: last one accepted)
        ("t_reject_start", np.float64),  # start of the current run of such rejections, s (NaN: none)
        ("t_heading_set", np.float64),  # since when the fields the heading rests on were taken, s (NaN: none)
        ("reject_r0", np.float64),  # the run's first innovation, rad
        ("reject_line", np.float64, (5,)),  # EW means of τ, τ², x, τx, x² (x = wrap(r − r0), τ = t − start)
        ("guess_w", np.float64),  # summed weight of the flagged fields in the heading guess (0: no guess)
        ("fix_beyond_linear", np.bool_),  # the first fix may be beyond the linear range (tilt, history)
        ("reset_jump", np.float64),  # heading re-acquisitions since the last row: their summed jump, rad
        ("cal_cov", np.float64, (3, 3)),  # covariance of the calibration's offset, device frame, µT²
        ("cal_var", np.float64),  # g Σ_b gᵀ at the latest sample, rad² (read without offset states only)
        ("cal_g", np.float64, (3,)),  # ∂ψ/∂m_d at that sample, rad/µT (the std's floor, g Σ_b gᵀ, from it)
        ("cal_m", np.float64, (3,)),  # that sample's calibrated field, device frame, µT (NaN: none yet)
        ("suspect_cov", np.float64, (3, 3)),  # ΔΔᵀ of an offset shift the stale test suspects, µT² (0: none)
        ("cal_jump_d", np.float64, (3, 3)),  # a calibration change: the old field is m − (D m + e), m the new
        ("cal_jump_e", np.float64, (3,)),  # … (µT, device frame; both zero: no change pending)
        ("t_cal_start", np.float64),  # since when the calibration in force shapes the heading, s
        ("env_d2", np.float64),  # EW mean of d_min², the disturbances of the recent environment, µT²
        ("t_env", np.float64),  # time of its last sample, s
        ("env_seen2", np.float64),  # the same mean over the samples seen only (no prior), µT²
        ("env_w", np.float64),  # its EW weight of the samples seen (1 − e^(−(t − t_first)/τ))
        ("flag_share", np.float64),  # EW share of flagged samples over mag.env_tau_s (of the weight seen)
        ("flag_w", np.float64),  # the EW weight of the samples seen so far (1 − e^(−T/τ) at uniform rate)
        ("flag_d2", np.float64),  # the detectors' tolerance as a disturbance, tol_F² + (F tol_I)², µT²
        ("t_flag", np.float64),  # time of the last sample in flag_share, s
        ("bh_ref", np.float64),  # horizontal strength of the local reference field, µT (NaN: unknown)
        ("det", DETECTOR_STATE),  # the interference detectors (pdr_mag.fusion.detectors)
        # output rows
        ("t_next_out", np.float64),  # grid time of the next output row, s
        ("mag_used", np.bool_),  # the magnetometer corrected the heading since the last row
        ("interference_seen", np.bool_),  # the flag was up since the last row
    ],
    align=True,
)

#: the settings in the kernel's units (:class:`pdr_mag.fusion.settings.FusionSettings`, built by
#: :func:`pdr_mag._records.settings_dtype`): one nested record per group (``p.gyro``, ``p.accel``, ``p.mag``,
#: ``p.uncertainty``, ``p.interference``), ``*_rad`` for the settings ``*_deg`` and ``out_dt_s`` (0: every
#: gyro sample) for ``output_rate_hz``
PARAMS = settings_dtype(FusionSettings)

def new_state() -> np.ndarray:
    """A filter that has seen nothing: a one-element array of :data:`STATE` (the kernels take its record)."""
    return copy_record(_fresh_state())


@functools.cache
def _fresh_state() -> np.ndarray:
    st = np.zeros(1, dtype=STATE)
    st["q"] = st["q_gyro"] = (1.0, 0.0, 0.0, 0.0)
    for name in (
        "t_gyro",
        "still_since",
        "t_acc",
        "t_acc_prev",
        "acc_w",
        "t_acc_update",
        "t_acc_w0",
        "f_ref",
        "dip_ref",
        "t_mag_update",
        "t_reject",
        "t_reject_start",
        "t_heading_set",
        "t_env",
        "t_flag",
        "bh_ref",
        "t_next_out",
        "bias0_var",
        "t_cal_start",
        "cal_m",
    ):
        st[name] = np.nan
    st["u_phi"] = 1.0
    st["det"] = new_detector_state()
    return st


# ------------------------------------------------------------------------------------------ JSON
def state_to_json(rec: np.void) -> dict:
    """A record as a JSON-serialisable dict: field name → number, nested list or dict (a nested record);
    non-finite floats as :func:`pdr_mag._json.state_float` strings, so the round trip is exact."""
    out = {}
    for name in rec.dtype.names:
        v = rec[name]
        if v.dtype.names is not None:
            out[name] = state_to_json(v)
        elif v.dtype == np.bool_:
            out[name] = bool(v)
        elif np.issubdtype(v.dtype, np.integer):
            out[name] = int(v)
        elif v.ndim:
            out[name] = np.vectorize(state_float, otypes=[object])(v).tolist()
        else:
            out[name] = state_float(v)
    return out


def state_from_json(dtype: np.dtype, obj, where: str = "state") -> np.ndarray:
    """The one-element array of ``dtype`` that :func:`state_to_json` wrote; ``ValueError`` naming the field
    when a field is missing or has the wrong shape."""
    if not isinstance(obj, dict):
        raise ValueError(f"{where}: expected a dict of the fields of {sorted(dtype.names)}")
    rec = np.zeros(1, dtype=dtype)
    for name in dtype.names:
        sub = dtype[name]
        if name not in obj:
            raise ValueError(f"{where}.{name}: missing")
        if sub.names is not None:
            rec[name] = state_from_json(sub, obj[name], f"{where}.{name}")
            continue
        try:
            v = np.array(obj[name], dtype=np.float64) if sub.base != np.bool_ else np.array(obj[name])
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{where}.{name}: expected numbers ({exc})") from exc
        if v.shape != sub.shape:
            raise ValueError(f"{where}.{name}: expected shape {sub.shape}, got {v.shape}")
        rec[name] = v
    return rec
