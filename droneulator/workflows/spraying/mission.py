"""Fly a coverage plan with the spray on and report where the liquid went.

The vehicle (the config's first, flown by the internal controller) takes off, flies each leg of the
plan with :meth:`~droneulator.vehicles.vehicle.Vehicle.goto` at the leg's speed, and sprays over the
target area of spraying legs, its flow following its ground speed; after the last leg it lands while
the cloud settles. The report holds the mass balance, each plant's dose by third of its height, the
ground deposit inside the target area and off it, and the drift curve downwind of the target area.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from droneulator.config import SimConfig
from droneulator.spray.spraying import Spraying
from droneulator.spray.trials import DRIFT_M, UL_CM2
from droneulator.workflows.spraying.coverage import CoveragePlan, coverage_plan

#: the longest a leg may take beyond its planned duration (s) before the mission gives up on it
LEG_SLACK_S = 20.0


def fly_plan(
    config: SimConfig,
    plan: CoveragePlan | None = None,
    height: float = 1.5,
    speed: float = 3.0,
    progress: Callable[[float, str], None] | None = None,
) -> tuple[dict[str, Any], Spraying]:
    """Fly ``plan`` (default: :func:`coverage_plan` of the config's scene) spraying; returns the report
    and the :class:`Spraying` (its cloud holds the deposit grids)."""
    from droneulator.world.world import World

    world = World(config, render=False)
    spraying = Spraying(world)
    plan = plan or coverage_plan(world.scene, height=height, speed=speed)
    v = world.vehicle()
    system = spraying.system(v.name)
    x0, x1, y0, y1 = plan.target
    total = sum(np.linalg.norm(leg.end - leg.start) / leg.speed for leg in plan.legs) + 10.0
    done = 0.0

    def run(seconds: float, spray_leg: bool, speed: float = 1.0) -> None:
        nonlocal done
        for _ in range(max(1, round(seconds / (world.control_period_ns / 1e9)))):
            st = v.state
            p = st.position
            inside = x0 <= p[0] <= x1 and y0 <= p[1] <= y1
            # the flow follows the ground speed (as spray drones' rate control does), so the dose per
            # metre stays as planned where the vehicle speeds up and slows down at a row's ends
            ground = float(np.hypot(st.velocity[0], st.velocity[1]))
            want = min(1.0, ground / speed) if (spray_leg and inside and system.level_l > 0) else 0.0
            if abs(want - system.rate) > 0.02 or (want == 0.0) != (system.rate == 0.0):
                system.set(want)
            world.step()
            spraying.step()
        done += seconds
        if progress:
            progress(min(done / total, 0.99), f"t={world.t:.0f}s tank={system.level_l:.2f}L")

    v.takeoff(plan.altitude)
    run(v.goto(plan.legs[0].start, yaw=_yaw(plan.legs[0]), speed=2.0) + 2.0, False)
    for leg in plan.legs:
        duration = v.goto(leg.end, yaw=_yaw(leg), speed=leg.speed)
        run(duration + 0.5, leg.spray, leg.speed)
        slack = 0.0
        while np.linalg.norm(v.state.position - leg.end) > 0.5 and slack < LEG_SLACK_S:
            run(0.5, leg.spray, leg.speed)
            slack += 0.5
    system.set(0.0)
    run(v.land() + 1.0, False)
    spraying.cloud.settle([], limit_s=60.0)
    if progress:
        progress(1.0, "settled")
    return report(spraying, plan), spraying


def _yaw(leg: Any) -> float:
    d = leg.end - leg.start
    return math.atan2(d[1], d[0])


def report(spraying: Spraying, plan: CoveragePlan) -> dict[str, Any]:
    """The mass balance, plant doses, ground deposit and drift of a flown plan (litres, uL/cm^2, %)."""
    cloud = spraying.cloud
    ledger = cloud.ledger_now()
    ground = cloud.ground_deposit()
    c = cloud.ground_cell
    xs = cloud.ground_origin[0] + (np.arange(ground.shape[0]) + 0.5) * c
    ys = cloud.ground_origin[1] + (np.arange(ground.shape[1]) + 0.5) * c
    x0, x1, y0, y1 = plan.target
    inside = (xs[:, None] >= x0) & (xs[:, None] <= x1) & (ys[None, :] >= y0) & (ys[None, :] <= y1)
    target_area = (x1 - x0) * (y1 - y0)
    applied = ledger.sprayed / target_area  # m^3 per m^2 over the target
    dose = cloud.plant_dose()
    tg = spraying.targets
    per_plant = dose.sum(1)
    leaf_cm2 = np.maximum(tg.leaf_area, 1e-9) * 1e4
    hx, hy = spraying.world.config.wind.heading
    drift = _drift_curve(ground, xs, ys, plan.target, (hx, hy), applied)
    parts_l = {k: v * 1000.0 for k, v in ledger.parts.items()}
    ground_in = float(ground[inside].sum())
    return {
        "sprayed_l": ledger.sprayed * 1000.0,
        "mass_balance_l": parts_l,
        "mass_balance_error": abs(ledger.accounted - ledger.sprayed) / max(ledger.sprayed, 1e-30),
        "target_area_m2": target_area,
        "applied_l_ha": applied * 1e7,
        "ground_in_target_l": ground_in * 1000.0,
        "ground_off_target_l": (float(ground.sum()) - ground_in) * 1000.0 + parts_l["ground_off_grid"],
        "canopy_share": ledger.parts["canopy"] / max(ledger.sprayed, 1e-30),
        "plants": {
            "count": tg.plant_count,
            "positions": tg.plants[:, :2].tolist(),
            "dose_ul": (dose * 1e9).tolist(),
            "dose_ul_per_cm2_leaf": (per_plant * 1e9 / leaf_cm2).tolist(),
            "thirds_share": (dose.sum(0) / max(dose.sum(), 1e-30)).tolist(),
            "cv": float(per_plant.std() / per_plant.mean()) if per_plant.mean() > 0 else math.inf,
        },
        "drift": drift,
        "tank": spraying.system(None).state(),
        "parcels": cloud.parcels_released,
        "sim_s": spraying.world.t,
        "ground_grid": {
            "x0": float(cloud.ground_origin[0]),
            "y0": float(cloud.ground_origin[1]),
            "cell_m": c,
        },
    }


def _drift_curve(
    ground: np.ndarray,
    xs: np.ndarray,
    ys: np.ndarray,
    target: tuple[float, float, float, float],
    heading: tuple[float, float],
    applied: float,
) -> dict[str, list[float]]:
    """Mean ground deposit in 1 m bands at :data:`DRIFT_M` downwind of the target area's edge (along the
    wind's main axis, over the area's width), as % of the applied volume per area."""
    x0, x1, y0, y1 = target
    hx, hy = heading
    out = []
    c = xs[1] - xs[0]
    for dist in DRIFT_M:
        if abs(hx) >= abs(hy):
            edge = x1 if hx > 0 else x0
            band = np.abs(xs - (edge + math.copysign(dist, hx))) <= 0.5
            across = (ys >= y0) & (ys <= y1)
            cells = ground[np.ix_(band, across)]
        else:
            edge = y1 if hy > 0 else y0
            band = np.abs(ys - (edge + math.copysign(dist, hy))) <= 0.5
            across = (xs >= x0) & (xs <= x1)
            cells = ground[np.ix_(across, band)]
        per_area = cells.sum() / max(cells.size * c * c, 1e-9)
        out.append(float(per_area / applied * 100.0) if applied > 0 else 0.0)
    return {"distance_m": DRIFT_M.tolist(), "drift_percent": out, "deposit_ul_cm2_applied": applied * UL_CM2}
