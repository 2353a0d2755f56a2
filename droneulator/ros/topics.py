"""What a subscriber of the simulator's ROS 2 topics needs: their names and types, stamp conversion, and
decoding of the published images into numpy arrays.

The simulator publishes under these names, and every client (capture, the RL remote backend, the demo
client, the benchmarks) finds them here instead of spelling them out itself::

    /clock                                           rosgraph_msgs/Clock
    /tf, /tf_static                                  tf2_msgs/TFMessage
    /<ns>/odom                                       nav_msgs/Odometry (twist in base_link, REP 105)
    /<ns>/odom_world                                 nav_msgs/Odometry (twist in odom: EGO-Planner's)
    /<ns>/wind                                       geometry_msgs/Vector3Stamped (true wind in odom, m/s)
    /<ns>/imu                                        sensor_msgs/Imu (base_link FLU, no orientation)
    /<ns>/gps/fix                                    sensor_msgs/NavSatFix (WGS84, ENU covariance)
    /<ns>/air_pressure                               sensor_msgs/FluidPressure (Pa, base_link)
    /<ns>/magnetic_field                             sensor_msgs/MagneticField (tesla, base_link)
    /<ns>/spray/state                                std_msgs/Float64MultiArray (spray.enabled: rate,
                                                     level_l, tank_l, flow_l_min, sprayed_l, labelled)
    /<namespace>/spray/deposit                       nav_msgs/OccupancyGrid (spray.enabled, 1 Hz: the
                                                     ground deposit, log scale, in map; docs/spray.md)
    /<ns>/battery                                    sensor_msgs/BatteryState (battery.enabled: voltage,
                                                     current, charge, per cell; docs/battery.md)
    /<ns>/cmd_vel, /<ns>/goal_pose       (in)        geometry_msgs/Twist, geometry_msgs/PoseStamped
    /<ns>/position_cmd                   (in)        quadrotor_msgs/PositionCommand (EGO-Planner's)
    /<ns>/setpoint_raw/attitude          (in)        mavros_msgs/AttitudeTarget (MAVROS's: CTBR, attitude)
    /<ns>/command/motor_speed            (in)        actuator_msgs/Actuators (rotor speeds, Gazebo's)
    /<ns>/fault                          (in)        std_msgs/String (the ``fault`` op's fields as JSON;
                                                     docs/faults.md)
    /<ns>/faults                                     std_msgs/String (the active faults, a JSON list, on
                                                     every change and once a second)
    /<ns>/<cam>/pose                                 geometry_msgs/PoseStamped (optical frame in odom)
    /<ns>/<cam>/{color,depth,segmentation}/camera_info   sensor_msgs/CameraInfo
    /<ns>/<cam>/color/image_raw/compressed           sensor_msgs/CompressedImage (jpeg)
    /<ns>/<cam>/depth/image_raw                      sensor_msgs/Image (32FC1, metres, NaN = no return)
    /<ns>/<cam>/segmentation/image_raw/compressed    sensor_msgs/CompressedImage (png, class ids)

A world of several vehicles puts each vehicle's topics under ``/<ns>/<vehicle>/`` (``/droneulator/uav1/odom``,
``/droneulator/uav1/front/color/...``) and tells their TF frames apart in one of two conventions
(``bridge.fleet_tf``, :class:`VehicleNames`): ``prefix`` (default) publishes every vehicle on the one
``/tf`` with its frames prefixed (``uav1/odom``, ``uav1/base_link``, ``uav1/front_optical_frame``) under a
shared unprefixed ``map``, as Aerostack2 and ``robot_state_publisher``'s ``frame_prefix`` do;
``namespace`` gives each vehicle its own ``/<ns>/<vehicle>/tf`` and ``tf_static`` with unprefixed frames,
as Nav2's multi-robot launch does. One ``/clock`` serves all. A world of one vehicle keeps the names
above, so single-vehicle clients never change.

Stamps are ``builtin_interfaces/Time`` (``sec``, ``nanosec``) of the simulator's monotonic clock
(integer nanoseconds, the API's ``stamp_ns``, which keeps counting across resets); the helpers here
convert between the two without floats.
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from typing import Any

import numpy as np
from PIL import Image

NS_PER_S = 1_000_000_000

CLOCK = "/clock"
TF = "/tf"
TF_STATIC = "/tf_static"

#: TF frame ids (REP 105): map -> odom -> base_link -> <cam>_link -> <cam>_optical_frame
MAP_FRAME = "map"
ODOM_FRAME = "odom"
BASE_FRAME = "base_link"

#: ROS 2 message type of each key of :func:`topic_names` and :func:`vehicle_topics`
TYPES: dict[str, str] = {
    "clock": "rosgraph_msgs/msg/Clock",
    "tf": "tf2_msgs/msg/TFMessage",
    "tf_static": "tf2_msgs/msg/TFMessage",
    "odom": "nav_msgs/msg/Odometry",
    "odom_world": "nav_msgs/msg/Odometry",
    "wind": "geometry_msgs/msg/Vector3Stamped",
    "imu": "sensor_msgs/msg/Imu",
    "gps_fix": "sensor_msgs/msg/NavSatFix",
    "air_pressure": "sensor_msgs/msg/FluidPressure",
    "magnetic_field": "sensor_msgs/msg/MagneticField",
    "spray": "std_msgs/msg/Float64MultiArray",
    "spray_deposit": "nav_msgs/msg/OccupancyGrid",
    "battery": "sensor_msgs/msg/BatteryState",
    "faults": "std_msgs/msg/String",
    "cmd_vel": "geometry_msgs/msg/Twist",
    "goal_pose": "geometry_msgs/msg/PoseStamped",
    "position_cmd": "quadrotor_msgs/msg/PositionCommand",
    "attitude_target": "mavros_msgs/msg/AttitudeTarget",
    "motor_speed": "actuator_msgs/msg/Actuators",
    "fault": "std_msgs/msg/String",
    "pose": "geometry_msgs/msg/PoseStamped",
    "rgb": "sensor_msgs/msg/CompressedImage",
    "depth": "sensor_msgs/msg/Image",
    "seg": "sensor_msgs/msg/CompressedImage",
    "info_rgb": "sensor_msgs/msg/CameraInfo",
    "info_depth": "sensor_msgs/msg/CameraInfo",
    "info_seg": "sensor_msgs/msg/CameraInfo",
}


#: the topic key (of :func:`vehicle_topics`) of each noisy sensor kind (``VehicleConfig.sensors``) a
#: vehicle publishes; the airspeed sensor has no topic
SENSOR_TOPICS: dict[str, str] = {
    "imu": "imu",
    "gps": "gps_fix",
    "baro": "air_pressure",
    "mag": "magnetic_field",
}


def _check_name(what: str, name: str) -> None:
    if not name or name.startswith("/") or name.endswith("/") or " " in name:
        raise ValueError(f"{what} must be a relative ROS name without spaces, got {name!r}")


def topic_names(ns: str, cam: str) -> dict[str, str]:
    """Image, camera_info and pose topics of camera ``cam`` under namespace ``ns`` (keys as in :data:`TYPES`).

    ``pose`` is the optical frame's pose in ``odom``, stamped like the images (EGO-Planner's grid map
    input with ``pose_type`` 1).
    """
    _check_name("namespace", ns)
    _check_name("camera name", cam)
    base = f"/{ns}/{cam}"
    return {
        "rgb": f"{base}/color/image_raw/compressed",
        "depth": f"{base}/depth/image_raw",
        "seg": f"{base}/segmentation/image_raw/compressed",
        "info_rgb": f"{base}/color/camera_info",
        "info_depth": f"{base}/depth/camera_info",
        "info_seg": f"{base}/segmentation/camera_info",
        "pose": f"{base}/pose",
    }


#: the spray state's fields, in order, as its layout labels them
SPRAY_FIELDS = ("rate", "level_l", "tank_l", "flow_l_min", "sprayed_l")


def spray_state_topic(ns: str) -> str:
    """A vehicle's spray state (``spray.enabled``), under its namespace ``ns``."""
    _check_name("namespace", ns)
    return f"/{ns}/spray/state"


