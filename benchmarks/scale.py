"""Past one machine on Ray: what Ray costs and gives, against the same work without it, in one run.

1. Training: PPO for ``--steps`` env steps on the batched vineyard env, ``--worlds`` worlds in all,
   rollouts of 32 steps per world (a batch of worlds x 32), 5 epochs of minibatches of 2,048:
   * without Ray: Stable-Baselines3 PPO on the native vector env in this process (``droneulator train
     --num-envs``, the same settings);
   * with Ray: ``droneulator train --ray`` (RLlib PPO, its current API stack) on a local multi-node
     cluster of 1, 2 and 3 nodes (``ray.cluster_utils.Cluster``, one CPU each, as separate raylets),
     one env runner per node, the worlds split between them; the learner in this process;
   * with Ray, SB3: ``droneulator train --ray ... --ray-backend sb3`` on the same clusters, SB3's PPO
     here with the worlds split over one Ray actor per node (one round trip to every actor per step).
   Reported: env steps/s over the run and training wall time, Ray's overhead as the ratio to the run
   without Ray, and the env's own speed (random actions, no learning) for scale.
2. Sweeps: ``droneulator sweep capture`` of ``--jobs`` small captures (160x120, 3 views, seeds 0..)
   on a local Ray with 2 CPUs: 1 worker (2 CPUs per job) against 2 workers (1 CPU per job); jobs/hour.

On this project's 2-core machine nodes beyond 2 share cores: the 3-node figure shows the cost of
oversubscription, not of Ray.

3. ``--curve 1 2 4 8 16`` (instead of 1 and 2 above): the scaling curve on one bigger machine. A local Ray
   with every core; for each count N, RLlib PPO with N env runners of ``--worlds-per-runner`` worlds
   each (one CPU, one thread each): env steps/s of the runners sampling together (no learning) and of
   training (sampling and the learner in this process, one after the other, as RLlib's PPO runs).
   Against, in the same run: the env alone on one thread (``--worlds-per-runner`` worlds; N times it is
   perfect scaling) and on every core in one process (N x ``--worlds-per-runner`` worlds). Writes
   ``scale_curve.json`` and a plot beside it.

Reproduce: ``python benchmarks/scale.py`` (about 10 min on 2 cores; ``--quick`` for a smoke run);
``python benchmarks/scale.py --curve 1 2 4 8 16`` on a 16-core machine (about 4 min).
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from _common import write

ROOT = Path(__file__).resolve().parents[1]
#: training on Ray: RLlib's env runners and learner, or SB3 here with the worlds in Ray actors
LABELS = {"rllib": "RLlib PPO", "sb3": "SB3 PPO, worlds in Ray actors"}


def env_speed(worlds: int, steps: int, threads: int | None = None) -> float:
    """Env steps/s of the batched env alone: random actions, autoresets, no learning; on ``threads``
    threads (default: every core)."""
    from droneulator.workflows.rl.vector import VineyardNavVectorEnv

    env = VineyardNavVectorEnv(worlds, threads=threads)
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    for _ in range(20):  # compile and warm up
        env.step(rng.uniform(-1, 1, (worlds, 2)).astype(np.float32))
    n = max(1, steps // worlds)
    t0 = time.perf_counter()
    for _ in range(n):
        env.step(rng.uniform(-1, 1, (worlds, 2)).astype(np.float32))
    rate = n * worlds / (time.perf_counter() - t0)
    env.close()
    return rate


def without_ray(worlds: int, steps: int, out: Path) -> dict[str, Any]:
    from droneulator.workflows.rl.train import train

    s = train(None, out, steps=steps, n_envs=worlds, algo="ppo", vec="native", progress=False)
    return {"steps": s["steps"], "wall_s": s["wall_s"], "steps_per_s": s["steps_per_s"]}


def with_ray(nodes: int, worlds: int, steps: int, out: Path, backend: str) -> dict[str, Any]:
    """PPO on a fresh local cluster of ``nodes`` raylets (one CPU each): RLlib with one env runner per
    node (``backend="rllib"``), or SB3 here with the worlds in one Ray actor per node (``"sb3"``)."""
    import ray
    from ray.cluster_utils import Cluster

    from droneulator.workflows.rl.rllib import train_on_ray
    from droneulator.workflows.rl.train import train

    t0 = time.perf_counter()
    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False})
    for _ in range(nodes - 1):
        cluster.add_node(num_cpus=1)
    cluster.wait_for_nodes()
    start_s = time.perf_counter() - t0
    try:
        t1 = time.perf_counter()
        if backend == "rllib":
            s = train_on_ray(
                None, out, address=cluster.address, steps=steps, env_runners=nodes,
                num_envs=worlds // nodes, progress=False,
            )  # fmt: skip
        else:
            s = train(
                None, out, steps=steps, n_envs=worlds, algo="ppo", vec="ray", progress=False,
                ray_address=cluster.address, actors=nodes,
            )  # fmt: skip
        total_s = time.perf_counter() - t1
    finally:
        if ray.is_initialized():
            ray.shutdown()
        cluster.shutdown()
    return {
        "backend": backend,
        "nodes": s["ray_nodes"],
        "env_runners": nodes,
        "worlds_per_runner": worlds // nodes,
        "steps": s["steps"],
        "wall_s": s["wall_s"],
        "steps_per_s": s["steps_per_s"],
        "cluster_start_s": start_s,
        "build_and_eval_s": total_s - s["wall_s"],
    }


def _sample(runner: Any) -> int:
    """One env runner's rollout (its worlds x the fragment length), as env steps."""
    return sum(len(episode) for episode in runner.sample())


