"""``droneulator train``: SAC on the vineyard navigation environment (needs the rl extra)."""

from __future__ import annotations

import argparse
from pathlib import Path

from droneulator.cli.common import add_rl_config_args
from droneulator.runtime import preflight


def add(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "train",
        help="train SAC on droneulator/VineyardNav-v0 with Stable-Baselines3 (pip install droneulator[rl])",
        description="Train SAC on the vineyard navigation environment. Writes the final model, checkpoints, "
        "monitor.csv, progress.csv, TensorBoard logs (tb/), config.json and train_summary.json to --out.",
    )
    p.add_argument("--algo", choices=("sac",), default="sac", help="algorithm (default sac)")
    p.add_argument("--steps", type=int, default=50_000, help="environment steps (default 50000)")
    p.add_argument(
        "--seed", type=int, default=0, help="training seed: env i starts from seed + i (default 0)"
    )
    p.add_argument("--envs", type=int, default=1, help="parallel environments (default 1)")
    p.add_argument(
        "--vec",
        choices=("auto", "dummy", "subproc"),
        default="auto",
        help="vectorisation: subprocesses when --envs > 1 (auto, default), or all in this process (dummy)",
    )
    p.add_argument("--out", default="out/rl", help="run folder (default out/rl)")
    p.add_argument("--learning-starts", type=int, default=None, help="random warm-up steps (default 2000)")
    p.add_argument("--checkpoint-every", type=int, default=10_000, help="checkpoint period in steps")
    p.add_argument("--threads", type=int, default=None, help="torch threads for the learner (default 1)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_rl_config_args(p)
    p.set_defaults(func=cmd_train)


def cmd_train(args: argparse.Namespace) -> int:
    from droneulator.workflows.rl.train import train

    cfg = preflight.load(args.config, args.overrides, seed=args.scene_seed)
    overrides = {} if args.learning_starts is None else {"learning_starts": args.learning_starts}
    summary = train(
        cfg,
        Path(args.out),
        steps=args.steps,
        seed=args.seed,
        n_envs=args.envs,
        algo=args.algo,
        vec=args.vec,
        checkpoint_every=args.checkpoint_every,
        threads=args.threads,
        progress=not args.no_progress,
        overrides=overrides,
    )
    print(
        f"trained {summary['steps']} steps in {summary['wall_s']:.0f} s "
        f"({summary['steps_per_s']:.1f} steps/s, {summary['n_envs']} env(s)); model: {summary['model']}"
    )
    return 0
