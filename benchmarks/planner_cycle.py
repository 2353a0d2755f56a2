"""Planner cycle time (issue 11 target: replanning median <= 20 ms on the 2-core CPU).

Synthetic scene, no renderer: a vertical column (radius 0.3 m at x = 3 m) seen by a 640x480 depth
camera at the start, its depth image computed in closed form (ray/cylinder intersection, NaN where a
ray misses, so free space is cleared up to ``max_ray_length``). The map is built from depth alone
(``--frames`` updates, timed), then ``Planner.plan`` is timed from the start to five goals on the far
side of the column, from far left to far right (every straight line meets the inflated column), each
``--repeats`` times after a warm-up plan that compiles the numba code. Prints and writes median and
p99 of map update and plan times, and how many plans succeeded, to
``benchmarks/results/planner_cycle.json``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from _common import write

from droneulator.workflows.planning.config import PlannerConfig
from droneulator.workflows.planning.planner import Planner

COLUMN = np.array([3.0, 0.0])
COLUMN_R = 0.3
START = np.array([0.5, 0.0, 1.5])
GOALS = [np.array([5.5, y, 1.5]) for y in (-0.8, -0.4, 0.0, 0.4, 0.8)]
W, H, F = 640, 480, 320.0


def camera() -> tuple[np.ndarray, np.ndarray]:
    """Intrinsics and world-from-optical pose of a camera at START looking along world +x."""
    K = np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1.0]])
    T = np.eye(4)
    T[:3, :3] = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], dtype=float)  # optical x right, y down, z ahead
    T[:3, 3] = START
    return K, T


def column_depth(K: np.ndarray, T: np.ndarray) -> np.ndarray:
    """32FC1 depth (z along the optical axis, metres) of the column; NaN where the ray misses it."""
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1) @ T[:3, :3].T
    o = T[:2, 3] - COLUMN
    d = rays[..., :2]
    a, b, c = (d**2).sum(-1), 2 * (d @ o), o @ o - COLUMN_R**2
    disc = b**2 - 4 * a * c
    z = (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a)  # optical z = 1 along each ray
    return np.where((disc >= 0) & (z > 0), z, np.nan).astype(np.float32)


def stats(times: list[float]) -> dict[str, float]:
    ms = 1e3 * np.asarray(times)
    return {"median_ms": float(np.median(ms)), "p99_ms": float(np.percentile(ms, 99)),
            "max_ms": float(ms.max()), "n": int(ms.size)}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=30, help="timed depth-image map updates")
    ap.add_argument("--repeats", type=int, default=20, help="timed plans per goal")
    ap.add_argument("--out", default=None, help="JSON path (default benchmarks/results/planner_cycle.json)")
    args = ap.parse_args()
    if args.frames < 1 or args.repeats < 1:
        ap.error("--frames and --repeats must be >= 1")
    cfg = PlannerConfig()
    planner = Planner(cfg, centre=np.array([3.0, 0.0, 1.5]))
    K, T = camera()
    depth = column_depth(K, T)
    planner.update_map(depth, T, K)  # warm-up (compile)
    update_times = []
    for _ in range(args.frames):
        t0 = time.perf_counter()
        planner.update_map(depth, T, K)
        update_times.append(time.perf_counter() - t0)
    if not planner.map.is_occupied(np.array([COLUMN[0] - COLUMN_R, 0.0, 1.5])):
        raise RuntimeError("the column did not make it into the map: the synthetic depth is wrong")
    zero = np.zeros(3)
    planner.plan(START, zero, zero, GOALS[0])  # warm-up (compile)
    plan_times, ok = [], 0
    for _ in range(args.repeats):
        for goal in GOALS:
            t0 = time.perf_counter()
            traj = planner.plan(START, zero, zero, goal)
            plan_times.append(time.perf_counter() - t0)
            ok += traj is not None
    result = {"map_update": stats(update_times), "plan": stats(plan_times),
              "plans_ok": ok, "plans": len(plan_times), "target_plan_median_ms": 20.0}  # fmt: skip
    for name in ("map_update", "plan"):
        s = result[name]
        print(f"{name:10s} median {s['median_ms']:7.2f} ms  p99 {s['p99_ms']:7.2f} ms  (n={s['n']})")
    print(f"plans ok: {ok}/{len(plan_times)}")
    write("planner_cycle", result, args.out)


if __name__ == "__main__":
    main()
