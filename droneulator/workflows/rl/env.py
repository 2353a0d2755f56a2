"""``droneulator/VineyardNav-v0``: point-to-point flight through the vineyard on a depth strip (§III-C).

Spaces (both float32):

* **Observation** (35,): ``[0:32]`` the depth strip, the centre row of the depth image min-pooled
  into 32 equal sectors of the field of view (the nearest return in each, so a thin post is never
  skipped), clipped at ``rl.depth_clip`` and divided by it (NaN, no return: 1.0); ``[32]`` heading
  error to the target divided by pi, in [-1, 1] (positive: turn left); ``[33]`` measured forward
  speed (body x) and ``[34]`` measured yaw rate (world z), normalised like the action and clipped.
  The target is a point ``rl.lookahead`` m along the shortest path to the goal (``rl.heading =
  "path"``, default: the global planner's guidance, so a goal behind a vine row is reached round the
  row end) or the goal itself (``"goal"``).
* **Action** (2,) in [-1, 1]: forward speed ``mid + a0 * half`` with ``mid, half`` the centre and
  half-width of ``[rl.forward_min, rl.forward_max]`` (default [-2, 3] m/s: a0 = 0 means 0.5 m/s)
  and yaw rate ``a1 * rl.max_yaw_rate`` (default 1.5 rad/s), sent through the velocity mode, which
  holds the altitude. ``rl.action`` chooses a level below it (``ctbr``, ``attitude``, ``rotors``: four
  numbers in [-1, 1], :mod:`.levels`); the observation then has 9 more entries after ``[34]``: body rates,
  gravity's direction in the body frame, lateral and vertical speed and the height error (:mod:`.task`).

One step is one camera frame (``render.camera_hz``, 30 Hz sim time): the command is applied and the
simulation runs in lockstep up to the next camera instant. Reward: ``rl.progress_scale * (d_prev -
d) - rl.step_penalty``, plus ``rl.goal_reward`` on reaching ``rl.goal_radius`` of the goal, minus
``rl.collision_penalty`` on a collision (the simulator's event) or on leaving the flyable bounds;
``d`` is the shortest-path distance to the goal on the occupancy grid (:mod:`.astar`). Episodes are
truncated after ``rl.time_limit_base_s + d0 / rl.min_average_speed`` seconds of sim time.

``mode="local"`` (default) steps an in-process :class:`~droneulator.world.World` and draws depth only
(the camera pipeline, :mod:`droneulator.render.pipeline`); ``mode="remote"`` drives a running
``droneulator run`` (:mod:`.remote`). Both return the depth image and the vehicle state, and the
observation is built from them by the same code. ``reset(options={"start": (x, y, yaw), "goal": (x,
y)})`` sets the task explicitly.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np

from droneulator.config import CameraConfig, RLConfig, SimConfig, load_config
from droneulator.config.randomize import Draw
from droneulator.frames import wrap_angle
from droneulator.render.pipeline import DEPTH_SOURCES
from droneulator.scenes.base import Scene
from droneulator.workflows.rl.astar import DistanceField, OccupancyGrid, occupancy_from_scene
from droneulator.workflows.rl.backend import CAMERA_NAME, SCENE, Backend, Kinematics
from droneulator.workflows.rl.levels import Actuator
from droneulator.workflows.rl.task import REASONS, TaskRows, state_row, tail_size

STRIP_SAMPLES = 32
#: the observation's size at the velocity level (:func:`obs_size` for any)
OBS_SIZE = STRIP_SAMPLES + 3


def obs_size(action: str) -> int:
    """The observation's size at control level ``action`` (``rl.action``)."""
    return STRIP_SAMPLES + tail_size(action)


_GRIDS: dict[tuple[Any, ...], OccupancyGrid] = {}


def rl_camera(rl: RLConfig) -> CameraConfig:
    """The RL depth camera: level, at the default mount, far plane at the depth clip, ``rl.depth_model``'s
    errors."""
    size = (rl.camera_width, rl.camera_height)
    return CameraConfig(CAMERA_NAME, *size, rl.hfov_deg, far=rl.depth_clip, depth_model=rl.depth_model)


