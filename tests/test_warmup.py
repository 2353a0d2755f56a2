"""``droneulator compile`` (scripts/setup.sh runs it): after it, a later process loads every kernel a run,
a learning env, the planner, the spray and dense stereo use from numba's cache and compiles none."""

from __future__ import annotations

import os
import subprocess
import sys

#: a later process using each part compiled ahead, as a run, a training or a test would
_LATER = """
import numpy as np
from droneulator.config import load_config
from droneulator.world import World
from droneulator.workflows.rl.vector import VineyardNavVectorEnv
from droneulator.workflows.planning.config import PlannerConfig
from droneulator.workflows.planning.mapping import LocalMap
from droneulator.workflows.planning.planner import Planner
from droneulator.warmup import _dense, _spray

w = World(load_config(scene="default"), render=False)
w.vehicle().goto([2.0, 1.0, 3.0])
w.step(10)
env = VineyardNavVectorEnv(num_envs=3, depth="raycast")
env.reset(seed=5)
env.step(np.full((3, 2), 0.5, dtype=np.float32))
cfg = PlannerConfig()
planner = Planner(cfg)
planner.map = LocalMap(cfg, centre=np.array([2.0, 0.0, 1.5]))
y, z = np.meshgrid(np.arange(-1.0, 1.0, 0.1), np.arange(0.0, 3.0, 0.1))
planner.map.insert_points(np.stack([np.full(y.size, 2.0), y.ravel(), z.ravel()], 1))
zero = np.zeros(3)
print("planned", planner.plan(np.array([0.0, 0.0, 1.5]), zero, zero, np.array([4.0, 0.3, 1.5])) is not None)
_spray()
_dense()
print("done")
"""


def test_after_compile_a_later_process_compiles_nothing() -> None:
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    done = subprocess.run([sys.executable, "-m", "droneulator.cli", "compile", "--no-progress"], env=env,
                          capture_output=True, text=True, timeout=900)  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    for part in ("learning envs", "world", "dense stereo", "spray", "planner"):
        assert part in done.stdout, done.stdout
    later = subprocess.run([sys.executable, "-c", _LATER], env=env | {"NUMBA_DEBUG_CACHE": "1"},
                           capture_output=True, text=True, timeout=900)  # fmt: skip
    assert later.returncode == 0 and "done" in later.stdout, later.stderr[-3000:]
    log = later.stdout + later.stderr
    saved = [line for line in log.splitlines() if "[cache] data saved" in line]
    assert saved == [], "\n".join(saved)
    loaded = {line.split("/")[-1] for line in log.splitlines() if "[cache] data loaded" in line}
    kernels = ("step.step_to_frame", "raycast.", "task._task_rows", "bspline._lbfgs", "kernel.", "patchmatch")
    for kernel in kernels:
        assert any(name.startswith(kernel) for name in loaded), (kernel, sorted(loaded))


def test_compile_refuses_no_jobs() -> None:
    done = subprocess.run([sys.executable, "-m", "droneulator.cli", "compile", "--jobs", "0"],
                          capture_output=True, text=True, timeout=120)  # fmt: skip
    assert done.returncode == 2 and "--jobs must be at least 1, got 0" in done.stderr, done.stderr
