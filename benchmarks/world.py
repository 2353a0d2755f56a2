"""A world of many vehicles: how fast it steps, how fast it renders, and one vehicle in another's wake.

1. Physics + control, vehicle-steps/s (one vehicle-step: one 10 ms control period of one vehicle, its
   SE(3) controller and its rigid-body step) for N = 1, 8, 64, 512, 4096 vehicles hovering on a grid
   at 12 m in the ``default`` scene (above every tree: no scene contact), through :class:`World.step`
   (flight modes, the batched SE(3) and physics kernels, the wake and contact searches), with the
   simulator's own integration (10 RK4 sub-steps a period) and with one RK4 step a period (what
   RotorPy's batched model does). In the same run: RotorPy's ``BatchedMultirotor`` (torch, ``rk4``,
   one step a period) with its ``BatchedSE3Control`` on the CPU, the reference the issue names, and
   a one-vehicle ``World``'s real-time factor (what ``Simulator`` measured before it was retired).
2. In-process lockstep with every vehicle's camera rig (the default 640x480 front camera, RGB, depth
   and segmentation at 30 Hz) for N = 1, 2, 4, 8 vehicles flying circles at 3 m: real-time factor,
   camera frames per second, and where the wall time goes (rendering and readback, the rest).
3. Downwash: a vehicle descending from 7 m to 1 m straight below another hovering at 8 m, against
   the same descent alone: the wake it meets, its thrust and its height error.

Prints the figures, writes ``benchmarks/results/world.json`` and the downwash figure
``benchmarks/results/world_downwash.png``.
"""

from __future__ import annotations

import argparse
import math
import time
from typing import Any

import numpy as np
from _common import write

from droneulator.config import VehicleSpec, load_config
from droneulator.state import STATE
from droneulator.world import World

GRID_SPACING = 0.8
HOVER_Z = 12.0


