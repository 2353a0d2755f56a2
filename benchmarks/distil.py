"""A ctbr policy by distillation: wall time to 45/50 held-out check episodes and the 50 evaluation episodes.

For each seed: ``droneulator train --algo distil --set rl.action=ctbr --num-envs B --stop-at 0.9`` (DAgger
from the scripted path follower flown through the CTBR tracker, :mod:`droneulator.workflows.rl.distil`),
its held-out checks (50 episodes from seed 2,500,000) every ``--check-every`` steps; then the student,
and the expert it imitates, on the 50 evaluation episodes (seeds from 1,000,000, never trained on nor used
to stop), both on the batched env (depth by ray casting, as the checks). ``--algos distil sac`` adds the
velocity level's SAC (``droneulator train --num-envs 16 --stop-at 0.9``, capped at ``--cap`` s of training)
trained and evaluated the same way, beside it. The pipeline's wall time counts everything from the start
of training to the saved model, the checks included; the training time leaves the checks out, as
``train`` reports it.

Reproduce: ``python benchmarks/distil.py`` (about 11 min per seed on this 2-core CPU under load).
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path
from typing import Any

from _common import write


def _ctbr_config() -> Any:
    from droneulator.config import load_config
    from droneulator.workflows.rl.env import env_config

    cfg = load_config(None)
    cfg.rl.action = "ctbr"
    return env_config(cfg)


def expert_successes(seeds: list[int]) -> int:
    """Episodes of the distillation's expert reaching the goal, one per seed, on the batched env."""
    from droneulator.workflows.rl.distil import expert_successes as flown

    return flown(_ctbr_config(), seeds)


def run(out: Path, algo: str, seed: int, envs: int, every: int, cap_s: float | None) -> dict[str, Any]:
    """Train ``algo`` (distil at ctbr, or SAC at velocity) to 45/50 checks, then the evaluation episodes."""
    from stable_baselines3 import PPO, SAC

    from droneulator.workflows.rl.env import env_config
    from droneulator.workflows.rl.heldout import EVAL_EPISODES, EVAL_SEED, interval_record
    from droneulator.workflows.rl.train import held_out_env, held_out_successes, train

    cfg = _ctbr_config() if algo == "distil" else env_config()
    t0 = time.perf_counter()
    summary = train(cfg, out, steps=50_000_000 if algo == "sac" else 1_000_000, seed=seed, n_envs=envs,
                    algo=algo, vec="native", progress=False, stop_at=0.9, check_every=every,
                    max_wall_s=cap_s)  # fmt: skip
    pipeline_s = time.perf_counter() - t0
    if algo == "distil":
        policy = PPO.load(out / "model.zip", device="cpu")
    else:
        policy = SAC.load(out / "model.zip", device="cpu", custom_objects={"replay_buffer_class": None})
    seeds = list(range(EVAL_SEED, EVAL_SEED + EVAL_EPISODES))
    env = held_out_env(cfg, len(seeds), "raycast")
    try:
        successes = held_out_successes(policy, env, seeds)
    finally:
        env.close()
    reached = summary["reached"]
    level = "ctbr" if algo == "distil" else "velocity"
    return {
        "algo": algo,
        "level": level,
        "seed": seed,
        "envs": envs,
        "reached_target": reached is not None,
        "train_wall_s_to_target": reached["wall_s"] if reached else None,
        "steps_to_target": reached["steps"] if reached else None,
        "train_wall_s": summary["wall_s"],
        "checks_wall_s": summary["checks_wall_s"],
        "pipeline_wall_s": pipeline_s,
        "steps": summary["steps"],
        "checks": summary["checks"],
        "evaluation_seeds": [seeds[0], seeds[-1]],
        "evaluation": interval_record(successes, len(seeds)),
        "command": f"droneulator train --algo {algo} --set rl.action={level} --num-envs {envs} --seed {seed} "
        f"--stop-at 0.9 --check-every {every} --out {out}",
    }


def main() -> None:
    from droneulator.workflows.rl.heldout import EVAL_EPISODES, EVAL_SEED, interval_record, rate_text

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0], help="training seeds (default 0)")
    ap.add_argument("--envs", type=int, default=128, help="batched worlds of the distillation (default 128)")
    ap.add_argument("--check-every", type=int, default=50_000, help="distillation steps between checks")
    ap.add_argument("--algos", nargs="+", choices=("distil", "sac"), default=["distil"],
                    help="distil (ctbr) and/or sac (velocity level, B = 16) (default distil)")  # fmt: skip
    ap.add_argument("--cap", type=float, default=600.0, help="SAC's training time cap per seed (s)")
    ap.add_argument("--out", default="out/distil-bench", help="training runs folder")
    ap.add_argument("--json", default=None, help="output path (default benchmarks/results/distil.json)")
    args = ap.parse_args()
    load_start = os.getloadavg()
    seeds = list(range(EVAL_SEED, EVAL_SEED + EVAL_EPISODES))
    t = time.perf_counter()
    k = expert_successes(seeds)
    expert = {**interval_record(k, len(seeds)), "wall_s": time.perf_counter() - t}
    print(f"expert (path follower through the CTBR tracker): {rate_text(k, len(seeds))}", flush=True)
    runs = []
    for seed in args.seeds:
        jobs = {"distil": (args.envs, args.check_every, None), "sac": (16, 10_000, args.cap)}
        for algo in args.algos:
            envs, every, cap = jobs[algo]
            r = run(Path(args.out) / f"{algo}{seed}", algo, seed, envs, every, cap)
            runs.append(r)
            when = "45/50 checks not reached"
            if r["reached_target"]:
                when = f"45/50 checks after {r['steps_to_target']} steps, {r['train_wall_s_to_target']:.0f} s"
            ev = r["evaluation"]
            rate = rate_text(ev["successes"], ev["episodes"])
            print(f"{algo} ({r['level']}), seed {seed}: {when} ({r['pipeline_wall_s']:.0f} s with the "
                  f"checks); evaluation {rate}", flush=True)  # fmt: skip
    load = {"start": load_start, "end": os.getloadavg()}  # 1, 5 and 15 min: the machine may be shared
    write("distil", {"expert": expert, "runs": runs, "load_average": load, "settings": vars(args)}, args.json)


if __name__ == "__main__":
    main()
