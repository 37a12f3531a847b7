"""The smartphone attitude benchmark layouts (Inria Tyrex, "On Attitude Estimation with Smartphones").

A recording is a folder of space-separated text files without header, time in seconds in the first column.

Android (Senslogs app), recognised by ``record.properties``:

==========================  =======================================================================
``accelerometer.txt``       t, ax, ay, az — m/s², specific force (``TYPE_ACCELEROMETER``)
``gyroscope.txt``           t, wx, wy, wz, drift x, y, z — rad/s, raw (``TYPE_GYROSCOPE_UNCALIBRATED``)
``magnetometer.txt``        t, mx, my, mz, bias x, y, z — µT, raw (``TYPE_MAGNETIC_FIELD_UNCALIBRATED``)
``record.properties``       ``Model``, ``Manufacturer``, ``ID``; ``StartTime`` (Unix s) of the record clock
==========================  =======================================================================

Android's device frame is the contract's: no axis change, no unit change. A row with more fields than its
file has (4, 7, 7 on Android; 4 in every iOS file) or with a field that is not a number is dropped and
counted (``<stream>:extra_fields``, ``<stream>:non_numeric``). The streams read are the raw ones
(``mag_os_calibrated`` and ``gyro_os_calibrated`` False). Their last three columns are what the OS states
about its own calibration (:mod:`replay.formats._phone`): the hard-iron estimate in force at the first
magnetometer sample, ``mag_os_bias_uT``, and its later changes, ``mag_os_bias_changes`` (the Nexus 5 walks:
(57.96, −35.74, 419.90) µT throughout Dist_Texting, two changes in NoDist_Swinging; the calibration
recordings change it 12–33 times), and the gyroscope's drift, ``gyro_os_bias_rad_s`` /
``gyro_os_bias_changes``. A first pass over the two files collects them (the streams are then read as
before); a row whose sample is kept but whose estimate is not three finite numbers (NaN, inf, a column
missing) counts as ``mag_os_bias:nan`` / ``gyro_os_bias:nan``, a row of four columns states no estimate,
and a garbled row (text in any cell, an eighth field) is dropped whole by the stream and states nothing.
``ID`` is ``meta["device_id"]``.

iOS, recognised by ``description.txt`` with ``BootTime``: the same three files, with

* time in seconds since boot: ``t = t_file - BootTime``;
* ``accelerometer.txt`` in g with iOS's sign (≈ −1 g on z lying flat, screen up), so
  ``accel = -9.80665 * a`` (iOS's device axes are Android's: x right, y top, z out of the screen);
* ``gyroscope.txt`` rad/s and ``magnetometer.txt`` µT (raw ``CMMagnetometerData``), unchanged.

Both are raw (``mag_os_calibrated``, ``gyro_os_calibrated`` False): the magnetometer is ``CMMagnetometerData``
(offsets of 100–290 µT). Its OS estimate comes from the calibrated field beside it,
``magnetometer-calibrated.txt`` (Core Motion's, device bias removed): ``mag_os_bias_uT`` is raw − calibrated
over the first two seconds (:func:`_ios_mag_bias`; (103.7, 289.6, 63.2) µT on the iPhone 5 Dist_Texting walk,
the day's calibration recording (105.8, 292.7, 62.9) µT). The gyroscope, though stamped at Core
Motion's device-motion epochs, keeps its bias — it differs from the rate of the logged attitude by a constant
(0.111, −0.023, 0.012) rad/s (median over each of the three iPhone 5 trials, within 0.005 rad/s).

The phone's own fusion, when logged, becomes ``references["os"]`` (device → ENU; a reference, and the
heading of the rows whose heading pdr_mag does not know): Android's ``rotation-vector.txt`` (t, qx, qy,
qz, qw, heading accuracy; ``TYPE_ROTATION_VECTOR``, magnetic north) and iOS's ``attitude.txt`` (t, qw, qx,
qy, qz; CoreMotion's ``XMagneticNorthZVertical`` frame, x to magnetic north, z up, so
``q_ENU = q_z(90°) ⊗ q``), both then put in the pipeline's north (:mod:`replay.formats._attitude`); odd
rows are counted as the streams' are, under ``os:`` (``os:nan``,
``os:duplicate_t``, a garbled row ``os:extra_fields`` / ``os:non_numeric``).

Truth. When the benchmark's mocap file ``../../qualisys/<trial>.mat`` and the trial's ``timeAlignment.txt``
(Δ, with ``t_qualisys = t_phone + Δ``) are present, the Qualisys rigid-body rotation (device → ENU, true
north) becomes :attr:`Recording.truth` at ``t = i / FrameRate - Δ`` on the phone clock. NaN frames are
dropped (``truth:nan``), as are the mocap glitches that the benchmark's authors exclude by hand
(``truth:glitch``). In that case ``meta`` also gets the benchmark's place and date (Kinovis room, Inria
Grenoble; the values the upstream code uses for the reference field).
"""

