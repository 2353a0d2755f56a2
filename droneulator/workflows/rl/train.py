"""``droneulator train``: Stable-Baselines3 SAC or PPO on ``droneulator/VineyardNav-v0``, or a ``ctbr``
policy distilled from an expert (``algo="distil"``, :mod:`~droneulator.workflows.rl.distil`).

Writes to ``out``: ``model.zip`` (final policy), ``checkpoints/``, ``monitor.csv`` (one row per
episode: return, length, wall time, success, termination), ``progress.csv`` and ``tb/`` (SB3's
training log as CSV and TensorBoard), ``config.json`` (the SimConfig the environments ran with) and
``train_summary.json`` (steps, wall time, seeds, hyperparameters).

The SAC settings are tuned for a 50k-step budget on a small CPU: two gradient steps per transition
(update-to-data ratio 2) on small 2x64 MLPs (cheap updates, so the ratio is affordable), 5-step
returns with gamma 0.99 (a 3 s horizon at 30 Hz, long enough to see a vine row before reaching it),
a 2k-step uniform-random warm-up, batch 256. ``demonstrations`` (``--demonstrations N``, velocity level,
off by default) has the scripted path teacher fly the first N steps instead (:func:`demonstrated_sac`;
measured in docs/rl.md: not better enough to be the default). The learner uses one torch thread by default;
environment stepping and learning alternate (SB3 is synchronous), and vectorised environments step
in parallel subprocesses, each single-threaded.

``vec="native"`` (``--num-envs B``) trains on the batched env instead
(:class:`~droneulator.workflows.rl.vector.VineyardNavVectorEnv` through
:class:`~droneulator.workflows.rl.sb3.SB3VectorEnv`): B worlds in this process, depth by ray casting.
SAC stays the default there: in the runs measured (``benchmarks/rl.py``, docs/rl.md; stopped on 10
check episodes, before 2026-11-29) it reached 9/10 held-out successes sooner than PPO (119 to 161 s
over three seeds against 258 s) and its policies held up better on 50 further held-out episodes (40 to
50 against 36); it takes one
gradient step per transition (``gradient_steps = B`` per vector step) unless told otherwise. PPO
(:data:`PPO_HYPERPARAMETERS`: on-policy batches of B x ``n_steps`` transitions) uses the env's speed
but needs about 60 times the transitions.
"""

from __future__ import annotations

import contextlib
import functools
import json
import math
import os
import time
import warnings
from collections import Counter, deque
from pathlib import Path
from typing import Any

from tqdm import TqdmExperimentalWarning

from droneulator.config import SimConfig, from_dict, to_dict
from droneulator.workflows.rl import ENV_ID
from droneulator.workflows.rl.env import env_config
from droneulator.workflows.rl.heldout import CHECK_EPISODES, check_seeds, interval_record, refuse_overlap

ALGORITHMS = ("sac", "ppo", "distil")
VEC_KINDS = ("auto", "dummy", "subproc", "native", "ray")

#: SAC hyperparameters (Stable-Baselines3 names) for ~50k environment steps
SAC_HYPERPARAMETERS: dict[str, Any] = {
    "learning_rate": 1e-3,
    "buffer_size": 200_000,
    "learning_starts": 2_000,
    "batch_size": 256,
    "tau": 0.01,
    "gamma": 0.99,
    "n_steps": 5,
    "train_freq": 1,
    "gradient_steps": 2,
    "ent_coef": "auto_0.1",
    # torch's fused CPU Adam: a gradient step in 3.7 ms instead of 4.3 (batch 256, 2x64, one thread)
    "policy_kwargs": {"net_arch": [64, 64], "optimizer_kwargs": {"fused": True}},
    # SAC from demonstrations (velocity level, not SB3 names): the first ``demonstrations`` env steps are
    # flown by the scripted teacher (:class:`~droneulator.workflows.rl.distil.PathTeacher`, its actions
    # plus Gaussian noise of std ``demonstration_noise``) instead of uniform random actions, then
    # ``demonstration_bc_steps`` Adam steps regress the actor's mean action on the replay buffer's
    # actions (behaviour cloning) before the actor flies; ``demonstration_anchor`` > 0 then adds that
    # weight times the squared distance of the actor's mean action from the teacher's action to every
    # SAC actor loss (on the batch's observations: the teacher is a function of the observation), so
    # that the cloned actor is not unlearnt while the critic catches up; 0: off
    "demonstrations": 0,
    "demonstration_noise": 0.1,
    "demonstration_bc_steps": 0,
    "demonstration_anchor": 0.0,
}
#: the entries of :data:`SAC_HYPERPARAMETERS` that are the demonstrations', not SB3's
DEMONSTRATION_KEYS = (
    "demonstrations",
    "demonstration_noise",
    "demonstration_bc_steps",
    "demonstration_anchor",
)

