"""``droneulator plan``: the depth-only local planner node, against a running ``droneulator run``."""

from __future__ import annotations

import argparse
import json
import logging
import sys
import threading
from pathlib import Path
from typing import TYPE_CHECKING, Any

from droneulator.cli.common import DEFAULT_ZENOH, add_file_args
from droneulator.runtime import preflight
from droneulator.runtime.preflight import StartupError

if TYPE_CHECKING:
    from droneulator.config import SimConfig
    from droneulator.workflows.planning.fleet import PlannedVehicle

log = logging.getLogger("droneulator.plan")
DEFAULT_URL = "ws://127.0.0.1:8765"


def add(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "plan",
        help="run the depth-only local planner node against a running `droneulator run`",
        description="Map from the depth image, plan B-splines to goals taken on /<ns>/planner/goal "
        "(geometry_msgs/PoseStamped) and publish quadrotor_msgs/PositionCommand on /<ns>/position_cmd "
        "at 100 Hz of sim time, all over Zenoh, for one vehicle (one process per vehicle of a fleet: "
        "<ns> is then /droneulator/<vehicle>). Asks the run's API once which names that vehicle has "
        "(scene_info, or reads the run's --config); never reads the scene or the vehicle state.",
    )
    p.add_argument("--zenoh", default=DEFAULT_ZENOH, help="Zenoh endpoint of the run's bridge")
    p.add_argument(
        "--vehicle",
        default=None,
        metavar="NAME",
        help="the vehicle to plan for (default: the run's first); its topics, TF frames and PX4 instance "
        "as the run's scene_info lists them (--url), or as its --config sets them",
    )
    p.add_argument("--url", default=DEFAULT_URL, help="the run's WebSocket API, asked for scene_info")
    add_file_args(p, "--set px4.instance=2")
    p.add_argument(
        "--namespace",
        default=None,
        help="the ROS namespace of a one-vehicle run: its names, without asking the run (default: ask "
        "the run; droneulator if none answers)",
    )
    p.add_argument("--camera", default="front", help="depth camera to map from")
    p.add_argument(
        "--goal", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"), help="first goal (odom frame)"
    )
    p.add_argument(
        "--bounds",
        type=float,
        nargs=6,
        default=None,
        metavar=("XMIN", "YMIN", "ZMIN", "XMAX", "YMAX", "ZMAX"),
        help="box goals must lie in (default: the local map around the vehicle when the goal arrives)",
    )
    from droneulator.workflows.planning.config import PlannerConfig

    defaults = PlannerConfig()
    p.add_argument(
        "--ceiling", type=float, default=None, metavar="Z", help="virtual ceiling (world z, m), as EGO's"
    )
    p.add_argument("--floor", type=float, default=None, metavar="Z", help="virtual floor (world z, m)")
    p.add_argument(
        "--margin",
        type=float,
        default=defaults.inflation_margin,
        help=f"obstacles are inflated by the vehicle radius ({defaults.vehicle_radius} m) plus this (m)",
    )
    p.add_argument(
        "--tracking-margin-max",
        type=float,
        default=0.5,
        metavar="M",
        help="with --px4/--ardupilot, obstacles grow by up to M more (0: never) by the 95th percentile of "
        "the measured distance between the setpoints and the autopilot's estimate (default 0.5)",
    )
    p.add_argument("--max-vel", type=float, default=defaults.max_vel, help="planning speed limit (m/s)")
    p.add_argument("--max-acc", type=float, default=defaults.max_acc, help="planning accel. limit (m/s²)")
    p.add_argument(
        "--stats",
        default=None,
        metavar="FILE",
        help="on exit, write plan/map-update times and counters as JSON",
    )
    p.add_argument(
        "--yaw-lookahead",
        type=float,
        default=None,
        metavar="S",
        help="face the trajectory this many sim seconds ahead (EGO's traj_server time_forward; 0: along "
        "the velocity; default: PlanNodeConfig.yaw_lookahead_s, 1 s)",
    )
    p.add_argument("-v", "--verbose", action="store_true", help="log every plan (debug level)")
    p.add_argument(
        "--px4",
        action="store_true",
        help="fly PX4 SITL in OFFBOARD (SET_POSITION_TARGET_LOCAL_NED on UDP 14540+N, 14549 past 9) instead "
        "of publishing PositionCommand: a goal makes PX4 hold where it is in OFFBOARD, then the planner "
        "plans, checks arrival and tracking on PX4's own position estimate; see docs/planning.md",
    )
    p.add_argument(
        "--px4-instance",
        type=int,
        default=None,
        metavar="N",
        help="PX4 instance (implies --px4; default: the vehicle's, from scene_info or --config, else 0)",
    )
    p.add_argument(
        "--px4-sysid",
        type=int,
        default=None,
        metavar="ID",
        help="PX4's MAV_SYS_ID to follow on the port (default: instance + 1, as PX4 SITL sets it)",
    )
    p.add_argument("--px4-host", default="127.0.0.1", help="address to bind PX4's offboard UDP port on")
    p.add_argument(
        "--px4-origin",
        type=float,
        nargs=3,
        default=None,
        metavar=("X", "Y", "Z"),
        help="world (ENU) position of PX4's local NED origin (default: PX4's GPS_GLOBAL_ORIGIN and the home)",
    )
    p.add_argument(
        "--px4-home",
        type=float,
        nargs=3,
        default=None,
        metavar=("LAT", "LON", "ALT"),
        help="geodetic point of the run's world origin (default: the run's site section, else the default)",
    )
    p.add_argument(
        "--px4-on-stop",
        choices=("hold", "loiter", "land"),
        default="hold",
        help="when setpoints stop: keep streaming the last position (hold) or switch PX4 to AUTO.LOITER/LAND",
    )
    p.add_argument(
        "--ardupilot",
        action="store_true",
        help="fly ArduCopter SITL in GUIDED (SET_POSITION_TARGET_LOCAL_NED over its MAVLink, TCP 5760+10N) "
        "instead of publishing PositionCommand: a goal puts it in GUIDED (arming and taking off if it is on "
        "the ground), then the planner plans on its EKF's estimate; see docs/ardupilot.md",
    )
    p.add_argument(
        "--ardupilot-instance",
        type=int,
        default=None,
        metavar="N",
        help="ArduPilot instance (implies --ardupilot; default: the vehicle's, from scene_info or --config, "
        "else 0)",
    )
    p.add_argument("--ardupilot-host", default="127.0.0.1", help="where ArduCopter's MAVLink TCP port is")
    p.add_argument(
        "--ardupilot-takeoff",
        type=float,
        default=2.0,
        metavar="M",
        help="take off to this height when a goal comes with ArduCopter on the ground (default 2 m)",
    )
    p.add_argument(
        "--ardupilot-on-stop",
        choices=("hold", "loiter", "land"),
        default="hold",
        help="on exit: stay in GUIDED holding the last position, or switch ArduCopter to LOITER or LAND",
    )
    p.set_defaults(func=cmd_plan)


