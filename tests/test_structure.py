"""Package structure: no import circles, the sensor registry, named state fields, lazy Gym registration."""

from __future__ import annotations

import ast
import functools
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from rotorpy.vehicles.multirotor import Multirotor

from droneulator.config import PX4Config
from droneulator.sensors import SENSORS, SensorSuite, Truth, get_sensor
from droneulator.vehicles.dynamics import STATE, STATE_SIZE, pack_state, unpack_state

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "droneulator"


def _fresh(code: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True, timeout=300
    )


def _import_graph() -> dict[str, set[str]]:
    """Module -> droneulator modules it imports anywhere in its source (lazy imports included)."""
    mods = {}
    for f in PACKAGE.rglob("*.py"):
        name = ".".join(f.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
        mods[name] = f
    graph: dict[str, set[str]] = {}
    for name, f in mods.items():
        deps: set[str] = set()
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module, *(f"{node.module}.{a.name}" for a in node.names)]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            else:
                continue
            deps |= {m for m in names if m in mods and m != name}
        graph[name] = deps
    return graph


def _reaches(graph: dict[str, set[str]], start: str, goal: str) -> bool:
    seen, todo = set(), [start]
    while todo:
        m = todo.pop()
        if m == goal:
            return True
        if m not in seen:
            seen.add(m)
            todo.extend(graph[m])
    return False


@pytest.mark.parametrize(
    ("a", "b"),
    [
        ("droneulator.scenes.base", "droneulator.scenes.collision"),
        ("droneulator.workflows.rl.env", "droneulator.workflows.rl.remote"),
        ("droneulator.frames", "droneulator.vehicles.dynamics"),
        ("droneulator.sensors.registry", "droneulator.sensors"),
        ("droneulator.ros", "droneulator.ros.zenoh_node"),
    ],
)
def test_no_import_circle(a: str, b: str) -> None:
    graph = _import_graph()
    assert not (_reaches(graph, a, b) and _reaches(graph, b, a)), f"{a} and {b} import each other"


#: the package's layers, bottom up (docs/architecture.md): a module may import its own layer and those
#: below, never one above, not even lazily or for type checking
LAYERS: dict[str, int] = {
    "frames": 0, "frames_numba": 0, "state": 0, "config": 0, "logs": 0, "threads": 0,
    "scenes": 1, "wind": 1, "trajectories": 1, "sensors": 1, "commands": 1,
    "controllers": 2,
    "vehicles": 3,
    "world": 4, "render": 4, "imaging": 4, "spray": 4,
    "api": 5, "ros": 5, "px4": 5, "ardupilot": 5, "recording": 5,
    "runtime": 6, "ui": 6,
    "workflows": 7,
    "cli": 8, "warmup": 8, "": 8,
}  # fmt: skip


def _layer(module: str) -> int:
    top = module.split(".")[1] if "." in module else ""
    assert top in LAYERS, f"{module}: its package {top!r} has no layer in LAYERS"
    return LAYERS[top]


def test_no_module_imports_a_layer_above_its_own() -> None:
    upward = sorted(
        f"{m} (layer {_layer(m)}) imports {d} (layer {_layer(d)})"
        for m, deps in _import_graph().items()
        for d in deps
        if d != "droneulator" and _layer(d) > _layer(m)  # `from droneulator import frames` names the module
    )
    assert not upward, "\n".join(upward)


@pytest.mark.parametrize(
    "module",
    [
        "droneulator.scenes.collision",
        "droneulator.scenes.base",
        "droneulator.workflows.rl.remote",
        "droneulator.workflows.rl.env",
        "droneulator.sensors.camera",
        "droneulator.px4.link",
    ],
)
def test_module_imports_first_in_a_fresh_interpreter(module: str) -> None:
    r = _fresh(f"import {module}")
    assert r.returncode == 0, r.stderr


def test_the_simulators_processes_do_not_import_torch() -> None:
    """torch is installed here (the rl extra), and RotorPy's modules import it when it is: 4 s and 250 MB
    in every simulator process, for batched classes the simulator does not use. A flight works without."""
    code = """
import sys
import droneulator.runtime.dynamics_server, droneulator.runtime.render_server, droneulator.runtime.bridge
from droneulator.world import World
world = World(render=False)
world.vehicle().takeoff(1.0)
world.step(50)
assert "torch" not in sys.modules and "roma" not in sys.modules, "torch was imported"
import torch  # and it is still importable afterwards
"""
    r = _fresh(code)
    assert r.returncode == 0, r.stderr


