"""ROS 2 MCAP (sensor_msgs/msg/Imu + MagneticField): fixtures generated with mcap-ros2-support's writer."""

from __future__ import annotations

import numpy as np
import pytest

from replay.errors import InputError
from replay.formats import detect, read_recording, rosmcap

_SEP = "=" * 80 + "\n"
_DEPS = (
    _SEP
    + "MSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id\n"
    + _SEP
    + "MSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n"
    + _SEP
    + "MSG: geometry_msgs/Vector3\nfloat64 x\nfloat64 y\nfloat64 z\n"
)
IMU_DEF = (
    "std_msgs/Header header\ngeometry_msgs/Quaternion orientation\nfloat64[9] orientation_covariance\n"
    "geometry_msgs/Vector3 angular_velocity\nfloat64[9] angular_velocity_covariance\n"
    "geometry_msgs/Vector3 linear_acceleration\nfloat64[9] linear_acceleration_covariance\n"
    + _DEPS
    + _SEP
    + "MSG: geometry_msgs/Quaternion\nfloat64 x\nfloat64 y\nfloat64 z\nfloat64 w\n"
)
MAG_DEF = (
    "std_msgs/Header header\ngeometry_msgs/Vector3 magnetic_field\nfloat64[9] magnetic_field_covariance\n"
    + _DEPS
)


def _hdr(t, frame="imu_link"):
    sec = int(np.floor(t))
    return {"stamp": {"sec": sec, "nanosec": int(round((t - sec) * 1e9))}, "frame_id": frame}


def _vec(v):
    return {"x": float(v[0]), "y": float(v[1]), "z": float(v[2])}


def write_bag(
    path,
    n=100,
    t0=1700000000.0,
    mag_flu_T=(20e-6, 0.0, -40e-6),
    extra_imu=False,
    gyro_missing=False,
    mag_edit=None,
):
    from mcap_ros2.writer import Writer

    rng = np.random.default_rng(3)
    with open(path, "wb") as fh:
        w = Writer(fh)
        imu_s = w.register_msgdef("sensor_msgs/msg/Imu", IMU_DEF)
        mag_s = w.register_msgdef("sensor_msgs/msg/MagneticField", MAG_DEF)
        for i in range(n):
            t = t0 + i * 0.01
            ns = int(round(t * 1e9))
            imu = {
                "header": _hdr(t),
                "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
                "orientation_covariance": [-1.0] + [0.0] * 8,
                "angular_velocity": _vec([0.1, 0.0, 0.02] + 0.001 * rng.standard_normal(3)),
                "angular_velocity_covariance": ([-1.0] if gyro_missing else [0.0]) + [0.0] * 8,
                "linear_acceleration": _vec([0.0, 0.0, 9.81] + 0.01 * rng.standard_normal(3)),
                "linear_acceleration_covariance": [0.0] * 9,
            }
            w.write_message("/imu/data_raw", imu_s, imu, log_time=ns, publish_time=ns)
            if extra_imu:
                w.write_message("/imu/data", imu_s, {**imu, "linear_acceleration": _vec([1, 1, 1])}, ns, ns)
            if i % 2 == 0:
                m = {
                    "header": _hdr(t + 0.001),
                    "magnetic_field": _vec(mag_flu_T),
                    "magnetic_field_covariance": [0.0] * 9,
                }
                if mag_edit is not None:
                    m = mag_edit(i, m)
                w.write_message("/imu/mag", mag_s, m, log_time=ns, publish_time=ns)
        w.finish()
    return path


def test_read_flu_to_device(tmp_path):
    f = write_bag(tmp_path / "bag.mcap", extra_imu=True)
    assert detect(f) == "ros2-mcap"
    rec = read_recording(f)
    assert rec.format == "ros2-mcap" and rec.meta["ros_topics"] == {"mag": "/imu/mag", "imu": "/imu/data_raw"}
    assert (len(rec.mag), len(rec.accel), len(rec.gyro)) == (50, 100, 100)
    # tesla → µT, FLU → device: field north-ish along the body's forward axis → device +y
    np.testing.assert_allclose(rec.mag.xyz[0], [0.0, 20.0, -40.0], atol=1e-9)
    np.testing.assert_allclose(rec.accel.xyz.mean(axis=0), [0, 0, 9.81], atol=0.01)
    np.testing.assert_allclose(
        rec.gyro.xyz.mean(axis=0), [0.0, 0.1, 0.02], atol=0.001
    )  # roll rate → device y
    np.testing.assert_allclose(rec.mag.t[:2], [1700000000.001, 1700000000.021], atol=1e-6)
    raw = rosmcap.read(f, axes="device")
    np.testing.assert_allclose(raw.mag.xyz[0], [20.0, 0.0, -40.0], atol=1e-9)


def test_gyro_not_provided(tmp_path):
    rec = read_recording(write_bag(tmp_path / "bag.mcap", gyro_missing=True))
    assert rec.gyro is None and len(rec.accel) == 100


def test_field_in_gauss_is_wrong_unit(tmp_path):
    f = write_bag(tmp_path / "g.mcap", mag_flu_T=(0.2, 0.0, -0.4))  # gauss written as tesla
    with pytest.raises(InputError, match="outside the plausible"):
        read_recording(f)


def test_nan_duplicate_and_backwards(tmp_path):
    def nan_dup(i, m):
        if i == 10:
            m["magnetic_field"]["x"] = float("nan")
        if i == 12:
            m["header"] = _hdr(1700000000.0 + 0.10 + 0.001)  # same stamp as i == 10
        return m

    rec = read_recording(write_bag(tmp_path / "a.mcap", mag_edit=nan_dup))
    assert rec.dropped == {"mag:nan": 1} and len(rec.mag) == 49  # the NaN one left its time free

    def back(i, m):
        if i == 20:
            m["header"] = _hdr(1699999999.0)
        return m

    with pytest.raises(InputError, match=r"time goes backwards .* of /imu/mag"):
        read_recording(write_bag(tmp_path / "b.mcap", mag_edit=back))


def test_truncated_and_no_mag(tmp_path):
    f = write_bag(tmp_path / "t.mcap", n=400)
    data = f.read_bytes()
    f.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match="truncated or damaged MCAP"):
        read_recording(f)
    from mcap_ros2.writer import Writer

    g = tmp_path / "imu_only.mcap"
    with open(g, "wb") as fh:
        w = Writer(fh)
        s = w.register_msgdef("sensor_msgs/msg/Imu", IMU_DEF)
        w.write_message("/imu", s, {"header": _hdr(1.0), "linear_acceleration": _vec([0, 0, 9.8])}, 1, 1)
        w.finish()
    with pytest.raises(InputError, match="without /mag/raw .*MagneticField channel"):
        read_recording(g)
