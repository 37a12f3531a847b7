"""Readers: one module per format, each converting units and axes into the contract (INTERFACE.md).

:func:`open_recording` detects the format of a path and returns a :class:`replay.source.RecordingSource`:
the recording's metadata, and its sensor streams read as they are consumed, a chunk at a time, never whole
(:mod:`replay.source`). :func:`read_recording` collects one into a :class:`replay.recording.Recording`.

Streaming
---------
Every reader streams, except the MATLAB files of ``broad`` (``scipy.io.loadmat`` cannot read a variable
in parts; those are small research recordings): they are loaded whole, then served through the same source
API. Readers of several files (``pdr-csv``, ``tyrex``, ``sunsided-marg``, ``sensor-logger``, ``phyphox``)
have one lazily advanced parser per file; readers of one interleaved file (``ipin``, ``ms-indoor``,
``xio-csv``, ``pdr-mcap``, ``ros2-mcap``) demultiplex it in one pass. Where metadata needs the whole file —
IPIN's clock shift and fixes, ms-indoor's choice of raw or calibrated streams and its waypoints, pdr-mcap's
truth topics — a first pass collects it without keeping samples (the file is parsed twice). Because the
checks run as the samples stream, an error late in a file is raised after the earlier slices went through
the pipeline; it is the same one-line :class:`InputError`. The evaluation-only series (truth — e.g. the
tyrex Qualisys ``.mat`` —, the phone's own orientation, temperature) are loaded whole: they are small and
never read by the pipeline. ``replay`` streams; ``calibrate`` and ``diagnose`` fit batches and collect.

Detection
---------
Every reader module has ``NAME`` (str), ``detect(path) -> bool``, ``open_source(path) -> RecordingSource``
and ``read(path) -> Recording`` (``open_source(path).collect()``).
``detect`` is cheap and certain: it looks at file names, a header line or a file's magic bytes — never at the
whole file — and it never raises. :data:`READERS` lists the modules in the order they are asked; the first
that recognises the path reads it. A path that no reader recognises is an :class:`InputError`.
A reader may also be chosen by name with ``read_recording(path, fmt=NAME)``.

Formats (module → ``NAME``): ``pdrcsv`` → ``pdr-csv`` (the contract's layout); ``tyrex`` → ``tyrex``
(smartphone attitude benchmark, Android Senslogs and iOS layouts, Qualisys truth); ``sunsided`` →
``sunsided-marg`` (breadboard MPU6050 + HMC5883L); ``sensorlogger`` → ``sensor-logger`` and ``phyphox`` →
``phyphox`` (phone-app CSV exports, folder or zip); ``msindoor`` → ``ms-indoor`` (Indoor Location
Competition 2.0 logs); ``ipin`` → ``ipin`` (IPIN/GetSensorData logfiles); ``broad`` → ``broad`` (BROAD
MATLAB files, OptiTrack truth); ``xio`` → ``xio-csv`` (x-io CSV); ``pdrmcap`` → ``pdr-mcap`` (our own
MCAP, the layout of :mod:`pdr_mag.sinks.mcap`); ``rosmcap`` → ``ros2-mcap`` (ROS 2 ``sensor_msgs`` Imu +
MagneticField).

Errors and odd samples
----------------------
A file that cannot be right (missing stream, bad header, a last row with fewer fields than the format needs
— a truncated file —, time going backwards — also across chunks —, implausible unit) raises
:class:`~replay.errors.InputError` naming the file and, for text, the line. The unit is judged on a
stream's first :data:`~replay.formats._common.UNIT_CHECK_SAMPLES` samples (median vector norm), a stream too
short when it ends (its message then names the odd samples dropped from it). Odd samples are counted in
``Recording.dropped`` under ``"<stream>:<reason>"``:

* ``nan`` (a NaN/inf/null value) and ``duplicate_t`` (the previous sample's time again): dropped;
* ``not_unit`` (an attitude row — the truth, the phone's own — whose quaternion is far from norm 1, e.g. all
  zero): dropped;
* ``extra_fields`` (a text row with more fields than the header or the format defines) and ``non_numeric``
  (a field anywhere in the row that is not a number): a garbled row, dropped whole, never read in part —
  one rule and one count for every text reader, :func:`replay.formats._common.row_values`; ``short_row``
  (a row with fewer fields than the format needs, with more rows after it: a write cut short and resumed,
  :class:`replay.formats._common.ShortRows`) the same;
* ``implausible`` (an axis beyond :data:`~replay.formats._common.PHYSICAL_LIMITS`, about twice the widest
  range any sensor of the kind offers: a corrupt number, not a measurement): dropped;
* ``saturated`` (an accelerometer/gyroscope axis at the sensor's range): **kept**, counted — from the range
  the format states, else from :func:`replay.formats._common.flag_saturation`'s heuristic, run as the
  stream goes (:class:`~replay.formats._common.Saturation`: the same count, known when the stream ends);
* format-specific: ``truth:nan``/``truth:glitch`` (mocap occlusions), ``mag:held_repeat`` (a
  sample-and-hold repeat), ``accel:no_gravity_sample`` (Sensor Logger's user acceleration without a
  gravity sample at the same time), ``mag_os_bias:nan``/``gyro_os_bias:nan`` (an OS estimate's value
  NaN, infinite or missing; text in it makes the row garbled).

The phone's own attitude (``references["os"]``) counts its odd rows by the same names, under ``os:``; where
its records are read among the others' (``ms-indoor``, ``ipin``), one too short is counted as ``os:nan`` (a
value missing) rather than ending the read, the series being a reference, not a sensor stream.

What the phone states about itself
----------------------------------
Every reader puts into ``meta`` what its file states about the phone's own calibration — the OS's
hard-iron and gyro-drift estimates at the first sample and their later changes, whether the streams read
are OS-calibrated — and the date, place and device id it states (keys in INTERFACE.md, "Recording
``meta``"; helpers in :mod:`replay.formats._phone`); each reader's docstring says what its format has.
Where the estimates are spread over the file they are collected by the first pass (``ms-indoor``) or one
of their own (``tyrex`` Android: the two files' estimate columns, read before the streams).
"""

