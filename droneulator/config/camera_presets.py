"""The camera model presets ``render.cameras[].depth_model`` and ``rgb_noise`` name: one table each, read by
the config's checks, the runtime's cameras and the batched RL environment alike
(:mod:`droneulator.sensors.camera_models`). Sources and derivations are in docs/sensors.md.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class DepthModel:
    """A depth camera's error model.

    ``kind``: "ideal" (exact depth), "stereo" (active stereo: noise in disparity, so depth noise grows with
    z^2) or "tof" (time of flight: noise linear in depth). Stereo: ``baseline_m``, ``subpixel`` (RMS
    disparity error, px) and ``disparities`` (search range: the nearest valid depth is f B / disparities);
    ToF: ``noise_floor_m + noise_slope * z`` is the noise std and ``min_range_m`` the nearest valid depth.
    ``max_range_m``: the farthest return (for ToF, of a surface facing the camera: the return falls with
    cos(incidence) / z^2). ``noise_window_px``: std (px) of the Gaussian the noise is smoothed with, as
    stereo matching's window correlates neighbours (0: white, per pixel). ``flying_prob``: chance that a
    pixel at a depth edge reads a mix of the two sides; ``thin_px`` / ``thin_dropout``: near structures
    at most this many pixels wide go invalid with this probability; ``occlusion``: invalidate what the
    second imager cannot see (the band left of a near object's left edge).
    """

    kind: str
    max_range_m: float = float("inf")
    baseline_m: float = 0.0
    subpixel: float = 0.0
    disparities: int = 0
    noise_floor_m: float = 0.0
    noise_slope: float = 0.0
    min_range_m: float = 0.0
    noise_window_px: float = 0.0
    flying_prob: float = 0.0
    thin_px: int = 0
    thin_dropout: float = 0.0
    occlusion: bool = False


#: ``CameraConfig.depth_model`` choices. d435: Intel RealSense D435 (D400 series datasheet: 50 mm baseline,
#: max range approx. 10 m; Intel's "Tuning depth cameras for best performance": depth RMS error = z^2 *
#: subpixel / (f_px * baseline), subpixel approx. 0.08 px on a well-textured target, MinZ = f_px * baseline
#: / 126 for the D4's 126-disparity search). tof: an Azure Kinect-class AMCW time-of-flight camera (Azure
#: Kinect DK hardware spec: random error std <= 17 mm, NFOV 2x2-binned range 0.5-5.46 m); the linear noise
#: law 1.5 mm + 0.15 % of z is approximate, chosen within that bound.
DEPTH_PRESETS: dict[str, DepthModel] = {
    "ideal": DepthModel("ideal"),
    "d435": DepthModel(
        "stereo",
        max_range_m=10.0,
        baseline_m=0.050,
        subpixel=0.08,
        disparities=126,
        noise_window_px=1.0,
        flying_prob=0.3,
        thin_px=4,
        thin_dropout=0.7,
        occlusion=True,
    ),
    "tof": DepthModel(
        "tof",
        max_range_m=5.46,
        min_range_m=0.5,
        noise_floor_m=0.0015,
        noise_slope=0.0015,
        flying_prob=0.6,
        thin_px=2,
        thin_dropout=0.3,
    ),
}


@dataclass(frozen=True)
class RgbSensor:
    """An image sensor's noise: ``full_well_e`` (electrons at 255 at unit gain; inf: no shot noise),
    ``read_noise_e`` (Gaussian, electrons) and ``max_gain`` (the most gain auto-exposure may add)."""

    full_well_e: float = float("inf")
    read_noise_e: float = 0.0
    max_gain: float = 16.0

    @property
    def ideal(self) -> bool:
        return self.full_well_e == float("inf") and self.read_noise_e == 0.0


#: ``CameraConfig.rgb_noise`` choices (EMVA 1288 figures, approx.): machine_vision, a 5.86 um global
#: shutter pixel (Sony IMX174 class: about 30 ke- full well, about 7 e- read noise, up to 24 dB gain);
#: small_pixel, a 1.5-2 um rolling-shutter pixel of a compact drone camera (about 6 ke-, 2.5 e-, 24 dB).
RGB_PRESETS: dict[str, RgbSensor] = {
    "ideal": RgbSensor(),
    "machine_vision": RgbSensor(full_well_e=30000.0, read_noise_e=7.0, max_gain=16.0),
    "small_pixel": RgbSensor(full_well_e=6000.0, read_noise_e=2.5, max_gain=16.0),
}

#: the exposure the rendered image stands for (s): a frame exposed ``t`` s is ``t / REFERENCE_EXPOSURE_S``
#: times as bright (before auto-exposure or clipping)
REFERENCE_EXPOSURE_S = 0.002
#: auto-exposure aims the frame's mean at this fraction of full scale
AE_TARGET = 0.45
#: auto-exposure never exposes shorter than this (s)
MIN_EXPOSURE_S = 2e-5


def radial_invertible(distortion: tuple[float, ...], corner_radius: float) -> bool:
    """Whether plumb_bob ``distortion``'s radial part maps ideal radii one-to-one onto every distorted radius
    up to ``corner_radius`` (normalised image coordinates): the distorted image can then be drawn from the
    ideal one. Tangential terms are small beside it and left out of the check."""
    k1, k2, _, _, k3 = distortion
    r = np.linspace(0.0, 4.0 * corner_radius, 4001)
    r2 = r * r
    distorted = r * (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3)))
    slope = 1.0 + r2 * (3.0 * k1 + r2 * (5.0 * k2 + r2 * 7.0 * k3))
    reach = np.flatnonzero(distorted >= corner_radius)
    return bool(len(reach) and np.all(slope[: reach[0] + 1] > 0.0))
