"""Receive odometry and the colour image from a running simulator with only ``zenoh`` and ``rosbags``.

The simulator publishes ROS 2 messages as CDR on Zenoh with zenoh-bridge-ros2dds' key convention
(docs/ros2.md): the ROS topic ``/a/b`` is the Zenoh key ``a/b``, and the payload is the CDR
sample with its 4-byte encapsulation header, which rosbags' typestore decodes. No ROS 2
installation and no droneulator import is needed.

    droneulator run --scene orchard               # in another terminal (Zenoh on tcp/127.0.0.1:7448)
    python examples/subscribe_zenoh.py --seconds 5 --out frames/

It prints the odometry at 2 Hz of sim time and one line per colour frame, saves every ``--every``-th
JPEG to ``--out`` (named by its stamp), and exits after ``--seconds`` of wall time or once
``--frames`` images (and an odometry message) have arrived. ``--summary FILE`` writes the counts and
the last odometry as JSON.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from pathlib import Path
from typing import Any

import zenoh
from rosbags.typesys import Stores, get_typestore

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
ODOMETRY = "nav_msgs/msg/Odometry"
COMPRESSED = "sensor_msgs/msg/CompressedImage"


def stamp_ns(msg: Any) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def session_config(endpoint: str) -> zenoh.Config:
    """A Zenoh peer that connects to the simulator's endpoint only (no multicast scouting)."""
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return conf


class Receiver:
    """Decodes odometry and colour images as they arrive (Zenoh calls back on its own threads)."""

    def __init__(self, out: Path | None, every: int) -> None:
        self.out = out
        self.every = every
        self.lock = threading.Lock()
        self.odometry = 0
        self.images = 0
        self.saved: list[str] = []
        self.last_odom: dict[str, Any] | None = None
        self._next_print_ns = 0

    def on_odometry(self, sample: zenoh.Sample) -> None:
        msg = TYPESTORE.deserialize_cdr(sample.payload.to_bytes(), ODOMETRY)
        p, v = msg.pose.pose.position, msg.twist.twist.linear
        t = stamp_ns(msg)
        with self.lock:
            self.odometry += 1
            self.last_odom = {
                "stamp_ns": t,
                "frame_id": msg.header.frame_id,
                "child_frame_id": msg.child_frame_id,
                "position": [p.x, p.y, p.z],
                "velocity_body": [v.x, v.y, v.z],
            }
            if t < self._next_print_ns:
                return
            self._next_print_ns = t + 500_000_000
        print(
            f"odom  t={t / 1e9:7.2f} s  {msg.header.frame_id}->{msg.child_frame_id}  "
            f"position=({p.x:6.2f}, {p.y:6.2f}, {p.z:5.2f})  forward={v.x:5.2f} m/s"
        )

    def on_image(self, sample: zenoh.Sample) -> None:
        msg = TYPESTORE.deserialize_cdr(sample.payload.to_bytes(), COMPRESSED)
        t = stamp_ns(msg)
        with self.lock:
            n = self.images
            self.images += 1
        print(f"image t={t / 1e9:7.2f} s  {msg.header.frame_id}  {msg.format}  {len(msg.data)} bytes")
        if self.out is not None and n % self.every == 0:
            path = self.out / f"color_{t:019d}.jpg"
            path.write_bytes(bytes(msg.data))  # the JPEG exactly as published
            with self.lock:
                self.saved.append(str(path))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--connect", default="tcp/127.0.0.1:7448", help="the simulator's Zenoh endpoint")
    ap.add_argument("--namespace", default="droneulator", help="the run's ROS namespace (bridge.namespace)")
    ap.add_argument("--camera", default="front", help="camera name")
    ap.add_argument("--seconds", type=float, default=10.0, help="stop after this many wall seconds")
    ap.add_argument(
        "--frames", type=int, default=0, help="stop after this many images and one odometry (0: no limit)"
    )
    ap.add_argument("--out", default=None, help="folder for the saved JPEG files")
    ap.add_argument("--every", type=int, default=10, help="save every N-th image")
    ap.add_argument("--summary", default=None, help="write the counts and the last odometry as JSON")
    args = ap.parse_args()
    if args.seconds <= 0 or args.every < 1 or args.frames < 0:
        ap.error("--seconds must be positive, --every at least 1, --frames not negative")
    out = Path(args.out) if args.out else None
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)

    rx = Receiver(out, args.every)
    odom_key = f"{args.namespace}/odom"
    image_key = f"{args.namespace}/{args.camera}/color/image_raw/compressed"
    with zenoh.open(session_config(args.connect)) as session:
        subs = [
            session.declare_subscriber(odom_key, rx.on_odometry),
            session.declare_subscriber(image_key, rx.on_image),
        ]
        print(f"listening on {args.connect}: {odom_key}, {image_key}")
        deadline = time.monotonic() + args.seconds
        # with --frames, wait for odometry too: each subscription takes effect at the router on its own,
        # and on a busy machine 20 images can arrive before the first odometry message does
        while time.monotonic() < deadline and not (args.frames and rx.images >= args.frames and rx.odometry):
            time.sleep(0.05)
        for sub in subs:
            sub.undeclare()
    with rx.lock:
        summary = {
            "odometry": rx.odometry,
            "images": rx.images,
            "saved": rx.saved,
            "last_odometry": rx.last_odom,
        }
    print(
        f"received {summary['odometry']} odometry messages and {summary['images']} images; "
        f"saved {len(summary['saved'])} JPEG files"
    )
    if args.summary:
        Path(args.summary).write_text(json.dumps(summary, indent=2))
    return 0 if rx.odometry and rx.images else 1


if __name__ == "__main__":
    sys.exit(main())
