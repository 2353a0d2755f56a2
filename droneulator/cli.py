"""The ``droneulator`` command line."""

from __future__ import annotations

import argparse
import json
import sys
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
