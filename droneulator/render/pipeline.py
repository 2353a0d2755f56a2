"""The one camera pipeline: every picture the simulator takes goes through :class:`CameraPipeline`.

A picture is drawn (the OpenGL renderer, every vehicle's body in the other vehicles' cameras, one mesh per
airframe; or, for depth alone, the ray caster of :mod:`droneulator.render.raycast`, equal to the
renderer's depth to a millimetre) and then delivered as the configured camera delivers it (its realism
models, :mod:`droneulator.sensors.camera_models`: noise, blur, distortion, exposure, the depth presets).
The in-process world (:meth:`droneulator.world.World.render`), the runtime's render server and every
learning environment call this class and nothing else draws, so a camera looks the same wherever its
frames are used (``tests/test_structure.py`` checks that only this module calls the renderer's draw).

Two ways in:

* :meth:`CameraPipeline.frames`: every camera of every vehicle's rig at one instant (RGB, depth,
  segmentation), each through its own model, as a consumer of the camera topics sees them;
* :meth:`CameraPipeline.depth` and :meth:`CameraPipeline.centre_rows`: the first camera's depth at many
  poses of one vehicle (the learning environments' batches), each pose through a depth preset of its own
  (its episode's, under domain randomisation) with its own noise and dropout factors.

A scene change (:meth:`CameraPipeline.load`) rebuilds the drawing and reseeds the models with the scene;
a light change (:meth:`CameraPipeline.set_light`) only redraws the shadow map.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Collection, Iterator, Sequence
from typing import Any

import numpy as np

from droneulator.config import LightConfig, SimConfig
from droneulator.render.renderer import CameraFrame, Renderer, config_lighting, fleet_renderer
from droneulator.scenes.base import Scene
from droneulator.sensors.camera_models import CameraModel, camera_rng, fleet_camera_models

#: where depth comes from: the OpenGL renderer, or ray casting (depth only)
DEPTH_SOURCES = ("render", "raycast")
#: other bodies as spheres for the cast depth: centres (B, K, 3) and radii (B, K) (pad with radius 0)
Spheres = tuple[Any, Any]
#: a pose's motion for the motion blur: (velocity m/s world, angular velocity rad/s body FLU)
Motion = tuple[Any, Any]


def _no_spheres(spheres: Spheres | None) -> None:
    """ValueError for spheres given to the renderer, which draws the vehicles' own bodies."""
    if spheres is not None:
        raise ValueError(
            "spheres are for the ray caster: the renderer draws the other vehicles' bodies itself "
            "(pose them with frames())"
        )


def _picked(spheres: Spheres | None, mask: np.ndarray) -> Spheres | None:
    """The spheres of the poses ``mask`` selects."""
    return None if spheres is None else (np.asarray(spheres[0])[mask], np.asarray(spheres[1])[mask])


def depth_presets(config: SimConfig, seed: int | None = None) -> dict[str, CameraModel | None]:
    """The first camera's depth errors under every preset an episode may fly with, by name (None: ideal):
    its own (``depth_model``) and, with domain randomisation, each of ``randomize.depth_models``; each
    seeded as that camera (:func:`~droneulator.sensors.camera_models.camera_rng`)."""
    cam = config.render.cameras[0]
    seed = config.seed if seed is None else seed
    names = [cam.depth_model, *(config.randomize.depth_models if config.randomize.enabled else [])]
    models: dict[str, CameraModel | None] = {}
    for name in dict.fromkeys(names):
        preset = dataclasses.replace(cam, depth_model=name)
        models[name] = None if name == "ideal" else CameraModel(preset, camera_rng(seed))
    return models


