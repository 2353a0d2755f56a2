"""Which scene the render server and the bridge must draw and describe: the world's, as resets change it.

A run starts every process on the config's scene, seed, vegetation and light. An API ``reset`` may
change any of them in the dynamics server's world; the other processes then need a ``LoadScene``: at
once (:meth:`SceneSync.changed`, checked after each step) and, for a process that connects later (a
restarted render server or bridge), on connecting (:meth:`SceneSync.for_newcomer`).
"""

from __future__ import annotations

from typing import Any

from droneulator.config import SimConfig
from droneulator.runtime.ipc import LoadScene


def scene_of(config: SimConfig) -> tuple[str, int, Any, float]:
    """The (scene, seed, light, vegetation) a config draws."""
    return config.scene, config.seed, config.light, config.vegetation


class SceneSync:
    """Follows the world's config (``world_config``, changed in place by resets) against what it held when
    the run started, which the other processes were started with."""

    def __init__(self, world_config: SimConfig) -> None:
        self._world = world_config
        self._start = self._sent = scene_of(world_config)

    def for_newcomer(self) -> LoadScene | None:
        """What a process that connects now must load: None when the world still draws the run's start."""
        now = scene_of(self._world)
        return None if now == self._start else LoadScene(*now)

    def changed(self) -> LoadScene | None:
        """What every process must load after a reset changed the scene, its seed, light or vegetation
        (once per change); None when nothing changed."""
        now = scene_of(self._world)
        if now == self._sent:
            return None
        self._sent = now
        return LoadScene(*now)
