"""``droneulator snapshot``: RGB, depth, segmentation and camera info from a scene's spawn pose."""

from __future__ import annotations

import argparse
from pathlib import Path

from droneulator.cli.common import add_config_args, simulation_config


def add(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "snapshot", help="save RGB, depth, segmentation and camera info from a scene's spawn pose"
    )
    add_config_args(p, "default", fleet=True)
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--altitude", type=float, default=1.5, help="camera height above the spawn point (m)")
    p.set_defaults(func=cmd_snapshot)


def cmd_snapshot(args: argparse.Namespace) -> int:
    cfg = simulation_config(args)  # before the heavy imports: a start-up error is reported at once
    from droneulator.workflows.snapshot import snapshot

    written = snapshot(cfg, Path(args.out), altitude=args.altitude)
    for key, path in written.items():
        print(f"{key:28s} {path}")
    return 0
