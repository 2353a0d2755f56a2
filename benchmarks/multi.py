"""Many agents in many worlds: agent-steps per second of the multi-agent vineyard env, and a shared policy
trained for teams of two.

1. Agent-steps per second (random actions, every agent's restarts included, depth by ray casting with
   the other agents as spheres) of :class:`~droneulator.workflows.rl.multi.VineyardMultiVectorEnv` at W
   worlds x N agents (default 64 x 4, 128 x 2, 256 x 1), each in its own process, against the one-agent
   vector env at B = 256 measured in the same run (the ratio is what to quote on a shared machine).
2. ``--train``: SAC with one policy shared by two agents per world (``droneulator train --num-envs 8
   --agents 2 --stop-at 0.9``): training stops once 45 of 50 held-out team episodes (seeds from
   2,500,000, two agents per world, a success both at their goals and no collision) succeed, or at the
   cap (default 600 s); the final policy then flies the 50 evaluation team episodes (seeds from
   1,000,000, never used to decide when to stop), with the 95 % Wilson interval. One run per seed.
   It trains as ``droneulator train --agents 2`` does: the team recipe (``--demonstrations 20000
   --bc-steps 5000 --anchor 10``, ``--encounters 0.5``: ``rl.encounters`` of the training worlds, the
   share of tasks sent against the other agent) unless the flags say otherwise (``--demonstrations 0
   --encounters 0``: plain SAC on plain tasks); the held-out worlds always draw plainly.

Reproduce: ``python benchmarks/multi.py`` (about 3 min), ``--train`` adds up to 11 min per seed; the
figure that meets the 90 % target: ``--sizes --train --seeds 0 1 2`` (2 to 3 min per seed, docs/rl.md).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
from _common import write

from droneulator.cli.train import TEAM_ENCOUNTERS, TEAM_FLAGS, TEAM_RECIPE

#: the train command's flag for each SAC demonstration setting
FLAGS = {
    "demonstrations": "demonstrations",
    "demonstration_bc_steps": "bc-steps",
    "demonstration_anchor": "anchor",
}
#: steps per figure: every agent flies this many frames (10 s), so restarts are part of the figure
STEPS = 300


def agent_steps(worlds: int, agents: int, steps: int = STEPS) -> dict[str, Any]:
    """Agent-steps per second of ``worlds`` x ``agents`` (``agents`` 0: the one-agent vector env)."""
    if agents:
        from droneulator.workflows.rl.multi import VineyardMultiVectorEnv

        env: Any = VineyardMultiVectorEnv(worlds, agents)
    else:
        from droneulator.workflows.rl.vector import VineyardNavVectorEnv

        env = VineyardNavVectorEnv(worlds)
    rows = env.num_envs
    rng = np.random.default_rng(0)
    t = time.perf_counter()
    env.reset(seed=0)
    reset_s = time.perf_counter() - t
    for _ in range(10):  # warm-up: compiled code, the BVH
        env.step(rng.uniform(-1, 1, (rows, 2)).astype(np.float32))
    ended = 0
    t0 = time.perf_counter()
    for _ in range(steps):
        _, _, term, trunc, _ = env.step(rng.uniform(-1, 1, (rows, 2)).astype(np.float32))
        ended += int((term | trunc).sum())
    wall = time.perf_counter() - t0
    env.close()
    return {
        "worlds": worlds,
        "agents": agents or 1,
        "agent_steps": steps * rows,
        "wall_s": wall,
        "agent_steps_per_s": steps * rows / wall,
        "episodes_ended": ended,
        "first_reset_s": reset_s,
    }


def in_subprocess(fn: str, *args: Any, wait_policy: str = "PASSIVE") -> dict[str, Any]:
    """``multi.fn(*args)`` in a fresh process whose OpenMP threads wait by ``wait_policy`` (``default``:
    libgomp's own, spinning 300,000 times before sleeping; the package sets PASSIVE unless told)."""
    code = f"import json, sys; sys.path.insert(0, {str(Path(__file__).parent)!r}); import multi; "
    code += f"print(json.dumps(multi.{fn}(*{args!r})))"
    # an empty value is not one libgomp knows: it keeps its default (and says so on stderr)
    env = os.environ | {"OMP_WAIT_POLICY": "" if wait_policy == "default" else wait_policy}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env)
    return json.loads(out.stdout.strip().splitlines()[-1])


