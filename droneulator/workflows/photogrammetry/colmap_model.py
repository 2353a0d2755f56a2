"""COLMAP text models of known camera poses, and the conventions that join them to ROS.

Two conventions differ between ``camera_info`` / OpenCV and COLMAP:

* **Pose.** COLMAP's camera frame is the ROS optical frame (x right, y down, z forward), and
  ``images.txt`` stores the *world-to-camera* transform as ``QW QX QY QZ TX TY TZ``. The conversion
  lives in :func:`droneulator.frames.colmap_cam_from_world`.
* **Pixels.** OpenCV/ROS put the centre of the top-left pixel at (0, 0); COLMAP puts the top-left
  *corner* at (0, 0), so that pixel's centre is at (0.5, 0.5). The same image point therefore has
  COLMAP coordinates ``u + 0.5, v + 0.5`` and a ``camera_info`` K becomes a COLMAP PINHOLE camera with
  ``fx, fy`` unchanged and ``cx + 0.5, cy + 0.5`` (a symmetric frustum gets exactly ``W/2, H/2``).
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from droneulator.frames import colmap_cam_from_world, colmap_to_T_world_optical, transform_points

#: COLMAP pixel coordinates minus OpenCV/ROS pixel coordinates of the same image point
COLMAP_PIXEL_OFFSET = 0.5


# --------------------------------------------------------------------------- pixel convention
def colmap_pinhole_params(K: np.ndarray) -> np.ndarray:
    """COLMAP ``PINHOLE`` parameters ``[fx, fy, cx, cy]`` of an OpenCV/ROS intrinsic matrix."""
    K = np.asarray(K, dtype=float).reshape(3, 3)
    if abs(K[0, 1]) > 1e-12:
        raise ValueError("PINHOLE has no skew term: K[0, 1] must be 0")
    return np.array([K[0, 0], K[1, 1], K[0, 2] + COLMAP_PIXEL_OFFSET, K[1, 2] + COLMAP_PIXEL_OFFSET])


def K_from_colmap_pinhole(params: Sequence[float]) -> np.ndarray:
    """OpenCV/ROS K of COLMAP ``PINHOLE`` parameters (the inverse of :func:`colmap_pinhole_params`)."""
    fx, fy, cx, cy = (float(p) for p in params)
    return np.array(
        [[fx, 0.0, cx - COLMAP_PIXEL_OFFSET], [0.0, fy, cy - COLMAP_PIXEL_OFFSET], [0.0, 0.0, 1.0]]
    )


def opencv_to_colmap_pixels(uv: np.ndarray) -> np.ndarray:
    return np.asarray(uv, dtype=float) + COLMAP_PIXEL_OFFSET


def colmap_to_opencv_pixels(uv: np.ndarray) -> np.ndarray:
    return np.asarray(uv, dtype=float) - COLMAP_PIXEL_OFFSET


def project_opencv(K: np.ndarray, T_world_optical: np.ndarray, points_world: np.ndarray) -> np.ndarray:
    """OpenCV pixel coordinates (n, 2) of world points (n, 3) seen by a camera posed in the world.

    Points behind the camera come out as NaN.
    """
    p = transform_points(np.linalg.inv(T_world_optical), np.atleast_2d(points_world))
    uvw = p @ np.asarray(K, dtype=float).T
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = uvw[:, :2] / uvw[:, 2:3]
    uv[p[:, 2] <= 0] = np.nan
    return uv


# --------------------------------------------------------------------------- the model
@dataclass
class PinholeCamera:
    """One COLMAP camera: ``params`` are ``fx, fy, cx, cy`` in COLMAP's pixel convention."""

    camera_id: int
    width: int
    height: int
    params: np.ndarray

    @property
    def K(self) -> np.ndarray:
        """The same camera in the OpenCV/ROS convention of ``camera_info``."""
        return K_from_colmap_pinhole(self.params)


