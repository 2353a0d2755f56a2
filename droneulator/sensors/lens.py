"""Lens distortion: OpenCV's plumb_bob (Brown-Conrady) model, ``D = (k1, k2, p1, p2, k3)``, as ROS'
``camera_info`` carries it; and :func:`remap`, the image lookup the camera models draw through.

The renderer draws an ideal pinhole image; the distorted image is drawn from it by inverse mapping: each
distorted pixel looks up the ideal pixel its ray comes from (:func:`undistort_points`, the fixed-point
inversion OpenCV's ``undistortPoints`` iterates), through :func:`remap`. So ``cv2.undistort(distorted, K,
D)`` gives the ideal image back (up to resampling), and a ROS consumer that rectifies with the published
``camera_info`` sees the rendered geometry. Plain numpy and numba, so the base install (and the bundle)
needs no OpenCV; the tests judge both functions against OpenCV's.
"""

from __future__ import annotations

from collections.abc import Sequence

import numba
import numpy as np

#: the inversion stops when no point moves more than this (normalised coordinates), or after
#: ``_MAX_ITERATIONS`` (OpenCV's default 5 iterations leave sub-pixel errors at the corners of strongly
#: distorted images)
_TOLERANCE = 1e-10
_MAX_ITERATIONS = 100


def is_distorted(distortion: Sequence[float]) -> bool:
    return any(float(c) != 0.0 for c in distortion)


def undistort_points(uv: np.ndarray, K: np.ndarray, distortion: Sequence[float]) -> np.ndarray:
    """The ideal pixels ``(..., 2)`` whose rays the distorted pixels ``uv`` (``(..., 2)``) show: the
    plumb_bob model ``x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + tangential(x)`` inverted by its fixed point
    ``x = (x_d - tangential(x)) / radial(x)``, as OpenCV iterates it."""
    k1, k2, p1, p2, k3 = (float(c) for c in distortion)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    xd = (np.asarray(uv[..., 0], dtype=np.float64) - cx) / fx
    yd = (np.asarray(uv[..., 1], dtype=np.float64) - cy) / fy
    x, y = xd.copy(), yd.copy()
    for _ in range(_MAX_ITERATIONS):
        r2 = x * x + y * y
        radial = 1.0 + ((k3 * r2 + k2) * r2 + k1) * r2
        dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        nx, ny = (xd - dx) / radial, (yd - dy) / radial
        moved = max(float(np.max(np.abs(nx - x), initial=0.0)), float(np.max(np.abs(ny - y), initial=0.0)))
        x, y = nx, ny
        if moved < _TOLERANCE:
            break
    return np.stack([fx * x + cx, fy * y + cy], axis=-1)


def distortion_maps(K: np.ndarray, distortion: Sequence[float], width: int, height: int) -> np.ndarray:
    """``(height, width, 2)`` float32: for each pixel of the distorted image, the ideal image's pixel
    (u, v) that it shows."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    return undistort_points(np.stack([u, v], axis=-1), K, distortion).astype(np.float32)


def distort(image: np.ndarray, maps: np.ndarray, nearest: bool = False, fill: float = 0.0) -> np.ndarray:
    """``image`` (``(H, W)`` or ``(H, W, C)``) drawn through ``maps`` (:func:`distortion_maps`): bilinear,
    or ``nearest`` for depth and segmentation (a depth or a class is never blended across an edge);
    pixels whose ray falls outside the ideal image read ``fill`` (0 for colour, NaN for depth, SKY for
    segmentation)."""
    return remap(image, maps[..., 0], maps[..., 1], nearest=nearest, replicate=False, fill=fill)


def remap(
    image: np.ndarray,
    map_u: np.ndarray,
    map_v: np.ndarray,
    nearest: bool = False,
    replicate: bool = False,
    fill: float = 0.0,
) -> np.ndarray:
    """``out[i, j] = image(map_v[i, j], map_u[i, j])`` (``cv2.remap``'s contract): bilinear or ``nearest``;
    outside the image the nearest edge pixel (``replicate``) or ``fill``, which a bilinear sample blends
    with the pixels inside. Keeps ``image``'s dtype (integers rounded)."""
    src = np.ascontiguousarray(image)
    flat = src.reshape(src.shape[0], src.shape[1], -1)
    shape = np.broadcast_shapes(np.shape(map_u), np.shape(map_v))
    mu = np.ascontiguousarray(np.broadcast_to(map_u, shape), dtype=np.float32)
    mv = np.ascontiguousarray(np.broadcast_to(map_v, shape), dtype=np.float32)
    out = np.empty((*mu.shape, flat.shape[2]), dtype=src.dtype)
    _remap(flat, mu, mv, out, nearest, replicate, float(fill), np.issubdtype(src.dtype, np.integer))
    return out.reshape(*mu.shape, *src.shape[2:])


@numba.njit(cache=True, parallel=True)
def _remap(
    src: np.ndarray,
    mu: np.ndarray,
    mv: np.ndarray,
    out: np.ndarray,
    nearest: bool,
    replicate: bool,
    fill: float,
    integer: bool,
) -> None:
    h, w, c = src.shape
    for i in numba.prange(mu.shape[0]):
        for j in range(mu.shape[1]):
            u, v = mu[i, j], mv[i, j]
            if nearest:
                x, y = int(np.floor(u + 0.5)), int(np.floor(v + 0.5))
                inside = 0 <= x < w and 0 <= y < h
                if not inside and replicate:
                    x, y, inside = min(max(x, 0), w - 1), min(max(y, 0), h - 1), True
                for k in range(c):
                    out[i, j, k] = src[y, x, k] if inside else fill
                continue
            x0f, y0f = np.floor(u), np.floor(v)
            fx, fy = u - x0f, v - y0f
            x0, y0 = int(x0f), int(y0f)
            for k in range(c):
                acc = 0.0
                for dy in range(2):
                    wy = fy if dy else 1.0 - fy
                    yy = y0 + dy
                    for dx in range(2):
                        wx = fx if dx else 1.0 - fx
                        xx = x0 + dx
                        if 0 <= xx < w and 0 <= yy < h:
                            value = float(src[yy, xx, k])
                        elif replicate:
                            value = float(src[min(max(yy, 0), h - 1), min(max(xx, 0), w - 1), k])
                        else:
                            value = fill
                        acc += wx * wy * value
                out[i, j, k] = np.floor(acc + 0.5) if integer else acc
