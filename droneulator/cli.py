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
    if args.ui_port is not None:
        cfg.ui.port = args.ui_port
    preflight.check_run(cfg)
    if args.demo:
        preflight.check_output_dir(args.out)
    if args.record:
        _check_bag_output(args.record, "--record")

    from droneulator.runtime.supervisor import Supervisor

    sup = Supervisor(cfg)
    sup.install_signal_handlers()
    recorder = None
    if args.record:
        from droneulator.recording.recorder import Recorder, run_recorder_config

        rec_cfg = run_recorder_config(cfg.bridge, sup.zenoh_endpoint, args.compression)
        recorder = Recorder(args.record, rec_cfg)
    try:
        # the recorder subscribes once the dynamics server's Zenoh session is up and before the render
        # server and the bridge start, so it sees the first /clock of the run (the clock starts with them)
        sup.start(on_hub_ready=recorder.start if recorder is not None else None)
    except (RuntimeError, ConnectionError) as exc:
        sup.stop()
        if recorder is not None and recorder.started:
            recorder.close()
        raise StartupError(str(exc)) from None
    ui = None
    if args.ui or args.ui_port is not None:
        ui = _start_ui(cfg, sup)
    if args.demo:
        from droneulator.workflows.demo_client import run_demo_client

        threading.Thread(
            target=run_demo_client, args=(cfg, Path(args.out), sup.stop_requested), daemon=True
        ).start()
    try:
        code = sup.wait(args.duration)
    finally:
        if recorder is not None:
            _report_recording(recorder.close())
        if ui is not None:
            ui.stop()
    if sup.failure:
        print(f"droneulator: {sup.failure}", file=sys.stderr)
    return code


def _check_bag_output(path: str, option: str) -> None:
    from droneulator.recording.bag import check_output

    try:
        check_output(path)
    except ValueError as exc:
        raise StartupError(f"{option}: {exc}", preflight.USAGE) from None


def _report_recording(stats: object) -> None:
    from droneulator.recording.recorder import RecordingStats

    assert isinstance(stats, RecordingStats)
    total = sum(stats.written.values())
    print(
        f"recorded {total} messages on {len(stats.written)} topics to {stats.path} "
        f"({stats.bytes / 1e6:.1f} MB)",
        flush=True,
    )
    for topic, n in sorted(stats.written.items()):
        print(f"  {n:8d}  {topic}", flush=True)
    for topic, n in sorted(stats.untyped.items()):
        print(f"  {n:8d}  {topic}  NOT RECORDED: its type was never announced", flush=True)


def cmd_record(args: argparse.Namespace) -> int:
    import signal

    from droneulator.recording.recorder import Recorder, RecorderConfig

    try:
        cfg = RecorderConfig(
            connect=tuple(args.zenoh),
            namespace=args.namespace,
            key_mode=args.key_mode,
            domain_id=args.domain_id,
            ros2dds_namespace=args.ros2dds_namespace,
            compression=args.compression,
        )
    except ValueError as exc:
        raise StartupError(str(exc), preflight.USAGE) from None
    _check_bag_output(args.out, "-o")
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    recorder = Recorder(args.out, cfg)
    try:
        recorder.start()
    except ConnectionError as exc:
        raise StartupError(str(exc)) from None
    print(f"recording {', '.join(recorder.key_expressions())} to {args.out}; Ctrl-C stops", flush=True)
    stop.wait(args.duration)
    _report_recording(recorder.close())
    return 0


def cmd_replay(args: argparse.Namespace) -> int:
    import signal

    from droneulator.recording.replay import ReplayConfig, replay

    cfg = ReplayConfig(
        listen=tuple(args.zenoh),
        connect=tuple(args.connect),
        key_mode=args.key_mode,
        domain_id=args.domain_id,
        ros2dds_namespace=args.ros2dds_namespace,
        rate=args.rate,
        wait_subscriber_s=args.wait_subscriber,
    )
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    where = ", ".join(cfg.listen) or "no listen endpoint"
    print(f"replaying {args.bag} at {args.rate:g}x on {where}", flush=True)
    try:
        counts = replay(args.bag, cfg, stop)
    except ConnectionError as exc:
        raise StartupError(str(exc)) from None
    done = "interrupted: " if stop.is_set() else ""
    print(f"{done}published {sum(counts.values())} messages", flush=True)
    for topic, n in sorted(counts.items()):
        print(f"  {n:8d}  {topic}", flush=True)
    return 130 if stop.is_set() else 0


