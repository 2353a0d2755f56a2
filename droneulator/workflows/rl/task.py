"""The vineyard task's step, written once: reward, termination and observation tail of any number of envs.

Every env of the vineyard task (:class:`~droneulator.workflows.rl.env.VineyardNavEnv`, each agent of
:class:`~droneulator.workflows.rl.multi.VineyardNavParallelEnv` and each env of
:class:`~droneulator.workflows.rl.vector.VineyardNavVectorEnv`) keeps its episode in a :class:`TaskRows`
row and steps it through one compiled kernel (:func:`_task_rows`): a single env is a batch of one.

For each env at its camera instant (a state row in RotorPy's layout, :data:`~droneulator.state.STATE`):

* ``d``: the distance to the goal along the shortest path (the goal's distance field, bilinear; off the
  grid plus the straight distance to it);
* reward ``rl.progress_scale * (d_prev - d) - rl.step_penalty``, plus ``rl.goal_reward`` on reaching
  ``rl.goal_radius`` of the goal, minus ``rl.collision_penalty`` on a collision or leaving the scene's
  bounds; the episode is truncated after its step budget;
* the observation tail: the heading error to the steering target (a carrot ``rl.lookahead`` m along the
  shortest path, or the goal) over pi, the forward speed and the yaw rate normalised like the velocity
  action, each clipped to [-1, 1]; at the levels below velocity (``rl.action`` other than ``"velocity"``,
  :data:`LEVEL_TAIL` more): the body rates over the ``ctbr`` action's
  (:func:`~droneulator.workflows.rl.levels.action_rates`), the direction of gravity in the body frame
  (the attitude's roll and pitch), the lateral (body y) and vertical (world z) speeds over
  :data:`SPEED_SCALE` and the height above ``rl.altitude`` over :data:`HEIGHT_SCALE`, clipped likewise.
"""

from __future__ import annotations

import math
from typing import Any

import numba
import numpy as np

from droneulator.config import SimConfig
from droneulator.frames_numba import quat_to_matrix_into
from droneulator.scenes.base import Scene
from droneulator.state import STATE, STATE_SIZE
from droneulator.workflows.rl.astar import DistanceField, OccupancyGrid, bilinear, carrot
from droneulator.workflows.rl.levels import action_rates

#: where position, velocity, attitude and body rates start in a state row (plain ints for the kernel)
_X, _V, _Q, _W = STATE.x.start, STATE.v.start, STATE.q.start, STATE.w.start
#: why an episode ended (index 0: it goes on)
REASONS = (None, "collision", "out_of_bounds", "goal", "time_limit")
#: the observation tail's size at the velocity level and what the levels below it add
TAIL, LEVEL_TAIL = 3, 9
#: the speed (m/s) and height error (m) that read 1 in the levels' tail
SPEED_SCALE, HEIGHT_SCALE = 2.0, 1.0


def tail_size(action: str) -> int:
    """The observation tail's size at control level ``action`` (``rl.action``)."""
    return TAIL if action == "velocity" else TAIL + LEVEL_TAIL


@numba.njit(cache=True)
def _unit(x: float) -> float:
    return min(max(x, -1.0), 1.0)


@numba.njit(cache=True)
def _node(fx: float, fy: float, nx: int, ny: int) -> tuple[int, int]:
    return min(max(int(np.rint(fx)), 0), nx - 1), min(max(int(np.rint(fy)), 0), ny - 1)


@numba.njit(cache=True, parallel=True)
def _task_rows(
    run, advance, rows, hit, values, nxt, reach, free, near_i, near_j, origin, res, goal, d_prev, steps,
    max_steps, bmin, bmax, k, reward, reason, tail, dist, goal_dist,
):  # fmt: skip
    """For every env where ``run``: with ``advance``, the reward and end of its step (``reward``,
    ``reason``, ``dist``, ``goal_dist``, counting the step); always its observation tail (``tail``); from
    its state at the camera instant (``rows``) and its goal's distance field (``values``, ``nxt``,
    ``reach``). ``k``: progress scale, step penalty, goal reward, collision penalty, goal radius, lookahead
    (m; 0: steer at the goal), forward mid, forward half-range, max yaw rate, the body rates that read 1
    (3), the flight altitude; a ``tail`` wider than :data:`TAIL` takes the levels' part too."""
    nx, ny = free.shape
    for b in numba.prange(run.shape[0]):
        if not run[b]:
            continue
        s = rows[b]
        px, py = s[_X], s[_X + 1]
        fx, fy = (px - origin[0]) / res, (py - origin[1]) / res
        if advance:
            cx, cy = min(max(fx, 0.0), nx - 1.0), min(max(fy, 0.0), ny - 1.0)
            d = bilinear(values[b], cx, cy) + math.hypot(fx - cx, fy - cy) * res
            steps[b] += 1
            r = k[0] * (d_prev[b] - d) - k[1]
            d_prev[b] = d
            dist[b] = d
            gd = math.hypot(px - goal[b, 0], py - goal[b, 1])
            goal_dist[b] = gd
            why = 0
            if hit[b]:
                why = 1
            elif px < bmin[0] or py < bmin[1] or px > bmax[0] or py > bmax[1]:
                why = 2
            elif gd <= k[4]:
                why = 3
            if why == 3:
                r += k[2]
            elif why != 0:
                r -= k[3]
            if why == 0 and steps[b] >= max_steps[b]:
                why = 4
            reward[b] = r
            reason[b] = why
        # the steering target (DistanceField.lookahead, or the goal)
        tx, ty = goal[b, 0], goal[b, 1]
        if k[5] > 0.0:
            i, j = _node(fx, fy, nx, ny)
            if not free[i, j]:
                i, j = near_i[i, j], near_j[i, j]
            if reach[b, i, j]:
                ax, ay = fx, fy
                if not free[_node(fx, fy, nx, ny)]:
                    ax, ay = float(i), float(j)
                a, c, reached = carrot(free, nxt[b], i, j, ax, ay, k[5] / res)
                if not reached:
                    tx, ty = origin[0] + a * res, origin[1] + c * res
        # heading, forward speed (body x) and yaw rate (world z) from the attitude (frames_numba)
        R = np.empty((3, 3))
        quat_to_matrix_into(s[_Q : _Q + 4], R)
        yaw = math.atan2(R[1, 0], R[0, 0])
        heading = ((math.atan2(ty - py, tx - px) - yaw + math.pi) % (2 * math.pi) - math.pi) / math.pi
        forward = R[0, 0] * s[_V] + R[1, 0] * s[_V + 1] + R[2, 0] * s[_V + 2]
        yaw_rate = R[2, 0] * s[_W] + R[2, 1] * s[_W + 1] + R[2, 2] * s[_W + 2]
        tail[b, 0] = _unit(heading)
        tail[b, 1] = _unit((forward - k[6]) / k[7])
        tail[b, 2] = _unit(yaw_rate / k[8])
        if tail.shape[1] > 3:
            for j in range(3):
                tail[b, 3 + j] = _unit(s[_W + j] / k[9 + j])
                tail[b, 6 + j] = -R[2, j]  # gravity's direction (world -z) in the body frame
            lateral = R[0, 1] * s[_V] + R[1, 1] * s[_V + 1] + R[2, 1] * s[_V + 2]
            tail[b, 9] = _unit(lateral / SPEED_SCALE)
            tail[b, 10] = _unit(s[_V + 2] / SPEED_SCALE)
            tail[b, 11] = _unit((s[_X + 2] - k[12]) / HEIGHT_SCALE)


