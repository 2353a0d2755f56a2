"""``droneulator run``: the dynamics server, render server and bridge as child processes (flown by PX4
SITL with ``--px4``, by ArduPilot SITL with ``--ardupilot``); the recorder, the browser UI and the demo
client run in this process."""

from __future__ import annotations

import argparse
import sys
import threading
from pathlib import Path
from typing import TYPE_CHECKING

from droneulator.cli.common import (
    add_bag_split_args,
    add_compression_arg,
    add_config_args,
    check_bag_output,
    config_from_args,
    report_recording,
)
from droneulator.config import SimConfig
from droneulator.logs import say
from droneulator.runtime import preflight
from droneulator.runtime.preflight import StartupError

if TYPE_CHECKING:
    from droneulator.runtime.supervisor import Supervisor
    from droneulator.ui.server import UIServer


def add(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "run",
        help="start the dynamics server, render server and ROS 2/Zenoh bridge (API ws://127.0.0.1:8765)",
    )
    add_config_args(p, "default", fleet=True)
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--lockstep", action="store_true", help="sim time waits for every consumer (default)")
    mode.add_argument("--realtime", action="store_true", help="pace sim time by the wall clock")
    p.add_argument("--api-port", type=int, default=None, help="WebSocket API port (default 8765)")
    p.add_argument(
        "--px4",
        action="store_true",
        help="fly the first vehicle from PX4 SITL: listen on TCP 4560 for PX4's simulator MAVLink; in a "
        "fleet, vehicles with controlled_by: px4 in the config are flown by PX4 instance k (their index) on "
        "4560+k without this flag (see docs/px4.md)",
    )
    p.add_argument(
        "--px4-instance",
        type=int,
        default=None,
        metavar="N",
        help="PX4 instance N: listen on TCP 4560+N (implies --px4)",
    )
    p.add_argument(
        "--ardupilot",
        action="store_true",
        help="fly the first vehicle from ArduPilot SITL (arducopter --model JSON): answer its servo packets "
        "on UDP 9002; in a fleet, vehicles with controlled_by: ardupilot in the config are flown by "
        "ArduPilot instance k (their index, arducopter -I k) on 9002+10k without this flag "
        "(see docs/ardupilot.md)",
    )
    p.add_argument(
        "--ardupilot-instance",
        type=int,
        default=None,
        metavar="N",
        help="ArduPilot instance N (arducopter -I N): answer on UDP 9002+10N (implies --ardupilot)",
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
    add_compression_arg(p)
    add_bag_split_args(p, "with --record: ")
    p.add_argument(
        "--ui", action="store_true", help="also serve the browser UI (http://127.0.0.1:8080, see docs/ui.md)"
    )
    p.add_argument("--ui-port", type=int, default=None, help="browser UI port (implies --ui; default 8080)")
    p.set_defaults(func=cmd_run)


def cmd_run(args: argparse.Namespace) -> int:
    cfg = config_from_args(args)
    if args.realtime:
        cfg.runtime.mode = "realtime"
    if args.api_port is not None:
        cfg.runtime.api_port = args.api_port
    defaults = SimConfig()
    if args.px4 or args.px4_instance is not None:
        cfg.px4.enabled = True
        cfg.px4.instance = args.px4_instance or 0
    if args.ardupilot or args.ardupilot_instance is not None:
        if cfg.px4.enabled:
            raise StartupError(
                "--px4 and --ardupilot: both would fly the first vehicle; for a mixed fleet name each "
                "vehicle's autopilot in the config's vehicles list (controlled_by: px4 / ardupilot)",
                preflight.USAGE,
            )
        cfg.ardupilot.enabled = True
        cfg.ardupilot.instance = args.ardupilot_instance or 0
    try:
        cfg.check_autopilots()
    except ValueError as exc:
        raise StartupError(str(exc), preflight.USAGE) from exc
    if cfg.px4_instances():
        # PX4's lockstep runs at 250 Hz; its SIH quad-X parameters suit PX4's default gains. Beside
        # ArduPilot (whose IMU must beat 1.8 x its 400 Hz loop) the world steps at 1000 Hz and PX4 is
        # sent its sensor data every 4th step
        if cfg.vehicle.control_hz == defaults.vehicle.control_hz:
            cfg.vehicle.control_hz = 1000.0 if cfg.ardupilot_instances() else 250.0
        if not cfg.vehicles and cfg.vehicle.params == defaults.vehicle.params:
            cfg.vehicle.params = "px4_quadx"
        for spec in cfg.vehicles:
            if spec.controlled_by == "px4" and spec.params is None:
                spec.params = "px4_quadx"
        n = cfg.px4.instance
        if n:  # one simulator per vehicle: keep the instances' ports and topics apart
            if args.api_port is None:
                cfg.runtime.api_port += n
            if cfg.bridge.listen == defaults.bridge.listen:
                cfg.bridge.listen = [f"tcp/127.0.0.1:{7448 + n}"]
            if cfg.bridge.namespace == defaults.bridge.namespace:
                cfg.bridge.namespace = f"{defaults.bridge.namespace}{n}"
    if cfg.ardupilot_instances():
        # after PX4's: a mixed fleet keeps its 1000 Hz (ArduPilot's clock follows the replies)
        shifted = bool(cfg.px4_instances()) and cfg.px4.instance > 0  # PX4's instance moved the API port
        _ardupilot_defaults(cfg, defaults, args.api_port is None and not shifted)
    if args.ui_port is not None:
        cfg.ui.port = args.ui_port
    with_ui = args.ui or args.ui_port is not None
    preflight.prepare_access(cfg, [cfg.runtime.api_host, *([cfg.ui.host] if with_ui else [])])
    preflight.check_run(cfg)
    if args.demo:
        preflight.check_output_dir(args.out)
        if cfg.runtime.api_port == 0:
            raise StartupError(
                "--demo flies through the API on a port it must know: give --api-port N", preflight.USAGE
            )
    if args.record:
        check_bag_output(args.record, "--record", args.max_bag_size, args.max_bag_duration)
    elif args.max_bag_size or args.max_bag_duration:
        raise StartupError(
            "--max-bag-size and --max-bag-duration split a recording: add --record BAG", preflight.USAGE
        )

    from droneulator.runtime.supervisor import Supervisor

    sup = Supervisor(cfg)
    sup.install_signal_handlers()
    recorder = None
    if args.record:
        from droneulator.recording.recorder import Recorder, run_recorder_config

        rec_cfg = run_recorder_config(
            cfg.bridge, sup.zenoh_endpoint, args.compression, args.max_bag_size, args.max_bag_duration
        )
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
    if with_ui:
        ui = _start_ui(cfg, sup)
    if args.demo:
        from droneulator.workflows.demo_client import run_demo_client

        threading.Thread(
            target=run_demo_client,
            args=(cfg, Path(args.out), sup.stop_requested, sup.zenoh_endpoint),
            daemon=True,
        ).start()
    try:
        code = sup.wait(args.duration)
    finally:
        if recorder is not None:
            report_recording(recorder.close())
        if ui is not None:
            ui.stop()
    if sup.failure:
        print(f"droneulator: {sup.failure}", file=sys.stderr)
    return code


def _ardupilot_defaults(cfg: SimConfig, defaults: SimConfig, api_port_default: bool) -> None:
    """What an ArduPilot run changes unless set: the world steps at ArduCopter SITL's frame rate
    (SIM_RATE_HZ 1200: one step per servo packet), its vehicles are the quad-X ``px4_quadx`` airframe, and
    instance N keeps its API port, Zenoh endpoint and ROS namespace apart from instance 0's."""
    if cfg.vehicle.control_hz == defaults.vehicle.control_hz:
        cfg.vehicle.control_hz = 1200.0
    if not cfg.vehicles and cfg.vehicle.params == defaults.vehicle.params:
        cfg.vehicle.params = "px4_quadx"
    for spec in cfg.vehicles:
        if spec.controlled_by == "ardupilot" and spec.params is None:
            spec.params = "px4_quadx"
    n = cfg.ardupilot.instance
    if n:
        if api_port_default:
            cfg.runtime.api_port += n
        if cfg.bridge.listen == defaults.bridge.listen:
            cfg.bridge.listen = [f"tcp/127.0.0.1:{7448 + n}"]
        if cfg.bridge.namespace == defaults.bridge.namespace:
            cfg.bridge.namespace = f"{defaults.bridge.namespace}{n}"


def _ui_zenoh_endpoint(cfg: SimConfig) -> str:
    """Where a UI in this process reaches the run's Zenoh router: its first TCP listen endpoint."""
    tcp = [e for e in cfg.bridge.listen if e.startswith("tcp/")]
    if not tcp:
        raise StartupError(f"--ui needs a tcp/ endpoint in bridge.listen, got {cfg.bridge.listen}")
    return tcp[0].replace("tcp/0.0.0.0:", "tcp/127.0.0.1:").replace("tcp/[::]:", "tcp/127.0.0.1:")


def _start_ui(cfg: SimConfig, sup: Supervisor) -> UIServer:
    """Start the browser UI on a thread of this process, once the simulator is up; prints its URL."""
    from droneulator.ui.server import UIServer

    host = cfg.runtime.api_host if cfg.runtime.api_host not in ("0.0.0.0", "::") else "127.0.0.1"
    server = UIServer(
        f"{'wss' if cfg.access.tls_cert else 'ws'}://{host}:{cfg.runtime.api_port}",
        _ui_zenoh_endpoint(cfg),
        cfg.ui,
        cfg.bridge,
        px4=bool(cfg.px4_instances()),
        access=cfg.access,
    )
    try:
        url = server.start_in_thread()
    except OSError as exc:
        sup.stop()
        raise StartupError(
            f"cannot start the UI on {cfg.ui.host}:{cfg.ui.port}: {exc.strerror or exc}"
        ) from None
    say(f"UI: {url}")
    return server
