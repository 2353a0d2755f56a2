"""``droneulator ui``: the browser UI for a simulator that runs elsewhere."""

from __future__ import annotations

import argparse

from droneulator.cli.common import DEFAULT_ZENOH, add_file_args
from droneulator.runtime import preflight
from droneulator.runtime.preflight import StartupError


def add(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "ui",
        help="serve the browser UI for a running simulator (http://127.0.0.1:8080)",
        description="Level select, live camera views, a map with click-to-fly and telemetry in the browser, "
        "for the `droneulator run` whose API is at --url and whose Zenoh router is at --zenoh.",
    )
    p.add_argument("--url", default="ws://127.0.0.1:8765", help="the simulator's WebSocket API")
    p.add_argument("--zenoh", default=DEFAULT_ZENOH, help="Zenoh endpoint of the run's bridge")
    p.add_argument("--namespace", default=None, help="the run's ROS namespace (default droneulator)")
    p.add_argument("--host", default=None, help="address to serve on (default 127.0.0.1: this machine only)")
    p.add_argument("--port", type=int, default=None, help="port to serve on (default 8080)")
    p.add_argument("--px4", action="store_true", help="the run flies with --px4: show PX4's status")
    add_file_args(p, "--set ui.image_hz=5 --set bridge.key_mode=rmw_zenoh")
    p.set_defaults(func=cmd_ui)


def cmd_ui(args: argparse.Namespace) -> int:
    cfg = preflight.load(args.config, args.overrides)
    if args.host is not None:
        cfg.ui.host = args.host
    if args.port is not None:
        cfg.ui.port = args.port
    cfg.ui.__post_init__()
    preflight.prepare_access(cfg, [cfg.ui.host], lambda line: print(line, flush=True))
    from droneulator.ui.server import UIServer, run_ui

    server = UIServer(
        args.url, args.zenoh, cfg.ui, cfg.bridge, namespace=args.namespace, px4=args.px4, access=cfg.access
    )
    try:
        return run_ui(server, lambda line: print(line, flush=True))
    except OSError as exc:
        raise StartupError(
            f"cannot start the UI on {cfg.ui.host}:{cfg.ui.port}: {exc.strerror or exc}"
        ) from None
