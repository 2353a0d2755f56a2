"""Inter-process plumbing of the runtime.

* **Control**: the dynamics server is the hub. The render server and the bridge connect to it
  over a local ``multiprocessing.connection`` socket (authenticated with a per-run key) and open
  with a handshake (:class:`Hello`, answered by :class:`Welcome` or :class:`Refused`). After that
  only the typed messages below flow, each a small frozen dataclass: :class:`Render` ->
  :class:`Rendered` (render server), :class:`Publish` -> :class:`Published` (bridge), and
  :class:`LoadScene` to both. States travel as :class:`~droneulator.vehicles.vehicle.VehicleState`, every
  vehicle's at one camera instant together (by name).
  Odometry, TF, ``/clock`` and ROS commands do not pass through here: the dynamics server, which
  owns the state, publishes and receives them on Zenoh itself.
* **Images**: a ring of frame slots in shared memory (each slot one image set per camera per vehicle),
  created by the supervisor. The render server
  writes slot ``seq % slots``; the bridge reads it after the hub forwards the acknowledgement. The hub
  never has more than ``slots - 1`` frames in flight, so a slot is never rewritten while being read.
"""

from __future__ import annotations

import os
import secrets
from dataclasses import dataclass, field
from multiprocessing import resource_tracker
from multiprocessing.connection import Client, Connection
from multiprocessing.shared_memory import SharedMemory
from typing import TYPE_CHECKING

import numpy as np

from droneulator.config import CameraConfig, LightConfig

if TYPE_CHECKING:
    from droneulator.vehicles.vehicle import VehicleState

ENV_ADDRESS = "DRONEULATOR_HUB_ADDRESS"
ENV_AUTHKEY = "DRONEULATOR_HUB_AUTHKEY"
ENV_RING = "DRONEULATOR_FRAME_RING"
ENV_CONFIG = "DRONEULATOR_CONFIG_JSON"
ENV_ZENOH = "DRONEULATOR_ZENOH_ENDPOINT"
PROTOCOL_VERSION = 6


# --------------------------------------------------------------------------- typed messages
@dataclass(frozen=True)
class Hello:
    """First message of a process connecting to the hub."""

    role: str
    pid: int
    version: int = PROTOCOL_VERSION


@dataclass(frozen=True)
class Welcome:
    """The hub's answer to a valid :class:`Hello`: the scene to load."""

    role: str
    scene: str
    seed: int


@dataclass(frozen=True)
class Refused:
    """The hub's answer to an invalid :class:`Hello`; the connection is closed after it."""

    reason: str


@dataclass(frozen=True)
class Render:
    """Hub -> render server: draw every vehicle's cameras at ``states`` (by name) into frame slot ``seq``;
    only the cameras of ``rigs`` when given (triggered cameras), with every vehicle's body drawn."""

    seq: int
    states: dict[str, VehicleState]
    rigs: tuple[str, ...] | None = None


@dataclass(frozen=True)
class Rendered:
    """Render server -> hub: slot ``seq`` holds the images."""

    seq: int


@dataclass(frozen=True)
class Publish:
    """Hub -> bridge: publish the images in slot ``seq``, rendered at ``states`` (by vehicle name)."""

    seq: int
    states: dict[str, VehicleState]


@dataclass(frozen=True)
class Published:
    """Bridge -> hub: slot ``seq`` is published and free again."""

    seq: int


@dataclass(frozen=True)
class LoadScene:
    """Hub -> both: the API reset the simulation into another scene, seed, light or vegetation density."""

    scene: str
    seed: int
    light: LightConfig = field(default_factory=LightConfig)
    vegetation: float = 1.0


HubMessage = Render | Rendered | Publish | Published | LoadScene


@dataclass
class CameraImages:
    """Views into one slot for one camera (no copies)."""

    rgb: np.ndarray
    depth: np.ndarray
    seg: np.ndarray


class FrameRing:
    """Fixed-layout frame slots in POSIX shared memory, one image set per camera of every vehicle
    (``rigs``: vehicle name -> its cameras) per slot."""

    def __init__(
        self, name: str, rigs: dict[str, list[CameraConfig]], slots: int, create: bool = False
    ) -> None:
        self.rigs = rigs
        self.slots = slots
        layout: list[tuple[str, str, str, tuple[int, ...], np.dtype, int]] = []
        offset = 0
        for vehicle, cameras in rigs.items():
            for cam in cameras:
                h, w = cam.height, cam.width
                for kind, shape, dtype in (
                    ("depth", (h, w), np.float32),
                    ("rgb", (h, w, 3), np.uint8),
                    ("seg", (h, w), np.uint8),
                ):
                    layout.append((vehicle, cam.name, kind, shape, np.dtype(dtype), offset))
                    offset += int(np.prod(shape)) * np.dtype(dtype).itemsize
                    offset = (offset + 63) // 64 * 64
        self.slot_bytes = offset
        size = max(1, offset * slots)
        if create:
            self.shm = SharedMemory(name=name, create=True, size=size)
        else:
            self.shm = SharedMemory(name=name)
            # Python < 3.13 registers attached segments for unlinking at exit: only the creator may.
            resource_tracker.unregister(self.shm._name, "shared_memory")  # type: ignore[attr-defined]
        self.owner = create
        self._views: list[dict[str, dict[str, CameraImages]]] = []
        for slot in range(slots):
            base = slot * self.slot_bytes
            parts: dict[tuple[str, str], dict[str, np.ndarray]] = {}
            for vehicle, cam_name, kind, shape, dtype, off in layout:
                view = np.ndarray(shape, dtype, self.shm.buf, base + off)
                parts.setdefault((vehicle, cam_name), {})[kind] = view
            views: dict[str, dict[str, CameraImages]] = {v: {} for v in rigs}
            for (vehicle, cam_name), p in parts.items():
                views[vehicle][cam_name] = CameraImages(**p)
            self._views.append(views)

    @staticmethod
    def new_name() -> str:
        return f"droneulator_{os.getpid()}_{secrets.token_hex(4)}"

    def slot(self, seq: int) -> dict[str, dict[str, CameraImages]]:
        """Slot ``seq``'s images: vehicle -> camera -> views."""
        return self._views[seq % self.slots]

    def close(self) -> None:
        self._views.clear()
        self.shm.close()
        if self.owner:
            self.shm.unlink()


class HubGoneError(ConnectionError):
    """The dynamics server's hub is not there (it stopped, or the run is shutting down)."""


def hub_connect(
    role: str, address: str | None = None, authkey: bytes | None = None
) -> tuple[Connection, Welcome]:
    """Connect to the dynamics server hub and complete the handshake; returns (connection, welcome)."""
    address = address or os.environ[ENV_ADDRESS]
    authkey = authkey or bytes.fromhex(os.environ[ENV_AUTHKEY])
    try:
        conn = Client(address, family="AF_UNIX", authkey=authkey)
    except (FileNotFoundError, ConnectionRefusedError) as e:
        raise HubGoneError(f"the dynamics server is not running (hub {address}: {e.strerror})") from None
    conn.send(Hello(role, os.getpid()))
    welcome = conn.recv()
    if not isinstance(welcome, Welcome) or welcome.role != role:
        conn.close()
        reason = welcome.reason if isinstance(welcome, Refused) else repr(welcome)
        raise ConnectionRefusedError(f"hub refused {role}: {reason}")
    return conn, welcome
