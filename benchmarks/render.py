"""Renderer throughput: frames/s for a camera flying through a scene, RGB + depth + seg read back.

Runs three modes on the same flight (shadows on, shadows off, depth + segmentation only), each flight
repeated and interleaved with the other modes, then prints median and best frames/s, the CPU time per
frame and, for shadows on, the time split between issuing draws, rasterising and each readback, and
writes ``benchmarks/results/render.json``. ``--synthetic N`` swaps the named scene for a generated
orchard of about N triangles (textured ground, trunks, branches and fruit, alpha-tested leaf cards).
"""

from __future__ import annotations

import argparse
import math
import os
import resource
import time
from pathlib import Path

import numpy as np
from _common import RESULTS, write

from droneulator import frames
from droneulator.config import CameraConfig
from droneulator.render import Renderer
from droneulator.scenes.base import CollisionModel, MeshPart, Scene, SemanticClass

OUTPUT = RESULTS / "render.json"


# --------------------------------------------------------------------------- synthetic orchard
def _noise_texture(
    rng: np.random.Generator, size: int, base: tuple[int, int, int], spread: int
) -> np.ndarray:
    img = np.empty((size, size, 4), dtype=np.uint8)
    noise = rng.integers(-spread, spread + 1, size=(size, size, 1))
    img[..., :3] = np.clip(np.array(base) + noise, 0, 255)
    img[..., 3] = 255
    return img


def _leaf_texture(rng: np.random.Generator, size: int = 256) -> np.ndarray:
    """Green leaves (ellipses) on a transparent background, about half the texels opaque."""
    img = np.zeros((size, size, 4), dtype=np.uint8)
    y, x = np.mgrid[0:size, 0:size] / size
    for _ in range(40):
        cx, cy, a, b, ang = (
            *rng.random(2),
            0.04 + 0.05 * rng.random(),
            0.02 + 0.02 * rng.random(),
            rng.random() * 3,
        )
        dx, dy = x - cx, y - cy
        u, v = dx * math.cos(ang) + dy * math.sin(ang), -dx * math.sin(ang) + dy * math.cos(ang)
        mask = (u / a) ** 2 + (v / b) ** 2 < 1
        img[mask] = (40 + rng.integers(0, 40), 110 + rng.integers(0, 60), 30 + rng.integers(0, 30), 255)
    return img


def _cylinder(p0: np.ndarray, p1: np.ndarray, radius: float, sides: int) -> tuple[np.ndarray, ...]:
    """Open cylinder between two points: positions, normals, uvs, indices (unshared side quads)."""
    axis = p1 - p0
    length = np.linalg.norm(axis)
    w = axis / length
    u = np.cross(w, [1.0, 0, 0] if abs(w[0]) < 0.9 else [0, 1.0, 0])
    u /= np.linalg.norm(u)
    v = np.cross(w, u)
    ang = np.linspace(0, 2 * math.pi, sides + 1)
    ring = np.cos(ang)[:, None] * u + np.sin(ang)[:, None] * v
    pos = np.concatenate([p0 + radius * ring, p1 + radius * ring])
    nrm = np.concatenate([ring, ring])
    uv = np.concatenate(
        [
            np.stack([ang / (2 * math.pi), np.zeros_like(ang)], 1),
            np.stack([ang / (2 * math.pi), np.full_like(ang, length)], 1),
        ]
    )
    i = np.arange(sides)
    j = sides + 1
    idx = np.concatenate([np.stack([i, i + 1, i + j], 1), np.stack([i + 1, i + 1 + j, i + j], 1)])
    return pos, nrm, uv, idx


class _Builder:
    """Accumulates triangles of one MeshPart."""

    def __init__(self) -> None:
        self.pos: list[np.ndarray] = []
        self.nrm: list[np.ndarray] = []
        self.uv: list[np.ndarray] = []
        self.cls: list[np.ndarray] = []
        self.idx: list[np.ndarray] = []
        self.n = 0

    def add(self, pos: np.ndarray, nrm: np.ndarray, uv: np.ndarray, idx: np.ndarray, cls: int) -> None:
        self.pos.append(pos)
        self.nrm.append(nrm)
        self.uv.append(uv)
        self.cls.append(np.full(len(pos), cls, dtype=np.uint8))
        self.idx.append(idx + self.n)
        self.n += len(pos)

    def part(self, name: str, texture: str, alpha_test: bool = False) -> MeshPart:
        return MeshPart(
            name,
            np.concatenate(self.pos).astype(np.float32),
            np.concatenate(self.nrm).astype(np.float32),
            np.concatenate(self.uv).astype(np.float32),
            np.concatenate(self.cls),
            np.concatenate(self.idx).astype(np.uint32),
            texture,
            alpha_test,
        )


