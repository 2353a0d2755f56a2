"""numba-compiled twins of the :mod:`droneulator.frames` conversions that compiled kernels need.

``@njit`` code cannot call SciPy or the NumPy helpers in :mod:`droneulator.frames`, so the few
conversions the dynamics and controller kernels use are written here once, scalar by scalar, in
the same conventions (quaternions ``[x, y, z, w]`` rotating body FLU vectors into the ENU world).
``tests/test_frames.py`` checks every twin against its NumPy counterpart on random inputs.
"""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True)
def quat_to_matrix_into(q: np.ndarray, R: np.ndarray) -> None:
    """Write the rotation matrix of quaternion ``[x, y, z, w]`` into ``R`` (3x3), normalising it first
    (as SciPy does); allocation free, for kernels that step many vehicles."""
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    x, y, z, w = q[0] / n, q[1] / n, q[2] / n, q[3] / n
    R[0, 0] = 1 - 2 * (y * y + z * z)
    R[0, 1] = 2 * (x * y - z * w)
    R[0, 2] = 2 * (x * z + y * w)
    R[1, 0] = 2 * (x * y + z * w)
    R[1, 1] = 1 - 2 * (x * x + z * z)
    R[1, 2] = 2 * (y * z - x * w)
    R[2, 0] = 2 * (x * z - y * w)
    R[2, 1] = 2 * (y * z + x * w)
    R[2, 2] = 1 - 2 * (x * x + y * y)


@numba.njit(cache=True)
def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of quaternion ``[x, y, z, w]``, normalising it first (as SciPy does)."""
    R = np.empty((3, 3))
    quat_to_matrix_into(q, R)
    return R


@numba.njit(cache=True)
def yaw_of(q: np.ndarray) -> float:
    """Heading (ZYX Euler yaw, radians in (-pi, pi]) of a unit quaternion ``[x, y, z, w]``."""
    x, y, z, w = q[0], q[1], q[2], q[3]
    return math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


@numba.njit(cache=True)
def set_quat_from_yaw(q: np.ndarray, yaw: float) -> None:
    """Write the level attitude with heading ``yaw`` into ``q`` (a view of a packed state, in place)."""
    q[0] = 0.0
    q[1] = 0.0
    q[2] = math.sin(yaw / 2)
    q[3] = math.cos(yaw / 2)


@numba.njit(cache=True)
def body_to_world(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """A body-frame vector expressed in the world frame: ``R(q) @ v``."""
    return quat_to_matrix(q) @ v


@numba.njit(cache=True)
def world_to_body(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """A world-frame vector expressed in the body frame: ``R(q)^T @ v``."""
    return quat_to_matrix(q).T @ v


@numba.njit(cache=True)
def enu_to_ned(v: np.ndarray) -> np.ndarray:
    """One ENU vector in NED (self-inverse)."""
    return np.array([v[1], v[0], -v[2]])


@numba.njit(cache=True)
def flu_to_frd(v: np.ndarray) -> np.ndarray:
    """One FLU body vector in FRD (self-inverse)."""
    return np.array([v[0], -v[1], -v[2]])
