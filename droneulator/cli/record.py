"""``droneulator record``: a running simulator's ROS 2 topics, from Zenoh to an MCAP bag."""

from __future__ import annotations

import argparse
import threading

from droneulator.cli.common import (
    DEFAULT_ZENOH,
    add_bag_split_args,
    add_compression_arg,
    add_key_mode_args,
    check_bag_output,
    report_recording,
)
from droneulator.runtime import preflight
from droneulator.runtime.preflight import StartupError


def add(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
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
    add_key_mode_args(p)
    p.add_argument("--namespace", default="droneulator", help="the run's ROS namespace (bridge.namespace)")
    p.add_argument("--duration", type=float, default=None, help="stop after this many wall seconds")
    add_compression_arg(p)
    add_bag_split_args(p)
    p.set_defaults(func=cmd_record)


def cmd_record(args: argparse.Namespace) -> int:
    import signal

    from droneulator.recording.recorder import Recorder, RecorderConfig

    try:
        cfg = RecorderConfig(
            connect=tuple(args.zenoh or [DEFAULT_ZENOH]),
            namespace=args.namespace,
            key_mode=args.key_mode,
            domain_id=args.domain_id,
            ros2dds_namespace=args.ros2dds_namespace,
            compression=args.compression,
            max_bag_bytes=args.max_bag_size,
            max_bag_duration_s=args.max_bag_duration,
        )
    except ValueError as exc:
        raise StartupError(str(exc), preflight.USAGE) from None
    check_bag_output(args.out, "-o", args.max_bag_size, args.max_bag_duration)
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
    report_recording(recorder.close())
    return 0
