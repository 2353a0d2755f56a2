"""Settings of the local planner: map size and sensor model, vehicle size, limits and optimiser weights."""

from __future__ import annotations

import math
from dataclasses import dataclass


def logit(p: float) -> float:
    """Log-odds of probability ``p``."""
    return math.log(p / (1.0 - p))


@dataclass
class PlannerConfig:
    """Every knob of mapping and planning, defaults close to EGO-Planner's ``advanced_param.xml``."""

    #: voxel edge, metres
    resolution: float = 0.1
    #: map extent (x, y, z) in metres, centred on the vehicle
    map_size: tuple[float, float, float] = (20.0, 20.0, 6.0)
    #: the map scrolls when the vehicle is this far (metres, any axis) from the map's centre
    recenter_distance: float = 2.0
    #: use every n-th pixel in u and v of the depth image
    pixel_skip: int = 4
    #: returns nearer than this are ignored (sensor noise, propellers)
    min_depth: float = 0.2
    #: rays are cut at this range; NaN (no return) clears free space up to it
    max_ray_length: float = 6.5
    #: one hit makes a voxel occupied (logit 0.82 > logit p_occupied): the rendered depth has no noise
    #: to vote away, and thin leaf cards are hit by one frame and missed through their gaps by the next;
    #: with EGO's two-hit setting (0.70) foliage behind the crown went unmapped and flights came 0.4 m
    #: from it
    p_hit: float = 0.82
    p_miss: float = 0.35
    p_min: float = 0.12
    p_max: float = 0.97
    p_occupied: float = 0.80
    #: vehicle radius plus margin: obstacles are inflated by this much for planning
    vehicle_radius: float = 0.25
    inflation_margin: float = 0.25
    #: planning limits
    max_vel: float = 2.0
    max_acc: float = 3.0
    #: spacing of B-spline control points along the initial straight line, metres
    ctrl_spacing: float = 0.4
    #: extra distance control points must keep beyond the inflated surface (the curve cuts corners)
    safety_extra: float = 0.15
    lambda_smooth: float = 1.0
    lambda_collision: float = 1000.0
    lambda_feasibility: float = 0.1
    #: L-BFGS stops when the cost falls by less than this fraction per iteration, or after opt_max_iters
    opt_ftol: float = 1e-5
    opt_max_iters: int = 200
    #: A* gives up after this many node expansions
    astar_max_expansions: int = 200_000
    #: A* first searches the box round the colliding stretch grown by this much (metres), then the whole map
    astar_margin: float = 2.0
    #: planning horizon: goals further than this are approached through a local goal on the way
    horizon: float = 7.5
    #: a local goal is at least this far along its guiding path (metres), seen or not
    min_step: float = 1.5
    #: the local goal's guiding A* first searches the box round start and target grown by this (m)
    local_goal_margin: float = 5.0
    #: virtual ceiling and floor (world z, metres; None = none): voxels above / below count as occupied,
    #: like EGO-Planner's ``virtual_ceil_height`` / ``ground_height``, so routes bend round obstacles
    #: instead of over them
    ceiling: float | None = None
    floor: float | None = None
    #: extra growth of the mapped obstacles (not of the virtual ceiling and floor) for how far the vehicle
    #: strays from its setpoints: set while flying from the measured tracking error (:class:`TrackingMargin`)
    tracking_margin: float = 0.0

    def __post_init__(self) -> None:
        if self.resolution <= 0:
            raise ValueError("resolution must be positive")
        if any(s < 4 * self.resolution for s in self.map_size):
            raise ValueError("map_size must span at least 4 voxels on every axis")
        if self.pixel_skip < 1:
            raise ValueError("pixel_skip must be >= 1")
        if not 0 <= self.min_depth < self.max_ray_length:
            raise ValueError("need 0 <= min_depth < max_ray_length")
        if not 0 < self.p_min < self.p_miss < 0.5 < self.p_hit < self.p_max < 1:
            raise ValueError("need 0 < p_min < p_miss < 0.5 < p_hit < p_max < 1")
        if not 0.5 < self.p_occupied < self.p_max:
            raise ValueError("need 0.5 < p_occupied < p_max")
        if self.vehicle_radius < 0 or self.inflation_margin < 0 or self.tracking_margin < 0:
            raise ValueError("vehicle_radius, inflation_margin and tracking_margin must be >= 0")
        if self.max_vel <= 0 or self.max_acc <= 0:
            raise ValueError("max_vel and max_acc must be positive")
        if not 0 < self.opt_ftol < 1 or self.opt_max_iters < 1:
            raise ValueError("need 0 < opt_ftol < 1 and opt_max_iters >= 1")
        if self.astar_margin < 0:
            raise ValueError("astar_margin must be >= 0")
        if self.ctrl_spacing <= 0:
            raise ValueError("ctrl_spacing must be positive")
        both = self.ceiling is not None and self.floor is not None
        if both and self.ceiling - self.floor < 2 * self.inflation:
            raise ValueError("need ceiling - floor >= 2 * (vehicle_radius + inflation_margin)")

    @property
    def inflation(self) -> float:
        """Distance by which the virtual ceiling and floor are grown (vehicle radius + margin)."""
        return self.vehicle_radius + self.inflation_margin

    @property
    def obstacle_inflation(self) -> float:
        """Distance by which mapped obstacles are grown for planning: :attr:`inflation` plus the
        tracking margin."""
        return self.inflation + self.tracking_margin