#: PPO hyperparameters (Stable-Baselines3 names) for the batched env (hundreds of environments)
PPO_HYPERPARAMETERS: dict[str, Any] = {
    "learning_rate": 3e-4,
    "n_steps": 32,
    "batch_size": 2048,
    "n_epochs": 5,
    "gamma": 0.99,
    "gae_lambda": 0.95,
    "clip_range": 0.2,
    "ent_coef": 0.0,
    "policy_kwargs": {"net_arch": [64, 64]},
}

#: torch threads for the learner (``--threads``): one. At 2x64 networks and batch 256 a second thread
#: saves at most a fifth of a gradient step on an idle 2-core machine and costs more than that when
#: anything else runs (``benchmarks/rl.py`` measures both), and one leaves a core to other runs
DEFAULT_THREADS = 1


def _make_env(config: dict[str, Any], single_thread: bool = False) -> Any:
    """One environment (module level, so SubprocVecEnv can pickle it). ``single_thread`` (subprocess
    environments) keeps llvmpipe and BLAS on one thread, so N environments fit N cores; it must be set
    before the renderer creates its GL context, hence here."""
    if single_thread:
        for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "LP_NUM_THREADS"):
            os.environ[var] = "1"
    import gymnasium as gym

    import droneulator.workflows.rl  # noqa: F401  (registers the environment id in a fresh subprocess)

    return gym.make(ENV_ID, config=from_dict(SimConfig, config))


def make_vec_env(
    cfg: SimConfig,
    n_envs: int = 1,
    vec: str = "auto",
    monitor: Path | None = None,
    depth: str = "raycast",
    actors: int = 1,
    agents: int = 1,
) -> Any:
    """``n_envs`` environments in a DummyVecEnv (one, or ``vec="dummy"``), a SubprocVecEnv, the batched
    env (``vec="native"``, ``depth`` from ray casting or the renderer; with ``agents`` > 1, ``n_envs``
    worlds of that many agents sharing each, one row per agent), or batched envs in ``actors`` Ray actors
    (``vec="ray"``, Ray connected), wrapped in a VecMonitor writing ``monitor`` (CSV) when given."""
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecMonitor

    kind = ("subproc" if n_envs > 1 else "dummy") if vec == "auto" else vec
    if agents > 1:
        from gymnasium.vector import AutoresetMode

        from droneulator.workflows.rl.multi import VineyardMultiVectorEnv
        from droneulator.workflows.rl.sb3 import SB3VectorEnv

        if kind != "native":
            raise ValueError("several agents per world train on the batched env (vec='native')")
        venv = SB3VectorEnv(VineyardMultiVectorEnv(n_envs, agents, cfg, depth, AutoresetMode.SAME_STEP))
    elif kind == "ray":
        from droneulator.workflows.rl.ray_vec import RayVecEnv

        venv = RayVecEnv(cfg, n_envs, actors, depth)
    elif kind == "native":
        from gymnasium.vector import AutoresetMode

        from droneulator.workflows.rl.sb3 import SB3VectorEnv
        from droneulator.workflows.rl.vector import VineyardNavVectorEnv

        venv = SB3VectorEnv(VineyardNavVectorEnv(n_envs, cfg, depth, AutoresetMode.SAME_STEP))
    elif kind == "subproc":
        factory = functools.partial(_make_env, to_dict(cfg), True)
        venv = SubprocVecEnv([factory] * n_envs, start_method="forkserver")
    elif kind == "dummy":
        venv = DummyVecEnv([functools.partial(_make_env, to_dict(cfg))] * n_envs)
    else:
        raise ValueError(f"vec must be one of {', '.join(VEC_KINDS)}, got {vec!r}")
    filename = None if monitor is None else str(monitor)
    return VecMonitor(venv, filename=filename, info_keywords=("is_success", "termination"))


