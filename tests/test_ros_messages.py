"""Message builders round-trip through rosbags' own CDR deserialiser; decoders reject bad payloads."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest
from rosbags.serde import SerdeError
from rosbags.typesys import Stores, get_typestore

from droneulator.ros import messages as M

#: an independent typestore: decoding here does not share state with the code under test
REF = get_typestore(Stores.ROS2_JAZZY)

T_NS = 1_700_000_123_456_789_012
SEC, NSEC = 1_700_000_123, 456_789_012


def roundtrip(msg: object, typename: str) -> object:
    cdr = M.serialize(msg)
    assert isinstance(cdr, bytes | bytearray)
    assert bytes(cdr[:4]) == b"\x00\x01\x00\x00"
    assert msg.__msgtype__ == typename
    return REF.deserialize_cdr(bytes(cdr), typename)


def assert_stamp(hdr: object, frame_id: str) -> None:
    assert (hdr.stamp.sec, hdr.stamp.nanosec) == (SEC, NSEC)
    assert hdr.frame_id == frame_id


def test_stamp_splits_like_rclpy() -> None:
    assert (M.stamp(T_NS).sec, M.stamp(T_NS).nanosec) == (SEC, NSEC)
    assert (M.stamp(0).sec, M.stamp(0).nanosec) == (0, 0)
    neg = M.stamp(-1)
    assert (neg.sec, neg.nanosec) == (-1, 999_999_999)
    with pytest.raises(ValueError):
        M.stamp(2**31 * 1_000_000_000)


def test_clock_and_header() -> None:
    out = roundtrip(M.clock(T_NS), "rosgraph_msgs/msg/Clock")
    assert (out.clock.sec, out.clock.nanosec) == (SEC, NSEC)
    assert_stamp(roundtrip(M.header(T_NS, "map"), "std_msgs/msg/Header"), "map")


def test_odometry_fields() -> None:
    pos, quat = np.array([1.0, -2.0, 3.5]), np.array([0.0, 0.0, math.sin(0.3), math.cos(0.3)])
    v_body, w_body = np.array([0.5, 0.1, -0.2]), np.array([0.01, -0.02, 0.3])
    pose_cov = np.diag(np.arange(1.0, 7.0))
    out = roundtrip(
        M.odometry(T_NS, "odom", "base_link", pos, quat, v_body, w_body, pose_cov=pose_cov),
        "nav_msgs/msg/Odometry",
    )
    assert_stamp(out.header, "odom")
    assert out.child_frame_id == "base_link"
    p, q = out.pose.pose.position, out.pose.pose.orientation
    assert [p.x, p.y, p.z] == pos.tolist()
    assert [q.x, q.y, q.z, q.w] == quat.tolist()
    lin, ang = out.twist.twist.linear, out.twist.twist.angular
    assert [lin.x, lin.y, lin.z] == v_body.tolist()
    assert [ang.x, ang.y, ang.z] == w_body.tolist()
    np.testing.assert_array_equal(out.pose.covariance, pose_cov.reshape(-1))
    np.testing.assert_array_equal(out.twist.covariance, np.zeros(36))
    with pytest.raises(ValueError):
        M.odometry(0, "odom", "base_link", [0, 0], quat, v_body, w_body)


def test_transform_and_tf_message() -> None:
    a = M.transform_stamped(T_NS, "odom", "base_link", [1.0, 2.0, 3.0], [0.0, 0.0, 0.0, 1.0])
    b = M.transform_stamped(T_NS, "base_link", "front_link", [0.12, 0.0, 0.0], [0.5, -0.5, 0.5, -0.5])
    out = roundtrip(M.tf_message([a, b]), "tf2_msgs/msg/TFMessage")
    assert len(out.transforms) == 2
    first, second = out.transforms
    assert_stamp(first.header, "odom")
    assert first.child_frame_id == "base_link"
    t, r = first.transform.translation, first.transform.rotation
    assert [t.x, t.y, t.z, r.x, r.y, r.z, r.w] == [1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 1.0]
    assert (second.header.frame_id, second.child_frame_id) == ("base_link", "front_link")
    r = second.transform.rotation
    assert [r.x, r.y, r.z, r.w] == [0.5, -0.5, 0.5, -0.5]
    assert roundtrip(M.tf_message([]), "tf2_msgs/msg/TFMessage").transforms == []


def test_camera_info_is_ideal_pinhole() -> None:
    K = np.array([[320.0, 0.0, 319.5], [0.0, 320.0, 239.5], [0.0, 0.0, 1.0]])
    out = roundtrip(M.camera_info(T_NS, "front_optical_frame", 640, 480, K), "sensor_msgs/msg/CameraInfo")
    assert_stamp(out.header, "front_optical_frame")
    assert (out.width, out.height, out.distortion_model) == (640, 480, "plumb_bob")
    np.testing.assert_array_equal(out.k, K.reshape(-1))
    np.testing.assert_array_equal(out.d, np.zeros(5))
    np.testing.assert_array_equal(out.r, np.eye(3).reshape(-1))
    np.testing.assert_array_equal(out.p.reshape(3, 4), np.hstack([K, np.zeros((3, 1))]))
    assert (out.binning_x, out.binning_y, out.roi.width, out.roi.height) == (0, 0, 0, 0)


@pytest.mark.parametrize("fmt", ["jpeg", "png"])
def test_compressed_image(fmt: str) -> None:
    payload = bytes(range(256)) * 7 + b"\xff\xd9"
    out = roundtrip(M.compressed_image(T_NS, "cam", fmt, payload), "sensor_msgs/msg/CompressedImage")
    assert_stamp(out.header, "cam")
    assert out.format == fmt
    assert out.data.tobytes() == payload


@pytest.mark.parametrize(
    ("array", "encoding", "bpp"),
    [
        (np.arange(12, dtype=np.float32).reshape(3, 4) / 7, "32FC1", 4),
        (np.arange(12, dtype=np.uint16).reshape(3, 4) * 1000, "16UC1", 2),
        (np.arange(12, dtype=np.uint8).reshape(3, 4), "mono8", 1),
        (np.arange(36, dtype=np.uint8).reshape(3, 4, 3), "rgb8", 3),
        (np.arange(48, dtype=np.uint8).reshape(3, 4, 4), "rgba8", 4),
    ],
)
def test_image_encodings(array: np.ndarray, encoding: str, bpp: int) -> None:
    out = roundtrip(M.image(T_NS, "cam", array), "sensor_msgs/msg/Image")
    assert_stamp(out.header, "cam")
    assert (out.height, out.width, out.encoding, out.is_bigendian) == (3, 4, encoding, 0)
    assert out.step == 4 * bpp
    assert out.data.tobytes() == array.astype(array.dtype.newbyteorder("<")).tobytes()


def test_depth_image_keeps_nan_and_is_zero_copy() -> None:
    depth = np.full((480, 640), 7.25, dtype=np.float32)
    depth[10, 20] = np.nan
    msg = M.image(T_NS, "front_optical_frame", depth)
    assert np.shares_memory(msg.data, depth), "the builder must not copy the pixels"
    out = roundtrip(msg, "sensor_msgs/msg/Image")
    assert out.encoding == "32FC1" and out.step == 640 * 4
    assert out.data.tobytes() == depth.tobytes()
    back = out.data.view("<f4").reshape(480, 640)
    assert np.isnan(back[10, 20]) and back[0, 0] == np.float32(7.25)


def test_image_big_endian_and_strided_inputs_are_converted() -> None:
    base = np.arange(24, dtype=np.float32).reshape(4, 6)
    out = roundtrip(M.image(0, "cam", base.astype(">f4")), "sensor_msgs/msg/Image")
    assert out.is_bigendian == 0 and out.data.tobytes() == base.tobytes()
    strided = base[:, ::2]
    out = roundtrip(M.image(0, "cam", strided), "sensor_msgs/msg/Image")
    assert (out.width, out.step) == (3, 12) and out.data.tobytes() == np.ascontiguousarray(strided).tobytes()


def test_image_rejects_unknown_layouts() -> None:
    with pytest.raises(ValueError):
        M.image(0, "cam", np.zeros((2, 2), dtype=np.float64))
    with pytest.raises(ValueError):
        M.image(0, "cam", np.zeros((2, 2, 2), dtype=np.uint8))
    with pytest.raises(ValueError):
        M.image(0, "cam", np.zeros((2, 2), dtype=np.uint8), encoding="rgb8")
    out = roundtrip(
        M.image(0, "cam", np.zeros((2, 2, 3), np.uint8), encoding="bgr8"), "sensor_msgs/msg/Image"
    )
    assert out.encoding == "bgr8"


def test_image_wire_layout_is_standard_cdr() -> None:
    """Independent check of the bytes against the XCDR1 rules (4-byte aligned after the header)."""
    depth = np.array([[1.5, -2.0]], dtype=np.float32)
    cdr = bytes(M.serialize(M.image(T_NS, "cam", depth)))
    body = struct.pack("<iiI4s", SEC, NSEC, 4, b"cam\x00")
    body += struct.pack("<III6s", 1, 2, 6, b"32FC1\x00")
    body += b"\x00"  # is_bigendian
    body += b"\x00" * (-len(body) % 4)
    body += struct.pack("<II", 8, 8) + depth.tobytes()
    assert cdr == b"\x00\x01\x00\x00" + body


def test_decode_round_trip_and_hash() -> None:
    twist = REF.types["geometry_msgs/msg/Twist"]
    vec = REF.types["geometry_msgs/msg/Vector3"]
    raw = bytes(
        REF.serialize_cdr(
            twist(linear=vec(x=1.5, y=0, z=0), angular=vec(x=0, y=0, z=-0.25)), twist.__msgtype__
        )
    )
    msg = M.decode("geometry_msgs/msg/Twist", raw)
    assert M.twist_to_command(msg) == (1.5, -0.25)
    assert M.type_hash("geometry_msgs/msg/Twist") == (
        "RIHS01_9c45bf16fe0983d80e3cfe750d6835843d265a9a6c46bd2e609fcddde6fb8d2a"
    )


@pytest.mark.parametrize(
    "payload",
    [
        b"",
        b"\x00\x01",
        b"garbage bytes that are not cdr at all",
        b"\x00\x01\x00\x00" + bytes(20),
        b"\x00\x01\x00\x00" + bytes(48) + bytes(16),
    ],
    ids=["empty", "header-only", "garbage", "truncated", "trailing"],
)
def test_decode_rejects_bad_payloads(payload: bytes) -> None:
    with pytest.raises(SerdeError):
        M.decode("geometry_msgs/msg/Twist", payload)


def pose_stamped(
    frame: str, xyz: tuple[float, float, float], quat: tuple[float, float, float, float]
) -> object:
    T = REF.types
    return T["geometry_msgs/msg/PoseStamped"](
        header=T["std_msgs/msg/Header"](
            stamp=T["builtin_interfaces/msg/Time"](sec=1, nanosec=2), frame_id=frame
        ),
        pose=T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=xyz[0], y=xyz[1], z=xyz[2]),
            orientation=T["geometry_msgs/msg/Quaternion"](x=quat[0], y=quat[1], z=quat[2], w=quat[3]),
        ),
    )


def qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of [x, y, z, w] quaternions."""
    x1, y1, z1, w1 = a
    x2, y2, z2, w2 = b
    return np.array(
        [
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
        ]
    )