def faults_topic(ns: str) -> str:
    """The faults active on a vehicle (std_msgs/String, a JSON list; docs/faults.md), under ``ns``."""
    _check_name("namespace", ns)
    return f"/{ns}/faults"


def battery_state_topic(ns: str) -> str:
    """A vehicle's battery (``battery.enabled``), under its namespace ``ns``."""
    _check_name("namespace", ns)
    return f"/{ns}/battery"


def spray_deposit_topic(namespace: str) -> str:
    """The world's ground-deposit grid, under the run's namespace (one for the whole fleet)."""
    _check_name("namespace", namespace)
    return f"/{namespace}/spray/deposit"


def optical_frame(cam: str) -> str:
    """Frame id of camera ``cam``'s optical frame (x right, y down, z forward), its images' ``frame_id``."""
    return f"{cam}_optical_frame"


def vehicle_topics(ns: str) -> dict[str, str]:
    """The vehicle's own topics under namespace ``ns`` and the global clock and TF topics."""
    _check_name("namespace", ns)
    return {
        "clock": CLOCK,
        "tf": TF,
        "tf_static": TF_STATIC,
        "odom": f"/{ns}/odom",
        "odom_world": f"/{ns}/odom_world",
        "wind": f"/{ns}/wind",
        "imu": f"/{ns}/imu",
        "gps_fix": f"/{ns}/gps/fix",
        "air_pressure": f"/{ns}/air_pressure",
        "magnetic_field": f"/{ns}/magnetic_field",
        "cmd_vel": f"/{ns}/cmd_vel",
        "goal_pose": f"/{ns}/goal_pose",
        "position_cmd": f"/{ns}/position_cmd",
        "attitude_target": f"/{ns}/setpoint_raw/attitude",
        "motor_speed": f"/{ns}/command/motor_speed",
        "fault": f"/{ns}/fault",
    }


