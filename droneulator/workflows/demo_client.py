"""``droneulator run --demo``: fly the demo mission like a user's script would — commands over the
WebSocket API, images from the ROS 2 topics over Zenoh — print telemetry and save frames."""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from droneulator.api.client import DroneulatorClient
from droneulator.config import SimConfig
from droneulator.imaging import depth_to_rgb, segmentation_to_rgb
from droneulator.logs import say
from droneulator.ros.topics import (
    TYPES,
    decode_compressed,
    decode_depth,
    header_ns,
    seconds_to_ns,
    topic_names,
)
from droneulator.ros.zenoh_node import RosZenohNode
from droneulator.scenes import get_scene
from droneulator.workflows.demo import plan_mission, telemetry_line

#: how long a command may wait for its reply: the simulation lock is held while a kernel compiles, which
#: a first run (the bundle's on a new machine) does on first use, for up to a minute on a loaded machine
REQUEST_TIMEOUT_S = 180.0
#: how long the demo waits for the clock's first step (the world's kernels compiling, cameras warming up)
CLOCK_WAIT_S = 600.0


class FrameSaver:
    """Saves one RGB/depth/segmentation set per ``every`` sim seconds, as received from the topics."""

    def __init__(self, out: Path, every: float = 1.0) -> None:
        self.out = out
        self.every_ns = seconds_to_ns(every)
        self.lock = threading.Lock()
        self.received = 0
        self.saved = 0
        self.pending: dict[int, dict[str, Any]] = {}
        self.next_ns = 0

    def on(self, kind: str, msg: Any) -> None:
        t = header_ns(msg)
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
        depth = decode_depth(parts["depth"])
        np.save(stem.parent / f"{stem.name}_depth.npy", depth)
        Image.fromarray(depth_to_rgb(depth)).save(stem.parent / f"{stem.name}_depth.png")
        seg = decode_compressed(parts["seg"])
        Image.fromarray(segmentation_to_rgb(seg)).save(stem.parent / f"{stem.name}_seg.png")


def _connect(cfg: SimConfig, stop: threading.Event, timeout: float = 60.0) -> DroneulatorClient:
    access = cfg.access
    url = f"{'wss' if access.tls_cert else 'ws'}://{cfg.runtime.api_host}:{cfg.runtime.api_port}"
    deadline = time.monotonic() + timeout
    while True:
        try:
            return DroneulatorClient(
                url, REQUEST_TIMEOUT_S, token=access.token, cafile=access.tls_ca or access.tls_cert
            )
        except OSError:
            if stop.is_set() or time.monotonic() > deadline:
                raise
            time.sleep(0.2)


def run_demo_client(
    cfg: SimConfig, out: Path, stop: threading.Event, hub_endpoint: str | None = None
) -> None:
    """Fly the mission, then ask the supervisor to stop (``stop.set()``). The frames come through
    ``hub_endpoint``, the run's private Zenoh endpoint (its bridge's and recorder's), whatever ports
    ``bridge.listen`` names (a port 0 included); without it, or when the simulator is a client of the
    user's router (``bridge.mode`` ``client``), through the bridge's own endpoints."""
    try:
        _fly(cfg, out, stop, hub_endpoint)
    finally:
        stop.set()


def _fly(cfg: SimConfig, out: Path, stop: threading.Event, hub_endpoint: str | None) -> None:
    out.mkdir(parents=True, exist_ok=True)
    client = _connect(cfg, stop)
    cam = cfg.render.cameras[0].name
    saver = FrameSaver(out)
    names = topic_names(cfg.bridge.namespace, cam)
    if hub_endpoint and cfg.bridge.mode != "client":
        node = RosZenohNode.from_config(
            cfg.bridge, mode="client", listen=(), connect=(hub_endpoint,), config_file=None,
            tls_ca="", tls_cert="", tls_key="", tls_mtls=False,
        )  # fmt: skip
    else:
        node = RosZenohNode.from_config(cfg.bridge, listen=(), connect=tuple(cfg.bridge.listen))
    for kind in ("rgb", "depth", "seg"):
        node.subscribe(names[kind], TYPES[kind], lambda m, k=kind: saver.on(k, m))
    try:  # the state op does not wait for the simulation lock; commands do
        client.wait_until(lambda s: s["t"] > 0.0, timeout=2.0)
    except TimeoutError:
        say("waiting for the simulation clock to start (a first run compiles its kernels: a minute or two)")
        client.wait_until(lambda s: s["t"] > 0.0, timeout=CLOCK_WAIT_S)
    client.subscribe(["state", "events"], rate_hz=10.0)
    wall0 = time.monotonic()
    state: dict[str, Any] = client.state()
    t_start = state["t"]
    next_log = state["t"]
    try:
        for leg in plan_mission(get_scene(cfg.scene, cfg.seed, cfg.vegetation), cfg):
            if stop.is_set():
                return
            client.request(leg.op, **leg.args)
            state = client.state()  # replies are ordered: this already reflects the command
            say(f"[{state['t']:6.2f}s] {leg.label}")
            end = state["t"] + (leg.until if isinstance(leg.until, float) else 60.0)
            while not stop.is_set() and state["t"] < end and state["mode"] not in (leg.until, "collided"):
                msg = client.next_message(timeout=5.0)
                if msg is None:
                    continue
                if msg["type"] == "event":
                    say(f"[{msg['event']['t']:6.2f}s] event {msg['event']['type']}")
                    continue
                state = msg["state"]
                if state["t"] >= next_log:
                    say(telemetry_line(state))
                    next_log = state["t"] + 1.0
        wall = time.monotonic() - wall0
        sim_s = state["t"] - t_start
        # let the last frames arrive, and say the events that come meanwhile: states and events are two
        # streams, so the state of the mode that ends the mission can come before the event that said so
        drain_until = time.monotonic() + 0.5
        while (left := drain_until - time.monotonic()) > 0:
            msg = client.next_message(timeout=left)
            if msg is not None and msg["type"] == "event":
                say(f"[{msg['event']['t']:6.2f}s] event {msg['event']['type']}")
        say(
            f"demo finished: {sim_s:.1f} s simulated in {wall:.1f} s wall "
            f"(real-time factor {sim_s / wall:.2f}), "
            f"{saver.received} RGB frames received over Zenoh, {saver.saved} frame sets saved to {out}"
        )
    finally:
        client.close()
        node.close()
