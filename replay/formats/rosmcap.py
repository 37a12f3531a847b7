"""ROS 2 MCAP (rosbag2's MCAP storage) with ``sensor_msgs/msg/Imu`` and ``sensor_msgs/msg/MagneticField``.

Messages are CDR-encoded (``message_encoding="cdr"``, schemas ``ros2msg``) and decoded with
``mcap-ros2-support``'s decoder, one at a time as the file is read (once, streamed).

Streams
    * magnetometer: the ``sensor_msgs/msg/MagneticField`` channel (``magnetic_field`` in **tesla** → ×1e6 µT);
    * accelerometer and gyroscope: the ``sensor_msgs/msg/Imu`` channel's ``linear_acceleration`` (m/s²) and
      ``angular_velocity`` (rad/s). Per REP 145 the accelerometer reports specific force (+9.81 m/s² up at
      rest), as the contract does. A field whose covariance starts with −1 ("not provided") is skipped.

    With several channels of one type, a topic whose name contains ``raw`` (e.g. ``/imu/data_raw``,
    ``/imu/mag_raw``) is preferred, then the one with the most messages, then the first by name.
    ``meta["ros_topics"]`` names the channels used.

Time
    ``header.stamp`` (sec, nanosec) as seconds, or the message's ``log_time`` when the stamp is zero.

Axes — the assumption
    REP 103: a body frame is x forward, y left, z up (FLU), and the world is ENU. An IMU's ``frame_id`` is
    such a body frame, so the device frame of the contract is taken as the body laid flat with its forward
    axis as the "top" of a phone: ``x_d = -y``, ``y_d = x``, ``z_d = z`` (a 90° turn about z). The heading
    then is the direction of the body's forward axis, as a ROS user expects. (A phone whose driver publishes
    Android's own axes — x right, y top — would come out turned by 90° in heading and must be read with
    ``axes="device"``.) ``meta["ros_axes"]`` says which mapping was used.

What the device states about itself
    Nothing: ``sensor_msgs`` has no field for a calibration or a bias, and the bag's metadata no date or
    device id. The streams are taken as the raw readings IMU drivers publish (``meta["mag_os_calibrated"]``
    and ``["gyro_os_calibrated"]`` False).
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np

from replay.errors import InputError
from replay.formats import _common, _mcap
from replay.formats._common import StreamBuilder, StreamSpec, chunks_of
from replay.recording import Recording
from replay.source import Feed, RecordingSource

NAME = "ros2-mcap"
IMU = "sensor_msgs/msg/Imu"
MAG = "sensor_msgs/msg/MagneticField"
UT_PER_TESLA = 1e6

#: FLU body axes → device axes (x right, y top = forward, z up)
FLU_TO_DEVICE = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
_AXES = {"flu": FLU_TO_DEVICE, "device": np.eye(3)}


def _ros_channels(channels):
    return [c for c in channels if c.message_encoding == "cdr" and c.schema_name in (IMU, MAG)]


def detect(path: Path) -> bool:
    if not _mcap.is_mcap(path):
        return False
    channels, _ = _mcap.scan(path)
    return any(c.schema_name == MAG for c in _ros_channels(channels))


def _pick(channels, schema: str, counts: dict) -> str | None:
    cands = [c.topic for c in channels if c.schema_name == schema]
    if not cands:
        return None
    return sorted(cands, key=lambda t: ("raw" not in t.lower(), -counts.get(t, 0), t))[0]


def _message_counts(path: Path) -> dict:
    from mcap.reader import make_reader

    with path.open("rb") as fh:
        try:
            s = make_reader(fh).get_summary()
        except _mcap.read_errors():
            return {}
    if s is None or s.statistics is None:
        return {}
    return {
        s.channels[cid].topic: n
        for cid, n in s.statistics.channel_message_counts.items()
        if cid in s.channels
    }


def _stamp(msg, log_time: int) -> float:
    st = msg.header.stamp
    sec, nsec = int(st.sec), int(st.nanosec)
    if sec == 0 and nsec == 0:
        return log_time * 1e-9
    return sec + nsec * 1e-9


def _provided(cov) -> bool:
    return len(cov) == 0 or cov[0] != -1.0


def _parse(p: Path, mag_topic: str, imu_topic: str | None, builders: dict, opened: list):
    """Decode the messages into the builders, yielding after each; errors name the message."""
    from mcap_ros2.decoder import DecoderFactory

    topics = [t for t in (mag_topic, imu_topic) if t is not None]
    mag_b, acc_b, gyr_b = builders["mag"], builders["accel"], builders["gyro"]
    n = 0
    try:
        for channel, message, msg in _mcap.iter_messages(p, topics, [DecoderFactory()], opened=opened):
            n += 1
            yield
            t = _stamp(msg, message.log_time)
            if channel.topic == mag_topic:
                f = msg.magnetic_field
                mag_b.add(None, t, (f.x, f.y, f.z))
                continue
            if _provided(msg.linear_acceleration_covariance):
                a = msg.linear_acceleration
                acc_b.add(None, t, (a.x, a.y, a.z))
            if _provided(msg.angular_velocity_covariance):
                w = msg.angular_velocity
                gyr_b.add(None, t, (w.x, w.y, w.z))
    except InputError as exc:
        if exc.path == str(p) and "time goes backwards" in exc.problem:
            raise InputError(p, f"{exc.problem} at message {n} of {channel.topic}") from None
        raise
    except (AttributeError, ValueError, IndexError, KeyError, TypeError, EOFError) as exc:
        raise InputError(
            p, f"message {n + 1}: cannot decode as {IMU}/{MAG} ({type(exc).__name__}: {exc})"
        ) from None


def read(path, axes: str = "flu") -> Recording:
    """Read a ROS 2 MCAP file into a :class:`Recording` (see the module docstring for the axis assumption)."""
    return open_source(path, axes).collect()


def open_source(path, axes: str = "flu") -> RecordingSource:
    """Open a ROS 2 MCAP file: channels now, messages streamed (the module docstring has the axes)."""
    p = Path(path)
    if axes not in _AXES:
        raise ValueError(f"axes: expected one of {sorted(_AXES)}, got {axes!r}")
    channels, error = _mcap.scan(p)
    if error is not None:
        raise InputError(p, error)
    ros = _ros_channels(channels)
    counts = _message_counts(p)
    mag_topic, imu_topic = _pick(ros, MAG, counts), _pick(ros, IMU, counts)
    if mag_topic is None:
        raise InputError(p, f"no {MAG} channel (a stream missing)")
    dropped: Counter = Counter()

    def chunks():
        builders = {k: StreamBuilder(p, k, dropped) for k in ("mag", "accel", "gyro")}
        opened: list = []
        steps = _common.every(_parse(p, mag_topic, imu_topic, builders, opened))
        yield from chunks_of(opened, builders, steps)

    m = _AXES[axes]
    specs = {"mag": StreamSpec(p, "mag", scale=UT_PER_TESLA, axes=m, unit_hint="tesla × 1e6")}
    if imu_topic is not None:
        specs["accel"] = StreamSpec(p, "accel", axes=m, unit_hint="m/s²", optional=True)
        specs["gyro"] = StreamSpec(p, "gyro", axes=m, unit_hint="rad/s", optional=True)
    meta = {
        "ros_topics": {"mag": mag_topic, "imu": imu_topic},
        "ros_axes": "flu: x_d=-y, y_d=x, z_d=z" if axes == "flu" else "device: unchanged",
        "mag_os_calibrated": False,
        "gyro_os_calibrated": False,
    }
    feed = Feed(tuple(specs), chunks, p.stat().st_size)
    return RecordingSource(specs, [feed], meta=meta, source=str(p), format=NAME, dropped=dropped)
