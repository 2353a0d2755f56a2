"""``droneulator train --ray``: the vineyard task on Ray RLlib (its current API stack), across a cluster.

Each of RLlib's env runners hosts one batched env
(:class:`~droneulator.workflows.rl.vector.VineyardNavVectorEnv`, ``num_envs`` worlds) through
``gym_env_vectorize_mode="vector_entry_point"``: RLlib calls ``gym.make_vec`` on the registered
``droneulator/VineyardNav-v0``, whose vector entry point builds that env, and re-wraps nothing.
The env runners go wherever Ray places them (one CPU each);
the learner runs in this process (``learners=0``, the default) or as ``learners`` Ray actors.

A failed env runner (its process killed, its node lost) is restarted by RLlib after
``restart_delay_s`` and training goes on with the others meanwhile (``restart_failed_env_runners``).
The algorithm's whole state is saved to ``out/checkpoint`` every ``checkpoint_every`` env steps and at
the end; ``resume=True`` restores it and trains on to ``steps`` in total, so an interrupted run loses
at most one checkpoint period.

Writes to ``out``: ``checkpoint/`` (RLlib's), ``progress.csv`` (one row per training iteration),
``tb/`` (TensorBoard scalars), ``config.json`` and ``train_summary.json``, which ends with the
deterministic policy flown on ``check_episodes`` held-out seeds (50 by default, from
:data:`~droneulator.workflows.rl.heldout.CHECK_SEED`, batched on one vector env), as ``--stop-at`` checks
do, with the success rate's 95 % Wilson interval.
"""

from __future__ import annotations

import csv
import json
import shutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from droneulator.config import SimConfig, to_dict
from droneulator.workflows.rl import ENV_ID
from droneulator.workflows.rl.env import env_config
from droneulator.workflows.rl.heldout import CHECK_EPISODES, check_seeds, interval_record, refuse_overlap
from droneulator.workflows.rl.train import (
    PPO_HYPERPARAMETERS,
    SAC_HYPERPARAMETERS,
    held_out_successes,
)

ALGORITHMS = ("ppo", "sac")

#: the environment of every Ray worker of a training run: each env runner has one CPU, so its numba
#: pool gets one thread. Numba's OpenMP pool sets the process's OpenMP thread count when it starts, and
#: the policy's torch shares that OpenMP runtime: with every core there, N runners on N cores ran N x
#: cores threads, and 2, 4 or 8 runners on 16 cores sampled 2,550 env steps/s together against 6,160
#: for one (benchmarks/scale.py --curve; with one thread each, 8 runners sample 7.96x one)
WORKER_ENV = {"NUMBA_NUM_THREADS": "1"}


def ppo_settings() -> dict[str, Any]:
    """RLlib's names for the SB3 PPO run's settings (:data:`~.train.PPO_HYPERPARAMETERS`, one source):
    32-step rollouts per env, minibatches of 2,048, 5 epochs; SB3's default value-loss weight."""
    h = PPO_HYPERPARAMETERS
    return {
        "lr": h["learning_rate"], "gamma": h["gamma"], "lambda_": h["gae_lambda"],
        "clip_param": h["clip_range"], "num_epochs": h["n_epochs"], "minibatch_size": h["batch_size"],
        "entropy_coeff": h["ent_coef"],
        "vf_loss_coeff": 0.5,
    }  # fmt: skip


def sac_settings() -> dict[str, Any]:
    """RLlib's names for the SB3 SAC run's settings (:data:`~.train.SAC_HYPERPARAMETERS`, one source)."""
    h = SAC_HYPERPARAMETERS
    lr = h["learning_rate"]
    return {
        "actor_lr": lr, "critic_lr": lr, "alpha_lr": lr, "gamma": h["gamma"], "tau": h["tau"],
        "n_step": h["n_steps"], "initial_alpha": float(str(h["ent_coef"]).removeprefix("auto_")),
        "train_batch_size_per_learner": h["batch_size"],
        "num_steps_sampled_before_learning_starts": h["learning_starts"],
    }  # fmt: skip


