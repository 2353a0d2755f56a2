"""Batched RL depth: DepthCaster (BVH ray casting) against the OpenGL renderer (llvmpipe), same run.

1. Speed. For B = 1, 16, 64, 256, 1024 body poses in the vineyard, RL-like (alleys and headlands at about
   1.5 m, any heading, small roll and pitch), the RL depth camera (128x9, 90 deg, far 10 m):
   ``DepthCaster.centre_row`` (the strip's row: 128 rays a pose) and ``DepthCaster.depth`` (all 1152),
   with one thread and with every CPU; the renderer drawing the same B depth images, one
   ``Renderer.render(T, rgb=False)`` call per pose (what ``LocalBackend`` does), and one
   ``Renderer.render_rigs`` call drawing B one-camera rigs. Median wall time per batch over the repeats
   (interleaved, so that load from other processes hits every method alike), rays/s, poses/s and the
   speed-up over the per-pose renderer.
2. Accuracy: the caster's depth against the renderer's on 1024 of those vineyard poses and 256 poses round
   the tree of ``tree_inspection`` (RL camera), and on 16 poses each with the default 640x480 camera (far
   200 m): pixels within 1 mm among those with a return in both, NaN pattern agreement, the disagreeing
   pixels (first surface alpha-tested, beside a depth edge, neither), and the 32-sector depth strips.

Reproduce: ``.venv/bin/python benchmarks/raycast.py`` (writes ``benchmarks/results/raycast.json``).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from _common import write
from scipy.ndimage import maximum_filter, minimum_filter

from droneulator import frames
from droneulator.config import CameraConfig
from droneulator.render.raycast import DepthCaster
from droneulator.render.renderer import Renderer
from droneulator.scenes import get_scene
from droneulator.scenes.base import Scene
from droneulator.workflows.rl.env import depth_strip, rl_camera

BATCHES = (1, 16, 64, 256, 1024)


def pose(x: float, y: float, z: float, yaw: float, pitch: float = 0.0, roll: float = 0.0) -> np.ndarray:
    return frames.transform_from_pose(np.array([x, y, z]), frames.quat_from_euler(roll, pitch, yaw))


def rl_poses(scene: Scene, n: int, seed: int = 0) -> np.ndarray:
    """Where the RL agent flies: 70 % in an alley (0.5 m either side of its centre line), else in a
    headland beyond the row ends; 1.5 m up (0.1 m std), any heading, roll and pitch of 0.05 rad std."""
    rng = np.random.default_rng(seed)
    alleys = scene.landmarks["alley_y"]
    out = []
    for _ in range(n):
        if rng.random() < 0.7:
            x, y = rng.uniform(-17, 17), rng.choice(alleys) + rng.uniform(-0.5, 0.5)
        else:
            x, y = rng.choice([-1, 1]) * rng.uniform(16.5, 24), rng.uniform(-15, 15)
        z = 1.5 + rng.normal(0, 0.1)
        out.append(pose(x, y, z, rng.uniform(-math.pi, math.pi), rng.normal(0, 0.05), rng.normal(0, 0.05)))
    return np.array(out)


def tree_poses(scene: Scene, n: int, seed: int = 1) -> np.ndarray:
    """Round the crown at 2.8-7 m and 1-5.5 m up, looking at the crown centre."""
    rng = np.random.default_rng(seed)
    c = scene.landmarks["crown_center"]
    out = []
    for k in range(n):
        ang = 2 * math.pi * k / n
        r = rng.uniform(2.8, 7.0)
        p = np.array([c[0] + r * math.cos(ang), c[1] + r * math.sin(ang), rng.uniform(1.0, 5.5)])
        to = c - p
        pitch = -math.atan2(to[2], math.hypot(to[0], to[1])) + rng.normal(0, 0.05)
        out.append(pose(*p, math.atan2(to[1], to[0]) + rng.normal(0, 0.1), pitch))
    return np.array(out)


# --------------------------------------------------------------------------- speed
def median_time(fn: Callable[[], Any], repeats: int) -> list[float]:
    """Wall times of ``repeats`` calls."""
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return out


def speed(
    scene: Scene, cam: CameraConfig, poses: np.ndarray, batches: tuple[int, ...], budget_s: float
) -> dict[str, Any]:
    casters = {1: DepthCaster(scene, [cam], threads=1)}
    cpus = os.cpu_count() or 1
    if cpus > 1:
        casters[cpus] = DepthCaster(scene, [cam], threads=cpus)
    t0 = time.perf_counter()
    single = Renderer(scene, [cam], shadows=False)
    renderer_setup = time.perf_counter() - t0
    with single.ctx:
        gl_renderer = single.ctx.info["GL_RENDERER"]
    t0 = time.perf_counter()
    DepthCaster(scene, [cam])
    caster_setup = time.perf_counter() - t0
    for c in casters.values():  # warm up: numba (compiled or loaded from its cache)
        c.depth(poses[:4])
    single.render(poses[0], rgb=False)

    def per_pose(P: np.ndarray) -> np.ndarray:
        return np.stack([single.render(T, rgb=False)[cam.name].depth.copy() for T in P])

    rows = []
    for B in batches:
        P = poses[:B]
        rigs = Renderer(scene, rigs={f"v{k}": [cam] for k in range(B)}, shadows=False)
        names = [f"v{k}" for k in range(B)]

        def batched(P: np.ndarray = P, rigs: Renderer = rigs, names: list[str] = names) -> np.ndarray:
            out = rigs.render_rigs(dict(zip(names, P, strict=True)), rgb=False)
            return np.stack([out[v][cam.name].depth.copy() for v in names])

        batched()
        methods: dict[str, tuple[Callable[[], Any], int]] = {}
        for threads, c in casters.items():
            methods[f"caster_row_t{threads}"] = (lambda c=c, P=P: c.centre_row(P), cam.width)
            methods[f"caster_image_t{threads}"] = (lambda c=c, P=P: c.depth(P), cam.width * cam.height)
        methods["gl_render_per_pose"] = (lambda P=P: per_pose(P), cam.width * cam.height)
        methods["gl_render_rigs"] = (batched, cam.width * cam.height)
        # repeats sized so that the slowest method takes about budget_s at this B
        probe = {name: median_time(fn, 1)[0] for name, (fn, _) in methods.items()}
        repeats = int(np.clip(budget_s / max(probe.values()), 3, 200))
        times: dict[str, list[float]] = {name: [] for name in methods}
        for _ in range(repeats):
            for name, (fn, _) in methods.items():
                times[name] += median_time(fn, 1)
        rigs.close()
        row: dict[str, Any] = {"B": B, "repeats": repeats}
        for name, (_, rays_per_pose) in methods.items():
            t = float(np.median(times[name]))
            row[name] = {"ms": 1e3 * t, "poses_per_s": B / t, "rays_per_s": B * rays_per_pose / t}
        base = row["gl_render_per_pose"]["ms"]
        for name in methods:
            row[name]["speedup_vs_gl_per_pose"] = base / row[name]["ms"]
        rows.append(row)
        print(
            f"B={B:5d} ({repeats} repeats): "
            + ", ".join(f"{k} {row[k]['ms']:.2f} ms ({row[k]['poses_per_s']:.0f} poses/s)" for k in methods)
        )
    single.close()
    return {
        "gl_renderer": gl_renderer,
        "renderer_setup_s": renderer_setup,
        "caster_setup_s": caster_setup,
        "threads": list(casters),
        "batches": rows,
    }


# --------------------------------------------------------------------------- accuracy
def near_edge(depth: np.ndarray, far: float) -> np.ndarray:
    """Pixels whose 3x3 neighbourhood spans a depth discontinuity (over 5 cm + 2 %, NaN as beyond far)."""
    d = np.where(np.isnan(depth), 2 * far, depth)
    box = {"size": (1, 3, 3), "mode": "nearest"}
    span = maximum_filter(d, **box) - minimum_filter(d, **box)
    return span > 0.05 + 0.02 * np.minimum(d, far)


def accuracy(scene: Scene, cam: CameraConfig, poses: np.ndarray, strips: bool) -> dict[str, Any]:
    caster = DepthCaster(scene, [cam])
    depth = caster.depth(poses)
    opaque = dataclasses.replace(scene, parts=[dataclasses.replace(p, alpha_test=False) for p in scene.parts])
    first = DepthCaster(opaque, [cam]).trace(poses)[1]
    with Renderer(scene, [cam], shadows=False) as r:
        gl = np.stack([r.render(T, rgb=False)[cam.name].depth.copy() for T in poses])
    hit, gl_hit = ~np.isnan(depth), ~np.isnan(gl)
    both = hit & gl_hit
    err = np.abs(depth - gl)
    bad = (hit != gl_hit) | (both & (err > 1e-3))
    on_alpha = (first >= 0) & caster.alpha_tested[np.maximum(first, 0)]
    edge = near_edge(depth, cam.far) | near_edge(gl, cam.far)
    res: dict[str, Any] = {
        "scene": scene.name,
        "camera": dataclasses.asdict(cam),
        "poses": len(poses),
        "pixels": int(depth.size),
        "pixels_return_both": int(both.sum()),
        "within_1mm": float((err[both] <= 1e-3).mean()),
        "median_abs_diff_m": float(np.median(err[both])),
        "p99_abs_diff_m": float(np.percentile(err[both], 99)),
        "nan_pattern_agreement": float((hit == gl_hit).mean()),
        "disagreeing_pixels": int(bad.sum()),
        "disagreeing_alpha_first_surface": int((bad & on_alpha).sum()),
        "disagreeing_beside_edge": int((bad & edge).sum()),
        "disagreeing_neither": int((bad & ~on_alpha & ~edge).sum()),
    }
    if strips:
        a = np.stack([depth_strip(d, cam.far) for d in depth])
        b = np.stack([depth_strip(d, cam.far) for d in gl])
        off = np.abs(a - b) > 1e-3
        res["strip_sectors_within_1e-3"] = float((~off).mean())
        res["strip_poses_all_within_1e-3"] = float((~off.any(axis=1)).mean())
        res["strip_max_sectors_off"] = int(off.sum(axis=1).max())
        res["strip_max_abs_diff"] = float(np.abs(a - b).max())
    print(
        f"{scene.name} {cam.width}x{cam.height} far {cam.far:g}, {len(poses)} poses: "
        f"{100 * res['within_1mm']:.3f} % within 1 mm, "
        f"NaN pattern {100 * res['nan_pattern_agreement']:.4f} %, "
        f"{res['disagreeing_pixels']} px differ ({res['disagreeing_alpha_first_surface']} alpha, "
        f"{res['disagreeing_beside_edge']} edge, {res['disagreeing_neither']} neither)"
        + (
            f"; strips: {100 * res['strip_poses_all_within_1e-3']:.1f} % of poses all sectors within 1e-3"
            if strips
            else ""
        )
    )
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--batches", default=",".join(map(str, BATCHES)), help="batch sizes, comma-separated")
    ap.add_argument("--budget", type=float, default=3.0, help="seconds of the slowest method per batch size")
    ap.add_argument("--json", default=None, help="output path (default benchmarks/results/raycast.json)")
    args = ap.parse_args()
    batches = tuple(int(b) for b in args.batches.split(","))

    from droneulator.config import RLConfig

    cam = rl_camera(RLConfig())
    vineyard, tree = get_scene("vineyard", 0), get_scene("tree_inspection", 0)
    poses = rl_poses(vineyard, max(max(batches), 1024))
    load_before = os.getloadavg()
    res: dict[str, Any] = {
        "scene": vineyard.name,
        "triangles": vineyard.triangle_count,
        "camera": dataclasses.asdict(cam),
        "speed": speed(vineyard, cam, poses, batches, args.budget),
    }
    big = CameraConfig()
    res["accuracy"] = [
        accuracy(vineyard, cam, poses[:1024], strips=True),
        accuracy(tree, cam, tree_poses(tree, 256), strips=True),
        accuracy(vineyard, big, poses[:16], strips=False),
        accuracy(tree, big, tree_poses(tree, 16), strips=False),
    ]
    res["load_average_before_after"] = [load_before, os.getloadavg()]
    write("raycast", res, args.json)


if __name__ == "__main__":
    main()
