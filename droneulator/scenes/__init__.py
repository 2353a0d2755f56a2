"""Scene registry: procedural, seeded scenes built on demand and cached per (name, seed).

Builders are plain functions ``(seed: int, vegetation: float = 1.0) -> Scene`` decorated with
:func:`register`; ``vegetation`` scales the leaves (cards per cluster or per metre of hedge: a sparse or
a dense canopy), not the collision model. The scene
modules are imported lazily on the first registry query, so importing :mod:`droneulator.scenes.base`
alone stays cheap (no numba, no texture generation).

A built scene is also kept on disk (:func:`cache_dir`), keyed by its name, seed and a hash of this
package's source and numpy's version: a scene takes 1-3 s to build (its textures, meshes and collision
grid) and every process of a run (dynamics and render server) and every test process needs it; a
pickled one loads in about 10 ms. At most :data:`CACHE_FILES` scenes are kept (the least recently
used go). ``DRONEULATOR_CACHE_DIR`` moves the cache; set to ``off`` it turns it off.
"""

from __future__ import annotations

import functools
import hashlib
import importlib
import logging
import os
import pickle
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

from droneulator.config.scene import check_vegetation
from droneulator.scenes.base import MeshPart, Scene

SceneBuilder = Callable[[int, float], Scene]

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


#: scenes kept on disk at most (each is 30-40 MB)
CACHE_FILES = 16

log = logging.getLogger("droneulator.scenes")


def cache_dir() -> Path | None:
    """Where built scenes are kept: ``$DRONEULATOR_CACHE_DIR`` (``off``: nowhere), else
    ``$XDG_CACHE_HOME/droneulator/scenes`` (``~/.cache/...``); None in a frozen bundle, whose scene code
    has no source to key the files by."""
    env = os.environ.get("DRONEULATOR_CACHE_DIR")
    if env == "off" or getattr(sys, "frozen", False):
        return None
    if env:
        return Path(env)
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "droneulator" / "scenes"


@functools.lru_cache(maxsize=1)
def _source_key() -> str:
    """A hash of every module of this package (what a scene is built from) and of numpy's version."""
    h = hashlib.sha256(np.__version__.encode())
    for path in sorted(Path(__file__).parent.glob("*.py")):
        h.update(path.name.encode())
        h.update(path.read_bytes())
    return h.hexdigest()[:16]


def _cached(name: str, seed: int, build: Callable[[], Scene], vegetation: float = 1.0) -> Scene:
    """``build()``'s scene from the disk cache when there, else built and stored (a failure to read or
    write the cache only costs the build)."""
    root = cache_dir()
    if root is None:
        return build()
    density = "" if vegetation == 1.0 else f"-v{vegetation:g}"
    path = root / f"{name}-{seed}{density}-{_source_key()}.pkl"
    try:
        with path.open("rb") as f:
            scene = pickle.load(f)
        os.utime(path)  # recently used
        return scene
    except FileNotFoundError:
        pass
    except Exception as exc:  # a truncated or foreign file: build it again
        log.warning("scene cache %s unreadable (%s): building the scene", path, exc)
    scene = build()
    try:
        root.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=root, suffix=".tmp", delete=False) as f:
            pickle.dump(scene, f, protocol=pickle.HIGHEST_PROTOCOL)
        os.replace(f.name, path)  # atomic: a process starting meanwhile never reads half a file
        kept = sorted(root.glob("*.pkl"), key=lambda p: p.stat().st_mtime, reverse=True)
        for old in kept[CACHE_FILES:]:
            old.unlink(missing_ok=True)
    except OSError as exc:
        log.warning("scene cache %s not written: %s", root, exc)
    return scene


@functools.lru_cache(maxsize=16)
def _build(name: str, seed: int, vegetation: float) -> Scene:
    def build() -> Scene:
        scene = _REGISTRY[name][1](seed, vegetation)
        scene.vegetation = vegetation
        return scene

    return _cached(name, seed, build, vegetation)


def get_scene(name: str, seed: int = 0, vegetation: float = 1.0) -> Scene:
    """The scene ``name`` built with ``seed`` and ``vegetation`` density (cached: repeated calls return the
    same object)."""
    _load()
    if name not in _REGISTRY:
        raise ValueError(f"unknown scene {name!r}; known scenes: {', '.join(sorted(_REGISTRY))}")
    return _build(name, int(seed), check_vegetation(vegetation))


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