def algorithm_config(
    cfg: SimConfig,
    algo: str,
    env_runners: int,
    num_envs: int,
    seed: int,
    depth: str = "raycast",
    learners: int = 0,
    restart_delay_s: float = 10.0,
) -> Any:
    """The RLlib ``AlgorithmConfig`` of a run (see the module docstring)."""
    from ray.rllib.algorithms.ppo import PPOConfig
    from ray.rllib.algorithms.sac import SACConfig

    if algo not in ALGORITHMS:
        raise ValueError(f"unknown algorithm {algo!r} on Ray; available: {', '.join(ALGORITHMS)}")
    if env_runners < 1 or num_envs < 1:
        raise ValueError(f"--env-runners and --num-envs must be at least 1, got {env_runners}, {num_envs}")
    if learners < 0:
        raise ValueError(f"learners must be 0 (this process) or more, got {learners}")
    config = PPOConfig() if algo == "ppo" else SACConfig()
    activation = "tanh" if algo == "ppo" else "relu"  # SB3's defaults for each
    hyper = PPO_HYPERPARAMETERS if algo == "ppo" else SAC_HYPERPARAMETERS
    hidden = hyper["policy_kwargs"]["net_arch"]
    config = (
        # the SimConfig itself, not a dict: unpickling it imports droneulator on the env runner, which
        # registers ENV_ID with Gymnasium there (Tune's env registry keys entries by the process's first
        # Ray job, so a second run in one process would not find them)
        config.environment(ENV_ID, env_config={"config": cfg, "depth": depth})
        .env_runners(
            num_env_runners=env_runners,
            num_envs_per_env_runner=num_envs,
            gym_env_vectorize_mode="vector_entry_point",
            num_cpus_per_env_runner=1,
            # PPO: the rollout per env; SAC: at least its n-step return (RLlib checks it)
            rollout_fragment_length=hyper["n_steps"],
        )
        .learners(num_learners=learners)
        .rl_module(model_config={"fcnet_hiddens": hidden, "fcnet_activation": activation})
        .debugging(seed=seed, log_level="WARN")
        .fault_tolerance(
            restart_failed_env_runners=True,
            max_num_env_runner_restarts=1_000,
            delay_between_env_runner_restarts_s=restart_delay_s,
        )
    )
    if algo == "ppo":
        batch = env_runners * num_envs * PPO_HYPERPARAMETERS["n_steps"]
        settings = ppo_settings()
        settings["minibatch_size"] = min(settings["minibatch_size"], batch)
        config = config.training(train_batch_size_per_learner=batch, **settings)
    else:
        # uniform sampling, as SB3's buffer
        buffer = {"type": "EpisodeReplayBuffer", "capacity": SAC_HYPERPARAMETERS["buffer_size"]}
        config = config.training(**sac_settings(), replay_buffer_config=buffer)
    return config


