"""ROS 2 (Jazzy) messages as rosbags objects, their CDR bytes, and decoders for the command topics.

Builders return rosbags message objects from the one Jazzy typestore (``TYPESTORE``); :func:`serialize`
turns any of them into the full CDR sample that goes on the wire: the 4-byte encapsulation header
``00 01 00 00`` (CDR, little endian) followed by the body. This is the payload both
zenoh-bridge-ros2dds and rmw_zenoh carry (rmw_zenoh: ``TypeSupport::serializeROSmessage`` writes the
encapsulation before the body).

Values are taken as ROS-frame values: positions and orientations in ``map``/``odom`` (ENU), body
rates and velocities in ``base_link`` (FLU), quaternions ``[x, y, z, w]``. Nothing here converts
frames; the goal heading comes from :func:`droneulator.frames.yaw_of`.

Speed: rosbags' generated serialiser copies a ``uint8[]`` field with a single buffer copy, so a
640x480 ``32FC1`` image (1.2 MB) serialises in about 0.06 ms; no hand-written CDR path is needed.
:func:`image` and :func:`compressed_image` build their ``data`` field as a zero-copy ``uint8`` view,
so the only copy of the pixels is the one :func:`serialize` makes.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from rosbags.serde import SerdeError
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from droneulator.frames import yaw_of

__all__ = [
    "ACTUATORS",
    "ACTUATORS_MSG",
    "ATTITUDE_TARGET",
    "ATTITUDE_TARGET_MSG",
    "POSITION_COMMAND",
    "POSITION_COMMAND_MSG",
    "actuators",
    "attitude_target",
    "TYPESTORE",
    "CdrBytes",
    "SerdeError",
    "StatePacker",
    "battery_state",
    "camera_info",
    "SensorPacker",
    "clock",
    "compressed_image",
    "decode",
    "fluid_pressure",
    "header",
    "image",
    "imu",
    "labelled_array",
    "occupancy_grid",
    "magnetic_field",
    "nav_sat_fix",
    "odometry",
    "pose_stamped",
    "position_command",
    "pose_stamped_to_goal",
    "serialize",
    "stamp",
    "tf_message",
    "transform_stamped",
    "vector3_stamped",
    "twist_to_command",
    "type_hash",
]

#: the one typestore every builder and decoder uses (ROS 2 Jazzy definitions and RIHS01 hashes)
TYPESTORE = get_typestore(Stores.ROS2_JAZZY)

#: ``quadrotor_msgs/msg/PositionCommand``, the trajectory server output of ZJU-FAST-Lab's EGO-Planner,
#: field for field as in ZJU-FAST-Lab/ego-planner-swarm
#: ``src/uav_simulator/Utils/quadrotor_msgs/msg/PositionCommand.msg`` (the misspelt ``TRAJECTROY`` is
#: theirs). Positions, velocities and accelerations are world-frame (ENU) values, yaw in rad about +z.
POSITION_COMMAND = "quadrotor_msgs/msg/PositionCommand"
POSITION_COMMAND_MSG = """\
std_msgs/Header header
geometry_msgs/Point position
geometry_msgs/Vector3 velocity
geometry_msgs/Vector3 acceleration
float64 yaw
float64 yaw_dot
float64[3] kx
float64[3] kv

uint32 trajectory_id

uint8 TRAJECTORY_STATUS_EMPTY = 0
uint8 TRAJECTORY_STATUS_READY = 1
uint8 TRAJECTORY_STATUS_COMPLETED = 3
uint8 TRAJECTROY_STATUS_ABORT = 4
uint8 TRAJECTORY_STATUS_ILLEGAL_START = 5
uint8 TRAJECTORY_STATUS_ILLEGAL_FINAL = 6
uint8 TRAJECTORY_STATUS_IMPOSSIBLE = 7

uint8 trajectory_flag
"""
# Registered like any Jazzy type: builders, decode() and the Zenoh node (which keys topics by the
# RIHS01 hash) handle it the same way. rosbags hashes a registered type from its field descriptions
# exactly as rosidl does (REP 2011: fields and nested types, no constants or comments).
TYPESTORE.register(get_types_from_msg(POSITION_COMMAND_MSG, POSITION_COMMAND))

#: ``mavros_msgs/msg/AttitudeTarget``, MAVROS's ``setpoint_raw/attitude`` (MAVLink SET_ATTITUDE_TARGET),
#: field for field as in mavlink/mavros ``mavros_msgs/msg/AttitudeTarget.msg``: the orientation (ENU world,
#: FLU body, as MAVROS takes it), body rates (FLU, rad/s) and a thrust normalised to [0, 1]
ATTITUDE_TARGET = "mavros_msgs/msg/AttitudeTarget"
ATTITUDE_TARGET_MSG = """\
std_msgs/Header header