def synthetic_orchard(n_triangles: int, seed: int = 0) -> Scene:
    """An orchard of about ``n_triangles`` triangles, about half of them alpha-tested leaf cards."""
    rng = np.random.default_rng(seed)
    per_tree = 2 * 12 + 4 * 2 * 8 + 2 * 300 + 8 * 2 * 8  # trunk, branches, leaf cards, fruit
    n_trees = max(1, round((n_triangles - 2 * 64 * 64) / per_tree))
    rows = max(1, int(round(math.sqrt(n_trees / 3))))
    per_row = math.ceil(n_trees / rows)
    size_x, size_y = per_row * 2.5 + 10, rows * 4.0 + 10

    ground = _Builder()
    g = 64
    gx, gy = np.meshgrid(np.linspace(-5, size_x - 5, g + 1), np.linspace(-5, size_y - 5, g + 1))
    pos = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], 1)
    k = (np.arange(g)[:, None] * (g + 1) + np.arange(g)[None]).ravel()
    quads = np.concatenate([np.stack([k, k + 1, k + g + 2], 1), np.stack([k, k + g + 2, k + g + 1], 1)])
    ground.add(pos, np.tile([0.0, 0, 1], (len(pos), 1)), pos[:, :2] / 4.0, quads, SemanticClass.GROUND)

    wood, leaves, fruit = _Builder(), _Builder(), _Builder()
    for t in range(n_trees):
        base = np.array([(t % per_row) * 2.5, (t // per_row) * 4.0, 0.0])
        top = base + [0, 0, 1.2]
        wood.add(*_cylinder(base, top, 0.08, 12)[:4], SemanticClass.TRUNK)
        for _ in range(4):
            d = rng.normal(size=3) * [1, 1, 0.3] + [0, 0, 1.2]
            wood.add(*_cylinder(top, top + 0.9 * d / np.linalg.norm(d), 0.03, 8), SemanticClass.BRANCH)
        centre = top + [0, 0, 0.9]
        c = centre + rng.normal(size=(300, 3)) * [0.6, 0.6, 0.45]
        a = rng.normal(size=(300, 3))
        a /= np.linalg.norm(a, axis=1, keepdims=True)
        b = np.cross(a, rng.normal(size=(300, 3)))
        b /= np.linalg.norm(b, axis=1, keepdims=True)
        a, b = 0.18 * a, 0.18 * b
        quad = np.stack([c - a - b, c + a - b, c + a + b, c - a + b], 1).reshape(-1, 3)
        nrm = np.repeat(np.cross(a, b) / np.linalg.norm(np.cross(a, b), axis=1, keepdims=True), 4, 0)
        uvq = np.tile([[0, 0], [1, 0], [1, 1], [0, 1]], (300, 1)) * 0.5 + np.repeat(
            rng.integers(0, 2, (300, 2)) * 0.5, 4, 0
        )
        q = np.arange(300)[:, None] * 4
        leaves.add(quad, nrm, uvq, np.concatenate([q + [0, 1, 2], q + [0, 2, 3]]), SemanticClass.CANOPY)
        for f in centre + rng.normal(size=(8, 3)) * [0.5, 0.5, 0.35]:
            fruit.add(*_cylinder(f - [0, 0, 0.04], f + [0, 0, 0.04], 0.04, 8), SemanticClass.FRUIT)

    textures = {
        "grass": _noise_texture(rng, 512, (90, 120, 60), 25),
        "bark": _noise_texture(rng, 256, (100, 75, 50), 20),
        "leaf": _leaf_texture(rng),
        "fruit": _noise_texture(rng, 64, (200, 40, 40), 15),
    }
    parts = [
        ground.part("ground", "grass"),
        wood.part("wood", "bark"),
        leaves.part("leaves", "leaf", True),
        fruit.part("fruit", "fruit"),
    ]
    return Scene(
        name=f"synthetic_{n_triangles}",
        seed=seed,
        parts=parts,
        textures=textures,
        collision=CollisionModel(np.ones((2, 2, 2)), np.zeros(3), 1.0),
        spawn_position=np.array([-2.0, 2.0, 0.0]),
        spawn_yaw=0.0,
        bounds_min=np.array([-5.0, -5.0, 0.0]),
        bounds_max=np.array([size_x - 5, size_y - 5, 10.0]),
    )


# --------------------------------------------------------------------------- benchmark
def flight(scene: Scene, n_frames: int) -> list[np.ndarray]:
    """Body poses along x across the scene at the spawn point's y, 2.5 m up, gently weaving in yaw
    (for the synthetic orchard this is the lane between the first two rows)."""
    lo, hi = scene.bounds_min, scene.bounds_max
    poses = []
    for i in range(n_frames):
        s = i / max(n_frames - 1, 1)
        x = lo[0] + (0.1 + 0.8 * s) * (hi[0] - lo[0])
        q = frames.quat_from_euler(0.0, 0.05, 0.3 * math.sin(4 * math.pi * s))
        poses.append(frames.transform_from_pose(np.array([x, scene.spawn_position[1], 2.5]), q))
    return poses


def _cpu_seconds() -> float:
    """CPU time of this process, all threads (llvmpipe rasterises on worker threads)."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def run_pass(renderer: Renderer, poses: list[np.ndarray], rgb: bool) -> tuple[float, float]:
    """Wall and CPU milliseconds per frame of full ``render`` calls (draw and readback) over ``poses``."""
    t0, c0 = time.perf_counter(), _cpu_seconds()
    for T in poses:
        renderer.render(T, rgb=rgb)
    return 1000 * (time.perf_counter() - t0) / len(poses), 1000 * (_cpu_seconds() - c0) / len(poses)


def profile(renderer: Renderer, poses: list[np.ndarray]) -> dict[str, float]:
    """Milliseconds per frame: draw calls issued (vertex work on llvmpipe), rasterisation until
    glFinish, then each readback. Uses the renderer's private per-camera steps that ``render`` chains.
    """
    t = renderer.targets[0]
    names = ("submit", "raster", "read_rgb", "read_seg", "read_depth")
    times = dict.fromkeys(names, 0.0)
    renderer.ctx.__enter__()
    for T in poses:
        stamps = [time.perf_counter()]
        renderer._draw(t, T, rgb=True)
        stamps.append(time.perf_counter())
        renderer.ctx.finish()
        stamps.append(time.perf_counter())
        t.fbo_color.read_into(t.rgb, components=3, attachment=0)
        stamps.append(time.perf_counter())
        t.fbo_color.read_into(t.seg, components=1, attachment=1, dtype="u1")
        stamps.append(time.perf_counter())
        t.fbo_color.read_into(t.depth, components=1, attachment=2, dtype="f4")
        stamps.append(time.perf_counter())
        for k, t0, t1 in zip(names, stamps[:-1], stamps[1:], strict=True):
            times[k] += 1000 * (t1 - t0) / len(poses)
    renderer.ctx.__exit__(None, None, None)
    return times


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--scene", default="orchard", help="scene name for droneulator.scenes.get_scene (default orchard)"
    )
    ap.add_argument(
        "--synthetic",
        type=int,
        metavar="N_TRIANGLES",
        help="use a generated orchard of about N triangles instead of --scene",
    )
    ap.add_argument("--frames", type=int, default=120, help="frames in the flight (default 120)")
    ap.add_argument("--repeats", type=int, default=3, help="flights per mode, interleaved (default 3)")
    ap.add_argument("--width", type=int, default=640, help="image width, pixels (default 640)")
    ap.add_argument("--height", type=int, default=480, help="image height, pixels (default 480)")
    ap.add_argument("--hfov", type=float, default=90.0, help="horizontal field of view, degrees (default 90)")
    ap.add_argument("--shadow-map-size", type=int, default=2048, help="texels a side (default 2048)")
    ap.add_argument(
        "--output", type=Path, default=OUTPUT, help="JSON results (default benchmarks/results/render.json)"
    )
    args = ap.parse_args()

    if args.synthetic:
        scene = synthetic_orchard(args.synthetic)
    else:
        from droneulator.scenes import get_scene

        scene = get_scene(args.scene)
    cam = CameraConfig(width=args.width, height=args.height, hfov_deg=args.hfov, rpy_deg=(0.0, 15.0, 0.0))
    poses = flight(scene, args.frames)
    results: dict[str, object] = {
        "scene": scene.name,
        "triangles": scene.triangle_count,
        "frames": args.frames,
        "resolution": [args.width, args.height],
        "LP_NUM_THREADS": os.environ.get("LP_NUM_THREADS"),
        "modes": {},
    }
    modes = {"shadows_on": (True, True), "shadows_off": (False, True), "depth_seg_only": (False, False)}
    renderers: dict[bool, Renderer] = {}
    for shadows in (True, False):
        t0 = time.perf_counter()
        renderers[shadows] = Renderer(scene, [cam], shadows=shadows, shadow_map_size=args.shadow_map_size)
        results[f"setup_s_shadows_{'on' if shadows else 'off'}"] = time.perf_counter() - t0
    with renderers[True].ctx:
        results["gl_renderer"] = renderers[True].ctx.info["GL_RENDERER"]
    samples: dict[str, list[tuple[float, float]]] = {name: [] for name in modes}
    for shadows, rgb in modes.values():  # warm up: shader compilation, first-touch allocations
        run_pass(renderers[shadows], poses[:3], rgb)
    for _ in range(args.repeats):  # interleaved, so that load from other processes hits every mode alike
        for name, (shadows, rgb) in modes.items():
            samples[name].append(run_pass(renderers[shadows], poses, rgb))
    for name, runs in samples.items():
        wall = sorted(w for w, _ in runs)
        res = {
            "fps_median": 1000 / float(np.median(wall)),
            "fps_best": 1000 / wall[0],
            "ms_per_frame_median": float(np.median(wall)),
            "cpu_ms_per_frame_median": float(np.median([c for _, c in runs])),
        }
        results["modes"][name] = res
        print(
            f"{name:15s} {res['fps_median']:6.1f} fps median, {res['fps_best']:6.1f} best "
            f"({res['ms_per_frame_median']:.1f} ms/frame, {res['cpu_ms_per_frame_median']:.1f} CPU ms/frame)"
        )
    prof = profile(renderers[True], poses[: min(len(poses), 30)])
    results["profile_shadows_on_ms"] = prof
    print("shadows_on split (ms/frame): " + ", ".join(f"{k} {v:.2f}" for k, v in prof.items()))
    for r in renderers.values():
        r.close()
    write("render", results, str(args.output))


if __name__ == "__main__":
    main()