def _episode_callback() -> Any:
    from stable_baselines3.common.callbacks import BaseCallback

    class EpisodeOutcomes(BaseCallback):
        """Logs the share of the last 100 episodes ending at the goal, in a collision or at the limit,
        and writes a last log row when training ends (short runs may finish no logged episode)."""

        def __init__(self) -> None:
            super().__init__()
            self.recent: deque[str] = deque(maxlen=100)

        def _on_step(self) -> bool:
            for done, info in zip(self.locals["dones"], self.locals["infos"], strict=True):
                if done:
                    self.recent.append(str(info.get("termination")))
            if self.recent:
                counts = Counter(self.recent)
                for reason in ("goal", "collision", "out_of_bounds", "time_limit"):
                    self.logger.record(f"rollout/{reason}_rate", counts[reason] / len(self.recent))
            return True

        def _on_training_end(self) -> None:
            self.logger.record("time/total_timesteps", self.num_timesteps)
            self.logger.dump(self.num_timesteps)

    return EpisodeOutcomes()


def held_out_successes(policy: Any, env: Any, seeds: list[int]) -> int:
    """Episodes of ``policy`` (deterministic) reaching the goal, one per seed, on the batched ``env``
    (``len(seeds)`` environments, NEXT_STEP autoreset: each env's first episode counts). On a multi-agent
    env (``len(seeds)`` worlds, episodes="world") an episode is a world's, a success every agent of it
    reaching its goal without touching anything."""
    import numpy as np

    team = getattr(env, "num_agents", 1)
    obs, _ = env.reset(seed=seeds)
    done = np.zeros(len(seeds), dtype=bool)
    success = np.zeros(len(seeds), dtype=bool)
    while not done.all():
        action, _ = policy.predict(obs, deterministic=True)
        obs, _, terminated, truncated, info = env.step(action)
        if team > 1:
            ended = info["world_over"][::team] & ~done
            success |= ended & info["world_success"][::team]
        else:
            ended = (terminated | truncated) & ~done
            success |= ended & info["is_success"]
        done |= ended
    return int(success.sum())


def passes(successes: int, episodes: int, target: float) -> bool:
    """Whether ``successes`` of ``episodes`` reach the share ``target`` (45 of 50 reach 0.9)."""
    return successes >= math.ceil(target * episodes - 1e-9)


def held_out_env(cfg: SimConfig, episodes: int, depth: str, agents: int = 1) -> Any:
    """The batched env that flies ``episodes`` held-out episodes at once: one vector env of that many
    worlds (of ``agents`` agents each, whose episodes are the world's)."""
    if agents > 1:
        from droneulator.workflows.rl.multi import VineyardMultiVectorEnv

        return VineyardMultiVectorEnv(episodes, agents, cfg, depth, episodes="world", encounters=0.0)
    from droneulator.workflows.rl.vector import VineyardNavVectorEnv

    return VineyardNavVectorEnv(episodes, cfg, depth)


