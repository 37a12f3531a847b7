"""Schemas of the MCAP sink: ``ros2msg`` definitions for the high-rate topics, JSON schemas for the rest.

High-rate messages are CDR (``message_encoding="cdr"``) with ``ros2msg`` schemas: Foxglove decodes both
natively (no ROS install), and ``mcap-ros2-support`` encodes them from these definitions.  ROS 2 field names
are lower case, so the diagnostic columns are :data:`DIAG_FIELDS` (``DIAG_KEYS`` lower-cased).  Low-rate,
free-form messages (events, calibrations) are JSON with JSON schemas; events use Foxglove's ``foxglove.Log``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

from pdr_mag.estimates import DIAG_KEYS
from pdr_mag.fusion.detectors import BANDS as DETECTOR_BANDS

_SEP = "=" * 80

#: Extra columns of ``/pdr/diag``: the bands of the detectors that have one
#: (:data:`pdr_mag.fusion.detectors.BANDS`), column → (its band, −1 / +1): ``<detector>_lower_<unit>`` /
#: ``_upper_`` = reference ∓ tolerance.
BAND_COLUMNS = {
    f"{name}_{side}_{band.unit}": (band, sign)
    for name, band in DETECTOR_BANDS.items()
    for side, sign in (("lower", -1.0), ("upper", 1.0))
}
#: The same columns → their meaning, for the schema's comments.
BANDS = {
    col: f"{band.reference} {'-' if sign < 0 else '+'} {band.tolerance}"
    for col, (band, sign) in BAND_COLUMNS.items()
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


# ---------------------------------------------------------------------- ros2msg definitions
VECTOR3_MSG = """\
# A 3-vector at the recording time t, device frame (unit in the channel metadata "unit")
# t: recording clock, s, exactly as read; log_time = round(t * 1e9) + time_offset_ns
float64 t
float64 x
float64 y
float64 z
"""

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
#: The frame of every pose: the world frame, east-north-up.
POSE_FRAME = "enu"

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

HEADING_REF_MSG = """\
# Heading of a reference orientation (truth, the phone's own), deg from north
# t: recording clock, s
float64 t
float64 heading_deg
"""


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


#: Every schema the sink writes, by a short key.
SCHEMAS: dict[str, Schema] = {
    "vector3": Schema("pdr_mag/msg/Vector3Stamped", "ros2msg", "cdr", VECTOR3_MSG),
    "pose": Schema("foxglove_msgs/msg/PoseInFrame", "ros2msg", "cdr", POSE_MSG),
    "heading": Schema("pdr_mag/msg/Heading", "ros2msg", "cdr", HEADING_MSG),
    "heading_ref": Schema("pdr_mag/msg/HeadingReference", "ros2msg", "cdr", HEADING_REF_MSG),
    "diag": Schema("pdr_mag/msg/Diagnostics", "ros2msg", "cdr", DIAG_MSG),
    "log": Schema("foxglove.Log", "jsonschema", "json", json.dumps(LOG_JSON)),
    "calibration": Schema("pdr_mag.MagCalibration", "jsonschema", "json", json.dumps(CALIBRATION_JSON)),
}
