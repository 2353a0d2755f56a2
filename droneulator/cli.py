"""The ``droneulator`` command line.

A start-up failure the user can cause (a bad ``--config`` file or ``--set`` value, an unknown scene, a
port in use, no EGL) ends in one ``droneulator: error: ...`` line on stderr before any simulator
process starts: exit status 2 for usage and configuration errors, 1 otherwise (see
:mod:`droneulator.runtime.preflight`).
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
from pathlib import Path

from droneulator.config import SimConfig
from droneulator.runtime import preflight
from droneulator.runtime.preflight import StartupError
from droneulator.runtime.spawn import CHILD_COMMAND, frozen, run_child

#: commands the PyInstaller bundle leaves out (torch, pycolmap), with the pip extra each needs
PIP_ONLY = {"train": "rl", "evaluate": "rl", "reconstruct": "colmap"}


def _add_file_args(p: argparse.ArgumentParser, example: str) -> None:
    """``--config FILE`` and repeatable ``--set KEY=VALUE`` (applied in that order over the defaults)."""
    p.add_argument("--config", default=None, help="JSON or TOML file with SimConfig fields")
    p.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help=f"override one option, e.g. {example}",
    )


def _add_config_args(p: argparse.ArgumentParser, scene_default: str | None = None) -> None:
    p.add_argument("--scene", default=scene_default, help="scene name (see `droneulator scenes`)")
    p.add_argument("--seed", type=int, default=None, help="scene and noise seed (default 0)")
    _add_file_args(p, "--set render.shadows=false --set vehicle.params=crazyflie")


def _config(args: argparse.Namespace) -> SimConfig:
    return preflight.load(args.config, args.overrides, scene=args.scene, seed=args.seed)


def _simulation_config(args: argparse.Namespace) -> SimConfig:
    """The config of an in-process simulator (snapshot, demo), checked with its output folder and EGL."""
    cfg = _config(args)
    preflight.check_simulation(cfg)
    preflight.check_output_dir(args.out)
    preflight.check_egl()
    return cfg


def cmd_scenes(args: argparse.Namespace) -> int:
    from droneulator.scenes import list_scenes

    for name, desc in list_scenes().items():
        print(f"{name:18s} {desc}")
    return 0


def cmd_snapshot(args: argparse.Namespace) -> int:
    cfg = _simulation_config(args)  # before the heavy imports: a start-up error is reported at once
    from droneulator.workflows.snapshot import snapshot

    written = snapshot(cfg, Path(args.out), altitude=args.altitude)
    for key, path in written.items():
        print(f"{key:28s} {path}")
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    cfg = _simulation_config(args)
    from droneulator.workflows.demo import run_demo

    summary = run_demo(cfg, Path(args.out), save_every=args.save_every)
    Path(args.out, "summary.json").write_text(json.dumps(summary, indent=2))
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    cfg = _config(args)
    if args.realtime:
        cfg.runtime.mode = "realtime"
    if args.api_port is not None:
        cfg.runtime.api_port = args.api_port
    if args.px4 or args.px4_instance is not None:
        defaults = SimConfig()
        cfg.px4.enabled = True
        cfg.px4.instance = args.px4_instance or 0
        # PX4's lockstep runs at 250 Hz; its SIH quad-X parameters suit PX4's default gains
        if cfg.vehicle.control_hz == defaults.vehicle.control_hz:
            cfg.vehicle.control_hz = 250.0
        if cfg.vehicle.params == defaults.vehicle.params:
            cfg.vehicle.params = "px4_quadx"
        n = cfg.px4.instance
        if n:  # one simulator per vehicle: keep the instances' ports and topics apart
            if args.api_port is None:
                cfg.runtime.api_port += n
            if cfg.bridge.listen == defaults.bridge.listen:
                cfg.bridge.listen = [f"tcp/127.0.0.1:{7448 + n}"]
            if cfg.bridge.namespace == defaults.bridge.namespace:
                cfg.bridge.namespace = f"{defaults.bridge.namespace}{n}"
    preflight.check_run(cfg)
    if args.demo:
        preflight.check_output_dir(args.out)

    from droneulator.runtime.supervisor import Supervisor

    sup = Supervisor(cfg)
    sup.install_signal_handlers()
    try:
        sup.start()
    except RuntimeError as exc:
        sup.stop()
        raise StartupError(str(exc)) from None
    if args.demo:
        from droneulator.workflows.demo_client import run_demo_client

        threading.Thread(
            target=run_demo_client, args=(cfg, Path(args.out), sup.stop_requested), daemon=True
        ).start()
    code = sup.wait(args.duration)
    if sup.failure:
        print(f"droneulator: {sup.failure}", file=sys.stderr)
    return code


def cmd_plan(args: argparse.Namespace) -> int:
    import logging
    import signal
    import threading

    from droneulator.workflows.planning.node import PlanNode, PlanNodeConfig

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    bounds = None if args.bounds is None else (tuple(args.bounds[:3]), tuple(args.bounds[3:]))
    cfg = PlanNodeConfig(zenoh=args.zenoh, namespace=args.namespace, camera=args.camera, bounds=bounds)
    done = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    with PlanNode(cfg) as node:
        if args.goal is not None:
            node.set_goal(args.goal)
        try:
            done.wait()
        except KeyboardInterrupt:
            print("droneulator plan: interrupted, closing", file=sys.stderr)
    return 0


def cmd_config(args: argparse.Namespace) -> int:
    from droneulator.config import to_dict

    print(json.dumps(to_dict(_config(args)), indent=2))
    return 0


def cmd_capture(args: argparse.Namespace) -> int:
    import signal

    from droneulator.workflows.photogrammetry.capture import capture

    cfg = _config(args)
    cap = cfg.capture
    for name in (
        "views",
        "radius",
        "altitudes",
        "arc_deg",
        "pitch_deg",
        "width",
        "height",
        "hfov_deg",
        "speed",
        "camera_hz",
        "jpeg_quality",
        "settle_position_m",
        "settle_speed_mps",
        "settle_time_s",
    ):
        value = getattr(args, name)
        if value is not None:
            setattr(cap, name, value)
    cap.__post_init__()

    def interrupt(*_: object) -> None:
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, interrupt)  # a kill stops like Ctrl-C: the views so far stay valid
    try:
        capture(cfg, Path(args.out), url=args.url, zenoh_endpoint=args.zenoh, progress=not args.no_progress)
    except KeyboardInterrupt:
        print(
            f"interrupted: the views captured so far are in {args.out}; run again to resume", file=sys.stderr
        )
        return 130
    return 0


def cmd_reconstruct(args: argparse.Namespace) -> int:
    from droneulator.workflows.photogrammetry.reconstruct import ReconstructOptions, reconstruct

    opts = ReconstructOptions(
        max_features=args.max_features,
        matcher=args.matcher,
        spatial_neighbors=args.neighbors,
        prior_position_std_m=args.prior_std,
        verification=args.verification,
        refine_rotations=args.refine_rotations,
        dense=not args.no_dense,
    )
    report = reconstruct(Path(args.dataset), opts)
    return 0 if report["registered_images"] >= 2 else 1


def _add_rl_config_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scene-seed", type=int, default=None, help="vineyard scene seed (default 0)")
    _add_file_args(p, "--set rl.heading=goal --set rl.safety_margin=0.4")


def cmd_train(args: argparse.Namespace) -> int:
    from droneulator.workflows.rl.train import train

    cfg = preflight.load(args.config, args.overrides, seed=args.scene_seed)
    overrides = {} if args.learning_starts is None else {"learning_starts": args.learning_starts}
    summary = train(
        cfg,
        Path(args.out),
        steps=args.steps,
        seed=args.seed,
        n_envs=args.envs,
        algo=args.algo,
        vec=args.vec,
        checkpoint_every=args.checkpoint_every,
        threads=args.threads,
        progress=not args.no_progress,
        overrides=overrides,
    )
    print(
        f"trained {summary['steps']} steps in {summary['wall_s']:.0f} s "
        f"({summary['steps_per_s']:.1f} steps/s, {summary['n_envs']} env(s)); model: {summary['model']}"
    )
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    from droneulator.workflows.rl.evaluate import evaluate, load_run_config, resolve_model

    model = resolve_model(args.model)
    cfg = load_run_config(model)
    if args.config or args.overrides or args.scene_seed is not None:
        base = model.parent / "config.json"
        cfg = preflight.load(
            args.config or (base if base.exists() else None), args.overrides, seed=args.scene_seed
        )
    summary = evaluate(
        model,
        episodes=args.episodes,
        seed=args.seed,
        out=Path(args.out) if args.out else None,
        cfg=cfg,
        logs=Path(args.logs) if args.logs else None,
        mode="remote" if args.url else "local",
        url=args.url,
        zenoh=args.zenoh,
        deterministic=not args.stochastic,
    )
    for i, e in enumerate(summary["per_episode"]):
        print(
            f"episode {i} (seed {e['seed']}): {e['termination']:13s} {e['sim_time_s']:6.1f} s "
            f"return {e['return']:7.1f}  path {e['shortest_path_m']:5.1f} m  flown {e['flown_m']:5.1f} m"
        )
    where = Path(summary["figures"]["trajectories"]).parent
    print(f"success rate {summary['successes']}/{summary['episodes']}; evaluation.json and figures: {where}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="droneulator", description="UAV simulator for agricultural robotics.")
    sub = ap.add_subparsers(dest="command", required=True)

    p = sub.add_parser("scenes", help="list the built-in scenes")
    p.set_defaults(func=cmd_scenes)

    p = sub.add_parser(
        "snapshot", help="save RGB, depth, segmentation and camera info from a scene's spawn pose"
    )
    _add_config_args(p, "default")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--altitude", type=float, default=1.5, help="camera height above the spawn point (m)")
    p.set_defaults(func=cmd_snapshot)

    p = sub.add_parser("demo", help="fly a short in-process demo mission, print telemetry and save frames")
    _add_config_args(p, "default")
    p.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    p.add_argument("--save-every", type=float, default=1.0, help="save one frame set every N sim seconds")
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser(
        "run",
        help="start the dynamics server, render server and ROS 2/Zenoh bridge (API ws://127.0.0.1:8765)",
    )
    _add_config_args(p, "default")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--lockstep", action="store_true", help="sim time waits for every consumer (default)")
    mode.add_argument("--realtime", action="store_true", help="pace sim time by the wall clock")
    p.add_argument("--api-port", type=int, default=None, help="WebSocket API port (default 8765)")
    p.add_argument(
        "--px4",
        action="store_true",
        help="fly from PX4 SITL: listen on TCP 4560 for PX4's simulator MAVLink (see docs/px4.md)",
    )
    p.add_argument(
        "--px4-instance",
        type=int,
        default=None,
        metavar="N",
        help="PX4 instance N: listen on TCP 4560+N (implies --px4)",
    )
    p.add_argument("--duration", type=float, default=None, help="stop after this many wall seconds")
    p.add_argument(
        "--demo",
        action="store_true",
        help="fly a short demo mission through the WebSocket API, print telemetry, save the frames "
        "received over Zenoh to --out, then stop",
    )
    p.add_argument("--out", default="out/run", help="where --demo saves frames (default out/run)")
    p.set_defaults(func=cmd_run)

    p = sub.add_parser(
        "capture",
        help="fly a circular photogrammetry capture around the scene's tree and record a COLMAP dataset",
        description="Fly rings of viewpoints around the tree over the WebSocket API, record RGB, TF poses "
        "and camera_info from the ROS 2 topics over Zenoh, and write images/, sparse_known/, poses.json/.csv "
        "and metadata.json to --out. Re-running the same command resumes an interrupted capture.",
    )
    _add_config_args(p, "tree_inspection")
    p.add_argument("--out", required=True, help="dataset folder")
    p.add_argument("--views", type=int, default=None, help="number of views, shared out between the rings")
    p.add_argument("--radius", type=float, default=None, help="orbit radius around the trunk (m)")
    p.add_argument(
        "--altitudes", type=float, nargs="+", default=None, metavar="Z", help="one ring per altitude (m)"
    )
    p.add_argument(
        "--arc", dest="arc_deg", type=float, default=None, help="arc of each ring in degrees (default 360)"
    )
    p.add_argument(
        "--pitch",
        dest="pitch_deg",
        type=float,
        default=None,
        help="camera pitch, deg down (default: aim at the crown)",
    )
    p.add_argument("--width", type=int, default=None, help="image width (px)")
    p.add_argument("--height", type=int, default=None, help="image height (px)")
    p.add_argument("--hfov", dest="hfov_deg", type=float, default=None, help="horizontal field of view (deg)")
    p.add_argument("--speed", type=float, default=None, help="peak speed of each leg (m/s)")
    p.add_argument("--camera-hz", type=float, default=None, help="camera rate while capturing (sim Hz)")
    p.add_argument("--jpeg-quality", type=int, default=None, help="JPEG quality of the published images")
    p.add_argument("--settle-position", dest="settle_position_m", type=float, default=None, help="m")
    p.add_argument("--settle-speed", dest="settle_speed_mps", type=float, default=None, help="m/s")
    p.add_argument("--settle-time", dest="settle_time_s", type=float, default=None, help="sim seconds")
    p.add_argument(
        "--url", default=None, help="use the simulator at this WebSocket URL instead of starting one"
    )
    p.add_argument(
        "--zenoh", default=None, help="with --url: Zenoh endpoint of its bridge (default tcp/127.0.0.1:7448)"
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_capture)

    p = sub.add_parser(
        "reconstruct",
        help="COLMAP reconstruction of a capture: SIFT, matching, triangulation from the known poses, "
        "bundle adjustment with pose priors (needs pycolmap: pip install droneulator[colmap])",
    )
    p.add_argument("dataset", help="a folder written by `droneulator capture`")
    p.add_argument("--max-features", type=int, default=8192, help="SIFT features per image")
    p.add_argument(
        "--matcher",
        choices=("spatial", "exhaustive"),
        default="spatial",
        help="spatial: each image with its nearest neighbours by prior position (default); "
        "exhaustive: all pairs",
    )
    p.add_argument("--neighbors", type=int, default=12, help="spatial matcher: neighbours per image")
    p.add_argument(
        "--prior-std", type=float, default=0.01, help="standard deviation of the position priors (m)"
    )
    p.add_argument(
        "--verification",
        choices=("ransac", "known_poses"),
        default="ransac",
        help="two-view verification: COLMAP's RANSAC (homographies not accepted; default) or the matches "
        "that agree with the recorded relative poses",
    )
    p.add_argument(
        "--refine-rotations", action="store_true", help="let bundle adjustment refine the camera rotations"
    )
    p.add_argument("--no-dense", action="store_true", help="skip dense stereo even where CUDA is available")
    p.set_defaults(func=cmd_reconstruct)

    p = sub.add_parser(
        "train",
        help="train SAC on droneulator/VineyardNav-v0 with Stable-Baselines3 (pip install droneulator[rl])",
        description="Train SAC on the vineyard navigation environment. Writes the final model, checkpoints, "
        "monitor.csv, progress.csv, TensorBoard logs (tb/), config.json and train_summary.json to --out.",
    )
    p.add_argument("--algo", choices=("sac",), default="sac", help="algorithm (default sac)")
    p.add_argument("--steps", type=int, default=50_000, help="environment steps (default 50000)")
    p.add_argument(
        "--seed", type=int, default=0, help="training seed: env i starts from seed + i (default 0)"
    )
    p.add_argument("--envs", type=int, default=1, help="parallel environments (default 1)")
    p.add_argument(
        "--vec",
        choices=("auto", "dummy", "subproc"),
        default="auto",
        help="vectorisation: subprocesses when --envs > 1 (auto, default), or all in this process (dummy)",
    )
    p.add_argument("--out", default="out/rl", help="run folder (default out/rl)")
    p.add_argument("--learning-starts", type=int, default=None, help="random warm-up steps (default 2000)")
    p.add_argument("--checkpoint-every", type=int, default=10_000, help="checkpoint period in steps")
    p.add_argument("--threads", type=int, default=None, help="torch threads for the learner (default 1)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    _add_rl_config_args(p)
    p.set_defaults(func=cmd_train)

    p = sub.add_parser(
        "evaluate",
        help="evaluate a trained policy on held-out seeds; writes evaluation.json and the paper's figures",
        description="Roll the policy out (deterministic actions) on seeds not used in training and write "
        "evaluation.json, trajectories.png and training_curves.png (from the run's monitor.csv).",
    )
    p.add_argument("model", help="model .zip written by `droneulator train`, or its run folder")
    p.add_argument("--episodes", type=int, default=10, help="episodes (default 10)")
    p.add_argument("--seed", type=int, default=1_000_000, help="first evaluation seed (default 1000000)")
    p.add_argument("--out", default=None, help="output folder (default: the model's folder)")
    p.add_argument("--logs", default=None, help="training run folder for the curves (default: the model's)")
    p.add_argument("--stochastic", action="store_true", help="sample actions instead of the policy mean")
    p.add_argument("--url", default=None, help="evaluate against a running `droneulator run` at this URL")
    p.add_argument("--zenoh", default=None, help="with --url: Zenoh endpoint of its bridge")
    _add_rl_config_args(p)
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser(
        "plan",
        help="run the depth-only local planner node against a running `droneulator run`",
        description="Map from the depth image, plan B-splines to goals taken on /<ns>/planner/goal "
        "(geometry_msgs/PoseStamped) and publish quadrotor_msgs/PositionCommand on /<ns>/position_cmd "
        "at 100 Hz of sim time, all over Zenoh. Never reads the scene or the WebSocket state.",
    )
    p.add_argument("--zenoh", default="tcp/127.0.0.1:7448", help="Zenoh endpoint of the run's bridge")
    p.add_argument("--namespace", default="droneulator", help="the run's ROS namespace")
    p.add_argument("--camera", default="front", help="depth camera to map from")
    p.add_argument(
        "--goal", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"), help="first goal (odom frame)"
    )
    p.add_argument(
        "--bounds",
        type=float,
        nargs=6,
        default=None,
        metavar=("XMIN", "YMIN", "ZMIN", "XMAX", "YMAX", "ZMAX"),
        help="box goals must lie in (default: the local map around the vehicle when the goal arrives)",
    )
    p.set_defaults(func=cmd_plan)

    p = sub.add_parser("config", help="print the effective configuration as JSON")
    _add_config_args(p)
    p.set_defaults(func=cmd_config)
    return ap


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == [CHILD_COMMAND]:  # hidden: how the bundle starts its child processes
        return run_child(argv[1:])
    args = build_parser().parse_args(argv)
    if frozen() and args.command in PIP_ONLY:
        print(
            f"droneulator: error: `droneulator {args.command}` is not in this bundle: it needs the pip "
            f"install (pip install 'droneulator[{PIP_ONLY[args.command]}]', or bash scripts/setup.sh --dev)",
            file=sys.stderr,
        )
        return 1
    try:
        return args.func(args)
    except StartupError as exc:
        print(f"droneulator: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except (ValueError, FileNotFoundError) as exc:
        print(f"droneulator: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
