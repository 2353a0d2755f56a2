"""Workflow 3 (RL in the vineyard): batched environment throughput, wall time to a good policy, memory.

1. Environment steps per second with random actions (autoresets included) of today's single env
   (``VineyardNavEnv``, one in-process ``World`` and one OpenGL renderer) and of the native vector env
   (``gym.make_vec("droneulator/VineyardNav-v0", num_envs=B)``, B batched worlds, depth by ray casting)
   for B = 1, 16, 64, 256, 1024, each in its own process, with the memory each env adds (the process's
   resident memory before and after making and resetting it, over B, once a one-env copy has loaded
   everything shared) and the share of time spent in resets.
2. Wall time to a policy that reaches the goal in >= 45 of 50 held-out check episodes (``droneulator
   train --num-envs B --stop-at 0.9``: SAC on the batched env, the 50 check episodes from seed 2,500,000
   flown at once every ``--check-every`` steps, the checks' time left out), for 3 training seeds; each
   final policy's success on the 50 evaluation episodes (seeds 1,000,000 to 1,000,049, as ``droneulator
   evaluate``: none of them was used to decide when to stop), every rate with its 95 % Wilson interval.
   Before 2026-11-29 the check flew 10 episodes (seeds 1,000,000 to 1,000,009, stopping at 9 of 10) and
   the final policy 50 from 1,000,100.
3. The same with PPO on the batched env at B = 256 (one seed, capped), to say which algorithm fits.
4. ``--baseline-training``: today's SAC on one single env for 50k steps (about 10 min), the paper's
   budget, for the wall-time comparison in the same run.

Reproduce: ``python benchmarks/rl.py`` (about 25 min on 2 cores; ``--quick`` for a smoke run).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from _common import write

PAPER_STEPS = 50_000
CAMERA_HZ = 30.0
#: each env of a throughput figure steps at least this long (10 s of flight), so resets are in it
MIN_STEPS_PER_ENV = 300


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


def rss_bytes() -> int:
    """This process's resident memory (Linux)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    return 0


