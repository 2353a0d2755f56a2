"""The demo mission: take off, fly a small square around the spawn point (legs that would come
within 1 m of an obstacle are skipped), turn a full circle in velocity mode, return and land.

:func:`plan_mission` is shared by ``droneulator demo`` (in process, :func:`run_demo`) and
``droneulator run --demo`` (through the WebSocket API, :mod:`droneulator.workflows.demo_client`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from droneulator.config import SimConfig
from droneulator.controllers.flight import Event
from droneulator.frames import quat_from_yaw, quat_to_matrix
from droneulator.scenes.base import Scene
from droneulator.workflows.snapshot import save_frames
from droneulator.world import World

TURN_RATE = 0.8


@dataclass
class Leg:
    """One API operation and what ends it: ``until`` is a mode to reach or a duration in seconds."""

    op: str
    args: dict[str, Any] = field(default_factory=dict)
    until: str | float = "hold"

    @property
    def label(self) -> str:
        args = ", ".join(
            f"{k}={np.round(v, 2).tolist() if isinstance(v, list) else v}" for k, v in self.args.items()
        )
        return f"{self.op}({args})"


def plan_mission(scene: Scene, cfg: SimConfig) -> list[Leg]:
    home = scene.spawn_position.copy()
    R = quat_to_matrix(quat_from_yaw(scene.spawn_yaw))
    alt = cfg.flight.takeoff_altitude
    corners = [
        home + R @ np.array(p) for p in ([3.0, 0, alt], [3.0, 3.0, alt + 0.5], [0, 3.0, alt], [0, 0, alt])
    ]
    clear = 1.0 + cfg.vehicle.collision_radius
    legs = [Leg("takeoff", {"altitude": alt})]
    legs += [
        Leg("goto", {"position": p.tolist(), "speed": 1.5})
        for p in corners
        if scene.collision.distance(p) > clear
    ]
    legs += [
        Leg("velocity", {"forward": 0.0, "yaw_rate": TURN_RATE}, 2 * math.pi / TURN_RATE),
        Leg("hold", {}, 0.5),
        Leg("land", {}, "idle"),
    ]
    return legs


def telemetry_line(st: dict[str, Any]) -> str:
    x, y, z = st["position"]
    return (
        f"t={st['t']:6.2f}s  mode={st['mode']:<8} pos=({x:6.2f},{y:6.2f},{z:5.2f})  "
        f"speed={np.linalg.norm(st['velocity']):4.2f} m/s  yaw={math.degrees(st['yaw']):7.1f} deg"
    )


def run_demo(
    config: SimConfig, out: Path, save_every: float = 1.0, log: Callable[[str], None] = tqdm.write
) -> dict:
    """Fly the demo mission in process; returns a summary (events, frames saved, real-time factor)."""
    out.mkdir(parents=True, exist_ok=True)
    events: list[Event] = []
    saved, next_save, next_log = 0, 0.0, 0.0
    with World(config=config) as world:
        uav = world.vehicle()
        plan = plan_mission(world.scene, config)
        wall0 = time.perf_counter()
        for leg in tqdm(plan, desc="demo mission", unit="leg", leave=False, disable=None):
            getattr(uav, leg.op)(**leg.args)
            log(f"[{world.t:6.2f}s] {leg.label}")
            end = world.t + (leg.until if isinstance(leg.until, float) else 60.0)
            while world.t < end and uav.mode.value != leg.until and uav.mode.value != "collided":
                res = world.step()
                events.extend(res.events)
                for e in res.events:
                    log(f"[{e.t:6.2f}s] event {e.type}")
                if res.frames and world.t >= next_save:
                    save_frames(res.frames[-1], out, prefix=f"{saved:04d}_", vehicle=uav.name)
                    saved, next_save = saved + 1, next_save + save_every
                if world.t >= next_log:
                    log(telemetry_line(uav.state.to_dict()))
                    next_log += 1.0
        wall = time.perf_counter() - wall0
        summary = {
            "sim_seconds": world.t,
            "wall_seconds": wall,
            "real_time_factor": world.t / wall,
            "frames_rendered": world.frame_count,
            "frames_saved": saved,
            "events": [e.to_dict() for e in events],
            "out": str(out),
        }
    log(
        f"demo finished: {world.t:.1f} s simulated in {wall:.1f} s wall (real-time factor "
        f"{summary['real_time_factor']:.2f}), {summary['frames_rendered']} frames rendered, "
        f"{saved} saved to {out}"
    )
    return summary
