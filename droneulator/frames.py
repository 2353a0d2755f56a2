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


# --------------------------------------------------------------------------- quaternions [x,y,z,w]
def quat_normalize(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, dtype=float)
    return q / np.linalg.norm(q)


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a (normalised here) ``[x, y, z, w]`` quaternion."""
    x, y, z, w = quat_normalize(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """``[x, y, z, w]`` quaternion (w >= 0) of a rotation matrix (Shepperd's method)."""
    R = np.asarray(R, dtype=float)
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s, (R[2, 1] - R[1, 2]) / s]
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s, (R[0, 2] - R[2, 0]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s, (R[1, 0] - R[0, 1]) / s]
    q = np.array(q)
    return quat_normalize(-q if q[3] < 0 else q)


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product ``a * b`` (apply ``b`` first, then ``a``)."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return np.array(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ]
    )


def quat_conjugate(q: np.ndarray) -> np.ndarray:
    return np.array([-q[0], -q[1], -q[2], q[3]], dtype=float)


def quat_from_euler(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Quaternion of intrinsic Z-Y-X (yaw, then pitch, then roll) Euler angles in radians."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return np.array(
        [
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
            cr * cp * cy + sr * sp * sy,
        ]
    )


def quat_to_euler(q: np.ndarray) -> tuple[float, float, float]:
    """(roll, pitch, yaw) in radians, Z-Y-X convention, inverse of :func:`quat_from_euler`."""
    x, y, z, w = quat_normalize(q)
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return roll, pitch, yaw


def quat_from_yaw(yaw: float) -> np.ndarray:
    return np.array([0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)])


def yaw_of(q: np.ndarray) -> float:
    """Heading (rotation about world z) of a body quaternion, radians in (-pi, pi]."""
    return quat_to_euler(q)[2]


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
    return matrix_to_quat(R_NED_ENU @ quat_to_matrix(q) @ R_FRD_FLU.T)


def quat_ned_frd_to_enu_flu(q: np.ndarray) -> np.ndarray:
    return matrix_to_quat(R_NED_ENU.T @ quat_to_matrix(q) @ R_FRD_FLU)


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
