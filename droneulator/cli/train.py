"""``droneulator train``: SAC or PPO on the vineyard navigation environment (needs the rl extra), with
Stable-Baselines3 in this process or, with ``--ray``, Ray RLlib across a cluster (the ray extra)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from droneulator.cli.common import add_ray_arg, add_rl_config_args
from droneulator.config import SimConfig
from droneulator.runtime import preflight
from droneulator.workflows.rl.heldout import CHECK_EPISODES, CHECK_SEED

#: steps between ``--stop-at`` checks by default, per algorithm
CHECK_EVERY = {"sac": 10_000, "ppo": 100_000, "distil": 50_000}
#: a SAC team's defaults (``--agents`` > 1 without ``--demonstrations``): the recipe that trained teams of
#: two to 45-47 of 50 held-out team episodes in 107-172 s for three seeds (docs/rl.md): the path teacher
#: (which gives way) flies the first steps, the actor is cloned on them and anchored to it after
TEAM_RECIPE = {"demonstrations": 20_000, "demonstration_bc_steps": 5_000, "demonstration_anchor": 10.0}
#: and the share of its training tasks that send an agent against the other's route (``rl.encounters``)
TEAM_ENCOUNTERS = 0.5
#: the team recipe's flags, as said
TEAM_FLAGS = (
    f"--demonstrations {TEAM_RECIPE['demonstrations']} --bc-steps {TEAM_RECIPE['demonstration_bc_steps']} "
    f"--anchor {TEAM_RECIPE['demonstration_anchor']:g}"
)


def add(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "train",
        help="train SAC or PPO on droneulator/VineyardNav-v0 with Stable-Baselines3 (the rl extra), or on "
        "Ray RLlib with --ray (the ray extra too)",
        description="Train SAC (or PPO) on the vineyard navigation environment: single environments, or "
        "--num-envs B batched worlds in one process. Writes the final model, checkpoints, "
        "monitor.csv, progress.csv, TensorBoard logs (tb/), config.json and train_summary.json to --out. "
        "With --ray: PPO (or SAC) on Ray RLlib, --env-runners runners of --num-envs worlds each, placed "
        "by Ray over the cluster; writes checkpoint/, progress.csv, tb/ and train_summary.json; with "
        "--ray-backend sb3, Stable-Baselines3 here with the --num-envs worlds split over --env-runners Ray "
        "actors, writing what a run without --ray writes (see docs/cluster.md). --algo distil --set "
        "rl.action=ctbr --num-envs B: no RL; a ctbr policy imitating an expert by DAgger, written as "
        "model.zip (a PPO actor that evaluate reads), monitor.csv, config.json and train_summary.json, "
        "with no checkpoints, progress.csv or tb/ (docs/rl.md).",
    )
    p.add_argument(
        "--algo",
        choices=("sac", "ppo", "distil"),
        default=None,
        help="algorithm (default sac; with --ray ppo; see docs/rl.md and docs/cluster.md); distil: a ctbr "
        "policy (needs --set rl.action=ctbr and --num-envs B; not with --ray) imitating a scripted A*-path "
        "follower flown through the CTBR tracker, by DAgger (docs/rl.md, 'Does a policy learn at ctbr?')",
    )
    p.add_argument("--steps", type=int, default=50_000, help="environment steps (default 50000)")
    p.add_argument(
        "--seed", type=int, default=0, help="training seed: env i starts from seed + i (default 0)"
    )
    p.add_argument(
        "--num-envs",
        type=int,
        default=None,
        metavar="B",
        help="B batched worlds in this process (the native vector env, depth by ray casting; e.g. 16 for "
        "SAC, 256 for PPO); with --ray, in each env runner (default 64)",
    )
    p.add_argument(
        "--agents",
        type=int,
        default=1,
        metavar="N",
        help="agents sharing each of the --num-envs worlds (default 1): they see, downwash and hit each "
        "other and train one shared policy; a held-out episode is a world's, a success all of its agents "
        "at their goals, none touching. A SAC team trains with the team recipe (docs/rl.md): "
        f"{TEAM_FLAGS} unless --demonstrations is given, and rl.encounters={TEAM_ENCOUNTERS} unless --set "
        "names it (--demonstrations 0 --set rl.encounters=0: plain SAC on plain tasks)",
    )
    p.add_argument(
        "--depth",
        choices=("raycast", "render"),
        default="raycast",
        help="depth of the batched env (--num-envs): ray casting (default) or the OpenGL renderer",
    )
    p.add_argument("--envs", type=int, default=1, help="parallel single environments (default 1)")
    p.add_argument(
        "--stop-at",
        type=float,
        default=None,
        metavar="SHARE",
        help="end training once this share (e.g. 0.9) of --check-episodes held-out episodes (default "
        f"{CHECK_EPISODES}, seeds from {CHECK_SEED}, never trained on nor evaluated) reaches the goal, "
        "checked every --check-every steps (the checks' time is not counted as training time)",
    )
    p.add_argument(
        "--check-episodes",
        type=int,
        default=None,
        metavar="N",
        help=f"held-out episodes each --stop-at check flies, batched (default {CHECK_EPISODES}; with --ray, "
        "the final check's). Fewer than 50 is a weak gate: at 10 a 70 %% policy passes 9/10 about one time "
        "in seven",
    )
    p.add_argument(
        "--check-every",
        type=int,
        default=None,
        help="steps between --stop-at checks (default 10000 for SAC, 100000 for PPO, 50000 for distil, "
        "checked after the DAgger iteration that passes them)",
    )
    p.add_argument(
        "--vec",
        choices=("auto", "dummy", "subproc"),
        default="auto",
        help="vectorisation: subprocesses when --envs > 1 (auto, default), or all in this process (dummy)",
    )
    p.add_argument("--out", default="out/rl", help="run folder (default out/rl)")
    p.add_argument("--learning-starts", type=int, default=None, help="random warm-up steps (default 2000)")
    p.add_argument(
        "--demonstrations",
        type=int,
        default=None,
        metavar="N",
        help="SAC from demonstrations: the first N env steps flown by the scripted path teacher instead of "
        "random actions (velocity level; default 0: off)",
    )
    p.add_argument(
        "--bc-steps",
        type=int,
        default=None,
        metavar="K",
        help="with --demonstrations: K behaviour-cloning steps of the actor on them before it flies",
    )
    p.add_argument(
        "--anchor",
        type=float,
        default=None,
        metavar="W",
        help="with --demonstrations: after them every SAC actor update also pulls the actor's mean action "
        "towards the teacher's, weight W (default 0: off)",
    )
    p.add_argument(
        "--checkpoint-every", type=int, default=10_000, help="checkpoint period in steps (not distil)"
    )
    p.add_argument("--threads", type=int, default=None, help="torch threads for the learner (default 1)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    ray = p.add_argument_group("on a Ray cluster (the ray extra)")
    add_ray_arg(ray, "train on Ray RLlib")
    ray.add_argument(
        "--ray-backend",
        choices=("rllib", "sb3"),
        default="rllib",
        help="rllib (default): RLlib's env runners and learner; sb3: Stable-Baselines3 here, its "
        "--num-envs worlds split over --env-runners Ray actors (faster on one machine: docs/cluster.md)",
    )
    ray.add_argument(
        "--env-runners", type=int, default=1, metavar="N", help="RLlib env runners / SB3's actors (default 1)"
    )
    ray.add_argument(
        "--learners",
        type=int,
        default=0,
        metavar="N",
        help="RLlib learners as Ray actors (default 0: the learner runs in this process)",
    )
    ray.add_argument(
        "--resume", action="store_true", help="go on from --out's checkpoint to --steps in total"
    )
    add_rl_config_args(p)
    p.set_defaults(func=cmd_train)


def cmd_train(args: argparse.Namespace) -> int:
    from droneulator.workflows.rl.train import train

    if args.check_episodes is not None and args.check_episodes < 1:
        raise ValueError(f"--check-episodes must be at least 1, got {args.check_episodes}")
    rllib = args.ray is not None and args.ray_backend == "rllib"  # its final check flies them
    if args.check_episodes is not None and args.stop_at is None and not rllib:
        raise ValueError("--check-episodes goes with --stop-at (or --ray's RLlib run)")
    if args.algo == "distil" and args.ray is not None:
        raise ValueError("--algo distil trains here on the batched env (--num-envs B), not with --ray")
    cfg = preflight.load(args.config, args.overrides, seed=args.scene_seed)
    if args.ray is not None:
        return _train_on_ray(args, cfg)
    if args.resume or args.env_runners != 1 or args.learners:
        raise ValueError("--resume, --env-runners and --learners go with --ray")
    native = args.num_envs is not None
    if native and args.num_envs < 1:
        raise ValueError(f"--num-envs must be at least 1, got {args.num_envs}")
    if args.agents < 1 or (args.agents > 1 and not native):
        raise ValueError(f"--agents must be at least 1, and more than one need --num-envs, got {args.agents}")
    algo = args.algo or "sac"
    overrides = _sac_overrides(args, algo)
    if args.agents > 1 and algo == "sac":
        cfg, overrides = team_defaults(cfg, overrides, args.overrides)
    summary = train(
        cfg,
        Path(args.out),
        steps=args.steps,
        seed=args.seed,
        n_envs=args.num_envs if native else args.envs,
        algo=algo,
        vec="native" if native else args.vec,
        depth=args.depth,
        stop_at=args.stop_at,
        check_every=args.check_every or CHECK_EVERY[algo],
        check_episodes=args.check_episodes or CHECK_EPISODES,
        checkpoint_every=args.checkpoint_every,
        threads=args.threads,
        progress=not args.no_progress,
        overrides=overrides,
        agents=args.agents,
    )
    print(
        f"trained {summary['steps']} steps in {summary['wall_s']:.0f} s "
        f"({summary['steps_per_s']:.1f} steps/s, {summary['n_envs']} env(s)); model: {summary['model']}"
    )
    if args.stop_at is not None:
        _print_checks(summary, args.stop_at)
    return 0


def team_defaults(
    cfg: SimConfig, overrides: dict[str, Any], sets: list[str] | None
) -> tuple[SimConfig, dict[str, Any]]:
    """A SAC team's config and hyperparameters: :data:`TEAM_RECIPE` where ``overrides`` (the flags) give no
    ``demonstrations``, and ``rl.encounters`` :data:`TEAM_ENCOUNTERS` where no ``--set`` (``sets``) names it
    and the config leaves it at 0; says what it chose."""
    chosen = []
    if "demonstrations" not in overrides:
        overrides = {**TEAM_RECIPE, **overrides}  # --bc-steps or --anchor given alone still count
        o = overrides
        chosen.append(
            f"--demonstrations {o['demonstrations']} --bc-steps {o['demonstration_bc_steps']} "
            f"--anchor {o['demonstration_anchor']:g}"
        )
    named = any(s.split("=", 1)[0].strip() == "rl.encounters" for s in sets or [])
    if not named and cfg.rl.encounters == 0.0:  # neither a --set nor a --config file chose a share
        cfg.rl.encounters = TEAM_ENCOUNTERS
        chosen.append(f"rl.encounters={TEAM_ENCOUNTERS}")
    if chosen:
        print(f"a team of SAC agents: {' and '.join(chosen)} (the team recipe, docs/rl.md)")
    return cfg, overrides


def _print_checks(summary: dict[str, Any], stop_at: float) -> None:
    """The stop check's line: the rate that stopped training (or the last one), with its 95 % interval."""
    from droneulator.workflows.rl.heldout import rate_text

    n, seeds = summary["check_episodes"], summary["check_seeds"]
    where = f"held-out episodes (seeds {seeds[0]}-{seeds[-1]})"
    reached, checks = summary["reached"], summary["checks"]
    if reached:
        print(
            f"{rate_text(reached['successes'], n)} {where} reached the goal after {reached['steps']} steps, "
            f"{reached['wall_s']:.0f} s of training"
        )
    elif checks:
        last = checks[-1]
        print(
            f"the policy never reached {stop_at:.0%} of {n} {where}; last check: "
            f"{rate_text(last['successes'], n)} after {last['steps']} steps"
        )
    else:
        print(f"the policy never reached {stop_at:.0%} of {n} {where}: no check ran")


