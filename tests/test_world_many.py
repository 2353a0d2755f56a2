"""One World over (worlds, vehicles): many worlds step as each would alone, reset by mask, and only the
vehicles of one world see each other's wakes and bodies."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from droneulator.config import fleet, load_config
from droneulator.state import STATE
from droneulator.world import World


def _config(vehicles: int):
    cfg = load_config(scene="vineyard", overrides=["render.camera_hz=30"])
    cfg.vehicles = fleet(vehicles)
    return cfg


STARTS = np.array([[[-8.0, 0.0, 1.5], [-8.0, 3.0, 1.5]],
                   [[-6.0, -3.0, 1.8], [-6.0, 0.0, 1.2]],
                   [[-8.0, -6.0, 1.5], [-4.0, -6.0, 1.5]]])  # fmt: skip
YAWS = np.array([[0.0, 0.3], [0.1, -0.2], [0.0, np.pi]])
COMMANDS = np.array([[[1.5, 0.2], [1.0, -0.3]], [[2.0, 0.0], [0.5, 0.4]], [[1.0, 0.0], [1.0, 0.0]]])


def test_many_worlds_step_exactly_as_each_world_alone():
    many = World(_config(2), render=False, worlds=3)
    many.place(None, STARTS, YAWS)
    many.velocity(None, COMMANDS[..., 0], COMMANDS[..., 1])
    alone = []
    for w in range(3):
        one = World(_config(2), render=False, worlds=1)
        one.place([0], STARTS[w][None], YAWS[w][None])
        one.velocity([0], COMMANDS[w, :, 0][None], COMMANDS[w, :, 1][None])
        alone.append(one)
    met = np.full((3, 2), -1)
    for _ in range(75):
        cams, hit = many.step_frame()
        met = np.maximum(met, many.touched)
        for w, one in enumerate(alone):
            c, h = one.step_frame()
            np.testing.assert_array_equal(cams[w], c[0])
            np.testing.assert_array_equal(hit[w], h[0])
            np.testing.assert_array_equal(many.touched[w], one.touched[0])
    assert np.array_equal(many.frame_t_ns(), np.full(3, alone[0].frame_t_ns()[0]))
    # they flew: every vehicle moved off its start, and world 2's head-on pair met and stopped each other
    assert (np.linalg.norm(many.states[:, :, 0:2] - STARTS[:, :, 0:2], axis=2) > 0.5).all()
    assert met[2].tolist() == [1, 0] and not many.active[2].any() and (met[:2] == -1).all()


def test_a_world_restarted_by_mask_leaves_the_others_untouched():
    a, b = (World(_config(2), render=False, worlds=3) for _ in range(2))
    for w in (a, b):
        w.place(None, STARTS, YAWS)
        w.velocity(None, COMMANDS[..., 0], COMMANDS[..., 1])
        for _ in range(10):
            w.step_frame()
    a.place([1], STARTS[1][None] + [1.0, 0.0, 0.0], YAWS[1][None])  # world 1 starts over, elsewhere
    assert a.frame_t_ns()[1] == 0 and a.frame_t_ns()[0] == b.frame_t_ns()[0] > 0
    for _ in range(12):
        a.step_frame()
        b.step_frame()
    np.testing.assert_array_equal(a.states[[0, 2]], b.states[[0, 2]])
    np.testing.assert_allclose(a.states[1, :, 0:3], STARTS[1] + [1.0, 0.0, 0.0], atol=0.05)  # holding
    assert a.frame_t_ns()[1] == 12 * a.camera_period_ns
    # run=False worlds do not move at all
    before = a.states.copy()
    a.step_frame(np.array([True, False, True]))
    np.testing.assert_array_equal(a.states[1], before[1])


def test_only_vehicles_of_one_world_feel_each_others_wakes_and_bodies():
    cfg = _config(1)
    w = World(cfg, render=False, worlds=2)
    # one vehicle per world, one straight above the other's spot: no wake crosses worlds
    w.place(None, [[[-8.0, 0.0, 3.0]], [[-8.0, 0.0, 1.5]]], [[0.0], [0.0]])
    for _ in range(10):
        w.step_frame()
    np.testing.assert_array_equal(w.states[:, 0, STATE.wind], 0.0)
    # the same two in one world: the lower one feels the wake
    two = World(_config(2), render=False, worlds=1)
    two.place([0], [[[-8.0, 0.0, 3.0], [-8.0, 0.0, 1.5]]], [[0.0, 0.0]])
    for _ in range(10):
        two.step_frame()
    assert two.states[0, 1, STATE.wind][2] < -0.5 and np.allclose(two.states[0, 0, STATE.wind], 0.0)
    # bodies: two vehicles at one spot in different worlds fly through each other
    w.place(None, [[[-8.0, 0.0, 1.5]], [[-8.0, 0.0, 1.5]]], [[0.0], [0.0]])
    w.velocity(None, [[1.0], [1.0]], [[0.0], [0.0]])
    for _ in range(10):
        w.step_frame()
    assert (w.touched == -1).all() and w.active.all()


def test_scene_variants_per_world_collide_with_their_own_scene():
    from droneulator.scenes import get_scene

    w = World(_config(1), render=False, worlds=2)
    empty = w.add_scene(get_scene("default", 0, 1.0))
    # both fly into the vine row beside the alley; world 1 flies the default (empty) scene
    w.place(None, [[[-8.0, 0.0, 1.5]], [[-8.0, 0.0, 1.5]]], [[np.pi / 2], [np.pi / 2]], variant=[0, empty])
    w.velocity(None, [[2.0], [2.0]], [[0.0], [0.0]])
    hits = np.zeros((2, 1), dtype=bool)
    for _ in range(60):
        _, hit = w.step_frame()
        hits |= hit
    assert hits[:, 0].tolist() == [True, False]
    assert w.states[1, 0, 1] > 2.5  # world 1 flew on across where the row stands in world 0


def test_retired_rows_are_not_flown_touched_or_blowing():
    two = World(_config(2), render=False, worlds=1)
    two.place([0], [[[-8.0, 0.0, 3.0], [-8.0, 0.0, 1.5]]], [[0.0, 0.0]])
    two.retire([0], [0])
    for _ in range(10):
        two.step_frame()
    np.testing.assert_array_equal(two.states[0, 0, 0:3], [-8.0, 0.0, 3.0])
    np.testing.assert_allclose(two.states[0, 1, STATE.wind], 0.0)
    with pytest.raises(ValueError, match="retired"):
        two.velocity_rows([0], [0], [1.0], [0.0])


def test_bad_batched_input_is_a_clear_error_and_the_world_goes_on():
    w = World(_config(2), render=False, worlds=2)
    w.place(None, STARTS[:2], YAWS[:2])
    for bad, match in (
        (lambda: World(_config(1), render=False, worlds=0), "worlds must be"),
        (lambda: w.place([5], STARTS[:1], YAWS[:1]), "world indices"),
        (lambda: w.place(None, STARTS[:1], YAWS[:1]), "positions needs"),
        (lambda: w.place(None, STARTS[:2] * np.nan, YAWS[:2]), "finite"),
        (lambda: w.place(None, STARTS[:2], YAWS[:2], variant=3), "scene variants"),
        (lambda: w.velocity(None, [[99.0, 0.0], [0.0, 0.0]], np.zeros((2, 2))), "forward"),
        (lambda: w.velocity_rows([0], [2], [1.0], [0.0]), "rows must lie"),
        (lambda: w.step_frame(np.ones(3, dtype=bool)), "run must be"),
        (lambda: w.step(), "step_frame"),
    ):
        with pytest.raises(ValueError if match != "step_frame" else RuntimeError, match=match):
            bad()
    w.velocity(None, np.ones((2, 2)), np.zeros((2, 2)))
    w.step_frame()
    assert w.frame_t_ns().tolist() == [w.camera_period_ns] * 2


_PARALLEL_WORLD = """
import numpy as np
from droneulator.config import load_config
from droneulator.vehicles.dynamics import PARALLEL_ROWS
from droneulator.world import World

