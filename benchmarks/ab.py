"""Old commit against new: run one benchmark in two checkouts, alternating, and compare every figure.

A refactor must leave the figures unchanged within noise, and this machine is shared and noisy, so the
two versions are measured in turns in the same run (old, new, old, new, ...) and compared by their
medians. The benchmark command is given after ``--`` with ``{json}`` where its JSON output path goes; it
runs in each checkout's folder with that checkout first on ``PYTHONPATH``. Every number in the JSON
outputs (nested keys joined with ``.``) is compared: old and new medians and their ratio.

    git worktree add /tmp/old 68f4b51
    python benchmarks/ab.py --old /tmp/old --rounds 3 -- python benchmarks/world.py --sizes 1 8 \\
        --seconds 2 --output {json}

Writes ``benchmarks/results/ab.json`` (``--out``): the command, both commits, every round's figures
and the comparison.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]


def flatten(value: Any, prefix: str = "") -> dict[str, float]:
    """Every number in a JSON value, keyed by its path (``a.b.0.c``); booleans are not figures."""
    out: dict[str, float] = {}
    if isinstance(value, dict):
        for k, v in value.items():
            out |= flatten(v, f"{prefix}{k}.")
    elif isinstance(value, list):
        for i, v in enumerate(value):
            out |= flatten(v, f"{prefix}{i}.")
    elif isinstance(value, (int, float)) and not isinstance(value, bool):
        out[prefix.rstrip(".")] = float(value)
    return out


def commit_of(checkout: Path) -> str:
    r = subprocess.run(
        ["git", "-C", str(checkout), "rev-parse", "--short", "HEAD"], capture_output=True, text=True
    )
    return r.stdout.strip() or "?"


def run_once(checkout: Path, command: list[str]) -> dict[str, float]:
    """The benchmark's figures from one run in ``checkout``."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "out.json"
        cmd = [part.replace("{json}", str(path)) for part in command]
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(checkout), os.environ.get("PYTHONPATH", "")])}
        r = subprocess.run(cmd, cwd=checkout, env=env, capture_output=True, text=True)
        if r.returncode != 0 or not path.exists():
            tail = (r.stderr or r.stdout).strip().splitlines()[-5:]
            raise SystemExit(
                f"ab: the benchmark failed in {checkout} (exit {r.returncode}):\n" + "\n".join(tail)
            )
        return flatten(json.loads(path.read_text()))


def compare(old: list[dict[str, float]], new: list[dict[str, float]]) -> dict[str, dict[str, float]]:
    """Per figure present in every run: the old and new medians and new / old."""
    keys = set.intersection(*(set(r) for r in old + new))
    out = {}
    for key in sorted(keys):
        a = statistics.median(r[key] for r in old)
        b = statistics.median(r[key] for r in new)
        out[key] = {"old": a, "new": b, "ratio": b / a if a else float("nan")}
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--old", type=Path, required=True, help="checkout of the old commit (a git worktree)")
    ap.add_argument("--new", type=Path, default=ROOT, help="checkout of the new commit (default: this one)")
    ap.add_argument("--rounds", type=int, default=3, help="runs of each version, alternating (default 3)")
    ap.add_argument("--match", default="", help="show only figures whose key contains this text")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks/results/ab.json", help="JSON output path")
    ap.add_argument("command", nargs=argparse.REMAINDER, help="-- the benchmark command, with {json}")
    args = ap.parse_args(argv)
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command or not any("{json}" in part for part in command):
        ap.error("give the benchmark command after --, with {json} where its JSON output path goes")
    if args.rounds < 1:
        ap.error("--rounds must be at least 1")
    for checkout in (args.old, args.new):
        if not (checkout / "droneulator").is_dir():
            ap.error(f"{checkout} is not a Droneulator checkout")
    runs: dict[str, list[dict[str, float]]] = {"old": [], "new": []}
    for k in range(args.rounds):
        for side, checkout in (("old", args.old), ("new", args.new)):
            print(f"round {k + 1}/{args.rounds}: {side} ({commit_of(checkout)})", file=sys.stderr, flush=True)
            runs[side].append(run_once(checkout.resolve(), command))
    table = compare(runs["old"], runs["new"])
    print(f"{'figure':60s} {'old':>12s} {'new':>12s} {'new/old':>8s}")
    for key, row in table.items():
        if args.match in key:
            print(f"{key[:60]:60s} {row['old']:12.4g} {row['new']:12.4g} {row['ratio']:8.3f}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    report = {
        "command": command,
        "old": {"path": str(args.old), "commit": commit_of(args.old)},
        "new": {"path": str(args.new), "commit": commit_of(args.new)},
        "rounds": args.rounds,
        "runs": runs,
        "comparison": table,
    }
    args.out.write_text(json.dumps(report, indent=2))
    print(f"wrote {args.out}", file=sys.stderr)


if __name__ == "__main__":
    main()
