"""Where to spray: a coverage plan over a scene's rows or over its open field.

Rows (the scene's ``row_y``, ``row_x_min``/``row_x_max`` and canopy-top landmarks, as the vineyard and
the orchard give them) are flown one by one along their centre line, ``height`` m above the canopy's
top, alternating direction with a headland turn ``run_in`` m beyond the row's ends; the spray is on over
the row. A scene without rows is covered by parallel swaths ``swath`` m apart over its flyable area.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from droneulator.scenes.base import Scene


@dataclass(frozen=True)
class Leg:
    """One straight leg: from ``start`` to ``end`` (world, m) at ``speed`` m/s, spraying or not."""

    start: np.ndarray
    end: np.ndarray
    speed: float
    spray: bool


@dataclass(frozen=True)
class CoveragePlan:
    legs: list[Leg]
    #: the sprayed (target) area, x0, x1, y0, y1 (m): deposits outside it have drifted
    target: tuple[float, float, float, float]
    altitude: float

    @property
    def spray_length_m(self) -> float:
        return float(sum(np.linalg.norm(leg.end - leg.start) for leg in self.legs if leg.spray))


def coverage_plan(
    scene: Scene, height: float = 1.5, speed: float = 3.0, swath: float | None = None, run_in: float = 3.0
) -> CoveragePlan:
    """The plan for ``scene`` (see the module docstring); ``swath`` (m) is the row spacing by default."""
    if not (height > 0 and speed > 0 and run_in >= 0):
        raise ValueError(
            f"coverage plan: height and speed must be > 0, run_in >= 0 (got {height}, {speed}, {run_in})"
        )
    lm = scene.landmarks
    if "row_y" in lm and "row_x_min" in lm:
        rows = np.asarray(lm["row_y"], float)
        x0, x1 = float(lm["row_x_min"][0]), float(lm["row_x_max"][0])
        top = (
            float(np.max(lm["canopy_z"]))
            if "canopy_z" in lm
            else float(np.max(lm.get("tree_heights", [3.0])))
        )
        spacing = float(np.median(np.diff(rows))) if len(rows) > 1 else 3.0
        lanes = list(rows)
        half = spacing / 2.0
        target = (x0 - 0.5, x1 + 0.5, float(rows.min() - half), float(rows.max() + half))
    else:
        spacing = swath or 4.0
        top = 0.0
        lo, hi = scene.bounds_min + 5.0, scene.bounds_max - 5.0
        x0, x1 = float(lo[0]), float(hi[0])
        lanes = list(np.arange(lo[1] + spacing / 2, hi[1], spacing))
        target = (x0, x1, float(lanes[0] - spacing / 2), float(lanes[-1] + spacing / 2))
    if swath is not None and "row_y" in lm:
        spacing = swath
    z = top + height
    legs: list[Leg] = []
    lo_b, hi_b = scene.bounds_min, scene.bounds_max
    a, b = max(x0 - run_in, lo_b[0] + 0.5), min(x1 + run_in, hi_b[0] - 0.5)
    for k, y in enumerate(lanes):
        xs = (a, b) if k % 2 == 0 else (b, a)
        start, end = np.array([xs[0], y, z]), np.array([xs[1], y, z])
        if legs:
            legs.append(Leg(legs[-1].end, start, speed, False))
        legs.append(Leg(start, end, speed, True))
    return CoveragePlan(legs, target, z)


def first_lanes(plan: CoveragePlan, n: int) -> CoveragePlan:
    """``plan`` cut to its first ``n`` spraying legs (rows or swaths) and the turns between them, its target
    area to those lanes (their spacing's half beyond the outer ones): a short flight over part of a field."""
    if n < 1:
        raise ValueError(f"coverage plan: the number of lanes must be >= 1, got {n}")
    spraying = [k for k, leg in enumerate(plan.legs) if leg.spray]
    if n >= len(spraying):
        return plan
    legs = plan.legs[: spraying[n - 1] + 1]
    ys = sorted(float(leg.start[1]) for leg in legs if leg.spray)
    all_ys = sorted(float(leg.start[1]) for leg in plan.legs if leg.spray)
    x0, x1, y0, y1 = plan.target
    half = (all_ys[1] - all_ys[0]) / 2.0
    return CoveragePlan(legs, (x0, x1, max(y0, ys[0] - half), min(y1, ys[-1] + half)), plan.altitude)
