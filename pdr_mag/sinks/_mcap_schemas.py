"""Schemas of the MCAP sink: ``ros2msg`` definitions with their CDR byte layouts, and two JSON schemas.

High-rate, fixed-layout messages are CDR (``message_encoding="cdr"``) with ``ros2msg`` schemas: Foxglove
decodes both natively (no ROS install), and a fixed layout lets the sink encode a whole batch with one numpy
structured array instead of formatting each message.  Low-rate, free-form messages (events, calibrations)
stay JSON with JSON schemas.

CDR, as ROS 2 writes it (XCDR1, little endian): a 4-byte encapsulation header ``00 01 00 00``, then the
fields in order, each primitive aligned to its own size *counted from the end of that header*; a string is a
``uint32`` length (including the terminating NUL), the bytes and the NUL.  :func:`cdr_dtype` turns a field
list into a numpy dtype with exactly those offsets (padding left as zero bytes).  ROS 2 field names are
lower case, so the diagnostic columns are :data:`DIAG_FIELDS` (``DIAG_KEYS`` lower-cased).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from pdr_mag.estimates import DIAG_KEYS

#: CDR encapsulation header, little endian (``CDR_LE``), as one ``<u4``: bytes 00 01 00 00.
CDR_LE = 0x0100
_SEP = "=" * 80

#: Extra columns of ``/pdr/diag``: the detector bands, from the reference and tolerance columns.
BANDS = {
    "strength_lower_uT": "field_ref_uT - strength_tol_uT",
    "strength_upper_uT": "field_ref_uT + strength_tol_uT",
    "dip_lower_deg": "dip_ref_deg - dip_tol_deg",
    "dip_upper_deg": "dip_ref_deg + dip_tol_deg",
}
#: Diagnostic column (``DIAG_KEYS`` and :data:`BANDS`) → its ROS 2 field name in ``pdr_mag/msg/Diagnostics``.
DIAG_FIELDS = {k: k.lower() for k in (*DIAG_KEYS, *BANDS)}


@dataclass(frozen=True)
class Schema:
    """A schema record and the message encoding of the channels that use it."""

    name: str
    encoding: str  # "ros2msg" or "jsonschema"
    message_encoding: str  # "cdr" or "json"
    text: str  # the schema record's data (msg definition or JSON)


def cdr_dtype(fields: list[tuple[str, str]], prefix: int = 0) -> np.dtype:
    """Numpy dtype of a CDR message: ``encapsulation`` (``<u4``) then ``fields`` at CDR-aligned offsets.

    ``fields`` are ``(name, numpy type)`` pairs (``"<f8"``, ``"<u4"``, ``"?"``, ``"S4"`` for string bytes,
    aligned to 1).  ``prefix`` shifts every offset (room for the MCAP message-record header in front), so
    one structured array holds whole records.
    """
    names, formats, offsets = ["encapsulation"], ["<u4"], [prefix]
    pos = 0  # position after the encapsulation header, the origin of the alignment
    for name, fmt in fields:
        dt = np.dtype(fmt)
        align = 1 if dt.kind in "SV" else dt.itemsize
        pos += -pos % align
        names.append(name)
        formats.append(dt)
        offsets.append(prefix + 4 + pos)
        pos += dt.itemsize
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": prefix + 4 + pos})


# ---------------------------------------------------------------------- ros2msg definitions
VECTOR3_MSG = """\
# A 3-vector at the recording time t, device frame (unit in the channel metadata "unit")
# t: recording clock, s, exactly as read; log_time = round(t * 1e9) + time_offset_ns
float64 t
float64 x
float64 y
float64 z
"""
VECTOR3_FIELDS = [("t", "<f8"), ("x", "<f8"), ("y", "<f8"), ("z", "<f8")]

#: foxglove_msgs/msg/PoseInFrame (Foxglove's well-known schema, ROS 2 form) with its dependencies.
POSE_MSG = f"""\
# foxglove_msgs/msg/PoseInFrame: a timestamped pose for an object or reference frame in 3D space
builtin_interfaces/Time timestamp
string frame_id
geometry_msgs/Pose pose
{_SEP}
MSG: builtin_interfaces/Time
int32 sec
uint32 nanosec
{_SEP}
MSG: geometry_msgs/Pose
geometry_msgs/Point position
geometry_msgs/Quaternion orientation
{_SEP}
MSG: geometry_msgs/Point
float64 x
float64 y
float64 z
{_SEP}
MSG: geometry_msgs/Quaternion
float64 x
float64 y
float64 z
float64 w
"""
#: The frame of every pose; constant, so the CDR pose message has a fixed size.
POSE_FRAME = b"enu"
POSE_FIELDS = [
    ("sec", "<i4"),
    ("nanosec", "<u4"),
    ("frame_len", "<u4"),
    ("frame_id", f"S{len(POSE_FRAME) + 1}"),
    ("px", "<f8"),
    ("py", "<f8"),
    ("pz", "<f8"),
    ("qx", "<f8"),
    ("qy", "<f8"),
    ("qz", "<f8"),
    ("qw", "<f8"),
]

HEADING_MSG = """\
# Heading output of the pipeline (the replay --out-csv columns); NaN where not available
# t: recording clock, s
float64 t
float64 heading_deg
float64 heading_std_deg
bool mag_used
bool interference
# calibration state: none, offset, sphere, ellipsoid, ...
string cal_state
"""
HEADING_FIXED = [
    ("t", "<f8"),
    ("heading_deg", "<f8"),
    ("heading_std_deg", "<f8"),
    ("mag_used", "?"),
    ("interference", "?"),
    ("cal_len", "<u4"),
]


@lru_cache(maxsize=8)
def heading_dtype(width: int, prefix: int = 0) -> np.dtype:
    """Heading record dtype with room for a ``cal_state`` of up to ``width - 1`` bytes (+ NUL)."""
    return cdr_dtype([*HEADING_FIXED, ("cal_state", f"S{width}")], prefix)


HEADING_REF_MSG = """\
# Heading of a reference orientation (truth, the phone's own), deg from north
# t: recording clock, s
float64 t
float64 heading_deg
"""
HEADING_REF_FIELDS = [("t", "<f8"), ("heading_deg", "<f8")]


def _diag_msg() -> str:
    lines = [
        "# Diagnostic columns of the pipeline (DIAG_KEYS, lower-cased); NaN where not available",
        "# t: recording clock, s",
        "float64 t",
    ]
    for key, field in DIAG_FIELDS.items():
        doc = DIAG_KEYS.get(key) or BANDS[key]
        lines += [f"# {key}: {doc}", f"float64 {field}"]
    return "\n".join(lines) + "\n"


DIAG_MSG = _diag_msg()
DIAG_COLUMNS = [("t", "<f8")] + [(f, "<f8") for f in DIAG_FIELDS.values()]

# ---------------------------------------------------------------------- JSON schemas (low-rate topics)
_TIME = {
    "type": "object",
    "title": "time",
    "properties": {
        "sec": {"type": "integer", "minimum": 0},
        "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999},
    },
}
_NUM = {"type": "number"}
_NUM_OR_NULL = {"type": ["number", "null"]}

LOG_JSON = {
    "title": "foxglove.Log",
    "description": "A log message",
    "type": "object",
    "properties": {
        "timestamp": _TIME,
        "level": {
            "title": "foxglove.LogLevel",
            "type": "integer",
            "oneOf": [
                {"title": name, "const": i}
                for i, name in enumerate(("UNKNOWN", "DEBUG", "INFO", "WARNING", "ERROR", "FATAL"))
            ],
        },
        "message": {"type": "string"},
        "name": {"type": "string"},
        "file": {"type": "string"},
        "line": {"type": "integer", "minimum": 0},
    },
}
CALIBRATION_JSON = {
    "title": "pdr_mag.MagCalibration",
    "description": "A magnetometer calibration (calibrate --json object of INTERFACE.md) at time t",
    "type": "object",
    "properties": {
        "t": _NUM,
        "format_version": {"type": "integer"},
        "method": {"type": "string"},
        "offset_uT": {"type": "array", "items": _NUM},
        "soft_iron": {"type": "array", "items": {"type": "array", "items": _NUM}},
        "field_uT": _NUM_OR_NULL,
        "residual_rms_uT": _NUM_OR_NULL,
        "offset_std_uT": {"type": "array", "items": _NUM_OR_NULL},
        "n_samples": {"type": "integer"},
        "coverage": _NUM_OR_NULL,
        "accepted": {"type": "boolean"},
        "reasons": {"type": "array", "items": {"type": "string"}},
    },
    "required": ["t", "offset_uT", "soft_iron"],
}


def _json(obj: dict) -> str:
    import json

    return json.dumps(obj)


#: Every schema the sink writes, by a short key.
SCHEMAS: dict[str, Schema] = {
    "vector3": Schema("pdr_mag/msg/Vector3Stamped", "ros2msg", "cdr", VECTOR3_MSG),
    "pose": Schema("foxglove_msgs/msg/PoseInFrame", "ros2msg", "cdr", POSE_MSG),
    "heading": Schema("pdr_mag/msg/Heading", "ros2msg", "cdr", HEADING_MSG),
    "heading_ref": Schema("pdr_mag/msg/HeadingReference", "ros2msg", "cdr", HEADING_REF_MSG),
    "diag": Schema("pdr_mag/msg/Diagnostics", "ros2msg", "cdr", DIAG_MSG),
    "log": Schema("foxglove.Log", "jsonschema", "json", _json(LOG_JSON)),
    "calibration": Schema("pdr_mag.MagCalibration", "jsonschema", "json", _json(CALIBRATION_JSON)),
}
