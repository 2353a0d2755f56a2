"""``droneulator evaluate``: a trained policy rolled out on held-out seeds (needs the rl extra)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from droneulator.cli.common import add_rl_config_args
from droneulator.runtime import preflight
from droneulator.workflows.rl.heldout import EVAL_EPISODES, EVAL_SEED


def add(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "evaluate",
        help="evaluate a trained policy on held-out seeds; writes evaluation.json and the paper's figures",
        description="Roll the policy out (deterministic actions) on seeds used neither in training nor by "
        "its stop check (both read from train_summary.json; an overlap is refused) and write "
        "evaluation.json (the success rate with its 95 % Wilson interval), trajectories.png and "
        "training_curves.png (from the run's monitor.csv). A team policy (train --agents N) flies one world "
        "of N agents per seed; a success is every agent at its goal without touching anything.",
    )
    p.add_argument("model", help="model .zip written by `droneulator train`, or its run folder")
    p.add_argument(
        "--episodes",
        type=int,
        default=EVAL_EPISODES,
        help=f"episodes (default {EVAL_EPISODES}; a rate on fewer says little: 9/10 is 60-98 %% at 95 %%)",
    )
    p.add_argument("--seed", type=int, default=EVAL_SEED, help=f"first evaluation seed (default {EVAL_SEED})")
    p.add_argument("--out", default=None, help="output folder (default: the model's folder)")
    p.add_argument("--logs", default=None, help="training run folder for the curves (default: the model's)")
    p.add_argument("--stochastic", action="store_true", help="sample actions instead of the policy mean")
    p.add_argument("--url", default=None, help="evaluate against a running `droneulator run` at this URL")
    p.add_argument("--zenoh", default=None, help="with --url: Zenoh endpoint of its bridge")
    add_rl_config_args(p)
    p.set_defaults(func=cmd_evaluate)


def cmd_evaluate(args: argparse.Namespace) -> int:
    from droneulator.workflows.rl.evaluate import evaluate, load_run_config, resolve_model
    from droneulator.workflows.rl.heldout import rate_text

    if args.episodes < 1:
        raise ValueError(f"--episodes must be at least 1, got {args.episodes}")
    model = resolve_model(args.model)
    cfg = load_run_config(model)
    if args.config or args.overrides or args.scene_seed is not None:
        base = model.parent / "config.json"
        cfg = preflight.load(
            args.config or (base if base.exists() else None), args.overrides, seed=args.scene_seed
        )
    summary = evaluate(
        model,
        episodes=args.episodes,
        seed=args.seed,
        out=Path(args.out) if args.out else None,
        cfg=cfg,
        logs=Path(args.logs) if args.logs else None,
        mode="remote" if args.url else "local",
        url=args.url,
        zenoh=args.zenoh,
        deterministic=not args.stochastic,
    )
    for i, e in enumerate(summary["per_episode"]):
        head = f"episode {i} (seed {e['seed']}):"
        if "agents" not in e:
            print(f"{head} {_flight(e)}")
            continue
        print(f"{head} {'every agent at its goal' if e['success'] else 'failed'}")
        for k, a in enumerate(e["agents"]):
            print(f"  agent {k}: {_flight(a)}")
    where = Path(summary["figures"]["trajectories"]).parent
    if summary["warning"]:
        print(f"note: {summary['warning']}")
    rate = rate_text(summary["successes"], summary["episodes"])
    seeds = f"seeds {summary['seeds'][0]}-{summary['seeds'][-1]}"
    print(f"success rate {rate} ({seeds}); evaluation.json and figures: {where}")
    return 0


def _flight(e: dict[str, Any]) -> str:
    """One agent's episode on a line: how it ended, its time, return and path against the shortest."""
    touched = f" (touched {e['collided_with']})" if e.get("collided_with") else ""
    return (
        f"{e['termination']:13s} {e['sim_time_s']:6.1f} s return {e['return']:7.1f}  "
        f"path {e['shortest_path_m']:5.1f} m  flown {e['flown_m']:5.1f} m{touched}"
    )
