"""Stable-Baselines3 with its environments as Ray actors (:class:`RayVecEnv`): the alternative to RLlib
that the Ray issue asks to measure (``benchmarks/scale.py``; ``droneulator train --ray ... --ray-backend
sb3``).

The learner is SB3's, in this process; the worlds are split over ``actors`` Ray actors, each holding one
batched env (:class:`~droneulator.workflows.rl.vector.VineyardNavVectorEnv` behind
:class:`~droneulator.workflows.rl.sb3.SB3VectorEnv`, one CPU) wherever Ray places it. A step sends each
actor its slice of the actions and gathers the slices back: one round trip per actor per step, where
RLlib's env runners sample whole rollouts on their own.

An actor that dies (its process killed, its node lost) is started again (on any node) and its worlds
are reset with fresh seeds; the episodes it was flying end there as truncated (SB3 bootstraps them from
their last observation), and training goes on. ``restarts`` counts them.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any

import numpy as np
from stable_baselines3.common.vec_env import VecEnv

from droneulator.config import SimConfig, from_dict, to_dict

#: seeds of a restarted actor's worlds: ``seed + RESTART_SEED_STRIDE * restarts + i``, apart from the
#: first ones
RESTART_SEED_STRIDE = 1_000_003


class _Worlds:
    """A Ray actor's batch of worlds (the class Ray wraps with ``ray.remote``), stepped on ``threads``
    threads (its CPU allotment; at most the node's cores)."""

    def __init__(self, config: dict[str, Any], num_envs: int, depth: str, threads: int) -> None:
        import numba
        from gymnasium.vector import AutoresetMode

        import droneulator.workflows.rl  # noqa: F401  (registers the env id in a fresh worker)
        from droneulator.workflows.rl.sb3 import SB3VectorEnv
        from droneulator.workflows.rl.vector import VineyardNavVectorEnv

        cfg = from_dict(SimConfig, config)
        threads = min(threads, numba.config.NUMBA_NUM_THREADS)
        self.env = SB3VectorEnv(VineyardNavVectorEnv(num_envs, cfg, depth, AutoresetMode.SAME_STEP, threads))

    def spaces(self) -> tuple[Any, Any]:
        """One world's observation and action spaces."""
        return self.env.observation_space, self.env.action_space

    def reset(self, seed: int | None) -> np.ndarray:
        """Reset every world, world ``i`` of this actor seeded ``seed + i`` (None: unseeded)."""
        if seed is not None:
            self.env.seed(seed)
        return self.env.reset()

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[dict[str, Any]]]:
        self.env.step_async(actions)
        return self.env.step_wait()

    def where(self) -> tuple[int, str]:
        """(process id, Ray node id) of this actor."""
        import ray

        return os.getpid(), ray.get_runtime_context().get_node_id()


