"""Scene registry: procedural, seeded scenes built on demand and cached per (name, seed).

Builders are plain functions ``(seed: int) -> Scene`` decorated with :func:`register`. The scene
modules are imported lazily on the first registry query, so importing :mod:`droneulator.scenes.base`
alone stays cheap (no numba, no texture generation).
"""

from __future__ import annotations

import functools
import importlib
from collections.abc import Callable

import numpy as np

from droneulator.scenes.base import MeshPart, Scene

SceneBuilder = Callable[[int], Scene]

_SCENE_MODULES = ("default", "orchard", "planning", "tree_inspection", "vineyard")
_REGISTRY: dict[str, tuple[str, SceneBuilder]] = {}

#: minimum horizontal clearance (metres) between a spawn point and any obstacle
SPAWN_CLEARANCE = 3.0


def register(name: str, description: str) -> Callable[[SceneBuilder], SceneBuilder]:
    """Decorator adding a scene builder under ``name`` with a one-line ``description``."""

    def deco(fn: SceneBuilder) -> SceneBuilder:
        if name in _REGISTRY and _REGISTRY[name][1] is not fn:
            raise ValueError(f"scene {name!r} registered twice")
        _REGISTRY[name] = (description, fn)
        return fn

    return deco


def _load() -> None:
    for mod in _SCENE_MODULES:
        importlib.import_module(f"droneulator.scenes.{mod}")


def list_scenes() -> dict[str, str]:
    """Registered scene names and their descriptions."""
    _load()
    return {name: desc for name, (desc, _fn) in sorted(_REGISTRY.items())}


@functools.lru_cache(maxsize=16)
def _build(name: str, seed: int) -> Scene:
    return _REGISTRY[name][1](seed)


def get_scene(name: str, seed: int = 0) -> Scene:
    """The scene ``name`` built with ``seed`` (cached: repeated calls return the same object)."""
    _load()
    if name not in _REGISTRY:
        raise ValueError(f"unknown scene {name!r}; known scenes: {', '.join(sorted(_REGISTRY))}")
    return _build(name, int(seed))


def assemble_scene(
    name: str,
    seed: int,
    parts: list[MeshPart],
    primitives: list,
    spawn_position: np.ndarray,
    spawn_yaw: float,
    bounds_min: np.ndarray,
    bounds_max: np.ndarray,
    landmarks: dict[str, np.ndarray] | None = None,
) -> Scene:
    """Common tail of every builder: textures for the parts, collision grid, spawn sanity check."""
    from droneulator.scenes.collision import build_collision, primitive_distance
    from droneulator.scenes.textures import textures_for

    spawn = np.asarray(spawn_position, dtype=float)
    column = spawn + np.array([[0.0, 0.0, z] for z in np.linspace(0.0, 4.0, 9)])
    clear = float(primitive_distance(primitives, column).min()) if primitives else np.inf
    if clear < SPAWN_CLEARANCE:
        raise RuntimeError(f"scene {name!r}: spawn {spawn} is only {clear:.2f} m from an obstacle")
    return Scene(
        name=name,
        seed=seed,
        parts=parts,
        textures=textures_for({p.texture for p in parts}),
        collision=build_collision(primitives, bounds_min, bounds_max),
        spawn_position=spawn,
        spawn_yaw=float(spawn_yaw),
        bounds_min=np.asarray(bounds_min, dtype=float),
        bounds_max=np.asarray(bounds_max, dtype=float),
        landmarks=landmarks or {},
    )
