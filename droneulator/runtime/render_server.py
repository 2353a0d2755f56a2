"""The render server: draws every vehicle's camera rig for each set of states the dynamics server sends
(each vehicle's body in the others' cameras), through each camera's realism models
(:mod:`droneulator.sensors.camera_models`, as the in-process world applies them), into the shared-memory
frame ring, and acknowledges each frame set.

States arrive in the Z-up world (RotorPy); the renderer converts them to its Y-up OpenGL world
through :mod:`droneulator.frames` (``gl_view_matrix``), nowhere else.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import sys

import numpy as np

from droneulator.config import SimConfig, from_dict
from droneulator.frames import transform_from_pose
from droneulator.render import Renderer, fleet_renderer
from droneulator.render.renderer import config_lighting
from droneulator.runtime.ipc import (
    ENV_CONFIG,
    ENV_RING,
    FrameRing,
    HubGoneError,
    LoadScene,
    Render,
    Rendered,
    hub_connect,
)
from droneulator.scenes import get_scene
from droneulator.sensors.camera_models import CameraModel, fleet_camera_models

log = logging.getLogger("droneulator.render")


def serve(cfg: SimConfig) -> None:
    conn, welcome = hub_connect("renderer")
    rigs = cfg.camera_rigs()
    ring = FrameRing(os.environ[ENV_RING], rigs, cfg.runtime.frame_slots)

    def make(scene: str, seed: int, vegetation: float) -> tuple[Renderer, dict[str, dict[str, CameraModel]]]:
        """The renderer and the cameras' realism models (reseeded with the scene, as the world's are)."""
        renderer = fleet_renderer(get_scene(scene, seed, vegetation), cfg)
        return renderer, fleet_camera_models(cfg, seed)

    renderer, models = make(welcome.scene, welcome.seed, cfg.vegetation)
    loaded = (welcome.scene, welcome.seed, cfg.vegetation)
    log.info(
        "render server ready: %s, %s",
        welcome.scene,
        "; ".join(
            f"{vehicle}: " + ", ".join(f"{c.name} {c.width}x{c.height}" for c in cams)
            for vehicle, cams in rigs.items()
        ),
    )
    try:
        while True:
            try:
                msg = conn.recv()
            except (EOFError, OSError):
                return  # the dynamics server went away: the run is over
            match msg:
                case Render(seq, states, rigs):
                    poses = {
                        name: transform_from_pose(st.position, st.quaternion) for name, st in states.items()
                    }
                    slot = ring.slot(seq)
                    for vehicle, frames in renderer.render_rigs(poses, rigs=rigs).items():
                        st = states[vehicle]
                        for name, f in frames.items():
                            model = models.get(vehicle, {}).get(name)
                            if model is not None:
                                f = model.apply(f, st.velocity, st.angular_velocity)
                            out = slot[vehicle][name]
                            np.copyto(out.rgb, f.rgb)
                            np.copyto(out.depth, f.depth)
                            np.copyto(out.seg, f.seg)
                    try:
                        conn.send(Rendered(seq))
                    except OSError:
                        return
                case LoadScene(scene, seed, light, vegetation):
                    cfg.light = light
                    if (scene, seed, vegetation) == loaded:  # the light alone: the scene stays uploaded
                        renderer.set_light(config_lighting(renderer.scene, cfg))
                        log.info("light changed: %s", light)
                        continue
                    renderer.close()
                    renderer, models = make(scene, seed, vegetation)
                    loaded = (scene, seed, vegetation)
                    log.info("scene changed to %s (seed %d, vegetation %g)", scene, seed, vegetation)
    finally:
        renderer.close()
        ring.close()
        conn.close()


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s")
    signal.signal(signal.SIGTERM, lambda *_: os._exit(0))
    signal.signal(signal.SIGINT, lambda *_: os._exit(0))
    try:
        serve(from_dict(SimConfig, json.loads(os.environ[ENV_CONFIG])))
    except HubGoneError as e:
        log.error("%s; exiting", e)
        sys.exit(1)


if __name__ == "__main__":
    main()
