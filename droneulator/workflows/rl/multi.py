"""``droneulator_vineyard_nav_v0``: the vineyard navigation task for N vehicles sharing one world, as a
PettingZoo :class:`~pettingzoo.ParallelEnv` (optional extra ``droneulator[rl]``).

The agents are the vehicles ``uav0 .. uav<N-1>``. Each has the single-agent task of :mod:`.env`, through
the same :class:`~droneulator.workflows.rl.env.NavTask` code: the same observation and action spaces,
the same reward and termination, its own start, goal and time limit. Every dict the environment returns
is keyed by vehicle name and holds the agents that were live at the start of the step.

* One :class:`~droneulator.world.World` steps every vehicle together, one step per camera frame; one
  depth-only renderer draws every live agent's camera in one call, each seeing the other live agents'
  bodies (with one agent there are none, and it sees exactly what :class:`.env.VineyardNavEnv` sees).
* Starts and goals are drawn from the environment's generator (``reset(seed=...)`` reproduces them) so
  that no two starts and no two goals lie closer than ``min_spacing``.
* Two vehicles whose bodies touch both collide (the world's contact model stops them): each agent's
  episode ends then with ``rl.collision_penalty``, ``info["collided_with"]`` naming the other.
* An agent whose episode has ended leaves :attr:`agents` (PettingZoo semantics) and the world: its
  vehicle is parked on the ground, motors off, at a spot of its own by the scene's +y edge (outside the
  task area: starts and goals lie between the outermost alleys), and no longer drawn. A hovering or
  frozen vehicle would stay in the other agents' way (and a collided one, which the world no longer
  integrates, would be an obstacle they pass through unseen by the contact model).

``reset(options={"tasks": {"uav0": {"start": (x, y, yaw), "goal": (x, y)}, ...}})`` sets the tasks of
the named agents; the others are sampled apart from them.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.utils import seeding
from pettingzoo import ParallelEnv

from droneulator.config import SimConfig, fleet
from droneulator.scenes.base import Scene
from droneulator.scenes.collision import sdf_lookup_many
from droneulator.vehicles.vehicle import VehicleState
from droneulator.workflows.rl.backend import CAMERA_NAME, Kinematics
from droneulator.workflows.rl.env import NavTask, env_config

NAME = "droneulator_vineyard_nav_v0"

Info = dict[str, Any]


def parking_spots(scene: Scene, n: int, radius: float, gap: float = 1.0) -> list[np.ndarray]:
    """``n`` ground spots ``gap`` apart in lines along the scene's +y edge (the first ``gap`` inside it),
    each at least ``radius + gap`` from the scene's geometry."""
    col = scene.collision
    lo, hi = scene.bounds_min, scene.bounds_max
    spots: list[np.ndarray] = []
    y = hi[1] - gap
    while len(spots) < n and y > lo[1]:
        xs = np.arange(lo[0] + gap, hi[0] - gap + 1e-9, gap)
        pts = np.column_stack([xs, np.full_like(xs, y), np.full_like(xs, radius + 0.05)])
        clear = sdf_lookup_many(col.sdf, col.origin, col.resolution, pts) >= radius + gap
        spots += [np.array([p[0], p[1], 0.0]) for p in pts[clear]]
        y -= gap
    if len(spots) < n:
        raise ValueError(f"the scene has no room to park {n} vehicles")
    return spots[:n]


