"""``droneulator config``: the effective configuration, as JSON."""

from __future__ import annotations

import argparse
import json

from droneulator.cli.common import add_config_args, config_from_args


def add(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("config", help="print the effective configuration as JSON")
    add_config_args(p, fleet=True)
    p.set_defaults(func=cmd_config)


def cmd_config(args: argparse.Namespace) -> int:
    from droneulator.config import to_dict

    print(json.dumps(to_dict(config_from_args(args)), indent=2))
    return 0