def env_config(config: SimConfig | None = None, **rl_overrides: Any) -> SimConfig:
    """A copy of ``config`` set up for the environment: vineyard scene, the RL camera only, at its rate
    (one frame a step, never triggered), no shadows (depth is unaffected), ``rl`` fields replaced by
    ``rl_overrides``, ``vehicle.substeps`` set to ``rl.substeps``'s (resolved at this level: a config made
    here keeps it, so change ``rl.action`` before calling this, not on its result). The scene's seed and
    vegetation stay the config's (applying this twice changes nothing): with domain randomisation of the
    scene the environment flies in :func:`scene_variants` of it."""
    cfg = copy.deepcopy(config) if config is not None else load_config()
    cfg.scene = SCENE
    if rl_overrides:
        cfg.rl = dataclasses.replace(cfg.rl, **rl_overrides)
    cfg.vehicle.substeps = cfg.rl.substeps_for(cfg.vehicle.substeps)
    cfg.render.cameras = [rl_camera(cfg.rl)]
    cfg.render.shadows = False
    cfg.render.camera_trigger = "rate"
    return cfg


def scene_variants(cfg: SimConfig) -> list[SimConfig]:
    """The configs of the scenes an environment of ``cfg`` flies its episodes in: ``cfg`` alone, or with
    domain randomisation of the scene (``randomize.scene_seed``, ``randomize.vegetation``) one per scene
    of :meth:`~droneulator.config.RandomizeConfig.scene_variants_of` (their seed is the layout's). Every
    environment made from ``cfg`` gets the same ones, so a batched env and the single env agree."""
    variants = cfg.randomize.scene_variants_of(cfg.seed, cfg.vegetation)
    if variants == [(cfg.seed, cfg.vegetation)]:
        return [cfg]
    out = []
    for seed, vegetation in variants:
        c = copy.deepcopy(cfg)
        c.seed, c.vegetation = seed, vegetation
        out.append(c)
    return out


def runtime_overrides(cfg: SimConfig) -> list[str]:
    """``--set`` options for ``droneulator run`` so that its camera matches the RL camera (remote mode)."""
    cam = rl_camera(cfg.rl)
    model = "" if cam.depth_model == "ideal" else f', "depth_model": "{cam.depth_model}"'
    spec = (
        f'[{{"name": "{cam.name}", "width": {cam.width}, "height": {cam.height}, '
        f'"hfov_deg": {cam.hfov_deg}, "far": {cam.far}{model}}}]'
    )
    substeps = cfg.rl.substeps_for(cfg.vehicle.substeps)
    return [f"render.cameras={spec}", "render.shadows=false", "render.camera_trigger=rate",
            f"vehicle.substeps={substeps}"]  # fmt: skip


