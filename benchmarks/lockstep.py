"""Lockstep real-time factor with the full sensor rig.

An in-process one-vehicle World flies a velocity-mode pattern on a scene with the default 640x480
camera (RGB + depth + segmentation with readback) at 30 Hz simulation time, physics and SE(3)
control at 100 Hz. Real-time factor = simulated seconds / wall seconds; 1.0 or more means the
rig keeps up with real time while never skipping a frame.
"""

from __future__ import annotations

import argparse
import time

from _common import write

from droneulator.config import load_config
from droneulator.world import World


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="orchard", help="scene name (default orchard)")
    ap.add_argument("--seconds", type=float, default=10.0, help="simulated seconds to time (default 10)")
    ap.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="config override, e.g. render.shadows=false",
    )
    ap.add_argument("--json", default=None, help="output path (default benchmarks/results/lockstep.json)")
    args = ap.parse_args()

    cfg = load_config(None, args.overrides, scene=args.scene)
    with World(config=cfg) as world:
        uav = world.vehicle()
        world.reset(position=world.scene.spawn_position + [0.0, 0.0, 2.0])
        uav.velocity(0.5, 0.3)
        world.run(0.5)  # warm up (shader compilation, numba)
        frames0 = world.frame_count
        t_sim0 = world.t
        t0 = time.perf_counter()
        world.run(args.seconds)
        wall = time.perf_counter() - t0
        frames = world.frame_count - frames0
        sim_s = world.t - t_sim0
        res = {
            "scene": args.scene,
            "triangles": world.scene.triangle_count,
            "sim_seconds": sim_s,
            "wall_seconds": wall,
            "real_time_factor": sim_s / wall,
            "frames": frames,
            "frames_expected": round(sim_s * cfg.render.camera_hz),
            "wall_fps": frames / wall,
            "cameras": [f"{c.name} {c.width}x{c.height}" for c in cfg.render.cameras],
            "shadows": cfg.render.shadows,
            "camera_hz": cfg.render.camera_hz,
        }
    print(
        f"{args.scene} ({res['triangles']} triangles), {', '.join(res['cameras'])} "
        f"at {cfg.render.camera_hz:g} Hz:"
    )
    print(f"  {sim_s:.2f} s simulated in {wall:.2f} s wall -> real-time factor {res['real_time_factor']:.2f}")
    print(
        f"  {frames} frames rendered ({res['frames_expected']} expected), {res['wall_fps']:.1f} frames/s wall"
    )
    write("lockstep", res, args.json)


if __name__ == "__main__":
    main()
