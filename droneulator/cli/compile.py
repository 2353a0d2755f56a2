"""``droneulator compile``: compile the numba kernels into numba's cache once, ahead of the first run."""

from __future__ import annotations

import argparse
import sys


def add(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "compile",
        help="compile the simulator's kernels ahead of use (scripts/setup.sh runs it)",
        description="Compile the physics, ray-cast, learning-task, planner, spray and dense-stereo kernels "
        "into numba's on-disk cache, so the first run, training or test does not wait for them (a minute "
        "or two of CPU on a fresh install; a later process loads them in about a second). Parts whose "
        "optional extra is not installed are skipped. Editing a kernel's source makes it compile again on "
        "its next use.",
    )
    p.add_argument("--jobs", type=int, default=2, help="parts compiled at once, one process each (default 2)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_compile)


def cmd_compile(args: argparse.Namespace) -> int:
    from droneulator.runtime.spawn import frozen
    from droneulator.warmup import warm

    if frozen():
        print("droneulator: error: `droneulator compile` needs the pip install: the bundle compiles its "
              "kernels on first use", file=sys.stderr)  # fmt: skip
        return 1
    if args.jobs < 1:
        raise ValueError(f"--jobs must be at least 1, got {args.jobs}")
    done = warm(args.jobs, progress=not args.no_progress)
    print("compiled: " + ", ".join(f"{name} {seconds:.0f} s" for name, seconds in done.items()))
    return 0