def runner_curve(counts: list[int], per_runner: int, rounds: int, iterations: int) -> list[dict[str, Any]]:
    """Env steps/s of 1..N RLlib env runners on a local Ray with every core (section 3 of the docstring)."""
    import os

    from tqdm import tqdm

    from droneulator.runtime.cluster import connect
    from droneulator.workflows.rl.env import env_config
    from droneulator.workflows.rl.rllib import WORKER_ENV, _sampled, algorithm_config

    cfg = env_config(None)
    rows = []
    with connect("local", num_cpus=os.cpu_count(), worker_env=WORKER_ENV):
        for n in tqdm(counts, desc="env runners", unit="point"):
            t0 = time.perf_counter()
            algorithm = algorithm_config(cfg, "ppo", n, per_runner, seed=0).build_algo()
            build_s = time.perf_counter() - t0
            try:
                group = algorithm.env_runner_group
                group.foreach_env_runner(_sample, local_env_runner=False)  # warm-up
                t0 = time.perf_counter()
                sampled = sum(
                    sum(group.foreach_env_runner(_sample, local_env_runner=False)) for _ in range(rounds)
                )
                sample_rate = sampled / (time.perf_counter() - t0)
                before = _sampled(algorithm.train())  # the learner's first step builds its optimiser
                t0 = time.perf_counter()
                for _ in range(iterations):
                    after = _sampled(algorithm.train())
                train_rate = (after - before) / (time.perf_counter() - t0)
            finally:
                algorithm.stop()
            rows.append({
                "env_runners": n, "worlds": n * per_runner, "sampling_steps_per_s": sample_rate,
                "training_steps_per_s": train_rate, "build_s": build_s,
            })  # fmt: skip
            tqdm.write(f"{n} env runner(s): sampling {sample_rate:,.0f} steps/s, training {train_rate:,.0f}")
    return rows


def curve_main(args: argparse.Namespace) -> None:
    """``--curve``: the env-runner scaling curve (section 3 of the docstring), its table, JSON and plot."""
    counts, w = sorted(args.curve), args.worlds_per_runner
    one = env_speed(w, 20_000, threads=1)
    print(f"env alone, {w} worlds, one thread: {one:,.0f} steps/s", flush=True)
    alls = {n: env_speed(n * w, 20_000) for n in counts}
    for n, rate in alls.items():
        print(f"env alone, {n * w} worlds, every core in one process: {rate:,.0f} steps/s", flush=True)
    rows = runner_curve(counts, w, args.rounds, args.iterations)
    for r in rows:
        r["one_thread_steps_per_s"] = one
        r["one_process_steps_per_s"] = alls[r["env_runners"]]
        r["sampling_efficiency"] = r["sampling_steps_per_s"] / (r["env_runners"] * one)
        r["sampling_x_first"] = r["sampling_steps_per_s"] / rows[0]["sampling_steps_per_s"]
    print(f"\n| env runners | worlds | sampling steps/s | x {counts[0]} runner(s) | x one thread "
          "| efficiency | training steps/s | one process, every core |")
    print("|---|---|---|---|---|---|---|---|")  # fmt: skip
    for r in rows:
        print(f"| {r['env_runners']} | {r['worlds']} | {r['sampling_steps_per_s']:,.0f} | "
              f"{r['sampling_x_first']:.2f} | "
              f"{r['sampling_steps_per_s'] / one:.1f} | {r['sampling_efficiency']:.0%} | "
              f"{r['training_steps_per_s']:,.0f} | {r['one_process_steps_per_s']:,.0f} |")  # fmt: skip
    out = write(
        "scale_curve",
        {
            "settings": {"worlds_per_runner": w, "rounds": args.rounds, "iterations": args.iterations},
            "rows": rows,
        },
        args.output,
    )
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = [r["env_runners"] for r in rows]
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(n, [k * one for k in n], "k:", label="perfect (N x one thread)")
    ax.plot(n, [r["sampling_steps_per_s"] for r in rows], "o-", label="RLlib env runners, sampling")
    ax.plot(n, [r["training_steps_per_s"] for r in rows], "s-", label="RLlib PPO, training")
    ax.plot(n, [r["one_process_steps_per_s"] for r in rows], "^--", label="one process, every core")
    ax.set(xscale="log", yscale="log", xlabel=f"env runners (N x {w} worlds)", ylabel="env steps/s")
    ax.set_xticks(n, [str(k) for k in n])
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(out.with_suffix(".png"), dpi=120)
    print(f"wrote {out.with_suffix('.png')}")