from __future__ import annotations

import importlib
from pathlib import Path

from replay.errors import InputError
from replay.formats import _mcap
from replay.recording import Recording

#: Reader modules (under ``replay.formats``), in detection order: specific layouts before generic ones.
READERS = (
    "pdrcsv",
    "tyrex",
    "sunsided",
    "sensorlogger",
    "phyphox",
    "msindoor",
    "ipin",
    "broad",
    "xio",
    "pdrmcap",
    "rosmcap",
)


def _modules():
    for name in READERS:
        try:
            yield importlib.import_module(f"replay.formats.{name}")
        except ModuleNotFoundError as exc:  # a reader not written yet is simply absent
            if exc.name != f"replay.formats.{name}":
                raise


def formats() -> list[str]:
    """Names of the formats the readers recognise."""
    return [m.NAME for m in _modules()]


def detect(path) -> str | None:
    """Name of the format of ``path``, or None."""
    p = Path(path)
    for mod in _modules():
        try:
            if mod.detect(p):
                return mod.NAME
        except OSError:
            continue
    return None


def read_recording(path, fmt: str | None = None) -> Recording:
    """Read any recording a reader recognises, whole; raises :class:`InputError` otherwise."""
    return open_recording(path, fmt).collect()


def open_recording(path, fmt: str | None = None):
    """Open any recording a reader recognises as a :class:`replay.source.RecordingSource` (streaming)."""
    p = Path(path)
    return _reader(p, fmt).open_source(p)


def _reader(p: Path, fmt: str | None):
    """The reader module for ``p`` (by name when ``fmt`` is given), else InputError."""
    if not p.exists():
        raise InputError(p, "no such file or directory")
    mods = list(_modules())
    if fmt is not None:
        for mod in mods:
            if mod.NAME == fmt:
                return mod
        raise InputError(p, f"unknown format {fmt!r} (known: {', '.join(m.NAME for m in mods)})")
    for mod in mods:
        try:
            hit = mod.detect(p)
        except OSError:
            hit = False
        if hit:
            return mod
    if p.is_file():
        with p.open("rb") as fh:
            head = fh.read(8)
        if head.startswith(b"\x89MCAP"):
            raise InputError(p, _mcap.why_unknown(p))
        if head.startswith(b"MATLAB"):
            raise InputError(
                p,
                "a MATLAB file without a known layout's variables (imu_mag, imu_acc, imu_gyr), or truncated",
            )
    raise InputError(
        p, "not a recording in a known format (expected one of: " + ", ".join(m.NAME for m in mods) + ")"
    )
