"""The vineyard navigation task for many vehicles: W worlds of N agents on the one core.

Every agent has the single-agent task of :mod:`.env` (the same :class:`~droneulator.workflows.rl.env.NavTask`
rules, observation and action spaces, reward and termination through the task kernel of :mod:`.task`, its
own start, goal and time limit). The N agents of a world share it: they see each other in their depth,
feel each other's rotor wakes, and two whose bodies touch both collide (each episode ends with
``rl.collision_penalty``, ``collided_with`` naming the other). Starts and goals are drawn apart: no two
closer than ``min_spacing``. With two agents or more (and ``rl.neighbour_range`` > 0) each agent also
observes the nearest other live agent of its world within ``rl.neighbour_range``: the observation ends in
:data:`NEIGHBOUR_SIZE` entries (:func:`neighbour_block`), as a swarm's position broadcast gives them,
since a 90 degree strip sees an agent crossing its path at a row end too late to give way.

Two faces of one environment:

* :class:`VineyardMultiVectorEnv` (for trainers): a :class:`gymnasium.vector.VectorEnv` of ``W * N`` rows,
  row ``r`` agent ``r % N`` of world ``r // N``. One :class:`~droneulator.world.World` of W worlds steps
  every vehicle to the next camera frame in one compiled call; the depth of every agent comes from one
  batched ray cast (``depth="raycast"``, the other vehicles as spheres of their collision radius) or from
  the renderer, world by world (``depth="render"``: each camera sees the other vehicles' meshes).
  ``episodes="agent"`` (the default): a row is a stream of single-agent episodes, an agent whose episode
  ends starts a new task in its world while the others fly on (Gymnasium's autoreset, ``NEXT_STEP`` or
  ``SAME_STEP``). ``episodes="world"``: an agent whose episode ended leaves its world (it is no longer
  flown, touched or seen) and the world starts over once all its agents are done (held-out evaluation of
  a team; ``info["world_success"]``: every agent of the world reached its goal).
* :class:`VineyardNavParallelEnv` (``droneulator_vineyard_nav_v0``): PettingZoo's
  :class:`~pettingzoo.ParallelEnv`, dicts keyed by vehicle name (``uav0 .. uav<N-1>``), a view of the
  vector env with one world and ``episodes="world"``: a done agent leaves :attr:`agents`. Its depth is the
  renderer's by default, as the single env's.

``reset(options={"tasks": {"uav0": {"start": (x, y, yaw), "goal": (x, y)}, ...}})`` sets the tasks of the
named agents in every world; the others are sampled apart from them.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numba
import numpy as np
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode
from gymnasium.vector.utils import batch_space
from pettingzoo import ParallelEnv

from droneulator.config import SimConfig, fleet
from droneulator.frames import transforms_from_poses, yaws_of
from droneulator.render.pipeline import CameraPipeline
from droneulator.state import STATE
from droneulator.workflows.rl.backend import CAMERA_NAME, Kinematics
from droneulator.workflows.rl.env import DEPTH_SOURCES, STRIP_SAMPLES, NavTask, env_config, strips
from droneulator.workflows.rl.levels import Actuator
from droneulator.workflows.rl.task import REASONS, TaskRows
from droneulator.workflows.rl.vector import ThreadedVectorEnv, depth_strips
from droneulator.world.world import NS, World

NAME = "droneulator_vineyard_nav_v0"
EPISODES = ("agent", "world")
#: the neighbour block's entries: seen (1, else all 0), its forward and leftward offset over
#: ``rl.neighbour_range``, and its velocity relative to the agent's (forward, leftward) over
#: :data:`NEIGHBOUR_SPEED`, each clipped to [-1, 1]
NEIGHBOUR_SIZE = 5
NEIGHBOUR_SPEED = 4.0

Info = dict[str, Any]


def neighbour_block(states: np.ndarray, live: np.ndarray, reach: float) -> np.ndarray:
    """Each agent's neighbour block (``(W * N, NEIGHBOUR_SIZE)`` float32) for ``states`` ``(W, N, state)``
    and ``live`` ``(W * N,)``: the nearest other live agent of its world within ``reach`` m (horizontal
    distance), in the agent's heading frame (x forward, y left; the yaw of its attitude)."""
    W, N = states.shape[:2]
    p, v, q = states[..., 0:2], states[..., 3:5], states[..., 6:10]
    yaw = yaws_of(q)
    d = np.linalg.norm(p[:, None, :, :] - p[:, :, None, :], axis=-1)  # (W, me, other)
    alive = live.reshape(W, N)
    d = np.where(alive[:, None, :] & ~np.eye(N, dtype=bool)[None], d, np.inf)
    other = d.argmin(axis=2)
    seen = np.take_along_axis(d, other[..., None], axis=2)[..., 0] <= reach
    dp = np.take_along_axis(p, other[..., None], axis=1) - p
    dv = np.take_along_axis(v, other[..., None], axis=1) - v
    c, s = np.cos(yaw), np.sin(yaw)
    out = np.zeros((W, N, NEIGHBOUR_SIZE), dtype=np.float32)
    out[..., 0] = 1.0
    out[..., 1] = (c * dp[..., 0] + s * dp[..., 1]) / reach
    out[..., 2] = (c * dp[..., 1] - s * dp[..., 0]) / reach
    out[..., 3] = (c * dv[..., 0] + s * dv[..., 1]) / NEIGHBOUR_SPEED
    out[..., 4] = (c * dv[..., 1] - s * dv[..., 0]) / NEIGHBOUR_SPEED
    out = np.clip(out, -1.0, 1.0)
    out[~seen] = 0.0
    return out.reshape(W * N, NEIGHBOUR_SIZE)