def _ui_zenoh_endpoint(cfg: SimConfig) -> str:
    """Where a UI in this process reaches the run's Zenoh router: its first TCP listen endpoint."""
    tcp = [e for e in cfg.bridge.listen if e.startswith("tcp/")]
    if not tcp:
        raise StartupError(f"--ui needs a tcp/ endpoint in bridge.listen, got {cfg.bridge.listen}")
    return tcp[0].replace("tcp/0.0.0.0:", "tcp/127.0.0.1:").replace("tcp/[::]:", "tcp/127.0.0.1:")


def _start_ui(cfg: SimConfig, sup: object) -> object:
    """Start the browser UI on a thread of this process, once the simulator is up; prints its URL."""
    from droneulator.ui.server import UIServer

    host = cfg.runtime.api_host if cfg.runtime.api_host not in ("0.0.0.0", "::") else "127.0.0.1"
    server = UIServer(
        f"ws://{host}:{cfg.runtime.api_port}",
        _ui_zenoh_endpoint(cfg),
        cfg.ui,
        cfg.bridge,
        px4=cfg.px4.enabled,
    )
    try:
        url = server.start_in_thread()
    except OSError as exc:
        sup.stop()  # type: ignore[attr-defined]
        raise StartupError(
            f"cannot start the UI on {cfg.ui.host}:{cfg.ui.port}: {exc.strerror or exc}"
        ) from None
    print(f"UI: {url}", flush=True)
    return server


def cmd_ui(args: argparse.Namespace) -> int:
    cfg = preflight.load(args.config, args.overrides)
    if args.host is not None:
        cfg.ui.host = args.host
    if args.port is not None:
        cfg.ui.port = args.port
    cfg.ui.__post_init__()
    from droneulator.ui.server import UIServer, run_ui

    server = UIServer(args.url, args.zenoh, cfg.ui, cfg.bridge, namespace=args.namespace, px4=args.px4)
    try:
        return run_ui(server, lambda line: print(line, flush=True))
    except OSError as exc:
        raise StartupError(
            f"cannot start the UI on {cfg.ui.host}:{cfg.ui.port}: {exc.strerror or exc}"
        ) from None


def cmd_plan(args: argparse.Namespace) -> int:
    import contextlib
    import logging
    import signal
    import threading

    from droneulator.workflows.planning.config import PlannerConfig
    from droneulator.workflows.planning.node import PlanNode, PlanNodeConfig

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    if args.verbose:
        logging.getLogger("droneulator").setLevel(logging.DEBUG)
    bounds = None if args.bounds is None else (tuple(args.bounds[:3]), tuple(args.bounds[3:]))
    cfg = PlanNodeConfig(zenoh=args.zenoh, namespace=args.namespace, camera=args.camera, bounds=bounds)
    try:
        planner = PlannerConfig(
            ceiling=args.ceiling,
            floor=args.floor,
            max_vel=args.max_vel,
            max_acc=args.max_acc,
            inflation_margin=args.margin,
        )
    except ValueError as exc:
        raise SystemExit(f"droneulator: error: {exc}") from None
    done = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    with contextlib.ExitStack() as stack:
        autopilot = None
        if args.px4 or args.px4_instance is not None:
            from droneulator.workflows.planning.offboard import OffboardConfig, OffboardLink

            home = {}
            if args.px4_home is not None:
                home = dict(zip(("home_lat_deg", "home_lon_deg", "home_alt_m"), args.px4_home, strict=True))
            origin = None if args.px4_origin is None else tuple(args.px4_origin)
            link_cfg = OffboardConfig(
                host=args.px4_host,
                instance=args.px4_instance or 0,
                on_stop=args.px4_on_stop,
                origin_enu=origin,
                **home,
            )
            autopilot = stack.enter_context(OffboardLink(link_cfg))
        node = stack.enter_context(PlanNode(cfg, planner, autopilot=autopilot))
        if args.goal is not None:
            node.set_goal(args.goal)
        try:
            done.wait()
        except KeyboardInterrupt:
            print("droneulator plan: interrupted, closing", file=sys.stderr)
    if args.stats:
        import json
        from pathlib import Path

        Path(args.stats).write_text(json.dumps(node.stats(), indent=1))
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
    from droneulator.workflows.photogrammetry.dense import DenseOptions
    from droneulator.workflows.photogrammetry.mvs import MvsOptions
    from droneulator.workflows.photogrammetry.reconstruct import ReconstructOptions, reconstruct

    mvs = MvsOptions() if args.dense_scale is None else MvsOptions(scale=args.dense_scale)
    dense = DenseOptions(mvs=mvs, mask=args.dense_mask, path="cpu" if args.cpu_dense else "auto")
    opts = ReconstructOptions(
        mask=args.mask,
        dense_options=dense,
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


def cmd_score(args: argparse.Namespace) -> int:
    import json

    from droneulator.workflows.photogrammetry.reconstruct import report_markdown
    from droneulator.workflows.photogrammetry.score import score, score_markdown

    dataset = Path(args.dataset)
    result = score(dataset, spacing=args.spacing, radius=args.radius)
    report_path = dataset / "report.json"
    if report_path.is_file():  # keep report.md whole: the reconstruction's figures and this score
        report = json.loads(report_path.read_text())
        report["score"] = result
        report_path.write_text(json.dumps(report, indent=1))
        (dataset / "report.md").write_text(report_markdown(report))
    print(score_markdown(result))
    return 0


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


def _add_compression_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--compression",
        choices=("zstd", "lz4", "none"),
        default="zstd",
        help="MCAP chunk compression of the bag (default zstd)",
    )


