"""``droneulator train --algo distil --set rl.action=ctbr``: a CTBR policy distilled from an expert by DAgger.

Reinforcement learning from scratch at ``ctbr`` learns to hover and stay (docs/rl.md). Here the policy
imitates an expert instead:

* the **teacher** (:class:`PathTeacher`) flies the task at the velocity level from the observation alone:
  it turns toward the steering target the observation's heading error points at (a carrot 2 m along the
  A* shortest path, ``rl.heading = "path"``) and slows down for large heading errors and near depth returns;
* the **expert** (:class:`CTBRExpert`) turns the teacher's (forward speed, yaw rate) into collective thrust
  and body rates from the vehicle's state, through the SE(3) position feedback and flat feed-forward of
  :class:`~droneulator.controllers.flatness.CTBRTracker`: the velocity along the current heading, the
  turn's centripetal acceleration, and the altitude ``rl.altitude`` held. Its reference is rebuilt from
  the current state every frame (no reference integrated over time, as velocity mode's is), so its
  label is a function of what the vehicle is doing now, which the student's observation holds;
* the **student** is the actor of a Stable-Baselines3 PPO ``MlpPolicy`` on the 44-entry observation
  (saved as ``model.zip``, so ``droneulator evaluate`` and PPO fine-tuning take it as they are), trained
  by DAgger (Ross et al. 2011) on the batched env: each iteration rolls out B envs for ``rollout_steps``
  frames, acting with the expert with probability ``beta`` (1 in the first iteration, then multiplied by
  ``beta_decay``) and with the student otherwise, labels every visited state with the expert's action
  (:meth:`~droneulator.workflows.rl.levels.Actuator.actions`, the inverse of the env's scaling), adds
  them to the data set, and regresses the student's mean action on all of it (mean squared error per
  action entry, each weighted by the inverse variance of the first iteration's labels: thrust and rates
  labels are a few hundredths of the airframe's range).

The stop check and the seeds are :func:`~droneulator.workflows.rl.train.train`'s: training seeds ``seed``
to ``seed + B - 1``, the check (``stop_at``) on held-out seeds from
:data:`~droneulator.workflows.rl.heldout.CHECK_SEED`, flown after the iteration that passes every
``check_every`` steps.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from droneulator.config import SimConfig
from droneulator.controllers.flatness import GRAVITY, CTBRTracker
from droneulator.state import STATE
from droneulator.workflows.rl import ENV_ID
from droneulator.workflows.rl.env import STRIP_SAMPLES, obs_size
from droneulator.workflows.rl.heldout import interval_record
from droneulator.workflows.rl.levels import Actuator
from droneulator.workflows.rl.multi import NEIGHBOUR_SIZE, NEIGHBOUR_SPEED

#: DAgger's settings (``train``'s ``overrides`` replace them): vector steps per iteration, the share of
#: expert actions in the first iteration and its decay per iteration, the student's gradient steps per
#: iteration, batch, learning rate and actor layers; the actor's log std (for fine-tuning with PPO)
DISTIL_HYPERPARAMETERS: dict[str, Any] = {
    "rollout_steps": 200,
    "beta": 1.0,
    "beta_decay": 0.5,
    "gradient_steps": 1500,
    "batch_size": 1024,
    "learning_rate": 1e-3,
    "net_arch": [256, 256],
    "log_std_init": -2.0,
}

#: the teacher's cruise speed (m/s), yaw-rate gain on the heading error (1/s), the heading error (rad) at
#: which it stops going forward, and the depth (m) of the nearest return ahead below which it slows down
TEACHER_SPEED, TURN_GAIN, STOP_HEADING, SLOW_DEPTH = 2.0, 2.0, 1.2, 1.9
#: the strip's sectors the teacher reads for returns ahead (the middle half of the 90 degree strip)
AHEAD = slice(STRIP_SAMPLES // 4, 3 * STRIP_SAMPLES // 4)
#: giving way to a neighbour (the multi-agent observation's block): it is a threat within GIVE_WAY_RANGE
#: (m) whose closest approach within GIVE_WAY_HORIZON (s), at the present relative velocity, comes
#: nearer than GIVE_WAY_MISS (m), and it is given way to when it lies within GIVE_WAY_CONE (rad) of the
#: heading: the teacher turns away from it (to the right unless it is more than GIVE_WAY_TIE rad to the
#: right: two agents meeting head on both keep right) at up to GIVE_WAY_TURN rad/s and slows to
#: GIVE_WAY_SLOW of its speed, both growing linearly from GIVE_WAY_RANGE to GIVE_WAY_NEAR m
GIVE_WAY_RANGE, GIVE_WAY_HORIZON, GIVE_WAY_MISS, GIVE_WAY_CONE, GIVE_WAY_TIE = 3.0, 2.5, 1.0, 1.75, 0.3
GIVE_WAY_TURN, GIVE_WAY_SLOW, GIVE_WAY_NEAR = 1.5, 0.3, 0.8


class PathTeacher:
    """A scripted velocity-level policy on the task's observation: yaw rate ``TURN_GAIN`` times the heading
    error (clipped to ``rl.max_yaw_rate``); forward speed ``TEACHER_SPEED``, falling linearly to 0 at a
    heading error of ``STOP_HEADING`` and scaled down (to 0.3 at most) as the nearest return ahead comes
    within ``SLOW_DEPTH``; given an observation that ends in a neighbour block (the multi-agent env's,
    :func:`~.multi.neighbour_block`), it gives way to a neighbour on a collision course (``GIVE_WAY_*``).
    Flown through :class:`CTBRExpert` it reached the goal in 50 of 50 held-out episodes (docs/rl.md); at
    the velocity level (``Actuator.actions``) in 50 of 50; in team episodes of two agents per world (SAC's
    demonstrations, :func:`~.train.demonstrated_sac`) 295 of 300 giving way, 283 of 300 on depth alone
    (every failure the two agents touching at a row end; docs/rl.md)."""

    def __init__(self, config: SimConfig) -> None:
        self.max_yaw_rate = config.rl.max_yaw_rate
        self.depth_clip = config.rl.depth_clip
        self.reach = config.rl.neighbour_range
        self.size = obs_size(config.rl.action)

    def __call__(self, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(forward speed m/s, yaw rate rad/s) for each row of ``obs`` (``(B, 35 or 44)``, or with a
        neighbour block at the end)."""
        err = np.asarray(obs[:, STRIP_SAMPLES], dtype=float) * math.pi
        forward = TEACHER_SPEED * np.clip(1.0 - np.abs(err) / STOP_HEADING, 0.0, 1.0)
        near = np.asarray(obs[:, AHEAD], dtype=float).min(axis=1) * self.depth_clip
        forward *= np.clip((near - 0.4) / (SLOW_DEPTH - 0.4), 0.3, 1.0)
        yaw_rate = TURN_GAIN * err
        if obs.shape[1] == self.size + NEIGHBOUR_SIZE:
            forward, yaw_rate = self.give_way(np.asarray(obs[:, self.size :], dtype=float), forward, yaw_rate)
        elif obs.shape[1] != self.size:
            raise ValueError(
                f"observations of {self.size} or {self.size + NEIGHBOUR_SIZE} entries, got {obs.shape[1]}"
            )
        return forward, np.clip(yaw_rate, -self.max_yaw_rate, self.max_yaw_rate)

    def give_way(
        self, block: np.ndarray, forward: np.ndarray, yaw_rate: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """``forward`` and ``yaw_rate`` giving way to the neighbours of ``block`` (the ``GIVE_WAY_*``
        rule)."""
        px, py = block[:, 1] * self.reach, block[:, 2] * self.reach
        vx, vy = block[:, 3] * NEIGHBOUR_SPEED, block[:, 4] * NEIGHBOUR_SPEED
        vv = vx * vx + vy * vy
        t = np.clip(-(px * vx + py * vy) / np.maximum(vv, 1e-6), 0.0, GIVE_WAY_HORIZON)
        miss = np.hypot(px + vx * t, py + vy * t)
        distance, bearing = np.hypot(px, py), np.arctan2(py, px)
        threat = (block[:, 0] > 0.5) & (miss < GIVE_WAY_MISS) & (distance < GIVE_WAY_RANGE)
        threat &= np.abs(bearing) < GIVE_WAY_CONE
        closeness = np.where(
            threat, np.clip((GIVE_WAY_RANGE - distance) / (GIVE_WAY_RANGE - GIVE_WAY_NEAR), 0, 1), 0
        )
        side = np.where(bearing > -GIVE_WAY_TIE, -1.0, 1.0)
        slowed = forward * (1.0 - (1.0 - GIVE_WAY_SLOW) * closeness)
        return slowed, yaw_rate + side * GIVE_WAY_TURN * closeness


class CTBRExpert:
    """The ``ctbr`` commands and actions that fly :class:`PathTeacher`'s velocity commands (module
    docstring): ``actuator`` is the env's (its airframe and scaling), ``k_att`` the tracker's attitude
    gain (1/s; the action stands for a 33 ms camera frame, so well below the rate loop's)."""

    def __init__(self, config: SimConfig, actuator: Actuator, k_att: float = 10.0) -> None:
        if actuator.level != "ctbr":
            raise ValueError(f"the expert labels the ctbr level, not {actuator.level!r}")
        self.actuator = actuator
        self.teacher = PathTeacher(config)
        self.altitude = config.rl.altitude
        af = actuator.airframe
        self.tracker = CTBRTracker(af.weight / GRAVITY, af.max_thrust, af.max_rate, k_att=k_att)

    def commands(self, obs: np.ndarray, states: np.ndarray) -> np.ndarray:
        """``(B, 4)`` thrust (N) and body rates (rad/s) for the observations ``obs`` and vehicle states
        ``states`` (``(B, STATE_SIZE)``, the same instants)."""
        forward, yaw_rate = self.teacher(obs)
        out = np.empty((len(obs), 4))
        zero = np.zeros(3)
        for b, s in enumerate(states):
            p, v, q = s[STATE.x], s[STATE.v], s[STATE.q]
            x, y, z, w = q / np.linalg.norm(q)
            yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
            c, si = math.cos(yaw), math.sin(yaw)
            u, r = forward[b], yaw_rate[b]
            reference = (
                np.array([p[0], p[1], self.altitude]),
                np.array([u * c, u * si, 0.0]),
                np.array([-u * r * si, u * r * c, 0.0]),
                zero,
                yaw,
                r,
            )
            out[b, 0], out[b, 1:] = self.tracker.command(p, v, q, reference)
        return out

    def actions(self, obs: np.ndarray, states: np.ndarray) -> np.ndarray:
        """The expert's normalised ``ctbr`` actions (``(B, 4)`` float32) for ``obs`` and ``states``."""
        return self.actuator.actions(self.commands(obs, states))


def expert_successes(cfg: SimConfig, seeds: list[int]) -> int:
    """Episodes the expert flies to the goal, one per seed, on the batched env of ``cfg`` (``ctbr``)."""
    from droneulator.workflows.rl.vector import VineyardNavVectorEnv

    env = VineyardNavVectorEnv(len(seeds), cfg)
    try:
        expert = CTBRExpert(cfg, env.actuator)
        obs, _ = env.reset(seed=seeds)
        done, success = np.zeros(len(seeds), dtype=bool), np.zeros(len(seeds), dtype=bool)
        while not done.all():
            obs, _, terminated, truncated, info = env.step(expert.actions(obs, env.states))
            ended = (terminated | truncated) & ~done
            success |= ended & info["is_success"]
            done |= ended
    finally:
        env.close()
    return int(success.sum())


def actor_mean(policy: Any, obs: Any) -> Any:
    """The mean action (a torch tensor, not clipped) of an SB3 actor-critic ``policy`` for ``obs``."""
    features = policy.extract_features(obs, policy.pi_features_extractor)
    return policy.action_net(policy.mlp_extractor.forward_actor(features))


def student_model(venv: Any, hyper: dict[str, Any], seed: int) -> Any:
    """An untrained SB3 PPO model whose actor is the student (``hyper["net_arch"]`` layers, tanh)."""
    from stable_baselines3 import PPO

    kwargs = {
        "net_arch": {"pi": list(hyper["net_arch"]), "vf": [64, 64]},
        "log_std_init": hyper["log_std_init"],
    }
    return PPO("MlpPolicy", venv, seed=seed, device="cpu", verbose=0, policy_kwargs=kwargs)


def label_weights(labels: np.ndarray) -> np.ndarray:
    """Each action entry's weight in the loss: the inverse variance of ``labels`` (floored at 1e-4)."""
    return 1.0 / np.maximum(labels.var(axis=0), 1e-4)


def regress(
    policy: Any, obs: np.ndarray, labels: np.ndarray, weights: np.ndarray, steps: int, batch: int,
    optimizer: Any, rng: np.random.Generator,
) -> float:  # fmt: skip
    """``steps`` Adam steps of the weighted squared error of the student's mean action on ``labels``,
    batches drawn uniformly from ``obs``; returns the mean loss of the last tenth of them."""
    import torch

    w = torch.as_tensor(weights, dtype=torch.float32)
    x_all, y_all = torch.from_numpy(obs), torch.from_numpy(labels)
    losses = []
    for _ in range(steps):
        idx = torch.from_numpy(rng.integers(0, len(obs), size=min(batch, len(obs))))
        loss = ((actor_mean(policy, x_all[idx]) - y_all[idx]) ** 2 * w).sum(dim=1).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(float(loss.detach()))
    return float(np.mean(losses[-max(1, steps // 10) :]))


def weighted_error(policy: Any, obs: np.ndarray, labels: np.ndarray, weights: np.ndarray) -> float:
    """The student's weighted squared error (:func:`regress`'s loss) on all of ``obs``."""
    import torch

    with torch.no_grad():
        pred = actor_mean(policy, torch.from_numpy(obs)).numpy()
    return float((((pred - labels) ** 2) * weights).sum(axis=1).mean())


def distil(
    cfg: SimConfig, out: Path, steps: int, seed: int, n_envs: int, hyper: dict[str, Any],
    stop_at: float | None, check_every: int, held_out: list[int], depth: str = "raycast",
    progress: bool = True, max_wall_s: float | None = None,
) -> dict[str, Any]:  # fmt: skip
    """DAgger for ``steps`` env steps (rounded up to whole iterations of ``n_envs`` x ``rollout_steps``) on
    ``n_envs`` batched worlds seeded ``seed + i``; writes ``model.zip``, ``monitor.csv`` and
    ``train_summary.json`` to ``out`` and returns the summary (:func:`~droneulator.workflows.rl.train.train`
    checks the arguments and calls this); ``max_wall_s`` ends it after the iteration that passes that much
    training time (the checks' left out)."""
    import torch

    from droneulator.workflows.rl.train import held_out_env, held_out_successes, make_vec_env, passes

    venv = make_vec_env(cfg, n_envs, "native", monitor=out / "monitor.csv", depth=depth)
    env = venv.venv.env  # the VineyardNavVectorEnv under the SB3 adapter and the monitor
    check_env = held_out_env(cfg, len(held_out), depth) if stop_at is not None else None
    try:
        expert = CTBRExpert(cfg, env.actuator)
        model = student_model(venv, hyper, seed)
        policy = model.policy
        optimizer = torch.optim.Adam(policy.parameters(), lr=hyper["learning_rate"])
        rng = np.random.default_rng(seed)
        per_iteration = n_envs * hyper["rollout_steps"]
        iterations = max(1, math.ceil(steps / per_iteration))
        # the data set grows by doubling: a long --steps must not allocate all of it up front
        data_obs = np.empty((per_iteration, env.single_observation_space.shape[0]), dtype=np.float32)
        data_act = np.empty((per_iteration, 4), dtype=np.float32)
        venv.seed(seed)
        obs = venv.reset()
        history: list[dict[str, Any]] = []
        checks: list[dict[str, Any]] = []
        reached, weights = None, None
        filled, check_s, next_check, label_s = 0, 0.0, check_every, 0.0
        t0 = time.perf_counter()
        for it in range(iterations):
            beta = hyper["beta"] * hyper["beta_decay"] ** it
            if filled + per_iteration > len(data_obs):
                data_obs = np.concatenate([data_obs[:filled], np.empty_like(data_obs)])
                data_act = np.concatenate([data_act[:filled], np.empty_like(data_act)])
            outcomes: list[str] = []
            for _ in range(hyper["rollout_steps"]):
                t = time.perf_counter()
                labels = expert.actions(obs, env.states)
                label_s += time.perf_counter() - t
                data_obs[filled : filled + n_envs] = obs
                data_act[filled : filled + n_envs] = labels
                filled += n_envs
                act = labels.copy()
                own = rng.random(n_envs) >= beta
                if own.any():
                    with torch.no_grad():
                        mine = actor_mean(policy, torch.from_numpy(obs[own])).clamp(-1.0, 1.0).numpy()
                    act[own] = mine
                obs, _, dones, infos = venv.step(act)
                outcomes += [str(infos[i]["termination"]) for i in np.flatnonzero(dones)]
            if weights is None:
                weights = label_weights(data_act[:filled])
            loss = regress(
                policy, data_obs[:filled], data_act[:filled], weights, hyper["gradient_steps"],
                hyper["batch_size"], optimizer, rng,
            )  # fmt: skip
            wall = time.perf_counter() - t0 - check_s
            goals = sum(o == "goal" for o in outcomes)
            history.append({
                "iteration": it, "beta": beta, "steps": filled, "wall_s": wall,
                "loss": loss, "episodes_ended": len(outcomes), "goals": goals,
            })  # fmt: skip
            if progress:
                print(
                    f"iteration {it}: beta {beta:.3f}, {filled} steps, {wall:.0f} s, loss {loss:.4f}, "
                    f"{goals}/{len(outcomes)} episodes ended at the goal",
                    flush=True,
                )
            if check_env is not None and filled >= next_check:
                next_check += check_every
                t = time.perf_counter()
                k = held_out_successes(model, check_env, held_out)
                check_s += time.perf_counter() - t
                checks.append({"steps": filled, "wall_s": wall, **interval_record(k, len(held_out))})
                if progress:
                    print(f"  held-out check: {k}/{len(held_out)}", flush=True)
                assert stop_at is not None
                if passes(k, len(held_out), stop_at):
                    reached = checks[-1]
                    break
            if max_wall_s is not None and wall > max_wall_s:
                break
        wall = time.perf_counter() - t0 - check_s
        model.num_timesteps = filled
        model.save(out / "model.zip")
    finally:
        venv.close()
        if check_env is not None:
            check_env.close()
    summary: dict[str, Any] = {
        "algo": "distil",
        "env_id": ENV_ID,
        "steps": filled,
        "requested_steps": steps,
        "wall_s": wall,
        "steps_per_s": filled / wall,
        "label_s": label_s,
        "sim_s": filled / cfg.render.camera_hz,
        "n_envs": n_envs,
        "agents": 1,
        "vec": "native",
        "depth": depth,
        "torch_threads": torch.get_num_threads(),
        "seed": seed,
        "train_seeds": list(range(seed, seed + n_envs)),
        "hyperparameters": hyper,
        "label_weights": [float(v) for v in np.asarray(weights)],
        "iterations": history,
        "model": str(out / "model.zip"),
    }
    if stop_at is not None:
        summary.update({
            "stop_at": stop_at, "check_episodes": len(held_out), "check_seeds": held_out, "checks": checks,
            "checks_wall_s": check_s, "reached": reached,
        })  # fmt: skip
    (out / "train_summary.json").write_text(json.dumps(summary, indent=2, default=str))
    return summary