uint8 type_mask
uint8 IGNORE_ROLL_RATE = 1
uint8 IGNORE_PITCH_RATE = 2
uint8 IGNORE_YAW_RATE = 4
uint8 IGNORE_THRUST = 64
uint8 IGNORE_ATTITUDE = 128

geometry_msgs/Quaternion orientation
geometry_msgs/Vector3 body_rate
float32 thrust
"""
TYPESTORE.register(get_types_from_msg(ATTITUDE_TARGET_MSG, ATTITUDE_TARGET))

#: ``actuator_msgs/msg/Actuators`` (ROS 2 Jazzy's actuator_msgs, the message ros_gz bridges to Gazebo's
#: multicopter motor model): per actuator a position, a velocity (rad/s for a rotor) or a normalised
#: command
ACTUATORS = "actuator_msgs/msg/Actuators"
ACTUATORS_MSG = """\
std_msgs/Header header

float64[] position
float64[] velocity
float64[] normalized
"""
TYPESTORE.register(get_types_from_msg(ACTUATORS_MSG, ACTUATORS))

#: a serialised sample: ``bytes`` or the ``bytearray`` rosbags serialised into (Zenoh takes both)
CdrBytes = bytes | bytearray

_T = TYPESTORE.types
_Time = _T["builtin_interfaces/msg/Time"]
_Header = _T["std_msgs/msg/Header"]
_Clock = _T["rosgraph_msgs/msg/Clock"]
_Vector3 = _T["geometry_msgs/msg/Vector3"]
_Point = _T["geometry_msgs/msg/Point"]
_Quaternion = _T["geometry_msgs/msg/Quaternion"]
_Pose = _T["geometry_msgs/msg/Pose"]
_PoseWithCovariance = _T["geometry_msgs/msg/PoseWithCovariance"]
_Twist = _T["geometry_msgs/msg/Twist"]
_TwistWithCovariance = _T["geometry_msgs/msg/TwistWithCovariance"]
_Transform = _T["geometry_msgs/msg/Transform"]
_TransformStamped = _T["geometry_msgs/msg/TransformStamped"]
_TFMessage = _T["tf2_msgs/msg/TFMessage"]
_Odometry = _T["nav_msgs/msg/Odometry"]
_CameraInfo = _T["sensor_msgs/msg/CameraInfo"]
_RegionOfInterest = _T["sensor_msgs/msg/RegionOfInterest"]
_CompressedImage = _T["sensor_msgs/msg/CompressedImage"]
_Image = _T["sensor_msgs/msg/Image"]
_PoseStamped = _T["geometry_msgs/msg/PoseStamped"]
_Vector3Stamped = _T["geometry_msgs/msg/Vector3Stamped"]
_PositionCommand = _T[POSITION_COMMAND]
_AttitudeTarget = _T[ATTITUDE_TARGET]
_Actuators = _T[ACTUATORS]
_Imu = _T["sensor_msgs/msg/Imu"]
_MagneticField = _T["sensor_msgs/msg/MagneticField"]
_FluidPressure = _T["sensor_msgs/msg/FluidPressure"]
_NavSatFix = _T["sensor_msgs/msg/NavSatFix"]
_NavSatStatus = _T["sensor_msgs/msg/NavSatStatus"]
_Float64MultiArray = _T["std_msgs/msg/Float64MultiArray"]
_MultiArrayLayout = _T["std_msgs/msg/MultiArrayLayout"]
_MultiArrayDimension = _T["std_msgs/msg/MultiArrayDimension"]
_OccupancyGrid = _T["nav_msgs/msg/OccupancyGrid"]
_MapMetaData = _T["nav_msgs/msg/MapMetaData"]
_BatteryState = _T["sensor_msgs/msg/BatteryState"]

_NS_PER_S = 1_000_000_000

#: sensor_msgs/Image encodings (REP 118 / sensor_msgs image_encodings.hpp): numpy dtype, channels
_ENCODINGS: dict[str, tuple[np.dtype, int]] = {
    "32FC1": (np.dtype("<f4"), 1),
    "16UC1": (np.dtype("<u2"), 1),
    "mono16": (np.dtype("<u2"), 1),
    "mono8": (np.dtype("u1"), 1),
    "8UC1": (np.dtype("u1"), 1),
    "rgb8": (np.dtype("u1"), 3),
    "bgr8": (np.dtype("u1"), 3),
    "rgba8": (np.dtype("u1"), 4),
    "bgra8": (np.dtype("u1"), 4),
}
#: default encoding chosen from (dtype kind and size, channels)
_DEFAULT_ENCODING: dict[tuple[str, int], str] = {
    ("f4", 1): "32FC1",
    ("u2", 1): "16UC1",
    ("u1", 1): "mono8",
    ("u1", 3): "rgb8",
    ("u1", 4): "rgba8",
}


# --------------------------------------------------------------------------- building blocks
def stamp(t_ns: int) -> Any:
    """builtin_interfaces/Time for ``t_ns`` nanoseconds: ``sec, nanosec = divmod(t_ns, 1e9)`` like rclpy."""
    sec, nanosec = divmod(int(t_ns), _NS_PER_S)
    if not -(2**31) <= sec < 2**31:
        raise ValueError(f"time {t_ns} ns does not fit builtin_interfaces/Time (int32 seconds)")
    return _Time(sec=sec, nanosec=nanosec)


def header(t_ns: int, frame_id: str) -> Any:
    """std_msgs/Header stamped ``t_ns`` in ``frame_id``."""
    return _Header(stamp=stamp(t_ns), frame_id=frame_id)


def _vec3(v: ArrayLike, name: str) -> tuple[float, float, float]:
    a = np.asarray(v, dtype=np.float64).reshape(-1)
    if a.shape != (3,):
        raise ValueError(f"{name} must have 3 elements, got shape {np.shape(v)}")
    return float(a[0]), float(a[1]), float(a[2])


def _quat(q: ArrayLike, name: str = "quaternion") -> Any:
    a = np.asarray(q, dtype=np.float64).reshape(-1)
    if a.shape != (4,):
        raise ValueError(f"{name} must be [x, y, z, w], got shape {np.shape(q)}")
    return _Quaternion(x=float(a[0]), y=float(a[1]), z=float(a[2]), w=float(a[3]))


def _covariance(cov: ArrayLike | None, name: str) -> np.ndarray:
    if cov is None:
        return np.zeros(36, dtype=np.float64)
    a = np.array(cov, dtype=np.float64).reshape(-1)
    if a.shape != (36,):
        raise ValueError(f"{name} must be 6x6 (36 values), got shape {np.shape(cov)}")
    return a


# --------------------------------------------------------------------------- builders
def clock(t_ns: int) -> Any:
    """rosgraph_msgs/Clock for ``/clock``."""
    return _Clock(clock=stamp(t_ns))


def odometry(
    t_ns: int,
    frame_id: str,
    child_frame_id: str,
    position: ArrayLike,
    quat_xyzw: ArrayLike,
    linear_velocity_body: ArrayLike,
    angular_velocity_body: ArrayLike,
    pose_cov: ArrayLike | None = None,
    twist_cov: ArrayLike | None = None,
) -> Any:
    """nav_msgs/Odometry: pose of ``child_frame_id`` in ``frame_id``, twist in ``child_frame_id``.

    REP 105 / nav_msgs: the twist is expressed in the child (body) frame, so the velocities given
    here must already be body-frame (FLU) values. Covariances are 6x6 row-major, default zeros.
    """
    px, py, pz = _vec3(position, "position")
    vx, vy, vz = _vec3(linear_velocity_body, "linear_velocity_body")
    wx, wy, wz = _vec3(angular_velocity_body, "angular_velocity_body")
    pose = _Pose(position=_Point(x=px, y=py, z=pz), orientation=_quat(quat_xyzw))
    twist = _Twist(linear=_Vector3(x=vx, y=vy, z=vz), angular=_Vector3(x=wx, y=wy, z=wz))
    return _Odometry(
        header=header(t_ns, frame_id),
        child_frame_id=child_frame_id,
        pose=_PoseWithCovariance(pose=pose, covariance=_covariance(pose_cov, "pose_cov")),
        twist=_TwistWithCovariance(twist=twist, covariance=_covariance(twist_cov, "twist_cov")),
    )


def transform_stamped(
    t_ns: int, parent: str, child: str, translation: ArrayLike, quat_xyzw: ArrayLike
) -> Any:
    """geometry_msgs/TransformStamped: pose of ``child`` expressed in ``parent``."""
    tx, ty, tz = _vec3(translation, "translation")
    transform = _Transform(translation=_Vector3(x=tx, y=ty, z=tz), rotation=_quat(quat_xyzw))
    return _TransformStamped(header=header(t_ns, parent), child_frame_id=child, transform=transform)


def vector3_stamped(t_ns: int, frame_id: str, vector: ArrayLike) -> Any:
    """geometry_msgs/Vector3Stamped: a vector (e.g. the wind's velocity) expressed in ``frame_id``."""
    x, y, z = _vec3(vector, "vector")
    return _Vector3Stamped(header=header(t_ns, frame_id), vector=_Vector3(x=x, y=y, z=z))


def tf_message(transforms: Sequence[Any]) -> Any:
    """tf2_msgs/TFMessage carrying ``transforms`` (from :func:`transform_stamped`), for /tf and /tf_static."""
    return _TFMessage(transforms=list(transforms))


def camera_info(
    t_ns: int, frame_id: str, width: int, height: int, K: ArrayLike, D: ArrayLike | None = None
) -> Any:
    """sensor_msgs/CameraInfo of a pinhole camera with ``plumb_bob`` distortion ``D`` = (k1, k2, p1, p2,
    k3) as OpenCV defines it (None: five zeros, an ideal pinhole).

    ``R`` identity and ``P = [K | 0]`` (monocular, so no baseline term; the rectified image of a
    distorted camera keeps K); binning 0 and an empty ROI mean full resolution.
    """
    k = np.array(K, dtype=np.float64).reshape(-1)
    if k.shape != (9,):
        raise ValueError(f"K must be 3x3, got shape {np.shape(K)}")
    d = np.zeros(5, dtype=np.float64) if D is None else np.array(D, dtype=np.float64).reshape(-1)
    if d.shape != (5,):
        raise ValueError(f"D must hold the five plumb_bob coefficients, got shape {np.shape(D)}")
    p = np.zeros((3, 4), dtype=np.float64)
    p[:, :3] = k.reshape(3, 3)
    return _CameraInfo(
        header=header(t_ns, frame_id),
        height=int(height),
        width=int(width),
        distortion_model="plumb_bob",
        d=d,
        k=k,
        r=np.eye(3, dtype=np.float64).reshape(-1),
        p=p.reshape(-1),
        binning_x=0,
        binning_y=0,
        roi=_RegionOfInterest(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
    )


def pose_stamped(t_ns: int, frame_id: str, position: ArrayLike, quat_xyzw: ArrayLike) -> Any:
    """geometry_msgs/PoseStamped: a pose in ``frame_id`` (e.g. a camera's optical frame in odom)."""
    px, py, pz = _vec3(position, "position")
    pose = _Pose(position=_Point(x=px, y=py, z=pz), orientation=_quat(quat_xyzw))
    return _PoseStamped(header=header(t_ns, frame_id), pose=pose)


def position_command(
    t_ns: int,
    frame_id: str,
    position: ArrayLike,
    velocity: ArrayLike = (0.0, 0.0, 0.0),
    acceleration: ArrayLike = (0.0, 0.0, 0.0),
    yaw: float = 0.0,
    yaw_dot: float = 0.0,
    trajectory_id: int = 0,
    trajectory_flag: int = 1,
    kx: ArrayLike = (0.0, 0.0, 0.0),
    kv: ArrayLike = (0.0, 0.0, 0.0),
) -> Any:
    """quadrotor_msgs/PositionCommand (EGO-Planner's): a flat-output setpoint in ``frame_id``.

    ``trajectory_flag`` defaults to ``TRAJECTORY_STATUS_READY`` (1); ``kx``/``kv`` are the optional
    per-axis gains EGO's ``so3_control`` reads, zero meaning "use your own".
    """
    px, py, pz = _vec3(position, "position")
    vx, vy, vz = _vec3(velocity, "velocity")
    ax, ay, az = _vec3(acceleration, "acceleration")
    return _PositionCommand(
        header=header(t_ns, frame_id),
        position=_Point(x=px, y=py, z=pz),
        velocity=_Vector3(x=vx, y=vy, z=vz),
        acceleration=_Vector3(x=ax, y=ay, z=az),
        yaw=float(yaw),
        yaw_dot=float(yaw_dot),
        kx=np.array(_vec3(kx, "kx"), dtype=np.float64),
        kv=np.array(_vec3(kv, "kv"), dtype=np.float64),
        trajectory_id=int(trajectory_id),
        trajectory_flag=int(trajectory_flag),
    )


def attitude_target(
    t_ns: int,
    frame_id: str,
    thrust: float,
    quat_xyzw: ArrayLike = (0.0, 0.0, 0.0, 1.0),
    body_rate: ArrayLike = (0.0, 0.0, 0.0),
    type_mask: int = 0,
) -> Any:
    """mavros_msgs/AttitudeTarget: a normalised ``thrust`` with an attitude or body rates (``type_mask``
    says which fields to ignore: 128 the orientation, 1, 2, 4 the body rates, 64 the thrust)."""
    rx, ry, rz = _vec3(body_rate, "body_rate")
    return _AttitudeTarget(
        header=header(t_ns, frame_id),
        type_mask=int(type_mask),
        orientation=_quat(quat_xyzw),
        body_rate=_Vector3(x=rx, y=ry, z=rz),
        thrust=np.float32(thrust),
    )


def actuators(
    t_ns: int, velocity: ArrayLike = (), normalized: ArrayLike = (), position: ArrayLike = ()
) -> Any:
    """actuator_msgs/Actuators: per actuator commands (rotor speeds in ``velocity``, rad/s)."""
    return _Actuators(
        header=header(t_ns, ""),
        position=np.asarray(position, dtype=np.float64),
        velocity=np.asarray(velocity, dtype=np.float64),
        normalized=np.asarray(normalized, dtype=np.float64),
    )


def _cov3(cov: ArrayLike | None, name: str) -> np.ndarray:
    if cov is None:
        return np.zeros(9, dtype=np.float64)
    a = np.array(cov, dtype=np.float64).reshape(-1)
    if a.shape == (3,):
        return np.diag(a).reshape(-1)  # a diagonal
    if a.shape != (9,):
        raise ValueError(f"{name} must be 3x3 (9 values) or its diagonal (3 values), got {np.shape(cov)}")
    return a


#: REP 145: ``orientation_covariance[0] = -1`` says the message carries no orientation
NO_ORIENTATION = np.array([-1.0, 0, 0, 0, 0, 0, 0, 0, 0])


def imu(
    t_ns: int,
    frame_id: str,
    angular_velocity: ArrayLike,
    linear_acceleration: ArrayLike,
    angular_velocity_cov: ArrayLike | None = None,
    linear_acceleration_cov: ArrayLike | None = None,
    orientation_xyzw: ArrayLike | None = None,
    orientation_cov: ArrayLike | None = None,
) -> Any:
    """sensor_msgs/Imu in ``frame_id`` (the body, FLU: REP 103): rates (rad/s) and specific force (m/s^2,
    +9.81 up at rest). Covariances are 3x3 row-major or their diagonal. Without ``orientation_xyzw`` the
    orientation is the identity with ``orientation_covariance[0] = -1`` (REP 145: no orientation given)."""
    wx, wy, wz = _vec3(angular_velocity, "angular_velocity")
    ax, ay, az = _vec3(linear_acceleration, "linear_acceleration")
    if orientation_xyzw is None:
        q, q_cov = _Quaternion(x=0.0, y=0.0, z=0.0, w=1.0), NO_ORIENTATION.copy()
    else:
        q, q_cov = _quat(orientation_xyzw, "orientation_xyzw"), _cov3(orientation_cov, "orientation_cov")
    return _Imu(
        header=header(t_ns, frame_id),
        orientation=q,
        orientation_covariance=q_cov,
        angular_velocity=_Vector3(x=wx, y=wy, z=wz),
        angular_velocity_covariance=_cov3(angular_velocity_cov, "angular_velocity_cov"),
        linear_acceleration=_Vector3(x=ax, y=ay, z=az),
        linear_acceleration_covariance=_cov3(linear_acceleration_cov, "linear_acceleration_cov"),
    )


def magnetic_field(t_ns: int, frame_id: str, field_tesla: ArrayLike, cov: ArrayLike | None = None) -> Any:
    """sensor_msgs/MagneticField: the field (tesla) in ``frame_id``, covariance (T^2) 3x3 or diagonal."""
    x, y, z = _vec3(field_tesla, "field_tesla")
    return _MagneticField(
        header=header(t_ns, frame_id),
        magnetic_field=_Vector3(x=x, y=y, z=z),
        magnetic_field_covariance=_cov3(cov, "cov"),
    )


def fluid_pressure(t_ns: int, frame_id: str, pressure_pa: float, variance: float = 0.0) -> Any:
    """sensor_msgs/FluidPressure: absolute pressure (Pa) and its variance (Pa^2; 0 is unknown)."""
    return _FluidPressure(
        header=header(t_ns, frame_id), fluid_pressure=float(pressure_pa), variance=float(variance)
    )


#: sensor_msgs/NavSatStatus values
STATUS_NO_FIX, STATUS_FIX, STATUS_SBAS_FIX, STATUS_GBAS_FIX = -1, 0, 1, 2
SERVICE_GPS = 1
COVARIANCE_TYPE_DIAGONAL_KNOWN = 2


def nav_sat_fix(
    t_ns: int,
    frame_id: str,
    lat_deg: float,
    lon_deg: float,
    alt_m: float,
    cov_enu: ArrayLike | None = None,
    status: int = STATUS_FIX,
    service: int = SERVICE_GPS,
    cov_type: int = COVARIANCE_TYPE_DIAGONAL_KNOWN,
) -> Any:
    """sensor_msgs/NavSatFix: a WGS84 fix with its position covariance (m^2, east/north/up, 3x3 or its
    diagonal), ``status`` (-1 no fix, 0 fix, 1 SBAS, 2 ground-based augmentation: RTK) and ``service``."""
    return _NavSatFix(
        header=header(t_ns, frame_id),
        status=_NavSatStatus(status=int(status), service=int(service)),
        latitude=float(lat_deg),
        longitude=float(lon_deg),
        altitude=float(alt_m),
        position_covariance=_cov3(cov_enu, "cov_enu"),
        position_covariance_type=int(cov_type),
    )


def battery_state(
    t_ns: int,
    frame_id: str,
    voltage: float,
    current: float,
    charge_ah: float,
    capacity_ah: float,
    percentage: float,
    cells: int,
    empty: bool = False,
) -> Any:
    """sensor_msgs/BatteryState of a LiPo pack of ``cells`` equal cells in series: terminal ``voltage`` (V),
    ``current`` (A, discharging positive as the simulator counts it; the message carries it negative, as
    sensor_msgs defines), remaining ``charge_ah`` of ``capacity_ah`` (the design capacity too), ``percentage``
    in [0, 1]; temperatures unmeasured (NaN). Status discharging while it gives current, health dead once
    the pack is spent (``empty``)."""
    B = _BatteryState
    status = B.POWER_SUPPLY_STATUS_DISCHARGING if current > 0.0 else B.POWER_SUPPLY_STATUS_NOT_CHARGING
    return B(
        header=header(t_ns, frame_id),
        voltage=np.float32(voltage),
        temperature=np.float32(math.nan),
        current=np.float32(-current),
        charge=np.float32(charge_ah),
        capacity=np.float32(capacity_ah),
        design_capacity=np.float32(capacity_ah),
        percentage=np.float32(percentage),
        power_supply_status=status,
        power_supply_health=B.POWER_SUPPLY_HEALTH_DEAD if empty else B.POWER_SUPPLY_HEALTH_GOOD,
        power_supply_technology=B.POWER_SUPPLY_TECHNOLOGY_LIPO,
        present=True,
        cell_voltage=np.full(int(cells), voltage / cells, dtype=np.float32),
        cell_temperature=np.full(int(cells), math.nan, dtype=np.float32),
        location="",
        serial_number="",
    )


def compressed_image(t_ns: int, frame_id: str, fmt: str, data_bytes: bytes | bytearray) -> Any:
    """sensor_msgs/CompressedImage; ``fmt`` is the image_transport format string ("jpeg", "png").

    ``data`` is a zero-copy ``uint8`` view of ``data_bytes``: do not mutate a ``bytearray`` passed
    here before the message is serialised.
    """
    return _CompressedImage(
        header=header(t_ns, frame_id), format=fmt, data=np.frombuffer(data_bytes, dtype=np.uint8)
    )


def image(t_ns: int, frame_id: str, array: np.ndarray, encoding: str | None = None) -> Any:
    """sensor_msgs/Image from an HxW or HxWxC array, little endian, ``step = width * bytes per pixel``.

    Encodings: float32 HxW -> ``32FC1`` (depth in metres, NaN = no return, REP 118), uint16 HxW ->
    ``16UC1``, uint8 HxW -> ``mono8``, uint8 HxWx3 -> ``rgb8``, uint8 HxWx4 -> ``rgba8``; ``encoding``
    may name another layout-compatible one (``bgr8``, ``mono16``...). A C-contiguous little-endian
    array is not copied: ``data`` is a ``uint8`` view of it, so keep it unchanged until serialised.
    """
    arr = np.asarray(array)
    if arr.ndim not in (2, 3):
        raise ValueError(f"image must be HxW or HxWxC, got shape {arr.shape}")
    channels = 1 if arr.ndim == 2 else arr.shape[2]
    if encoding is None:
        encoding = _DEFAULT_ENCODING.get((f"{arr.dtype.kind}{arr.dtype.itemsize}", channels))
        if encoding is None:
            raise ValueError(f"no sensor_msgs/Image encoding for dtype {arr.dtype} with {channels} channels")
    if encoding not in _ENCODINGS:
        raise ValueError(f"unsupported image encoding {encoding!r}; known: {sorted(_ENCODINGS)}")
    dtype, want_channels = _ENCODINGS[encoding]
    if channels != want_channels or arr.dtype.kind != dtype.kind or arr.dtype.itemsize != dtype.itemsize:
        raise ValueError(
            f"encoding {encoding!r} needs {want_channels} x {dtype}, got {channels} x {arr.dtype}"
        )
    # both calls return ``arr`` itself when it is already little-endian and C-contiguous
    arr = np.ascontiguousarray(arr.astype(dtype, copy=False))
    height, width = arr.shape[:2]
    return _Image(
        header=header(t_ns, frame_id),
        height=height,
        width=width,
        encoding=encoding,
        is_bigendian=0,
        step=width * channels * dtype.itemsize,
        data=arr.reshape(-1).view(np.uint8),
    )


# --------------------------------------------------------------------------- (de)serialisation
def string(data: str) -> Any:
    """std_msgs/String holding ``data``."""
    return _T["std_msgs/msg/String"](data=data)


def labelled_array(labels: Sequence[str], values: Sequence[float]) -> Any:
    """std_msgs/Float64MultiArray of ``values``, one layout dimension per value naming it (size 1)."""
    if len(labels) != len(values):
        raise ValueError(f"{len(labels)} labels for {len(values)} values")
    dims = [_MultiArrayDimension(label=str(k), size=1, stride=1) for k in labels]
    return _Float64MultiArray(
        layout=_MultiArrayLayout(dim=dims, data_offset=0), data=np.asarray(values, dtype=np.float64)
    )


def occupancy_grid(
    t_ns: int, frame_id: str, values: np.ndarray, resolution: float, origin_xy: ArrayLike
) -> Any:
    """nav_msgs/OccupancyGrid of ``values`` (int8, indexed ``[x, y]``, -1..100): row-major in y as the
    message wants, its cell (0, 0) corner at ``origin_xy`` (m) in ``frame_id``."""
    grid = np.ascontiguousarray(np.asarray(values, dtype=np.int8).T)
    h, w = grid.shape
    ox, oy = (float(v) for v in np.asarray(origin_xy, dtype=float)[:2])
    info = _MapMetaData(
        map_load_time=stamp(t_ns), resolution=float(resolution), width=w, height=h,
        origin=_Pose(position=_Point(x=ox, y=oy, z=0.0), orientation=_Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)),
    )  # fmt: skip
    return _OccupancyGrid(header=header(t_ns, frame_id), info=info, data=grid.reshape(-1))


def serialize(msg: Any) -> CdrBytes:
    """CDR bytes of a rosbags message, encapsulation header included (``00 01 00 00``, little endian).

    Returns the ``bytearray`` rosbags serialised into (no extra copy); Zenoh publishes it as is.
    """
    view = TYPESTORE.serialize_cdr(msg, msg.__msgtype__)
    buf = view.obj
    if isinstance(buf, bytearray | bytes) and len(buf) == view.nbytes:
        return buf
    return bytes(view)


class StatePacker:
    """CDR bytes of the per-step state messages (Clock, Odometry, one-transform TFMessage, the wind's
    Vector3Stamped) in a few microseconds, for the odometry latency path.

    Their layout is fixed once the frame ids are: a template is serialised by rosbags once, the byte
    offsets of the stamp and the numeric fields are found in it (from sentinel values), and each call
    copies the template and writes the numbers in place. The output is byte-identical to
    :func:`serialize` of the :func:`odometry` / :func:`tf_message` / :func:`clock` builders (tested).
    """

    _SENTINEL = 1.0000000000000002e-299  # a double no real field holds

    def __init__(self, frame_id: str, child_frame_id: str) -> None:
        s = self._SENTINEL
        probe = odometry(0, frame_id, child_frame_id, [s, 2 * s, 3 * s], [4 * s, 5 * s, 6 * s, 7 * s],
                         [8 * s, 9 * s, 10 * s], [11 * s, 12 * s, 13 * s])
        self._odom = bytes(serialize(probe))
        self._odom_pose = self._offset(self._odom, s)
        self._odom_twist = self._offset(self._odom, 8 * s)
        tf = tf_message([transform_stamped(0, frame_id, child_frame_id, [s, 2 * s, 3 * s],
                                           [4 * s, 5 * s, 6 * s, 7 * s])])
        self._tf = bytes(serialize(tf))
        self._tf_pose = self._offset(self._tf, s)
        self._tf_stamp = 8  # encapsulation (4) + sequence length (4): the first transform's header
        self._vec = bytes(serialize(vector3_stamped(0, frame_id, [s, 2 * s, 3 * s])))
        self._vec_value = self._offset(self._vec, s)

    @staticmethod
    def _offset(buf: bytes, value: float) -> int:
        i = buf.find(struct.pack("<d", value))
        if i < 0:
            raise AssertionError("sentinel not found in the serialised template")
        return i

    @staticmethod
    def _stamp(t_ns: int) -> tuple[int, int]:
        sec, nanosec = divmod(int(t_ns), _NS_PER_S)
        if not -(2**31) <= sec < 2**31:
            raise ValueError(f"time {t_ns} ns does not fit builtin_interfaces/Time (int32 seconds)")
        return sec, nanosec

    def clock(self, t_ns: int) -> bytes:
        return _CLOCK.pack(0x0100, 0, *self._stamp(t_ns))

    def odometry(self, t_ns: int, position: np.ndarray, quat_xyzw: np.ndarray, v_body: np.ndarray,
                 w_body: np.ndarray) -> bytearray:
        buf = bytearray(self._odom)
        _STAMP.pack_into(buf, 4, *self._stamp(t_ns))
        _POSE.pack_into(buf, self._odom_pose, *position, *quat_xyzw)
        _TWIST.pack_into(buf, self._odom_twist, *v_body, *w_body)
        return buf

    def vector(self, t_ns: int, vector: np.ndarray) -> bytearray:
        """A Vector3Stamped in the packer's ``frame_id``."""
        buf = bytearray(self._vec)
        _STAMP.pack_into(buf, 4, *self._stamp(t_ns))
        _VEC.pack_into(buf, self._vec_value, *vector)
        return buf

    def transform(self, t_ns: int, position: np.ndarray, quat_xyzw: np.ndarray) -> bytearray:
        buf = bytearray(self._tf)
        _STAMP.pack_into(buf, self._tf_stamp, *self._stamp(t_ns))
        _POSE.pack_into(buf, self._tf_pose, *position, *quat_xyzw)
        return buf


class SensorPacker:
    """CDR bytes of one vehicle's sensor messages in ``frame_id`` (its base_link): Imu (no orientation),
    MagneticField and FluidPressure with fixed covariances, from templates as :class:`StatePacker` does
    (byte-identical to :func:`serialize` of :func:`imu`, :func:`magnetic_field`, :func:`fluid_pressure`;
    tested). Variances: ``gyro_var`` (rad/s)^2, ``accel_var`` (m/s^2)^2 per axis, ``mag_var`` T^2 per
    axis, ``pressure_var`` Pa^2."""

    _SENTINEL = StatePacker._SENTINEL

    def __init__(
        self, frame_id: str, gyro_var: float = 0.0, accel_var: float = 0.0, mag_var: float = 0.0,
        pressure_var: float = 0.0,
    ) -> None:  # fmt: skip
        s = self._SENTINEL
        probe = imu(0, frame_id, [s, 2 * s, 3 * s], [4 * s, 5 * s, 6 * s], [gyro_var] * 3, [accel_var] * 3)
        self._imu = bytes(serialize(probe))
        self._imu_gyro = StatePacker._offset(self._imu, s)
        self._imu_accel = StatePacker._offset(self._imu, 4 * s)
        self._mag = bytes(serialize(magnetic_field(0, frame_id, [s, 2 * s, 3 * s], [mag_var] * 3)))
        self._mag_value = StatePacker._offset(self._mag, s)
        self._baro = bytes(serialize(fluid_pressure(0, frame_id, s, pressure_var)))
        self._baro_value = StatePacker._offset(self._baro, s)

    def imu(self, t_ns: int, gyro_flu: np.ndarray, accel_flu: np.ndarray) -> bytearray:
        buf = bytearray(self._imu)
        _STAMP.pack_into(buf, 4, *StatePacker._stamp(t_ns))
        _VEC.pack_into(buf, self._imu_gyro, *gyro_flu)
        _VEC.pack_into(buf, self._imu_accel, *accel_flu)
        return buf

    def magnetic_field(self, t_ns: int, field_tesla: np.ndarray) -> bytearray:
        buf = bytearray(self._mag)
        _STAMP.pack_into(buf, 4, *StatePacker._stamp(t_ns))
        _VEC.pack_into(buf, self._mag_value, *field_tesla)
        return buf

    def fluid_pressure(self, t_ns: int, pressure_pa: float) -> bytearray:
        buf = bytearray(self._baro)
        _STAMP.pack_into(buf, 4, *StatePacker._stamp(t_ns))
        _DOUBLE.pack_into(buf, self._baro_value, pressure_pa)
        return buf


_CLOCK = struct.Struct("<HHiI")
_STAMP = struct.Struct("<iI")
_POSE = struct.Struct("<7d")
_TWIST = struct.Struct("<6d")
_VEC = struct.Struct("<3d")
_DOUBLE = struct.Struct("<d")


def decode(typename: str, payload: bytes | bytearray | memoryview) -> Any:
    """Deserialise a full CDR sample (with its encapsulation header) into a rosbags message.

    Raises :class:`rosbags.serde.SerdeError` for anything that is not a valid ``typename`` sample:
    a bad encapsulation header, a truncated body or trailing bytes beyond CDR padding.
    """
    try:
        return TYPESTORE.deserialize_cdr(payload, typename)
    except SerdeError:
        raise
    except (IndexError, ValueError, TypeError, OverflowError) as exc:
        raise SerdeError(f"could not deserialize {typename!r}: {exc}") from exc


def type_hash(typename: str) -> str:
    """REP 2011 type hash ``RIHS01_<64 hex>`` of a message type, as ROS 2 Jazzy computes it."""
    return TYPESTORE.hash_rihs01(typename)


# --------------------------------------------------------------------------- command decoders
def _finite(*values: float) -> None:
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f"non-finite value in command: {values}")


def twist_to_command(msg: Any) -> tuple[float, float]:
    """geometry_msgs/Twist on ``cmd_vel`` -> (forward m/s = ``linear.x``, yaw rate rad/s = ``angular.z``).

    The other components are ignored (a multirotor velocity command in FLU body axes, REP 103).
    """
    forward, yaw_rate = float(msg.linear.x), float(msg.angular.z)
    _finite(forward, yaw_rate)
    return forward, yaw_rate


def pose_stamped_to_goal(msg: Any) -> tuple[str, np.ndarray, float]:
    """geometry_msgs/PoseStamped goal -> (frame_id, position (3,), yaw rad about +z).

    The yaw is the heading of the orientation quaternion (ZYX Euler yaw); the quaternion need not be
    normalised but must not be zero.
    """
    p, q = msg.pose.position, msg.pose.orientation
    position = np.array([p.x, p.y, p.z], dtype=np.float64)
    x, y, z, w = float(q.x), float(q.y), float(q.z), float(q.w)
    _finite(*position, x, y, z, w)
    norm2 = x * x + y * y + z * z + w * w
    if norm2 < 1e-12:
        raise ValueError("goal orientation quaternion is zero")
    return msg.header.frame_id, position, yaw_of(np.array([x, y, z, w]))
