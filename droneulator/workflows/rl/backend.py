"""What both backends of ``droneulator/VineyardNav-v0`` share: the scene, the camera, the vehicle
state an observation needs and the backend interface.

:mod:`.env` (the environment and its local backend) and :mod:`.remote` (the WebSocket/Zenoh backend)
both import this module and never each other at import time.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from droneulator.frames import body_to_world, world_to_body, yaw_of
from droneulator.scenes.base import Scene

SCENE = "vineyard"
CAMERA_NAME = "front"


@dataclass
class Kinematics:
    """The vehicle state an observation needs (Z-up world, quaternion [x, y, z, w], body rates)."""

    t: float
    position: np.ndarray
    quaternion: np.ndarray
    velocity: np.ndarray  # world frame, m/s
    angular_velocity: np.ndarray  # body frame, rad/s
    mode: str

    @classmethod
    def from_dict(cls, st: dict[str, Any]) -> Kinematics:
        """From a state dict of the WebSocket API or :meth:`VehicleState.to_dict`."""
        return cls(
            float(st["t"]),
            np.asarray(st["position"], dtype=float),
            np.asarray(st["quaternion"], dtype=float),
            np.asarray(st["velocity"], dtype=float),
            np.asarray(st["angular_velocity"], dtype=float),
            str(st["mode"]),
        )

    @property
    def yaw(self) -> float:
        return yaw_of(self.quaternion)

    @property
    def forward_speed(self) -> float:
        return float(world_to_body(self.quaternion, self.velocity)[0])

    @property
    def yaw_rate(self) -> float:
        return float(body_to_world(self.quaternion, self.angular_velocity)[2])


class Backend(Protocol):
    """Where the vehicle flies: reset to a pose, step one camera frame under a velocity command."""

    scene: Scene

    def reset(self, position: np.ndarray, yaw: float) -> tuple[np.ndarray, Kinematics]: ...

    def step(self, forward: float, yaw_rate: float) -> tuple[np.ndarray, Kinematics, bool]:
        """Depth image and state at the next camera frame, and whether a collision happened."""
        ...

    def close(self) -> None: ...