def resolve_vehicle(args: argparse.Namespace) -> tuple[PlannedVehicle, SimConfig | None]:
    """The vehicle to plan for, and the run's configuration when ``--config``/``--set`` gave it: from
    that configuration, else the single vehicle's names under ``--namespace`` when it is given without
    ``--vehicle``, else from the run's ``scene_info``; with no run answering, the single vehicle's."""
    from droneulator.workflows.planning import fleet

    if args.vehicle is None and args.namespace is not None and args.config is None and not args.overrides:
        return fleet.single_vehicle(args.namespace), None
    triggered = StartupError(
        "the run triggers its cameras (render.camera_trigger=command): the planner needs depth at the "
        "camera rate; start the run without that setting",
        preflight.USAGE,
    )
    try:
        if args.config is not None or args.overrides:
            cfg = preflight.load(args.config, args.overrides)
            if cfg.render.camera_trigger == "command":
                raise triggered
            return fleet.from_config(cfg, args.vehicle), cfg
        info = _scene_info(args.url)
        if info is not None:
            if info.get("camera_trigger") == "command":
                raise triggered
            return fleet.from_scene_info(info, args.vehicle), None
    except ValueError as exc:
        raise StartupError(f"--vehicle: {exc}", preflight.USAGE) from None
    if args.vehicle is not None:
        raise StartupError(
            f"--vehicle {args.vehicle}: the run's API at {args.url} does not answer; give the run's --url, "
            "or its --config",
            preflight.USAGE,
        )
    ns = args.namespace or "droneulator"
    log.info("no run answers at %s: planning for the single vehicle's topics under /%s", args.url, ns)
    return fleet.single_vehicle(ns), None


def _scene_info(url: str) -> dict[str, Any] | None:
    """The run's ``scene_info``, or None when nothing answers at ``url``."""
    from websockets.exceptions import WebSocketException

    from droneulator.api.client import ApiError, DroneulatorClient

    try:
        with DroneulatorClient(url, timeout=5.0) as client:
            return client.scene_info()
    except (OSError, TimeoutError, WebSocketException, ApiError) as exc:
        log.debug("scene_info from %s: %s", url, exc)
        return None


