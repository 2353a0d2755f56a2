"""Single-vehicle flights recorded before the simulator became a world of many vehicles.

``tests/data/golden_single.npz`` holds the state after every control step of each scenario below, as
the single-vehicle ``Simulator`` of commit 18605a3 flew them (before ``World`` and ``Vehicle``
existed), with every event. ``test_world.py`` flies the same scenarios through today's code and
requires the same states to 1e-12, so a one-vehicle world is today's simulator. Re-recording the file
with today's code would make that test check nothing: run this module only to record a new reference
on purpose (``python tests/golden.py``), and say why in the commit.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

GOLDEN = Path(__file__).parent / "data" / "golden_single.npz"


def _record(sim: Any, seconds: float, rows: list[np.ndarray], events: list[str]) -> None:
    for _ in range(round(seconds * sim.config.vehicle.control_hz)):
        res = sim.step()
        st = sim.state
        rows.append(
            np.concatenate(
                [
                    [st.t_ns],
                    st.position,
                    st.velocity,
                    st.quaternion,
                    st.angular_velocity,
                    st.rotor_speeds,
                    sim.specific_force,
                    sim.wind_velocity,
                ]
            )
        )
        events.extend(f"{e.type}@{e.t:.6f}" for e in res.events)


def _sim(scene: str, overrides: list[str]) -> Any:
    from droneulator.config import load_config
    from droneulator.sim.simulator import Simulator

    return Simulator(config=load_config(overrides=overrides, scene=scene), render=False)


def mission(sim: Any, rows: list[np.ndarray], events: list[str]) -> None:
    """Take off, goto with a turn, velocity mode, hold, land: every flight mode of the API."""
    sim.reset()
    sim.takeoff(2.0)
    _record(sim, 5.0, rows, events)
    x0 = sim.state.position
    sim.goto(x0 + [3.0, 1.0, 0.5], yaw=0.5)
    _record(sim, 7.5, rows, events)
    sim.velocity(1.0, 0.3)
    _record(sim, 3.0, rows, events)
    sim.hold()
    _record(sim, 1.0, rows, events)
    sim.land()
    _record(sim, 12.0, rows, events)


def short(sim: Any, rows: list[np.ndarray], events: list[str]) -> None:
    sim.reset()
    sim.takeoff(1.5)
    _record(sim, 3.0, rows, events)
    sim.goto(sim.state.position + [1.0, -1.0, 0.0], yaw=-0.4)
    _record(sim, 4.0, rows, events)


def crash(sim: Any, rows: list[np.ndarray], events: list[str]) -> None:
    """Straight into the tree of tree_inspection: a scene collision, then a restart from it."""
    tree = np.asarray(sim.scene.landmarks["tree"], dtype=float)
    sim.reset(position=[tree[0] - 6.0, tree[1], 2.0], yaw=0.0)
    sim.goto([tree[0] + 6.0, tree[1], 2.0], speed=3.0)
    _record(sim, 5.0, rows, events)
    sim.goto(sim.state.position + [-2.0, 0.0, 0.5])
    _record(sim, 4.0, rows, events)


def drop(sim: Any, rows: list[np.ndarray], events: list[str]) -> None:
    """Rotor speeds set from outside (an autopilot): a hard touchdown (impact event) and a rest."""
    sim.reset(position=[0.0, 0.0, 2.0])
    qp = sim.quad_params
    sim.set_rotor_speeds([0.6 * sim.vehicle.hover_speed] * 4 if qp else [0.0] * 4)
    _record(sim, 2.5, rows, events)
    sim.motors_off()
    _record(sim, 1.0, rows, events)


#: name -> (scene, config overrides, flight)
SCENARIOS: dict[str, tuple[str, list[str], Callable[[Any, list, list], None]]] = {
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
    sim = _sim(scene, overrides)
    rows: list[np.ndarray] = []
    events: list[str] = []
    flight(sim, rows, events)
    sim.close()
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
