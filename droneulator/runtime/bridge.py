"""The bridge: turns simulator states and frames into ROS 2 messages (CDR) on Zenoh, and ROS
commands (``cmd_vel``, ``goal_pose``) into flight commands for the dynamics server.

Topics (namespace ``ns``, default ``droneulator``)::

    /clock                                           rosgraph_msgs/Clock
    /tf, /tf_static                                  tf2_msgs/TFMessage: map -> odom -> base_link
                                                     -> <cam>_link -> <cam>_optical_frame
    /<ns>/odom                                       nav_msgs/Odometry (odom -> base_link, twist in base_link)
    /<ns>/<cam>/{color,depth,segmentation}/camera_info   sensor_msgs/CameraInfo
    /<ns>/<cam>/color/image_raw/compressed           sensor_msgs/CompressedImage (jpeg)
    /<ns>/<cam>/depth/image_raw                      sensor_msgs/Image (32FC1, metres, NaN = no return)
    /<ns>/<cam>/segmentation/image_raw/compressed    sensor_msgs/CompressedImage (png, class ids)
    /<ns>/cmd_vel      (in)                          geometry_msgs/Twist: linear.x m/s, angular.z rad/s
    /<ns>/goal_pose    (in)                          geometry_msgs/PoseStamped in map/odom: goto

All images of one frame carry the same stamp (the sim time they were rendered at) and their
camera's optical frame id.
"""

from __future__ import annotations

import json
import logging
import math
import os
import signal
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from droneulator.config import SimConfig, from_dict
from droneulator.frames import T_link_optical, camera_mount, pose_from_transform, world_to_body
from droneulator.imaging import encode_jpeg, encode_png
from droneulator.ros import messages as M
from droneulator.ros.topics import topic_names
from droneulator.ros.zenoh_node import RosZenohNode
from droneulator.runtime.ipc import ENV_CONFIG, ENV_RING, FrameRing, hub_connect
from droneulator.sensors.camera import intrinsics

log = logging.getLogger("droneulator.bridge")

STATIC_TF_PERIOD_S = 1.0


