"""``droneulator replay``: an MCAP bag republished on Zenoh at the recorded rate."""

from __future__ import annotations

import argparse
import threading

from droneulator.cli.common import DEFAULT_ZENOH, add_key_mode_args
from droneulator.runtime.preflight import StartupError


def add(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
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
    add_key_mode_args(p)
    p.add_argument(
        "--wait-subscriber",
        type=float,
        default=0.0,
        metavar="S",
        help="wait up to S seconds for a subscriber before the first message (default 0)",
    )
    p.set_defaults(func=cmd_replay)


def cmd_replay(args: argparse.Namespace) -> int:
    import signal

    from droneulator.recording.replay import ReplayConfig, replay

    cfg = ReplayConfig(
        listen=tuple(args.zenoh or [DEFAULT_ZENOH]),
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
