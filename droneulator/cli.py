"""The ``droneulator`` command line."""

from __future__ import annotations

import argparse
import json
import sys
import threading
from pathlib import Path

from droneulator.config import SimConfig, load_config


def _add_config_args(p: argparse.ArgumentParser, scene_default: str | None = None) -> None:
    p.add_argument("--scene", default=scene_default, help="scene name (see `droneulator scenes`)")
    p.add_argument("--seed", type=int, default=None, help="scene and noise seed (default 0)")
    p.add_argument("--config", default=None, help="JSON or TOML file with SimConfig fields")
    p.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override one option, e.g. --set render.shadows=false --set vehicle.params=crazyflie",
    )


def _config(args: argparse.Namespace) -> SimConfig:
    return load_config(args.config, args.overrides, scene=args.scene, seed=args.seed)


def cmd_scenes(args: argparse.Namespace) -> int:
    from droneulator.scenes import list_scenes

    for name, desc in list_scenes().items():
        print(f"{name:18s} {desc}")
    return 0


def cmd_snapshot(args: argparse.Namespace) -> int:
    from droneulator.snapshot import snapshot

    written = snapshot(_config(args), Path(args.out), altitude=args.altitude)
    for key, path in written.items():
        print(f"{key:28s} {path}")
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from droneulator.demo import run_demo

    summary = run_demo(_config(args), Path(args.out), save_every=args.save_every)
    Path(args.out, "summary.json").write_text(json.dumps(summary, indent=2))
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    from droneulator.runtime.supervisor import Supervisor

    cfg = _config(args)
    if args.realtime:
        cfg.runtime.mode = "realtime"
    if args.api_port is not None:
        cfg.runtime.api_port = args.api_port
    if args.px4 or args.px4_instance is not None:
        defaults = load_config()
        cfg.px4.enabled = True
        cfg.px4.instance = args.px4_instance or 0
        # PX4's lockstep runs at 250 Hz; its SIH quad-X parameters suit PX4's default gains
        if cfg.vehicle.control_hz == defaults.vehicle.control_hz:
            cfg.vehicle.control_hz = 250.0
        if cfg.vehicle.params == defaults.vehicle.params:
            cfg.vehicle.params = "px4_quadx"
        n = cfg.px4.instance
        if n:  # one simulator per vehicle: keep the instances' ports and topics apart
            if args.api_port is None:
                cfg.runtime.api_port += n
            if cfg.bridge.listen == defaults.bridge.listen:
                cfg.bridge.listen = [f"tcp/127.0.0.1:{7448 + n}"]
            if cfg.bridge.namespace == defaults.bridge.namespace:
                cfg.bridge.namespace = f"{defaults.bridge.namespace}{n}"
    sup = Supervisor(cfg)
    sup.install_signal_handlers()
    try:
        sup.start()
    except RuntimeError as exc:
        sup.stop()
        print(f"droneulator: error: {exc}", file=sys.stderr)
        return 1
    if args.demo:
        from droneulator.runtime.demo_client import run_demo_client

        threading.Thread(
            target=run_demo_client, args=(cfg, Path(args.out), sup.stop_requested), daemon=True
        ).start()
    code = sup.wait(args.duration)
    if sup.failure:
        print(f"droneulator: {sup.failure}", file=sys.stderr)
    return code


def cmd_config(args: argparse.Namespace) -> int:
    from droneulator.config import to_dict

    print(json.dumps(to_dict(_config(args)), indent=2))
    return 0


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="droneulator", description="UAV simulator for agricultural robotics.")
    sub = ap.add_subparsers(dest="command", required=True)

    p = sub.add_parser("scenes", help="list the built-in scenes")
    p.set_defaults(func=cmd_scenes)

    p = sub.add_parser(
        "snapshot", help="save RGB, depth, segmentation and camera info from a scene's spawn pose"
    )
    _add_config_args(p, "default")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--altitude", type=float, default=1.5, help="camera height above the spawn point (m)")
    p.set_defaults(func=cmd_snapshot)

    p = sub.add_parser("demo", help="fly a short in-process demo mission, print telemetry and save frames")
    _add_config_args(p, "default")
    p.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    p.add_argument("--save-every", type=float, default=1.0, help="save one frame set every N sim seconds")
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser(
        "run",
        help="start the dynamics server, render server and ROS 2/Zenoh bridge (API ws://127.0.0.1:8765)",
    )
    _add_config_args(p, "default")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--lockstep", action="store_true", help="sim time waits for every consumer (default)")
    mode.add_argument("--realtime", action="store_true", help="pace sim time by the wall clock")
    p.add_argument("--api-port", type=int, default=None, help="WebSocket API port (default 8765)")
    p.add_argument(
        "--px4",
        action="store_true",
        help="fly from PX4 SITL: listen on TCP 4560 for PX4's simulator MAVLink (see docs/px4.md)",
    )
    p.add_argument(
        "--px4-instance",
        type=int,
        default=None,
        metavar="N",
        help="PX4 instance N: listen on TCP 4560+N (implies --px4)",
    )
    p.add_argument("--duration", type=float, default=None, help="stop after this many wall seconds")
    p.add_argument(
        "--demo",
        action="store_true",
        help="fly a short demo mission through the WebSocket API, print telemetry, save the frames "
        "received over Zenoh to --out, then stop",
    )
    p.add_argument("--out", default="out/run", help="where --demo saves frames (default out/run)")
    p.set_defaults(func=cmd_run)

    p = sub.add_parser("config", help="print the effective configuration as JSON")
    _add_config_args(p)
    p.set_defaults(func=cmd_config)
    return ap


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (ValueError, FileNotFoundError) as exc:
        print(f"droneulator: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
