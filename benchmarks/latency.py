"""End-to-end latency of the ROS 2 / Zenoh bridge (paper Table II), plus the full run's lockstep
real-time factor.

1. ``droneulator run --realtime`` on a scene (default ``default``) with the 640x480 rig at 30 Hz and
   odometry at 30 Hz, while the vehicle flies (``bridge.latency_log``). Odometry is timed from where
   a user's latency starts: the end of the physics step that produced the state (logged by the
   dynamics server, which publishes it). Images are timed from the bridge's publish call, before
   encoding and serialisation (as before, so the figures compare).
2. A subscriber in a separate process (this script with ``--subscriber``) connects over Zenoh,
   deserialises every odometry, JPEG RGB and raw float32 depth message with rosbags, and logs the
   wall-clock time once each is decoded.
3. Latency = decoded time - start time, matched by stream and stamp: mean, std, p50, p99, n, over
   the window after a warm-up (``--warmup``, default 1 s: the first large samples set up Zenoh's
   shared-memory pool).
4. Where the floor is: the same run with no camera load (one 8x6 camera at 1 Hz), and Zenoh alone
   (a router process publishing odometry-sized samples at 30 Hz to the same subscriber, no simulator).
5. Then ``droneulator run`` in lockstep for ``--rtf-seconds`` wall seconds: real-time factor =
   sim seconds advanced / wall seconds, read from the WebSocket state.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _common import write

from droneulator.api.client import DroneulatorClient
from droneulator.config import load_config
from droneulator.ros.topics import TYPES, header_ns, topic_names, vehicle_topics
from droneulator.runtime.launch import LaunchedRun, launch_run

PAPER_MS = {"odom": 0.45, "rgb": 5.65, "depth": 17.06}
_NAMES = {**vehicle_topics("droneulator"), **topic_names("droneulator", "front")}
#: stream -> (zenoh-bridge-ros2dds key: the topic name without its leading slash, message type)
STREAMS = {k: (_NAMES[k].lstrip("/"), TYPES[k]) for k in ("odom", "rgb", "depth")}


def subscriber(endpoint: str, out: str, seconds: float) -> None:
    """Separate process: decode every sample of the three streams and log when it was decoded."""
    import zenoh
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_JAZZY)
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    rows: list[str] = []

    def handler(stream: str, typename: str):
        def cb(sample) -> None:
            msg = ts.deserialize_cdr(sample.payload.to_bytes(), typename)
            now = time.time_ns()
            rows.append(f"{stream} {header_ns(msg)} {now}\n")

        return cb

    with zenoh.open(conf) as session:
        subs = [session.declare_subscriber(key, handler(name, t)) for name, (key, t) in STREAMS.items()]
        time.sleep(seconds)
        for s in subs:
            s.undeclare()
    Path(out).write_text("".join(rows))


def zenoh_publisher(endpoint: str, out: str, seconds: float) -> None:
    """Separate process: a Zenoh router publishing packed odometry at 30 Hz, logging each put's time."""
    import numpy as np

    from droneulator.ros.messages import StatePacker
    from droneulator.ros.zenoh_node import RosZenohNode, ZenohNodeConfig

    packer, rows = StatePacker("odom", "base_link"), []
    p, q, v = np.array([1.0, 2.0, 3.0]), np.array([0.0, 0.0, 0.0, 1.0]), np.zeros(3)
    with RosZenohNode(ZenohNodeConfig(mode="router", listen=(endpoint,))) as node:
        pub = node.publisher(_NAMES["odom"], TYPES["odom"])
        t_end = time.monotonic() + seconds
        k = 0
        while time.monotonic() < t_end:
            k += 1
            stamp = k * 33_333_333
            rows.append(f"odom {stamp} {time.time_ns()}\n")
            pub.publish(packer.odometry(stamp, p, q, v, v), stamp)
            time.sleep(1 / 30)
    Path(out).write_text("".join(rows))


def read_log(path: Path) -> dict[tuple[str, int], int]:
    out = {}
    for line in path.read_text().splitlines():
        stream, stamp, wall = line.split()
        out.setdefault((stream, int(stamp)), int(wall))
    return out


def take_off_and_circle(run: LaunchedRun) -> DroneulatorClient:
    """Connect, take off to 2 m and fly a slow circle in velocity mode, so the images change."""
    client = run.client()
    client.subscribe(["events"])
    client.takeoff(altitude=2.0)
    client.wait_for_event("arrived", timeout=60)
    client.velocity(0.5, 0.3)
    return client


def _subscribe(args: argparse.Namespace, endpoint: str, out: Path) -> subprocess.Popen:
    cmd = [sys.executable, __file__, "--subscriber", endpoint, "--sub-out", str(out)]
    return subprocess.Popen([*cmd, "--seconds", str(args.seconds)])


def _statistics(pub_log: Path, sub_log: Path, warmup: float) -> dict:
    published, decoded = read_log(pub_log), read_log(sub_log)
    res = {}
    for stream in STREAMS:
        pairs = [(published[k], decoded[k]) for k in decoded if k[0] == stream and k in published]
        if not pairs:
            continue
        start = min(p for p, _ in pairs) + warmup * 1e9
        lat = np.array([(d - p) / 1e6 for p, d in pairs if p >= start])
        res[stream] = {
            "n": int(lat.size),
            "mean_ms": float(lat.mean()),
            "std_ms": float(lat.std()),
            "p50_ms": float(np.percentile(lat, 50)),
            "p99_ms": float(np.percentile(lat, 99)),
            "paper_mean_ms": PAPER_MS[stream],
        }
    return res