class Bridge:
    def __init__(self, cfg: SimConfig, node: RosZenohNode, ring: FrameRing | None, conn: Any) -> None:
        self.cfg = cfg
        self.node = node
        self.ring = ring
        self.conn = conn
        self.send_lock = threading.Lock()
        ns = cfg.bridge.namespace
        self.pub_clock = node.publisher("/clock", "rosgraph_msgs/msg/Clock")
        self.pub_odom = node.publisher(f"/{ns}/odom", "nav_msgs/msg/Odometry")
        self.pub_tf = node.publisher("/tf", "tf2_msgs/msg/TFMessage")
        self.pub_tf_static = node.publisher("/tf_static", "tf2_msgs/msg/TFMessage")
        self.cams = []
        for cam in cfg.render.cameras:
            names = topic_names(ns, cam.name)
            pubs = {
                "rgb": node.publisher(names["rgb"], "sensor_msgs/msg/CompressedImage"),
                "depth": node.publisher(names["depth"], "sensor_msgs/msg/Image"),
                "seg": node.publisher(names["seg"], "sensor_msgs/msg/CompressedImage"),
                **{
                    k: node.publisher(names[k], "sensor_msgs/msg/CameraInfo")
                    for k in ("info_rgb", "info_depth", "info_seg")
                },
            }
            self.cams.append((cam, f"{cam.name}_optical_frame", intrinsics(cam), pubs))
        self.static_tf = self._static_transforms()
        self._last_static = -math.inf
        self._latency = open(cfg.bridge.latency_log, "a") if cfg.bridge.latency_log else None  # noqa: SIM115
        node.subscribe(f"/{ns}/cmd_vel", "geometry_msgs/msg/Twist", self._on_cmd_vel)
        node.subscribe(f"/{ns}/goal_pose", "geometry_msgs/msg/PoseStamped", self._on_goal_pose)

    # ------------------------------------------------------------------ ROS -> simulator
    def _relay(self, op: str, args: dict[str, Any]) -> None:
        try:
            with self.send_lock:
                self.conn.send(("command", op, args))
        except OSError:
            log.error("dropped a ROS %s command: the dynamics server is gone", op)

    def _on_cmd_vel(self, msg: Any) -> None:
        forward, yaw_rate = M.twist_to_command(msg)
        self._relay("velocity", {"forward": forward, "yaw_rate": yaw_rate})

    def _on_goal_pose(self, msg: Any) -> None:
        frame_id, position, yaw = M.pose_stamped_to_goal(msg)
        if frame_id not in ("", "map", "odom"):
            log.error("goal_pose in frame %r ignored: only map/odom goals are supported", frame_id)
            return
        self._relay("goto", {"position": [float(v) for v in position], "yaw": float(yaw)})

    # ------------------------------------------------------------------ simulator -> ROS
    def _static_transforms(self) -> list[Any]:
        tfs = [M.transform_stamped(0, "map", "odom", np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]))]
        for cam in self.cfg.render.cameras:
            link = f"{cam.name}_link"
            p, q = pose_from_transform(camera_mount(np.array(cam.position), cam.rpy))
            tfs.append(M.transform_stamped(0, "base_link", link, p, q))
            p, q = pose_from_transform(T_link_optical())
            tfs.append(M.transform_stamped(0, link, f"{cam.name}_optical_frame", p, q))
        return tfs

    def _mark(self, stream: str, t_ns: int) -> None:
        if self._latency is not None:
            self._latency.write(f"{stream} {t_ns} {time.time_ns()}\n")

    def publish_state(self, st: dict[str, Any]) -> None:
        t = st["t_ns"]
        self.pub_clock.publish(M.serialize(M.clock(t)), t)
        self._mark("odom", t)
        pos, quat = np.array(st["position"]), np.array(st["quaternion"])
        v_body = world_to_body(quat, np.array(st["velocity"]))
        odom = M.odometry(t, "odom", "base_link", pos, quat, v_body, np.array(st["angular_velocity"]))
        self.pub_odom.publish(M.serialize(odom), t)
        tf = M.tf_message([M.transform_stamped(t, "odom", "base_link", pos, quat)])
        self.pub_tf.publish(M.serialize(tf), t)
        now = time.monotonic()
        if now - self._last_static > STATIC_TF_PERIOD_S:
            self._last_static = now
            self.pub_tf_static.publish(M.serialize(M.tf_message(self.static_tf)), t)

    def publish_frame(self, seq: int, st: dict[str, Any]) -> None:
        t = st["t_ns"]
        assert self.ring is not None
        slot = self.ring.slot(seq)
        for cam, frame_id, K, pubs in self.cams:
            images = slot[cam.name]
            info = M.serialize(M.camera_info(t, frame_id, cam.width, cam.height, K))
            for key in ("info_rgb", "info_depth", "info_seg"):
                pubs[key].publish(info, t)
            self._mark("rgb", t)
            jpeg = encode_jpeg(images.rgb, self.cfg.bridge.jpeg_quality)
            pubs["rgb"].publish(M.serialize(M.compressed_image(t, frame_id, "jpeg", jpeg)), t)
            self._mark("depth", t)
            pubs["depth"].publish(M.serialize(M.image(t, frame_id, images.depth)), t)
            png = encode_png(images.seg)
            pubs["seg"].publish(M.serialize(M.compressed_image(t, frame_id, "png", png)), t)

    def serve(self) -> None:
        while True:
            try:
                msg = self.conn.recv()
            except (EOFError, OSError):
                return
            if msg[0] == "state":
                self.publish_state(msg[1])
            elif msg[0] == "frame":
                self.publish_frame(msg[1], msg[2])
                try:
                    with self.send_lock:
                        self.conn.send(("published", msg[1]))
                except OSError:
                    return

    def close(self) -> None:
        if self._latency is not None:
            self._latency.close()


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s")
    signal.signal(signal.SIGTERM, lambda *_: os._exit(0))
    signal.signal(signal.SIGINT, lambda *_: os._exit(0))
    cfg = from_dict(SimConfig, json.loads(os.environ[ENV_CONFIG]))
    conn, _ = hub_connect("bridge")
    ring = FrameRing(os.environ[ENV_RING], cfg.render.cameras, cfg.runtime.frame_slots)
    if cfg.bridge.latency_log:
        Path(cfg.bridge.latency_log).parent.mkdir(parents=True, exist_ok=True)
    with RosZenohNode.from_config(cfg.bridge) as node:
        bridge = Bridge(cfg, node, ring, conn)
        log.info(
            "bridge ready: namespace /%s, %s keys, listening on %s",
            cfg.bridge.namespace,
            cfg.bridge.key_mode,
            ", ".join(cfg.bridge.listen) or "-",
        )
        try:
            bridge.serve()
        finally:
            bridge.close()
            ring.close()


if __name__ == "__main__":
    main()