#: how a fleet's TF frames are told apart (``bridge.fleet_tf``): see the module docstring
FLEET_TF = ("prefix", "namespace")


@dataclass(frozen=True)
class VehicleNames:
    """Where one vehicle's topics and TF frames are: its ``namespace`` (relative), its ``frame_prefix``
    (``""`` or ``"<vehicle>/"``) and the TF topics its transforms go on."""

    vehicle: str
    namespace: str
    frame_prefix: str
    tf: str
    tf_static: str

    @property
    def odom_frame(self) -> str:
        return self.frame_prefix + ODOM_FRAME

    @property
    def base_frame(self) -> str:
        return self.frame_prefix + BASE_FRAME

    def link_frame(self, cam: str) -> str:
        return f"{self.frame_prefix}{cam}_link"

    def optical_frame(self, cam: str) -> str:
        """Frame id of camera ``cam``'s optical frame, its images' ``frame_id``."""
        return self.frame_prefix + optical_frame(cam)

    def topics(self) -> dict[str, str]:
        """The vehicle's own topics and the clock and TF topics it uses (keys as :func:`vehicle_topics`)."""
        return {**vehicle_topics(self.namespace), "tf": self.tf, "tf_static": self.tf_static}

    def camera_topics(self, cam: str) -> dict[str, str]:
        return topic_names(self.namespace, cam)

    def describe(self, cameras: list[str]) -> dict[str, Any]:
        """What the API's ``scene_info`` lists for the vehicle: namespace, TF prefix, topics by key."""
        return {
            "namespace": f"/{self.namespace}",
            "tf_prefix": self.frame_prefix,
            "topics": {**self.topics(), "cameras": {cam: self.camera_topics(cam) for cam in cameras}},
        }


