"""The whole simulator in one Python process: no servers, no sockets, stepped in lockstep.

``droneulator.world.World`` composes the scene, the RotorPy vehicles (one by default), their flight
controllers and the headless renderer; ``world.vehicle()`` is its first vehicle, which takes the
commands. Every call below is what the dynamics server does for a WebSocket command, and
:meth:`World.run` returns the camera frames rendered in sim time (30 Hz by default). Use it for
scripted data collection, tests and learning loops where processes would only add latency.

    python examples/world_in_process.py --scene orchard --out out/in_process

It takes off, flies to a point beside the spawn, turns in velocity mode, lands, and saves the last
frame's colour image, depth (metres, .npy) and segmentation class ids; it prints the class
histogram of that frame and writes a summary JSON.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from PIL import Image

from droneulator.config import CameraConfig, load_config
from droneulator.scenes.base import SemanticClass
from droneulator.world import World


def fly(scene: str, seed: int, out: Path, width: int, height: int) -> dict:
    """Fly the short mission and save the last frame; returns a summary."""
    cfg = load_config(scene=scene, seed=seed)
    cfg.render.cameras = [CameraConfig(name="front", width=width, height=height)]
    out.mkdir(parents=True, exist_ok=True)
    events: list[dict] = []
    with World(config=cfg) as world:
        uav = world.vehicle()
        spawn = world.scene.spawn_position
        uav.takeoff(2.0)
        world.run_until(lambda w: uav.mode == "hold", timeout=20)
        target = [float(spawn[0]) + 1.5, float(spawn[1]), 2.5]
        uav.goto(target, yaw=0.5, speed=1.5)  # minimum-snap, SE(3) tracking
        reached = world.run_until(lambda w: uav.mode == "hold", timeout=20)
        error = float(np.linalg.norm(uav.state.position - target))
        print(f"t={world.t:5.2f} s goto {target}: reached={reached}, off by {error:.3f} m")

        uav.velocity(0.0, 0.8)  # turn on the spot, altitude held
        result = world.run(2.0)  # lockstep: every camera instant is rendered
        events += [e.to_dict() for e in result.events]
        frame = result.frames[-1].cameras[uav.name]["front"]
        print(
            f"t={world.t:5.2f} s velocity mode: {len(result.frames)} frame sets in 2 s of sim time, "
            f"yaw now {uav.state.yaw:.2f} rad"
        )

        Image.fromarray(frame.rgb).save(out / "front_rgb.png")
        np.save(out / "front_depth.npy", frame.depth)
        Image.fromarray(frame.seg).save(out / "front_seg_ids.png")
        ids, counts = np.unique(frame.seg, return_counts=True)
        classes = {SemanticClass(c).name: int(n) for c, n in zip(ids, counts, strict=True)}
        print(
            f"last frame {frame.rgb.shape[1]}x{frame.rgb.shape[0]}, K fx={frame.K[0, 0]:.1f}, "
            f"depth {np.nanmin(frame.depth):.2f}..{np.nanmax(frame.depth):.2f} m, classes {classes}"
        )

        uav.land()
        landed = world.run_until(lambda w: uav.mode == "idle", timeout=20)
        print(f"t={world.t:5.2f} s landed={landed} at {np.round(uav.state.position, 2).tolist()}")
        return {
            "scene": scene,
            "goto_target": target,
            "goto_error_m": error,
            "frames_in_2s": len(result.frames),
            "classes": classes,
            "landed": landed,
            "final_state": uav.state.to_dict(),
            "events": events,
            "rendered": world.frame_count,
        }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="default", help="scene name (droneulator scenes)")
    ap.add_argument("--seed", type=int, default=0, help="scene seed")
    ap.add_argument("--out", default="out/in_process", help="output folder")
    ap.add_argument("--width", type=int, default=640, help="camera width, px")
    ap.add_argument("--height", type=int, default=480, help="camera height, px")
    args = ap.parse_args()
    summary = fly(args.scene, args.seed, Path(args.out), args.width, args.height)
    (Path(args.out) / "summary.json").write_text(json.dumps(summary, indent=2))
    return 0 if summary["landed"] else 1


if __name__ == "__main__":
    sys.exit(main())
