"""Depth camera error models: what an active stereo or a time-of-flight camera reports for the renderer's
exact depth.

Every function takes depth images ``(..., H, W)`` (float32 optical-frame z in metres, NaN where nothing is
hit; any leading batch axes, as the batched RL environment's ``(B, H, W)``) and returns new arrays; invalid
pixels read NaN, which is what ROS consumers of 32FC1 depth take as "no return" (REP 118). Randomness comes
from the ``numpy.random.Generator`` passed in, in a fixed order, so a seeded run is reproducible. The
presets and their sources are in :mod:`droneulator.config.camera_presets` and docs/sensors.md.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from droneulator.config.camera_presets import DepthModel

#: a depth step larger than this fraction of the nearer depth is an edge (flying pixels, thin structures)
EDGE_STEP = 0.1
#: thin-structure dropouts are decided per block of this many pixels a side, so a wire loses whole stretches
DROPOUT_BLOCK_PX = 8


def apply_depth_model(
    depth: np.ndarray,
    model: DepthModel,
    K: np.ndarray,
    rng: np.random.Generator,
    noise_scale: float | np.ndarray = 1.0,
    dropout_scale: float | np.ndarray = 1.0,
) -> np.ndarray:
    """``depth`` as the camera of ``model`` with intrinsics ``K`` measures it (a new float32 array).

    Structure-dependent invalidity (stereo occlusion, thin structures) and flying pixels are found on the
    exact depth, then noise is added and pixels out of range are invalidated. ``noise_scale`` multiplies
    the preset's noise (the stereo subpixel error, the ToF noise std) and ``dropout_scale`` its thin
    structure dropout and flying pixel probabilities (at most 1): one number, or one per image of a
    ``(B, H, W)`` batch (domain randomisation draws them per episode)."""
    z = np.asarray(depth, dtype=np.float32)
    if model.kind == "ideal":
        return z.copy()
    per_image = z.shape[:-2] + (1, 1)
    noise = np.broadcast_to(np.asarray(noise_scale, dtype=np.float32), z.shape[:-2]).reshape(per_image)
    drop = np.broadcast_to(np.asarray(dropout_scale, dtype=np.float32), z.shape[:-2]).reshape(per_image)
    fx = float(K[0, 0])
    invalid = ~np.isfinite(z)
    if model.occlusion:
        invalid |= stereo_occluded(z, fx * model.baseline_m)
    if model.thin_px > 0 and model.thin_dropout > 0:
        thin = thin_structures(z, model.thin_px)
        invalid |= thin & (_block_uniform(z.shape, rng) < np.minimum(model.thin_dropout * drop, 1.0))
    flying = np.minimum(model.flying_prob * drop, 1.0)
    out = flying_pixels(z, flying, rng) if model.flying_prob > 0 else z.copy()
    if model.kind == "stereo":
        fb = fx * model.baseline_m
        with np.errstate(divide="ignore", invalid="ignore"):
            disparity = fb / out
            error = (model.subpixel * noise) * correlated_normal(z.shape, model.noise_window_px, rng)
            noisy = disparity + error
            out = np.where(noisy > 0, fb / noisy, np.nan).astype(np.float32)
        min_range = fb / model.disparities
    elif model.kind == "tof":
        sigma = (model.noise_floor_m + model.noise_slope * out) * noise
        out = out + sigma * correlated_normal(z.shape, model.noise_window_px, rng)
        min_range = model.min_range_m
        invalid |= low_return(z, K, model.max_range_m)
    else:
        raise ValueError(f"unknown depth model kind {model.kind!r}")
    with np.errstate(invalid="ignore"):
        invalid |= (z > model.max_range_m) | (z < min_range)
    out[invalid] = np.nan
    return out


def correlated_normal(shape: tuple[int, ...], window_px: float, rng: np.random.Generator) -> np.ndarray:
    """Unit-variance Gaussian noise over the last two axes, smoothed by a Gaussian of std ``window_px``
    pixels (white for 0): stereo matching's window makes neighbouring errors alike."""
    noise = rng.standard_normal(shape, dtype=np.float32)
    if window_px <= 0:
        return noise
    radius = max(1, math.ceil(3.0 * window_px))
    x = np.arange(-radius, radius + 1, dtype=np.float64)
    g = np.exp(-0.5 * (x / window_px) ** 2)
    g /= g.sum()
    for axis in (-1, -2):
        noise = ndimage.correlate1d(noise, g.astype(np.float32), axis=axis, mode="reflect")
    # each pass scales the variance by sum(g^2): undo both
    return noise / np.float32(np.sum(g * g))