def vehicle_names(ns: str, vehicle: str, fleet: bool, fleet_tf: str = "prefix") -> VehicleNames:
    """The names of ``vehicle`` under namespace ``ns``: today's single-vehicle names unless ``fleet``
    (the world has more than one vehicle), then ``/<ns>/<vehicle>/...`` with ``fleet_tf``'s TF frames."""
    _check_name("namespace", ns)
    _check_name("vehicle name", vehicle)
    if fleet_tf not in FLEET_TF:
        raise ValueError(f"fleet_tf must be one of {', '.join(FLEET_TF)}, got {fleet_tf!r}")
    if not fleet:
        return VehicleNames(vehicle, ns, "", TF, TF_STATIC)
    vns = f"{ns}/{vehicle}"
    if fleet_tf == "prefix":
        return VehicleNames(vehicle, vns, f"{vehicle}/", TF, TF_STATIC)
    return VehicleNames(vehicle, vns, "", f"/{vns}/tf", f"/{vns}/tf_static")


# --------------------------------------------------------------------------- stamps
def stamp_to_ns(stamp: Any) -> int:
    """Integer nanoseconds of a ``builtin_interfaces/Time`` (anything with ``sec`` and ``nanosec``)."""
    return int(stamp.sec) * NS_PER_S + int(stamp.nanosec)


def header_ns(msg: Any) -> int:
    """Integer nanoseconds of a stamped message's ``header.stamp``."""
    return stamp_to_ns(msg.header.stamp)


def ns_to_sec_nanosec(t_ns: int) -> tuple[int, int]:
    """``(sec, nanosec)`` of ``t_ns`` as rclpy splits it (``nanosec`` in [0, 1e9), also below zero)."""
    return divmod(int(t_ns), NS_PER_S)


def seconds_to_ns(t: float) -> int:
    """Seconds (the WebSocket API's ``t``) to integer nanoseconds, rounded to the nearest one."""
    return round(float(t) * NS_PER_S)


def ns_to_seconds(t_ns: int) -> float:
    return int(t_ns) / NS_PER_S


# --------------------------------------------------------------------------- images
def decode_compressed(msg: Any) -> np.ndarray:
    """Pixels of a ``sensor_msgs/CompressedImage`` in ``jpeg`` or ``png``: HxWx3 ``uint8`` for colour,
    HxW for single-channel images (the segmentation's class ids stay ``uint8`` ids)."""
    fmt = str(msg.format).split(";")[0].strip().lower()
    if fmt not in ("jpeg", "jpg", "png"):
        raise ValueError(f"unsupported CompressedImage format {msg.format!r} (expected jpeg or png)")
    data = bytes(msg.data)
    try:
        with Image.open(io.BytesIO(data)) as img:
            if img.format.lower() not in (("jpeg",) if fmt in ("jpeg", "jpg") else ("png",)):
                raise ValueError(f"CompressedImage says {msg.format!r} but holds {img.format}")
            return np.asarray(img)
    except OSError as exc:  # PIL's UnidentifiedImageError and truncated data
        raise ValueError(f"CompressedImage ({msg.format}, {len(data)} bytes) does not decode: {exc}") from exc


def decode_depth(msg: Any, stride: int = 1) -> np.ndarray:
    """Metres of a ``32FC1`` ``sensor_msgs/Image`` as an HxW ``float32`` array (NaN: no return), or of
    every ``stride``-th row and column of it (only those are copied).

    Honours ``step`` (row padding) and ``is_bigendian``; the result owns its memory.
    """
    if msg.encoding != "32FC1":
        raise ValueError(f"depth image encoding {msg.encoding!r} is not 32FC1")
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.asarray(msg.data, dtype=np.uint8).reshape(-1)
    if step < 4 * w or data.size < h * step:
        raise ValueError(f"32FC1 image {w}x{h}: step {step} and {data.size} data bytes do not fit")
    dtype = np.dtype(">f4" if msg.is_bigendian else "<f4")
    rows = data[: h * step].reshape(h, step)[::stride, : 4 * w]
    return np.ascontiguousarray(rows).view(dtype)[:, ::stride].astype(np.float32)
