"""``droneulator capture``: a photogrammetry capture around the scene's tree, written as a COLMAP dataset."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from droneulator.cli.common import add_config_args, config_from_args

#: the options that override the same-named fields of the capture section (cfg.capture)
_CAPTURE_FIELDS = (
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
    "trigger",
    "jpeg_quality",
    "settle_position_m",
    "settle_speed_mps",
    "settle_time_s",
    "vehicles",
)


def add(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "capture",
        help="fly a circular photogrammetry capture around the scene's tree and record a COLMAP dataset",
        description="Fly rings of viewpoints around the tree over the WebSocket API, record RGB, TF poses "
        "and camera_info from the ROS 2 topics over Zenoh, and write images/, sparse_known/, poses.json/.csv "
        "and metadata.json to --out. Re-running the same command resumes an interrupted capture.",
    )
    add_config_args(p, "tree_inspection")
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
    p.add_argument(
        "--continuous",
        dest="trigger",
        action="store_false",
        default=None,
        help="render the camera at --camera-hz throughout the flight, as a video camera, instead of "
        "triggering it once at each view (the default: nothing is rendered between views)",
    )
    p.add_argument(
        "--camera-hz",
        type=float,
        default=None,
        help="with --continuous: camera rate while capturing (sim Hz)",
    )
    p.add_argument("--jpeg-quality", type=int, default=None, help="JPEG quality of the published images")
    p.add_argument("--settle-position", dest="settle_position_m", type=float, default=None, help="m")
    p.add_argument("--settle-speed", dest="settle_speed_mps", type=float, default=None, help="m/s")
    p.add_argument("--settle-time", dest="settle_time_s", type=float, default=None, help="sim seconds")
    p.add_argument(
        "--vehicles",
        dest="capture_vehicles",
        type=int,
        default=None,
        metavar="N",
        help="fly N vehicles at once, each a contiguous arc of every ring (2: opposite halves, from where "
        "they stand outwards); the same views and dataset as one vehicle (default 1)",
    )
    p.add_argument(
        "--url", default=None, help="use the simulator at this WebSocket URL instead of starting one"
    )
    p.add_argument(
        "--zenoh", default=None, help="with --url: Zenoh endpoint of its bridge (default tcp/127.0.0.1:7448)"
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_capture)


def cmd_capture(args: argparse.Namespace) -> int:
    import signal

    from droneulator.workflows.photogrammetry.capture import capture

    if args.camera_hz is not None and args.trigger is None:
        raise ValueError(
            "--camera-hz is the rate of a continuous camera: add --continuous (by default the camera is "
            "triggered once at each view)"
        )
    cfg = config_from_args(args)
    cap = cfg.capture
    for name in _CAPTURE_FIELDS:
        value = getattr(args, "capture_vehicles" if name == "vehicles" else name)
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
