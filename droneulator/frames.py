"""Every frame convention in Droneulator, and the only place that converts between them.

Conventions
-----------
* **World (RotorPy / ROS ``map``, ENU)**: right-handed, Z up, metres. RotorPy integrates here.
* **Body (FLU)**: x forward, y left, z up (REP 103). Quaternions are ``[x, y, z, w]`` (RotorPy and
  SciPy order) and rotate body vectors into the world: ``v_world = R(q) @ v_body``.
* **OpenGL world (Y up)**: ``(x, y, z)_zup -> (x, z, -y)_yup``; the renderer's world. OpenGL cameras
  look down their own -Z with +Y up.
* **Camera optical (ROS)**: z forward, x right, y down. ``camera link`` frames follow body FLU axes.
* **PX4 NED / FRD**: world North-East-Down, body Forward-Right-Down.

Transforms are 4x4 homogeneous matrices named ``T_a_b``: they map coordinates in frame ``b`` to
frame ``a`` (``p_a = T_a_b @ p_b``).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

# --------------------------------------------------------------------------- constant axis swaps
#: Z-up world -> Y-up OpenGL world (rotation of -90 deg about x).
R_GL_ZUP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
#: Camera link (FLU axes) -> optical frame (z forward, x right, y down), i.e. p_opt = R @ p_link.
R_OPT_LINK = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
#: Optical frame -> OpenGL camera frame (x right, y up, looking down -z).
R_GLCAM_OPT = np.diag([1.0, -1.0, -1.0])
#: ENU world -> NED world (also FLU body -> FRD body is R_FRD_FLU).
R_NED_ENU = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
R_FRD_FLU = np.diag([1.0, -1.0, -1.0])
_ROT_NED_ENU = Rotation.from_matrix(R_NED_ENU)
_ROT_FRD_FLU = Rotation.from_matrix(R_FRD_FLU)


# --------------------------------------------------------------------------- quaternions [x,y,z,w]
# SciPy's ``Rotation`` uses the same [x, y, z, w] order; it does the quaternion algebra here. The
# numba kernels use the compiled twins in :mod:`droneulator.frames_numba` instead.
def quat_normalize(q: np.ndarray) -> np.ndarray:
    """Unit quaternion along ``q``; a zero quaternion has no attitude and raises ValueError."""
    q = np.asarray(q, dtype=float)
    n = float(np.linalg.norm(q))
    if q.shape != (4,) or not n > 0.0 or not math.isfinite(n):
        raise ValueError(f"a quaternion needs four finite components, not all zero; got {q.tolist()}")
    return q / n


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a (normalised here) ``[x, y, z, w]`` quaternion."""
    return Rotation.from_quat(quat_normalize(q)).as_matrix()


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """``[x, y, z, w]`` quaternion (w >= 0) of a rotation matrix."""
    return Rotation.from_matrix(np.asarray(R, dtype=float)).as_quat(canonical=True)


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Product ``a * b`` of unit quaternions (apply ``b`` first, then ``a``)."""
    return (Rotation.from_quat(quat_normalize(a)) * Rotation.from_quat(quat_normalize(b))).as_quat()


def quat_conjugate(q: np.ndarray) -> np.ndarray:
    """The inverse rotation of a unit quaternion."""
    return Rotation.from_quat(quat_normalize(q)).inv().as_quat()


def quat_from_euler(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Quaternion of intrinsic Z-Y-X (yaw, then pitch, then roll) Euler angles in radians."""
    return Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_quat()


def quat_to_euler(q: np.ndarray) -> tuple[float, float, float]:
    """(roll, pitch, yaw) in radians, Z-Y-X convention, inverse of :func:`quat_from_euler`."""
    yaw, pitch, roll = Rotation.from_quat(quat_normalize(q)).as_euler("ZYX")
    return float(roll), float(pitch), float(yaw)


def quat_from_yaw(yaw: float) -> np.ndarray:
    """Level attitude with heading ``yaw`` (radians about world z)."""
    return np.array([0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)])