def measure_latency(args: argparse.Namespace, cameras: str | None = None) -> dict:
    """The run's latency; ``cameras`` (a JSON list for ``render.cameras``) replaces the 640x480 rig."""
    tmp = Path(tempfile.mkdtemp(prefix="droneulator-latency-"))
    pub_log, sub_log = tmp / "publish.log", tmp / "decoded.log"
    extra = ["--realtime", "--set", f"bridge.latency_log={pub_log}", "--set", "runtime.state_hz=30"]
    if cameras is not None:
        extra += ["--set", f"render.cameras={cameras}", "--set", "render.camera_hz=1"]
    with launch_run(load_config(scene=args.scene), extra) as run:
        client = take_off_and_circle(run)
        _subscribe(args, run.zenoh_endpoint, sub_log).wait(args.seconds + 60)
        client.close()
    return _statistics(pub_log, sub_log, args.warmup)


def measure_zenoh_floor(args: argparse.Namespace) -> dict:
    """Zenoh alone: a router process publishing odometry, the same subscriber, no simulator."""
    from droneulator.runtime.launch import free_port

    tmp = Path(tempfile.mkdtemp(prefix="droneulator-latency-"))
    pub_log, sub_log = tmp / "publish.log", tmp / "decoded.log"
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    cmd = [sys.executable, __file__, "--publisher", endpoint, "--sub-out", str(pub_log)]
    pub = subprocess.Popen([*cmd, "--seconds", str(args.seconds + 3)])
    time.sleep(1.5)
    _subscribe(args, endpoint, sub_log).wait(args.seconds + 60)
    pub.wait(30)
    return _statistics(pub_log, sub_log, args.warmup)


def _table(title: str, lat: dict) -> None:
    print(title)
    print(f"{'stream':8s} {'n':>6s} {'mean':>8s} {'std':>8s} {'p50':>8s} {'p99':>8s}   paper mean (ms)")
    for name, r in lat.items():
        print(
            f"{name:8s} {r['n']:6d} {r['mean_ms']:8.2f} {r['std_ms']:8.2f} "
            f"{r['p50_ms']:8.2f} {r['p99_ms']:8.2f}   {r['paper_mean_ms']:.2f}"
        )


def measure_lockstep(args: argparse.Namespace) -> dict:
    with launch_run(load_config(scene=args.scene), ["--lockstep"]) as run:
        client = take_off_and_circle(run)
        t0, w0 = client.state()["t"], time.monotonic()
        time.sleep(args.rtf_seconds)
        t1, w1 = client.state()["t"], time.monotonic()
        client.close()
    return {"sim_seconds": t1 - t0, "wall_seconds": w1 - w0, "real_time_factor": (t1 - t0) / (w1 - w0)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="default", help="scene name (default default)")
    ap.add_argument("--seconds", type=float, default=60.0, help="latency window in wall seconds (default 60)")
    ap.add_argument("--warmup", type=float, default=1.0, help="seconds dropped at the start (default 1)")
    ap.add_argument("--rtf-seconds", type=float, default=20.0, help="lockstep timing window (default 20)")
    ap.add_argument("--json", default=None, help="output path (default benchmarks/results/latency.json)")
    ap.add_argument("--no-floor", action="store_true", help="skip the two floor measurements")
    ap.add_argument("--subscriber", metavar="ENDPOINT", help=argparse.SUPPRESS)
    ap.add_argument("--publisher", metavar="ENDPOINT", help=argparse.SUPPRESS)
    ap.add_argument("--sub-out", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.subscriber:
        subscriber(args.subscriber, args.sub_out, args.seconds)
        return
    if args.publisher:
        zenoh_publisher(args.publisher, args.sub_out, args.seconds)
        return
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    lat = measure_latency(args)
    what = f"{args.scene}, 640x480 at 30 Hz, {args.seconds:g} s, subscriber in another process"
    _table(f"end-to-end latency, {what}", lat)
    floor = {}
    if not args.no_floor:
        floor["no_cameras"] = measure_latency(args, '[{"name": "front", "width": 8, "height": 6}]')
        _table("the same, without camera load (one 8x6 camera at 1 Hz)", floor["no_cameras"])
        floor["zenoh_only"] = measure_zenoh_floor(args)
        _table("Zenoh alone: a router publishing odometry at 30 Hz, no simulator", floor["zenoh_only"])
    rtf = measure_lockstep(args)
    print(
        f"lockstep, all three processes, 640x480 at 30 Hz on {args.scene}: "
        f"{rtf['sim_seconds']:.1f} s simulated in {rtf['wall_seconds']:.1f} s -> real-time factor "
        f"{rtf['real_time_factor']:.2f}"
    )
    write("latency", {"scene": args.scene, "latency": lat, "floor": floor, "lockstep": rtf}, args.json)


if __name__ == "__main__":
    main()
