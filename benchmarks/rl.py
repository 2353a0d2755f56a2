"""Workflow 3 (RL in the vineyard): environment throughput, SAC training wall time, evaluation.

1. Environment steps per second of ``droneulator/VineyardNav-v0`` with random actions (resets
   included), single and vectorised (SubprocVecEnv, N = 2), and the real-time factor: simulated
   seconds per wall second (one step is one 30 Hz camera frame). The paper's environment runs
   locked to real time, i.e. a factor of 1.
2. SAC learner cost per gradient step with 1 and 2 torch threads (training uses 1 by default).
3. Wall time of a SAC training run (default 50,000 steps, the paper's budget: 28 min at 30 Hz real
   time); with ``--train-steps`` below 50,000 the 50k time is also projected from the measured rate.
4. Success rate of the trained policy on 10 held-out seeds (``droneulator evaluate``), with figures.

Reproduce: ``python benchmarks/rl.py --out out/rl-bench`` (``--model PATH`` evaluates an existing model
and skips training).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import numpy as np
from _common import write

PAPER_STEPS = 50_000
EPISODE_KEYS = ("seed", "termination", "sim_time_s", "shortest_path_m", "flown_m", "min_clearance_m")
CAMERA_HZ = 30.0


def env_throughput(n_envs: int, steps: int, vec: str) -> dict[str, Any]:
    """Transitions per second with random actions through an SB3 VecEnv (auto-reset included)."""
    from droneulator.config import load_config
    from droneulator.workflows.rl.train import make_vec_env

    venv = make_vec_env(load_config(), n_envs, vec)
    try:
        venv.seed(0)
        venv.reset()
        rng = np.random.default_rng(0)
        for _ in range(20):  # warm-up: numba, shaders
            venv.step(rng.uniform(-1, 1, (n_envs, 2)).astype(np.float32))
        calls = max(1, steps // n_envs)
        t0 = time.perf_counter()
        for _ in range(calls):
            venv.step(rng.uniform(-1, 1, (n_envs, 2)).astype(np.float32))
        wall = time.perf_counter() - t0
    finally:
        venv.close()
    rate = calls * n_envs / wall
    return {
        "n_envs": n_envs,
        "vec": vec,
        "steps": calls * n_envs,
        "wall_s": wall,
        "steps_per_s": rate,
        "real_time_factor": rate / CAMERA_HZ,
    }


def learner_cost(threads: int, updates: int = 200) -> float:
    """Milliseconds per SAC gradient step (batch 256, the training network) with ``threads`` threads."""
    import gymnasium as gym
    import torch
    from stable_baselines3 import SAC

    from droneulator.workflows.rl.train import SAC_HYPERPARAMETERS

    class Dummy(gym.Env):
        observation_space = gym.spaces.Box(-1, 1, (35,), np.float32)
        action_space = gym.spaces.Box(-1, 1, (2,), np.float32)

        def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
            return np.zeros(35, np.float32), {}

        def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
            return self.observation_space.sample(), 0.0, False, False, {}

    torch.set_num_threads(threads)
    hyper = {**SAC_HYPERPARAMETERS, "learning_starts": 0, "train_freq": 1, "gradient_steps": 1}
    model = SAC("MlpPolicy", Dummy(), device="cpu", verbose=0, **hyper)
    model.learn(300)
    t0 = time.perf_counter()
    model.train(gradient_steps=updates, batch_size=hyper["batch_size"])
    return (time.perf_counter() - t0) / updates * 1e3


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="out/rl-bench", help="training run folder (default out/rl-bench)")
    ap.add_argument("--env-steps", type=int, default=3000, help="steps per throughput measurement")
    ap.add_argument("--train-steps", type=int, default=PAPER_STEPS, help="SAC training steps (default 50000)")
    ap.add_argument("--envs", type=int, default=1, help="environments for the training run (default 1)")
    ap.add_argument("--seed", type=int, default=0, help="training seed")
    ap.add_argument("--episodes", type=int, default=10, help="evaluation episodes (default 10)")
    ap.add_argument("--model", default=None, help="evaluate this model instead of training one")
    ap.add_argument("--json", default=None, help="output path (default benchmarks/results/rl.json)")
    args = ap.parse_args()

    res: dict[str, Any] = {"throughput": []}
    for n, vec in ((1, "dummy"), (2, "subproc"), (2, "dummy")):
        r = env_throughput(n, args.env_steps, vec)
        res["throughput"].append(r)
        print(
            f"env x{n} ({vec:7s}): {r['steps_per_s']:7.1f} steps/s, real-time factor "
            f"{r['real_time_factor']:5.1f} ({r['steps']} steps in {r['wall_s']:.1f} s)"
        )
    res["learner_ms_per_update"] = {str(t): learner_cost(t) for t in (1, 2)}
    costs = res["learner_ms_per_update"]
    print("SAC gradient step:", ", ".join(f"{v:.1f} ms ({t} thread(s))" for t, v in costs.items()))

    out = Path(args.out)
    if args.model is None:
        from droneulator.workflows.rl.train import train

        summary = train(None, out, steps=args.train_steps, seed=args.seed, n_envs=args.envs, progress=False)
        projected = summary["wall_s"] * PAPER_STEPS / summary["steps"]
        res["training"] = {
            **{k: summary[k] for k in ("steps", "wall_s", "steps_per_s", "n_envs", "vec", "torch_threads")},
            "projected_50k_wall_s": projected,
            "paper_50k_wall_s": PAPER_STEPS / CAMERA_HZ,
            "speedup_vs_paper": PAPER_STEPS / CAMERA_HZ / projected,
            "command": f"droneulator train --algo sac --steps {args.train_steps} --seed {args.seed} "
            f"--envs {args.envs} --out {out}",
        }
        t = res["training"]
        print(
            f"SAC {t['steps']} steps: {t['wall_s'] / 60:.1f} min wall ({t['steps_per_s']:.1f} steps/s); "
            f"50k projected {projected / 60:.1f} min vs {PAPER_STEPS / CAMERA_HZ / 60:.1f} min real time"
        )
        model = out / "model.zip"
    else:
        model = Path(args.model)

    from droneulator.workflows.rl.evaluate import evaluate

    ev = evaluate(model, episodes=args.episodes)
    res["evaluation"] = {k: v for k, v in ev.items() if k != "per_episode"}
    res["evaluation"]["per_episode"] = [{k: e[k] for k in EPISODE_KEYS} for e in ev["per_episode"]]
    print(
        f"evaluation: {ev['successes']}/{ev['episodes']} successful on held-out seeds {ev['seeds'][0]}.."
        f"{ev['seeds'][-1]}; figures in {model.parent}"
    )
    write("rl", res, args.json)


if __name__ == "__main__":
    main()