class VineyardMultiVectorEnv(ThreadedVectorEnv):
    """``num_worlds`` worlds of ``num_agents`` agents as ``num_worlds * num_agents`` rows (see the module
    docstring).

    ``config``: a :class:`SimConfig` (its ``rl`` section and vehicle settings; its ``vehicles`` are replaced
    by ``num_agents`` vehicles ``uav0 ..``); ``depth``: ``"raycast"`` or ``"render"``; ``episodes``:
    ``"agent"`` or ``"world"``; ``min_spacing``: the least distance (m) between two agents' starts (a
    respawn: from the others' positions) and between two goals of a world; ``threads``: the compiled
    steps' threads (default: numba's); further keyword arguments replace fields of ``config.rl``.
    Seeding as Gymnasium's vector envs, per world: ``reset(seed=s)`` seeds world ``w`` with ``s + w``; a
    list gives each world its own (or each row its own, as SB3 does: a world takes its first row's).
    """

    metadata = {"autoreset_mode": AutoresetMode.NEXT_STEP, "render_modes": [], "render_fps": 30}

    def __init__(
        self,
        num_worlds: int = 1,
        num_agents: int = 2,
        config: SimConfig | None = None,
        depth: str = "raycast",
        autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP,
        episodes: str = "agent",
        min_spacing: float = 3.0,
        threads: int | None = None,
        **rl_overrides: Any,
    ) -> None:
        for name, value in (("num_worlds", num_worlds), ("num_agents", num_agents)):
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
        if depth not in DEPTH_SOURCES:
            raise ValueError(f"depth must be one of {', '.join(DEPTH_SOURCES)}, got {depth!r}")
        if episodes not in EPISODES:
            raise ValueError(f"episodes must be one of {', '.join(EPISODES)}, got {episodes!r}")
        if threads is not None and not 1 <= threads <= numba.config.NUMBA_NUM_THREADS:
            raise ValueError(f"threads must be 1 to {numba.config.NUMBA_NUM_THREADS}, got {threads!r}")
        if not min_spacing >= 0.0:
            raise ValueError(f"min_spacing must be a distance >= 0, got {min_spacing!r}")
        mode = AutoresetMode(autoreset_mode)
        if mode == AutoresetMode.DISABLED:
            raise ValueError("autoreset_mode must be NEXT_STEP or SAME_STEP")
        self.metadata = {**self.metadata, "autoreset_mode": mode}
        self.autoreset_mode = mode
        cfg = env_config(config, **rl_overrides)
        if cfg.randomize.enabled:
            raise ValueError("domain randomisation is batched for one agent per world only "
                             "(VineyardNavVectorEnv): set randomize.enabled = false")  # fmt: skip
        cfg.vehicles = fleet(int(num_agents))
        self.config = cfg
        self.episodes = episodes
        self.min_spacing = float(min_spacing)
        #: the share of drawn tasks sent against another agent (``rl.encounters``: training only)
        self.encounters = cfg.rl.encounters
        self._threads = threads
        self.num_worlds = W = int(num_worlds)
        self.num_agents = N = int(num_agents)
        self.num_envs = R = W * N
        #: every world, one compiled step (physics only)
        self.world = World(cfg, render=False, worlds=W)
        self.scene = self.world.scene
        self.agent_names: list[str] = list(self.world.vehicles)
        self.tasks = [NavTask(cfg, self.scene) for _ in range(R)]
        self.grid = self.tasks[0].grid
        task = self.tasks[0]
        #: the observation's columns: the depth strip, the task's tail, the neighbour block (if any)
        self._tail_end = task.observation_space.shape[0]
        self.neighbours = N > 1 and cfg.rl.neighbour_range > 0.0
        if self.neighbours:
            space = task.observation_space
            low = np.concatenate([space.low, [0.0], -np.ones(NEIGHBOUR_SIZE - 1)]).astype(np.float32)
            self.single_observation_space = gym.spaces.Box(low, np.ones_like(low), dtype=np.float32)
        else:
            self.single_observation_space = task.observation_space
        self.single_action_space = task.action_space
        self.observation_space = batch_space(self.single_observation_space, R)
        self.action_space = batch_space(self.single_action_space, R)
        self.rows = TaskRows(cfg, self.grid, R)
        self.cameras = CameraPipeline(self.scene, cfg, source=depth)
        self.depth = depth
        cam = cfg.render.cameras[0]
        self._presets = [cam.depth_model] * R
        self._scales = np.tile([cam.depth_noise_scale, cam.depth_dropout_scale], (R, 1))
        self._radius = float(cfg.vehicle.collision_radius)
        self._rngs = [np.random.default_rng() for _ in range(W)]
        self._obs = np.zeros((R, self.single_observation_space.shape[0]), dtype=np.float32)
        #: every row's action at ``rl.action``'s level and its command (:mod:`.levels`)
        self.actuator = Actuator(cfg, R)
        #: rows whose episode ended at the last step (restarted at this one, with NEXT_STEP)
        self._done = np.zeros(R, dtype=bool)
        #: rows in their world (with episodes="world", a done agent leaves it until the world starts over)
        self.live = np.zeros(R, dtype=bool)
        self._collided_with = np.full(R, "", dtype=object)
        self._reset_called = False

    # ------------------------------------------------------------------ rows and worlds
    def _where(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return rows // self.num_agents, rows % self.num_agents

    def _sample(self, rows: np.ndarray, given: dict[str, Any]) -> list[tuple[Any, ...]]:
        """A task for each of ``rows`` (in order), apart from the tasks of the other live agents of its
        world (their current position and goal) and from those sampled before it; with ``rl.encounters``,
        that share of them against one of those (:meth:`~.env.NavTask.meeting_task`)."""
        N = self.num_agents
        flat = self.world.states.reshape(self.num_envs, -1)
        picked: dict[int, tuple[Any, ...]] = {}
        for r in rows:
            w, a = divmod(int(r), N)
            name = self.agent_names[a]
            if name in given:
                picked[int(r)] = self.tasks[r].given_task(given[name])
                continue
            taken = []
            for o in range(w * N, (w + 1) * N):
                if o in picked:
                    taken.append((picked[o][0], picked[o][2]))
                elif o != r and self.live[o] and o not in rows:
                    taken.append((flat[o, STATE.x][:2], self.tasks[o].goal))
            rng = self._rngs[w]
            if taken and self.encounters > 0.0 and rng.random() < self.encounters:
                position, goal = taken[int(rng.integers(len(taken)))]
                task = self.tasks[r].meeting_task(rng, position, goal)
                if task is not None:
                    picked[int(r)] = task
                    continue
            picked[int(r)] = self.tasks[r].sample_task(rng, taken, self.min_spacing)
        return [picked[int(r)] for r in rows]

    def _start(self, rows: np.ndarray, given: dict[str, Any], whole_worlds: bool) -> None:
        """New tasks for ``rows``: sampled (or ``given``), their vehicles placed hovering at the starts (whole
        worlds restart their clocks) and their episodes begun there."""
        if len(rows) == 0:
            return
        tasks = self._sample(rows, given)
        alt = self.config.rl.altitude
        pos = np.array([(s[0], s[1], alt) for s, *_ in tasks])
        yaw = np.array([y for _, y, *_ in tasks])
        w, a = self._where(rows)
        if whole_worlds:
            worlds = w[:: self.num_agents]
            self.world.place(worlds, pos, yaw)
        else:
            self.world.place_rows(w, a, pos, yaw)
        self.live[rows] = True
        self._collided_with[rows] = ""
        states = self.world.states
        for r, (start, heading, goal, field) in zip(rows, tasks, strict=True):
            s = states[r // self.num_agents, r % self.num_agents]
            t = self.world.clocks[r // self.num_agents] / NS
            kin = Kinematics(t, s[STATE.x].copy(), s[STATE.q].copy(), s[STATE.v].copy(), s[STATE.w].copy(),
                             "hold")  # fmt: skip
            self.tasks[r].begin(start, heading, goal, field, kin, self.rows, int(r))
            self.tasks[r].field = None  # its arrays live in this env's rows now
        mask = np.zeros(self.num_envs, dtype=bool)
        mask[rows] = True
        self.rows.step(mask, self._flat(states), ~mask, self.grid, self.scene, advance=False)
        self._obs[rows, STRIP_SAMPLES : self._tail_end] = self.rows.tail[rows]
        self.actuator.begin(rows, yaw)

    def _flat(self, states: np.ndarray) -> np.ndarray:
        return states.reshape(self.num_envs, -1)

    def _see(self, rows: np.ndarray, states: np.ndarray) -> None:
        """The depth strips and neighbour blocks of ``rows`` at ``states`` (worlds, agents, state) into
        ``_obs``."""
        if len(rows) == 0:
            return
        self._strips(rows, states)
        if self.neighbours:
            block = neighbour_block(states, self.live, self.config.rl.neighbour_range)
            self._obs[rows, self._tail_end :] = block[rows]

    def _strips(self, rows: np.ndarray, states: np.ndarray) -> None:
        """The depth strips of ``rows`` at ``states`` into ``_obs``: each agent sees the other agents of its
        world that are in it."""
        N, clip = self.num_agents, self.config.rl.depth_clip
        flat = self._flat(states)
        if self.depth == "render":
            for w in np.unique(rows // N):
                mine = rows[rows // N == w]
                inside = [w * N + a for a in range(N) if self.live[w * N + a] or w * N + a in mine]
                bodies = transforms_from_poses(flat[inside, 0:3], flat[inside, 6:10])
                names = [self.agent_names[r % N] for r in mine]
                frames = self.cameras.frames(
                    {self.agent_names[r % N]: T for r, T in zip(inside, bodies, strict=True)},
                    rigs=names, rgb=False, copy=False,
                )  # fmt: skip
                rows_px = [frames[name][CAMERA_NAME].depth for name in names]
                centre = np.array([d[d.shape[0] // 2] for d in rows_px])
                self._obs[mine, :STRIP_SAMPLES] = strips(centre, clip)
            return
        poses = transforms_from_poses(flat[rows, 0:3], flat[rows, 6:10])
        others = np.array([[o for o in range(N) if o != a] for a in range(N)], dtype=np.int64)
        others = others.reshape(N, N - 1)
        w, a = self._where(rows)
        idx = w[:, None] * N + others[a]
        centres = flat[idx, 0:3]
        radii = np.where(self.live[idx], self._radius, 0.0)
        spheres = (centres, radii) if N > 1 else None
        self._obs[rows, :STRIP_SAMPLES] = depth_strips(
            self.cameras, poses, [self._presets[r] for r in rows], self._scales[rows], clip, spheres
        )

    def _infos(
        self, states: np.ndarray, mask: np.ndarray, world_over: np.ndarray, world_success: np.ndarray
    ) -> dict[str, Any]:
        """The single env's info keys as arrays, with ``collided_with``, ``world`` and ``agent`` (and, with
        episodes="world", ``world_over``: its world's episode ended at this step, and ``world_success``:
        every agent of it reached its goal)."""
        flat = self._flat(states)
        yaw = yaws_of(flat[:, 6:10])
        w, a = self._where(np.arange(self.num_envs))
        info = {
            "t": np.repeat(self.world.frame_t_ns() / NS, self.num_agents),
            "position": flat[:, 0:3].copy(),
            "yaw": yaw,
            "command": self.actuator.commands.copy(),
            "distance": self.rows.dist.copy(),
            "goal_distance": self.rows.goal_dist.copy(),
            "termination": np.array([REASONS[r] for r in self.rows.reason], dtype=object),
            "is_success": self.rows.reason == REASONS.index("goal"),
            "collided_with": self._collided_with.copy(),
            "world": w,
            "agent": a,
        }
        if self.episodes == "world":
            info["world_over"], info["world_success"] = world_over, world_success
        return self._masked(info, mask)

    def _reset(
        self, seed: int | list[int | None] | None, options: dict[str, Any] | None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        W = self.num_worlds
        if isinstance(seed, (list, tuple)) and len(seed) == self.num_envs != W:  # one per row, as SB3's:
            seed = list(seed)[:: self.num_agents]  # each world takes its first row's
        seeds = self._seeds(seed, W, "worlds")
        given = dict((options or {}).get("tasks", {}))
        unknown = set(given) - set(self.agent_names)
        if unknown:
            raise ValueError(f"options name unknown agents {sorted(unknown)}, not of {self.agent_names}")
        for w, s in enumerate(seeds):
            if s is not None or not self._reset_called:
                self._rngs[w], _ = seeding.np_random(s)
        self._reset_called = True
        self.live[:] = False
        self.rows.reason[:] = 0
        rows = np.arange(self.num_envs)
        self._start(rows, given, whole_worlds=True)
        self._see(rows, self.world.states)
        self._done[:] = False
        none = np.zeros(self.num_envs, dtype=bool)
        infos = self._infos(self.world.states, ~none, none, none)
        return self._obs.copy(), infos

    def _step(
        self, actions: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        if not self._reset_called:
            raise RuntimeError("call reset() before step()")
        R, N = self.num_envs, self.num_agents
        size = self.actuator.space.shape[0]
        a = np.asarray(actions, dtype=np.float64)
        if a.shape != (R, size) or not np.all(np.isfinite(a)):
            raise ValueError(f"actions must be finite numbers of shape ({R}, {size}), got shape {a.shape}")
        next_step = self.autoreset_mode == AutoresetMode.NEXT_STEP
        restarting = self._restart(self._done, observe=False) if next_step else np.zeros(R, dtype=bool)
        moving = self.live & ~restarting
        a = np.clip(a, -1.0, 1.0)
        idx = np.flatnonzero(moving)
        w, ag = self._where(idx)
        self.actuator.send_rows(self.world, w, ag, self.actuator.map(idx, a[idx]))
        # restarted agents wait at their start through this frame (not flown: their episode begins now);
        # a world with none of its agents flying does not step
        held = np.flatnonzero(restarting)
        self.world.active[held // N, held % N] = False
        cams, hits = self.world.step_frame(moving.reshape(-1, N).any(axis=1))
        self.world.active[held // N, held % N] = True
        cams[held // N, held % N] = self.world.states[held // N, held % N]
        touched = self.world.touched.reshape(R)
        hit = hits.reshape(R) | (touched >= 0)
        for r in np.flatnonzero(moving & (touched >= 0)):
            self._collided_with[r] = self.agent_names[touched[r]]
        cam = self._flat(cams)
        self.rows.step(moving, cam, hit, self.grid, self.scene, advance=True)
        self.rows.step(restarting, cam, ~restarting, self.grid, self.scene, advance=False)
        seen = moving | restarting
        self._obs[seen, STRIP_SAMPLES : self._tail_end] = self.rows.tail[seen]
        self._see(np.flatnonzero(seen), cams)
        rewards = np.where(moving, self.rows.reward, 0.0)
        reason = np.where(moving, self.rows.reason, 0)
        truncated = reason == REASONS.index("time_limit")
        terminated = (reason != 0) & ~truncated
        done = terminated | truncated
        over = np.zeros(self.num_worlds, dtype=bool)
        world_success = np.zeros(self.num_worlds, dtype=bool)
        if self.episodes == "world" and done.any():
            ended = np.flatnonzero(done)
            self.world.retire(ended // N, ended % N)
            was_live = self.live.reshape(-1, N).any(axis=1)
            self.live[ended] = False
            over = was_live & ~self.live.reshape(-1, N).any(axis=1)
            goal = REASONS.index("goal")
            # every agent's last episode of a finished world: ``reason`` keeps each row's last outcome
            world_success = over & (self.rows.reason.reshape(-1, N) == goal).all(axis=1)
        infos = self._infos(cams, np.ones(R, dtype=bool), np.repeat(over, N), np.repeat(world_success, N))
        if not next_step and done.any():
            final_obs = np.full(R, None, dtype=object)
            for r in np.flatnonzero(done):
                final_obs[r] = self._obs[r].copy()
            final_info = {
                key: done.copy() if key.startswith("_") else value.copy() for key, value in infos.items()
            }
            fresh = self._restart(done)
            ends = np.repeat(over, N), np.repeat(world_success, N)
            fresh_infos = self._infos(self.world.states, fresh, *ends)
            for key, value in fresh_infos.items():
                if not key.startswith("_"):
                    infos[key][fresh] = value[fresh]
            infos["final_obs"], infos["_final_obs"] = final_obs, done.copy()
            infos["final_info"], infos["_final_info"] = final_info, done.copy()
        self._done = done if next_step else np.zeros(R, dtype=bool)
        return self._obs.copy(), rewards, terminated, truncated, infos

    def _restart(self, done: np.ndarray, observe: bool = True) -> np.ndarray:
        """Start over what ``done`` ended: each done agent (episodes="agent"), or each world none of whose
        agents is left (episodes="world"). Returns the rows restarted (with ``observe``, their observations
        are in ``_obs``; else the caller draws them)."""
        N = self.num_agents
        if self.episodes == "agent":
            rows = np.flatnonzero(done)
            self._start(rows, {}, whole_worlds=False)
        else:
            over = np.flatnonzero(~self.live.reshape(-1, N).any(axis=1))
            rows = (over[:, None] * N + np.arange(N)).ravel()
            self._start(rows, {}, whole_worlds=True)
        mask = np.zeros(self.num_envs, dtype=bool)
        mask[rows] = True
        if observe:
            self._see(rows, self.world.states)
        return mask

    def close_extras(self, **kwargs: Any) -> None:
        if getattr(self, "cameras", None) is not None:
            self.cameras.close()
            self.cameras = None  # type: ignore[assignment]


class VineyardNavParallelEnv(ParallelEnv[str, np.ndarray, np.ndarray]):
    """Vineyard point-to-point navigation for ``num_agents`` vehicles in one world: PettingZoo's parallel
    API over :class:`VineyardMultiVectorEnv` with one world and ``episodes="world"`` (see the module
    docstring). ``depth``: ``"render"`` (default, as the single env) or ``"raycast"``."""

    metadata = {"name": NAME, "render_modes": []}

    def __init__(
        self,
        config: SimConfig | None = None,
        num_agents: int = 2,
        min_spacing: float = 3.0,
        depth: str = "render",
        **rl_overrides: Any,
    ) -> None:
        self.core = VineyardMultiVectorEnv(1, num_agents, config, depth=depth, episodes="world",
                                           min_spacing=min_spacing, **rl_overrides)  # fmt: skip
        self.config = self.core.config
        self.world = self.core.world
        self.min_spacing = self.core.min_spacing
        self.render_mode: str | None = None
        self.possible_agents: list[str] = list(self.core.agent_names)
        self.agents: list[str] = []
        #: each agent's task (start, goal, the rules)
        self.tasks = dict(zip(self.possible_agents, self.core.tasks, strict=True))
        task = self.core.tasks[0]
        space = self.core.single_observation_space
        self.observation_spaces = {name: space for name in self.possible_agents}
        self.action_spaces = {name: task.action_space for name in self.possible_agents}

    def observation_space(self, agent: str) -> gym.spaces.Box:
        return self.observation_spaces[agent]

    def action_space(self, agent: str) -> gym.spaces.Box:
        return self.action_spaces[agent]

    def _dicts(self, obs: np.ndarray, infos: dict[str, Any], names: list[str]) -> tuple[dict, dict]:
        out_obs, out_info = {}, {}
        extra = ("world", "agent", "world_over", "world_success")
        keys = [k for k in infos if not k.startswith("_") and k not in extra]
        for name in names:
            r = self.possible_agents.index(name)
            out_obs[name] = obs[r]
            info = {k: infos[k][r] for k in keys}
            info["position"] = info["position"].copy()
            info["collided_with"] = [info["collided_with"]] if info["collided_with"] else []
            info["is_success"] = bool(info["is_success"])
            info["command"] = tuple(float(c) for c in info["command"])
            out_info[name] = info
        return out_obs, out_info

    def reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, Info]]:
        obs, infos = self.core.reset(seed=seed, options=options)
        self.agents = list(self.possible_agents)
        return self._dicts(obs, infos, self.agents)

    def step(
        self, actions: dict[str, np.ndarray]
    ) -> tuple[dict[str, np.ndarray], dict[str, float], dict[str, bool], dict[str, bool], dict[str, Info]]:
        """Apply every live agent's action (actions for agents already done are ignored) and run the world
        to the next camera frame."""
        if not self.agents:
            raise RuntimeError("no live agents: call reset()")
        unknown = set(actions) - set(self.possible_agents)
        missing = [name for name in self.agents if name not in actions]
        if unknown or missing:
            detail = f"missing {missing}, unknown {sorted(unknown)}"
            raise ValueError(f"need an action for each live agent {self.agents}: {detail}")
        live = list(self.agents)
        size = self.core.actuator.space.shape[0]
        batch = np.zeros((len(self.possible_agents), size))
        for name in live:
            self.tasks[name].check_action(actions[name])
            row = self.possible_agents.index(name)
            batch[row] = np.asarray(actions[name], dtype=np.float64).reshape(size)
        obs, rewards, terminated, truncated, infos = self.core.step(batch)
        out_obs, out_info = self._dicts(obs, infos, live)
        rows = [self.possible_agents.index(name) for name in live]
        rew = {name: float(rewards[r]) for name, r in zip(live, rows, strict=True)}
        term = {name: bool(terminated[r]) for name, r in zip(live, rows, strict=True)}
        trunc = {name: bool(truncated[r]) for name, r in zip(live, rows, strict=True)}
        self.agents = [name for name in live if not (term[name] or trunc[name])]
        return out_obs, rew, term, trunc, out_info

    def close(self) -> None:
        if getattr(self, "core", None) is not None:
            self.core.close()