def test_pose_stamped_to_goal() -> None:
    yaw = 2.5
    frame, pos, got = M.pose_stamped_to_goal(
        pose_stamped("map", (1.0, 2.0, 3.0), (0, 0, math.sin(yaw / 2), math.cos(yaw / 2)))
    )
    assert frame == "map" and pos.tolist() == [1.0, 2.0, 3.0] and got == pytest.approx(yaw)
    # yaw 0.7 composed with a roll (ZYX order: q = q_yaw * q_roll), scaled so it is not unit length
    q = 3.0 * qmul(
        np.array([0.0, 0.0, math.sin(0.35), math.cos(0.35)]), np.array([math.sin(0.2), 0, 0, math.cos(0.2)])
    )
    assert M.pose_stamped_to_goal(pose_stamped("odom", (0, 0, 0), tuple(q)))[2] == pytest.approx(0.7)
    with pytest.raises(ValueError):
        M.pose_stamped_to_goal(pose_stamped("map", (0, 0, 0), (0, 0, 0, 0)))
    with pytest.raises(ValueError):
        M.pose_stamped_to_goal(pose_stamped("map", (math.nan, 0, 0), (0, 0, 0, 1)))


@pytest.mark.parametrize("frames", [("odom", "base_link"), ("map", "uav1/base_link_with_a_long_name")])
def test_state_packer_is_byte_identical_to_rosbags(frames):
    """The fast fixed-layout packer writes exactly what rosbags serialises, for any values and stamp."""
    rng = np.random.default_rng(3)
    packer = M.StatePacker(*frames)
    for t_ns in (0, 1, 33_333_333, 12_345_678_901, 2**31 * 1_000_000_000 - 1):
        p, v, w = rng.normal(size=3) * 100, rng.normal(size=3), rng.normal(size=3)
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        odom_ref = M.serialize(M.odometry(t_ns, *frames, p, q, v, w))
        assert bytes(packer.odometry(t_ns, p, q, v, w)) == bytes(odom_ref)
        tf = M.tf_message([M.transform_stamped(t_ns, *frames, p, q)])
        assert bytes(packer.transform(t_ns, p, q)) == bytes(M.serialize(tf))
        assert packer.clock(t_ns) == bytes(M.serialize(M.clock(t_ns)))
        assert bytes(packer.vector(t_ns, v)) == bytes(M.serialize(M.vector3_stamped(t_ns, frames[0], v)))
        wind = REF.deserialize_cdr(bytes(packer.vector(t_ns, v)), "geometry_msgs/msg/Vector3Stamped")
        assert wind.header.frame_id == frames[0] and [wind.vector.x, wind.vector.y, wind.vector.z] == list(v)
        odom = REF.deserialize_cdr(bytes(packer.odometry(t_ns, p, q, v, w)), "nav_msgs/msg/Odometry")
        assert odom.child_frame_id == frames[1] and odom.pose.pose.position.x == p[0]
    with pytest.raises(ValueError):
        packer.clock(2**31 * 1_000_000_000)


