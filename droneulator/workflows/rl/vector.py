"""``gym.make_vec("droneulator/VineyardNav-v0", num_envs=B)``: B vineyard tasks stepped together.

A native :class:`gymnasium.vector.VectorEnv` (the registration's vector entry point), not B copies of
:class:`~droneulator.workflows.rl.env.VineyardNavEnv` in subprocesses: B independent one-vehicle worlds
of the vineyard (one :class:`~droneulator.world.World` of B worlds: their own clock, vehicle, start and
goal; the layout is the config's scene seed, as the single env's) step to their next camera frame in one
compiled call, and the depth of all of them comes from one batched call (``depth``: ``"raycast"``, our
BVH ray caster, the default here; ``"render"``, the OpenGL renderer drawing them one after the other,
as the single env does by default).

With domain randomisation of the scene, each env flies each episode in one of the single env's scene
variants (:func:`~droneulator.workflows.rl.env.scene_variants`), drawn at its reset as the single env
draws it: every variant is a scene of the world (:meth:`~droneulator.world.World.add_scene`), with its
own depth source and occupancy grid, and an env's world flies in its episode's scene.

Each env follows the single env's rules exactly (one :class:`~droneulator.workflows.rl.env.NavTask` per
env: task sampling, reward, terminations, time limit), so env ``i`` seeded ``s`` with the same actions
gives the single env's observations, rewards, terminations and truncations when both take depth from
the same source (tests/test_rl_vector.py checks it over long random rollouts with autoresets).

Seeding follows Gymnasium's vector envs: ``reset(seed=s)`` seeds env ``i`` with ``s + i`` (a list gives
each its own); later resets, autoresets included, continue each env's generator. Autoreset:
``autoreset_mode`` ``NEXT_STEP`` (Gymnasium's default: the step after an episode ends resets that env,
ignoring its action, with reward 0) or ``SAME_STEP`` (the final observation and info go to
``info["final_obs"]`` / ``info["final_info"]`` and the reset observation is returned at once, as
Stable-Baselines3 expects). ``info`` holds every single-env key as an array with its ``_key`` mask.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Sequence
from typing import Any

import gymnasium as gym
import numba
import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from droneulator.config import SimConfig
from droneulator.frames import transforms_from_poses, yaws_of
from droneulator.render.pipeline import CameraPipeline, Spheres
from droneulator.scenes import get_scene
from droneulator.state import STATE
from droneulator.workflows.rl.backend import Kinematics
from droneulator.workflows.rl.env import (
    DEPTH_SOURCES,
    STRIP_SAMPLES,
    NavTask,
    env_config,
    occupancy_grid,
    scene_variants,
    strips,
)
from droneulator.workflows.rl.levels import Actuator
from droneulator.workflows.rl.task import REASONS, TaskRows
from droneulator.world.world import NS, World


def depth_strips(
    cameras: CameraPipeline,
    poses: np.ndarray,
    presets: Sequence[str],
    scales: np.ndarray,
    clip: float,
    spheres: Spheres | None = None,
) -> np.ndarray:
    """The observation's depth strips (:func:`~droneulator.workflows.rl.env.strips`) at ``poses``, each
    through its episode's depth preset and factors; for exact depth cast, only each sector's nearest return
    is cast (the same strips sooner). ``spheres``: other vehicles' bodies as spheres, (centres ``(B, K, 3)``,
    radii ``(B, K)``), seen in the depth (ray casting only)."""
    if cameras.source == "raycast" and cameras.ideal(presets):
        return strips(cameras.sector_minima(poses, STRIP_SAMPLES, spheres), clip)
    return strips(cameras.centre_rows(poses, presets, scales, spheres), clip)


class ThreadedVectorEnv(VectorEnv):
    """A vector env whose compiled calls run on ``_threads`` threads (None: numba's, every core), the
    caller's thread keeping its own setting (numba's thread count belongs to the calling thread).
    Subclasses write ``_reset`` and ``_step``."""

    _threads: int | None = None

    @contextlib.contextmanager
    def _own_threads(self) -> Iterator[None]:
        if self._threads is None:
            yield
            return
        before = numba.get_num_threads()
        numba.set_num_threads(self._threads)
        try:
            yield
        finally:
            numba.set_num_threads(before)

    @staticmethod
    def _seeds(seed: int | list[int | None] | None, n: int, what: str) -> list[int | None]:
        """Gymnasium's vector seeding for ``n`` ``what``: None each, ``seed + i``, or a list of ``n``."""
        if seed is None:
            return [None] * n
        if isinstance(seed, (int, np.integer)):
            return [int(seed) + i for i in range(n)]
        seeds = list(seed)
        if len(seeds) != n:
            raise ValueError(f"reset got {len(seeds)} seeds for {n} {what}")
        return seeds

    @staticmethod
    def _masked(info: dict[str, Any], mask: np.ndarray) -> dict[str, Any]:
        """Gymnasium's vector info: each key's array with its ``_key`` mask."""
        out: dict[str, Any] = {}
        for key, value in info.items():
            out[key], out[f"_{key}"] = value, mask.copy()
        return out

    def reset(
        self, *, seed: int | list[int | None] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        with self._own_threads():
            return self._reset(seed, options)  # type: ignore[attr-defined]

    def step(
        self, actions: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        with self._own_threads():
            return self._step(actions)  # type: ignore[attr-defined]


class VineyardNavVectorEnv(ThreadedVectorEnv):
    """B vineyard navigation tasks in one process (see the module docstring).

    ``num_envs``: B; ``config``: a :class:`SimConfig` (its ``rl`` section and vehicle settings, as the
    single env); ``depth``: ``"raycast"`` or ``"render"``; ``autoreset_mode``: an
    :class:`~gymnasium.vector.AutoresetMode` (or its value); ``threads``: the compiled steps' threads
    (default: numba's, every core; the SB3 backend's Ray actors pass their CPU allotment, so that N
    actors on N cores run N threads, not N times the cores); further keyword arguments replace fields
    of ``config.rl``.

    Memory: each env holds its goal's distance field (float64), next-node chain (int32) and reachability
    over the occupancy grid, about 2 MB on the vineyard at the default 0.1 m grid.
    """

    metadata = {"autoreset_mode": AutoresetMode.NEXT_STEP, "render_modes": [], "render_fps": 30}

    def __init__(
        self,
        num_envs: int = 1,
        config: SimConfig | None = None,
        depth: str = "raycast",
        autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP,
        threads: int | None = None,
        **rl_overrides: Any,
    ) -> None:
        if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)) or num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
        if threads is not None and not 1 <= threads <= numba.config.NUMBA_NUM_THREADS:
            raise ValueError(f"threads must be 1 to {numba.config.NUMBA_NUM_THREADS}, got {threads!r}")
        self._threads = threads
        mode = AutoresetMode(autoreset_mode)
        if mode == AutoresetMode.DISABLED:
            raise ValueError("autoreset_mode must be NEXT_STEP or SAME_STEP")
        self.metadata = {**self.metadata, "autoreset_mode": mode}
        self.autoreset_mode = mode
        cfg = env_config(config, **rl_overrides)
        self.config = cfg
        self.num_envs = n = int(num_envs)
        if depth not in DEPTH_SOURCES:
            raise ValueError(f"depth must be one of {', '.join(DEPTH_SOURCES)}, got {depth!r}")
        #: every env's world: one vehicle each (physics only)
        self.worlds = World(cfg, render=False, worlds=n)
        #: the scenes episodes fly in (one, or randomisation's variants), each a scene of the world with
        #: its depth source and its occupancy grid, built the first time an env draws it
        self.variants = scene_variants(cfg)
        self._batches: dict[int, _SceneBatch] = {}
        self._variant = np.zeros(n, dtype=np.int64)
        self._depth = depth
        #: the first scene variant (with one scene, every env's; with scene randomisation an env's
        #: episode flies in the one ``_variant`` names)
        self.scene = self._batch(0).scene
        self.tasks = [NavTask(cfg, self.scene) for _ in range(n)]
        task = self.tasks[0]
        self.single_observation_space = task.observation_space
        self.single_action_space = task.action_space
        self.observation_space = batch_space(self.single_observation_space, n)
        self.action_space = batch_space(self.single_action_space, n)
        #: every env's episode in the task kernel (:mod:`.task`)
        self.rows = TaskRows(cfg, task.grid, n)
        self._rngs = [np.random.default_rng() for _ in range(n)]
        self._obs = np.zeros((n, self.single_observation_space.shape[0]), dtype=np.float32)
        self._done = np.zeros(n, dtype=bool)
        #: every env's action at ``rl.action``'s level and its command (:mod:`.levels`)
        self.actuator = Actuator(cfg, n)
        self._reset_called = False
        #: each env's depth preset this episode (``rl.depth_model``, or randomisation's draw)
        cam = cfg.render.cameras[0]
        self._depth_models = [cam.depth_model] * n
        #: each env's depth noise and dropout factors this episode
        self._depth_scales = np.tile([cam.depth_noise_scale, cam.depth_dropout_scale], (n, 1))
        self._base_wind = cfg.wind

    # ------------------------------------------------------------------ helpers
    def _batch(self, k: int) -> _SceneBatch:
        """Scene variant ``k``: its scene in the world, depth source and grid (built on first use)."""
        if k not in self._batches:
            self._batches[k] = _SceneBatch(self.variants[k], self.worlds, self._depth)
        return self._batches[k]

    def _groups(self, idx: np.ndarray) -> list[tuple[_SceneBatch, np.ndarray]]:
        """Envs ``idx`` grouped by the scene variant they fly in: (its batch, their indices)."""
        if len(self._batches) == 1:
            return [(self._batches[0], idx)]
        return [(self._batches[k], idx[self._variant[idx] == k]) for k in np.unique(self._variant[idx])]

    @property
    def states(self) -> np.ndarray:
        """Every env's vehicle state (``(B, STATE_SIZE)``, a view of its world's row)."""
        return self.worlds.states[:, 0]

    def _reset_envs(self, idx: np.ndarray, options: dict[str, Any] | None) -> None:
        """Sample (or take from ``options``) a task for each env of ``idx``, place its vehicle there and
        fill ``_obs`` rows and the reset part of the info arrays."""
        opts = options or {}
        rl = self.config.rl
        begun = []
        for i in idx:
            task = self.tasks[i]
            if len(self.variants) > 1:
                self._variant[i] = k = int(self._rngs[i].integers(len(self.variants)))
                task.use_scene(self._batch(k).scene)
            if "start" in opts or "goal" in opts:
                begun.append(task.given_task(opts))
            else:
                begun.append(task.sample_task(self._rngs[i]))
        positions = np.array([(start[0], start[1], rl.altitude) for start, *_ in begun]).reshape(-1, 3)
        yaws = np.array([yaw for _, yaw, *_ in begun])
        at = {int(i): j for j, i in enumerate(idx)}
        for batch, sub in self._groups(idx):
            rows = [at[int(i)] for i in sub]
            self.worlds.place(sub, positions[rows], yaws[rows], variant=batch.index)
        if self.config.randomize.enabled:
            draws = [self.config.randomize.draw(self._rngs[i], self._base_wind) for i in idx]
            self.worlds.set_wind_rows([d.wind for d in draws], idx)
            for i, d in zip(idx, draws, strict=True):
                self.worlds.rotor_efficiency[i, 0] = d.rotor_efficiency
                self._depth_models[i] = d.depth_model
                self._depth_scales[i] = d.depth_noise_scale, d.depth_dropout_scale
        for i, (start, yaw, goal, field) in zip(idx, begun, strict=True):
            kin = self._kinematics(int(i), 0)
            task = self.tasks[i]
            task.begin(start, yaw, goal, field, kin, self.rows, int(i))
            task.field = None  # its arrays live in this env's rows now
        rows, none = self.states, np.zeros(self.num_envs, dtype=bool)
        for batch, sub in self._groups(idx):
            mine = none.copy()
            mine[sub] = True
            self.rows.step(mine, rows, none, batch.grid, batch.scene, advance=False)
        self._obs[idx, STRIP_SAMPLES:] = self.rows.tail[idx]
        self.actuator.begin(idx, yaws)
        self._strips(idx, self.states)

    def _kinematics(self, i: int, t_ns: int) -> Kinematics:
        row = self.worlds.states[i, 0]
        return Kinematics(t_ns / NS, row[STATE.x].copy(), row[STATE.q].copy(), row[STATE.v].copy(),
                          row[STATE.w].copy(), "hold")  # fmt: skip

    def _strips(self, idx: np.ndarray, rows: np.ndarray) -> None:
        """The depth strips of envs ``idx`` at the states ``rows[idx]`` into ``_obs``."""
        if len(idx) == 0:
            return
        for batch, sub in self._groups(idx):
            poses = transforms_from_poses(rows[sub, 0:3], rows[sub, 6:10])
            models = [self._depth_models[i] for i in sub]
            scales, clip = self._depth_scales[sub], self.config.rl.depth_clip
            self._obs[sub, :STRIP_SAMPLES] = depth_strips(batch.cameras, poses, models, scales, clip)

    def _infos(self, rows: np.ndarray, t: np.ndarray, mask: np.ndarray) -> dict[str, Any]:
        """The single env's info keys as arrays (Gymnasium's vector form, every env present)."""
        yaw = yaws_of(rows[:, 6:10])
        task = self.rows
        termination = np.array([REASONS[r] for r in task.reason], dtype=object)
        info = {
            "t": t.astype(float),
            "position": rows[:, 0:3].copy(),
            "yaw": yaw,
            "command": self.actuator.commands.copy(),
            "distance": task.dist.copy(),
            "goal_distance": task.goal_dist.copy(),
            "termination": termination,
            "is_success": task.reason == REASONS.index("goal"),
        }
        return self._masked(info, mask)

    def _reset(
        self, seed: int | list[int | None] | None, options: dict[str, Any] | None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        n = self.num_envs
        seeds = self._seeds(seed, n, "environments")
        for i, s in enumerate(seeds):
            if s is not None or not self._reset_called:
                self._rngs[i], _ = gym.utils.seeding.np_random(s)
        self._reset_called = True
        self._reset_envs(np.arange(n), options)
        self._done[:] = False
        infos = self._infos(self.states, np.zeros(n), np.ones(n, dtype=bool))
        return self._obs.copy(), infos

    def _step(
        self, actions: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        if not self._reset_called:
            raise RuntimeError("call reset() before step()")
        n = self.num_envs
        size = self.actuator.space.shape[0]
        a = np.asarray(actions, dtype=np.float64)
        if a.shape != (n, size) or not np.all(np.isfinite(a)):
            raise ValueError(f"actions must be finite numbers of shape ({n}, {size}), got shape {a.shape}")
        next_step = self.autoreset_mode == AutoresetMode.NEXT_STEP
        resetting = self._done.copy() if next_step else np.zeros(n, dtype=bool)
        run = ~resetting
        idx = np.flatnonzero(run)
        a = np.clip(a, -1.0, 1.0)
        commands = self.actuator.map(idx, a[idx])
        self.actuator.send_rows(self.worlds, idx, np.zeros(len(idx), dtype=np.int64), commands)
        cams, hits = self.worlds.step_frame(run)
        cam, hit = cams[:, 0], hits[:, 0]
        t = self.worlds.frame_t_ns() / NS
        for batch, sub in self._groups(idx):
            mine = np.zeros(n, dtype=bool)
            mine[sub] = True
            self.rows.step(mine, cam, hit, batch.grid, batch.scene, advance=True)
        self._obs[idx, STRIP_SAMPLES:] = self.rows.tail[idx]
        self._strips(idx, cam)
        rewards = np.where(run, self.rows.reward, 0.0)
        reason = np.where(run, self.rows.reason, 0)
        truncated = reason == REASONS.index("time_limit")
        terminated = (reason != 0) & ~truncated
        done = terminated | truncated
        infos = self._infos(cam, t, np.ones(n, dtype=bool))
        if not next_step and done.any():
            final_obs = np.full(n, None, dtype=object)
            for i in np.flatnonzero(done):
                final_obs[i] = self._obs[i].copy()
            final_info = {
                key: done.copy() if key.startswith("_") else value.copy() for key, value in infos.items()
            }
            resetting = done
        if resetting.any():
            ridx = np.flatnonzero(resetting)
            self._reset_envs(ridx, None)
            fresh = self._infos(self.states, np.zeros(n), resetting)
            for key, value in fresh.items():
                if not key.startswith("_"):
                    infos[key][ridx] = value[ridx]
        if not next_step and done.any():
            infos["final_obs"], infos["_final_obs"] = final_obs, done.copy()
            infos["final_info"], infos["_final_info"] = final_info, done.copy()
        self._done = done if next_step else np.zeros(n, dtype=bool)
        return self._obs.copy(), rewards, terminated, truncated, infos

    def close_extras(self, **kwargs: Any) -> None:
        for batch in getattr(self, "_batches", {}).values():
            batch.cameras.close()
        self._batches = {}


class _SceneBatch:
    """One scene variant of a vector env: its scene in the world (``index``: the world's variant), its
    camera pipeline (depth from ``depth``) and occupancy grid."""

    def __init__(self, cfg: SimConfig, world: World, depth: str) -> None:
        if (cfg.scene, cfg.seed, cfg.vegetation) == (world.config.scene, world.config.seed,
                                                     world.config.vegetation):  # fmt: skip
            self.scene, self.index = world.scene, 0
        else:
            self.scene = get_scene(cfg.scene, cfg.seed, cfg.vegetation)
            self.index = world.add_scene(self.scene)
        self.cameras = CameraPipeline(self.scene, cfg, source=depth)
        self.grid = occupancy_grid(self.scene, cfg.rl, cfg.vehicle.collision_radius)