def _train_on_ray(args: argparse.Namespace, cfg: SimConfig) -> int:
    from droneulator.runtime.cluster import check_address
    from droneulator.workflows.rl.heldout import rate_text
    from droneulator.workflows.rl.rllib import train_on_ray

    check_address(args.ray)
    if args.ray_backend == "sb3":
        return _train_sb3_on_ray(args, cfg)
    ignored = [
        name
        for name, given in (
            ("--stop-at", args.stop_at is not None),
            ("--envs", args.envs != 1),
            ("--vec", args.vec != "auto"),
            ("--learning-starts", args.learning_starts is not None),
            ("--threads", args.threads is not None),
        )
        if given
    ]
    if ignored:
        raise ValueError(f"{', '.join(ignored)}: not with --ray (see droneulator train --help)")
    summary = train_on_ray(
        cfg,
        Path(args.out),
        address=args.ray,
        steps=args.steps,
        seed=args.seed,
        algo=args.algo or "ppo",
        env_runners=args.env_runners,
        num_envs=args.num_envs or 64,
        depth=args.depth,
        learners=args.learners,
        checkpoint_every=args.checkpoint_every,
        resume=args.resume,
        progress=not args.no_progress,
        check_episodes=args.check_episodes or CHECK_EPISODES,
    )
    print(
        f"trained {summary['steps']} steps in {summary['wall_s']:.0f} s "
        f"({summary['steps_per_s']:.0f} steps/s, {summary['env_runners']} env runner(s) x "
        f"{summary['num_envs_per_env_runner']} worlds on "
        f"{summary['ray_nodes']} Ray node(s)); "
        f"{rate_text(summary['held_out_successes'], summary['held_out_episodes'])} held-out episodes reached "
        f"the goal; checkpoint: {summary['checkpoint']}"
    )
    return 0