class ModulePolicy:
    """An RLlib module as a policy with SB3's ``predict`` (what :func:`held_out_successes` flies);
    ``squash``: the module's Gaussian is tanh-squashed (SAC's)."""

    def __init__(self, module: Any, squash: bool) -> None:
        self.module = module
        self.squash = squash

    def predict(self, obs: np.ndarray, deterministic: bool = True) -> tuple[np.ndarray, None]:
        import torch

        with torch.no_grad():
            out = self.module.forward_inference({"obs": torch.as_tensor(obs, dtype=torch.float32)})
        inputs = out["action_dist_inputs"].numpy()
        mean = inputs[:, : inputs.shape[1] // 2]  # a diagonal Gaussian's inputs: means, then log stds
        if self.squash:
            mean = np.tanh(mean)
        return np.clip(mean, -1.0, 1.0), None


def _sampled(result: dict[str, Any]) -> int:
    from ray.rllib.utils.metrics import ENV_RUNNER_RESULTS, NUM_ENV_STEPS_SAMPLED_LIFETIME

    value = result.get(NUM_ENV_STEPS_SAMPLED_LIFETIME)
    if value is None:
        value = result.get(ENV_RUNNER_RESULTS, {}).get(NUM_ENV_STEPS_SAMPLED_LIFETIME, 0)
    return int(value)


def _row(result: dict[str, Any], steps: int, wall: float, healthy: int, restarts: int) -> dict[str, Any]:
    runners = result.get("env_runners", {})
    learner = result.get("learners", {}).get("default_policy", {})
    return {
        "iteration": int(result.get("training_iteration", 0)),
        "env_steps": steps,
        "wall_s": round(wall, 3),
        "episode_return_mean": runners.get("episode_return_mean"),
        "episode_len_mean": runners.get("episode_len_mean"),
        "episodes": runners.get("num_episodes_lifetime"),
        "healthy_env_runners": healthy,
        "env_runner_restarts": restarts,
        "policy_loss": learner.get("policy_loss"),
        "vf_loss": learner.get("vf_loss"),
    }


def _save(algorithm: Any, checkpoint: Path) -> None:
    """Save next to ``checkpoint``, then swap it in: a run killed while saving keeps the last whole one."""
    saving = checkpoint.with_name(checkpoint.name + ".saving")
    shutil.rmtree(saving, ignore_errors=True)
    algorithm.save_to_path(str(saving))
    shutil.rmtree(checkpoint, ignore_errors=True)
    saving.rename(checkpoint)


def train_on_ray(
    cfg: SimConfig | None,
    out: Path,
    address: str = "local",
    steps: int = 200_000,
    seed: int = 0,
    algo: str = "ppo",
    env_runners: int = 1,
    num_envs: int = 64,
    depth: str = "raycast",
    learners: int = 0,
    checkpoint_every: int = 50_000,
    resume: bool = False,
    restart_delay_s: float = 10.0,
    num_cpus: int | None = None,
    progress: bool = True,
    on_iteration: Callable[[Any, dict[str, Any]], None] | None = None,
    check_episodes: int = CHECK_EPISODES,
) -> dict[str, Any]:
    """Train on Ray RLlib to ``steps`` env steps in total; returns (and writes) the summary, which ends
    with the policy flown on ``check_episodes`` held-out episodes (their seeds and 95 % interval too).

    ``address``: ``local``, ``auto`` or a head node's ``HOST:PORT`` (:mod:`droneulator.runtime.cluster`).
    ``on_iteration(algorithm, result)`` is called after every training iteration (tests kill an env
    runner from it). ``num_cpus`` limits a ``local`` Ray.
    """
    from tqdm import tqdm

    from droneulator.runtime.cluster import connect
    from droneulator.workflows.rl.vector import VineyardNavVectorEnv

    if steps < 1:
        raise ValueError(f"steps must be at least 1, got {steps}")
    held_out = check_seeds(check_episodes)  # refuses fewer than one
    # RLlib resets env runner k's worlds with seed + k + i (k = 1 .. env_runners; 0: the local one)
    refuse_overlap(range(seed, seed + env_runners + num_envs), held_out)
    cfg = env_config(cfg)
    out = Path(out)
    checkpoint = (out / "checkpoint").resolve()
    if resume and not (checkpoint / "algorithm_state.pkl").exists():
        raise FileNotFoundError(f"--resume: no checkpoint in {checkpoint} to resume from")
    if not resume and checkpoint.exists():
        raise FileExistsError(f"{out} holds a run already: --resume to go on with it, or another --out")
    config = algorithm_config(cfg, algo, env_runners, num_envs, seed, depth, learners, restart_delay_s)
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.json").write_text(json.dumps(to_dict(cfg), indent=2))
    with connect(address, num_cpus=num_cpus, worker_env=WORKER_ENV) as ray:
        from torch.utils.tensorboard import SummaryWriter

        nodes = sum(1 for n in ray.nodes() if n.get("Alive"))
        algorithm = config.build_algo()
        writer = SummaryWriter(str(out / "tb"))
        rows_path = out / "progress.csv"
        try:
            done = 0
            wall_before = 0.0
            if resume:
                algorithm.restore_from_path(str(checkpoint))
                previous = json.loads((out / "train_state.json").read_text())
                done, wall_before = int(previous["env_steps"]), float(previous["wall_s"])
            restarts = 0
            bar = tqdm(total=steps, initial=min(done, steps), unit="step", disable=not progress)
            t0 = time.perf_counter()
            next_checkpoint = done + checkpoint_every
            fields: list[str] | None = None
            while done < steps:
                result = algorithm.train()
                sampled = _sampled(result)
                bar.update(max(0, min(sampled, steps) - bar.n))
                done = sampled
                group = algorithm.env_runner_group
                restarts = group.num_remote_worker_restarts()
                wall = wall_before + time.perf_counter() - t0
                row = _row(result, done, wall, group.num_healthy_remote_workers(), restarts)
                with rows_path.open("a", newline="") as f:
                    w = csv.DictWriter(f, fieldnames=fields or list(row))
                    if fields is None:
                        fields = list(row)
                        if f.tell() == 0:
                            w.writeheader()
                    w.writerow(row)
                for key in ("episode_return_mean", "episode_len_mean", "policy_loss", "vf_loss"):
                    if isinstance(row[key], (int, float)):
                        writer.add_scalar(f"rollout/{key}", row[key], done)
                if done >= next_checkpoint or done >= steps:
                    _save(algorithm, checkpoint)
                    (out / "train_state.json").write_text(json.dumps({"env_steps": done, "wall_s": wall}))
                    next_checkpoint = done + checkpoint_every
                if on_iteration is not None:
                    on_iteration(algorithm, result)
            bar.close()
            wall = wall_before + time.perf_counter() - t0
            healthy = algorithm.env_runner_group.num_healthy_remote_workers()
            env = VineyardNavVectorEnv(len(held_out), cfg, depth)
            policy = ModulePolicy(algorithm.get_module(), squash=algo == "sac")
            successes = held_out_successes(policy, env, held_out)
            env.close()
        finally:
            writer.close()
            algorithm.stop()
    summary = {
        "algo": algo,
        "framework": "ray-rllib",
        "ray_address": address,
        "ray_nodes": nodes,
        "env_id": ENV_ID,
        "steps": done,
        "requested_steps": steps,
        "wall_s": wall,
        "steps_per_s": done / wall if wall > 0 else 0.0,
        "env_runners": env_runners,
        "num_envs_per_env_runner": num_envs,
        "healthy_env_runners": healthy,
        "env_runner_restarts": restarts,
        "learners": learners,
        "depth": depth,
        "seed": seed,
        "resumed": resume,
        "held_out_successes": successes,
        "held_out_episodes": len(held_out),
        "held_out_interval_95": interval_record(successes, len(held_out))["success_interval_95"],
        "check_seeds": held_out,
        "settings": ppo_settings() if algo == "ppo" else sac_settings(),
        "checkpoint": str(checkpoint),
    }
    (out / "train_summary.json").write_text(json.dumps(summary, indent=2, default=str))
    return summary
