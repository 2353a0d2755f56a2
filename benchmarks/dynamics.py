"""Physics + SE(3) control at 100 Hz without rendering: Droneulator vs RotorPy's own loop.

Both loops track the same 4-waypoint minimum-snap trajectory for 10 s with the same parameters:
RotorPy's ``Multirotor.step`` (solve_ivp RK45) + ``SE3Control.update`` + ``MinSnap.update``,
versus Droneulator's compiled RK4 + SE(3) + trajectory evaluation, and a full in-process one-vehicle
``World`` (flight modes, collision queries every sub-step) without the renderer.
Prints real-time factors measured in the same run and the largest position difference.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from _common import write
from rotorpy.controllers.quadrotor_control import SE3Control
from rotorpy.trajectories.minsnap import MinSnap
from rotorpy.vehicles.multirotor import Multirotor

from droneulator.controllers.se3 import FastSE3Control
from droneulator.trajectories.minsnap import PolyTrajectory
from droneulator.vehicles.dynamics import STATE, FastMultirotor, pack_state
from droneulator.vehicles.params import get_params
from droneulator.world import World

WAYPOINTS = np.array([[0, 0, 1.0], [3, 2, 2.5], [5, -1, 1.5], [1, 1, 1.0]])
YAWS = np.array([0, 1.0, -0.5, 0.3])


def initial() -> dict:
    return {
        "x": WAYPOINTS[0].copy(),
        "v": np.zeros(3),
        "q": np.array([0, 0, 0, 1.0]),
        "w": np.zeros(3),
        "wind": np.zeros(3),
        "rotor_speeds": np.full(4, 1788.53),
    }


def rotorpy_loop(qp: dict, traj: MinSnap, steps: int, dt: float) -> tuple[float, np.ndarray]:
    vehicle, ctrl, st = Multirotor(qp, initial_state=initial(), enable_ground=True), SE3Control(qp), initial()
    xs = np.zeros((steps, 3))
    t0 = time.perf_counter()
    for i in range(steps):
        fo = traj.update(i * dt)
        st = vehicle.step(st, ctrl.update(i * dt, st, fo), dt)
        xs[i] = st["x"]
    return time.perf_counter() - t0, xs


def droneulator_loop(
    qp: dict, traj: MinSnap, steps: int, dt: float, repeats: int
) -> tuple[float, np.ndarray]:
    vehicle, ctrl = FastMultirotor(qp, substep=dt / 10), FastSE3Control(qp)
    ref = PolyTrajectory(traj.x_poly, traj.yaw_poly, traj.t_keyframes)
    xs = np.zeros((steps, 3))
    vehicle.step(pack_state(initial()), np.zeros(4), dt)  # compile outside the timing
    t0 = time.perf_counter()
    for _ in range(repeats):
        s = pack_state(initial())
        for i in range(steps):
            vehicle.step(s, ctrl.motor_speeds(s, ref.flat(i * dt)), dt)
            xs[i] = s[STATE.x]
    return (time.perf_counter() - t0) / repeats, xs


def simulator_loop(seconds: float) -> float:
    world = World(scene="default", render=False)
    uav = world.vehicle()
    world.reset(position=world.scene.spawn_position + [0, 0, 2.0])
    uav.goto(world.scene.spawn_position + [0.5, 0.5, 2.5])
    world.run(0.1)
    t0 = time.perf_counter()
    world.run(seconds)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=10.0, help="simulated seconds per loop (default 10)")
    ap.add_argument("--rate", type=float, default=100.0, help="control and physics rate in Hz (default 100)")
    ap.add_argument(
        "--repeats", type=int, default=10, help="repeats of the fast loop for timing (default 10)"
    )
    ap.add_argument("--params", default="hummingbird", help="RotorPy parameter set (default hummingbird)")
    ap.add_argument("--json", default=None, help="output path (default benchmarks/results/dynamics.json)")
    args = ap.parse_args()

    qp = get_params(args.params)
    dt = 1.0 / args.rate
    steps = round(args.seconds / dt)
    traj = MinSnap(WAYPOINTS, yaw_angles=YAWS, v_avg=1.5, verbose=False)
    t_ref, x_ref = rotorpy_loop(qp, traj, steps, dt)
    t_fast, x_fast = droneulator_loop(qp, traj, steps, dt, args.repeats)
    t_sim = simulator_loop(args.seconds * 3)
    dev = float(np.max(np.linalg.norm(x_ref - x_fast, axis=1)))
    res = {
        "rate_hz": args.rate,
        "sim_seconds": args.seconds,
        "params": args.params,
        "rotorpy_rtf": args.seconds / t_ref,
        "droneulator_rtf": args.seconds / t_fast,
        "simulator_rtf": args.seconds * 3 / t_sim,
        "speedup": t_ref / t_fast,
        "max_position_difference_m": dev,
    }
    print(f"RotorPy default loop (solve_ivp + SE3Control + MinSnap): {res['rotorpy_rtf']:8.1f}x real time")
    print(
        f"Droneulator compiled loop (RK4 + SE3 + min-snap):        {res['droneulator_rtf']:8.1f}x real time"
        f"  ({res['speedup']:.1f}x RotorPy)"
    )
    print(f"Droneulator Simulator, no rendering (modes + collision):  {res['simulator_rtf']:8.1f}x real time")
    print(f"max position difference over {args.seconds:g} s: {dev * 1000:.3f} mm")
    write("dynamics", res, args.json)


if __name__ == "__main__":
    main()