class RayVecEnv(VecEnv):
    """``num_envs`` vineyard worlds split over ``actors`` Ray actors, seen by SB3 as one VecEnv.

    Ray must be connected (:func:`droneulator.runtime.cluster.connect`). ``cpus``: CPUs each actor asks
    Ray for. Worlds ``i`` are seeded ``seed + i`` at the first reset, as the in-process env seeds them.
    """

    def __init__(
        self, cfg: SimConfig, num_envs: int, actors: int, depth: str = "raycast", cpus: float = 1.0
    ) -> None:
        import ray

        if actors < 1 or num_envs < actors:
            raise ValueError(f"need at least one actor and one world per actor, got {actors} for {num_envs}")
        self._ray = ray
        self._remote = ray.remote(num_cpus=cpus, max_restarts=0)(_Worlds)
        self._config = to_dict(cfg)
        self._depth = depth
        self._threads = max(1, round(cpus))
        edges = np.linspace(0, num_envs, actors + 1).round().astype(int)
        self.slices = [slice(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:], strict=True)]
        self.actors = [self._spawn(s) for s in self.slices]
        #: actors started again after one died
        self.restarts = 0
        #: every seed a world was reset with (restarted actors' too): the run's training seeds
        self.seeds_used: list[int] = []
        #: the seed of the next reset (``seed``), and the last one given (restarted actors derive theirs)
        self._next_seed: int | None = None
        self._base_seed: int | None = None
        self._obs: np.ndarray | None = None
        self._pending: list[Any] = []
        observation_space, action_space = ray.get(self.actors[0].spaces.remote())
        super().__init__(num_envs, observation_space, action_space)

    def _spawn(self, part: slice) -> Any:
        return self._remote.remote(self._config, part.stop - part.start, self._depth, self._threads)

    def seed(self, seed: int | None = None) -> Sequence[None | int]:
        """Seed the next reset: world ``i`` with ``seed + i`` (as SB3's VecEnv.seed)."""
        self._next_seed = seed
        return [None if seed is None else seed + i for i in range(self.num_envs)]

    def reset(self) -> np.ndarray:
        seed = self._next_seed
        if seed is not None:
            self._base_seed = seed
            self.seeds_used.extend(seed + i for i in range(self.num_envs))
        firsts = [None if seed is None else seed + s.start for s in self.slices]
        obs = self._ray.get([a.reset.remote(f) for a, f in zip(self.actors, firsts, strict=True)])
        self._next_seed = None
        self._obs = np.concatenate(obs)
        return self._obs.copy()

    def step_async(self, actions: np.ndarray) -> None:
        a = np.asarray(actions, dtype=np.float32).reshape(self.num_envs, -1)
        self._pending = [actor.step.remote(a[s]) for actor, s in zip(self.actors, self.slices, strict=True)]

    def step_wait(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[dict[str, Any]]]:
        from ray.exceptions import RayActorError

        assert self._obs is not None, "reset first"
        obs = np.empty_like(self._obs)
        rewards = np.zeros(self.num_envs, dtype=np.float32)
        dones = np.zeros(self.num_envs, dtype=bool)
        infos: list[dict[str, Any]] = [{} for _ in range(self.num_envs)]
        for k, (ref, part) in enumerate(zip(self._pending, self.slices, strict=True)):
            try:
                o, r, d, info = self._ray.get(ref)
            except RayActorError:
                o, r, d, info = self._restart(k, part)
            obs[part], rewards[part], dones[part] = o, r, d
            infos[part] = info
        self._pending = []
        self._obs = obs
        return obs.copy(), rewards, dones, infos

    def _restart(
        self, k: int, part: slice
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[dict[str, Any]]]:
        """A new actor for slice ``part`` (its predecessor died): its worlds start new episodes, and the
        ones they were flying end truncated at their last observation."""
        assert self._obs is not None
        self.restarts += 1
        self.actors[k] = self._spawn(part)
        base = self._base_seed
        seed = None if base is None else base + RESTART_SEED_STRIDE * self.restarts + part.start
        if seed is not None:
            self.seeds_used.extend(range(seed, seed + part.stop - part.start))
        fresh = self._ray.get(self.actors[k].reset.remote(seed))
        n = part.stop - part.start
        infos = [
            {"terminal_observation": self._obs[part][i].copy(), "TimeLimit.truncated": True,
             "is_success": False, "termination": "env_restarted", "goal_distance": np.nan}
            for i in range(n)
        ]  # fmt: skip
        return fresh, np.zeros(n, dtype=np.float32), np.ones(n, dtype=bool), infos

    def where(self) -> list[tuple[int, str]]:
        """(process id, Ray node id) of each actor."""
        return self._ray.get([a.where.remote() for a in self.actors])

    def close(self) -> None:
        for actor in self.actors:
            self._ray.kill(actor)
        self.actors = []

    def get_attr(self, attr_name: str, indices: Any = None) -> list[Any]:
        if attr_name == "render_mode":  # the batched worlds draw nothing
            return [None] * len(self._indices(indices))
        raise AttributeError(f"RayVecEnv keeps its worlds in Ray actors: no attribute {attr_name!r} here")

    def set_attr(self, attr_name: str, value: Any, indices: Any = None) -> None:
        raise AttributeError(f"RayVecEnv keeps its worlds in Ray actors: cannot set {attr_name!r}")

    def env_method(self, method_name: str, *args: Any, indices: Any = None, **kwargs: Any) -> list[Any]:
        raise AttributeError(f"RayVecEnv keeps its worlds in Ray actors: cannot call {method_name!r}")

    def env_is_wrapped(self, wrapper_class: type, indices: Any = None) -> list[bool]:
        return [False] * len(self._indices(indices))

    def _indices(self, indices: Any) -> Sequence[int]:
        if indices is None:
            return range(self.num_envs)
        return [indices] if isinstance(indices, int) else list(indices)