def batched_throughput(n_envs: int, steps: int, depth: str = "raycast") -> dict[str, Any]:
    """Steps per second of the vector env at ``n_envs`` with random actions, the memory per env, and the
    share of time in resets (task sampling: the goal's distance field) (run in a fresh process); its
    depth from ``depth`` (``"raycast"``, or ``"render"``: the OpenGL renderer)."""
    import gymnasium as gym

    import droneulator.workflows.rl as rl

    warm = gym.make_vec(rl.ENV_ID, num_envs=1)  # imports, compiled code, the scene and its grid
    warm.reset(seed=0)
    base = rss_bytes()
    venv = gym.make_vec(rl.ENV_ID, num_envs=n_envs, depth=depth)
    venv.reset(seed=0)
    per_env = (rss_bytes() - base) / n_envs
    warm.close()
    rng = np.random.default_rng(0)
    for _ in range(5):  # warm-up: numba, the BVH
        venv.step(rng.uniform(-1, 1, (n_envs, 2)).astype(np.float32))
    reset_s = 0.0
    original = venv._reset_envs

    def timed(*a: Any, **k: Any) -> Any:
        nonlocal reset_s
        t = time.perf_counter()
        out = original(*a, **k)
        reset_s += time.perf_counter() - t
        return out

    venv._reset_envs = timed
    calls = max(MIN_STEPS_PER_ENV, steps // n_envs)  # every env long enough to end episodes
    episodes = 0
    t0 = time.perf_counter()
    for _ in range(calls):
        _, _, term, trunc, _ = venv.step(rng.uniform(-1, 1, (n_envs, 2)).astype(np.float32))
        episodes += int((term | trunc).sum())
    wall = time.perf_counter() - t0
    venv.close()
    return {
        "n_envs": n_envs,
        "depth": depth,
        "steps": calls * n_envs,
        "wall_s": wall,
        "steps_per_s": calls * n_envs / wall,
        "real_time_factor": calls * n_envs / wall / CAMERA_HZ,
        "episodes_ended": episodes,
        "reset_share": reset_s / wall,
        "rss_per_env_bytes": per_env,
    }


#: the train command's flag for each SAC demonstration setting
FLAGS = {
    "demonstrations": "demonstrations",
    "demonstration_bc_steps": "bc-steps",
    "demonstration_anchor": "anchor",
}


def in_subprocess(fn: str, *args: Any) -> dict[str, Any]:
    """``fn(*args)`` of this script in a fresh Python process (clean memory figures, no shared caches)."""
    code = f"import json, sys; sys.path.insert(0, {str(Path(__file__).parent)!r}); import rl; "
    code += f"print(json.dumps(rl.{fn}(*{args!r})))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def train_to_target(
    out: Path,
    seed: int,
    algo: str,
    n_envs: int,
    every: int,
    cap_s: float,
    demo: dict[str, float] | None = None,
) -> dict[str, Any]:
    """Train until 45 of the 50 check episodes succeed (or ``cap_s`` s), then the policy on the 50
    evaluation episodes (seeds apart from the check's); ``demo``: SAC's demonstration settings."""
    from droneulator.workflows.rl.heldout import EVAL_EPISODES, EVAL_SEED, interval_record
    from droneulator.workflows.rl.train import held_out_successes, train
    from droneulator.workflows.rl.vector import VineyardNavVectorEnv

    summary = train(None, out, steps=50_000_000, seed=seed, n_envs=n_envs, algo=algo, vec="native",
                    progress=False, stop_at=0.9, check_every=every, max_wall_s=cap_s,
                    overrides=demo or None)  # fmt: skip
    from stable_baselines3 import PPO, SAC

    # SB3 lets SAC choose its replay buffer again (evaluation never samples it) instead of warning that
    # the saved n-step buffer class overrides n_steps
    if algo == "ppo":
        policy = PPO.load(out / "model.zip", device="cpu")
    else:
        policy = SAC.load(out / "model.zip", device="cpu", custom_objects={"replay_buffer_class": None})
    seeds = list(range(EVAL_SEED, EVAL_SEED + EVAL_EPISODES))
    assert not set(seeds) & set(summary["check_seeds"])
    env = VineyardNavVectorEnv(len(seeds))
    try:
        successes = held_out_successes(policy, env, seeds)
    finally:
        env.close()
    reached = summary["reached"]
    return {
        "algo": algo,
        "seed": seed,
        "n_envs": n_envs,
        "check_episodes": summary["check_episodes"],
        "check_seeds": [summary["check_seeds"][0], summary["check_seeds"][-1]],
        "reached_target": reached is not None,
        "wall_s_to_target": reached["wall_s"] if reached else None,
        "steps_to_target": reached["steps"] if reached else None,
        "reached": reached,
        "train_wall_s": summary["wall_s"],
        "steps": summary["steps"],
        "steps_per_s": summary["steps_per_s"],
        "checks": summary["checks"],
        "evaluation_seeds": [seeds[0], seeds[-1]],
        "evaluation": interval_record(successes, len(seeds)),
        "hyperparameters": summary["hyperparameters"],
        "command": f"droneulator train --num-envs {n_envs} --algo {algo} --seed {seed} --stop-at 0.9 "
        f"--check-every {every} --out {out}" + "".join(f" --{FLAGS[k]} {v}" for k, v in (demo or {}).items()),
    }


def _reached(r: dict[str, Any], cap_s: float) -> str:
    """When the check first passed 45 of 50, or that it never did within the cap."""
    if r["wall_s_to_target"] is None:
        return f"45/50 checks not reached within the {cap_s:.0f} s cap"
    return f"45/50 checks after {r['wall_s_to_target']:.0f} s ({r['steps_to_target']} steps)"


