"""Colour camera image formation: exposure and gain (with a simple auto-exposure), motion blur over the
exposure, and sensor noise (photon shot noise and read noise).

The rendered image is taken as the scene's radiance as a camera exposed
:data:`~droneulator.config.camera_presets.REFERENCE_EXPOSURE_S` at unit gain records it, on a linear scale
(value / 255 is the fraction of full scale): exposing ``t`` seconds collects ``t / REFERENCE_EXPOSURE_S``
times as much light. Functions take and return float32 images in [0, 1] (``(H, W, 3)``) but for
:func:`expose`, which gives the 8-bit image; randomness comes from the ``numpy.random.Generator`` passed in.
"""

from __future__ import annotations

import math

import numpy as np

from droneulator.config.camera_presets import AE_TARGET, MIN_EXPOSURE_S, REFERENCE_EXPOSURE_S, RgbSensor
from droneulator.sensors.lens import remap

#: at most this many samples along the image motion average into a blurred pixel
MAX_BLUR_SAMPLES = 16


def auto_exposure(mean_radiance: float, max_exposure_s: float, max_gain: float) -> tuple[float, float]:
    """(exposure s, gain) that bring an image of mean ``mean_radiance`` (at the reference exposure) to
    :data:`AE_TARGET`: the exposure first, up to ``max_exposure_s``, then analogue gain up to ``max_gain``
    (gain amplifies noise, so a camera's auto-exposure raises it last). One-shot, as a converged AE loop."""
    wanted = AE_TARGET / max(float(mean_radiance), 1e-6)
    exposure = min(max(REFERENCE_EXPOSURE_S * wanted, MIN_EXPOSURE_S), max_exposure_s)
    gain = min(max(wanted * REFERENCE_EXPOSURE_S / exposure, 1.0), max_gain)
    return exposure, gain


def expose(
    radiance: np.ndarray, exposure_s: float, gain: float, sensor: RgbSensor, rng: np.random.Generator
) -> np.ndarray:
    """The 8-bit image a sensor records of ``radiance`` over ``exposure_s`` at ``gain``.

    Collected electrons: ``radiance * exposure_s / REFERENCE_EXPOSURE_S * full_well``, Poisson (shot noise,
    drawn as its Gaussian limit, variance equal to the mean) plus Gaussian read noise, clipped at the full
    well; then gain, 8-bit quantisation and clipping at 255."""
    signal = radiance * np.float32(exposure_s / REFERENCE_EXPOSURE_S)
    if sensor.ideal:
        out = signal * np.float32(gain)
    else:
        fw = np.float32(sensor.full_well_e)
        electrons = np.minimum(signal, 1.0) * fw
        noise = rng.standard_normal(electrons.shape, dtype=np.float32)
        electrons += noise * np.sqrt(electrons + np.float32(sensor.read_noise_e**2))
        np.clip(electrons, 0.0, fw, out=electrons)
        out = electrons * np.float32(gain / sensor.full_well_e)
    return np.clip(np.rint(out * 255.0), 0, 255).astype(np.uint8)


def image_motion(
    depth: np.ndarray, K: np.ndarray, velocity: np.ndarray, angular_velocity: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel image motion (du/dt, dv/dt in px/s) of a static scene seen by a camera moving at
    ``velocity`` (m/s) and turning at ``angular_velocity`` (rad/s), both in its optical frame (x right,
    y down, z forward); ``depth`` is the optical z (NaN: infinitely far, so only rotation moves it).

    The motion field of a point at normalised (x, y) and depth Z (Longuet-Higgins and Prazdny, 1980):
    dx/dt = (-Tx + x Tz) / Z + wx x y - wy (1 + x^2) + wz y, dy/dt = (-Ty + y Tz) / Z + wx (1 + y^2) -
    wy x y - wz x."""
    h, w = depth.shape
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    x = ((np.arange(w, dtype=np.float32) - cx) / fx)[None, :]
    y = ((np.arange(h, dtype=np.float32) - cy) / fy)[:, None]
    inv_z = np.where(np.isfinite(depth), 1.0 / np.where(np.isfinite(depth), depth, 1.0), 0.0)
    tx, ty, tz = (float(v) for v in velocity)
    wx, wy, wz = (float(v) for v in angular_velocity)
    dx = (x * tz - tx) * inv_z + wx * x * y - wy * (1.0 + x * x) + wz * y
    dy = (y * tz - ty) * inv_z + wx * (1.0 + y * y) - wy * x * y - wz * x
    return (fx * dx).astype(np.float32), (fy * dy).astype(np.float32)


def motion_blur(image: np.ndarray, du: np.ndarray, dv: np.ndarray) -> np.ndarray:
    """``image`` averaged along each pixel's displacement ``(du, dv)`` (px, over the exposure), centred on
    the exposure's middle: samples one pixel apart (at most :data:`MAX_BLUR_SAMPLES`), each drawn bilinearly
    (:func:`~droneulator.sensors.lens.remap`, the edge pixel beyond the border). A displacement under half
    a pixel everywhere leaves the image as it is."""
    reach = float(np.sqrt(np.max(du * du + dv * dv)))
    if reach < 0.5:
        return image
    n = min(MAX_BLUR_SAMPLES, math.ceil(reach) + 1)
    h, w = image.shape[:2]
    u = np.arange(w, dtype=np.float32)[None, :]
    v = np.arange(h, dtype=np.float32)[:, None]
    acc = np.zeros(image.shape, dtype=np.float32)
    for s in np.linspace(-0.5, 0.5, n, dtype=np.float32):
        acc += remap(image, u + s * du, v + s * dv, replicate=True)
    return acc / np.float32(n)
