"""The project's own depth-only local planner (issue 11): rolling occupancy map, A*, B-spline optimiser."""

from droneulator.workflows.planning.config import PlannerConfig

__all__ = ["PlannerConfig"]
