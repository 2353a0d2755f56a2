"""``droneulator sweep``: many captures or planning benchmarks over scenes and seeds, on Ray or here."""

from __future__ import annotations

import argparse
import signal
import sys
from pathlib import Path

from droneulator.cli.common import add_file_args, add_ray_arg


def add(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "sweep",
        help="run captures (and reconstructions) or planning benchmarks over scenes and seeds, on Ray",
        description="One job per scene x seed (x view count): each writes <out>/<scene>-seed<N>[-views<V>]/ "
        "with its config.json, its workflow's output and job.json; summary.csv and summary.json list them "
        "all. A rerun skips the jobs already done, so an interrupted sweep resumes. With --ray the jobs "
        "are Ray tasks over the cluster (their files come back to this machine); without, they run here "
        "one after another. See docs/cluster.md.",
    )
    p.add_argument(
        "kind",
        choices=("capture", "plan"),
        help="capture: `droneulator capture` (and --reconstruct); plan: the planning benchmark "
        "(benchmarks/planning.py, in a source checkout)",
    )
    p.add_argument(
        "--scenes", nargs="+", default=None, help="scenes (default tree_inspection; plan: planning)"
    )
    p.add_argument("--seeds", nargs="+", default=["0"], help="seeds: N or A-B, e.g. 0-99 (default 0)")
    p.add_argument(
        "--views",
        type=int,
        nargs="+",
        default=None,
        help="capture: view counts, e.g. 18 36 (default: the config's capture.views, 18)",
    )
    p.add_argument("--reconstruct", action="store_true", help="capture: reconstruct each dataset with COLMAP")
    p.add_argument("--goals", type=int, nargs="+", default=None, help="plan: only these goals (1-5)")
    p.add_argument("--out", required=True, help="sweep folder")
    add_ray_arg(p, "run the jobs on Ray")
    p.add_argument(
        "--cpus-per-job", type=float, default=2.0, help="CPU cores Ray reserves per job (default 2)"
    )
    p.add_argument(
        "--gpus-per-job",
        type=float,
        default=None,
        help="GPUs Ray reserves per job (default: none without GPUs, else a share so every job gets one)",
    )
    p.add_argument(
        "--zenoh-router",
        metavar="tls/HOST:PORT",
        default=None,
        help="capture: link every job's simulator to this TLS router (the one with the simulator's ACL, "
        "docs/security.md) with mutual TLS on bridge.tls_ca, tls_cert and tls_key, files read here and "
        "carried to each job's node (docs/cluster.md)",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_file_args(p, "--set capture.width=320 --set capture.height=240")
    p.set_defaults(func=cmd_sweep)


def cmd_sweep(args: argparse.Namespace) -> int:
    from droneulator.runtime import preflight
    from droneulator.runtime.cluster import check_address
    from droneulator.runtime.zenoh_security import RouterLink
    from droneulator.workflows.sweep import SweepSettings, make_jobs, parse_seeds, sweep, write_summary

    if args.ray is not None:
        check_address(args.ray)
    if args.cpus_per_job <= 0 or (args.gpus_per_job is not None and args.gpus_per_job < 0):
        raise ValueError("--cpus-per-job must be positive and --gpus-per-job not negative")
    if args.kind == "plan" and args.reconstruct:
        raise ValueError("--reconstruct goes with sweep capture")
    if args.kind == "capture" and args.goals:
        raise ValueError("--goals goes with sweep plan")
    if args.kind == "plan" and args.zenoh_router:
        raise ValueError("--zenoh-router goes with sweep capture (the planning benchmark runs no bridge)")
    scenes = args.scenes or (["tree_inspection"] if args.kind == "capture" else ["planning"])
    router = None
    if args.kind == "capture":
        cfg = preflight.load(args.config, args.overrides)
        views = args.views or [cfg.capture.views]
        if args.zenoh_router is not None:  # before any Ray work: the endpoint and the files, read here
            router = RouterLink.load(args.zenoh_router, cfg.bridge)
    else:
        views = args.views or []
    jobs = make_jobs(args.kind, scenes, parse_seeds(args.seeds), views)
    settings = SweepSettings(args.config, args.overrides, args.reconstruct, args.goals, router)
    out = Path(args.out)
    # Ctrl-C (SIGINT) stops the sweep as described even when it was started in the background, where
    # the shell leaves SIGINT ignored (the simulator's commands install their handlers the same way)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        rows = sweep(
            jobs,
            settings,
            out,
            address=args.ray,
            cpus=args.cpus_per_job,
            gpus=args.gpus_per_job,
            progress=not args.no_progress,
            log=lambda line: print(line, file=sys.stderr),
        )
    except KeyboardInterrupt:
        print(
            f"interrupted: finished jobs are in {out}; run the same command again to resume", file=sys.stderr
        )
        return 130
    print(write_summary(out, rows))
    failed = sum(r.get("status") == "failed" for r in rows)
    return 1 if failed else 0