def test_gym_make_after_plain_import_droneulator() -> None:
    code = """
import sys
import droneulator
import gymnasium as gym
ID = "droneulator/VineyardNav-v0"
spec = gym.spec(ID)
assert spec.entry_point == "droneulator.workflows.rl.env:VineyardNavEnv", spec.entry_point
lazy = [m for m in ("droneulator.workflows.rl.env", "torch", "moderngl") if m in sys.modules]
assert not lazy, f"registering imported {lazy}"
env = gym.make(ID)
obs, _ = env.reset(seed=0)
assert obs.shape == (35,), obs.shape
env.close()
print("ok")
"""
    r = _fresh(code)
    assert r.returncode == 0 and r.stdout.strip().endswith("ok"), r.stderr


def test_import_droneulator_without_gymnasium_registers_nothing() -> None:
    """A blocked gymnasium stands in for an install without the rl extra."""
    r = _fresh(
        "import sys; sys.modules['gymnasium'] = None\n"
        "import importlib.util, droneulator\n"
        "assert 'droneulator.workflows.rl.env' not in sys.modules and 'torch' not in sys.modules\n"
        "from droneulator.workflows.rl import register_envs\n"
        "assert register_envs() is False\n"
        "print('ok')"
    )
    assert r.returncode == 0 and r.stdout.strip() == "ok", r.stderr


def test_cli_command_modules_import_no_other_command() -> None:
    """Of droneulator/cli/, a command module imports only common.py (what several commands share)."""
    graph = _import_graph()
    cli = [m for m in graph if m.startswith("droneulator.cli.")]
    commands = [m for m in cli if not m.endswith((".common", ".__main__"))]
    assert len(commands) >= 14, commands
    wrong = {
        m: sorted(d for d in graph[m] if d.startswith("droneulator.cli") and d != "droneulator.cli.common")
        for m in commands
    }
    assert not any(wrong.values()), {m: d for m, d in wrong.items() if d}


def test_cli_help_imports_no_simulator() -> None:
    """Every ``--help`` of the command line is built without numba, the renderer, torch or the simulator."""
    r = _fresh(
        "import argparse, sys\n"
        "from droneulator.cli import build_parser\n"
        "ap = build_parser()\n"
        "sub = next(a for a in ap._actions if isinstance(a, argparse._SubParsersAction))\n"
        "for p in (ap, *sub.choices.values()):\n"
        "    p.format_help()\n"
        "heavy = ('numba', 'moderngl', 'torch', 'rotorpy', 'droneulator.world', 'droneulator.vehicles')\n"
        "print(sorted(m for m in heavy if m in sys.modules))"
    )
    assert r.returncode == 0 and r.stdout.strip() == "[]", r.stderr or r.stdout


# --------------------------------------------------------------------------- sensors
def test_every_sensor_kind_is_registered_and_unknown_kinds_are_named() -> None:
    assert {"imu", "mag", "baro", "gps", "airspeed", "camera"} <= set(SENSORS)
    assert all(get_sensor(k).kind == k for k in SENSORS)
    with pytest.raises(ValueError, match="unknown sensor kind 'lidar'; registered: .*imu"):
        get_sensor("lidar")


def test_each_sensor_draws_its_own_noise_stream() -> None:
    """Sampling the IMU more often leaves the GPS noise of the same seed unchanged."""
    z3 = np.zeros(3)
    truth = Truth(0, z3, z3, np.array([0.0, 0.0, 0.0, 1.0]), z3, z3, z3)
    a, b = SensorSuite(PX4Config(), seed=3), SensorSuite(PX4Config(), seed=3)
    for _ in range(5):
        b.imu(truth)
    ga, gb = a.gps(truth), b.gps(truth)
    assert (ga.lat_deg, ga.lon_deg, ga.alt_msl_m) == (gb.lat_deg, gb.lon_deg, gb.alt_msl_m)
    assert np.array_equal(ga.vel_ned, gb.vel_ned)
    assert not np.array_equal(a.imu(truth)[0], b.imu(truth)[0])


