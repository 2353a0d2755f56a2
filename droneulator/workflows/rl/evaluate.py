"""``droneulator evaluate``: roll a trained policy out on held-out seeds and draw the paper's figures.

Writes to ``out`` (default: the model's folder): ``evaluation.json`` (success rate and per-episode
outcomes), ``training_curves.png`` (episode return, length and success over training, from the
run's ``monitor.csv``) and ``trajectories.png`` (the rollouts over the vineyard's occupancy map,
coloured by time, with the forward-speed and yaw-rate commands along them).

Evaluation flies :data:`~droneulator.workflows.rl.heldout.EVAL_EPISODES` (50) episodes by default from
:data:`EVAL_SEED`, far from the training seeds (``seed`` to ``seed + envs - 1``; later training episodes
draw from those seeds' generators) and from the stop check's
(:data:`~droneulator.workflows.rl.heldout.CHECK_SEED` on): an overlap with either, as
``train_summary.json`` records them, is refused (summaries older than ``check_seeds`` give training seeds
only). The success rate comes with its 95 % Wilson interval. Actions are deterministic (the policy's
mean). A team policy (``train --agents N``) is judged by team episodes: one world of N agents per seed, a
success every agent at its goal without touching anything (the stop check's measure), drawn one colour
per agent.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from droneulator.config import SimConfig, load_config
from droneulator.workflows.rl.astar import occupancy_from_scene
from droneulator.workflows.rl.env import VineyardNavEnv, obs_size
from droneulator.workflows.rl.heldout import EVAL_EPISODES, EVAL_SEED, interval_record

#: the commands panel overlays this moving mean (s) on the per-step commands
SMOOTH_S = 0.5


@dataclass
class Rollout:
    """One evaluation episode, sampled at every environment step (the reset included)."""

    seed: int
    start: np.ndarray
    goal: np.ndarray
    initial_distance: float
    path: np.ndarray
    t: list[float] = field(default_factory=list)
    xy: list[np.ndarray] = field(default_factory=list)
    forward: list[float] = field(default_factory=list)
    yaw_rate: list[float] = field(default_factory=list)
    clearance: list[float] = field(default_factory=list)
    ret: float = 0.0
    termination: str | None = None
    #: the agent it touched (team episodes; "" for none)
    collided_with: str = ""

    def summary(self) -> dict[str, Any]:
        xy = np.array(self.xy)
        flown = float(np.linalg.norm(np.diff(xy, axis=0), axis=1).sum()) if len(xy) > 1 else 0.0
        duration = self.t[-1] - self.t[0] if self.t else 0.0
        return {
            "seed": self.seed,
            "success": self.termination == "goal",
            "termination": self.termination,
            "steps": len(self.t) - 1,
            "sim_time_s": duration,
            "return": self.ret,
            "start": [float(v) for v in self.start],
            "goal": [float(v) for v in self.goal],
            "shortest_path_m": self.initial_distance,
            "flown_m": flown,
            "path_ratio": flown / self.initial_distance if self.initial_distance > 0 else math.nan,
            "mean_speed_mps": flown / duration if duration > 0 else 0.0,
            "min_clearance_m": float(min(self.clearance)) if self.clearance else math.nan,
            **({"collided_with": self.collided_with} if self.collided_with else {}),
        }


def resolve_model(model: Path | str) -> Path:
    """A model .zip as given, or ``model.zip`` in a run folder."""
    model = Path(model)
    return model / "model.zip" if model.is_dir() else model


def load_run_config(model: Path) -> SimConfig:
    """The SimConfig the model was trained with (``config.json`` beside it), or the defaults."""
    path = Path(model).parent / "config.json"
    return load_config(path if path.exists() else None)


def _run_summary(model: Path) -> dict[str, Any]:
    path = Path(model).parent / "train_summary.json"
    return json.loads(path.read_text()) if path.exists() else {}


def training_seeds(model: Path) -> list[int]:
    """The seeds the run beside ``model`` trained on (``train_summary.json``; none without one)."""
    return [int(s) for s in _run_summary(model).get("train_seeds", [])]


def stop_check_seeds(model: Path) -> list[int]:
    """The seeds the run's stop check (``--stop-at``) or final check flew (``train_summary.json``); none
    for a run without a check or a summary older than ``check_seeds``."""
    return [int(s) for s in _run_summary(model).get("check_seeds", [])]


#: the seeds every stop check flew before they were recorded (10 from :data:`EVAL_SEED`, before 2026-11-29)
LEGACY_CHECK_SEEDS = range(EVAL_SEED, EVAL_SEED + 10)


def _legacy_warning(model: Path, seeds: list[int]) -> str | None:
    """A note when an older run (``stop_at`` but no ``check_seeds``) was stopped on some of ``seeds``."""
    run = _run_summary(model)
    if run.get("stop_at") is None or "check_seeds" in run or not set(seeds) & set(LEGACY_CHECK_SEEDS):
        return None
    return (
        f"this run predates recorded check seeds: its stop check flew seeds {EVAL_SEED} to {EVAL_SEED + 9}, "
        "some of these evaluation seeds, so this rate is not independent of when it stopped"
    )


def trained_algorithm(model: Path) -> str:
    """The algorithm ``train_summary.json`` beside the model names (``sac`` when there is none)."""
    path = Path(model).parent / "train_summary.json"
    return str(json.loads(path.read_text()).get("algo", "sac")) if path.exists() else "sac"


def rollout(env: VineyardNavEnv, policy: Any, seed: int, deterministic: bool = True) -> Rollout:
    """Run one episode with ``policy.predict`` from ``env.reset(seed=seed)``."""
    obs, info = env.reset(seed=seed)
    assert env.field is not None
    _, path = env.grid.shortest_path(env.start[:2], env.goal)
    ro = Rollout(seed, env.start.copy(), env.goal.copy(), env.initial_distance, path)
    col, radius = env.scene.collision, env.config.vehicle.collision_radius

    def record(info: dict[str, Any]) -> None:
        ro.t.append(float(info["t"]))
        ro.xy.append(np.asarray(info["position"][:2], dtype=float))
        if env.rl.action == "velocity":
            ro.forward.append(float(info["command"][0]))
            ro.yaw_rate.append(float(info["command"][1]))
        else:  # a level below velocity: the speeds flown (its commands are thrusts, rates or attitudes)
            assert env.kinematics is not None
            ro.forward.append(env.kinematics.forward_speed)
            ro.yaw_rate.append(env.kinematics.yaw_rate)
        ro.clearance.append(col.distance(np.asarray(info["position"], dtype=float)) - radius)

    record(info)
    while True:
        action, _ = policy.predict(obs, deterministic=deterministic)
        obs, reward, terminated, truncated, info = env.step(action)
        ro.ret += float(reward)
        record(info)
        if terminated or truncated:
            ro.termination = info["termination"]
            return ro


def plot_team_trajectories(
    scene: Any, grid: Any, cfg: SimConfig, teams: list[list[Rollout]], png: Path
) -> None:
    """Team episodes over the occupancy map, the failed ones drawn boldly over the successful ones (thin,
    faint, unlabelled): each agent's path in its own colour (agent 0 blue, 1 orange, ...), o start, * goal
    (gold when reached); for a failed team also its A* paths dashed, x where an agent touched the scene or
    left its bounds, a red ring where it touched another agent, a square at the time limit, and each start
    labelled world/agent."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(11, 8))
    _draw_map(ax, scene, grid, cfg.rl.altitude)
    failed = [not all(ro.termination == "goal" for ro in team) for team in teams]
    for bold in (False, True):  # the failures last, on top
        for w, team in enumerate(teams):
            if failed[w] != bold:
                continue
            for a, ro in enumerate(team):
                colour, xy = f"C{a % 10}", np.array(ro.xy)
                reached = ro.termination == "goal"
                faint = 1.0 if bold else 0.4
                ax.plot(xy[:, 0], xy[:, 1], color=colour, lw=2.0 if bold else 0.8, alpha=faint)
                ax.plot(*ro.start[:2], "o", color=colour, ms=6 if bold else 3, mec="k", alpha=faint)
                star = "gold" if reached else colour
                ax.plot(*ro.goal, "*", color=star, ms=12 if bold else 6, mec="k", alpha=faint)
                if not bold:
                    continue
                if len(ro.path):
                    ax.plot(ro.path[:, 0], ro.path[:, 1], "--", color=colour, lw=0.8)
                ax.annotate(f"{w}/{a}", ro.start[:2], textcoords="offset points", xytext=(4, 4), fontsize=8)
                if ro.collided_with:
                    ax.plot(*xy[-1], "o", ms=14, mfc="none", mec="red", mew=2)
                elif ro.termination == "time_limit":
                    ax.plot(*xy[-1], "s", color="orange", markersize=7, markeredgecolor="k")
                elif not reached:
                    ax.plot(*xy[-1], "x", color="red", markersize=10, mew=2.5)
    agents = len(teams[0]) if teams else 0
    ax.set_title(
        f"team evaluation: {len(teams) - sum(failed)}/{len(teams)} worlds with all {agents} agents at their "
        "goals (failed teams bold, labelled world/agent)\ncolour: agent; o start, * goal (gold: reached), "
        "-- A* path, x touched the scene or left it, red ring: touched another agent, square: time limit",
        fontsize=10,
    )
    fig.savefig(png, dpi=120, bbox_inches="tight")
    plt.close(fig)


