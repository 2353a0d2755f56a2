"""``droneulator spray``: fly a coverage plan spraying, or run a spray trial; JSON and figures out."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from droneulator.cli.common import add_config_args, config_from_args
from droneulator.runtime import preflight

if TYPE_CHECKING:
    from droneulator.config import SimConfig

AIRFRAMES = ("sprayer10", "sprayer40")
TRIALS = ("hover", "pass")
#: parcels a nozzle releases a second here, unless ``spray.parcels_per_s`` is set (a run's default is 250)
PARCELS_PER_S = 3000.0


def add(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "spray",
        help="spray a scene along a coverage plan (or run a hover / pass trial) and write the deposit, "
        "the canopy dose, the drift and the mass balance",
        description="Fly the coverage plan of the scene's rows (or an open field's swaths) with a spray "
        "drone and write report.json (mass balance, each plant's dose by third, ground deposit in and off "
        "the target, the drift curve) with deposit_map.png, canopy_dose.png and drift_curve.png. With "
        "--trial, run a standard trial instead over bare ground: a hover spraying over a line of "
        "collectors 5 m upwind to 50 m downwind, or one pass across the wind (swath CV, effective swath, "
        "drift curve of a field of such passes). Wind, weather and the spray system come from the config "
        "(wind.*, weather.*, spray.*). With --px4, PX4 SITL flies the plan instead of the internal "
        "controller: the plan goes up as a mission (spray on and off by DO_SET_ACTUATOR) and PX4 flies it "
        "in lockstep, from take-off to its RTL landing (docs/spray.md).",
    )
    add_config_args(p, "vineyard")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument(
        "--airframe",
        choices=AIRFRAMES,
        default="sprayer10",
        help="spray drone: its parameters (vehicle.params) and its spray system (tank and nozzles; "
        "--set spray.* still applies over them)",
    )
    p.add_argument("--trial", choices=TRIALS, default=None, help="run a trial instead of the scene's plan")
    p.add_argument("--height", type=float, default=None, help="height above the canopy (plan; default 1.5 m) "
                   "or above the ground (trial; default 2.5 m)")  # fmt: skip
    p.add_argument("--speed", type=float, default=None, help="flight speed (m/s; default 3 for the plan, 5 "
                   "for the pass trial)")  # fmt: skip
    p.add_argument("--duration", type=float, default=10.0, help="hover trial: spraying time (s)")
    p.add_argument("--rows", type=int, default=None, metavar="N",
                   help="fly only the plan's first N rows (or swaths), with the turns between")  # fmt: skip
    p.add_argument(
        "--px4",
        action="store_true",
        help="fly the plan with PX4 SITL (start it as docs/px4.md says): listen on TCP 4560+N for PX4's "
        "simulator link, set PX4's PWM_MAIN_FUNC5=301 (the spray output), upload the plan as a mission on "
        "PX4's onboard MAVLink (UDP 14540+N), start it, and wait until PX4 has landed and disarmed",
    )
    p.add_argument("--px4-instance", type=int, default=None, metavar="N",
                   help="PX4 instance N (implies --px4; default 0)")  # fmt: skip
    p.add_argument("--px4-port", type=int, default=None, metavar="PORT",
                   help="UDP port PX4's onboard MAVLink sends to (implies --px4; 14540+N)")  # fmt: skip
    p.add_argument("--px4-timeout", type=float, default=120.0, metavar="S",
                   help="wall seconds to wait for PX4 to connect before giving up (default 120)")  # fmt: skip
    p.set_defaults(func=cmd_spray)


def cmd_spray(args: argparse.Namespace) -> int:
    overrides = [f"vehicle.params={args.airframe}", *args.overrides]
    args.overrides = overrides
    cfg = config_from_args(args)
    from droneulator.config import apply_override, from_dict
    from droneulator.config.loading import load_file
    from droneulator.config.spray import SprayConfig
    from droneulator.vehicles.sprayers import spray_system

    # the airframe's spray system, under the config file's spray section and the --set spray.* overrides
    data = {
        "spray": {
            **spray_system(args.airframe),
            **(load_file(args.config).get("spray", {}) if args.config else {}),
        }
    }
    for item in args.overrides:
        if item.startswith("spray."):
            data = apply_override(data, item)
    data["spray"].setdefault("parcels_per_s", PARCELS_PER_S)  # a finer cloud than a live run's
    cfg.spray = from_dict(SprayConfig, data["spray"], "spray")
    sizes = (("height", args.height), ("speed", args.speed), ("duration", args.duration), ("rows", args.rows))
    for name, value in sizes:
        if value is not None and not value > 0:
            raise preflight.StartupError(f"--{name} must be > 0, got {value}", preflight.USAGE)
    px4 = args.px4 or args.px4_instance is not None or args.px4_port is not None
    if px4:
        _px4_config(args, cfg)
    preflight.check_output_dir(args.out)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    from tqdm import tqdm

    with tqdm(total=100, desc="spray", unit="%", bar_format="{l_bar}{bar}| {postfix}") as bar:

        def progress(frac: float, note: str = "") -> None:
            if int(100 * frac) != bar.n:
                bar.n = int(100 * frac)
                bar.set_postfix_str(note, refresh=False)
                bar.refresh()

        if args.trial:
            return _trial(args, cfg, out, progress)
        from droneulator.scenes import get_scene
        from droneulator.workflows.spraying.coverage import coverage_plan, first_lanes
        from droneulator.workflows.spraying.mission import fly_plan
        from droneulator.workflows.spraying.report import mission_figures, write_json

        plan = coverage_plan(get_scene(cfg.scene, cfg.seed, cfg.vegetation), height=args.height or 1.5,
                             speed=args.speed or 3.0)  # fmt: skip
        if args.rows is not None:
            plan = first_lanes(plan, args.rows)
        if px4:
            from droneulator.workflows.spraying.px4_flight import PX4FlightError, PX4Options, fly_plan_px4

            opts = PX4Options(args.px4_instance or 0, args.px4_port, args.px4_timeout)
            try:
                report, spraying = fly_plan_px4(cfg, plan, opts, progress=progress)
            except PX4FlightError as exc:
                raise preflight.StartupError(f"--px4: {exc}") from None
        else:
            report, spraying = fly_plan(cfg, plan, progress=progress)
        report["plan"] = {"legs": len(plan.legs), "altitude_m": plan.altitude, "target": list(plan.target),
                          "spray_length_m": plan.spray_length_m}  # fmt: skip
        write_json(out / "report.json", report)
        figures = mission_figures(out, report, spraying.cloud, plan.target)
    print(f"sprayed {report['sprayed_l']:.2f} L over {report['target_area_m2']:.0f} m^2 "
          f"({report['applied_l_ha']:.1f} L/ha): {100 * report['canopy_share']:.1f} % on the canopy, "
          f"mass balance error {report['mass_balance_error']:.1e}")  # fmt: skip
    for path in [out / "report.json", *figures]:
        print(path)
    return 0


def _px4_config(args: argparse.Namespace, cfg: SimConfig) -> None:
    """Hand the sprayer to PX4 (``px4.enabled``, instance N) at PX4's 250 Hz lockstep; refuse a trial or
    a vehicle that is not a sprayer."""
    from droneulator.vehicles.sprayers import SPRAYERS

    if args.trial:
        raise preflight.StartupError("--px4 flies the coverage plan, not a --trial", preflight.USAGE)
    params = cfg.vehicles[0].params if cfg.vehicles and cfg.vehicles[0].params else cfg.vehicle.params
    if params not in SPRAYERS:
        raise preflight.StartupError(
            f"--px4: the vehicle ({params}) is not a sprayer: fly one of {', '.join(SPRAYERS)} (--airframe)",
            preflight.USAGE,
        )
    if args.px4_timeout is None or not args.px4_timeout > 0:
        raise preflight.StartupError(f"--px4-timeout must be > 0, got {args.px4_timeout}", preflight.USAGE)
    cfg.px4.enabled = True
    cfg.px4.instance = args.px4_instance or 0
    cfg.vehicle.control_hz = 250.0  # PX4 SITL's lockstep rate (IMU_INTEG_RATE)
    if not any(item.startswith("px4.speed_factor=") for item in args.overrides):
        cfg.px4.speed_factor = 0.0  # a batch run: as fast as PX4 answers, not paced by the wall clock
    try:
        cfg.check_autopilots()
    except ValueError as exc:
        raise preflight.StartupError(f"--px4: {exc}", preflight.USAGE) from None


def _trial(args: argparse.Namespace, cfg: SimConfig, out: Path, progress: Callable[..., None]) -> int:
    import numpy as np

    from droneulator.spray import trials
    from droneulator.workflows.spraying.report import trial_figure, write_json

    if args.trial == "hover":
        result = trials.hover_trial(cfg.spray, cfg.weather, cfg.wind, args.airframe, args.height or 2.5,
                                    args.duration, cfg.seed, progress)  # fmt: skip
    else:
        result = trials.pass_trial(cfg.spray, cfg.weather, cfg.wind, args.airframe, args.height or 2.5,
                                   args.speed or 5.0, seed=cfg.seed, progress=progress)  # fmt: skip
    data = result.to_dict()
    xs, prof = np.asarray(result.profile_x_m), np.asarray(result.profile_ul_cm2)
    if args.trial == "pass":
        swath = trials.effective_swath(xs, prof)
        data["effective_swath_m"] = swath
        data["cv_at_effective_swath"] = trials.swath_cv(xs, prof, swath) if swath else None
        if swath:
            data["drift"] = trials.drift_curve(xs, prof, swath)
    write_json(out / f"trial_{args.trial}.json", data)
    trial_figure(out / f"trial_{args.trial}.png", data)
    print(f"{args.trial} trial: {data['sprayed_l']:.3f} L sprayed, {result.parcels} parcels, "
          f"{result.sim_s:.1f} s simulated" + (f", effective swath {data['effective_swath_m']:.2f} m"
                                               if args.trial == "pass" else ""))  # fmt: skip
    print(out / f"trial_{args.trial}.json")
    print(out / f"trial_{args.trial}.png")
    return 0