class VineyardNavParallelEnv(ParallelEnv[str, np.ndarray, np.ndarray]):
    """Vineyard point-to-point navigation for ``num_agents`` vehicles in one world (see the module
    docstring).

    ``config``: a :class:`SimConfig` (its ``rl`` section and vehicle/flight settings; its ``vehicles``
    are replaced by ``num_agents`` vehicles ``uav0 ..``); ``min_spacing``: the least distance (m) between
    two agents' sampled starts, and between two goals; further keyword arguments replace fields of
    ``config.rl``.
    """

    metadata = {"name": NAME, "render_modes": []}

    def __init__(
        self,
        config: SimConfig | None = None,
        num_agents: int = 2,
        min_spacing: float = 3.0,
        **rl_overrides: Any,
    ) -> None:
        from droneulator.render.pipeline import CameraPipeline
        from droneulator.world import World

        cfg = env_config(config, **rl_overrides)
        cfg.vehicles = fleet(num_agents)
        self.config = cfg
        self.rl = cfg.rl
        self.min_spacing = float(min_spacing)
        self.render_mode: str | None = None
        self.world = World(cfg, render=False, external_cameras=True)
        self.scene = self.world.scene
        vehicles = self.world.vehicles
        self.possible_agents: list[str] = list(vehicles)
        self.agents: list[str] = []
        #: each agent's task and episode state
        self.tasks = {name: NavTask(cfg, self.scene) for name in self.possible_agents}
        self.observation_spaces = {name: t.observation_space for name, t in self.tasks.items()}
        self.action_spaces = {name: t.action_space for name, t in self.tasks.items()}
        #: every live agent's depth camera, each seeing the other vehicles' bodies (one mesh per airframe),
        #: through its depth errors (rl.depth_model; seeded per vehicle)
        self.cameras = CameraPipeline(self.scene, cfg)
        spots = parking_spots(self.scene, num_agents, cfg.vehicle.collision_radius)
        #: where each agent's vehicle waits, motors off, once its episode has ended
        self.parking = dict(zip(self.possible_agents, spots, strict=True))
        self._np_random: np.random.Generator | None = None

    def observation_space(self, agent: str) -> gym.spaces.Box:
        return self.observation_spaces[agent]

    def action_space(self, agent: str) -> gym.spaces.Box:
        return self.action_spaces[agent]

    @property
    def np_random(self) -> np.random.Generator:
        """The generator of starts and goals (seeded by ``reset(seed=...)``, else from OS entropy)."""
        if self._np_random is None:
            self._np_random, _ = seeding.np_random()
        return self._np_random

    # ------------------------------------------------------------------ PettingZoo API
    def reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, Info]]:
        if seed is not None:
            self._np_random, _ = seeding.np_random(seed)
        given = dict((options or {}).get("tasks", {}))
        unknown = set(given) - set(self.possible_agents)
        if unknown:
            raise ValueError(f"options name unknown agents {sorted(unknown)}, not of {self.possible_agents}")
        tasks = {name: self.tasks[name].given_task(task) for name, task in given.items()}
        for name in self.possible_agents:
            if name not in tasks:
                taken = [(t[0], t[2]) for t in tasks.values()]
                tasks[name] = self.tasks[name].sample_task(self.np_random, taken, self.min_spacing)
        first, *others = self.possible_agents
        alt = self.rl.altitude
        start, yaw, *_ = tasks[first]
        self.world.reset(position=np.array([start[0], start[1], alt]), yaw=yaw, airborne=True, vehicle=first)
        for name in others:
            start, yaw, *_ = tasks[name]
            self.world.vehicles[name].place(np.array([start[0], start[1], alt]), yaw, airborne=True)
        self.agents = list(self.possible_agents)
        now = self.world.states_now()
        depth = self._depth(now)
        states = {name: _kinematics(st) for name, st in now.items()}
        obs, infos = {}, {}
        for name, task in self.tasks.items():
            start, yaw, goal, field = tasks[name]
            task.begin(start, yaw, goal, field, states[name])
            obs[name] = task.observe(depth[name], states[name])
            infos[name] = task.step_info(states[name], None, (0.0, 0.0)) | {"collided_with": []}
        return obs, infos

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
        commands = {name: self.tasks[name].check_action(actions[name]) for name in live}
        for name, command in commands.items():
            self.world.vehicles[name].velocity(*command)
        hit: dict[str, list[str]] = {}
        while True:
            res = self.world.step()
            for e in res.events:
                if e.type == "collision":
                    involved = e.data.get("vehicles", [e.vehicle])
                    for name in involved:
                        hit.setdefault(name, []).extend(n for n in involved if n != name)
            if res.camera_states:
                at_frame = {name: res.camera_states[-1][name] for name in live}
                break
        depth = self._depth(at_frame)
        states = {name: _kinematics(st) for name, st in at_frame.items()}
        obs, rewards, terminated, truncated, infos = {}, {}, {}, {}, {}
        for name in live:
            task, kin = self.tasks[name], states[name]
            reward, term, trunc, reason = task.advance(kin, name in hit)
            obs[name] = task.observe(depth[name], kin)
            rewards[name], terminated[name], truncated[name] = reward, term, trunc
            infos[name] = task.step_info(kin, reason, commands[name]) | {"collided_with": hit.get(name, [])}
        self.agents = [name for name in live if not (terminated[name] or truncated[name])]
        for name in live:
            if name not in self.agents:
                self.world.vehicles[name].place(self.parking[name], 0.0, airborne=False)
        return obs, rewards, terminated, truncated, infos

    def _depth(self, states: dict[str, VehicleState]) -> dict[str, np.ndarray]:
        """The depth image of each vehicle in ``states``, drawn in one call, each seeing the others'
        bodies (only theirs: done agents' vehicles are out of the picture)."""
        poses = {name: st.T_world_body for name, st in states.items()}
        frames = self.cameras.frames(poses, rgb=False, copy=False)
        return {name: frames[name][CAMERA_NAME].depth for name in states}

    def close(self) -> None:
        if getattr(self, "cameras", None) is not None:
            self.cameras.close()
            self.cameras = None  # type: ignore[assignment]
        if getattr(self, "world", None) is not None:
            self.world.close()
            self.world = None  # type: ignore[assignment]


def _kinematics(st: VehicleState) -> Kinematics:
    return Kinematics(st.t, st.position, st.quaternion, st.velocity, st.angular_velocity, st.mode)
