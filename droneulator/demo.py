"""``droneulator demo``: a short in-process mission that prints telemetry and saves frames.

Take off, fly a small square around the spawn point (legs that would come within 1 m of an
obstacle are skipped), turn a full circle in velocity mode to look around, return and land.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from tqdm import tqdm

from droneulator.config import SimConfig
from droneulator.controllers.flight import Event
from droneulator.frames import quat_to_matrix
from droneulator.sim.simulator import Simulator
from droneulator.snapshot import save_frames


def _telemetry(sim: Simulator) -> str:
    st = sim.state
    x, y, z = st.position
    return (
        f"t={st.t:6.2f}s  mode={st.mode:<8} pos=({x:6.2f},{y:6.2f},{z:5.2f})  "
        f"speed={np.linalg.norm(st.velocity):4.2f} m/s  yaw={math.degrees(st.yaw):7.1f} deg"
    )


def run_demo(
    config: SimConfig, out: Path, save_every: float = 1.0, log: Callable[[str], None] = print
) -> dict:
    """Fly the demo mission; returns a summary (events, frames saved, real-time factor)."""
    out.mkdir(parents=True, exist_ok=True)
    events: list[Event] = []
    saved = 0
    next_save = 0.0
    next_log = 0.0
    with Simulator(config=config) as sim:
        home = sim.scene.spawn_position.copy()
        R = quat_to_matrix(sim.state.quaternion)
        alt = config.flight.takeoff_altitude
        legs = [
            home + R @ np.array(p) for p in ([3.0, 0, alt], [3.0, 3.0, alt + 0.5], [0, 3.0, alt], [0, 0, alt])
        ]
        legs = [p for p in legs if sim.scene.collision.distance(p) > 1.0 + config.vehicle.collision_radius]
        plan: list[tuple[str, Callable[[], object], Callable[[Simulator], bool]]] = [
            ("takeoff", lambda: sim.takeoff(alt), lambda s: s.mode.value == "hold"),
            *[
                (
                    f"goto {np.round(p, 2).tolist()}",
                    lambda p=p: sim.goto(p, speed=1.5),
                    lambda s: s.mode.value == "hold",
                )
                for p in legs
            ],
            ("look around (velocity mode)", lambda: sim.velocity(0.0, 0.8), lambda s: s.t > t_turn_end),
            ("hold", sim.hold, lambda s: True),
            ("land", sim.land, lambda s: s.mode.value == "idle"),
        ]
        t_turn_end = math.inf
        wall0 = time.perf_counter()
        bar = tqdm(total=len(plan), desc="demo mission", unit="step", leave=False, disable=None)
        for label, command, done in plan:
            command()
            if label.startswith("look around"):
                t_turn_end = sim.t + 2 * math.pi / 0.8
            log(f"[{sim.t:6.2f}s] {label}")
            deadline = sim.t + 60.0
            while not done(sim) and sim.t < deadline:
                res = sim.step()
                events.extend(res.events)
                for e in res.events:
                    log(f"[{e.t:6.2f}s] event {e.type}")
                if sim.mode.value == "collided":
                    break
                if res.frames and sim.t >= next_save:
                    save_frames(res.frames[-1], out, prefix=f"{saved:04d}_")
                    saved += 1
                    next_save += save_every
                if sim.t >= next_log:
                    log(_telemetry(sim))
                    next_log += 1.0
            bar.update(1)
        bar.close()
        wall = time.perf_counter() - wall0
        summary = {
            "sim_seconds": sim.t,
            "wall_seconds": wall,
            "real_time_factor": sim.t / wall,
            "frames_rendered": sim.frame_count,
            "frames_saved": saved,
            "events": [e.to_dict() for e in events],
            "out": str(out),
        }
    log(
        f"demo finished: {summary['sim_seconds']:.1f} s simulated in {wall:.1f} s wall "
        f"(real-time factor {summary['real_time_factor']:.2f}), "
        f"{summary['frames_rendered']} frames rendered, "
        f"{saved} saved to {out}"
    )
    return summary
