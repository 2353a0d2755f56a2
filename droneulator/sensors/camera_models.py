"""A camera's realism models, applied where frames are produced so every consumer sees the same images.

:class:`CameraModel` turns a renderer frame (ideal pinhole RGB, exact depth, segmentation) into what the
configured camera delivers (:class:`~droneulator.config.CameraConfig`'s ``depth_model``, ``rgb_noise``,
``distortion``, ``exposure_s``, ``auto_exposure``, ``motion_blur``):

1. colour: auto-exposure picks exposure and gain; motion blur over the exposure along the image motion of
   the vehicle's velocity and rotation (:mod:`.rgb_models`);
2. depth: the depth camera's errors (:mod:`.depth_models`);
3. lens distortion of all three images alike, so they stay registered (:mod:`.lens`);
4. colour: the sensor's shot and read noise at that exposure and gain, and 8-bit quantisation.

:func:`fleet_camera_models` builds the models of every camera of a config that is not ideal; an all-ideal
rig gets none, and its frames pass untouched (no copy, no work). The in-process world
(:meth:`droneulator.world.world.World.render`), the runtime's render server and the RL environments call
it alike, each camera's noise seeded from the config seed, the vehicle and the camera (:func:`camera_rng`).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from droneulator.config import CameraConfig, SimConfig
from droneulator.config.camera_presets import DEPTH_PRESETS, REFERENCE_EXPOSURE_S, RGB_PRESETS
from droneulator.frames import T_link_optical, camera_mount
from droneulator.scenes.base import SemanticClass
from droneulator.sensors.camera import intrinsics
from droneulator.sensors.depth_models import apply_depth_model
from droneulator.sensors.lens import distort, distortion_maps, is_distorted
from droneulator.sensors.rgb_models import auto_exposure, expose, image_motion, motion_blur

#: mixed into every camera's seed so its noise never repeats another sensor's stream
_CAMERA_STREAM = 0x63616D


def is_ideal(cam: CameraConfig) -> bool:
    """Whether ``cam`` delivers the renderer's images as they are."""
    return (
        cam.depth_model == "ideal"
        and cam.rgb_noise == "ideal"
        and not is_distorted(cam.distortion)
        and cam.exposure_s == REFERENCE_EXPOSURE_S
        and not cam.auto_exposure
        and not cam.motion_blur
    )


def camera_rng(seed: int, vehicle_index: int = 0, camera_index: int = 0) -> np.random.Generator:
    """The noise generator of a world's ``vehicle_index``-th vehicle's ``camera_index``-th camera."""
    return np.random.default_rng([_CAMERA_STREAM, int(seed), vehicle_index, camera_index])