class CameraPipeline:
    """Draws and delivers the cameras of ``config``'s vehicles in ``scene`` (see the module docstring).

    ``source``: ``"render"`` (every image; needs an EGL context) or ``"raycast"`` (depth of the first
    camera only, on the CPU). ``seed`` (default: the config's) seeds the cameras' noise.
    """

    def __init__(
        self, scene: Scene, config: SimConfig, seed: int | None = None, source: str = "render"
    ) -> None:
        if source not in DEPTH_SOURCES:
            raise ValueError(f"the depth source must be one of {', '.join(DEPTH_SOURCES)}, got {source!r}")
        self.config = config
        self.source = source
        self.renderer: Renderer | None = None
        self.caster: Any = None
        self.scene = scene
        #: vehicle -> camera -> the realism model of every camera that is not ideal
        self.models: dict[str, dict[str, CameraModel]] = {}
        self._presets: dict[str, CameraModel | None] | None = None
        self._seed = config.seed if seed is None else seed
        #: the first vehicle: the one whose first camera :meth:`depth` and :meth:`centre_rows` draw
        self.vehicle = next(iter(config.camera_rigs()))
        self.load(scene, config.seed if seed is None else seed)

    def load(self, scene: Scene, seed: int) -> None:
        """Draw ``scene`` from now on (the config's light), the models reseeded with ``seed``."""
        self.close()
        if self.source == "render":
            self.renderer = fleet_renderer(scene, self.config)
        else:
            from droneulator.render.raycast import DepthCaster

            self.caster = DepthCaster(scene, self.config.render.cameras[0])
        self.scene = scene
        self.models = fleet_camera_models(self.config, seed)
        self._seed, self._presets = seed, None

    @property
    def presets(self) -> dict[str, CameraModel | None]:
        """The first camera's depth under each preset an episode may pick (:func:`depth_presets`), built on
        first use: only the learning envs' depth batches need them."""
        if self._presets is None:
            self._presets = depth_presets(self.config, self._seed)
        return self._presets

    def set_light(self, light: LightConfig) -> None:
        """Light the scene with ``light`` from the next frame on (the shadow map is drawn again). ValueError
        for a scene whose own light settings are bad, before anything changes."""
        if self.renderer is not None:
            self.renderer.set_light(
                config_lighting(self.scene, dataclasses.replace(self.config, light=light))
            )

    # ------------------------------------------------------------------ every camera of every rig
    def frames(
        self,
        poses: dict[str, np.ndarray],
        rigs: Collection[str] | None = None,
        motion: dict[str, Motion] | None = None,
        rgb: bool = True,
        copy: bool = True,
    ) -> dict[str, dict[str, CameraFrame]]:
        """vehicle -> camera -> frame for every camera of the vehicles in ``poses`` (vehicle -> body pose,
        4x4, Z-up world), of ``rigs`` only when given (every body in ``poses`` is drawn), each through its
        camera's models (``motion``: each vehicle's for the motion blur). ``rgb=False`` draws depth and
        segmentation only. With ``copy`` the images are the caller's; without, an ideal camera's images
        are the renderer's buffers, valid until the next call."""
        if self.renderer is None:
            why = "is closed" if self.source == "render" else "draws depth by ray casting only"
            raise RuntimeError(f"this camera pipeline {why}")
        drawn = self.renderer.render_rigs(poses, rgb=rgb, rigs=rigs)
        out: dict[str, dict[str, CameraFrame]] = {}
        for vehicle, cams in drawn.items():
            models = self.models.get(vehicle, {})
            velocity, angular = (motion or {}).get(vehicle, (None, None))
            out[vehicle] = {}
            for name, f in cams.items():
                model = models.get(name)
                if copy:
                    f = dataclasses.replace(
                        f, rgb=None if f.rgb is None else f.rgb.copy(), depth=f.depth.copy(), seg=f.seg.copy()
                    )
                out[vehicle][name] = f if model is None else model.apply(f, velocity, angular)
        return out

    # ------------------------------------------------------------------ one camera at many poses
    @property
    def camera(self) -> Any:
        """The first camera of the first vehicle: the one :meth:`depth` and :meth:`centre_rows` draw."""
        return self.config.render.cameras[0]

    def ideal(self, presets: Sequence[str] | None) -> bool:
        """Whether depth under ``presets`` (None: the camera's own) is the exact depth."""
        names = [self.camera.depth_model] if presets is None else presets
        return all(self.presets[name] is None for name in names)

    def depth(
        self,
        poses: np.ndarray,
        presets: Sequence[str] | None = None,
        scales: np.ndarray | None = None,
        spheres: Spheres | None = None,
    ) -> np.ndarray:
        """The first camera's depth images ``(B, H, W)`` at body poses ``(B, 4, 4)``, image ``b`` through the
        depth preset ``presets[b]`` (None: the camera's own) with noise and dropout factors ``scales[b]``
        (``(B, 2)``; None: the camera's). ``spheres``: other bodies as spheres, (centres ``(B, K, 3)``,
        radii ``(B, K)``), seen before the preset applies (ray casting only, see
        :meth:`DepthCaster.sphere_depth <droneulator.render.raycast.DepthCaster.sphere_depth>`)."""
        poses = np.asarray(poses, dtype=float).reshape(-1, 4, 4)
        if self.caster is not None:
            exact = self.caster.depth(poses, spheres=spheres)
        else:
            _no_spheres(spheres)
            exact = np.empty((len(poses), self.camera.height, self.camera.width), dtype=np.float32)
            for k, d in enumerate(self._drawn(poses)):
                exact[k] = d
        return self._through(exact, presets, scales)

    def centre_rows(
        self,
        poses: np.ndarray,
        presets: Sequence[str] | None = None,
        scales: np.ndarray | None = None,
        spheres: Spheres | None = None,
    ) -> np.ndarray:
        """The centre rows (row ``H // 2``) of :meth:`depth` ``(B, W)``; whole images are drawn only for the
        poses whose preset is not ideal (a depth model's edges and thin structures need the rows around).
        ``spheres``: as :meth:`depth`'s."""
        poses = np.asarray(poses, dtype=float).reshape(-1, 4, 4)
        if self.caster is None:
            _no_spheres(spheres)
        names = [self.camera.depth_model] * len(poses) if presets is None else list(presets)
        noisy = np.array([self.presets[m] is not None for m in names], dtype=bool)
        out = np.empty((len(poses), self.camera.width), dtype=np.float32)
        exact = ~noisy
        if exact.any():
            if self.caster is not None:
                out[exact] = self.caster.centre_row(poses[exact], spheres=_picked(spheres, exact))
            else:
                out[exact] = self._exact_rows(poses[exact])
        if noisy.any():
            picked = [m for m, n in zip(names, noisy, strict=True) if n]
            s = None if scales is None else np.asarray(scales)[noisy]
            depth = self.depth(poses[noisy], picked, s, _picked(spheres, noisy))
            out[noisy] = depth[:, depth.shape[1] // 2]
        return out

    def sector_minima(self, poses: np.ndarray, sectors: int, spheres: Spheres | None = None) -> np.ndarray:
        """``(B, sectors)``: the nearest exact depth in each of ``sectors`` equal runs of the centre row (NaN:
        no return), by ray casting only, which casts no more of a sector than its nearest return needs;
        ``spheres``: as :meth:`depth`'s."""
        if self.caster is None:
            raise RuntimeError("sector minima are cast: make the pipeline with source='raycast'")
        poses = np.asarray(poses, dtype=float).reshape(-1, 4, 4)
        return self.caster.centre_row_minima(poses, sectors, spheres=spheres)

    def _exact_rows(self, poses: np.ndarray) -> np.ndarray:
        """Exact depth centre rows drawn by the renderer."""
        rows = [d[d.shape[0] // 2].copy() for d in self._drawn(poses)]
        return np.array(rows).reshape(len(poses), -1)

    def _drawn(self, poses: np.ndarray) -> Iterator[np.ndarray]:
        """The renderer's exact depth of the first camera at each pose in turn (its buffer: copy to keep)."""
        if self.renderer is None:
            raise RuntimeError("this camera pipeline is closed")
        vehicle, name = self.vehicle, self.camera.name
        for T in poses:
            yield self.renderer.render_rigs({vehicle: T}, rgb=False)[vehicle][name].depth

    def _through(
        self, depth: np.ndarray, presets: Sequence[str] | None, scales: np.ndarray | None
    ) -> np.ndarray:
        """``depth`` (B, H, W, the caller's) with image ``b`` through preset ``presets[b]`` and factors
        ``scales[b]``, in place, each preset on its images in one batch."""
        out = depth
        names = [self.camera.depth_model] * len(depth) if presets is None else list(presets)
        which = np.asarray(names)
        for name in dict.fromkeys(names):
            model = self.presets[name]
            if model is None:
                continue
            sel = which == name
            if scales is None:
                out[sel] = model.apply_depth(depth[sel])
            else:
                s = np.asarray(scales)[sel]
                out[sel] = model.apply_depth(depth[sel], s[:, 0], s[:, 1])
        return out

    def close(self) -> None:
        if self.renderer is not None:
            self.renderer.close()
            self.renderer = None
        self.caster = None

    def __enter__(self) -> CameraPipeline:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