def yaw_of(q: np.ndarray) -> float:
    """Heading (Z-Y-X Euler yaw about world z) of a body quaternion, radians in (-pi, pi].

    ``q`` need not be normalised (ROS goal poses often are not); a zero quaternion raises ValueError.
    """
    x, y, z, w = (float(c) for c in quat_normalize(q))
    return math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def yaws_of(q: np.ndarray) -> np.ndarray:
    """:func:`yaw_of` of every unit quaternion along the last axis of ``q`` (``(..., 4)``: state rows)."""
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def quat_slerp(q0: np.ndarray, q1: np.ndarray, f: float) -> np.ndarray:
    """Spherical linear interpolation from ``q0`` (``f = 0``) to ``q1`` (``f = 1``) along the shorter arc."""
    key = Rotation.from_quat(np.stack([quat_normalize(q0), quat_normalize(q1)]))
    return Slerp([0.0, 1.0], key)(float(f)).as_quat()


def wrap_angle(a: float) -> float:
    """Angle wrapped to [-pi, pi)."""
    return (a + math.pi) % (2 * math.pi) - math.pi


# --------------------------------------------------------------------------- homogeneous transforms
def make_transform(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def invert_transform(T: np.ndarray) -> np.ndarray:
    R, t = T[:3, :3], T[:3, 3]
    return make_transform(R.T, -R.T @ t)


def transform_from_pose(position: np.ndarray, quat: np.ndarray) -> np.ndarray:
    """``T_parent_child`` from a child pose (position, ``[x,y,z,w]``) expressed in the parent."""
    return make_transform(quat_to_matrix(quat), np.asarray(position, dtype=float))


def transforms_from_poses(positions: np.ndarray, quats: np.ndarray) -> np.ndarray:
    """:func:`transform_from_pose` of many poses: ``(n, 3)`` positions and ``(n, 4)`` ``[x,y,z,w]``
    quaternions (normalised here) -> ``(n, 4, 4)``."""
    q = np.asarray(quats, dtype=float).reshape(-1, 4)
    n = np.linalg.norm(q, axis=1, keepdims=True)
    if not (np.all(n > 0.0) and np.all(np.isfinite(n))):
        raise ValueError("quaternions need four finite components, not all zero")
    T = np.zeros((len(q), 4, 4))
    T[:, :3, :3] = Rotation.from_quat(q / n).as_matrix()
    T[:, :3, 3] = np.asarray(positions, dtype=float).reshape(-1, 3)
    T[:, 3, 3] = 1.0
    return T


def pose_from_transform(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return T[:3, 3].copy(), matrix_to_quat(T[:3, :3])


def transform_points(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Apply ``T`` to points of shape (..., 3)."""
    p = np.asarray(p, dtype=float)
    return p @ T[:3, :3].T + T[:3, 3]


def world_to_body(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """A world-frame vector (velocity, ...) expressed in the body frame of attitude ``q`` ([x, y, z, w])."""
    return quat_to_matrix(q).T @ np.asarray(v, dtype=float)


def body_to_world(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """A body-frame vector (angular velocity, ...) expressed in the world frame."""
    return quat_to_matrix(q) @ np.asarray(v, dtype=float)


# --------------------------------------------------------------------------- named conversions
def zup_to_gl(v: np.ndarray) -> np.ndarray:
    """Points or directions (..., 3) from the Z-up world to the Y-up OpenGL world."""
    return np.asarray(v, dtype=float) @ R_GL_ZUP.T


def gl_to_zup(v: np.ndarray) -> np.ndarray:
    return np.asarray(v, dtype=float) @ R_GL_ZUP


def T_link_optical() -> np.ndarray:
    """Optical frame expressed in its camera link frame (the REP 103 static optical transform)."""
    return make_transform(R_OPT_LINK.T, np.zeros(3))


def camera_mount(position: np.ndarray, rpy: tuple[float, float, float]) -> np.ndarray:
    """``T_body_link`` of a camera link mounted at ``position`` (body FLU) with roll/pitch/yaw.

    Positive pitch tilts the camera's forward axis down (rotation about the body's left axis).
    """
    return make_transform(quat_to_matrix(quat_from_euler(*rpy)), np.asarray(position, dtype=float))


def T_world_optical(T_world_body: np.ndarray, T_body_link: np.ndarray) -> np.ndarray:
    """Pose of a camera's optical frame in the Z-up world."""
    return T_world_body @ T_body_link @ T_link_optical()


def gl_model_matrix(T_world_body: np.ndarray) -> np.ndarray:
    """OpenGL model matrix of a body posed in the Z-up world: body-frame points -> the Y-up GL world."""
    return make_transform(R_GL_ZUP, np.zeros(3)) @ np.asarray(T_world_body, dtype=float)


def gl_view_matrix(T_world_optical_: np.ndarray) -> np.ndarray:
    """OpenGL view matrix (Y-up GL world -> GL camera) for an optical frame posed in the Z-up world."""
    T_gl_world = make_transform(R_GL_ZUP, np.zeros(3))
    T_glworld_glcam = T_gl_world @ T_world_optical_ @ make_transform(R_GLCAM_OPT.T, np.zeros(3))
    return invert_transform(T_glworld_glcam)


def enu_to_ned(v: np.ndarray) -> np.ndarray:
    """Positions, velocities or accelerations (..., 3) from ENU to NED (self-inverse)."""
    return np.asarray(v, dtype=float) @ R_NED_ENU.T


ned_to_enu = enu_to_ned


def flu_to_frd(v: np.ndarray) -> np.ndarray:
    """Body vectors (..., 3) from FLU to FRD (self-inverse)."""
    return np.asarray(v, dtype=float) @ R_FRD_FLU.T


frd_to_flu = flu_to_frd


def quat_enu_flu_to_ned_frd(q: np.ndarray) -> np.ndarray:
    """Attitude ``[x,y,z,w]`` (FLU body in ENU world) -> FRD body in NED world, same ``[x,y,z,w]`` order."""
    return (_ROT_NED_ENU * Rotation.from_quat(quat_normalize(q)) * _ROT_FRD_FLU.inv()).as_quat(canonical=True)


def quat_ned_frd_to_enu_flu(q: np.ndarray) -> np.ndarray:
    """Inverse of :func:`quat_enu_flu_to_ned_frd`."""
    return (_ROT_NED_ENU.inv() * Rotation.from_quat(quat_normalize(q)) * _ROT_FRD_FLU).as_quat(canonical=True)


def yaw_enu_to_ned(yaw_enu: float) -> float:
    """Heading from east, counter-clockwise (ENU/FLU) -> from north, clockwise (NED/FRD)."""
    return yaw_of(quat_enu_flu_to_ned_frd(quat_from_yaw(yaw_enu)))


def yaw_ned_to_enu(yaw_ned: float) -> float:
    """Inverse of :func:`yaw_enu_to_ned`: heading from north, clockwise -> from east, counter-clockwise."""
    return yaw_of(quat_ned_frd_to_enu_flu(quat_from_yaw(yaw_ned)))


def yaw_rate_enu_to_ned(yaw_rate_enu: float) -> float:
    """Rate about world up -> rate about world down (the z of the ENU angular velocity in NED)."""
    return float(enu_to_ned(np.array([0.0, 0.0, yaw_rate_enu]))[2])


def xyzw_to_wxyz(q: np.ndarray) -> np.ndarray:
    """Reorder for consumers that want the scalar first (MAVLink, some ROS tools)."""
    return np.array([q[3], q[0], q[1], q[2]], dtype=float)


def wxyz_to_xyzw(q: np.ndarray) -> np.ndarray:
    return np.array([q[1], q[2], q[3], q[0]], dtype=float)


# --------------------------------------------------------------------------- geodetic (WGS84 lat/lon)
#: mean Earth radius PX4 uses for its local projections (``CONSTANTS_RADIUS_OF_EARTH``), metres
EARTH_RADIUS_M = 6371000.0


def enu_to_geodetic(
    enu: np.ndarray, lat0_deg: float, lon0_deg: float, alt0_m: float
) -> tuple[float, float, float]:
    """(latitude deg, longitude deg, altitude m) of an ENU offset from a geodetic origin.

    Uses the azimuthal equidistant projection of PX4's ``MapProjection::reproject`` on a sphere of
    radius :data:`EARTH_RADIUS_M`, so PX4 projects the result back onto exactly this ENU offset.
    Altitude is the origin's altitude plus the up component.
    """
    east, north, up = (float(v) for v in np.asarray(enu, dtype=float))
    lat0, lon0 = math.radians(lat0_deg), math.radians(lon0_deg)
    x_rad, y_rad = north / EARTH_RADIUS_M, east / EARTH_RADIUS_M
    c = math.hypot(x_rad, y_rad)
    if c == 0.0:
        return float(lat0_deg), float(lon0_deg), alt0_m + up
    sin_c, cos_c = math.sin(c), math.cos(c)
    arg = cos_c * math.sin(lat0) + x_rad * sin_c * math.cos(lat0) / c
    lat = math.asin(max(-1.0, min(1.0, arg)))
    lon = lon0 + math.atan2(y_rad * sin_c, c * math.cos(lat0) * cos_c - x_rad * math.sin(lat0) * sin_c)
    lon_deg = (math.degrees(lon) + 180.0) % 360.0 - 180.0
    return math.degrees(lat), lon_deg, alt0_m + up


def geodetic_to_enu(
    lat_deg: float, lon_deg: float, alt_m: float, lat0_deg: float, lon0_deg: float, alt0_m: float
) -> np.ndarray:
    """ENU offset (m) of a geodetic point from an origin: the inverse of :func:`enu_to_geodetic`
    (PX4's ``MapProjection::project``)."""
    lat, lon = math.radians(lat_deg), math.radians(lon_deg)
    lat0, lon0 = math.radians(lat0_deg), math.radians(lon0_deg)
    cos_d_lon = math.cos(lon - lon0)
    arg = math.sin(lat0) * math.sin(lat) + math.cos(lat0) * math.cos(lat) * cos_d_lon
    c = math.acos(max(-1.0, min(1.0, arg)))
    k = c / math.sin(c) if c != 0.0 else 1.0
    north = k * (math.cos(lat0) * math.sin(lat) - math.sin(lat0) * math.cos(lat) * cos_d_lon) * EARTH_RADIUS_M
    east = k * math.cos(lat) * math.sin(lon - lon0) * EARTH_RADIUS_M
    return np.array([east, north, alt_m - alt0_m])


# --------------------------------------------------------------------------- COLMAP image poses
def colmap_cam_from_world(T_world_optical_: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """COLMAP ``images.txt`` pose ``(QW QX QY QZ, TX TY TZ)`` of an optical frame posed in the world.

    COLMAP's camera frame is the ROS optical frame (x right, y down, z forward), so no axis swap is
    needed; COLMAP stores the *world-to-camera* transform (``p_cam = R @ p_world + t``), i.e. the
    inverse of ``T_world_optical``, with its quaternion scalar first.
    """
    T_cam_world = invert_transform(np.asarray(T_world_optical_, dtype=float))
    return xyzw_to_wxyz(matrix_to_quat(T_cam_world[:3, :3])), T_cam_world[:3, 3].copy()


def colmap_to_T_world_optical(qvec_wxyz: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """Inverse of :func:`colmap_cam_from_world`: the optical frame's pose in the world."""
    R = quat_to_matrix(wxyz_to_xyzw(np.asarray(qvec_wxyz, dtype=float)))
    return invert_transform(make_transform(R, np.asarray(tvec, dtype=float)))
