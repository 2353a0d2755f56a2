"""Single-vehicle flights recorded before the simulator became a world of many vehicles.

``tests/data/golden_single.npz`` holds the state after every control step of each scenario below, as
the single-vehicle ``Simulator`` of commit 18605a3 flew them (before ``World`` and ``Vehicle``
existed), with every event. ``test_world.py`` flies the same scenarios through today's code (a
one-vehicle ``World`` and its ``world.vehicle()``) and requires the same states to 1e-12, so a
one-vehicle world is today's simulator. Re-recording the file with today's code would make that test
check nothing: run this module only to record a new reference on purpose (``python tests/golden.py``),
and say why in the commit.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from droneulator.world import World

GOLDEN = Path(__file__).parent / "data" / "golden_single.npz"


def _record(world: World, seconds: float, rows: list[np.ndarray], events: list[str]) -> None:
    uav = world.vehicle()
    for _ in range(round(seconds * world.config.vehicle.control_hz)):
        res = world.step()
        st = uav.state
        rows.append(
            np.concatenate(
                [
                    [st.t_ns],
                    st.position,
                    st.velocity,
                    st.quaternion,
                    st.angular_velocity,
                    st.rotor_speeds,
                    uav.specific_force,
                    uav.wind_velocity,
                ]
            )
        )
        events.extend(f"{e.type}@{e.t:.6f}" for e in res.events)


def _world(scene: str, overrides: list[str]) -> World:
    from droneulator.config import load_config
    from droneulator.world import World

    return World(load_config(overrides=overrides, scene=scene), render=False)


def mission(world: World, rows: list[np.ndarray], events: list[str]) -> None:
    """Take off, goto with a turn, velocity mode, hold, land: every flight mode of the API."""
    uav = world.vehicle()
    world.reset()
    uav.takeoff(2.0)
    _record(world, 5.0, rows, events)
    x0 = uav.state.position
    uav.goto(x0 + [3.0, 1.0, 0.5], yaw=0.5)
    _record(world, 7.5, rows, events)
    uav.velocity(1.0, 0.3)
    _record(world, 3.0, rows, events)
    uav.hold()
    _record(world, 1.0, rows, events)
    uav.land()
    _record(world, 12.0, rows, events)


def short(world: World, rows: list[np.ndarray], events: list[str]) -> None:
    uav = world.vehicle()
    world.reset()
    uav.takeoff(1.5)
    _record(world, 3.0, rows, events)
    uav.goto(uav.state.position + [1.0, -1.0, 0.0], yaw=-0.4)
    _record(world, 4.0, rows, events)


def crash(world: World, rows: list[np.ndarray], events: list[str]) -> None:
    """Straight into the tree of tree_inspection: a scene collision, then a restart from it."""
    uav = world.vehicle()
    tree = np.asarray(world.scene.landmarks["tree"], dtype=float)
    world.reset(position=[tree[0] - 6.0, tree[1], 2.0], yaw=0.0)
    uav.goto([tree[0] + 6.0, tree[1], 2.0], speed=3.0)
    _record(world, 5.0, rows, events)
    uav.goto(uav.state.position + [-2.0, 0.0, 0.5])
    _record(world, 4.0, rows, events)


def drop(world: World, rows: list[np.ndarray], events: list[str]) -> None:
    """Rotor speeds set from outside (an autopilot): a hard touchdown (impact event) and a rest."""
    uav = world.vehicle()
    world.reset(position=[0.0, 0.0, 2.0])
    qp = uav.quad_params
    uav.set_rotor_speeds([0.6 * uav.hover_speed] * 4 if qp else [0.0] * 4)
    _record(world, 2.5, rows, events)
    uav.motors_off()
    _record(world, 1.0, rows, events)


#: name -> (scene, config overrides, flight)
SCENARIOS: dict[str, tuple[str, list[str], Callable[[World, list, list], None]]] = {
    "mission_hummingbird": ("default", [], mission),
    "mission_crazyflie": ("default", ["vehicle.params=crazyflie"], short),
    "mission_px4_quadx_250hz": ("default", ["vehicle.params=px4_quadx", "vehicle.control_hz=250"], short),
    "dryden_wind": ("default", ["vehicle.wind=dryden", "vehicle.wind_velocity=[2.0, -1.0, 0.0]"], short),
    "tree_collision": ("tree_inspection", [], crash),
    "external_drop": ("default", ["vehicle.params=px4_quadx", "vehicle.control_hz=250"], drop),
}


def fly(name: str) -> tuple[np.ndarray, list[str]]:
    """The scenario's states (one row per control step: t_ns, x, v, q, w, rotor speeds, specific force,
    wind) and its events."""
    scene, overrides, flight = SCENARIOS[name]
    world = _world(scene, overrides)
    rows: list[np.ndarray] = []
    events: list[str] = []
    flight(world, rows, events)
    world.close()
    return np.array(rows), events


def main() -> None:
    out: dict[str, np.ndarray] = {}
    for name in SCENARIOS:
        states, events = fly(name)
        out[name] = states
        out[f"{name}__events"] = np.array(events, dtype=str)
        print(f"{name}: {len(states)} steps, events {events}")
    GOLDEN.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(GOLDEN, **out)
    print(f"wrote {GOLDEN} ({GOLDEN.stat().st_size} bytes)")


if __name__ == "__main__":
    sys.exit(main())