# --------------------------------------------------------------------------- state layout
def test_state_layout_is_rotorpys_packing() -> None:
    r = np.random.default_rng(1)
    st = {
        "x": r.normal(size=3),
        "v": r.normal(size=3),
        "q": r.normal(size=4),
        "w": r.normal(size=3),
        "wind": r.normal(size=3),
        "rotor_speeds": r.normal(size=4),
    }
    s = pack_state(st)
    assert STATE_SIZE == 20 and s.shape == (STATE_SIZE,)
    np.testing.assert_array_equal(s, Multirotor._pack_state(st))
    for name in STATE.names:
        np.testing.assert_array_equal(s[getattr(STATE, name)], st[name])
        np.testing.assert_array_equal(unpack_state(s)[name], st[name])


def test_no_raw_state_slices_outside_vehicles() -> None:
    """``s[13:16]``-style slices of the packed state are written only in droneulator/vehicles/."""
    import re

    raw = re.compile(r"\bs\[(0:3|3:6|6:10|10:13|13:16|16:20)\]")
    offenders = [
        f"{f.relative_to(ROOT)}:{i}"
        for f in PACKAGE.rglob("*.py")
        if "vehicles" not in f.parts
        for i, line in enumerate(f.read_text().splitlines(), 1)
        if raw.search(line)
    ]
    assert offenders == []


def _calls(module_file: Path) -> set[str]:
    """The names a module calls: ``f(...)`` gives ``f``, ``x.f(...)`` gives ``.f``."""
    out: set[str] = set()
    for node in ast.walk(ast.parse(module_file.read_text())):
        if isinstance(node, ast.Call):
            if isinstance(node.func, ast.Name):
                out.add(node.func.id)
            elif isinstance(node.func, ast.Attribute):
                out.add("." + node.func.attr)
    return out


@functools.cache
def _package_calls() -> dict[str, frozenset[str]]:
    """Package module (path under droneulator/) -> the names it calls."""
    return {str(f.relative_to(PACKAGE)): frozenset(_calls(f)) for f in PACKAGE.rglob("*.py")}


def _callers(names: set[str]) -> dict[str, set[str]]:
    """Package module (path under droneulator/) -> which of ``names`` it calls."""
    return {m: set(calls & names) for m, calls in _package_calls().items() if calls & names}


def test_only_the_camera_pipeline_draws_cameras() -> None:
    """One camera pipeline (render/pipeline.py): nothing else builds a camera renderer or ray caster or
    draws a camera; the UI's scene map (a top-down view, no camera) builds a bare renderer."""
    draws = _callers({".render_rigs", "fleet_renderer", "DepthCaster", "Renderer"})
    assert draws.pop("render/pipeline.py") >= {".render_rigs", "fleet_renderer", "DepthCaster"}
    assert draws.pop("render/renderer.py") == {".render_rigs", "Renderer"}  # render() and fleet_renderer
    assert draws.pop("ui/scenes.py") == {"Renderer"}
    assert ".render_top_down" in _calls(PACKAGE / "ui/scenes.py")
    assert not draws, draws


def test_only_the_world_calls_the_physics_kernel() -> None:
    """The compiled physics step (vehicles/dynamics.py) is called by the world's step alone, and the world's
    step by the world alone: one stepper."""
    callers = {m for m in _callers({"integrate", "state_derivative"}) if m != "vehicles/dynamics.py"}
    assert callers == {"world/step.py"}, callers
    steps = {"step_to_frame", "run_period_serial", "run_period_parallel", "end_period"}
    steps |= {f".{name}" for name in steps}
    assert {m for m in _callers(steps) if m != "world/step.py"} == {"world/world.py"}


def test_no_parallel_loop_passes_its_bare_index_to_a_compiled_function() -> None:
    """Numba types a ``prange`` index int64, then uint64 once the loop is parallelised, and compiles a
    function given the bare index once for each: the row kernels, the ray tracer and PatchMatch's plane cost
    compiled twice (about 4 s of the vector env's 53 s of cold compiling, measured); the loops pass
    ``np.int64(index)``."""
    bare = []
    for f in PACKAGE.rglob("*.py"):
        for loop in ast.walk(ast.parse(f.read_text())):
            if not (isinstance(loop, ast.For) and isinstance(loop.target, ast.Name)):
                continue
            if not (isinstance(loop.iter, ast.Call) and ast.unparse(loop.iter.func).endswith("prange")):
                continue
            for call in (n for stmt in loop.body for n in ast.walk(stmt) if isinstance(n, ast.Call)):
                if ast.unparse(call.func) == "np.int64":
                    continue
                if any(isinstance(a, ast.Name) and a.id == loop.target.id for a in call.args):
                    bare.append(f"{f.relative_to(PACKAGE)}:{call.lineno} {ast.unparse(call.func)}")
    assert not bare, bare