from __future__ import annotations

import configparser
import itertools
from collections import Counter
from pathlib import Path

import numpy as np

from pdr_mag.conventions import GRAVITY, quat_multiply, rot_to_quat
from replay.errors import InputError
from replay.formats._attitude import in_output_north, rotation_vector_quat
from replay.formats._common import (
    CHUNK,
    StreamBuilder,
    StreamSpec,
    chunks_of,
    iter_table,
    open_text,
    read_text,
    require,
    row_values,
)
from replay.formats._phone import PAIR_WINDOW_S, OsEstimate, bias_from_pair, utc_date
from replay.recording import Recording
from replay.source import Feed, RecordingSource

NAME = "tyrex"
#: Fields of a row (time first) in each file, per platform: a row with more is garbled.
FIELDS = {"android": {"mag": 7, "accel": 4, "gyro": 7}, "ios": {"mag": 4, "accel": 4, "gyro": 4}}
#: Fields of a row of the phone's own attitude: t, qx, qy, qz, qw, heading accuracy (Android's
#: ``rotation-vector.txt``); t, qw, qx, qy, qz (iOS's ``attitude.txt``).
OS_FIELDS = {"android": 6, "ios": 5}

# Mocap glitches excluded by hand upstream (qualisys seconds).
_GLITCHES = {
    "Thibaud_Nexus5_Dist_FrontPocket": [(40.0, 52.6)],
    "Thibaud_Nexus5_Dist_Swinging": [(105.45, 105.5)],
    "Thibaud_Nexus5_NoDist_Swinging": [(36.8, 37.2)],
}
# Where and when the benchmark was recorded (upstream's reference-field inputs).
_BENCH_META = {
    "latitude_deg": 45.187778,
    "longitude_deg": 5.726945,
    "altitude_m": 200.0,
    "date": "2016-05-31",
}


def _platform(path: Path) -> str | None:
    if not path.is_dir() or not (path / "magnetometer.txt").is_file():
        return None
    if (path / "record.properties").is_file():
        return "android"
    if (path / "description.txt").is_file():
        return "ios"
    return None


def detect(path: Path) -> bool:
    return _platform(path) is not None


def _properties(path: Path) -> configparser.ConfigParser:
    cp = configparser.ConfigParser(strict=False)
    try:
        cp.read_string(read_text(path), source=str(path))
    except configparser.Error as exc:
        raise InputError(path, f"not a properties file ({exc.message.splitlines()[0]})") from None
    return cp


def columns_feed(path: Path, key: str, dropped: Counter, most: int, ncol: int = 3) -> Feed:
    """A header-less, whitespace-separated file ``t v1 v2 v3 [more…]`` of at most ``most`` fields a row,
    parsed a chunk at a time."""

    def chunks():
        b = StreamBuilder(path, key, dropped, width=ncol)
        with open_text(path) as fh:
            steps = iter_table(fh, path, [(b, list(range(1, ncol + 1)))], ncol + 1, most=most)
            yield from chunks_of(fh, {key: b}, steps)

    return Feed((key,), chunks, path.stat().st_size)


