"""``droneulator plan``: the depth-only local planner node, against a running ``droneulator run``."""

from __future__ import annotations

import argparse
import json
import sys
import threading
from pathlib import Path

from droneulator.cli.common import DEFAULT_ZENOH


def add(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "plan",
        help="run the depth-only local planner node against a running `droneulator run`",
        description="Map from the depth image, plan B-splines to goals taken on /<ns>/planner/goal "
        "(geometry_msgs/PoseStamped) and publish quadrotor_msgs/PositionCommand on /<ns>/position_cmd "
        "at 100 Hz of sim time, all over Zenoh. Never reads the scene or the WebSocket state.",
    )
    p.add_argument("--zenoh", default=DEFAULT_ZENOH, help="Zenoh endpoint of the run's bridge")
    p.add_argument("--namespace", default="droneulator", help="the run's ROS namespace")
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
    p.add_argument("--max-vel", type=float, default=defaults.max_vel, help="planning speed limit (m/s)")
    p.add_argument("--max-acc", type=float, default=defaults.max_acc, help="planning accel. limit (m/s²)")
    p.add_argument(
        "--stats",
        default=None,
        metavar="FILE",
        help="on exit, write plan/map-update times and counters as JSON",
    )
    p.add_argument("-v", "--verbose", action="store_true", help="log every plan (debug level)")
    p.add_argument(
        "--px4",
        action="store_true",
        help="fly PX4 SITL in OFFBOARD (SET_POSITION_TARGET_LOCAL_NED on UDP 14540+N) instead of "
        "publishing PositionCommand: a goal makes PX4 hold where it is in OFFBOARD, then the planner "
        "plans, checks arrival and tracking on PX4's own position estimate; see docs/planning.md",
    )
    p.add_argument("--px4-instance", type=int, default=None, metavar="N", help="PX4 instance (implies --px4)")
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
        help="geodetic point of the run's world origin if the run changed px4.home_* (default: the defaults)",
    )
    p.add_argument(
        "--px4-on-stop",
        choices=("hold", "loiter", "land"),
        default="hold",
        help="when setpoints stop: keep streaming the last position (hold) or switch PX4 to AUTO.LOITER/LAND",
    )
    p.set_defaults(func=cmd_plan)


def cmd_plan(args: argparse.Namespace) -> int:
    import contextlib
    import logging
    import signal

    from droneulator.workflows.planning.config import PlannerConfig
    from droneulator.workflows.planning.node import PlanNode, PlanNodeConfig

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    if args.verbose:
        logging.getLogger("droneulator").setLevel(logging.DEBUG)
    bounds = None if args.bounds is None else (tuple(args.bounds[:3]), tuple(args.bounds[3:]))
    cfg = PlanNodeConfig(zenoh=args.zenoh, namespace=args.namespace, camera=args.camera, bounds=bounds)
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
        if args.px4 or args.px4_instance is not None:
            from droneulator.workflows.planning.offboard import OffboardConfig, OffboardLink

            home = {}
            if args.px4_home is not None:
                home = dict(zip(("home_lat_deg", "home_lon_deg", "home_alt_m"), args.px4_home, strict=True))
            origin = None if args.px4_origin is None else tuple(args.px4_origin)
            link_cfg = OffboardConfig(
                host=args.px4_host,
                instance=args.px4_instance or 0,
                on_stop=args.px4_on_stop,
                origin_enu=origin,
                **home,
            )
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
