"""Scene pictures for the UI, drawn by the simulator's own renderer: level-select previews and top-down maps.

Building a scene and rendering it takes a second or more, so every picture is drawn once per (scene,
seed) and kept as encoded bytes. All drawing happens on one worker thread that owns the GL work, so a
browser asking for four previews at once never runs four renderers side by side.
"""

from __future__ import annotations

import io
import math
import threading
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any

import numpy as np
from PIL import Image

from droneulator.config import CameraConfig
from droneulator.threads import DaemonWorker

#: preview camera: a 16:9 card picture looking 25 degrees down from above the spawn point
PREVIEW_CAMERA = CameraConfig(name="preview", width=480, height=270, hfov_deg=80.0, rpy_deg=(0.0, 25.0, 0.0))
PREVIEW_ALTITUDE_M = 5.0
#: the map shows this fraction of the flyable box's size beyond each of its sides (clicks there are refused)
MAP_MARGIN = 0.12
#: pixels along the longer side of a map
MAP_SIZE = 768
SHADOW_MAP_SIZE = 2048


@dataclass(frozen=True)
class MapImage:
    """A top-down map: PNG bytes and the world box it shows, ``extent`` = [x_min, y_min, x_max, y_max] (m)."""

    png: bytes
    extent: tuple[float, float, float, float]
    bounds_min: tuple[float, float, float]
    bounds_max: tuple[float, float, float]

    def meta(self) -> dict[str, Any]:
        return {
            "extent": list(self.extent),
            "bounds_min": list(self.bounds_min),
            "bounds_max": list(self.bounds_max),
        }


def map_extent(bounds_min: np.ndarray, bounds_max: np.ndarray) -> tuple[float, float, float, float]:
    """The world box a map of a scene with these flyable bounds shows: the box plus :data:`MAP_MARGIN`."""
    lo, hi = np.asarray(bounds_min, dtype=float)[:2], np.asarray(bounds_max, dtype=float)[:2]
    pad = MAP_MARGIN * (hi - lo)
    return (float(lo[0] - pad[0]), float(lo[1] - pad[1]), float(hi[0] + pad[0]), float(hi[1] + pad[1]))


def render_preview(name: str, seed: int) -> bytes:
    """JPEG of scene ``name`` seen from above its spawn point, looking along the spawn heading."""
    from droneulator.config import SimConfig
    from droneulator.frames import make_transform, quat_from_yaw, quat_to_matrix
    from droneulator.render.pipeline import CameraPipeline
    from droneulator.scenes import get_scene

    scene = get_scene(name, seed)
    pose = make_transform(
        quat_to_matrix(quat_from_yaw(scene.spawn_yaw)),
        scene.spawn_position + np.array([0.0, 0.0, PREVIEW_ALTITUDE_M]),
    )
    cfg = SimConfig(scene=name, seed=seed)
    cfg.render.cameras = [PREVIEW_CAMERA]
    cfg.render.shadow_map_size = SHADOW_MAP_SIZE
    with CameraPipeline(scene, cfg) as cameras:
        rgb = cameras.frames({cameras.vehicle: pose})[cameras.vehicle][PREVIEW_CAMERA.name].rgb
    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format="JPEG", quality=85)
    return buf.getvalue()


def render_map(name: str, seed: int) -> MapImage:
    """Top-down orthographic map of scene ``name`` over its flyable box plus a margin."""
    from droneulator.render.renderer import Renderer
    from droneulator.scenes import get_scene

    scene = get_scene(name, seed)
    extent = map_extent(scene.bounds_min, scene.bounds_max)
    w_m, h_m = extent[2] - extent[0], extent[3] - extent[1]
    scale = MAP_SIZE / max(w_m, h_m)
    width, height = max(1, math.ceil(w_m * scale)), max(1, math.ceil(h_m * scale))
    with Renderer(scene, [], shadow_map_size=SHADOW_MAP_SIZE) as r:
        rgb = r.render_top_down(extent[:2], extent[2:], width, height)
    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format="PNG", compress_level=3)
    return MapImage(
        buf.getvalue(),
        extent,
        tuple(float(v) for v in scene.bounds_min),
        tuple(float(v) for v in scene.bounds_max),
    )


class ScenePictures:
    """Previews and maps drawn on demand on one thread and cached per (scene, seed)."""

    def __init__(self, nice: int = 0) -> None:
        self._lock = threading.Lock()
        self._jobs: dict[tuple[str, str, int], Future[Any]] = {}
        self._worker = DaemonWorker("ui-render", nice=nice)

    def _get(self, kind: str, name: str, seed: int) -> Future[Any]:
        from droneulator.scenes import list_scenes

        if name not in list_scenes():
            raise KeyError(f"unknown scene {name!r}; known scenes: {', '.join(list_scenes())}")
        key = (kind, name, int(seed))
        with self._lock:
            job = self._jobs.get(key)
            if job is None or (job.done() and job.exception() is not None):
                fn = render_preview if kind == "preview" else render_map
                job = self._jobs[key] = self._worker.submit(fn, name, int(seed))
            return job

    def preview(self, name: str, seed: int = 0) -> Future[bytes]:
        """A future JPEG preview of ``name``; KeyError for an unknown scene."""
        return self._get("preview", name, seed)

    def map(self, name: str, seed: int = 0) -> Future[MapImage]:
        """A future top-down map of ``name``; KeyError for an unknown scene."""
        return self._get("map", name, seed)

    def close(self) -> None:
        """Cancel the pictures not started yet and let the worker end."""
        with self._lock:
            for job in self._jobs.values():
                job.cancel()
        self._worker.close()