def stereo_occluded(depth: np.ndarray, fb_px_m: float) -> np.ndarray:
    """Pixels of the left (reference) imager that the right imager, ``B`` to its right, cannot see:
    ``fb_px_m`` is f (px) times B (m). A pixel at column u with disparity d lands at u - d in the right
    image; it is hidden when a pixel further right lands at or left of it (a nearer surface covers it),
    or when it lands outside the right image. This is the band of width f B (1/z_near - 1/z_far) left of
    a near object's left edge, and the strip f B / z wide along the image's left border."""
    with np.errstate(divide="ignore", invalid="ignore"):
        disparity = np.where(np.isfinite(depth), fb_px_m / depth, 0.0)
    u = np.arange(depth.shape[-1], dtype=np.float64)
    x_right = u - disparity
    # the smallest right-image column of any pixel strictly to the right
    rightmost = np.minimum.accumulate(x_right[..., ::-1], axis=-1)[..., ::-1]
    beyond = np.full_like(x_right, np.inf)
    beyond[..., :-1] = rightmost[..., 1:]
    return (beyond < x_right - 1e-3) | (x_right < -0.5)


def _nearness(depth: np.ndarray) -> np.ndarray:
    """1 / z, 0 where there is no return (infinitely far)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(np.isfinite(depth), 1.0 / depth, 0.0).astype(np.float32)


def _window(depth: np.ndarray, k: int) -> tuple[int, ...]:
    return (1,) * (depth.ndim - 2) + (k, k)


def thin_structures(depth: np.ndarray, width_px: int) -> np.ndarray:
    """Pixels of near structures narrower than ``width_px`` pixels (wires, stems, leaf edges): what a grey
    opening of the nearness 1/z with a ``width_px`` square removes, when it stands out by more than
    :data:`EDGE_STEP` of its depth."""
    n = _nearness(depth)
    size = _window(depth, width_px + 1)
    opened = ndimage.maximum_filter(ndimage.minimum_filter(n, size=size), size=size)
    return opened < n * (1.0 - EDGE_STEP)


def _block_uniform(shape: tuple[int, ...], rng: np.random.Generator) -> np.ndarray:
    """Uniform numbers constant over :data:`DROPOUT_BLOCK_PX`-pixel blocks of the last two axes."""
    h, w = shape[-2:]
    b = DROPOUT_BLOCK_PX
    coarse = rng.random((*shape[:-2], -(-h // b), -(-w // b)), dtype=np.float32)
    return np.repeat(np.repeat(coarse, b, axis=-2), b, axis=-1)[..., :h, :w]


def flying_pixels(
    depth: np.ndarray, probability: float | np.ndarray, rng: np.random.Generator
) -> np.ndarray:
    """A copy of ``depth`` in which each pixel at a depth edge (its 3x3 neighbourhood spans more than
    :data:`EDGE_STEP` of its nearest depth) reads, with ``probability``, a random mix of the nearest and
    farthest depth around it: a stereo window or a ToF pixel straddling the edge sees both surfaces."""
    finite = np.isfinite(depth)
    size = _window(depth, 3)
    near = ndimage.minimum_filter(np.where(finite, depth, np.inf), size=size)
    far = ndimage.maximum_filter(np.where(finite, depth, -np.inf), size=size)
    with np.errstate(invalid="ignore"):
        edge = finite & (far - near > EDGE_STEP * near)
        mix = rng.random(depth.shape, dtype=np.float32)
        chosen = edge & (rng.random(depth.shape, dtype=np.float32) < probability)
        return np.where(chosen, near + mix * (far - near), depth).astype(np.float32)


def low_return(depth: np.ndarray, K: np.ndarray, max_range_m: float) -> np.ndarray:
    """Pixels whose time-of-flight return is too weak: the return falls as cos(incidence) / z^2, and a
    surface facing the camera is lost beyond ``max_range_m``, so a pixel is lost beyond
    ``max_range_m * sqrt(cos(incidence))``. The incidence comes from the depth image's own normals (the
    cross product of the back-projected points' image-space derivatives)."""
    h, w = depth.shape[-2:]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    x = ((np.arange(w, dtype=np.float32) - cx) / fx)[None, :]
    y = ((np.arange(h, dtype=np.float32) - cy) / fy)[:, None]
    z = depth.astype(np.float32)
    px, py = z * x, z * y
    ux, uy, uz = (np.gradient(c, axis=-1) for c in (px, py, z))
    vx, vy, vz = (np.gradient(c, axis=-2) for c in (px, py, z))
    nx, ny, nz = uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx
    with np.errstate(divide="ignore", invalid="ignore"):
        dot = np.abs(nx * px + ny * py + nz * z)
        norms = np.sqrt((nx * nx + ny * ny + nz * nz) * (px * px + py * py + z * z))
        cos = dot / norms
        cos = np.where(np.isfinite(cos), cos, 1.0)
        return depth > max_range_m * np.sqrt(cos)
