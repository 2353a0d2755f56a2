"""Pinhole camera model shared by the renderer, the bridge and the workflows.

Pixel convention (OpenCV / ROS ``camera_info``): pixel centres sit at integer coordinates, row 0
is the top of the image, u grows right and v grows down. A camera's symmetric frustum then has its
principal point at ``((w - 1) / 2, (h - 1) / 2)`` and the OpenGL projection below reproduces K
exactly.
"""

from __future__ import annotations

import math

import numpy as np

from droneulator.config import CameraConfig
from droneulator.frames import camera_mount
from droneulator.sensors.registry import register


def intrinsics(cam: CameraConfig) -> np.ndarray:
    """3x3 intrinsic matrix K matching the rendered images exactly (square pixels)."""
    fx = (cam.width / 2.0) / math.tan(math.radians(cam.hfov_deg) / 2.0)
    return np.array([[fx, 0.0, (cam.width - 1) / 2.0], [0.0, fx, (cam.height - 1) / 2.0], [0.0, 0.0, 1.0]])


def vfov_deg(cam: CameraConfig) -> float:
    fy = intrinsics(cam)[1, 1]
    return math.degrees(2.0 * math.atan((cam.height / 2.0) / fy))


def gl_projection(cam: CameraConfig) -> np.ndarray:
    """OpenGL projection (GL camera -> clip space) whose viewport mapping equals K.

    With NDC x in [-1, 1] spanning the pixel edges 0..w, pixel centre u maps to
    x_ndc = (2u + 1)/w - 1; substituting u = fx X/Z + cx gives the matrix below.
    """
    K = intrinsics(cam)
    w, h, n, f = cam.width, cam.height, cam.near, cam.far
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    P = np.zeros((4, 4))
    P[0, 0] = 2.0 * fx / w
    P[0, 2] = 1.0 - (2.0 * cx + 1.0) / w  # zero for the symmetric frustum
    P[1, 1] = 2.0 * fy / h
    P[1, 2] = (2.0 * cy + 1.0) / h - 1.0
    P[2, 2] = -(f + n) / (f - n)
    P[2, 3] = -2.0 * f * n / (f - n)
    P[3, 2] = -1.0
    return P


def project(K: np.ndarray, p_optical: np.ndarray) -> np.ndarray:
    """Pixel coordinates (..., 2) of points (..., 3) in the optical frame (z forward)."""
    p = np.asarray(p_optical, dtype=float)
    uvw = p @ K.T
    return uvw[..., :2] / uvw[..., 2:3]


@register("camera")
class Camera:
    """A body-mounted pinhole camera (RGB, depth and segmentation images are drawn by
    :class:`droneulator.render.Renderer`): its intrinsics and its mount on the body."""

    def __init__(self, cfg: CameraConfig) -> None:
        self.cfg = cfg
        self.K = intrinsics(cfg)
        #: camera link (FLU axes) in the body frame
        self.T_body_link = camera_mount(np.asarray(cfg.position, dtype=float), cfg.rpy)

    def project(self, p_optical: np.ndarray) -> np.ndarray:
        """Pixel coordinates (..., 2) of points (..., 3) in this camera's optical frame."""
        return project(self.K, p_optical)