cfg = load_config(scene="default")
cfg.vehicle.wind = "none"
world = World(cfg, render=False, worlds=PARALLEL_ROWS)
world.step_frame(np.ones(PARALLEL_ROWS, dtype=bool))
print("stepped", world.states.shape[0])
"""

#: one world of PARALLEL_ROWS vehicles stepped by its flight controllers: the parallel period kernel called
#: from Python (and so cached), ``step_to_frame`` not compiled
_PARALLEL_FLEET = """
from droneulator.config import fleet, load_config
from droneulator.vehicles.dynamics import PARALLEL_ROWS
from droneulator.world import World

cfg = load_config(scene="default")
cfg.vehicles = fleet(PARALLEL_ROWS)
world = World(cfg, render=False)
world.step(2)
print("stepped", world.states.shape[1])
"""


@pytest.mark.parametrize(
    ("given", "expected"),
    [
        (None, ["OMP_WAIT_POLICY = 'PASSIVE'", "GOMP_SPINCOUNT = '0'"]),
        ("ACTIVE", ["OMP_WAIT_POLICY = 'ACTIVE'"]),
    ],
)
def test_the_parallel_physics_threads_sleep_between_regions_unless_told(
    given: str | None, expected: list[str]
) -> None:
    """Importing the package makes libgomp's threads (numba's OpenMP layer, the many-world physics and the
    ray cast) wait passively: spinning threads took the cores a loaded machine needed (docs/rl.md). libgomp
    itself reports its setting (``OMP_DISPLAY_ENV``) once a parallel world step loads it (unset, it spins
    300,000 times before it sleeps, and reports that as ``GOMP_SPINCOUNT``); a value in the environment wins.
    """
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"} | {"OMP_DISPLAY_ENV": "VERBOSE"}
    if given is not None:
        env["OMP_WAIT_POLICY"] = given
    done = subprocess.run([sys.executable, "-c", _PARALLEL_WORLD], env=env, capture_output=True, text=True,
                          timeout=600)  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    assert "stepped" in done.stdout
    for line in expected:
        assert line in done.stderr, done.stderr[-2000:]


def _seed_cache_but_the_step(cache: Path) -> None:
    """Copy the package's in-tree kernel cache (``droneulator compile`` fills it at setup) to where numba
    looks under ``NUMBA_CACHE_DIR=cache``, all but ``world/step.py``'s kernels: the controllers and the
    dynamics load as in any run, and only the step's kernels are compiled afresh, as in the race (each of
    the three processes compiled everything from nothing before: 55 s for this test alone, now 29 s)."""
    import shutil

    from numba.core.caching import _CacheLocator

    import droneulator

    for pycache in Path(droneulator.__file__).parent.rglob("__pycache__"):
        into = cache / _CacheLocator.get_suitable_cache_subpath(str(pycache.parent / "module.py"))
        for kernel in pycache.iterdir():
            if kernel.suffix not in (".nbi", ".nbc"):
                continue
            if pycache.parent.name == "world" and kernel.name.startswith("step."):
                continue
            into.mkdir(parents=True, exist_ok=True)
            shutil.copy2(kernel, into / kernel.name)


def test_a_cached_step_compiled_against_a_cached_parallel_kernel_runs_in_the_next_process(tmp_path):
    """The race two test workers ran on a fresh clone: one process caches the parallel period kernel, the
    next compiles (and caches) ``step_to_frame``, which calls it, while it is in the cache, and the third
    loads ``step_to_frame`` and steps. Numba cached the second's ``step_to_frame`` broken and the third
    segfaulted (every time, in any later process) until ``step_to_frame`` called a dispatcher of the
    kernel compiled in its own process (``world/step.py``)."""
    import os
    import subprocess
    import sys

    env = os.environ | {"NUMBA_CACHE_DIR": str(tmp_path), "PYTHONFAULTHANDLER": "1"}
    _seed_cache_but_the_step(tmp_path)

    def run(code: str) -> None:
        cmd = [sys.executable, "-c", code]
        done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=900)
        assert done.returncode == 0, done.stderr[-3000:]
        assert "stepped" in done.stdout

    run(_PARALLEL_FLEET)  # caches the period kernel
    assert list(tmp_path.glob("world_*/step.run_period_parallel-*.nbc"))
    assert not list(tmp_path.glob("world_*/step.step_to_frame-*"))
    run(_PARALLEL_WORLD)  # compiles step_to_frame with the kernel in the cache, and caches it
    assert list(tmp_path.glob("world_*/step.step_to_frame-*.nbc"))
    run(_PARALLEL_WORLD)  # loads it