class CameraModel:
    """One camera's realism models (see the module docstring); ``rng`` draws its noise."""

    def __init__(self, cfg: CameraConfig, rng: np.random.Generator) -> None:
        self.cfg = cfg
        self.rng = rng
        self.K = intrinsics(cfg)
        self.depth_model = DEPTH_PRESETS[cfg.depth_model]
        self.sensor = RGB_PRESETS[cfg.rgb_noise]
        #: the plumb_bob coefficients camera_info carries (zeros: an ideal pinhole)
        self.D = np.asarray(cfg.distortion, dtype=np.float64)
        self._maps = None
        if self.distorted:
            self._maps = distortion_maps(self.K, cfg.distortion, cfg.width, cfg.height)
        T_body_optical = camera_mount(np.asarray(cfg.position, dtype=float), cfg.rpy) @ T_link_optical()
        self._R_body_optical = T_body_optical[:3, :3]
        self._mount = T_body_optical[:3, 3]
        self._exposes = not (
            self.sensor.ideal and cfg.exposure_s == REFERENCE_EXPOSURE_S and not cfg.auto_exposure
        )

    @property
    def distorted(self) -> bool:
        return is_distorted(self.cfg.distortion)

    @property
    def ideal(self) -> bool:
        return is_ideal(self.cfg)

    def apply(self, frame: Any, velocity: Any = None, angular_velocity: Any = None) -> Any:
        """A new :class:`~droneulator.render.CameraFrame` with this camera's images of ``frame`` (whose
        arrays are left as they are). ``velocity`` (m/s, world) and ``angular_velocity`` (rad/s, body
        FLU) are the vehicle's, for the motion blur (none without them)."""
        rgb, depth, seg = frame.rgb, frame.depth, frame.seg
        cfg = self.cfg
        exposure, gain = cfg.exposure_s, 1.0
        radiance = None
        if rgb is not None and (self._exposes or cfg.motion_blur):
            radiance = rgb.astype(np.float32) * np.float32(1.0 / 255.0)
            if cfg.auto_exposure:
                exposure, gain = auto_exposure(float(radiance.mean()), cfg.exposure_s, self.sensor.max_gain)
            if cfg.motion_blur and velocity is not None and angular_velocity is not None:
                v, w = self._optical_motion(frame.T_world_optical, velocity, angular_velocity)
                du, dv = image_motion(depth, self.K, v, w)
                radiance = motion_blur(radiance, du * np.float32(exposure), dv * np.float32(exposure))
        if self.depth_model.kind != "ideal":
            depth = self._depth(depth)
        if self._maps is not None:
            if radiance is not None:
                radiance = distort(radiance, self._maps)
            elif rgb is not None:
                rgb = distort(rgb, self._maps)
            depth = distort(depth, self._maps, nearest=True, fill=float("nan"))
            seg = distort(seg, self._maps, nearest=True, fill=int(SemanticClass.SKY))
        if radiance is not None:
            rgb = expose(radiance, exposure, gain, self.sensor, self.rng)
        D = self.D.copy() if self.distorted else None
        return dataclasses.replace(frame, rgb=rgb, depth=depth, seg=seg, D=D)

    def _depth(
        self, depth: np.ndarray, noise_scale: Any = None, dropout_scale: Any = None
    ) -> np.ndarray:
        cfg = self.cfg
        noise = cfg.depth_noise_scale if noise_scale is None else noise_scale
        dropout = cfg.depth_dropout_scale if dropout_scale is None else dropout_scale
        return apply_depth_model(depth, self.depth_model, self.K, self.rng, noise, dropout)

    def apply_depth(
        self, depth: np.ndarray, noise_scale: Any = None, dropout_scale: Any = None
    ) -> np.ndarray:
        """This camera's depth image(s) of exact ``depth`` ``(..., H, W)`` (the RL environments' batches):
        the depth model, then the lens distortion. ``noise_scale`` / ``dropout_scale`` (a number or one per
        image; None: the camera's ``depth_noise_scale`` / ``depth_dropout_scale``) scale the preset's
        noise and dropouts (:func:`~droneulator.sensors.depth_models.apply_depth_model`)."""
        out = self._depth(depth, noise_scale, dropout_scale)
        if self._maps is not None:
            flat = out.reshape(-1, *out.shape[-2:])
            out = np.stack([distort(d, self._maps, nearest=True, fill=float("nan")) for d in flat])
            out = out.reshape(depth.shape)
        return out

    def _optical_motion(
        self, T_world_optical: np.ndarray, velocity: Any, angular_velocity: Any
    ) -> tuple[np.ndarray, np.ndarray]:
        """The camera's linear and angular velocity in its optical frame, from the vehicle's."""
        R_wo = np.asarray(T_world_optical, dtype=float)[:3, :3]
        R_wb = R_wo @ self._R_body_optical.T
        w_body = np.asarray(angular_velocity, dtype=float)
        v_world = np.asarray(velocity, dtype=float) + R_wb @ np.cross(w_body, self._mount)
        return R_wo.T @ v_world, self._R_body_optical.T @ w_body


def fleet_camera_models(config: SimConfig, seed: int | None = None) -> dict[str, dict[str, CameraModel]]:
    """vehicle -> camera -> model, for every camera of ``config`` that is not ideal (empty when none is);
    ``seed`` (default: the config's) seeds their noise (:func:`camera_rng`)."""
    seed = config.seed if seed is None else seed
    models: dict[str, dict[str, CameraModel]] = {}
    for i, (vehicle, cams) in enumerate(config.camera_rigs().items()):
        for j, cam in enumerate(cams):
            if not is_ideal(cam):
                models.setdefault(vehicle, {})[cam.name] = CameraModel(cam, camera_rng(seed, i, j))
    return models