def depth_strip(depth: np.ndarray, clip: float, samples: int = STRIP_SAMPLES) -> np.ndarray:
    """The centre row (row ``h // 2``) of a depth image min-pooled into ``samples`` equal sectors,
    clipped at ``clip`` and divided by it; NaN (no return) reads 1.0."""
    return strips(np.asarray(depth)[depth.shape[0] // 2][None], clip, samples)[0]


def strips(rows: np.ndarray, clip: float, samples: int = STRIP_SAMPLES) -> np.ndarray:
    """:func:`depth_strip` of many centre rows at once: ``(k, width)`` depth rows -> ``(k, samples)``."""
    rows = np.asarray(rows, dtype=np.float64)
    if rows.shape[1] < samples:
        raise ValueError(f"a depth image {rows.shape[1]} px wide cannot give {samples} strip samples")
    rows = np.where(np.isnan(rows), clip, np.minimum(rows, clip))
    edges = np.linspace(0, rows.shape[1], samples + 1).round().astype(int)
    return (np.minimum.reduceat(rows, edges[:-1], axis=1) / clip).astype(np.float32)


class LocalBackend:
    """An in-process world (physics only, camera instants scheduled) and the camera pipeline's depth, drawn
    by the renderer or by ray casting (``depth="raycast"``)."""

    def __init__(self, cfg: SimConfig, depth: str = "render") -> None:
        from droneulator.render.pipeline import CameraPipeline
        from droneulator.world import World

        if depth not in DEPTH_SOURCES:
            raise ValueError(f"depth must be one of {', '.join(DEPTH_SOURCES)}, got {depth!r}")
        self.world = World(cfg, render=False, external_cameras=True)
        self.vehicle = self.world.vehicle()
        self.scene = self.world.scene
        self.cameras = CameraPipeline(self.scene, cfg, source=depth)
        #: the depth preset of the episode and its noise and dropout factors (``rl.depth_model``'s camera,
        #: or randomisation's draw)
        cam = cfg.render.cameras[0]
        self.depth_model = cam.depth_model
        self.depth_scales = np.array([[cam.depth_noise_scale, cam.depth_dropout_scale]])
        #: the episode's rotor efficiencies (randomisation's draw), set again after the world's reset
        self.rotor_efficiency = np.ones(4)

    def randomize(self, draw: Draw) -> None:
        """Fly the next episode in the conditions of ``draw``: its wind, depth camera and rotor efficiency."""
        self.world.set_wind(draw.wind)
        self.rotor_efficiency = np.asarray(draw.rotor_efficiency, dtype=float)
        self.depth_model = draw.depth_model
        self.depth_scales = np.array([[draw.depth_noise_scale, draw.depth_dropout_scale]])

    def _depth(self, T_world_body: np.ndarray) -> np.ndarray:
        return self.cameras.depth(T_world_body[None], [self.depth_model], self.depth_scales)[0]

    @staticmethod
    def _kinematics(st: Any) -> Kinematics:
        return Kinematics(st.t, st.position, st.quaternion, st.velocity, st.angular_velocity, st.mode)

    def reset(self, position: np.ndarray, yaw: float) -> tuple[np.ndarray, Kinematics]:
        st = self.world.reset(position=np.asarray(position, dtype=float), yaw=float(yaw), airborne=True)
        self.world.rotor_efficiency[0, 0] = self.rotor_efficiency  # a reset makes every rotor whole
        return self._depth(st.T_world_body), self._kinematics(st)

    def step(self, forward: float, yaw_rate: float) -> tuple[np.ndarray, Kinematics, bool]:
        self.vehicle.velocity(forward, yaw_rate)
        return self._frame()

    def fly(self, actuator: Actuator, command: np.ndarray) -> tuple[np.ndarray, Kinematics, bool]:
        """:meth:`step` with a command of ``actuator``'s control level."""
        actuator.send_vehicle(self.vehicle, command)
        return self._frame()

    def _frame(self) -> tuple[np.ndarray, Kinematics, bool]:
        """Run to the next camera instant: its depth image and state, and whether a collision happened."""
        name = self.vehicle.name
        collided = False
        while True:
            res = self.world.step()
            collided = collided or any(e.type == "collision" for e in res.events)
            if res.camera_states:
                st = res.camera_states[-1][name]
                return self._depth(st.T_world_body), self._kinematics(st), collided

    def close(self) -> None:
        self.cameras.close()
        self.world.close()


#: the run mask and the index of a batch of one
_ONE = np.ones(1, dtype=bool)
_FIRST = np.zeros(1, dtype=np.int64)


def _row(kin: Kinematics) -> np.ndarray:
    """``kin`` as a batch of one state row."""
    return state_row(kin.position, kin.quaternion, kin.velocity, kin.angular_velocity)[None]


class NavTask:
    """One vehicle's navigation task: the spaces, the action mapping, the observation, task sampling and
    the reward and termination of a step, with that vehicle's episode state.

    Kept apart from any backend so that :class:`VineyardNavEnv` (which is one) and
    :class:`~droneulator.workflows.rl.multi.VineyardNavParallelEnv` (which holds one per vehicle) share
    every rule of the task.
    """

    def __init__(self, config: SimConfig, scene: Scene) -> None:
        self.config = config
        self.rl = config.rl
        self.use_scene(scene)
        self.frame_dt = 1.0 / config.render.camera_hz
        size = obs_size(self.rl.action)
        low = np.concatenate([np.zeros(STRIP_SAMPLES), -np.ones(size - STRIP_SAMPLES)]).astype(np.float32)
        self.observation_space = gym.spaces.Box(low, np.ones(size, dtype=np.float32), dtype=np.float32)
        #: this env's action at ``rl.action``'s level (:mod:`.levels`), a batch of one
        self.actuator = Actuator(config, 1)
        self.action_space = self.actuator.space
        self._mid = 0.5 * (self.rl.forward_min + self.rl.forward_max)
        self._half = 0.5 * (self.rl.forward_max - self.rl.forward_min)
        self.field: DistanceField | None = None
        self.goal = np.zeros(2)
        self.start = np.zeros(3)
        self.max_steps = 0
        #: the episode's row of the task kernel (:mod:`.task`): this env is a batch of one
        self.rows = TaskRows(config, self.grid, 1)
        #: the vehicle state of the latest observation
        self.kinematics: Kinematics | None = None
        self.initial_distance = 0.0

    def use_scene(self, scene: Scene) -> None:
        """Fly the next tasks in ``scene`` (a scene variant of domain randomisation): its occupancy grid,
        alleys and rows."""
        self.scene = scene
        self.grid = occupancy_grid(scene, self.rl, self.config.vehicle.collision_radius)
        lm = scene.landmarks
        rows = np.asarray(lm["row_y"], dtype=float)
        spacing = float(rows[1] - rows[0]) if len(rows) > 1 else 3.0
        self.lanes = np.sort(np.concatenate([lm["alley_y"], [rows[0] - spacing / 2, rows[-1] + spacing / 2]]))
        self.row_x = (float(lm["row_x_min"][0]), float(lm["row_x_max"][0]))

    # ------------------------------------------------------------------ mappings
    def action_to_command(self, action: np.ndarray) -> tuple[float, float]:
        """Normalised action in [-1, 1]^2 -> (forward speed m/s, yaw rate rad/s)."""
        a = np.clip(np.asarray(action, dtype=np.float64).reshape(2), -1.0, 1.0)
        return float(self._mid + a[0] * self._half), float(a[1] * self.rl.max_yaw_rate)

    def command_to_action(self, forward: float, yaw_rate: float) -> np.ndarray:
        """Inverse of :meth:`action_to_command` (clipped to the action space)."""
        a = [(forward - self._mid) / self._half, yaw_rate / self.rl.max_yaw_rate]
        return np.clip(np.array(a, dtype=np.float32), -1.0, 1.0)

    def check_action(self, action: Any) -> np.ndarray:
        """The command for ``action`` at ``rl.action``'s level (:mod:`.levels`); a ValueError unless it
        is finite numbers of the action's size. Advances the attitude level's yaw setpoint."""
        try:
            a = self.actuator.check(action, 1)
        except ValueError:
            size = self.action_space.shape[0]
            raise ValueError(f"action must be {size} finite numbers, got {action!r}") from None
        return self.actuator.map(_FIRST, a)[0]

    def target(self, position: np.ndarray) -> np.ndarray:
        """The point the heading error refers to (see ``rl.heading``)."""
        assert self.field is not None
        if self.rl.heading == "goal":
            return self.goal
        return self.field.lookahead(position[:2], self.rl.lookahead)

    def observe(self, depth: np.ndarray, kin: Kinematics) -> np.ndarray:
        """The observation vector from a depth image and the vehicle state (both backends)."""
        return np.concatenate([depth_strip(depth, self.rl.depth_clip), self.tail(kin)])

    def tail(self, kin: Kinematics) -> np.ndarray:
        """The observation after the strip: heading error, forward speed and yaw rate, normalised (the task
        kernel's, :mod:`.task`)."""
        self.rows.step(_ONE, _row(kin), ~_ONE, self.grid, self.scene, advance=False)
        return self.rows.tail[0].astype(np.float32)

    # ------------------------------------------------------------------ tasks
    def _lane_point(self, rng: np.random.Generator, lane: int) -> np.ndarray:
        x0, x1 = self.row_x
        return np.array([rng.uniform(x0 + 1.0, x1 - 1.0), self.lanes[lane] + rng.uniform(-0.3, 0.3)])

    def _headland_point(self, rng: np.random.Generator) -> np.ndarray:
        x0, x1 = self.row_x
        x = x1 + rng.uniform(1.5, 6.0) if rng.random() < 0.5 else x0 - rng.uniform(1.5, 6.0)
        return np.array([x, rng.uniform(self.lanes[0], self.lanes[-1])])

    def sample_task(
        self,
        rng: np.random.Generator,
        taken: Sequence[tuple[np.ndarray, np.ndarray]] = (),
        spacing: float = 0.0,
    ) -> tuple[np.ndarray, float, np.ndarray, DistanceField]:
        """Random start (x, y), start yaw, goal (x, y) and the goal's distance field.

        Goals lie in an alley (85 %) or a headland; starts, for a goal in an alley, lie in another
        alley with probability ``rl.other_row_prob`` (the route then turns round a row end), else in
        the same alley or a headland. Both are free, the start is reachable and the shortest path
        length lies in ``[rl.min_separation, rl.max_path_length]``. The start faces the first leg of
        the shortest path, give or take ``rl.start_yaw_std_deg`` (one standard deviation).
        ``taken``: the (start, goal) of other vehicles; the goal lies at least ``spacing`` from theirs,
        and the start from theirs (so that vehicles sharing a world begin apart and aim apart).
        """
        n = len(self.lanes)

        def apart(p: np.ndarray, k: int) -> bool:
            return all(math.hypot(*(p - other[k][:2])) >= spacing for other in taken)

        for _ in range(200):
            goal_lane = int(rng.integers(n)) if rng.random() < 0.85 else -1
            goal = self._lane_point(rng, goal_lane) if goal_lane >= 0 else self._headland_point(rng)
            if not (self.grid.is_free(goal) and apart(goal, 1)):
                continue
            field = DistanceField(self.grid, goal)
            for _ in range(30):
                if goal_lane < 0:
                    start = self._lane_point(rng, int(rng.integers(n)))
                elif rng.random() < self.rl.other_row_prob:
                    start = self._lane_point(rng, int(rng.choice([k for k in range(n) if k != goal_lane])))
                elif rng.random() < 0.5:
                    start = self._lane_point(rng, goal_lane)
                else:
                    start = self._headland_point(rng)
                if not (self.grid.is_free(start) and field.is_reachable(start) and apart(start, 0)):
                    continue
                d0 = field.distance(start)
                if self.rl.min_separation <= d0 <= self.rl.max_path_length:
                    carrot = field.lookahead(start, self.rl.lookahead)
                    yaw = math.atan2(carrot[1] - start[1], carrot[0] - start[0])
                    yaw += rng.normal(0.0, math.radians(self.rl.start_yaw_std_deg))
                    return start, wrap_angle(yaw), goal, field
        raise RuntimeError("could not sample a start and goal: check the rl.* sampling settings")

    def meeting_task(
        self, rng: np.random.Generator, position: np.ndarray, goal: np.ndarray, spread: float = 1.0
    ) -> tuple[np.ndarray, float, np.ndarray, DistanceField] | None:
        """A task against another vehicle at ``position`` bound for ``goal``: start within ``spread`` m of
        ``goal``, goal within ``spread`` m of ``position`` (free, reachable, a path length in
        :meth:`sample_task`'s range), so that the two fly one route in opposite directions; None if no
        draw of 30 is one."""
        for _ in range(30):
            start = np.asarray(goal, dtype=float)[:2] + rng.uniform(-spread, spread, 2)
            aim = np.asarray(position, dtype=float)[:2] + rng.uniform(-spread, spread, 2)
            if not (self.grid.is_free(start) and self.grid.is_free(aim)):
                continue
            field = DistanceField(self.grid, aim)
            if not field.is_reachable(start):
                continue
            if self.rl.min_separation <= field.distance(start) <= self.rl.max_path_length:
                carrot = field.lookahead(start, self.rl.lookahead)
                yaw = math.atan2(carrot[1] - start[1], carrot[0] - start[0])
                yaw += rng.normal(0.0, math.radians(self.rl.start_yaw_std_deg))
                return start, wrap_angle(yaw), aim, field
        return None

    def given_task(self, task: dict[str, Any]) -> tuple[np.ndarray, float, np.ndarray, DistanceField]:
        """The task of ``{"start": (x, y, yaw), "goal": (x, y)}`` in :meth:`sample_task`'s form."""
        if not ("start" in task and "goal" in task):
            raise ValueError("options need both 'start' (x, y, yaw) and 'goal' (x, y)")
        sx, sy, yaw = (float(v) for v in task["start"])
        goal = np.asarray(task["goal"], dtype=float)[:2]
        return np.array([sx, sy]), yaw, goal, DistanceField(self.grid, goal)

    # ------------------------------------------------------------------ episodes
    def begin(
        self,
        start: np.ndarray,
        yaw: float,
        goal: np.ndarray,
        field: DistanceField,
        kin: Kinematics,
        rows: TaskRows | None = None,
        i: int = 0,
    ) -> None:
        """Start an episode on a task, the vehicle placed at the start with state ``kin``; its row is row
        ``i`` of ``rows`` (a batched env's) or this task's own."""
        self.field, self.goal = field, goal.copy()
        self.start = np.array([start[0], start[1], yaw])
        self.kinematics = kin
        self.actuator.begin(0, yaw)
        self.initial_distance = field.distance(kin.position)
        limit_s = self.rl.time_limit_base_s + self.initial_distance / self.rl.min_average_speed
        self.max_steps = math.ceil(limit_s / self.frame_dt)
        (self.rows if rows is None else rows).begin(
            i, field, self.goal, kin.position, self.initial_distance, self.max_steps
        )

    def advance(self, kin: Kinematics, collided: bool) -> tuple[float, bool, bool, str | None]:
        """One step's ``(reward, terminated, truncated, reason)`` for the vehicle now in state ``kin``,
        ``collided`` if it hit something meanwhile (the task kernel's, :mod:`.task`)."""
        assert self.field is not None
        self.kinematics = kin
        hit = np.array([collided or kin.mode == "collided"])
        self.rows.step(_ONE, _row(kin), hit, self.grid, self.scene, advance=True)
        reason = REASONS[int(self.rows.reason[0])]
        truncated = reason == "time_limit"
        return float(self.rows.reward[0]), reason is not None and not truncated, truncated, reason

    def step_info(
        self, kin: Kinematics, reason: str | None, command: Sequence[float] | np.ndarray
    ) -> dict[str, Any]:
        """The info dict of a step (of a reset: ``reason`` None, ``command`` zero); ``command`` is the
        level's (:data:`~droneulator.workflows.rl.levels.COMMAND_SIZE`)."""
        return {
            "t": kin.t,
            "position": kin.position.copy(),
            "yaw": kin.yaw,
            "command": tuple(float(c) for c in command),
            "distance": float(self.rows.d[0]),
            "goal_distance": float(math.hypot(*(kin.position[:2] - self.goal))),
            "termination": reason,
            "is_success": reason == "goal",
        }


class VineyardNavEnv(NavTask, gym.Env[np.ndarray, np.ndarray]):
    """Vineyard point-to-point navigation (see the module docstring for spaces, reward and episodes).

    ``config``: a :class:`SimConfig` (its ``rl`` section and vehicle/flight settings are used);
    ``mode``: "local" or "remote" (then ``url`` of the WebSocket API and ``zenoh`` endpoint of the
    bridge); ``depth`` (local mode): ``"render"`` or ``"raycast"`` (:data:`DEPTH_SOURCES`); further keyword
    arguments replace fields of ``config.rl``. With domain randomisation of the scene each reset draws
    one of :func:`scene_variants` (a backend for each, built the first time it is drawn).
    """

    metadata = {"render_modes": [], "render_fps": 30}

    def __init__(
        self,
        config: SimConfig | None = None,
        mode: str = "local",
        url: str | None = None,
        zenoh: str | None = None,
        depth: str = "render",
        **rl_overrides: Any,
    ) -> None:
        cfg = env_config(config, **rl_overrides)
        self.mode = mode
        if cfg.randomize.enabled and mode != "local":
            raise ValueError("domain randomisation (randomize.enabled) needs mode='local'")
        if cfg.rl.action != "velocity" and mode != "local":
            raise ValueError(f"rl.action = {cfg.rl.action!r} needs mode='local' (remote mode flies velocity)")
        self.variants = scene_variants(cfg)
        self._backends: dict[int, Backend] = {}
        self._depth = depth
        if mode == "local":
            backend: Backend = LocalBackend(self.variants[0], depth)
            self._backends[0] = backend
        elif mode == "remote":
            from droneulator.workflows.rl.remote import RemoteBackend

            backend = RemoteBackend(cfg, url or "ws://127.0.0.1:8765", zenoh)
        else:
            raise ValueError(f"mode must be 'local' or 'remote', got {mode!r}")
        self.backend = backend
        super().__init__(cfg, backend.scene)

    # ------------------------------------------------------------------ gymnasium API
    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        gym.Env.reset(self, seed=seed)
        opts = options or {}
        variant = self.variants[0]
        if len(self.variants) > 1:
            k = int(self.np_random.integers(len(self.variants)))
            if k not in self._backends:
                self._backends[k] = LocalBackend(self.variants[k], self._depth)
            self.backend, variant = self._backends[k], self.variants[k]
            self.use_scene(self.backend.scene)
        if "start" in opts or "goal" in opts:
            start, yaw, goal, field = self.given_task(opts)
        else:
            start, yaw, goal, field = self.sample_task(self.np_random)
        if self.config.randomize.enabled:
            draw = self.config.randomize.draw(self.np_random, self.config.wind)
            scene = {"scene_seed": variant.seed, "vegetation": variant.vegetation}
            self.conditions = dataclasses.replace(draw, **scene)
            self.backend.randomize(self.conditions)  # type: ignore[attr-defined]
        depth, kin = self.backend.reset(np.array([start[0], start[1], self.rl.altitude]), yaw)
        self.begin(start, yaw, goal, field, kin)
        return self.observe(depth, kin), self.step_info(kin, None, self.actuator.commands[0])

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        if self.field is None:
            raise RuntimeError("call reset() before step()")
        command = self.check_action(action)
        if self.rl.action == "velocity":
            depth, kin, collided = self.backend.step(float(command[0]), float(command[1]))
        else:
            depth, kin, collided = self.backend.fly(self.actuator, command)  # type: ignore[attr-defined]
        reward, terminated, truncated, reason = self.advance(kin, collided)
        return self.observe(depth, kin), reward, terminated, truncated, self.step_info(kin, reason, command)

    def close(self) -> None:
        backends = getattr(self, "_backends", {}) or {0: getattr(self, "backend", None)}
        for backend in backends.values():
            if backend is not None:
                backend.close()
        self._backends = {}
        self.backend = None  # type: ignore[assignment]
        super().close()


def occupancy_grid(scene: Scene, rl: RLConfig, collision_radius: float) -> OccupancyGrid:
    """The scene's occupancy grid at the RL altitude, inflated by the vehicle radius plus the safety
    margin; built once per process for each scene and setting."""
    key = (scene.name, scene.seed, rl.altitude, collision_radius + rl.safety_margin, rl.grid_resolution)
    if key not in _GRIDS:
        _GRIDS[key] = occupancy_from_scene(scene, rl.altitude, key[3], rl.grid_resolution)
    return _GRIDS[key]