def _add_key_mode_args(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--key-mode", choices=("ros2dds", "rmw_zenoh"), default="ros2dds", help="the run's bridge.key_mode"
    )
    p.add_argument("--domain-id", type=int, default=0, help="rmw_zenoh key mode: the ROS domain id")
    p.add_argument(
        "--ros2dds-namespace", default="/", help="ros2dds key mode: the run's bridge.ros2dds_namespace"
    )


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
    p.add_argument(
        "--record",
        default=None,
        metavar="BAG",
        help="record every ROS 2 message of the run to this MCAP bag (a .mcap file, or a bag directory "
        "like `ros2 bag record -o`); see docs/recording.md",
    )
    _add_compression_arg(p)
    p.add_argument(
        "--ui", action="store_true", help="also serve the browser UI (http://127.0.0.1:8080, see docs/ui.md)"
    )
    p.add_argument("--ui-port", type=int, default=None, help="browser UI port (implies --ui; default 8080)")
    p.set_defaults(func=cmd_run)

    p = sub.add_parser(
        "ui",
        help="serve the browser UI for a running simulator (http://127.0.0.1:8080)",
        description="Level select, live camera views, a map with click-to-fly and telemetry in the browser, "
        "for the `droneulator run` whose API is at --url and whose Zenoh router is at --zenoh.",
    )
    p.add_argument("--url", default="ws://127.0.0.1:8765", help="the simulator's WebSocket API")
    p.add_argument("--zenoh", default="tcp/127.0.0.1:7448", help="Zenoh endpoint of the run's bridge")
    p.add_argument("--namespace", default=None, help="the run's ROS namespace (default droneulator)")
    p.add_argument("--host", default=None, help="address to serve on (default 127.0.0.1: this machine only)")
    p.add_argument("--port", type=int, default=None, help="port to serve on (default 8080)")
    p.add_argument("--px4", action="store_true", help="the run flies with --px4: show PX4's status")
    _add_file_args(p, "--set ui.image_hz=5 --set bridge.key_mode=rmw_zenoh")
    p.set_defaults(func=cmd_ui)


    p = sub.add_parser(
        "record",
        help="record a running simulator's ROS 2 topics from Zenoh to an MCAP bag (ros2 bag format)",
        description="Subscribe to /clock, /tf, /tf_static and /<namespace>/** on Zenoh and write every "
        "message (same CDR bytes, sim-time log times) to a ROS 2 MCAP bag until Ctrl-C.",
    )
    p.add_argument("-o", "--out", required=True, help="bag to write: out.mcap, or a bag directory name")
    p.add_argument(
        "--zenoh",
        action="append",
        default=None,
        metavar="ENDPOINT",
        help="Zenoh endpoint of the run (its bridge.listen; default tcp/127.0.0.1:7448; repeatable)",
    )
    _add_key_mode_args(p)
    p.add_argument("--namespace", default="droneulator", help="the run's ROS namespace (bridge.namespace)")
    p.add_argument("--duration", type=float, default=None, help="stop after this many wall seconds")
    _add_compression_arg(p)
    p.set_defaults(func=cmd_record)

    p = sub.add_parser(
        "replay",
        help="republish an MCAP bag on Zenoh at the recorded rate, in the simulator's place",
        description="Publish every message of a ROS 2 MCAP bag on Zenoh under the keys the simulator "
        "uses, in log-time order, paced at --rate times the recorded rate.",
    )
    p.add_argument("bag", help="a .mcap file or a bag directory")
    p.add_argument("--rate", type=float, default=1.0, help="playback speed (default 1: recorded rate)")
    p.add_argument(
        "--zenoh",
        action="append",
        default=None,
        metavar="ENDPOINT",
        help="listen here, like the simulator (default tcp/127.0.0.1:7448; repeatable)",
    )
    p.add_argument(
        "--connect", action="append", default=[], metavar="ENDPOINT", help="also connect to this endpoint"
    )
    _add_key_mode_args(p)
    p.add_argument(
        "--wait-subscriber",
        type=float,
        default=0.0,
        metavar="S",
        help="wait up to S seconds for a subscriber before the first message (default 0)",
    )
    p.set_defaults(func=cmd_replay)

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
    p.add_argument("--no-dense", action="store_true", help="skip dense reconstruction")
    p.add_argument(
        "--mask",
        choices=("tree", "none"),
        default="tree",
        help="SIFT on the tree's pixels only (the recorded segmentation; default) or on whole images",
    )
    p.add_argument(
        "--dense-mask",
        choices=("tree", "none"),
        default="tree",
        help="CPU dense stereo on the tree's pixels only (default) or on whole images",
    )
    p.add_argument(
        "--dense-scale",
        type=float,
        default=None,
        help="CPU dense stereo image scale (default: MvsOptions.scale, 0.75)",
    )
    p.add_argument(
        "--cpu-dense", action="store_true", help="the CPU plane sweep even where pycolmap has CUDA"
    )
    p.set_defaults(func=cmd_reconstruct)

    p = sub.add_parser(
        "score",
        help="score a reconstruction against the true tree the capture recorded: accuracy (median, p90) "
        "and completeness, sparse and dense, tree and ground",
    )
    p.add_argument("dataset", help="a folder written by `droneulator capture` and `droneulator reconstruct`")
    p.add_argument("--spacing", type=float, default=0.02, help="true-surface sample spacing (m)")
    p.add_argument("--radius", type=float, default=0.05, help="completeness radius (m)")
    p.set_defaults(func=cmd_score)

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
    from droneulator.workflows.planning.config import PlannerConfig

    defaults = PlannerConfig()
    p.add_argument(
        "--ceiling", type=float, default=None, metavar="Z", help="virtual ceiling (world z, m), as EGO's"
    )
    p.add_argument("--floor", type=float, default=None, metavar="Z", help="virtual floor (world z, m)")
    p.add_argument(
        "--margin",
        type=float,
        default=defaults.inflation_margin,
        help=f"obstacles are inflated by the vehicle radius ({defaults.vehicle_radius} m) plus this (m)",
    )
    p.add_argument("--max-vel", type=float, default=defaults.max_vel, help="planning speed limit (m/s)")
    p.add_argument("--max-acc", type=float, default=defaults.max_acc, help="planning accel. limit (m/s²)")
    p.add_argument(
        "--stats",
        default=None,
        metavar="FILE",
        help="on exit, write plan/map-update times and counters as JSON",
    )
    p.add_argument("-v", "--verbose", action="store_true", help="log every plan (debug level)")
    p.add_argument(
        "--px4",
        action="store_true",
        help="fly PX4 SITL in OFFBOARD (SET_POSITION_TARGET_LOCAL_NED on UDP 14540+N) instead of "
        "publishing PositionCommand: a goal makes PX4 hold where it is in OFFBOARD, then the planner "
        "plans, checks arrival and tracking on PX4's own position estimate; see docs/planning.md",
    )
    p.add_argument("--px4-instance", type=int, default=None, metavar="N", help="PX4 instance (implies --px4)")
    p.add_argument("--px4-host", default="127.0.0.1", help="address to bind PX4's offboard UDP port on")
    p.add_argument(
        "--px4-origin",
        type=float,
        nargs=3,
        default=None,
        metavar=("X", "Y", "Z"),
        help="world (ENU) position of PX4's local NED origin (default: PX4's GPS_GLOBAL_ORIGIN and the home)",
    )
    p.add_argument(
        "--px4-home",
        type=float,
        nargs=3,
        default=None,
        metavar=("LAT", "LON", "ALT"),
        help="geodetic point of the run's world origin if the run changed px4.home_* (default: the defaults)",
    )
    p.add_argument(
        "--px4-on-stop",
        choices=("hold", "loiter", "land"),
        default="hold",
        help="when setpoints stop: keep streaming the last position (hold) or switch PX4 to AUTO.LOITER/LAND",
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
    if getattr(args, "zenoh", "") is None and args.command in ("record", "replay"):
        args.zenoh = ["tcp/127.0.0.1:7448"]
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