def _os_estimate(path: Path, key: str, dropped: Counter) -> OsEstimate:
    """The OS's estimate in columns 5–7 of a Senslogs file (a first pass, a chunk at a time): from the rows
    whose sample the stream keeps (t, x, y, z numbers, not a repeated time, the row not garbled); rows that
    do not parse are left to the stream's own pass, which reports them."""
    most = FIELDS["android"]["mag"]  # = the gyroscope's: t, x, y, z and the estimate's x, y, z
    est = OsEstimate(key, dropped)
    last_t = -np.inf
    with open_text(path) as fh:
        while lines := list(itertools.islice(fh, CHUNK)):
            try:
                arr = np.loadtxt(lines, ndmin=2, dtype=float, comments=None)
                stated = np.ones(len(arr), dtype=bool)
            except ValueError:
                arr = np.empty((0, most))
            if arr.shape != (len(lines), most):  # a row that does not parse, a short or long one: one by one
                rows = [r for r in map(_row, lines) if r is not None]
                arr = np.array([r for r, _ in rows], dtype=float).reshape(-1, most)
                stated = np.array([s for _, s in rows], dtype=bool)
            keep = np.all(np.isfinite(arr[:, :4]), axis=1)
            arr, stated = arr[keep], stated[keep]
            t = arr[:, 0]
            sel = stated & (t != np.concatenate([[last_t], t[:-1]]))  # not a repeated time
            est.add_block(t[sel], arr[sel, 4:7])
            if len(t):
                last_t = float(t[-1])
    return est


def _ios_mag_bias(raw_path: Path, cal_path: Path, dropped: Counter) -> list[float] | None:
    """iOS's hard-iron estimate at the start of the trial (:func:`replay.formats._phone.bias_from_pair`) from
    the two fields Core Motion logs: the raw ``CMMagnetometerData`` (``magnetometer.txt``) and the calibrated
    field with the device bias removed (``magnetometer-calibrated.txt``: t, x, y, z, calibration accuracy;
    rows of accuracy −1, uncalibrated, state none). Both files are on the same (boot) clock; the calibrated
    rows are taken from the raw field's first sample on. The calibrated file's odd rows are counted under
    ``mag_os_bias`` (the raw file's by its stream)."""
    first_raw = _leading_rows(raw_path, 4, Counter(), None, most=1)
    if not len(first_raw):
        return None
    cal = _leading_rows(cal_path, 5, dropped, "mag_os_bias", start=float(first_raw[0, 0]),
                        span_s=PAIR_WINDOW_S, use=lambda v: v[4] >= 0)  # fmt: skip
    if not len(cal):
        return None
    raw = _leading_rows(raw_path, 4, Counter(), None, until=float(cal[-1, 0]) + 1.0)
    return bias_from_pair(raw[:, 0], raw[:, 1:4], cal[:, 0], cal[:, 1:4])


def _leading_rows(path: Path, width: int, dropped: Counter, key: str | None, *, start: float = -np.inf,
                  span_s: float | None = None, until: float | None = None, most: int | None = None,
                  use=None) -> np.ndarray:  # fmt: skip
    """The leading rows of a header-less whitespace-separated file of ``width`` numbers a row, in time
    order (n, width): from time ``start`` on, the rows ``use(row)`` accepts (all without it), up to
    ``span_s`` seconds after the first of them, up to time ``until``, at most ``most`` of them. A garbled
    row (:func:`~replay.formats._common.row_values`), one with a value missing or not finite (``nan``) and
    one not later than the row before (``non_monotonic``) are skipped and counted under ``key`` (None: not
    counted, for a file another pass counts)."""
    rows: list[list[float]] = []
    last_t = -np.inf
    with open_text(path) as fh:
        for line in fh:
            parts = line.split()
            if not parts:
                continue
            v = row_values(parts, width, dropped=dropped, keys=() if key is None else (key,))
            if v is None:
                continue
            odd = "nan" if len(v) != width or not all(np.isfinite(v)) else ""
            odd = odd or ("non_monotonic" if v[0] <= last_t else "")
            if odd:
                if key is not None:
                    dropped[f"{key}:{odd}"] += 1
                continue
            last_t = v[0]
            if v[0] < start or (use is not None and not use(v)):
                continue
            past_span = span_s is not None and rows and v[0] > rows[0][0] + span_s
            if past_span or (until is not None and v[0] > until):
                break
            rows.append(v)
            if most is not None and len(rows) >= most:
                break
    return np.array(rows, dtype=float).reshape(-1, width)


