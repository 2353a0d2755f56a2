"""Inter-process plumbing of the runtime.

* **Control**: the dynamics server is the hub. The render server and the bridge connect to it
  over a local ``multiprocessing.connection`` socket (authenticated with a per-run key) and open
  with a handshake ``{"hello": role, "pid": ...}``; it answers ``{"welcome": role, ...}``. After that
  small messages (tuples) flow: render requests, acknowledgements, states, commands.
* **Images**: a ring of frame slots in shared memory, created by the supervisor. The render server
  writes slot ``seq % slots``; the bridge reads it after the hub forwards the acknowledgement. The hub
  never has more than ``slots - 1`` frames in flight, so a slot is never rewritten while being read.
"""

from __future__ import annotations

import os
import secrets
from dataclasses import dataclass
from multiprocessing import resource_tracker
from multiprocessing.connection import Client, Connection
from multiprocessing.shared_memory import SharedMemory
from typing import Any

import numpy as np

from droneulator.config import CameraConfig

ENV_ADDRESS = "DRONEULATOR_HUB_ADDRESS"
ENV_AUTHKEY = "DRONEULATOR_HUB_AUTHKEY"
ENV_RING = "DRONEULATOR_FRAME_RING"
ENV_CONFIG = "DRONEULATOR_CONFIG_JSON"
PROTOCOL_VERSION = 1


@dataclass
class CameraImages:
    """Views into one slot for one camera (no copies)."""

    rgb: np.ndarray
    depth: np.ndarray
    seg: np.ndarray


class FrameRing:
    """Fixed-layout frame slots in POSIX shared memory, one image set per camera per slot."""

    def __init__(self, name: str, cameras: list[CameraConfig], slots: int, create: bool = False) -> None:
        self.cameras = cameras
        self.slots = slots
        layout: list[tuple[str, str, tuple[int, ...], np.dtype, int]] = []
        offset = 0
        for cam in cameras:
            h, w = cam.height, cam.width
            for kind, shape, dtype in (
                ("depth", (h, w), np.float32),
                ("rgb", (h, w, 3), np.uint8),
                ("seg", (h, w), np.uint8),
            ):
                layout.append((cam.name, kind, shape, np.dtype(dtype), offset))
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
        self._views: list[dict[str, CameraImages]] = []
        for slot in range(slots):
            base = slot * self.slot_bytes
            parts: dict[str, dict[str, np.ndarray]] = {}
            for cam_name, kind, shape, dtype, off in layout:
                parts.setdefault(cam_name, {})[kind] = np.ndarray(shape, dtype, self.shm.buf, base + off)
            self._views.append({n: CameraImages(**p) for n, p in parts.items()})

    @staticmethod
    def new_name() -> str:
        return f"droneulator_{os.getpid()}_{secrets.token_hex(4)}"

    def slot(self, seq: int) -> dict[str, CameraImages]:
        return self._views[seq % self.slots]

    def close(self) -> None:
        self._views.clear()
        self.shm.close()
        if self.owner:
            self.shm.unlink()


def hub_connect(
    role: str, address: str | None = None, authkey: bytes | None = None
) -> tuple[Connection, dict]:
    """Connect to the dynamics server hub and complete the handshake; returns (connection, welcome)."""
    address = address or os.environ[ENV_ADDRESS]
    authkey = authkey or bytes.fromhex(os.environ[ENV_AUTHKEY])
    conn = Client(address, family="AF_UNIX", authkey=authkey)
    conn.send({"hello": role, "pid": os.getpid(), "version": PROTOCOL_VERSION})
    welcome: dict[str, Any] = conn.recv()
    if welcome.get("welcome") != role:
        conn.close()
        raise ConnectionRefusedError(f"hub refused {role}: {welcome.get('error', welcome)}")
    return conn, welcome
