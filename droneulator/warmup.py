"""Compile the simulator's numba kernels into numba's on-disk cache ahead of use (``droneulator compile``).

Each kernel is compiled the first time something calls it and then loaded from the cache (the
``__pycache__`` folders beside the sources) by every later process. On a fresh install that first time
falls on the first run, training or test: one to two minutes of a core (the learning envs' kernels alone
take about 75 s on this project's 2-core CI machine), which on a busy machine is a stall the user sees.
``scripts/setup.sh`` runs this once, so the cost is paid at install. Each job drives one part through its
public API with the types a real run uses, so what it compiles is what later runs load; a job whose
optional extra is not installed is skipped, and its kernels compile on first use as before.
"""

from __future__ import annotations

import importlib.util
import multiprocessing
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, as_completed

import numpy as np


def _world() -> None:
    """One vehicle flown by its controllers; a fleet whose wakes and bodies meet; many worlds in parallel."""
    from droneulator.config import fleet, load_config
    from droneulator.vehicles.dynamics import PARALLEL_ROWS
    from droneulator.world import World

    world = World(load_config(scene="default"), render=False)
    world.vehicle().takeoff(1.0)
    world.step(20)
    world.close()
    cfg = load_config(scene="vineyard", overrides=["render.camera_hz=30"])
    cfg.vehicles = fleet(2)
    pair = World(cfg, render=False, worlds=2)
    pair.place(None, np.array([[[-8.0, 0.0, 1.5], [-8.0, 0.5, 1.5]]] * 2), np.zeros((2, 2)))
    pair.velocity(None, np.ones((2, 2)), np.zeros((2, 2)))
    for _ in range(3):
        pair.step_frame()
    pair.close()
    cfg = load_config(scene="default")
    cfg.vehicles = fleet(PARALLEL_ROWS)
    many = World(cfg, render=False)
    many.step(2)
    many.close()


def _learning() -> None:
    """The vineyard task's vector env with its ray-cast depth (one agent a world, then two)."""
    from droneulator.workflows.rl.multi import VineyardMultiVectorEnv
    from droneulator.workflows.rl.vector import VineyardNavVectorEnv

    env = VineyardNavVectorEnv(num_envs=2, depth="raycast")
    env.reset(seed=0)
    for _ in range(3):
        env.step(np.zeros((2, 2), dtype=np.float32))
    env.close()
    multi = VineyardMultiVectorEnv(num_worlds=2, num_agents=2, depth="raycast")
    multi.reset(seed=0)
    for _ in range(3):
        multi.step(np.zeros((4, 2), dtype=np.float32))
    multi.close()


def _planning() -> None:
    """The local planner: a map of a column, a search round it and the B-spline optimised clear of it."""
    from droneulator.workflows.planning.config import PlannerConfig
    from droneulator.workflows.planning.mapping import LocalMap
    from droneulator.workflows.planning.planner import Planner

    cfg = PlannerConfig()
    planner = Planner(cfg)
    planner.map = LocalMap(cfg, centre=np.array([3.0, 0.0, 1.5]))
    a, z = np.meshgrid(np.linspace(0.0, 2.0 * np.pi, 60, endpoint=False), np.arange(0.0, 3.0, 0.1))
    planner.map.insert_points(np.stack([3.0 + 0.4 * np.cos(a), 0.4 * np.sin(a), z], -1).reshape(-1, 3))
    zero = np.zeros(3)
    planner.plan(np.array([0.5, 0.0, 1.5]), zero, zero, np.array([5.5, 0.0, 1.5]))


def _spray() -> None:
    """Droplet parcels released from a nozzle and carried down through still air."""
    from droneulator.config import SprayConfig, WeatherConfig, WindConfig
    from droneulator.spray.cloud import Domain, Emitter, SprayCloud

    cloud = SprayCloud(SprayConfig(), WeatherConfig(), WindConfig(), Domain(-5, 5, -5, 5, 5), seed=0)
    nozzle = cloud.config.nozzles[0]
    emitter = Emitter(np.array([0.0, 0.0, 3.0]), np.array([0, 0, 0, 1.0]), np.zeros(3), np.zeros((0, 8)),
                      [(nozzle, 1e-6)])  # fmt: skip
    cloud.release(emitter, 0.01)
    for _ in range(5):
        cloud.step([])


def _dense() -> None:
    """Dense stereo of ``droneulator reconstruct``: a plane sweep and PatchMatch on two small views."""
    from droneulator.workflows.photogrammetry.mvs import MvsOptions, View, plane_sweep
    from droneulator.workflows.photogrammetry.patchmatch import patchmatch_refine

    h, w = 24, 32
    K = np.array([[30.0, 0.0, (w - 1) / 2], [0.0, 30.0, (h - 1) / 2], [0.0, 0.0, 1.0]])
    gray = np.random.default_rng(0).random((h, w)).astype(np.float32)
    views = []
    for i, x in enumerate((-0.2, 0.2)):
        T = np.eye(4)
        T[0, 3] = x
        views.append(View(str(i), K, T, gray, np.repeat((gray[..., None] * 255).astype(np.uint8), 3, -1),
                          np.ones((h, w), bool)))  # fmt: skip
    plane_sweep(views[0], [views[1]], 2.0, 4.0, MvsOptions(neighbors=1, best_k=1))
    patchmatch_refine(views[0], [views[1]], np.full((h, w), np.nan, np.float32), 2.0, 4.0, iterations=1)


#: (name, the optional module it needs or None, the job), the longest first
JOBS: tuple[tuple[str, str | None, Callable[[], None]], ...] = (
    ("learning envs", "gymnasium", _learning),
    ("world", None, _world),
    ("dense stereo", "cv2", _dense),
    ("spray", None, _spray),
    ("planner", None, _planning),
)


def _run(job: Callable[[], None]) -> float:
    t = time.perf_counter()
    job()
    return time.perf_counter() - t


def warm(jobs: int = 2, progress: bool = True) -> dict[str, float]:
    """Run every job whose extra is installed, ``jobs`` processes at a time; returns each job's seconds."""
    from tqdm import tqdm

    todo = [(name, fn) for name, needs, fn in JOBS if needs is None or importlib.util.find_spec(needs)]
    done: dict[str, float] = {}
    # spawn: each job starts clean, as a later run does (no compiled state inherited from this process)
    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=max(1, jobs), mp_context=ctx) as pool, tqdm(
        total=len(todo), desc="compiling kernels", unit="part", disable=not progress
    ) as bar:
        futures = {pool.submit(_run, fn): name for name, fn in todo}
        for future in as_completed(futures):
            done[futures[future]] = future.result()
            bar.set_postfix_str(futures[future])
            bar.update()
    return done