def _rate(r: dict[str, Any]) -> str:
    from droneulator.workflows.rl.heldout import rate_text

    return rate_text(r["evaluation"]["successes"], r["evaluation"]["episodes"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="out/rl-bench", help="training runs folder (default out/rl-bench)")
    ap.add_argument("--env-steps", type=int, default=20_000, help="steps per batched throughput figure")
    ap.add_argument("--sizes", type=int, nargs="+", default=[1, 16, 64, 256, 1024], help="batch sizes B")
    ap.add_argument(
        "--depth",
        nargs="+",
        choices=["raycast", "render"],
        default=["raycast"],
        help="the vector env's depth for the throughput figures: raycast (default), render (the OpenGL "
        "renderer, a GPU where there is one), or both, each B measured with each",
    )
    ap.add_argument("--num-envs", type=int, default=16, help="B for the SAC training runs (default 16)")
    ap.add_argument("--seeds", type=int, nargs="*", default=[0, 1, 2], help="training seeds (none: skip)")
    ap.add_argument("--check-every", type=int, default=10_000, help="SAC steps between success checks")
    ap.add_argument("--cap", type=float, default=480.0, help="training time cap per run (s)")
    ap.add_argument("--ppo-envs", type=int, default=256, help="B for the PPO comparison (0: skip it)")
    ap.add_argument("--baseline-training", action="store_true", help="also SAC 50k on one single env")
    ap.add_argument("--quick", action="store_true", help="smoke run: small sizes, no training")
    ap.add_argument("--demonstrations", type=int, default=None, help="SAC: teacher warm-up steps")
    ap.add_argument("--bc-steps", type=int, default=None, help="SAC: actor cloning steps after them")
    ap.add_argument("--anchor", type=float, default=None, help="SAC: weight pulling the actor to the teacher")
    ap.add_argument("--json", default=None, help="output path (default benchmarks/results/rl.json)")
    args = ap.parse_args()
    if args.quick:
        args.sizes, args.env_steps, args.seeds, args.ppo_envs = [1, 16], 2000, [], 0

    res: dict[str, Any] = {}
    single = env_throughput(1, 600 if args.quick else 3000, "dummy")
    res["single_env"] = single
    print(f"single env (today's): {single['steps_per_s']:8.0f} steps/s", flush=True)
    res["batched"] = []
    for b, depth in ((b, d) for b in args.sizes for d in args.depth):
        r = in_subprocess("batched_throughput", b, args.env_steps, depth)
        r["vs_single"] = r["steps_per_s"] / single["steps_per_s"]
        res["batched"].append(r)
        print(
            f"batched B={b:5d}, depth by {depth:7s}: {r['steps_per_s']:8.0f} steps/s "
            f"({r['vs_single']:5.1f}x the single env, "
            f"real-time factor {r['real_time_factor']:6.0f}), {r['rss_per_env_bytes'] / 1e6:5.2f} MB/env, "
            f"resets {100 * r['reset_share']:4.1f} % of the time",
            flush=True,
        )
    out = Path(args.out)
    given = {
        "demonstrations": args.demonstrations,
        "demonstration_bc_steps": args.bc_steps,
        "demonstration_anchor": args.anchor,
    }
    demo = {k: v for k, v in given.items() if v is not None}
    res["training"] = []
    for seed in args.seeds:
        r = train_to_target(out / f"sac-{seed}", seed, "sac", args.num_envs, args.check_every, args.cap, demo)
        res["training"].append(r)
        print(
            f"SAC x{args.num_envs} seed {seed}: {_reached(r, args.cap)}; 50 evaluation episodes: {_rate(r)}"
        )
    if args.ppo_envs:
        r = train_to_target(out / "ppo-0", 0, "ppo", args.ppo_envs, 10 * args.check_every, args.cap)
        res["ppo_batched"] = r
        print(
            f"PPO x{args.ppo_envs} seed 0: {_reached(r, args.cap)} ("
            f"{r['steps_per_s']:.0f} steps/s); 50 evaluation episodes: {_rate(r)}"
        )
    if args.baseline_training:
        from droneulator.workflows.rl.train import train

        summary = train(None, out / "sac-single", steps=PAPER_STEPS, seed=0, progress=False)
        res["baseline_single_sac_50k"] = {k: summary[k] for k in ("steps", "wall_s", "steps_per_s")}
        print(f"baseline SAC 50k on one single env: {summary['wall_s'] / 60:.1f} min")
    write("rl", res, args.json)


if __name__ == "__main__":
    main()