@contextlib.contextmanager
def busy_cores(n: int) -> Iterator[None]:
    """``n`` processes each keeping a core busy (``python -c 'while 1: pass'``) while the block runs."""
    procs = [subprocess.Popen([sys.executable, "-c", "while 1: pass"]) for _ in range(n)]
    try:
        yield
    finally:
        for p in procs:
            p.kill()
            p.wait()


def train_team(
    out: Path, seed: int, worlds: int, every: int, cap_s: float, stop_at: float, demo: dict[str, float],
    encounters: float = 0.0,
) -> dict[str, Any]:  # fmt: skip
    """A shared policy for two agents per world to ``stop_at`` of 50 check team episodes (or ``cap_s``),
    then the 50 evaluation team episodes; ``demo``: SAC hyperparameters (the demonstrations');
    ``encounters``: ``rl.encounters`` of the training worlds."""
    from stable_baselines3 import SAC

    from droneulator.config import load_config
    from droneulator.workflows.rl.env import env_config
    from droneulator.workflows.rl.heldout import EVAL_EPISODES, EVAL_SEED, interval_record
    from droneulator.workflows.rl.train import held_out_env, held_out_successes, train

    cfg = load_config(overrides=[f"rl.encounters={encounters}"])
    summary = train(cfg, out, steps=50_000_000, seed=seed, n_envs=worlds, vec="native", agents=2,
                    progress=False, stop_at=stop_at, check_every=every, max_wall_s=cap_s,
                    overrides=demo)  # fmt: skip
    policy = SAC.load(out / "model.zip", device="cpu", custom_objects={"replay_buffer_class": None})
    seeds = list(range(EVAL_SEED, EVAL_SEED + EVAL_EPISODES))
    assert not set(seeds) & set(summary["check_seeds"])
    env = held_out_env(env_config(), len(seeds), "raycast", agents=2)
    try:
        successes = held_out_successes(policy, env, seeds)
    finally:
        env.close()
    reached = summary["reached"]
    return {
        "seed": seed,
        "worlds": worlds,
        "agents": 2,
        "reached_target": reached is not None,
        "wall_s_to_target": reached["wall_s"] if reached else None,
        "steps_to_target": reached["steps"] if reached else None,
        "train_wall_s": summary["wall_s"],
        "steps": summary["steps"],
        "checks": summary["checks"],
        "evaluation_seeds": [seeds[0], seeds[-1]],
        "evaluation": interval_record(successes, len(seeds)),
        "stop_at": stop_at,
        "hyperparameters": summary["hyperparameters"],
        "encounters": encounters,
        "command": f"droneulator train --num-envs {worlds} --agents 2 --seed {seed} --stop-at {stop_at} "
        f"--check-every {every} --out {out}" + "".join(f" --{FLAGS[k]} {v}" for k, v in demo.items())
        + (f" --set rl.encounters={encounters}" if encounters else ""),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", nargs="*", default=["64x4", "128x2", "256x1"], help="W x N (none: skip)")
    ap.add_argument("--steps", type=int, default=STEPS, help=f"steps per figure (default {STEPS})")
    ap.add_argument("--train", action="store_true", help="also train a shared policy for teams of two")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0], help="training seeds (default 0)")
    ap.add_argument("--worlds", type=int, default=8, help="training worlds of two agents (default 8)")
    ap.add_argument("--check-every", type=int, default=10_000, help="SAC steps between checks")
    ap.add_argument("--cap", type=float, default=600.0, help="training time cap per seed (s, default 600)")
    ap.add_argument("--stop-at", type=float, default=0.9, help="check share that ends training (default 0.9)")
    ap.add_argument("--demonstrations", type=int, default=None,
                    help=f"teacher warm-up steps (default: the team recipe's, {TEAM_FLAGS})")  # fmt: skip
    ap.add_argument("--bc-steps", type=int, default=None, help="actor cloning steps after them")
    ap.add_argument("--anchor", type=float, default=None, help="pull to the teacher after them")
    ap.add_argument("--encounters", type=float, default=TEAM_ENCOUNTERS,
                    help="rl.encounters of the training worlds: the share of tasks sent against the other "
                    f"agent (default {TEAM_ENCOUNTERS}, the team recipe's)")  # fmt: skip
    ap.add_argument("--out", default="out/multi-bench", help="training runs folder")
    ap.add_argument("--json", default=None, help="output path (default benchmarks/results/multi.json)")
    ap.add_argument(
        "--wait-policies",
        nargs="+",
        default=["PASSIVE"],
        help="OMP_WAIT_POLICY values to measure every figure under, in turn (PASSIVE, ACTIVE, "
        "or 'default': libgomp's own, spinning before it sleeps; default: PASSIVE, the "
        "package's)",
    )
    ap.add_argument(
        "--busy",
        type=int,
        default=0,
        help="processes keeping a core busy beside the figures (python -c 'while 1: pass')",
    )
    ap.add_argument("--rounds", type=int, default=1, help="rounds of every figure, alternated (default 1)")
    args = ap.parse_args()
    sizes = [tuple(int(v) for v in s.lower().split("x")) for s in args.sizes]
    bases, figures = [], []
    with busy_cores(args.busy):
        for rnd in range(args.rounds if sizes else 0):
            for policy in args.wait_policies:
                base = in_subprocess("agent_steps", 256, 0, args.steps, wait_policy=policy)
                base.update({"round": rnd, "wait_policy": policy, "busy": args.busy})
                bases.append(base)
                print(f"[round {rnd}, OMP_WAIT_POLICY {policy}, {args.busy} busy] one-agent vector env, "
                      f"B = 256: {base['agent_steps_per_s']:,.0f} steps/s", flush=True)  # fmt: skip
                for w, n in sizes:
                    r = in_subprocess("agent_steps", w, n, args.steps, wait_policy=policy)
                    r.update({"round": rnd, "wait_policy": policy, "busy": args.busy})
                    r["vs_one_agent_env_256"] = r["agent_steps_per_s"] / base["agent_steps_per_s"]
                    figures.append(r)
                    print(f"  {w} worlds x {n} agents: {r['agent_steps_per_s']:,.0f} agent-steps/s "
                          f"({r['vs_one_agent_env_256']:.2f} x the one-agent env), {r['episodes_ended']} "
                          "episodes ended", flush=True)  # fmt: skip
    teams = []
    given = {
        "demonstrations": args.demonstrations,
        "demonstration_bc_steps": args.bc_steps,
        "demonstration_anchor": args.anchor,
    }
    demo = {k: v for k, v in given.items() if v is not None}
    if "demonstrations" not in demo:  # as the train command: the recipe, flags given alone on top
        demo = {**TEAM_RECIPE, **demo}
    if args.train:
        from droneulator.workflows.rl.heldout import rate_text

        for seed in args.seeds:
            out = Path(args.out) / f"seed{seed}"
            r = train_team(
                out, seed, args.worlds, args.check_every, args.cap, args.stop_at, demo, args.encounters
            )
            teams.append(r)
            when = f"{args.stop_at:.0%} of the checks not reached within {args.cap:.0f} s"
            if r["reached_target"]:
                steps = r["steps_to_target"]
                when = f"{args.stop_at:.0%} of the checks after {r['wall_s_to_target']:.0f} s ({steps} steps)"
            ev = r["evaluation"]
            print(f"seed {seed}: {when}; evaluation {rate_text(ev['successes'], ev['episodes'])}", flush=True)
    write("multi", {"one_agent_256": bases, "throughput": figures, "teams": teams,
                    "settings": vars(args)}, args.json)  # fmt: skip


if __name__ == "__main__":
    main()