def _success_check(
    cfg: SimConfig, every: int, target: float, depth: str, max_wall_s: float | None, seeds: list[int],
    agents: int = 1,
) -> Any:  # fmt: skip
    """A callback that checks the policy on the held-out ``seeds`` (one batched env of ``len(seeds)``
    worlds, all flown at once) every ``every`` steps and ends training once ``target`` of them succeed
    (or after ``max_wall_s`` s of training); the checks' wall time is kept apart."""
    from stable_baselines3.common.callbacks import BaseCallback

    class SuccessCheck(BaseCallback):
        def __init__(self) -> None:
            super().__init__()
            self.env = held_out_env(cfg, len(seeds), depth, agents)
            self.seeds = list(seeds)
            self.next = every
            self.check_s = 0.0
            self.history: list[dict[str, Any]] = []
            self.reached: dict[str, Any] | None = None
            self.t0 = time.perf_counter()

        def _on_step(self) -> bool:
            if max_wall_s is not None and time.perf_counter() - self.t0 - self.check_s > max_wall_s:
                return False
            if self.num_timesteps < self.next:
                return True
            self.next += every
            t = time.perf_counter()
            k = held_out_successes(self.model, self.env, self.seeds)
            self.check_s += time.perf_counter() - t
            wall = time.perf_counter() - self.t0 - self.check_s
            self.history.append(
                {"steps": self.num_timesteps, "wall_s": wall, **interval_record(k, len(self.seeds))}
            )
            low, high = self.history[-1]["success_interval_95"]
            self.logger.record("eval/held_out_successes", k)
            self.logger.record("eval/held_out_success_rate", k / len(self.seeds))
            self.logger.record("eval/held_out_success_low95", low)
            self.logger.record("eval/held_out_success_high95", high)
            if passes(k, len(self.seeds), target):
                self.reached = self.history[-1]
                return False
            return True

        def _on_training_end(self) -> None:
            self.env.close()

    return SuccessCheck()