def _train_sb3_on_ray(args: argparse.Namespace, cfg: SimConfig) -> int:
    """``--ray-backend sb3``: Stable-Baselines3 here, the batched worlds in Ray actors."""
    from droneulator.workflows.rl.train import train

    ignored = [
        name
        for name, given in (("--resume", args.resume), ("--learners", bool(args.learners)),
                            ("--envs", args.envs != 1), ("--vec", args.vec != "auto"))
        if given
    ]  # fmt: skip
    if ignored:
        raise ValueError(f"{', '.join(ignored)}: not with --ray-backend sb3 (see droneulator train --help)")
    algo = args.algo or "ppo"
    overrides = _sac_overrides(args, algo)
    worlds = args.num_envs or 64
    if not 1 <= args.env_runners <= worlds:
        raise ValueError(f"--env-runners must be between 1 and --num-envs ({worlds}), got {args.env_runners}")
    summary = train(
        cfg, Path(args.out), steps=args.steps, seed=args.seed, n_envs=worlds, algo=algo, vec="ray",
        depth=args.depth, stop_at=args.stop_at,
        check_every=args.check_every or (10_000 if algo == "sac" else 100_000),
        check_episodes=args.check_episodes or CHECK_EPISODES, checkpoint_every=args.checkpoint_every,
        threads=args.threads, progress=not args.no_progress,
        overrides=overrides, ray_address=args.ray, actors=args.env_runners,
    )  # fmt: skip
    print(
        f"trained {summary['steps']} steps in {summary['wall_s']:.0f} s "
        f"({summary['steps_per_s']:.0f} steps/s, {worlds} worlds in {summary['ray_actors']} Ray actor(s) "
        f"on {summary['ray_nodes']} node(s), {summary['actor_restarts']} restarted); "
        f"model: {summary['model']}"
    )
    if args.stop_at is not None:
        _print_checks(summary, args.stop_at)
    return 0


#: the train command's SAC-only flags and the :data:`~droneulator.workflows.rl.train.SAC_HYPERPARAMETERS`
#: entry each sets
SAC_FLAGS = {
    "learning_starts": "learning_starts",
    "demonstrations": "demonstrations",
    "bc_steps": "demonstration_bc_steps",
    "anchor": "demonstration_anchor",
}


def _sac_overrides(args: argparse.Namespace, algo: str) -> dict[str, Any]:
    """The SAC hyperparameters the SAC-only flags set; a clear error when they meet another algorithm."""
    given = {key: getattr(args, flag) for flag, key in SAC_FLAGS.items()}
    overrides = {key: value for key, value in given.items() if value is not None}
    if overrides and algo != "sac":
        flags = ", ".join("--" + flag.replace("_", "-") for flag in SAC_FLAGS)
        raise ValueError(f"{flags} are SAC settings, not {algo}'s")
    return overrides