def sweep_rate(workers: int, jobs: int, out: Path) -> dict[str, Any]:
    cmd = [
        sys.executable, "-m", "droneulator.cli", "sweep", "capture", "--out", str(out),
        "--seeds", f"0-{jobs - 1}", "--views", "3", "--ray", "local", "--cpus-per-job", str(2 / workers),
        "--no-progress", "--set", "capture.width=160", "--set", "capture.height=120",
        "--set", "capture.arc_deg=30", "--set", "capture.speed=2", "--set", "capture.pitch_deg=10",
    ]  # fmt: skip
    t0 = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        raise RuntimeError(done.stdout + done.stderr)
    return {"workers": workers, "jobs": jobs, "wall_s": wall, "jobs_per_hour": jobs * 3600 / wall}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=40_960, help="env steps per training run")
    ap.add_argument("--worlds", type=int, default=96, help="batched worlds in all (split over runners)")
    ap.add_argument("--nodes", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument(
        "--backends", nargs="+", choices=tuple(LABELS), default=list(LABELS), help="training on Ray: which"
    )
    ap.add_argument("--no-sweeps", action="store_true", help="training figures only")
    ap.add_argument("--jobs", type=int, default=4, help="capture jobs per sweep")
    ap.add_argument("--quick", action="store_true", help="smoke run: few steps, 2 jobs")
    ap.add_argument(
        "--curve", type=int, nargs="+", default=None, metavar="N",
        help="instead: the scaling curve for these env-runner counts (e.g. 1 2 4 8 16)",
    )  # fmt: skip
    ap.add_argument("--worlds-per-runner", type=int, default=64, help="--curve: worlds per env runner")
    ap.add_argument("--rounds", type=int, default=10, help="--curve: timed sampling rounds per point")
    ap.add_argument("--iterations", type=int, default=3, help="--curve: timed training iterations per point")
    ap.add_argument("--output", default=None)
    args = ap.parse_args()
    if args.curve:
        if min(args.curve + [args.worlds_per_runner, args.rounds, args.iterations]) < 1:
            ap.error("--curve counts, --worlds-per-runner, --rounds and --iterations must be at least 1")
        curve_main(args)
        return
    if args.quick:
        args.steps, args.jobs, args.nodes = 6_144, 2, [1, 2]
    tmp = Path(tempfile.mkdtemp(prefix="droneulator-scale-"))
    try:
        env = env_speed(args.worlds, 20_000)
        print(f"env alone ({args.worlds} worlds, random actions): {env:,.0f} steps/s", flush=True)
        base = without_ray(args.worlds, args.steps, tmp / "sb3")
        print(f"no Ray (SB3 PPO): {base['steps_per_s']:,.0f} steps/s, {base['wall_s']:.1f} s", flush=True)
        runs = []
        for n in args.nodes:
            for backend in args.backends:
                r = with_ray(n, args.worlds, args.steps, tmp / f"{backend}{n}", backend)
                r["ratio_to_no_ray"] = r["steps_per_s"] / base["steps_per_s"]
                runs.append(r)
                print(
                    f"Ray, {n} node(s) ({LABELS[backend]}): {r['steps_per_s']:,.0f} steps/s, "
                    f"{r['wall_s']:.1f} s ({r['ratio_to_no_ray']:.2f}x no Ray; cluster start "
                    f"{r['cluster_start_s']:.1f} s, build and held-out check {r['build_and_eval_s']:.1f} s)",
                    flush=True,
                )
        sweeps = []
        for workers in () if args.no_sweeps else (1, 2):
            s = sweep_rate(workers, args.jobs, tmp / f"sweep{workers}")
            sweeps.append(s)
            print(f"sweep, {workers} worker(s): {s['jobs']} jobs in {s['wall_s']:.0f} s, "
                  f"{s['jobs_per_hour']:.0f} jobs/h", flush=True)  # fmt: skip
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    print("\n| run | env steps/s | training wall (s) | x no Ray |\n|---|---|---|---|")
    print(f"| SB3 PPO, no Ray | {base['steps_per_s']:,.0f} | {base['wall_s']:.1f} | 1.00 |")
    for r in runs:
        print(f"| {LABELS[r['backend']]}, {r['nodes']} node(s) | {r['steps_per_s']:,.0f} | "
              f"{r['wall_s']:.1f} | {r['ratio_to_no_ray']:.2f} |")  # fmt: skip
    write(
        "scale",
        {
            "settings": {"steps": args.steps, "worlds": args.worlds, "jobs": args.jobs},
            "env_alone_steps_per_s": env,
            "no_ray": base,
            "ray": runs,
            "sweeps": sweeps,
        },
        args.output,
    )


if __name__ == "__main__":
    main()
