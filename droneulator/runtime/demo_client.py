"""``droneulator run --demo``: fly the demo mission like a user's script would — commands over the
WebSocket API, images from the ROS 2 topics over Zenoh — print telemetry and save frames."""

from __future__ import annotations

import io
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from droneulator.api.client import DroneulatorClient
from droneulator.config import SimConfig
from droneulator.demo import plan_mission, telemetry_line
from droneulator.imaging import depth_to_rgb, segmentation_to_rgb
from droneulator.ros.zenoh_node import RosZenohNode
from droneulator.runtime.bridge import topic_names
from droneulator.scenes import get_scene

NS = 1_000_000_000


class FrameSaver:
    """Saves one RGB/depth/segmentation set per ``every`` sim seconds, as received from the topics."""

    def __init__(self, out: Path, every: float = 1.0) -> None:
        self.out = out
        self.every_ns = round(every * NS)
        self.lock = threading.Lock()
        self.received = 0
        self.saved = 0
        self.pending: dict[int, dict[str, Any]] = {}
        self.next_ns = 0

    def on(self, kind: str, msg: Any) -> None:
        t = msg.header.stamp.sec * NS + msg.header.stamp.nanosec
        with self.lock:
            self.received += kind == "rgb"
            if t < self.next_ns:
                return
            parts = self.pending.setdefault(t, {})
            parts[kind] = msg
            if len(parts) < 3:
                return
            del self.pending[t]
            self.pending = {k: v for k, v in self.pending.items() if k > t}
            self.next_ns = t + self.every_ns
            stem = self.out / f"{self.saved:04d}_front"
            self.saved += 1
        (stem.parent / f"{stem.name}_rgb.jpg").write_bytes(bytes(parts["rgb"].data))
        d = parts["depth"]
        depth = np.frombuffer(bytes(d.data), dtype="<f4").reshape(d.height, d.width)
        np.save(stem.parent / f"{stem.name}_depth.npy", depth)
        Image.fromarray(depth_to_rgb(depth)).save(stem.parent / f"{stem.name}_depth.png")
        seg = np.asarray(Image.open(io.BytesIO(bytes(parts["seg"].data))))
        Image.fromarray(segmentation_to_rgb(seg)).save(stem.parent / f"{stem.name}_seg.png")


def _connect(url: str, stop: threading.Event, timeout: float = 60.0) -> DroneulatorClient:
    deadline = time.monotonic() + timeout
    while True:
        try:
            return DroneulatorClient(url, timeout=30.0)
        except OSError:
            if stop.is_set() or time.monotonic() > deadline:
                raise
            time.sleep(0.2)


def run_demo_client(cfg: SimConfig, out: Path, stop: threading.Event) -> None:
    """Fly the mission, then ask the supervisor to stop (``stop.set()``)."""
    try:
        _fly(cfg, out, stop)
    finally:
        stop.set()


def _fly(cfg: SimConfig, out: Path, stop: threading.Event) -> None:
    out.mkdir(parents=True, exist_ok=True)
    client = _connect(f"ws://{cfg.runtime.api_host}:{cfg.runtime.api_port}", stop)
    cam = cfg.render.cameras[0].name
    saver = FrameSaver(out)
    names = topic_names(cfg.bridge.namespace, cam)
    node = RosZenohNode.from_config(cfg.bridge, listen=(), connect=tuple(cfg.bridge.listen))
    for kind, typename in (
        ("rgb", "sensor_msgs/msg/CompressedImage"),
        ("depth", "sensor_msgs/msg/Image"),
        ("seg", "sensor_msgs/msg/CompressedImage"),
    ):
        node.subscribe(names[kind], typename, lambda m, k=kind: saver.on(k, m))
    client.subscribe(["state", "events"], rate_hz=10.0)
    wall0 = time.monotonic()
    state: dict[str, Any] = client.state()
    t_start = state["t"]
    next_log = state["t"]
    try:
        for leg in plan_mission(get_scene(cfg.scene, cfg.seed), cfg):
            if stop.is_set():
                return
            client.request(leg.op, **leg.args)
            state = client.state()  # replies are ordered: this already reflects the command
            print(f"[{state['t']:6.2f}s] {leg.label}", flush=True)
            end = state["t"] + (leg.until if isinstance(leg.until, float) else 60.0)
            while not stop.is_set() and state["t"] < end and state["mode"] not in (leg.until, "collided"):
                msg = client.next_message(timeout=5.0)
                if msg is None:
                    continue
                if msg["type"] == "event":
                    print(f"[{msg['event']['t']:6.2f}s] event {msg['event']['type']}", flush=True)
                    continue
                state = msg["state"]
                if state["t"] >= next_log:
                    print(telemetry_line(state), flush=True)
                    next_log = state["t"] + 1.0
        wall = time.monotonic() - wall0
        sim_s = state["t"] - t_start
        time.sleep(0.5)  # let the last frames arrive
        print(
            f"demo finished: {sim_s:.1f} s simulated in {wall:.1f} s wall "
            f"(real-time factor {sim_s / wall:.2f}), "
            f"{saver.received} RGB frames received over Zenoh, {saver.saved} frame sets saved to {out}",
            flush=True,
        )
    finally:
        client.close()
        node.close()