def plot_training_curves(run_dir: Path, png: Path, window: int = 20) -> bool:
    """Episode return, length and success rate against environment steps from ``monitor.csv``
    (raw episodes and a ``window``-episode moving mean). False if the run has no monitor log."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import pandas as pd

    csv = Path(run_dir) / "monitor.csv"
    if not csv.exists():
        return False
    df = pd.read_csv(csv, skiprows=1)
    if df.empty:
        return False
    steps = df["l"].cumsum().to_numpy()
    success = df["is_success"].astype(str).str.lower().eq("true").astype(float)
    fig, axes = plt.subplots(3, 1, figsize=(8, 8), sharex=True)
    for ax, values, label in (
        (axes[0], df["r"].to_numpy(), "episode return"),
        (axes[1], df["l"].to_numpy(), "episode length (steps)"),
    ):
        ax.plot(steps, values, ".", color="0.65", markersize=3, label="episode")
        mean = pd.Series(values).rolling(window, min_periods=1).mean().to_numpy()
        ax.plot(steps, mean, color="C0", lw=2, label=f"mean of {window}")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        ax.legend(loc="best", fontsize=8)
    axes[2].plot(steps, success.rolling(window, min_periods=1).mean().to_numpy(), color="C2", lw=2)
    axes[2].set_ylabel(f"success rate ({window} ep.)")
    axes[2].set_ylim(-0.05, 1.05)
    axes[2].set_xlabel("environment steps")
    axes[2].grid(alpha=0.3)
    algo = trained_algorithm(Path(run_dir) / "model.zip").upper()
    fig.suptitle(f"{algo} training on VineyardNav-v0 ({len(df)} episodes, {int(steps[-1])} steps)")
    fig.tight_layout()
    fig.savefig(png, dpi=120)
    plt.close(fig)
    return True


def moving_mean(values: np.ndarray, n: int) -> np.ndarray:
    """Centred moving mean over ``n`` samples (shorter windows at the ends)."""
    if n <= 1 or len(values) == 0:
        return values
    kernel = np.ones(n)
    return np.convolve(values, kernel, "same") / np.convolve(np.ones(len(values)), kernel, "same")


def _draw_map(ax: Any, scene: Any, grid: Any, altitude: float) -> None:
    """The occupancy map on ``ax``: vine rows at flight altitude (green), the inflated margin (grey)."""
    from matplotlib.colors import ListedColormap

    solid = occupancy_from_scene(scene, altitude, 0.0, grid.resolution)
    layer = np.where(~solid.free, 2, np.where(~grid.free, 1, 0)).T
    x0, x1, y0, y1 = grid.extent()
    r = grid.resolution / 2
    cmap = ListedColormap(["white", "#d9d9d9", "#2e7d32"])
    ax.imshow(layer, origin="lower", extent=(x0 - r, x1 + r, y0 - r, y1 + r), cmap=cmap, vmin=0, vmax=2)
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")


def plot_trajectories(env: VineyardNavEnv, rollouts: list[Rollout], png: Path) -> None:
    """Rollouts over the occupancy map (vine rows at flight altitude, inflated margin lighter), each
    coloured by time, with the commands along them against time: every step in grey and their moving
    mean in the same colours as the path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection
    from matplotlib.colors import Normalize

    grid = env.grid
    t_max = max((ro.t[-1] - ro.t[0] for ro in rollouts), default=1.0) or 1.0
    smooth = max(1, round(SMOOTH_S * env.config.render.camera_hz))
    norm = Normalize(0.0, t_max)
    cmap = plt.get_cmap("viridis")

    fig = plt.figure(figsize=(15, 7.5))
    gs = fig.add_gridspec(2, 2, width_ratios=[1.45, 1.0])
    ax = fig.add_subplot(gs[:, 0])
    ax_v = fig.add_subplot(gs[0, 1])
    ax_w = fig.add_subplot(gs[1, 1], sharex=ax_v)
    _draw_map(ax, env.scene, grid, env.rl.altitude)
    for k, ro in enumerate(rollouts):
        t = np.array(ro.t) - ro.t[0]
        xy = np.array(ro.xy)
        if len(ro.path):
            ax.plot(ro.path[:, 0], ro.path[:, 1], "--", color="0.45", lw=0.8)
        seg = np.stack([xy[:-1], xy[1:]], axis=1)
        lc = LineCollection(seg, cmap=cmap, norm=norm, linewidths=2.2)
        lc.set_array(t[1:])
        ax.add_collection(lc)
        ax.plot(*ro.start[:2], "o", color="C0", markersize=7, markeredgecolor="k")
        ok = ro.termination == "goal"
        ax.plot(*ro.goal, "*", color="C3" if not ok else "gold", markersize=14, markeredgecolor="k")
        ax.add_patch(plt.Circle(tuple(ro.goal), env.rl.goal_radius, fill=False, ls=":", color="C3"))
        ax.annotate(str(k), ro.start[:2], textcoords="offset points", xytext=(5, 5), fontsize=8)
        if ro.termination == "time_limit":
            ax.plot(*xy[-1], "s", color="orange", markersize=7, markeredgecolor="k")
        elif not ok:
            ax.plot(*xy[-1], "x", color="red", markersize=10, mew=2.5)
        for axis, values in ((ax_v, ro.forward), (ax_w, ro.yaw_rate)):
            raw = np.array(values[1:])
            axis.plot(t[1:], raw, color="0.6", lw=0.4, alpha=0.5)
            pts = np.stack([t[1:], moving_mean(raw, smooth)], axis=1)
            if len(pts) > 1:
                cl = LineCollection(
                    np.stack([pts[:-1], pts[1:]], axis=1), cmap=cmap, norm=norm, linewidths=1.2
                )
                cl.set_array(t[2:])
                axis.add_collection(cl)
    n_ok = sum(ro.termination == "goal" for ro in rollouts)
    ax.set_title(
        f"evaluation: {n_ok}/{len(rollouts)} reached the goal\n"
        "o start, * goal, -- A* path, x collision, square time limit",
        fontsize=10,
    )
    rl = env.rl
    ax_v.set_ylim(rl.forward_min - 0.2, rl.forward_max + 0.2)
    what = "command" if rl.action == "velocity" else "flown"
    ax_v.set_ylabel(f"forward speed {what} (m/s)")
    ax_w.set_ylim(-rl.max_yaw_rate - 0.1, rl.max_yaw_rate + 0.1)
    ax_w.set_ylabel(f"yaw rate {what} (rad/s)")
    title = "commands" if rl.action == "velocity" else f"speeds flown ({rl.action} actions)"
    ax_v.set_title(f"{title}: each step (grey) and their {SMOOTH_S:g} s moving mean (coloured)", fontsize=10)
    ax_w.set_xlabel("time (s)")
    ax_v.set_xlim(0, t_max)
    for a in (ax_v, ax_w):
        a.grid(alpha=0.3)
    sm = plt.cm.ScalarMappable(norm=norm, cmap=cmap)
    fig.colorbar(sm, ax=[ax_v, ax_w], label="time since start (s)", fraction=0.05)
    fig.savefig(png, dpi=120, bbox_inches="tight")
    plt.close(fig)