def _row(line: str) -> tuple[list[float], bool] | None:
    """One Senslogs row as 7 numbers (NaN for a missing cell) and whether it states an estimate (more than
    t, x, y, z); None for a blank row and for a garbled one (the streams' rule, :func:`row_values`: the
    stream's own pass drops and counts it)."""
    parts = line.split()
    most = FIELDS["android"]["mag"]
    vals = row_values(parts, most)
    if not parts or vals is None:
        return None
    return vals + [np.nan] * (most - len(vals)), len(parts) > 4


def _truth(path: Path, dropped: Counter):
    """Qualisys orientation on the phone clock, or None when the mocap file is not beside the trial."""
    mat = path.parent.parent / "qualisys" / f"{path.name}.mat"
    align = path / "timeAlignment.txt"
    if not (mat.is_file() and align.is_file()):
        return None
    try:
        delta = float(read_text(align).split()[0])
    except (ValueError, IndexError):
        raise InputError(align, "expected one number (seconds)", 1) from None
    from scipy.io import loadmat

    try:
        m = loadmat(mat, squeeze_me=True, struct_as_record=False)
        body = m[path.name]
        rate = float(body.FrameRate)
        rot = np.asarray(body.RigidBodies.Rotations, dtype=float)
    except (KeyError, AttributeError, ValueError, OSError) as exc:
        raise InputError(mat, f"not a Qualisys export with RigidBodies.Rotations ({exc})") from None
    if rot.ndim != 2 or rot.shape[0] != 9:
        raise InputError(mat, f"RigidBodies.Rotations has shape {rot.shape}, expected 9×N")
    t_q = np.arange(rot.shape[1]) / rate
    good = np.all(np.isfinite(rot), axis=0)
    dropped["truth:nan"] += int((~good).sum())
    glitch = np.zeros_like(good)
    for a, b in _GLITCHES.get(path.name, []):
        glitch |= (t_q >= a) & (t_q <= b)
    dropped["truth:glitch"] += int((glitch & good).sum())
    keep = good & ~glitch
    # Column-major 3×3 per frame: R maps phone-body vectors into the mocap (ENU, true north) world frame.
    mats = rot[:, keep].T.reshape(-1, 3, 3).transpose(0, 2, 1)
    q = rot_to_quat(mats)
    q = q * np.where(q[:, :1] < 0, -1.0, 1.0)
    for k in ("truth:nan", "truth:glitch"):
        if dropped.get(k) == 0:
            del dropped[k]
    return t_q[keep] - delta, q


def read(path) -> Recording:
    """Read an Android (Senslogs) or iOS trial folder of the benchmark into a :class:`Recording`."""
    return open_source(path).collect()


