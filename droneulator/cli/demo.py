"""``droneulator demo``: a short mission flown by an in-process simulator."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from droneulator.cli.common import add_config_args, simulation_config


def add(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("demo", help="fly a short in-process demo mission, print telemetry and save frames")
    add_config_args(p, "default")
    p.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    p.add_argument("--save-every", type=float, default=1.0, help="save one frame set every N sim seconds")
    p.set_defaults(func=cmd_demo)


def cmd_demo(args: argparse.Namespace) -> int:
    cfg = simulation_config(args)
    from droneulator.workflows.demo import run_demo

    summary = run_demo(cfg, Path(args.out), save_every=args.save_every)
    Path(args.out, "summary.json").write_text(json.dumps(summary, indent=2))
    return 0