def state_row(position: Any, quaternion: Any, velocity: Any, angular_velocity: Any) -> np.ndarray:
    """A state row (:data:`~droneulator.state.STATE`) with the parts the task reads."""
    s = np.zeros(STATE_SIZE)
    s[STATE.x], s[STATE.q], s[STATE.v], s[STATE.w] = position, quaternion, velocity, angular_velocity
    return s


class TaskRows:
    """The episodes of ``num_envs`` envs of the task of ``config`` on a grid of ``grid``'s shape: each
    env's goal and its distance field, its distance, step count and budget, and the last step's outputs
    (``reward``, ``reason`` (index into :data:`REASONS`), ``tail``, ``dist``, ``goal_dist``)."""

    def __init__(self, config: SimConfig, grid: OccupancyGrid, num_envs: int) -> None:
        rl = config.rl
        n = num_envs
        mid = 0.5 * (rl.forward_min + rl.forward_max)
        half = 0.5 * (rl.forward_max - rl.forward_min)
        self.k = np.array([
            rl.progress_scale, rl.step_penalty, rl.goal_reward, rl.collision_penalty, rl.goal_radius,
            rl.lookahead if rl.heading == "path" else 0.0, mid, half, rl.max_yaw_rate,
            *action_rates(config), rl.altitude,
        ])  # fmt: skip
        shape = (n, *grid.shape) if n > 1 else (1, 1, 1)  # one env flies on its field's own arrays
        self.values = np.zeros(shape)
        self.next = np.zeros(shape, dtype=np.int32)
        self.reach = np.zeros(shape, dtype=bool)
        self.goal = np.zeros((n, 2))
        self.d = np.zeros(n)
        self.steps = np.zeros(n, dtype=np.int64)
        self.max_steps = np.zeros(n, dtype=np.int64)
        self.reward = np.zeros(n)
        self.reason = np.zeros(n, dtype=np.int64)
        self.tail = np.zeros((n, tail_size(rl.action)))
        self.dist = np.zeros(n)
        self.goal_dist = np.zeros(n)

    def begin(
        self, i: int, field: DistanceField, goal: np.ndarray, position: np.ndarray, d0: float, max_steps: int
    ) -> None:
        """Env ``i`` starts an episode at ``position`` toward ``goal`` (its distance field ``field``), ``d0``
        from it along the path, with ``max_steps`` steps."""
        if len(self.d) == 1:  # one env: the field's own arrays, no copy
            self.values, self.next, self.reach = field.values[None], field.next[None], field.reachable[None]
        else:
            self.values[i], self.next[i], self.reach[i] = field.values, field.next, field.reachable
        self.goal[i] = goal
        self.d[i] = self.dist[i] = d0
        self.goal_dist[i] = math.hypot(position[0] - goal[0], position[1] - goal[1])
        self.steps[i] = 0
        self.max_steps[i] = max_steps
        self.reward[i] = 0.0
        self.reason[i] = 0

    def step(
        self, run: Any, rows: np.ndarray, hit: Any, grid: OccupancyGrid, scene: Scene, advance: bool
    ) -> None:
        """The envs where ``run``, now in state ``rows`` (``hit``: collided meanwhile), flying on ``grid``
        in ``scene``: with ``advance`` their step's reward and end, always their observation tail."""
        near = grid.nearest
        run, hit = np.asarray(run, dtype=bool), np.asarray(hit, dtype=bool)
        _task_rows(
            run, advance, rows, hit, self.values, self.next, self.reach, grid.free, near[0], near[1],
            grid.origin, grid.resolution, self.goal, self.d, self.steps, self.max_steps,
            scene.bounds_min[:2], scene.bounds_max[:2], self.k, self.reward, self.reason, self.tail,
            self.dist, self.goal_dist,
        )  # fmt: skip