def cmd_plan(args: argparse.Namespace) -> int:
    import contextlib
    import signal

    from droneulator.workflows.planning.config import PlannerConfig
    from droneulator.workflows.planning.node import PlanNode, PlanNodeConfig

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    if args.verbose:
        logging.getLogger("droneulator").setLevel(logging.DEBUG)
    bounds = None if args.bounds is None else (tuple(args.bounds[:3]), tuple(args.bounds[3:]))
    vehicle, run_cfg = resolve_vehicle(args)
    try:
        cfg = PlanNodeConfig(
            zenoh=args.zenoh,
            camera=args.camera,
            bounds=bounds,
            vehicle=vehicle,
            tracking_margin_max=args.tracking_margin_max,
            **({} if args.yaw_lookahead is None else {"yaw_lookahead_s": args.yaw_lookahead}),
        )
    except ValueError as exc:
        raise StartupError(str(exc), preflight.USAGE) from None
    log.info("planning for vehicle %s (%s): goals on /%s/planner/goal", vehicle.name, vehicle.source,
             vehicle.names.namespace)  # fmt: skip
    try:
        planner = PlannerConfig(
            ceiling=args.ceiling,
            floor=args.floor,
            max_vel=args.max_vel,
            max_acc=args.max_acc,
            inflation_margin=args.margin,
        )
    except ValueError as exc:
        raise SystemExit(f"droneulator: error: {exc}") from None
    done = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    with contextlib.ExitStack() as stack:
        autopilot = None
        ardupilot = args.ardupilot or args.ardupilot_instance is not None
        if ardupilot and (args.px4 or args.px4_instance is not None):
            raise StartupError(
                "--px4 and --ardupilot: one autopilot flies the vehicle, choose one", preflight.USAGE
            )
        if ardupilot:
            autopilot = stack.enter_context(_guided_link(args, vehicle, run_cfg))
        if args.px4 or args.px4_instance is not None:
            from droneulator.workflows.planning.offboard import OffboardConfig, OffboardLink

            keys = ("home_lat_deg", "home_lon_deg", "home_alt_m")
            home = {}
            if args.px4_home is not None:
                home = dict(zip(keys, args.px4_home, strict=True))
            elif run_cfg is not None:
                home = dict(zip(keys, run_cfg.site.geodetic, strict=True))
            origin = None if args.px4_origin is None else tuple(args.px4_origin)
            try:
                link_cfg = OffboardConfig(
                    host=args.px4_host,
                    instance=_px4_instance(args, vehicle),
                    system_id=args.px4_sysid,
                    on_stop=args.px4_on_stop,
                    origin_enu=origin,
                    **home,
                )
            except ValueError as exc:
                raise StartupError(f"--px4: {exc}", preflight.USAGE) from None
            autopilot = stack.enter_context(OffboardLink(link_cfg))
        node = stack.enter_context(PlanNode(cfg, planner, autopilot=autopilot))
        if args.goal is not None:
            node.set_goal(args.goal)
        try:
            done.wait()
        except KeyboardInterrupt:
            print("droneulator plan: interrupted, closing", file=sys.stderr)
    if args.stats:
        Path(args.stats).write_text(json.dumps(node.stats(), indent=1))
    return 0


def _guided_link(args: argparse.Namespace, vehicle: PlannedVehicle, run_cfg: SimConfig | None) -> Any:
    """ArduCopter's GUIDED link for ``--ardupilot``: its instance (``--ardupilot-instance``, else the
    run's for the vehicle, else 0) and the run's site as home."""
    from droneulator.workflows.planning.guided import GuidedConfig, GuidedLink

    instance = args.ardupilot_instance
    if instance is None and vehicle.source != "defaults":
        try:
            instance = vehicle.ardupilot()
        except ValueError as exc:
            raise StartupError(f"--ardupilot: {exc}", preflight.USAGE) from None
    home = {}
    if run_cfg is not None:
        home = dict(zip(("home_lat_deg", "home_lon_deg", "home_alt_m"), run_cfg.site.geodetic, strict=True))
    try:
        cfg = GuidedConfig(
            host=args.ardupilot_host,
            instance=instance or 0,
            takeoff_alt_m=args.ardupilot_takeoff,
            on_stop=args.ardupilot_on_stop,
            **home,
        )
        return GuidedLink(cfg)
    except ValueError as exc:
        raise StartupError(f"--ardupilot: {exc}", preflight.USAGE) from None
    except OSError as exc:
        where = f"tcp://{args.ardupilot_host}:{5760 + 10 * (instance or 0)}"
        raise StartupError(
            f"--ardupilot: no ArduCopter MAVLink on {where} ({exc.strerror or exc}); start arducopter with "
            "--serial0 tcp:0 (docs/ardupilot.md)"
        ) from None


def _px4_instance(args: argparse.Namespace, vehicle: PlannedVehicle) -> int:
    """``--px4-instance``, else the PX4 instance the run gives the vehicle, else 0 (nothing told)."""
    if args.px4_instance is not None:
        return args.px4_instance
    if vehicle.source == "defaults":
        return 0
    try:
        return vehicle.px4()
    except ValueError as exc:
        raise StartupError(f"--px4: {exc}", preflight.USAGE) from None
