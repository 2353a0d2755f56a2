"""The local planner: depth images into the rolling map, A*-guided B-spline plans, replanning checks."""

from __future__ import annotations

import dataclasses
import logging
import math
import time

import numpy as np

from droneulator import frames
from droneulator.workflows.planning.astar import astar
from droneulator.workflows.planning.bspline import (
    BSpline,
    Pairs,
    Weights,
    optimize,
    reallocate_time,
    start_points,
    straight_line,
)
from droneulator.workflows.planning.config import PlannerConfig
from droneulator.workflows.planning.mapping import LocalMap

log = logging.getLogger(__name__)


class Planner:
    """Maps from depth alone and plans EGO-style B-splines in the map; ``reason`` says why a plan failed."""

    def __init__(self, config: PlannerConfig | None = None, centre: np.ndarray | None = None) -> None:
        self.cfg = config or PlannerConfig()
        self.map = LocalMap(self.cfg, centre)
        self.weights = Weights(self.cfg.lambda_smooth, self.cfg.lambda_collision, self.cfg.lambda_feasibility)
        self.reason = ""
        self.goal: np.ndarray | None = None

    def update_map(self, depth: np.ndarray, T_world_optical: np.ndarray, K: np.ndarray) -> int:
        """Integrate one depth image (32FC1 metres, NaN = no return); returns the voxel updates."""
        return self.map.update(depth, T_world_optical, K)

    def _fail(self, reason: str) -> None:
        self.reason = reason
        return None

    def _optimize(self, traj: BSpline, pairs: Pairs) -> BSpline:
        """One L-BFGS run with the configured limits, weights and stopping rule."""
        c = self.cfg
        limits = (c.safety_extra, c.max_vel, c.max_acc)
        return optimize(traj, pairs, *limits, self.weights, c.opt_max_iters, c.opt_ftol)

    def _colliding(self, traj: BSpline, t_from: float = 0.0) -> np.ndarray:
        """Sample times from ``t_from`` on where ``traj`` is inside the inflated map.

        A start inside the inflation (after passing close by) cannot be helped: the first stretch
        is not counted while it stays within two inflation radii of the start and out of the
        obstacle itself, so a curve that leaves is fine and one that goes in still collides."""
        t = traj.sample(0.5 * self.cfg.resolution / self.cfg.max_vel)
        t = t[t >= t_from]
        pos = traj.position(t)
        occ = self.map.is_occupied(pos)
        if len(occ) and occ[0]:
            near = np.linalg.norm(pos - pos[0], axis=1) <= 2 * self.cfg.obstacle_inflation
            exempt = occ & near & ~self.map.is_occupied(pos, inflated=False)
            occ[: int(np.argmin(exempt)) if not exempt.all() else len(occ)] = False
        return t[occ]

    def _anchor(self, q: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """EGO's {p, v}: v from q towards the guide path, p where that line leaves the inflated obstacle."""
        v = target - q
        dist = float(np.linalg.norm(v))
        if dist < 1e-6:
            return None
        v /= dist
        step = 0.5 * self.cfg.resolution
        if self.map.is_occupied(q):
            s = np.arange(0.0, dist + step, step)
            free = ~self.map.is_occupied(q + s[:, None] * v)
            if not free.any():
                return None
            return q + s[np.argmax(free)] * v, v
        s = np.arange(0.0, 2 * self.cfg.inflation + step, step)
        occ = self.map.is_occupied(q - s[:, None] * v)
        if not occ.any():
            return None
        return q - s[max(np.argmax(occ) - 1, 0)] * v, v

    def _add_pairs(self, traj: BSpline, times: np.ndarray, pairs: Pairs) -> bool:
        """A* round the colliding stretch, then anchors for its control points; False if no path."""
        n = len(traj.ctrl)
        seg = np.minimum((times / traj.dt).astype(int), n - 4)
        idx = sorted({int(i) for s in seg for i in range(s, s + 4) if 3 <= i < n - 3})
        if not idx:
            return True
        t_all = traj.sample(0.5 * self.cfg.resolution / self.cfg.max_vel)
        before = t_all[t_all < times.min()]
        after = t_all[t_all > times.max()]
        a = traj.position(before[-1] if len(before) else 0.0)
        b = traj.position(after[0] if len(after) else traj.duration)
        if not (self.map.inside(a) and self.map.inside(b)):
            return False
        blocked = self.map.count  # non-zero within the inflation radius; no bool copy of the grid
        # a start (or end) inside the inflation, e.g. after passing close by, is searched from the
        # nearest free voxel: the optimiser then pushes the curve out of the inflation
        reach = self.cfg.obstacle_inflation + self.cfg.resolution
        ia, ib = self.map.index(a), self.map.index(b)
        ia = ia if not blocked[tuple(ia)] else self.map.nearest_free(ia, reach)
        ib = ib if not blocked[tuple(ib)] else self.map.nearest_free(ib, reach)
        if ia is None or ib is None:
            return False
        margin = int(np.ceil(self.cfg.astar_margin / self.cfg.resolution))
        path = astar(blocked, ia, ib, self.cfg.astar_max_expansions, margin)
        if len(path) == 0:
            return False
        guide = self.map.point(path)
        for i in idx:
            q = traj.ctrl[i]
            tangent = traj.ctrl[i + 1] - traj.ctrl[i - 1]
            tn = np.linalg.norm(tangent)
            if tn < 1e-9:
                continue
            d = (guide - q) @ (tangent / tn)  # signed distance of guide points from q's normal plane
            k = int(np.argmin(np.abs(d) + 1e-3 * np.linalg.norm(guide - q, axis=1)))
            anchor = self._anchor(q, guide[k])
            if anchor is not None:
                pairs.add(i, *anchor)
        return True

    def plan(self, start_p: np.ndarray, start_v: np.ndarray, start_a: np.ndarray,
             goal: np.ndarray) -> BSpline | None:  # fmt: skip
        """A collision-free, feasible B-spline from the start state to ``goal`` (at rest), or None.

        The curve is optimised from the straight line, and again from the A* path when that one
        still collides or breaks the limits. On None, :attr:`reason` says why: goal outside the map,
        goal or start occupied, no path round the obstacles, no time allocation within the limits, or
        an optimised trajectory that still collides.
        """
        p0, v0, a0, goal = (np.asarray(x, dtype=float).reshape(3) for x in (start_p, start_v, start_a, goal))
        self.reason = ""
        self.goal = goal
        if not self.map.inside(goal):
            lo, hi = self.map.bounds
            return self._fail(f"goal {goal.round(2)} is outside the local map [{lo.round(2)}, {hi.round(2)}]")
        if not self.map.inside(p0):
            return self._fail(f"start {p0.round(2)} is outside the local map")
        near = f"within {self.cfg.obstacle_inflation:g} m of an obstacle"
        if self.map.is_occupied(goal):
            return self._fail(f"goal {goal.round(2)} is occupied ({near})")
        if self.map.is_occupied(p0, inflated=False):
            return self._fail(f"start {p0.round(2)} is inside a mapped obstacle")
        line = straight_line(p0, v0, a0, goal, self.cfg.ctrl_spacing, self.cfg.max_vel)
        traj = self._optimised(line, p0, v0, a0)
        if traj is None:
            return self._fail(f"no path from {p0.round(2)} to {goal.round(2)} round the obstacles")
        fits, clear = self._within_limits(traj), not len(self._colliding(traj))
        if fits and clear:
            return traj
        for seed, length in self._search_path_seeds(p0, v0, a0, goal):
            again = self._optimised(seed, p0, v0, a0)
            if again is not None and self._within_limits(again) and not len(self._colliding(again)):
                log.info("re-optimised from the search path (%.1f m): the curve from the straight line %s",
                         length, "still collided" if fits else "broke the limits")  # fmt: skip
                return again
        if not fits:
            return self._fail("no time allocation keeps the speed and acceleration limits from this start")
        return self._fail("the optimised trajectory still meets obstacles")

    def _optimised(self, traj: BSpline, p0: np.ndarray, v0: np.ndarray, a0: np.ndarray) -> BSpline | None:
        """EGO's rebound loop from an initial curve: optimise; while the result collides, add {p, v}
        pairs from an A* path round each colliding stretch, and while it breaks the speed or
        acceleration limit, stretch its time step; then optimise again (eight optimisations at most).
        The result is checked after every optimisation: smoothing alone can pull a clear curve (an A*
        path's) into an obstacle it has no pairs for, and stretching the time step alone moves the
        start's control points out by ``v0 dt`` and raises the acceleration where they meet the rest.
        A last time re-allocation makes sure of the limits. None if a colliding stretch has no path."""
        c = self.cfg
        pairs = Pairs()
        for i in range(8):
            hits = self._colliding(traj)
            vmax, amax = traj.max_vel_acc()
            ratio = max(vmax / c.max_vel, math.sqrt(amax / c.max_acc))
            if i > 0 and len(hits) == 0 and ratio <= 1.0:
                break
            if len(hits) and not self._add_pairs(traj, hits, pairs):
                return None
            if i > 0 and ratio > 1.0:
                dt = traj.dt * min(ratio * 1.02, 2.0)
                traj = BSpline(np.concatenate([start_points(p0, v0, a0, dt), traj.ctrl[3:]]), dt)
            traj = self._optimize(traj, pairs)
        return reallocate_time(traj, p0, v0, a0, c.max_vel, c.max_acc)

    def _within_limits(self, traj: BSpline) -> bool:
        """The curve stays in the local map, within 5 % of the speed and acceleration limits."""
        vmax, amax = traj.max_vel_acc()
        c = self.cfg
        inside = bool(self.map.inside(traj.ctrl).all())
        return inside and vmax <= 1.05 * c.max_vel and amax <= 1.05 * c.max_acc

    def _search_path_seeds(self, p0: np.ndarray, v0: np.ndarray, a0: np.ndarray,
                           goal: np.ndarray) -> list[tuple[BSpline, float]]:  # fmt: skip
        """Initial curves along the A* path from start to goal, for when the curve optimised from the
        straight line still collides (a narrow gap beside a trunk, say: the straight line's pairs pull
        it the wrong way). EGO re-initialises from the search path the same way. Control points every
        ``ctrl_spacing`` along the path shortened by line of sight, then along the voxel path itself;
        each with its length. Empty if there is no path."""
        m, c = self.map, self.cfg
        blocked = m.count
        ia, ib = m.index(p0), m.index(goal)
        if blocked[tuple(ia)]:
            ia = m.nearest_free(ia, c.obstacle_inflation + c.resolution)
        if ia is None or blocked[tuple(ib)]:
            return []
        path = astar(blocked, ia, ib, c.astar_max_expansions, int(np.ceil(c.astar_margin / c.resolution)))
        if len(path) < 2:
            return []
        pts = m.point(path)
        pts[0], pts[-1] = p0, goal
        corners = [0]  # line-of-sight shortening: from each kept point, the farthest one in clear line
        while corners[-1] < len(pts) - 1:
            i, j = corners[-1], len(pts) - 1
            while j > i + 1 and not self._segment_free(pts[i], pts[j]):
                j -= 1
            corners.append(j)
        seeds = []
        for poly in (pts[corners], pts):
            along = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(poly, axis=0), axis=1))])
            n = max(int(np.ceil(along[-1] / c.ctrl_spacing)), 1)
            s = np.linspace(0.0, along[-1], n + 1)
            inner = np.stack([np.interp(s, along, poly[:, k]) for k in range(3)], axis=1)[1:-1]
            dt = max(along[-1] / n, 1e-3) / c.max_vel
            ctrl = np.concatenate([start_points(p0, v0, a0, dt), inner, np.tile(goal, (3, 1))])
            seeds.append((BSpline(ctrl, dt), float(along[-1])))
        return seeds

    def _segment_free(self, a: np.ndarray, b: np.ndarray) -> bool:
        """True if the straight segment a -> b stays out of the inflated map (sampled every half voxel)."""
        n = max(int(np.ceil(np.linalg.norm(b - a) / (0.5 * self.cfg.resolution))), 1)
        return not self.map.is_occupied(a + np.linspace(0.0, 1.0, n + 1)[:, None] * (b - a)).any()

    def local_goal(self, p0: np.ndarray, goal: np.ndarray) -> np.ndarray:
        """Where to plan to this cycle: ``goal`` itself when it is within the horizon and free, else a
        point on the way that the camera has seen free.

        A weighted A* runs towards the goal (or where the line to it leaves the map), unknown space
        counting as free like EGO's map, and the local goal is its farthest point within the horizon
        and an inflation radius short of the first voxel the camera has not seen free: behind a crown
        seen from the front, the path's hidden part is not trusted until the vehicle has looked.
        At least ``min_step`` metres along the path are taken, so a fresh map does not stall it.
        """
        c, m = self.cfg, self.map
        p0, goal = np.asarray(p0, dtype=float), np.asarray(goal, dtype=float)
        d = goal - p0
        dist = float(np.linalg.norm(d))
        if dist <= c.horizon and m.inside(goal) and not m.is_occupied(goal):
            return goal
        straight = p0 + d * min(1.0, c.horizon / max(dist, 1e-9))
        lo, hi = m.bounds
        lo, hi = lo + c.inflation, hi - c.inflation
        with np.errstate(divide="ignore", invalid="ignore"):
            s_out = np.where(d > 0, (hi - p0) / d, np.where(d < 0, (lo - p0) / d, np.inf))
        target = p0 + d * float(np.clip(np.min(s_out), 0.0, 1.0))
        blocked = m.count
        reach = 2 * c.obstacle_inflation
        ia = m.index(p0)
        if not m.inside(p0):
            return straight
        if blocked[tuple(ia)]:
            ia = m.nearest_free(ia, reach)
        it = m.index(target)
        for s in np.linspace(1.0, 0.0, 50):  # back off along the line until the target is free
            q = p0 + s * (target - p0)
            if not m.is_occupied(q):
                it = m.index(q)
                break
        if ia is None or blocked[tuple(it)]:
            return straight
        margin = int(c.local_goal_margin / c.resolution)
        path = astar(blocked, ia, it, c.astar_max_expansions, margin, weight=2.0)
        if len(path) < 2:
            return straight
        pts = m.point(path)
        pts[0] = p0
        along = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
        seen = m.seen_free(path)
        seen[0] = True
        unseen = np.flatnonzero(~seen)
        # stop an inflation radius short of unseen space: an obstacle may start right there
        limit = min(c.horizon, along[unseen[0]] - c.obstacle_inflation) if len(unseen) else c.horizon
        ok = np.flatnonzero(along <= limit)
        k = int(ok[-1]) if len(ok) else 0
        if along[k] < c.min_step:
            k = int(np.flatnonzero(along <= min(c.min_step, c.horizon))[-1])
        return pts[k]

    def warm_up(self) -> float:
        """Compile (or load from numba's cache) every kernel on a throwaway map: a wall seen from 2 m,
        then a plan round it. Returns the wall time taken; leaves this planner's map untouched.

        The scratch planner has no virtual floor or ceiling: with them the scratch scene at z = 0 would
        be blocked, the plan would stop at its first check, and its kernels would compile during the
        first real plan (7 to 14 s of a flight spent hovering)."""
        t0 = time.perf_counter()
        scratch = Planner(dataclasses.replace(self.cfg, floor=None, ceiling=None), np.zeros(3))
        K = np.array([[40.0, 0.0, 40.0], [0.0, 40.0, 30.0], [0.0, 0.0, 1.0]])
        T = frames.T_link_optical()  # a camera at the origin looking along world +x
        depth = np.full((60, 80), np.nan, dtype=np.float32)
        depth[:, 30:50] = 2.0
        for _ in range(3):  # however many hits the sensor model needs to call a voxel occupied
            scratch.update_map(depth, T, K)
        scratch.map.recenter(np.array([0.0, 0.0, 0.05]), force=True)
        if scratch.plan(np.zeros(3), np.zeros(3), np.zeros(3), np.array([4.0, 0.0, 0.0])) is None:
            raise RuntimeError(f"planner warm-up: the plan round the scratch wall failed ({scratch.reason})")
        scratch.local_goal(np.zeros(3), np.array([9.0, 0.0, 0.0]))
        return time.perf_counter() - t0

    def needs_replan(self, trajectory: BSpline | None, t_now: float = 0.0) -> bool:
        """True when the rest of ``trajectory`` meets newly seen obstacles or leaves the local map."""
        if trajectory is None:
            return True
        t = trajectory.sample(0.5 * self.cfg.resolution / self.cfg.max_vel)
        rest = trajectory.position(t[t >= t_now])
        return bool(len(self._colliding(trajectory, t_now)) or not self.map.inside(rest).all())

    def time_to_collision(self, trajectory: BSpline, t_now: float) -> float:
        """Seconds from ``t_now`` until ``trajectory`` first meets the inflated map (inf if never)."""
        hits = self._colliding(trajectory, t_now)
        return float(hits[0] - t_now) if len(hits) else math.inf
