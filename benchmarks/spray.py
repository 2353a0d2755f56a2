"""The spray model's speed and its checks.

1. **Parcel steps per second** of the compiled step (:func:`droneulator.spray.kernel.step_parcels`): a
   cloud of ``--parcels`` parcels of a Fine spray under a hovering sprayer10 over the vineyard (canopy,
   wood and shelter grids, 3 m/s Dryden wind), stepped ``--steps`` times with the releases off; the same
   cloud stepped on one thread in the same run is the baseline to quote against.
2. **One 100 m row pass at 5 m/s** (the sprayer10 at 2.5 m with its four flat fans, ``--pass-parcels``
   parcels released per second of flight, 3 m/s wind): wall time against the flight's 20 s and against
   all the simulated time until the cloud has settled (real-time factor: simulated / wall).
3. **Spraying inside a fleet's lockstep step**: a World of four sprayer10 flying 3 m/s legs, stepped
   with and without their spray systems on (``--fleet-parcels`` per nozzle per second, a 20 ms cloud
   step), in one process, without cameras (the cheapest step there is: an upper bound on the share) and
   rendering every vehicle's cameras as a run does.
4. Checks: terminal velocities against Gunn & Kinzer (1949) and the row pass's mass balance.

Reproduce: ``python benchmarks/spray.py`` (about 2 min on 2 cores).
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import numpy as np
from _common import write


def parcel_steps(parcels: int, steps: int) -> dict[str, Any]:
    import numba

    from droneulator.config import SprayConfig, WeatherConfig, WindConfig, from_dict
    from droneulator.scenes import get_scene
    from droneulator.spray.cloud import Domain, SprayCloud
    from droneulator.spray.spraying import shelter_grid
    from droneulator.spray.targets import SprayTargets
    from droneulator.spray.trials import Airframe
    from droneulator.vehicles.sprayers import spray_system

    scene = get_scene("vineyard", 0)
    wind = WindConfig(speed_m_s=3.0)
    targets = SprayTargets.of(scene)
    spray = from_dict(SprayConfig, {**spray_system("sprayer10"), "parcels_per_s": parcels / 4 / 0.5})
    cloud = SprayCloud(
        spray,
        WeatherConfig(),
        wind,
        Domain(-80, 80, -70, 70, 40),
        targets,
        shelter_grid(scene, targets, wind),
    )
    frame = Airframe.of("sprayer10", spray)
    pos = np.array([0.0, scene.landmarks["row_y"][2], 3.5])
    wv = np.array([3.0, 0.0, 0.0])
    for _ in range(50):  # half a second of spraying: the cloud
        cloud.step([frame.emitter(pos, np.zeros(3), wv, [(n, 1e-5) for n in spray.nozzles])])
    quiet = [frame.emitter(pos, np.zeros(3), wv, [])]
    rotors, vortices = cloud.rotor_rows(quiet), cloud.vortex_rows(quiet)
    names = ("x", "v", "turb", "d", "dres", "n", "ids")
    state = [getattr(cloud, a).copy() for a in names]
    count = cloud.count

    def run(threads: int) -> float:
        for a, s in zip(names, state, strict=True):
            setattr(cloud, a, s.copy())
        cloud.count = count
        numba.set_num_threads(threads)
        cloud.advance(rotors, vortices)  # compiled
        alive = 0
        t0 = time.perf_counter()
        for _ in range(steps):
            alive += int(np.count_nonzero(cloud.n[: cloud.count] > 0))
            cloud.advance(rotors, vortices)
        return alive / (time.perf_counter() - t0)

    threads = numba.get_num_threads()
    serial = run(1)
    parallel = run(threads)
    numba.set_num_threads(threads)
    return {
        "parcels": int(cloud.count),
        "steps": steps,
        "threads": threads,
        "parcel_steps_per_s": parallel,
        "parcel_steps_per_s_one_thread": serial,
        "speedup": parallel / serial,
    }


def row_pass(parcels_per_s: float) -> dict[str, Any]:
    from droneulator.config import SprayConfig, WeatherConfig, WindConfig, from_dict
    from droneulator.spray import trials
    from droneulator.vehicles.sprayers import spray_system

    spray = from_dict(SprayConfig, {**spray_system("sprayer10"), "parcels_per_s": parcels_per_s / 4})
    t0 = time.perf_counter()
    flight: dict[str, float] = {}

    def progress(frac: float) -> None:
        if frac >= 0.5 and "wall_s" not in flight:
            flight["wall_s"] = time.perf_counter() - t0

    r = trials.pass_trial(
        spray, WeatherConfig(), WindConfig(speed_m_s=3.0), "sprayer10", 2.5, 5.0, 100.0, progress=progress
    )
    wall = time.perf_counter() - t0
    return {
        "parcels": r.parcels,
        "flight_s": 20.0,
        "flight_wall_s": flight["wall_s"],
        "sim_s": r.sim_s,
        "wall_s": wall,
        "real_time_factor_flight": 20.0 / flight["wall_s"],
        "real_time_factor": r.sim_s / wall,
        "mass_balance_error": abs(sum(r.ledger.values()) - 1.0),
        "ledger": r.ledger,
    }


def fleet_cost(seconds: float, parcels_per_s: float, render: bool) -> dict[str, Any]:
    from droneulator.config import SprayConfig, fleet, from_dict, load_config
    from droneulator.spray.spraying import Spraying
    from droneulator.vehicles.sprayers import spray_system
    from droneulator.world.world import World

    def run(spraying_on: bool) -> float:
        cfg = load_config(overrides=["vehicle.params=sprayer10", "scene=vineyard", "wind.speed_m_s=3"])
        cfg.spray = from_dict(
            SprayConfig, {**spray_system("sprayer10"), "parcels_per_s": parcels_per_s, "dt_s": 0.02}
        )
        cfg.vehicles = fleet(4)
        world = World(cfg, render=render)
        sp = Spraying(world) if spraying_on else None
        rows = world.scene.landmarks["row_y"]
        for v in world.vehicles.values():
            v.takeoff(3.5)
        for _ in range(300):
            world.step()
        for k, v in enumerate(world.vehicles.values()):
            v.goto([14.0, rows[k], 3.5], yaw=0.0, speed=3.0)
            if sp:
                sp.system(v.name).set(1.0)
        steps = round(seconds / 0.01)
        t0 = time.perf_counter()
        for _ in range(steps):
            world.step()
            if sp:
                sp.step()
        return seconds / (time.perf_counter() - t0)

    run(True)  # compile both paths
    plain, spraying = run(False), run(True)
    return {
        "render": render,
        "parcels_per_s_per_nozzle": parcels_per_s,
        "vehicles": 4,
        "sim_s": seconds,
        "real_time_factor": plain,
        "real_time_factor_spraying": spraying,
        "cost": 1.0 - spraying / plain,
    }


def checks() -> dict[str, Any]:
    from droneulator.config import WeatherConfig
    from droneulator.spray.droplets import Air, terminal_velocity

    gk = {
        100: 0.27,
        200: 0.72,
        300: 1.17,
        400: 1.62,
        500: 2.06,
        600: 2.47,
        700: 2.87,
        800: 3.27,
        900: 3.67,
        1000: 4.03,
    }
    air = Air.of(WeatherConfig(temperature_c=20.0, relative_humidity=0.5))
    rows = [
        {
            "d_um": d,
            "gunn_kinzer_m_s": v,
            "model_m_s": terminal_velocity(d * 1e-6, air),
            "error": terminal_velocity(d * 1e-6, air) / v - 1.0,
        }
        for d, v in gk.items()
    ]
    return {"terminal_velocity": rows}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--parcels", type=int, default=200_000)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--pass-parcels", type=float, default=6000.0, help="parcels per second of flight")
    ap.add_argument("--fleet-seconds", type=float, default=10.0)
    ap.add_argument("--fleet-parcels", type=float, default=250.0, help="parcels per second per nozzle")
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    out: dict[str, Any] = {"checks": checks()}
    for row in out["checks"]["terminal_velocity"]:
        d, v, gk, err = row["d_um"], row["model_m_s"], row["gunn_kinzer_m_s"], 100 * row["error"]
        print(f"terminal velocity {d:5d} um: {v:.3f} m/s (G&K {gk}, {err:+.1f} %)")
    out["parcel_steps"] = p = parcel_steps(a.parcels, a.steps)
    one = p["parcel_steps_per_s_one_thread"]
    print(
        f"parcel steps/s: {p['parcel_steps_per_s']:.3g} on {p['threads']} threads, {one:.3g} on one "
        f"({p['speedup']:.2f}x), {p['parcels']} parcels"
    )
    out["row_pass"] = r = row_pass(a.pass_parcels)
    print(
        f"100 m pass at 5 m/s: {r['parcels']} parcels, flight {r['flight_wall_s']:.1f} s wall for 20 s "
        f"({r['real_time_factor_flight']:.2f}x real time), all {r['sim_s']:.1f} s simulated in "
        f"{r['wall_s']:.1f} s ({r['real_time_factor']:.2f}x), mass balance error "
        f"{r['mass_balance_error']:.1e}"
    )
    out["fleet"] = []
    for render in (False, True):
        f = fleet_cost(a.fleet_seconds / (5 if render else 1), a.fleet_parcels, render)
        out["fleet"].append(f)
        rtf, rtf_s = f["real_time_factor"], f["real_time_factor_spraying"]
        what = "rendering its cameras" if render else "no cameras"
        print(
            f"fleet of 4 ({what}): {rtf:.2f}x real time, {rtf_s:.2f}x spraying (cost {100 * f['cost']:.0f} %)"
        )
    write("spray", out, a.out)


if __name__ == "__main__":
    main()