def open_source(path) -> RecordingSource:
    """Open an Android (Senslogs) or iOS trial folder: metadata and truth now, the streams when read."""
    p = Path(path)
    platform = _platform(p)
    if platform is None:
        raise InputError(
            p, "not a tyrex benchmark folder (magnetometer.txt + record.properties/description.txt)"
        )
    dropped: Counter = Counter()
    meta: dict = {"platform": platform}
    if platform == "android":
        cp = _properties(p / "record.properties")
        model = cp.get("Device", "Model", fallback="").strip()
        maker = cp.get("Device", "Manufacturer", fallback="").strip()
        if model:
            meta["device"] = f"{maker} {model}".strip()
        device_id = cp.get("Device", "ID", fallback="").strip()
        if device_id:
            meta["device_id"] = device_id
        start = cp.get("Time", "StartTime", fallback="").strip()
        if start:
            try:
                start_s = float(start)
            except ValueError:
                raise InputError(p / "record.properties", f"StartTime is not a number: {start!r}") from None
            meta["start_time_unix"] = start_s
            meta["date"] = utc_date(start_s)
        t_off = 0.0
    else:
        cp = _properties(p / "description.txt")
        boot = cp.get("Time", "BootTime", fallback=None)
        if boot is None:
            raise InputError(p / "description.txt", "no BootTime under [Time]")
        try:
            t_off = -float(boot)
        except ValueError:
            raise InputError(p / "description.txt", f"BootTime is not a number: {boot!r}") from None
        meta["device"] = "iPhone"
        meta["boot_time"] = -t_off

    files = {
        "mag": require(p / "magnetometer.txt", "magnetometer stream"),
        "accel": require(p / "accelerometer.txt", "accelerometer stream"),
        "gyro": require(p / "gyroscope.txt", "gyroscope stream"),
    }
    specs = {
        "mag": StreamSpec(files["mag"], "mag", t_offset=t_off, unit_hint="µT"),
        "accel": StreamSpec(files["accel"], "accel", unit_hint="m/s²")
        if platform == "android"
        else StreamSpec(files["accel"], "accel", scale=-GRAVITY, t_offset=t_off, unit_hint="g, iOS sign"),
        "gyro": StreamSpec(files["gyro"], "gyro", t_offset=t_off, unit_hint="rad/s"),
    }
    feeds = [columns_feed(f, k, dropped, FIELDS[platform][k]) for k, f in files.items()]
    meta["mag_os_calibrated"] = meta["gyro_os_calibrated"] = False
    if platform == "android":
        for key, f in (("mag_os_bias", files["mag"]), ("gyro_os_bias", files["gyro"])):
            _os_estimate(f, key, dropped).to_meta(meta)
    elif (p / "magnetometer-calibrated.txt").is_file():
        bias = _ios_mag_bias(files["mag"], p / "magnetometer-calibrated.txt", dropped)
        if bias is not None:
            meta["mag_os_bias_uT"] = bias
            meta["mag_os_bias_changes"] = []
    truth = _truth(p, dropped)
    if truth is not None:
        meta.update({k: v for k, v in _BENCH_META.items() if k != "date" or "date" not in meta})
        meta["truth_north"] = "true"
    references = {}
    os_ref = _os_attitude(p, platform, t_off, meta, dropped)
    if os_ref is not None:
        references["os"] = os_ref
    return RecordingSource(
        specs, feeds, meta=meta, truth=truth, references=references, source=str(p),
        format=f"{NAME}-{platform}", dropped=dropped,
    )


def _os_attitude(path: Path, platform: str, t_off: float, meta: dict, dropped: Counter):
    """The phone's own attitude (``rotation-vector.txt`` / ``attitude.txt``) in the pipeline's north, or
    None when the trial has none."""
    f = path / ("rotation-vector.txt" if platform == "android" else "attitude.txt")
    if not f.is_file():
        return None
    t, v = [], []
    for _, chunk in columns_feed(f, "os", dropped, OS_FIELDS[platform], ncol=4).chunks():
        if "os" in chunk:
            t.append(chunk["os"][0])
            v.append(chunk["os"][1])
    if not t:
        return None
    t, v = np.concatenate(t), np.concatenate(v)
    if platform == "android":  # x, y, z, w
        q = rotation_vector_quat(v[:, :3], v[:, 3])
    else:  # w, x, y, z in CoreMotion's x-north, z-up frame: turned +90° about Up into ENU
        up90 = np.array([np.sqrt(0.5), 0.0, 0.0, np.sqrt(0.5)])
        q = quat_multiply(up90, rotation_vector_quat(v[:, 1:], v[:, 0]))
    return t + t_off, in_output_north(q, meta)
