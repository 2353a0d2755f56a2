"""The render server: draws every vehicle's camera rig for each set of states the dynamics server sends
through the camera pipeline the in-process world uses (:mod:`droneulator.render.pipeline`: each vehicle's
body in the others' cameras, each camera's realism models) into the shared-memory frame ring, and
acknowledges each frame set.

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
from droneulator.render.pipeline import CameraPipeline
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
from droneulator.runtime.spawn import start_server_process
from droneulator.scenes import get_scene

log = logging.getLogger("droneulator.render")


def serve(cfg: SimConfig) -> None:
    conn, welcome = hub_connect("renderer")
    rigs = cfg.camera_rigs()
    ring = FrameRing(os.environ[ENV_RING], rigs, cfg.runtime.frame_slots)

    cameras = CameraPipeline(get_scene(welcome.scene, welcome.seed, cfg.vegetation), cfg, welcome.seed)
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
                    motion = {name: (st.velocity, st.angular_velocity) for name, st in states.items()}
                    slot = ring.slot(seq)
                    for vehicle, frames in cameras.frames(poses, rigs, motion, copy=False).items():
                        for name, f in frames.items():
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
                        cameras.set_light(light)
                        log.info("light changed: %s", light)
                        continue
                    cameras.load(get_scene(scene, seed, vegetation), seed)
                    loaded = (scene, seed, vegetation)
                    log.info("scene changed to %s (seed %d, vegetation %g)", scene, seed, vegetation)
    finally:
        cameras.close()
        ring.close()
        conn.close()


def main() -> None:
    start_server_process()
    signal.signal(signal.SIGTERM, lambda *_: os._exit(0))
    signal.signal(signal.SIGINT, lambda *_: os._exit(0))
    try:
        serve(from_dict(SimConfig, json.loads(os.environ[ENV_CONFIG])))
    except HubGoneError as e:
        log.error("%s; exiting", e)
        sys.exit(1)


if __name__ == "__main__":
    main()