def train(
    cfg: SimConfig | None,
    out: Path,
    steps: int = 50_000,
    seed: int = 0,
    n_envs: int = 1,
    algo: str = "sac",
    vec: str = "auto",
    checkpoint_every: int = 10_000,
    threads: int | None = None,
    progress: bool = True,
    overrides: dict[str, Any] | None = None,
    depth: str = "raycast",
    stop_at: float | None = None,
    check_every: int = 100_000,
    max_wall_s: float | None = None,
    ray_address: str | None = None,
    actors: int = 1,
    check_episodes: int = CHECK_EPISODES,
    agents: int = 1,
) -> dict[str, Any]:
    """Train ``algo`` for ``steps`` environment steps; returns (and writes) the training summary.

    ``vec="ray"``: the ``n_envs`` batched worlds are split over ``actors`` Ray actors on the cluster at
    ``ray_address`` (:class:`~droneulator.workflows.rl.ray_vec.RayVecEnv`), the learner here.

    ``overrides`` replace entries of :data:`SAC_HYPERPARAMETERS` or :data:`PPO_HYPERPARAMETERS` (e.g.
    ``learning_starts`` for a short run). Environment ``i`` is first reset with seed ``seed + i``.
    ``stop_at`` (a success share, e.g. 0.9): every ``check_every`` steps the deterministic policy flies
    ``check_episodes`` held-out episodes (:data:`CHECK_EPISODES` by default, seeds from
    :data:`~droneulator.workflows.rl.heldout.CHECK_SEED`, batched on one vector env) and training ends
    once that share reaches the goal (the summary's ``reached`` gives the steps, the training wall time
    and the success rate's 95 % interval, the checks' time left out); ``max_wall_s`` (with ``stop_at``)
    ends it after that much training time in any case. The check seeds may not meet the training seeds.
    ``agents`` > 1 (``vec="native"``): ``n_envs`` worlds of that many agents train one shared policy (one
    row per agent); a held-out episode is then a world's, a success every agent reaching its goal.
    ``algo="distil"`` (``vec="native"``, ``rl.action="ctbr"``): DAgger instead of RL
    (:func:`~droneulator.workflows.rl.distil.distil`; ``overrides`` replace entries of its
    :data:`~droneulator.workflows.rl.distil.DISTIL_HYPERPARAMETERS`); it writes ``model.zip``,
    ``monitor.csv``, ``config.json`` and ``train_summary.json``, no checkpoints or TensorBoard log.
    """
    import torch

    if algo not in ALGORITHMS:
        raise ValueError(f"unknown algorithm {algo!r}; available: {', '.join(ALGORITHMS)}")
    if steps < 1 or n_envs < 1:
        raise ValueError("steps and envs must be at least 1")
    if agents < 1 or (agents > 1 and vec != "native"):
        raise ValueError(f"agents must be at least 1, and more than one train on vec='native' (got {agents})")
    distilling = algo == "distil"
    if distilling and (vec != "native" or agents != 1):
        raise ValueError("distil trains on the batched env (--num-envs B), one agent per world")
    if stop_at is not None and not 0.0 < stop_at <= 1.0:
        raise ValueError(f"stop_at must be a share in (0, 1], got {stop_at}")
    held_out = check_seeds(check_episodes)  # refuses fewer than one
    if stop_at is not None:
        refuse_overlap(range(seed, seed + n_envs), held_out)
    if vec not in VEC_KINDS:
        raise ValueError(f"vec must be one of {', '.join(VEC_KINDS)}, got {vec!r}")
    on_ray = vec == "ray"
    if on_ray != (ray_address is not None):
        raise ValueError("vec='ray' and ray_address go together")
    if on_ray and not 1 <= actors <= n_envs:
        raise ValueError(f"need 1 to {n_envs} Ray actors (one world each at least), got {actors}")
    cfg = env_config(cfg)
    if distilling and cfg.rl.action != "ctbr":
        raise ValueError(f"distil trains a ctbr policy (--set rl.action=ctbr), not {cfg.rl.action!r}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    threads = threads or DEFAULT_THREADS
    torch.set_num_threads(threads)
    if distilling:
        from droneulator.workflows.rl.distil import DISTIL_HYPERPARAMETERS

        defaults = DISTIL_HYPERPARAMETERS
    else:
        defaults = SAC_HYPERPARAMETERS if algo == "sac" else PPO_HYPERPARAMETERS
    unknown = set(overrides or {}) - set(defaults)
    if unknown:
        raise ValueError(f"unknown {algo} hyperparameters: {', '.join(sorted(unknown))}")
    hyper = {**defaults, **(overrides or {})}
    cloning = algo == "sac" and (hyper["demonstration_bc_steps"] or hyper["demonstration_anchor"])
    if cloning and hyper["demonstrations"] <= 0:
        raise ValueError("demonstration_bc_steps and demonstration_anchor (--bc-steps, --anchor) act on "
                         "demonstrations: set demonstrations (--demonstrations N) as well")  # fmt: skip
    if algo == "sac" and vec in ("native", "ray") and "gradient_steps" not in (overrides or {}):
        hyper["gradient_steps"] = n_envs * agents  # one update per transition, as one env, train_freq 1
    if algo == "ppo":  # a minibatch never exceeds the rollout: B x n_steps transitions
        hyper["batch_size"] = min(hyper["batch_size"], hyper["n_steps"] * n_envs * agents)
    (out / "config.json").write_text(json.dumps(to_dict(cfg), indent=2))
    if distilling:
        from droneulator.workflows.rl.distil import distil

        return distil(
            cfg, out, steps, seed, n_envs, hyper, stop_at, check_every, held_out, depth, progress, max_wall_s
        )

    with contextlib.ExitStack() as stack:
        if on_ray:
            from droneulator.runtime.cluster import connect

            stack.enter_context(connect(str(ray_address)))
        return _learn(
            cfg, out, steps, seed, n_envs, algo, vec, checkpoint_every, threads, progress, hyper, depth,
            stop_at, check_every, max_wall_s, actors, held_out, agents,
        )  # fmt: skip


def demonstrated_sac(
    cfg: SimConfig, steps: int, noise: float, bc_steps: int, seed: int, anchor: float = 0.0
) -> Any:
    """SB3's SAC whose first ``steps`` env steps (counted over every env) fly the scripted teacher's
    velocity actions plus N(0, ``noise``) (clipped) instead of uniform random ones, and whose actor is
    regressed on the replay buffer's actions for ``bc_steps`` Adam steps (its mean action, squared
    error) in the last of those steps, before it flies; the buffer keeps the teacher's transitions and
    SAC learns on the reward.
    ``anchor`` > 0: from then on every actor update also descends ``anchor`` times the squared distance
    of the actor's mean action from the teacher's action on a replay batch's observations (the
    DDPGfD / TD3+BC idea with the teacher asked anew, as in DAgger), added to SAC's actor gradient
    before its optimiser steps."""
    import numpy as np
    import torch
    from stable_baselines3 import SAC

    from droneulator.workflows.rl.distil import PathTeacher
    from droneulator.workflows.rl.levels import Actuator

    if anchor < 0.0:
        raise ValueError(f"demonstration_anchor is a weight >= 0, got {anchor}")
    teacher, actuator = PathTeacher(cfg), Actuator(cfg, 1)
    rng = np.random.default_rng(seed)

    class DemonstratedSAC(SAC):
        bc_loss: float | None = None
        anchor_loss: float | None = None

        def _setup_model(self) -> None:
            super()._setup_model()
            if anchor > 0.0:  # SAC.train calls the actor optimiser's step() right after its loss's backward()
                step = self.actor.optimizer.step

                def anchored_step(*args: Any, **kwargs: Any) -> Any:
                    if self.num_timesteps >= steps:
                        self._anchor_gradient()
                    return step(*args, **kwargs)

                self.actor.optimizer.step = anchored_step

        def _sample_action(self, learning_starts: int, action_noise: Any = None, n_envs: int = 1) -> Any:
            if self.num_timesteps < steps:
                action = teacher_actions(teacher, actuator, self._last_obs)
                action = np.clip(action + rng.normal(0.0, noise, action.shape), -1.0, 1.0).astype(np.float32)
                if bc_steps > 0 and self.num_timesteps + n_envs >= steps:
                    # cloned during the last demonstration step, so that the callbacks after it (a held-out
                    # check at the hand-over) see the actor that flies next
                    self.bc_loss = self._clone(bc_steps)
                return action, action
            return super()._sample_action(learning_starts, action_noise, n_envs)

        def _cloning_loss(self, observations: Any, actions: Any) -> Any:
            mean, _, _ = self.actor.get_action_dist_params(observations)
            return ((torch.tanh(mean) - actions) ** 2).sum(dim=1).mean()

        def _clone(self, n: int) -> float:
            """``n`` Adam steps of the actor's mean action on the buffer's actions; the last loss."""
            loss = torch.zeros(())
            for _ in range(n):
                batch = self.replay_buffer.sample(self.batch_size, env=self._vec_normalize_env)
                loss = self._cloning_loss(batch.observations, batch.actions)
                self.actor.optimizer.zero_grad()
                loss.backward()
                self.actor.optimizer.step()  # not anchored: num_timesteps is still below steps
            return float(loss.detach())

        def _anchor_gradient(self) -> None:
            """Add ``anchor`` x the cloning loss on the teacher's actions to the actor's gradient."""
            batch = self.replay_buffer.sample(self.batch_size, env=self._vec_normalize_env)
            labels = torch.as_tensor(teacher_actions(teacher, actuator, batch.observations.cpu().numpy()))
            loss = self._cloning_loss(batch.observations, labels)
            (anchor * loss).backward()
            self.anchor_loss = float(loss.detach())

    return DemonstratedSAC


def teacher_actions(teacher: Any, actuator: Any, obs: Any) -> Any:
    """The teacher's velocity actions (``(B, 2)`` float32) for the observations ``obs``."""
    import numpy as np

    forward, yaw_rate = teacher(np.asarray(obs))
    return actuator.actions(np.column_stack([forward, yaw_rate]))


def _learn(
    cfg: SimConfig, out: Path, steps: int, seed: int, n_envs: int, algo: str, vec: str, checkpoint_every: int,
    threads: int, progress: bool, hyper: dict[str, Any], depth: str, stop_at: float | None, check_every: int,
    max_wall_s: float | None, actors: int, held_out: list[int], agents: int = 1,
) -> dict[str, Any]:  # fmt: skip
    """:func:`train`'s learning, once its settings are checked (and Ray connected for ``vec="ray"``)."""
    from stable_baselines3 import PPO, SAC
    from stable_baselines3.common.callbacks import CallbackList, CheckpointCallback
    from stable_baselines3.common.logger import Logger, make_output_format

    demo = {key: hyper.pop(key) for key in DEMONSTRATION_KEYS if key in hyper}
    if demo.get("demonstrations", 0) > 0 and cfg.rl.action != "velocity":
        raise ValueError(f"demonstrations fly the velocity level, not {cfg.rl.action!r}")
    venv = make_vec_env(
        cfg, n_envs, vec, monitor=out / "monitor.csv", depth=depth, actors=actors, agents=agents
    )
    restarts, nodes, ray_seeds = 0, None, []
    try:
        cls = SAC if algo == "sac" else PPO
        if demo.get("demonstrations", 0) > 0:
            cls = demonstrated_sac(
                cfg,
                demo["demonstrations"],
                demo["demonstration_noise"],
                demo["demonstration_bc_steps"],
                seed,
                demo.get("demonstration_anchor", 0.0),
            )
        model = cls("MlpPolicy", venv, seed=seed, device="cpu", verbose=0, **hyper)
        model.set_logger(
            Logger(
                str(out),
                [make_output_format("csv", str(out)), make_output_format("tensorboard", str(out / "tb"))],
            )
        )
        check = None
        if stop_at is not None:
            check = _success_check(cfg, check_every, stop_at, depth, max_wall_s, held_out, agents)
        checkpoints = CheckpointCallback(
            save_freq=max(1, checkpoint_every // n_envs), save_path=str(out / "checkpoints"), name_prefix=algo
        )
        callbacks = CallbackList([checkpoints, _episode_callback(), *([check] if check else [])])
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            # SB3 draws its progress bar with tqdm.rich, which tqdm still labels experimental
            warnings.filterwarnings("ignore", category=TqdmExperimentalWarning)
            model.learn(total_timesteps=steps, callback=callbacks, progress_bar=progress, log_interval=1)
        wall = time.perf_counter() - t0 - (check.check_s if check is not None else 0.0)
        model.save(out / "model.zip")
        model.logger.close()
        if vec == "ray":
            restarts = venv.venv.restarts
            nodes = len({node for _, node in venv.venv.where()})
            ray_seeds = venv.venv.seeds_used  # a restarted actor's worlds take fresh seeds
    finally:
        venv.close()
    summary = {
        "algo": algo,
        "env_id": ENV_ID,
        "steps": int(model.num_timesteps),
        "requested_steps": steps,
        "wall_s": wall,
        "steps_per_s": model.num_timesteps / wall,
        "sim_s": model.num_timesteps / cfg.render.camera_hz,
        "n_envs": n_envs,
        "agents": agents,
        "vec": ("subproc" if n_envs > 1 else "dummy") if vec == "auto" else vec,
        "depth": depth if vec in ("native", "ray") else "render",
        "torch_threads": threads,
        "seed": seed,
        "train_seeds": sorted({seed + i for i in range(n_envs)} | set(ray_seeds)),
        "hyperparameters": {**hyper, **demo},
        "model": str(out / "model.zip"),
    }
    if getattr(model, "bc_loss", None) is not None:
        summary["demonstration_bc_loss"] = model.bc_loss
    if getattr(model, "anchor_loss", None) is not None:
        summary["demonstration_anchor_loss"] = model.anchor_loss
    if vec == "ray":
        summary.update({"ray_actors": actors, "ray_nodes": nodes, "actor_restarts": restarts})
    if check is not None:
        summary["stop_at"] = stop_at
        summary["check_episodes"] = len(held_out)
        summary["check_seeds"] = held_out
        summary["checks"] = check.history
        summary["checks_wall_s"] = check.check_s
        summary["reached"] = check.reached
    (out / "train_summary.json").write_text(json.dumps(summary, indent=2, default=str))
    return summary
