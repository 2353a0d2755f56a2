"""The bridge: publishes every camera frame the render server draws as ROS 2 messages (CDR on Zenoh).

It is the image half of the ROS 2 interface; the dynamics server publishes the state half (clock,
odometry, TF) and takes the ROS commands itself (:mod:`droneulator.ros.publishers` has both halves
and the topic list). Encoding JPEG/PNG here keeps that work off the process that owns the clock.

The bridge's Zenoh session is a client of the dynamics server's (over the run's private Unix socket),
which routes its samples to every subscriber; with ``bridge.mode=client`` both sessions are clients
of the same external router. Lockstep publishes images with ``BLOCK`` (nothing is lost, the clock
waits for the slowest subscriber), realtime with ``DROP``.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import sys
from multiprocessing.connection import Connection

import zenoh

from droneulator.config import SimConfig, from_dict
from droneulator.ros.publishers import FramePublisher
from droneulator.ros.zenoh_node import RosZenohNode
from droneulator.runtime.ipc import (
    ENV_CONFIG,
    ENV_RING,
    ENV_ZENOH,
    FrameRing,
    HubGoneError,
    Publish,
    Published,
    hub_connect,
)
from droneulator.runtime.latency import LatencyLog
from droneulator.runtime.spawn import start_server_process

log = logging.getLogger("droneulator.bridge")


def open_bridge_node(cfg: SimConfig, hub_endpoint: str | None) -> RosZenohNode:
    """A Zenoh client of the run's hub session (or of the user's router when ``bridge.mode=client``)."""
    name = "droneulator_cameras"  # a node of its own in the ROS graph (rmw_zenoh key mode)
    if hub_endpoint and cfg.bridge.mode != "client":
        return RosZenohNode.from_config(
            cfg.bridge, mode="client", listen=(), connect=(hub_endpoint,), node_name=name
        )
    return RosZenohNode.from_config(cfg.bridge, listen=(), node_name=name)


def images_policy(cfg: SimConfig) -> zenoh.CongestionControl:
    """``BLOCK`` in lockstep (no image lost; an autopilot's lockstep too), ``DROP`` in real time (never
    stall the simulation)."""
    lockstep = cfg.runtime.mode == "lockstep" or bool(cfg.px4_instances() or cfg.ardupilot_instances())
    return zenoh.CongestionControl.BLOCK if lockstep else zenoh.CongestionControl.DROP


class Bridge:
    """Publish each :class:`Publish` request from the hub and acknowledge it with :class:`Published`."""

    def __init__(self, cfg: SimConfig, node: RosZenohNode, ring: FrameRing, conn: Connection) -> None:
        self.ring = ring
        self.conn = conn
        self.frames = FramePublisher(node, cfg, images_policy(cfg))
        self._publishing = False
        self._stop = False
        self._latency = LatencyLog.of(cfg)

    def on_signal(self, *_: object) -> None:
        """SIGTERM/SIGINT: exit at once between frames; mid-frame, finish the frame set first, so a
        recording never ends with one topic of a frame and not the others."""
        if self._publishing:
            self._stop = True
        else:
            os._exit(0)

    def serve(self) -> None:
        """Until the hub goes or a stop signal arrives; returns so the caller closes the Zenoh session
        (flushing what was put) after the last whole frame set."""
        mark = self._latency.mark if self._latency is not None else None
        while not self._stop:
            try:
                msg = self.conn.recv()
            except (EOFError, OSError):
                return
            if isinstance(msg, Publish):
                self._publishing = True
                self.frames.publish(msg.states, self.ring.slot(msg.seq), mark)
                self._publishing = False
                try:
                    self.conn.send(Published(msg.seq))
                except OSError:
                    return

    def close(self) -> None:
        self.frames.close()
        if self._latency is not None:
            self._latency.close()


def main() -> None:
    start_server_process()
    signal.signal(signal.SIGTERM, lambda *_: os._exit(0))
    signal.signal(signal.SIGINT, lambda *_: os._exit(0))
    cfg = from_dict(SimConfig, json.loads(os.environ[ENV_CONFIG]))
    try:
        conn, _ = hub_connect("bridge")
    except HubGoneError as e:
        log.error("%s; exiting", e)
        sys.exit(1)
    ring = FrameRing(os.environ[ENV_RING], cfg.camera_rigs(), cfg.runtime.frame_slots)
    with open_bridge_node(cfg, os.environ.get(ENV_ZENOH)) as node:
        bridge = Bridge(cfg, node, ring, conn)
        signal.signal(signal.SIGTERM, bridge.on_signal)
        signal.signal(signal.SIGINT, bridge.on_signal)
        log.info(
            "bridge ready: cameras on /%s, %s keys, images %s",
            cfg.bridge.namespace,
            cfg.bridge.key_mode,
            "lossless" if images_policy(cfg) == zenoh.CongestionControl.BLOCK else "best effort",
        )
        try:
            bridge.serve()
        finally:
            bridge.close()
            ring.close()


if __name__ == "__main__":
    main()
