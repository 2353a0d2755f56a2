"""The environment's remote backend: a running ``droneulator run`` driven like the paper's environment.

Commands (``reset``, ``velocity``) and the vehicle state go over the WebSocket API; the depth image
comes from the bridge's ROS 2 topic ``/<ns>/front/depth/image_raw`` over Zenoh. A step sends the
velocity command and waits for the first depth frame rendered after the simulator accepted it, then
reads the state. The simulation runs on its own clock (lockstep with its renderer and bridge, or
real time with ``--realtime``), so, unlike the local backend, a step may span more than one frame.

Start the runtime with the RL camera so that the strip matches the local backend, e.g.::

    droneulator run --scene vineyard --set 'render.cameras=[{"name": "front", "width": 128,
        "height": 9, "hfov_deg": 90.0, "far": 10.0}]' --set render.shadows=false

(:func:`droneulator.workflows.rl.env.runtime_overrides` gives these ``--set`` options).
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

import numpy as np

from droneulator.api.client import DroneulatorClient
from droneulator.config import SimConfig
from droneulator.ros.topics import decode_depth, header_ns, topic_names
from droneulator.ros.zenoh_node import RosZenohNode
from droneulator.scenes import get_scene
from droneulator.workflows.rl.backend import CAMERA_NAME, SCENE, Kinematics

log = logging.getLogger(__name__)

#: sim time to let pass after a reset before frames count: frames from before it are delivered by then
RESET_SETTLE_S = 0.2


class RemoteBackend:
    """WebSocket commands and state, Zenoh depth frames, for :class:`~.env.VineyardNavEnv`."""

    def __init__(self, cfg: SimConfig, url: str, zenoh: str | None = None, timeout: float = 30.0) -> None:
        self.timeout = timeout
        self.camera = cfg.render.cameras[0]
        self.client = DroneulatorClient(url, timeout=timeout)
        try:
            info = self.client.scene_info()
            if info.get("camera_trigger") == "command":
                raise ValueError(
                    f"the run at {url} triggers its cameras (render.camera_trigger=command): the environment "
                    "steps one depth frame per step; start the run without that setting"
                )
            if info["name"] != SCENE:
                self.client.reset(scene=SCENE, seed=cfg.seed)
                info = self.client.scene_info()
            self.scene = get_scene(info["name"], int(info["seed"]), float(info.get("vegetation", 1.0)))
            endpoints = (zenoh,) if zenoh else tuple(cfg.bridge.listen)
            self.node = RosZenohNode.from_config(cfg.bridge, listen=(), connect=endpoints)
        except BaseException:
            self.client.close()
            raise
        self._cond = threading.Condition()
        self._frame: tuple[int, np.ndarray] | None = None
        self._warned_size = False
        topic = topic_names(cfg.bridge.namespace, CAMERA_NAME)["depth"]
        self.node.subscribe(topic, "sensor_msgs/msg/Image", self._on_depth)

    def _on_depth(self, msg: Any) -> None:
        t_ns, depth = header_ns(msg), decode_depth(msg)
        with self._cond:
            self._frame = (t_ns, depth)
            self._cond.notify_all()

    def _frame_after(self, t_ns: int) -> np.ndarray:
        """The newest depth image stamped at or after ``t_ns`` (the ROS clock), waiting for it."""
        deadline = time.monotonic() + self.timeout
        with self._cond:
            while self._frame is None or self._frame[0] < t_ns:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise TimeoutError(
                        f"no depth frame after t = {t_ns / 1e9:.3f} s within {self.timeout} s: is the "
                        "runtime's bridge reachable on the Zenoh endpoint?"
                    )
                self._cond.wait(remaining)
            depth = self._frame[1]
        if depth.shape != (self.camera.height, self.camera.width) and not self._warned_size:
            self._warned_size = True
            log.warning(
                "the runtime's depth images are %dx%d, the RL camera is %dx%d: start it with "
                "runtime_overrides() so that the strip matches the local environment",
                depth.shape[1],
                depth.shape[0],
                self.camera.width,
                self.camera.height,
            )
        return depth

    def reset(self, position: np.ndarray, yaw: float) -> tuple[np.ndarray, Kinematics]:
        self.client.reset(position=[float(v) for v in position], yaw=float(yaw), airborne=True)
        deadline = time.monotonic() + self.timeout
        while (state := self.client.state())["t"] < RESET_SETTLE_S:
            if time.monotonic() > deadline:
                raise TimeoutError("the remote simulation clock does not advance after the reset")
            time.sleep(0.005)
        with self._cond:
            self._frame = None
        depth = self._frame_after(int(state["stamp_ns"]))
        return depth, Kinematics.from_dict(self.client.state())

    def step(self, forward: float, yaw_rate: float) -> tuple[np.ndarray, Kinematics, bool]:
        accepted = self.client.velocity(forward, yaw_rate)
        depth = self._frame_after(int(accepted["stamp_ns"]) + 1)
        kin = Kinematics.from_dict(self.client.state())
        return depth, kin, kin.mode == "collided"

    def close(self) -> None:
        try:
            self.client.hold()
        except Exception as exc:  # the runtime may be gone already; closing must still succeed
            log.debug("hold on close failed: %s", exc)
        self.node.close()
        self.client.close()