@dataclass
class ImagePose:
    """One COLMAP image: world-to-camera ``qvec`` (w, x, y, z) and ``tvec`` of ``name``."""

    image_id: int
    name: str
    camera_id: int
    qvec: np.ndarray
    tvec: np.ndarray

    @classmethod
    def from_optical(cls, image_id: int, name: str, camera_id: int, T_world_optical: np.ndarray) -> ImagePose:
        qvec, tvec = colmap_cam_from_world(T_world_optical)
        return cls(image_id, name, camera_id, qvec, tvec)

    @property
    def T_world_optical(self) -> np.ndarray:
        return colmap_to_T_world_optical(self.qvec, self.tvec)

    @property
    def center(self) -> np.ndarray:
        """Projection centre in the world (what a position prior constrains)."""
        return self.T_world_optical[:3, 3]


@dataclass
class KnownModel:
    """A COLMAP model of known poses and intrinsics without 3D points (``sparse_known``)."""

    cameras: dict[int, PinholeCamera]
    images: dict[int, ImagePose]

    @classmethod
    def from_views(
        cls, K: np.ndarray, width: int, height: int, views: Iterable[tuple[int, str, np.ndarray]]
    ) -> KnownModel:
        """One shared camera (``camera_info`` K) and ``(image_id, name, T_world_optical)`` views."""
        cam = PinholeCamera(1, int(width), int(height), colmap_pinhole_params(K))
        images = {i: ImagePose.from_optical(i, name, 1, T) for i, name, T in views}
        return cls({1: cam}, dict(sorted(images.items())))


def _fmt(values: Iterable[float]) -> str:
    return " ".join(repr(float(v)) for v in values)


def cameras_txt(model: KnownModel) -> str:
    lines = [
        "# Camera list with one line of data per camera:",
        "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
        f"# Number of cameras: {len(model.cameras)}",
    ]
    for c in model.cameras.values():
        lines.append(f"{c.camera_id} PINHOLE {c.width} {c.height} {_fmt(c.params)}")
    return "\n".join(lines) + "\n"


def images_txt(model: KnownModel) -> str:
    lines = [
        "# Image list with two lines of data per image:",
        "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
        "#   POINTS2D[] as (X, Y, POINT3D_ID)",
        f"# Number of images: {len(model.images)}, mean observations per image: 0",
    ]
    for im in model.images.values():
        if any(ch.isspace() for ch in im.name):
            raise ValueError(f"COLMAP text models cannot hold image names with spaces: {im.name!r}")
        lines.append(f"{im.image_id} {_fmt(im.qvec)} {_fmt(im.tvec)} {im.camera_id} {im.name}")
        lines.append("")
    return "\n".join(lines) + "\n"


POINTS3D_TXT = (
    "# 3D point list with one line of data per point:\n"
    "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n"
    "# Number of points: 0, mean track length: 0\n"
)


def atomic_write(path: Path, data: bytes | str) -> None:
    """Write ``path`` through a temporary file and a rename, so readers never see it half written."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data.encode() if isinstance(data, str) else data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_text_model(path: Path, model: KnownModel) -> None:
    """Write ``cameras.txt``, ``images.txt`` and an empty ``points3D.txt``, each replaced atomically."""
    path = Path(path)
    atomic_write(path / "cameras.txt", cameras_txt(model))
    atomic_write(path / "images.txt", images_txt(model))
    atomic_write(path / "points3D.txt", POINTS3D_TXT)


def _data_lines(path: Path) -> list[str]:
    return [ln for ln in path.read_text().splitlines() if not ln.startswith("#")]


def read_text_model(path: Path) -> KnownModel:
    """Read the cameras and image poses of a COLMAP text model (2D points and 3D points are ignored)."""
    path = Path(path)
    cameras: dict[int, PinholeCamera] = {}
    for line in _data_lines(path / "cameras.txt"):
        if not line.strip():
            continue
        f = line.split()
        if f[1] != "PINHOLE":
            raise ValueError(f"only PINHOLE cameras are supported, got {f[1]}")
        cameras[int(f[0])] = PinholeCamera(int(f[0]), int(f[2]), int(f[3]), np.array(f[4:8], dtype=float))
    images: dict[int, ImagePose] = {}
    lines = _data_lines(path / "images.txt")
    for line in lines[0::2]:  # every image line is followed by its (possibly empty) POINTS2D line
        f = line.split()
        if not f:
            continue
        images[int(f[0])] = ImagePose(
            int(f[0]), f[9], int(f[8]), np.array(f[1:5], dtype=float), np.array(f[5:8], dtype=float)
        )
    return KnownModel(cameras, images)
