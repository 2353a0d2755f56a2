"""The ``droneulator`` command line: one module per subcommand, each with ``add(sub)``, which adds its
parser, and its ``cmd_*`` function; what several share is in :mod:`droneulator.cli.common`.

A start-up failure the user can cause (a bad ``--config`` file or ``--set`` value, an unknown scene, a
port in use, no EGL) ends in one ``droneulator: error: ...`` line on stderr before any simulator
process starts: exit status 2 for usage and configuration errors, 1 otherwise (see
:mod:`droneulator.runtime.preflight`).
"""

from __future__ import annotations

import argparse
import sys

from droneulator.cli import (
    capture,
    compile,
    config,
    demo,
    evaluate,
    plan,
    reconstruct,
    record,
    replay,
    run,
    scenes,
    score,
    snapshot,
    spray,
    sweep,
    train,
    ui,
)
from droneulator.cli.common import PIP_ONLY
from droneulator.runtime.cluster import ClusterError
from droneulator.runtime.preflight import StartupError
from droneulator.runtime.spawn import CHILD_COMMAND, frozen, run_child

#: the subcommands, in the order ``droneulator --help`` lists them
COMMANDS = (
    scenes, snapshot, demo, run, ui, record, replay,
    capture, reconstruct, score, sweep, train, evaluate, plan, spray, config, compile,
)  # fmt: skip


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="droneulator", description="UAV simulator for agricultural robotics.")
    sub = ap.add_subparsers(dest="command", required=True)
    for command in COMMANDS:
        command.add(sub)
    return ap


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == [CHILD_COMMAND]:  # hidden: how the bundle starts its child processes
        return run_child(argv[1:])
    args = build_parser().parse_args(argv)
    if frozen() and args.command in PIP_ONLY:
        print(
            f"droneulator: error: `droneulator {args.command}` is not in this bundle: it needs the pip "
            f"install (pip install 'droneulator[{PIP_ONLY[args.command]}]', or bash scripts/setup.sh --dev)",
            file=sys.stderr,
        )
        return 1
    try:
        return args.func(args)
    except StartupError as exc:
        print(f"droneulator: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except (ValueError, FileNotFoundError, FileExistsError) as exc:
        print(f"droneulator: error: {exc}", file=sys.stderr)
        return 2
    except ClusterError as exc:
        print(f"droneulator: error: {exc}", file=sys.stderr)
        return 1