def evaluate(
    model: Path,
    episodes: int = EVAL_EPISODES,
    seed: int = EVAL_SEED,
    out: Path | None = None,
    cfg: SimConfig | None = None,
    logs: Path | None = None,
    mode: str = "local",
    url: str | None = None,
    zenoh: str | None = None,
    deterministic: bool = True,
) -> dict[str, Any]:
    """Evaluate the SAC, PPO or distilled policy in ``model`` (a .zip, or a run folder holding
    ``model.zip``) on seeds ``seed .. seed + episodes - 1``; returns (and writes) the summary, its
    success rate with the 95 % Wilson interval (``success_interval_95``). Seeds the run trained on or
    its stop check flew are refused. ``logs`` is the training run folder for the curves (default: the
    model's). A team policy (``train --agents N``, as ``train_summary.json`` says) flies one team episode
    per seed, all at once, in the held-out multi-agent env its stop check used (its training depth): a
    success is every agent at its goal without touching anything; ``per_episode`` then lists each world's
    agents."""
    from stable_baselines3 import PPO, SAC

    model = resolve_model(model)
    if not model.exists():
        raise FileNotFoundError(f"no model at {model}")
    if episodes < 1:
        raise ValueError(f"--episodes must be at least 1, got {episodes}")
    seeds = list(range(seed, seed + episodes))
    used_by = {"in training": training_seeds(model), "by its stop check": stop_check_seeds(model)}
    for what, used in used_by.items():
        overlap = sorted(set(seeds) & set(used))
        if overlap:
            shown = str(overlap) if len(overlap) <= 5 else f"{overlap[0]}..{overlap[-1]} ({len(overlap)})"
            raise ValueError(f"evaluation seeds {shown} were used {what}: pick another --seed")
    out = Path(out) if out is not None else model.parent
    out.mkdir(parents=True, exist_ok=True)
    cfg = cfg or load_run_config(model)
    # a saved run records the n-step buffer SB3 chose for it; let SB3 choose again instead of warning
    # that the saved buffer class overrides n_steps (evaluation never samples the buffer)
    # a distilled student (``train --algo distil``) is saved as a PPO actor-critic
    policy = (PPO if trained_algorithm(model) in ("ppo", "distil") else SAC).load(
        model, device="cpu", custom_objects={"replay_buffer_class": None}
    )
    run = _run_summary(model)
    agents = int(run.get("agents", 1))
    if agents > 1:
        if mode != "local":
            raise ValueError(f"a team policy (--agents {agents}) is evaluated in this process: drop --url")
        depth = str(run.get("depth", "raycast"))
        teams, wall = _fly_teams(policy, cfg, seeds, agents, depth, deterministic, out)
        rollouts = [ro for team in teams for ro in team]
        per_episode = [_team_summary(team) for team in teams]
    else:
        wanted, flown = policy.observation_space.shape, (obs_size(cfg.rl.action),)
        if wanted != flown:
            raise ValueError(
                f"the policy in {model} observes {wanted[0]} entries, one agent's task gives {flown[0]}"
            )
        env = VineyardNavEnv(config=cfg, mode=mode, url=url, zenoh=zenoh)
        t0 = time.perf_counter()
        try:
            rollouts = [rollout(env, policy, s, deterministic) for s in seeds]
            wall = time.perf_counter() - t0
            plot_trajectories(env, rollouts, out / "trajectories.png")
        finally:
            env.close()
        per_episode = [ro.summary() for ro in rollouts]
    curves = plot_training_curves(Path(logs) if logs else model.parent, out / "training_curves.png")
    n_ok = sum(e["success"] for e in per_episode)
    flights = [ro.summary() for ro in rollouts]  # every agent's (one per episode without a team)
    ok = [e for e in flights if e["success"]]
    summary = {
        "model": str(model),
        "mode": mode,
        "agents": agents,
        "episodes": episodes,
        "seeds": seeds,
        "training_seeds": training_seeds(model),
        "stop_check_seeds": stop_check_seeds(model),
        "warning": _legacy_warning(model, seeds),
        "deterministic": deterministic,
        **interval_record(n_ok, episodes),
        "terminations": {r: sum(e["termination"] == r for e in flights) for r in _reasons(flights)},
        "mean_return": float(np.mean([e["return"] for e in flights])) if flights else 0.0,
        "mean_time_to_goal_s": float(np.mean([e["sim_time_s"] for e in ok])) if ok else None,
        "mean_speed_mps": float(np.mean([e["mean_speed_mps"] for e in ok])) if ok else None,
        "mean_path_ratio": float(np.mean([e["path_ratio"] for e in ok])) if ok else None,
        "min_clearance_m": float(min(e["min_clearance_m"] for e in flights)) if flights else None,
        "wall_s": wall,
        "figures": {
            "trajectories": str(out / "trajectories.png"),
            "training_curves": str(out / "training_curves.png") if curves else None,
        },
        "per_episode": per_episode,
    }
    (out / "evaluation.json").write_text(json.dumps(summary, indent=2))
    return summary