@pytest.mark.parametrize("frame", ["base_link", "uav1/base_link_with_a_long_name"])
def test_sensor_packer_is_byte_identical_to_rosbags_and_reads_as_rep_145_says(frame):
    """Imu, MagneticField and FluidPressure from the fixed-layout packer are rosbags' bytes; decoded by an
    independent typestore they carry the covariances given, and an Imu without orientation says so
    (orientation_covariance[0] = -1)."""
    rng = np.random.default_rng(4)
    var = {"gyro_var": 2.5e-6, "accel_var": 4e-4, "mag_var": 4e-14, "pressure_var": 1.44}
    packer = M.SensorPacker(frame, **var)
    for t_ns in (0, 1, 12_345_678_901, 2**31 * 1_000_000_000 - 1):
        gyro, accel, field = rng.normal(size=3), rng.normal(size=3) * 10, rng.normal(size=3) * 5e-5
        pressure = float(rng.uniform(90_000, 102_000))
        ref = M.imu(t_ns, frame, gyro, accel, [var["gyro_var"]] * 3, [var["accel_var"]] * 3)
        assert bytes(packer.imu(t_ns, gyro, accel)) == bytes(M.serialize(ref))
        ref = M.magnetic_field(t_ns, frame, field, [var["mag_var"]] * 3)
        assert bytes(packer.magnetic_field(t_ns, field)) == bytes(M.serialize(ref))
        ref = M.fluid_pressure(t_ns, frame, pressure, var["pressure_var"])
        assert bytes(packer.fluid_pressure(t_ns, pressure)) == bytes(M.serialize(ref))
        imu = REF.deserialize_cdr(bytes(packer.imu(t_ns, gyro, accel)), "sensor_msgs/msg/Imu")
        assert imu.header.frame_id == frame
        assert imu.header.stamp.sec * 10**9 + imu.header.stamp.nanosec == t_ns
        assert imu.orientation_covariance[0] == -1.0 and imu.orientation.w == 1.0
        assert [imu.angular_velocity.x, imu.angular_velocity.y, imu.angular_velocity.z] == list(gyro)
        a = imu.linear_acceleration
        assert [a.x, a.y, a.z] == list(accel)
        assert imu.linear_acceleration_covariance.tolist() == np.diag([4e-4] * 3).reshape(-1).tolist()
        assert imu.angular_velocity_covariance.tolist() == np.diag([2.5e-6] * 3).reshape(-1).tolist()
        mag = REF.deserialize_cdr(bytes(packer.magnetic_field(t_ns, field)), "sensor_msgs/msg/MagneticField")
        assert [mag.magnetic_field.x, mag.magnetic_field.y, mag.magnetic_field.z] == list(field)
        raw = bytes(packer.fluid_pressure(t_ns, pressure))
        baro = REF.deserialize_cdr(raw, "sensor_msgs/msg/FluidPressure")
        assert (baro.fluid_pressure, baro.variance, baro.header.frame_id) == (pressure, 1.44, frame)
    fix = M.nav_sat_fix(5, frame, 53.2, -0.55, 12.5, [1e-4, 1e-4, 4e-4], M.STATUS_GBAS_FIX)
    fix = roundtrip(fix, "sensor_msgs/msg/NavSatFix")
    assert (fix.status.status, fix.status.service, fix.position_covariance_type) == (2, 1, 2)
    assert (fix.latitude, fix.longitude, fix.altitude) == (53.2, -0.55, 12.5)
    assert fix.position_covariance.tolist() == np.diag([1e-4, 1e-4, 4e-4]).reshape(-1).tolist()
    with pytest.raises(ValueError, match="cov"):
        M.imu(0, frame, gyro, accel, [1.0, 2.0])
