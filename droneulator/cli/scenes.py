"""``droneulator scenes``: list the built-in scenes."""

from __future__ import annotations

import argparse


def add(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("scenes", help="list the built-in scenes")
    p.set_defaults(func=cmd_scenes)


def cmd_scenes(args: argparse.Namespace) -> int:
    from droneulator.scenes import list_scenes

    for name, desc in list_scenes().items():
        print(f"{name:18s} {desc}")
    return 0