def _fly_teams(
    policy: Any, cfg: SimConfig, seeds: list[int], agents: int, depth: str, deterministic: bool, out: Path
) -> tuple[list[list[Rollout]], float]:
    """One team episode per seed, all at once: the held-out multi-agent env of ``len(seeds)`` worlds of
    ``agents`` (the stop check's, :func:`~droneulator.workflows.rl.train.held_out_env`: no meeting tasks,
    a world's episode ends when its last agent's does). Returns each world's agents' rollouts and the
    wall time; draws ``trajectories.png`` in ``out``."""
    from droneulator.workflows.rl.train import held_out_env

    env = held_out_env(cfg, len(seeds), depth, agents)
    try:
        wanted, flown = policy.observation_space.shape, env.single_observation_space.shape
        if wanted != flown:
            raise ValueError(f"the policy observes {wanted[0]} entries, a team of {agents} gives {flown[0]}")
        t0 = time.perf_counter()
        obs, info = env.reset(seed=seeds)
        teams = []
        for w, s in enumerate(seeds):
            team = []
            for task in env.tasks[w * agents : (w + 1) * agents]:
                _, path = env.grid.shortest_path(task.start[:2], task.goal)
                team.append(Rollout(s, task.start.copy(), task.goal.copy(), task.initial_distance, path))
            teams.append(team)
        flat = [ro for team in teams for ro in team]
        col, radius = env.scene.collision, cfg.vehicle.collision_radius
        live = np.ones(len(flat), dtype=bool)

        def record(rows: np.ndarray) -> None:
            for r in rows:
                ro, p = flat[r], np.asarray(info["position"][r], dtype=float)
                ro.t.append(float(info["t"][r]))
                ro.xy.append(p[:2].copy())
                ro.clearance.append(col.distance(p) - radius)

        record(np.arange(len(flat)))
        while live.any():
            action, _ = policy.predict(obs, deterministic=deterministic)
            obs, reward, terminated, truncated, info = env.step(action)
            rows = np.flatnonzero(live)
            record(rows)
            for r in rows:
                flat[r].ret += float(reward[r])
                if terminated[r] or truncated[r]:
                    flat[r].termination = str(info["termination"][r])
                    flat[r].collided_with = str(info["collided_with"][r])
                    live[r] = False
        wall = time.perf_counter() - t0
        plot_team_trajectories(env.scene, env.grid, cfg, teams, out / "trajectories.png")
    finally:
        env.close()
    return teams, wall


def _team_summary(team: list[Rollout]) -> dict[str, Any]:
    """A team episode: a success when every agent reached its goal (none touched anything), and each agent's
    flight."""
    flights = [ro.summary() for ro in team]
    return {
        "seed": team[0].seed,
        "success": all(e["success"] for e in flights),
        "sim_time_s": max(e["sim_time_s"] for e in flights),
        "agents": flights,
    }


def _reasons(per_episode: list[dict[str, Any]]) -> list[str]:
    return sorted({str(e["termination"]) for e in per_episode})