def hover_world(n: int, substeps: int) -> World:
    cfg = load_config(scene="default", overrides=[f"vehicle.substeps={substeps}"])
    side = math.ceil(math.sqrt(n))
    cfg.vehicles = [VehicleSpec(name=f"uav{i}", spawn=(0.0, 0.0, 0.0)) for i in range(n)]
    w = World(cfg, render=False)
    for i, v in enumerate(w.vehicles.values()):
        x = (i % side - (side - 1) / 2) * GRID_SPACING
        y = (i // side - (side - 1) / 2) * GRID_SPACING
        v.place([x, y, HOVER_Z], 0.0)
    return w


def time_world(n: int, substeps: int, seconds: float) -> dict[str, Any]:
    w = hover_world(n, substeps)
    w.step(5)  # compile, warm the caches
    steps = 0
    t0 = time.perf_counter()
    while (wall := time.perf_counter() - t0) < seconds or steps < 3:
        w.step(1)
        steps += 1
    drift = max(float(np.linalg.norm(v.s[STATE.v])) for v in w.vehicles.values())
    return {"n": n, "substeps": substeps, "steps": steps, "wall_s": wall,
            "vehicle_steps_per_s": n * steps / wall, "max_speed_m_s": drift}  # fmt: skip


def time_rotorpy(n: int, seconds: float) -> dict[str, Any] | None:
    """RotorPy's batched torch model with its batched SE(3) controller, hovering, one rk4 step a period."""
    try:
        import torch
        from rotorpy.controllers.quadrotor_control import BatchedSE3Control
        from rotorpy.vehicles.multirotor import BatchedMultirotor, BatchedMultirotorParams
    except ImportError as exc:
        print(f"  RotorPy batched: not available ({exc})")
        return None
    from droneulator.vehicles.params import get_params

    torch.set_num_threads(2)
    dev = torch.device("cpu")
    params = BatchedMultirotorParams([get_params("hummingbird")] * n, n, dev)
    side = math.ceil(math.sqrt(n))
    x = torch.tensor([[(i % side) * GRID_SPACING, (i // side) * GRID_SPACING, HOVER_Z] for i in range(n)],
                     dtype=torch.float64)  # fmt: skip
    qp = get_params("hummingbird")
    hover = math.sqrt(float(qp["mass"]) * 9.81 / (4 * qp["k_eta"]))

    def zeros(*shape: int) -> Any:
        return torch.zeros(*shape, dtype=torch.float64)

    state = {"x": x, "v": zeros(n, 3), "q": torch.tensor([[0.0, 0.0, 0.0, 1.0]] * n, dtype=torch.float64),
             "w": zeros(n, 3), "wind": zeros(n, 3),
             "rotor_speeds": torch.full((n, 4), hover, dtype=torch.float64)}  # fmt: skip
    vehicle = BatchedMultirotor(params, n, state, dev, integrator="rk4")
    ctrl = BatchedSE3Control(params, n, dev)
    flat = {"x": x.clone(), "x_dot": zeros(n, 3), "x_ddot": zeros(n, 3), "x_dddot": zeros(n, 3),
            "yaw": zeros(n), "yaw_dot": zeros(n)}  # fmt: skip
    idxs = torch.arange(n)

    def step(st: dict) -> dict:
        control = ctrl.update(0.0, st, flat, idxs)
        return vehicle.step(st, control, 0.01, idxs)

    with torch.no_grad():
        state = step(step(state))
        steps, t0 = 0, time.perf_counter()
        while (wall := time.perf_counter() - t0) < seconds or steps < 3:
            state = step(state)
            steps += 1
    return {"n": n, "steps": steps, "wall_s": wall, "vehicle_steps_per_s": n * steps / wall}


def time_single_vehicle(seconds: float) -> dict[str, Any]:
    """A one-vehicle world, hovering, no renderer: its real-time factor (control at 100 Hz)."""
    world = World(load_config(scene="default"), render=False)
    world.reset(position=[0.0, 0.0, HOVER_Z])
    world.step(5)
    steps, t0 = 0, time.perf_counter()
    while (wall := time.perf_counter() - t0) < seconds:
        world.step(10)
        steps += 10
    return {"steps": steps, "wall_s": wall, "real_time_factor": steps * 0.01 / wall}


def time_rendering(n: int, sim_seconds: float) -> dict[str, Any]:
    """N vehicles, each with the default 640x480 rig, flying circles at 3 m, lockstep in one process."""
    cfg = load_config(scene="default")
    cfg.vehicles = [VehicleSpec(name=f"uav{i}") for i in range(n)]
    w = World(cfg)
    for v in w.vehicles.values():
        v.place(v.s[STATE.x] + [0.0, 0.0, 3.0], 0.3 * len(v.name))
        v.velocity(1.0, 0.3)
    render_s = 0.0
    draw = w.cameras.renderer.render_rigs

    def timed(*a: Any, **k: Any) -> Any:
        nonlocal render_s
        t = time.perf_counter()
        try:
            return draw(*a, **k)
        finally:
            render_s += time.perf_counter() - t

    w.cameras.renderer.render_rigs = timed  # type: ignore[method-assign]
    w.run(0.5)  # shaders, caches
    render_s = 0.0
    frames = 0
    t0 = time.perf_counter()
    res = w.run(sim_seconds)
    wall = time.perf_counter() - t0
    frames = sum(len(cams) for f in res.frames for cams in f.cameras.values())
    collisions = [e for e in res.events if e.type == "collision"]
    w.close()
    return {"n": n, "sim_s": sim_seconds, "wall_s": wall, "real_time_factor": sim_seconds / wall,
            "camera_frames": frames, "camera_frames_per_s": frames / wall, "render_share": render_s / wall,
            "render_s": render_s, "collisions": len(collisions)}  # fmt: skip


def downwash_flight() -> dict[str, Any]:
    """The descent past a hovering vehicle, and alone: time series for the figure."""
    out: dict[str, Any] = {}
    for case in ("with", "alone"):
        cfg = load_config(scene="default")
        names = ["upper", "lower"] if case == "with" else ["lower"]
        cfg.vehicles = [VehicleSpec(name=n) for n in names]
        w = World(cfg, render=False)
        lower = w.vehicle("lower")
        lower.place([0.0, 0.0, 7.0], 0.0)
        if case == "with":
            w.vehicle("upper").place([0.0, 0.0, 8.0], 0.0)
        w.run(1.0)
        lower.goto([0.0, 0.0, 1.0], duration=12.0)
        rows = []
        for _ in range(1500):
            w.step()
            ref = lower._reference
            z_ref = float(ref[2]) if ref is not None else math.nan
            rows.append([w.t, lower.s[2], z_ref, lower.s[STATE.wind][2], lower.thrust])
        out[case] = np.array(rows)
    return out


def figure(data: dict[str, np.ndarray], path: Any) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 1, figsize=(8, 8), sharex=True)
    for case, style in (("alone", "--"), ("with", "-")):
        d = data[case]
        label = "below a vehicle hovering at 8 m" if case == "with" else "alone"
        axes[0].plot(d[:, 0], d[:, 1], style, label=f"height, {label}")
        axes[1].plot(d[:, 0], -d[:, 3], style, label=f"downward wind felt, {label}")
        axes[1].plot(d[:, 0], d[:, 4], style, lw=0.8, label=f"its thrust (N), {label}")
        axes[2].plot(d[:, 0], d[:, 1] - d[:, 2], style, label=f"height error, {label}")
    axes[0].axhline(8.0, color="grey", lw=0.8)
    axes[0].set_ylabel("height (m)")
    axes[1].set_ylabel("wake (m/s), thrust (N)")
    axes[2].set_ylabel("error (m)")
    axes[2].set_xlabel("time (s)")
    for ax in axes:
        ax.legend(fontsize=8)
        ax.grid(alpha=0.3)
    axes[0].set_title("A hummingbird descending 7 m -> 1 m in 12 s straight below another hovering at 8 m")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[1, 8, 64, 512, 4096])
    ap.add_argument("--rigs", type=int, nargs="+", default=[1, 2, 4, 8])
    ap.add_argument("--seconds", type=float, default=3.0, help="wall seconds per physics measurement")
    ap.add_argument("--sim-seconds", type=float, default=4.0, help="sim seconds per rendering measurement")
    ap.add_argument("--output", default=None, help="JSON path (default benchmarks/results/world.json)")
    args = ap.parse_args()

    physics = []
    print("physics + control, vehicle-steps/s (vehicles hovering; 1 vehicle-step = one 10 ms period):")
    heads = ("world, 10 RK4 sub-steps", "world, 1 RK4 step", "RotorPy batched rk4")
    print(f"  {'N':>5}  {heads[0]:>24}  {heads[1]:>18}  {heads[2]:>20}")
    for n in args.sizes:
        row = {"n": n, "world_10": time_world(n, 10, args.seconds), "world_1": time_world(n, 1, args.seconds),
               "rotorpy": time_rotorpy(n, args.seconds)}  # fmt: skip
        physics.append(row)
        rp = row["rotorpy"]["vehicle_steps_per_s"] if row["rotorpy"] else math.nan
        print(f"  {n:5d}  {row['world_10']['vehicle_steps_per_s']:24,.0f}  "
              f"{row['world_1']['vehicle_steps_per_s']:18,.0f}  {rp:20,.0f}", flush=True)  # fmt: skip
    single = time_single_vehicle(args.seconds)
    print(f"single-vehicle Simulator (no renderer): {single['real_time_factor']:.0f}x real time")

    rendering = []
    print("\nlockstep with every vehicle's 640x480 rig (RGB, depth, segmentation at 30 Hz):")
    for n in args.rigs:
        r = time_rendering(n, args.sim_seconds)
        rendering.append(r)
        print(f"  N={n}: RTF {r['real_time_factor']:.2f}, {r['camera_frames_per_s']:.1f} camera frames/s, "
              f"rendering {100 * r['render_share']:.0f} % of the wall time", flush=True)  # fmt: skip

    wake = downwash_flight()
    w_with, w_alone = wake["with"], wake["alone"]
    summary = {
        "peak_wake_m_s": float(-w_with[:, 3].min()),
        "peak_height_error_m": {"with": float(np.nanmax(np.abs(w_with[:, 1] - w_with[:, 2]))),
                                "alone": float(np.nanmax(np.abs(w_alone[:, 1] - w_alone[:, 2])))},
        "peak_thrust_n": {"with": float(w_with[:, 4].max()), "alone": float(w_alone[:, 4].max())},
    }  # fmt: skip
    err = summary["peak_height_error_m"]
    print(f"\ndownwash: peak wake {summary['peak_wake_m_s']:.2f} m/s, peak height error {err['with']:.3f} m "
          f"(alone {err['alone']:.3f} m)")  # fmt: skip
    out = write("world", {"physics": physics, "single_vehicle": single, "rendering": rendering,
                          "downwash": summary}, args.output)  # fmt: skip
    figure(wake, out.with_name("world_downwash.png"))


if __name__ == "__main__":
    main()
