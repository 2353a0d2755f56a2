"""What subscribers use from ``droneulator.ros.topics``: names, stamps and image decoding.

Messages are built by the bridge's own builders, put through CDR and read back by rosbags, so the
decoders see exactly what arrives over Zenoh.
"""

from __future__ import annotations

import numpy as np
import pytest

from droneulator.imaging import encode_jpeg, encode_png
from droneulator.ros import messages as M
from droneulator.ros import topics as T


def wire(msg):
    """The message as a subscriber receives it: CDR bytes decoded by rosbags."""
    return M.decode(msg.__msgtype__, M.serialize(msg))


def test_names_and_types_are_the_documented_ones():
    names = {**T.vehicle_topics("uav1"), **T.topic_names("uav1", "down")}
    assert names == {
        "clock": "/clock",
        "tf": "/tf",
        "tf_static": "/tf_static",
        "odom": "/uav1/odom",
        "odom_world": "/uav1/odom_world",
        "wind": "/uav1/wind",
        "imu": "/uav1/imu",
        "gps_fix": "/uav1/gps/fix",
        "air_pressure": "/uav1/air_pressure",
        "magnetic_field": "/uav1/magnetic_field",
        "cmd_vel": "/uav1/cmd_vel",
        "goal_pose": "/uav1/goal_pose",
        "position_cmd": "/uav1/position_cmd",
        "attitude_target": "/uav1/setpoint_raw/attitude",
        "motor_speed": "/uav1/command/motor_speed",
        "fault": "/uav1/fault",
        "rgb": "/uav1/down/color/image_raw/compressed",
        "depth": "/uav1/down/depth/image_raw",
        "seg": "/uav1/down/segmentation/image_raw/compressed",
        "info_rgb": "/uav1/down/color/camera_info",
        "info_depth": "/uav1/down/depth/camera_info",
        "info_seg": "/uav1/down/segmentation/camera_info",
        "pose": "/uav1/down/pose",
    }
    assert set(T.TYPES) == set(names) | {"spray", "spray_deposit", "battery", "faults"}
    assert T.faults_topic("uav1") == "/uav1/faults"
    assert T.spray_state_topic("uav1") == "/uav1/spray/state"
    assert T.battery_state_topic("uav1") == "/uav1/battery"
    assert T.spray_deposit_topic("droneulator") == "/droneulator/spray/deposit"
    for typename in T.TYPES.values():
        assert M.type_hash(typename).startswith("RIHS01_")  # a real ROS 2 Jazzy type
    assert T.optical_frame("down") == "down_optical_frame"
    for bad in ("", "/uav1", "uav1/", "two words"):
        with pytest.raises(ValueError, match="namespace"):
            T.vehicle_topics(bad)
    with pytest.raises(ValueError, match="camera name"):
        T.topic_names("uav1", "/down")


@pytest.mark.parametrize(
    "t_ns", [0, 1, 999_999_999, 1_000_000_000, 1_700_000_123_456_789_012, -1, -1_500_000_000]
)
def test_stamps_round_trip_through_builtin_interfaces_time(t_ns):
    msg = wire(M.clock(t_ns))
    assert T.stamp_to_ns(msg.clock) == t_ns
    assert (msg.clock.sec, msg.clock.nanosec) == T.ns_to_sec_nanosec(t_ns)
    assert 0 <= msg.clock.nanosec < T.NS_PER_S
    assert (
        T.header_ns(wire(M.compressed_image(t_ns, "f", "png", encode_png(np.zeros((2, 2), np.uint8)))))
        == t_ns
    )


def test_seconds_convert_to_the_nearest_nanosecond():
    assert T.seconds_to_ns(0.3) == 300_000_000  # int(0.3 * 1e9) would give 299_999_999
    assert T.seconds_to_ns(12.345678901) == 12_345_678_901
    assert T.ns_to_seconds(T.seconds_to_ns(1.25)) == 1.25


def test_compressed_images_decode_to_their_pixels():
    rng = np.random.default_rng(0)
    seg = rng.integers(0, 12, (24, 32), dtype=np.uint8)
    got = T.decode_compressed(wire(M.compressed_image(5, "cam", "png", encode_png(seg))))
    np.testing.assert_array_equal(got, seg)  # class ids survive exactly

    rgb = np.zeros((24, 32, 3), np.uint8)
    rgb[:, :16] = (200, 30, 40)
    rgb[:, 16:] = (20, 180, 90)
    got = T.decode_compressed(wire(M.compressed_image(5, "cam", "jpeg", encode_jpeg(rgb, 95))))
    assert got.shape == rgb.shape and got.dtype == np.uint8
    assert np.abs(got.astype(int) - rgb).mean() < 3.0

    with pytest.raises(ValueError, match="holds PNG"):
        T.decode_compressed(wire(M.compressed_image(5, "cam", "jpeg", encode_png(seg))))
    with pytest.raises(ValueError, match="does not decode"):
        T.decode_compressed(wire(M.compressed_image(5, "cam", "png", b"\x89PNG not really")))
    with pytest.raises(ValueError, match="unsupported"):
        T.decode_compressed(wire(M.compressed_image(5, "cam", "tiff", b"II*\x00")))


def test_depth_images_decode_to_metres_with_nan_and_padding():
    depth = np.arange(12, dtype=np.float32).reshape(3, 4) / 7
    depth[1, 2] = np.nan
    got = T.decode_depth(wire(M.image(9, "cam", depth)))
    assert got.dtype == np.float32 and got.flags.owndata
    np.testing.assert_array_equal(got, depth)  # NaN where NaN (assert_array_equal treats NaN as equal)

    Image = M.TYPESTORE.types["sensor_msgs/msg/Image"]
    padded = np.zeros((3, 24), np.uint8)  # step 24 bytes for 4 pixels: 8 bytes of row padding
    padded[:, :16] = depth.astype(">f4").view(np.uint8).reshape(3, 16)
    msg = Image(
        header=M.header(9, "cam"),
        height=3,
        width=4,
        encoding="32FC1",
        is_bigendian=1,
        step=24,
        data=padded.reshape(-1),
    )
    np.testing.assert_array_equal(T.decode_depth(wire(msg)), depth)
    # every 2nd row and column (the UI's depth view), padded rows and big-endian included
    half = T.decode_depth(wire(msg), stride=2)
    assert half.dtype == np.float32 and half.flags.owndata
    np.testing.assert_array_equal(half, depth[::2, ::2])

    with pytest.raises(ValueError, match="not 32FC1"):
        T.decode_depth(wire(M.image(9, "cam", np.zeros((2, 2), np.uint16))))
    short = Image(header=M.header(9, "cam"), height=3, width=4, encoding="32FC1", is_bigendian=0, step=16,
                  data=np.zeros(40, np.uint8))  # fmt: skip
    with pytest.raises(ValueError, match="do not fit"):
        T.decode_depth(wire(short))
