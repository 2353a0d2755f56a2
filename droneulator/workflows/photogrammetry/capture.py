"""``droneulator capture``: fly circular rings of viewpoints around a tree and record a COLMAP dataset.

The client works like a user's own script against a running simulator: waypoints go out over the
WebSocket API; everything recorded comes back from the ROS 2 topics over Zenoh. Each leg is one
min-snap ``goto`` along the circle (wide arcs split into several), and the vehicle counts as settled
when ``/droneulator/odom`` has stayed within position, speed, heading and turn-rate thresholds of the
viewpoint for a while. The next RGB frame after that is recorded with its ``camera_info`` and the
camera pose looked up in TF at the frame's stamp (``odom -> base_link`` from ``/tf``, interpolated
between its 100 Hz samples as tf2 does, and the static chain to the optical frame from ``/tf_static``).

Every view is written as soon as it is captured, and the model files are replaced atomically, so an
interrupted run leaves a valid partial dataset; running the same command again captures only the
views that are missing.

Dataset layout::

    images/NNNN.jpg          JPEG bytes exactly as published
    sparse_known/            COLMAP text model of the known poses (PINHOLE camera, empty points3D.txt)
    poses.json, poses.csv    stamp and pose of the optical frame and of base_link in the world (map)
    metadata.json            settings, intrinsics, tracking errors and timings
    simulator.log            output of the simulator this command started (if it started one)
"""

from __future__ import annotations

import contextlib
import copy
import csv
import ctypes
import io
import json
import math
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from droneulator.api.client import DroneulatorClient
from droneulator.config import CameraConfig, CaptureConfig, SimConfig, to_dict
from droneulator.frames import pose_from_transform, quat_slerp, transform_from_pose, wrap_angle, yaw_of
from droneulator.ros.zenoh_node import RosZenohNode
from droneulator.runtime.bridge import topic_names
from droneulator.workflows.photogrammetry.colmap_model import (
    KnownModel,
    atomic_write,
    colmap_pinhole_params,
    write_text_model,
)

NS = 1_000_000_000
WORLD_FRAME = "map"
BASE_FRAME = "base_link"


# --------------------------------------------------------------------------- the plan
@dataclass(frozen=True)
class Viewpoint:
    """One capture pose: ``index`` names the image (``NNNN.jpg``); ``yaw`` faces the tree."""

    index: int
    ring: int
    azimuth: float
    position: tuple[float, float, float]
    yaw: float

    @property
    def name(self) -> str:
        return image_name(self.index)


def image_name(index: int) -> str:
    return f"{index:04d}.jpg"


def ring_sizes(views: int, rings: int) -> list[int]:
    """Views per ring, shared out as evenly as possible (the first rings take the remainder)."""
    base, extra = divmod(views, rings)
    return [base + (r < extra) for r in range(rings)]


def ring_point(center: Sequence[float], radius: float, azimuth: float, altitude: float) -> np.ndarray:
    return np.array(
        [center[0] + radius * math.cos(azimuth), center[1] + radius * math.sin(azimuth), altitude]
    )


def facing_yaw(center: Sequence[float], p: Sequence[float]) -> float:
    """Heading from ``p`` towards the vertical axis through ``center``."""
    return math.atan2(center[1] - p[1], center[0] - p[0])


def plan_viewpoints(
    center: Sequence[float],
    radius: float,
    altitudes: Sequence[float],
    views: int,
    arc_deg: float = 360.0,
    start_azimuth: float = 0.0,
) -> list[Viewpoint]:
    """Rings of evenly spaced viewpoints around ``center`` (x, y), counter-clockwise, ring after ring.

    A full circle (``arc_deg`` 360) spaces a ring's views by 360/n and staggers successive rings by half
    a spacing so that their views interleave; a partial arc puts views at both of its ends.
    """
    plan: list[Viewpoint] = []
    full = arc_deg >= 360.0
    for ring, (alt, n) in enumerate(zip(altitudes, ring_sizes(views, len(altitudes)), strict=True)):
        step = math.radians(arc_deg) / (n if full else max(n - 1, 1))
        offset = 0.5 * (ring % 2) if full else 0.0
        for j in range(n):
            az = wrap_angle(start_azimuth + (j + offset) * step)
            p = ring_point(center, radius, az, alt)
            plan.append(Viewpoint(len(plan), ring, az, tuple(float(v) for v in p), facing_yaw(center, p)))
    return plan


def aim_pitch_deg(
    radius: float, altitudes: Sequence[float], look_at_z: float, mount: Sequence[float]
) -> float:
    """Mount pitch (degrees, positive down) that points the optical axis at height ``look_at_z`` on the
    tree's axis from the mean ring altitude, for a camera mounted at ``mount`` (body FLU) facing the tree."""
    drop = float(np.mean(altitudes)) + mount[2] - look_at_z
    return math.degrees(math.atan2(drop, radius - mount[0]))


def arc_waypoints(
    center: Sequence[float], radius: float, altitude: float, az_from: float, az_to: float, max_step_deg: float
) -> list[np.ndarray]:
    """Points along the shorter arc from ``az_from`` to ``az_to`` (end included), ``max_step_deg`` apart
    at most."""
    delta = wrap_angle(az_to - az_from)
    if abs(delta) < 1e-9:
        return []
    n = max(1, math.ceil(abs(math.degrees(delta)) / max_step_deg - 1e-9))
    return [ring_point(center, radius, az_from + delta * (k + 1) / n, altitude) for k in range(n)]


def segment_errors(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance of each point (n, 3) from the segment a-b, and its height error against the segment's
    height at the closest point: the tracking errors against a straight commanded path."""
    points = np.atleast_2d(points)
    ab = b - a
    denom = float(ab @ ab)
    s = np.zeros(len(points)) if denom < 1e-12 else np.clip((points - a) @ ab / denom, 0.0, 1.0)
    closest = a + s[:, None] * ab
    return np.linalg.norm(points - closest, axis=1), np.abs(points[:, 2] - closest[:, 2])


def pending_views(plan: Sequence[Viewpoint], done: set[int] | dict[int, Any]) -> list[Viewpoint]:
    """The viewpoints still to capture, in flight order."""
    return [v for v in plan if v.index not in done]


# --------------------------------------------------------------------------- TF
class TfBuffer:
    """A small tf2-like buffer: static edges, and timed dynamic edges interpolated at a stamp."""

    def __init__(self, history: int = 4000) -> None:
        self._lock = threading.Condition()
        self._static: dict[str, tuple[str, np.ndarray]] = {}
        self._dynamic: dict[str, tuple[str, deque[tuple[int, np.ndarray, np.ndarray]]]] = {}
        self._history = history

    @staticmethod
    def _unpack(tr: Any) -> tuple[str, str, int, np.ndarray, np.ndarray]:
        t, r = tr.transform.translation, tr.transform.rotation
        stamp = tr.header.stamp.sec * NS + tr.header.stamp.nanosec
        return (
            tr.header.frame_id,
            tr.child_frame_id,
            stamp,
            np.array([t.x, t.y, t.z]),
            np.array([r.x, r.y, r.z, r.w]),
        )

    def on_tf(self, msg: Any, static: bool = False) -> None:
        with self._lock:
            for tr in msg.transforms:
                parent, child, stamp, p, q = self._unpack(tr)
                if static:
                    self._static[child] = (parent, transform_from_pose(p, q))
                    continue
                entry = self._dynamic.get(child)
                if entry is None or entry[0] != parent:
                    entry = (parent, deque(maxlen=self._history))
                    self._dynamic[child] = entry
                series = entry[1]
                if series and stamp < series[-1][0]:  # the clock went back (a reset): start over
                    series.clear()
                series.append((stamp, p, q))
            self._lock.notify_all()

    def _edge(self, child: str, t_ns: int) -> tuple[str, np.ndarray] | None:
        """``(parent, T_parent_child)`` at ``t_ns``; None while the data to answer is not there yet."""
        if child in self._static:
            return self._static[child]
        if child not in self._dynamic:
            return None
        parent, series = self._dynamic[child]
        if not series or series[-1][0] < t_ns:
            return None
        if series[0][0] > t_ns:
            raise LookupError(f"TF {parent} -> {child} at {t_ns} ns is older than the buffer")
        stamps = [s for s, _, _ in series]
        i = int(np.searchsorted(stamps, t_ns))
        s1, p1, q1 = series[i]
        if s1 == t_ns or i == 0:
            return parent, transform_from_pose(p1, q1)
        s0, p0, q0 = series[i - 1]
        f = (t_ns - s0) / (s1 - s0)
        return parent, transform_from_pose(p0 + f * (p1 - p0), quat_slerp(q0, q1, f))

    def lookup(self, target: str, source: str, t_ns: int, timeout: float = 5.0) -> np.ndarray:
        """``T_target_source`` at ``t_ns``, waiting up to ``timeout`` s for the transforms to arrive."""
        deadline = time.monotonic() + timeout
        with self._lock:
            while True:
                T = np.eye(4)
                frame = source
                while frame != target:
                    edge = self._edge(frame, t_ns)
                    if edge is None:
                        break
                    frame, T_parent = edge[0], edge[1]
                    T = T_parent @ T
                else:
                    return T
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise TimeoutError(f"no TF {target} -> {source} at {t_ns} ns (stuck at {frame!r})")
                self._lock.wait(remaining)


# --------------------------------------------------------------------------- topics
@dataclass
class OdomSample:
    stamp: int
    position: np.ndarray
    quaternion: np.ndarray
    linear: np.ndarray  # body frame, m/s
    angular: np.ndarray  # body frame, rad/s


@dataclass
class Frame:
    stamp: int
    frame_id: str
    jpeg: bytes


class Topics:
    """Subscriptions to odometry, TF, the colour camera and its camera_info, decoded by rosbags."""

    def __init__(self, node: RosZenohNode, namespace: str, camera: str) -> None:
        self.tf = TfBuffer()
        self._cond = threading.Condition()
        self._odom: deque[OdomSample] = deque(maxlen=6000)
        self._infos: dict[int, Any] = {}
        self._frames: deque[Frame] = deque(maxlen=8)
        names = topic_names(namespace, camera)
        node.subscribe(f"/{namespace}/odom", "nav_msgs/msg/Odometry", self._on_odom)
        node.subscribe("/tf", "tf2_msgs/msg/TFMessage", self.tf.on_tf)
        node.subscribe("/tf_static", "tf2_msgs/msg/TFMessage", lambda m: self.tf.on_tf(m, static=True))
        node.subscribe(names["info_rgb"], "sensor_msgs/msg/CameraInfo", self._on_info)
        node.subscribe(names["rgb"], "sensor_msgs/msg/CompressedImage", self._on_rgb)

    @staticmethod
    def _stamp(msg: Any) -> int:
        return msg.header.stamp.sec * NS + msg.header.stamp.nanosec

    def _on_odom(self, msg: Any) -> None:
        p, q = msg.pose.pose.position, msg.pose.pose.orientation
        v, w = msg.twist.twist.linear, msg.twist.twist.angular
        s = OdomSample(
            self._stamp(msg),
            np.array([p.x, p.y, p.z]),
            np.array([q.x, q.y, q.z, q.w]),
            np.array([v.x, v.y, v.z]),
            np.array([w.x, w.y, w.z]),
        )
        with self._cond:
            if self._odom and s.stamp < self._odom[-1].stamp:
                self._odom.clear()
            self._odom.append(s)
            self._cond.notify_all()

    def _on_info(self, msg: Any) -> None:
        with self._cond:
            self._infos[self._stamp(msg)] = msg
            if len(self._infos) > 64:
                for k in sorted(self._infos)[:-32]:
                    del self._infos[k]
            self._cond.notify_all()

    def _on_rgb(self, msg: Any) -> None:
        with self._cond:
            self._frames.append(Frame(self._stamp(msg), msg.header.frame_id, bytes(msg.data)))
            self._cond.notify_all()

    def _wait(self, predicate: Callable[[], Any], timeout: float, what: str) -> Any:
        deadline = time.monotonic() + timeout
        with self._cond:
            while not (result := predicate()):
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise TimeoutError(f"no {what} within {timeout:.0f} s")
                self._cond.wait(remaining)
            return result

    def odom_after(self, t_ns: int, timeout: float) -> list[OdomSample]:
        """Odometry samples stamped after ``t_ns``, waiting up to ``timeout`` s for at least one."""
        return self._wait(lambda: [s for s in self._odom if s.stamp > t_ns], timeout, "odometry")

    def latest_odom(self, timeout: float = 30.0) -> OdomSample:
        return self._wait(lambda: self._odom[-1] if self._odom else None, timeout, "odometry")

    def odom_at(self, t_ns: int, timeout: float = 5.0) -> OdomSample:
        """The odometry sample nearest ``t_ns`` once a later one has arrived."""
        samples = self._wait(lambda: self._odom[-1].stamp >= t_ns and list(self._odom), timeout, "odometry")
        return min(samples, key=lambda s: abs(s.stamp - t_ns))

    def frame_after(self, t_ns: int, timeout: float) -> Frame:
        """The first colour frame stamped at or after ``t_ns``."""
        return self._wait(
            lambda: next((f for f in self._frames if f.stamp >= t_ns), None), timeout, "camera frame"
        )

    def camera_info(self, t_ns: int | None = None, timeout: float = 5.0) -> Any:
        """camera_info stamped ``t_ns`` (the latest one when None)."""
        if t_ns is None:
            return self._wait(
                lambda: self._infos[max(self._infos)] if self._infos else None, timeout, "camera_info"
            )
        return self._wait(lambda: self._infos.get(t_ns), timeout, f"camera_info at {t_ns} ns")


# --------------------------------------------------------------------------- the dataset
class DatasetMismatchError(ValueError):
    """The output folder holds a capture made with other settings."""


@dataclass
class CaptureDataset:
    """A capture folder: views are added one at a time and every file is rewritten atomically."""

    root: Path
    plan_settings: dict[str, Any]
    views: dict[int, dict[str, Any]] = field(default_factory=dict)
    camera: dict[str, Any] | None = None
    runs: list[dict[str, Any]] = field(default_factory=list)

    @property
    def images_dir(self) -> Path:
        return self.root / "images"

    @classmethod
    def open(cls, root: Path, plan_settings: dict[str, Any]) -> CaptureDataset:
        """Open ``root`` for ``plan_settings``: a new folder, or one to resume with the same settings."""
        root = Path(root)
        ds = cls(root, plan_settings)
        meta_path, poses_path = root / "metadata.json", root / "poses.json"
        if meta_path.exists():
            meta = json.loads(meta_path.read_text())
            if meta.get("plan") != plan_settings:
                diff = {
                    k: (meta.get("plan", {}).get(k), v)
                    for k, v in plan_settings.items()
                    if meta.get("plan", {}).get(k) != v
                }
                raise DatasetMismatchError(
                    f"{root} holds a capture with other settings ({diff}, as (stored, requested)); "
                    "use another --out or the stored settings"
                )
            ds.runs = list(meta.get("runs", []))
        if poses_path.exists():
            poses = json.loads(poses_path.read_text())
            ds.camera = poses.get("camera")
            for v in poses.get("views", []):
                if (ds.images_dir / v["name"]).is_file():
                    ds.views[int(v["index"])] = v
        return ds

    def set_camera(self, info: dict[str, Any]) -> None:
        if self.camera is not None and (
            self.camera["width"] != info["width"]
            or self.camera["height"] != info["height"]
            or not np.allclose(self.camera["K"], info["K"], atol=1e-9)
        ):
            raise DatasetMismatchError(
                f"{self.root}: the camera publishes {info['width']}x{info['height']} K={info['K']}, "
                f"the stored views used {self.camera['width']}x{self.camera['height']} K={self.camera['K']}"
            )
        self.camera = info

    def add(self, view: dict[str, Any], jpeg: bytes, run: dict[str, Any]) -> None:
        """Store one captured view: its image first, then the files that list it."""
        atomic_write(self.images_dir / view["name"], jpeg)
        self.views[int(view["index"])] = view
        self.write(run)

    def write(self, run: dict[str, Any] | None = None) -> None:
        views = [self.views[i] for i in sorted(self.views)]
        if self.camera is None:
            return
        poses = {
            "world_frame": WORLD_FRAME,
            "camera_frame": self.camera["frame_id"],
            "conventions": "positions in metres in the world frame (ENU, z up); quaternions [x, y, z, w] "
            "rotating the frame's axes into the world; K in the OpenCV/ROS pixel convention",
            "camera": self.camera,
            "views": views,
        }
        atomic_write(self.root / "poses.json", json.dumps(poses, indent=1))
        atomic_write(self.root / "poses.csv", _poses_csv(views))
        model = KnownModel.from_views(
            np.array(self.camera["K"]),
            self.camera["width"],
            self.camera["height"],
            [(v["image_id"], v["name"], _T_world_optical(v)) for v in views],
        )
        write_text_model(self.root / "sparse_known", model)
        atomic_write(self.root / "metadata.json", json.dumps(self.metadata(run), indent=1))

    def metadata(self, run: dict[str, Any] | None) -> dict[str, Any]:
        runs = [*self.runs, run] if run is not None else self.runs
        views = [self.views[i] for i in sorted(self.views)]
        legs = [v["leg"] for v in views if v["leg"]["kind"] == "capture"]
        K = np.array(self.camera["K"]) if self.camera else None
        s = self.plan_settings
        return {
            "scene": s["scene"],
            "seed": s["seed"],
            "views": s["views"],
            "views_captured": len(views),
            "complete": len(views) == s["views"],
            "radius": s["radius"],
            "altitudes": s["altitudes"],
            "pitch_deg": s["pitch_deg"],
            "resolution": [s["width"], s["height"]],
            "hfov_deg": s["hfov_deg"],
            "K": K.tolist() if K is not None else None,
            "colmap_pinhole": colmap_pinhole_params(K).tolist() if K is not None else None,
            "pixel_convention": "K: OpenCV/ROS (pixel centres at integers); COLMAP PINHOLE: cx, cy + 0.5",
            "tracking": {
                "per_view": {
                    v["name"]: {
                        "kind": v["leg"]["kind"],
                        "max_path_error_m": v["leg"]["max_path_error_m"],
                        "max_altitude_error_m": v["leg"]["max_altitude_error_m"],
                    }
                    for v in views
                },
                "max_path_error_m": max((g["max_path_error_m"] for g in legs), default=None),
                "max_altitude_error_m": max((g["max_altitude_error_m"] for g in legs), default=None),
                "capture_legs": len(legs),
            },
            "plan": s,
            "runs": runs,
            "timings": {
                "capture_wall_s": sum(r.get("wall_s", 0.0) for r in runs),
                "sim_s": sum(r.get("sim_s", 0.0) for r in runs),
            },
        }

    def finish_run(self, run: dict[str, Any]) -> None:
        self.runs.append(run)
        self.write()


def _T_world_optical(view: dict[str, Any]) -> np.ndarray:
    o = view["optical"]
    return transform_from_pose(np.array(o["position"]), np.array(o["quaternion_xyzw"]))


def _poses_csv(views: list[dict[str, Any]]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    cols = ["x", "y", "z", "qx", "qy", "qz", "qw"]
    w.writerow(["index", "name", "stamp_ns", *(f"optical_{c}" for c in cols), *(f"base_{c}" for c in cols)])
    for v in views:
        o, b = v["optical"], v["base_link"]
        w.writerow(
            [
                v["index"],
                v["name"],
                v["stamp_ns"],
                *(repr(float(x)) for x in [*o["position"], *o["quaternion_xyzw"]]),
                *(repr(float(x)) for x in [*b["position"], *b["quaternion_xyzw"]]),
            ]
        )
    return buf.getvalue()


# --------------------------------------------------------------------------- the simulator process
def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _die_with_parent() -> None:
    """Runs in the child before exec: receive SIGTERM when this process dies."""
    ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


def camera_for(cap: CaptureConfig, pitch_deg: float) -> CameraConfig:
    return CameraConfig(
        name=cap.camera,
        width=cap.width,
        height=cap.height,
        hfov_deg=cap.hfov_deg,
        rpy_deg=(0.0, pitch_deg, 0.0),
    )


class SimulatorProcess:
    """``droneulator run`` as a child process on free ports, with the capture camera rig."""

    def __init__(self, cfg: SimConfig, log_path: Path, start_timeout: float = 90.0) -> None:
        self.cfg = cfg
        self.api_port, self.zenoh_port = free_port(), free_port()
        cfg.runtime.api_port = self.api_port
        cfg.runtime.mode = "lockstep"
        cfg.bridge.listen = [f"tcp/127.0.0.1:{self.zenoh_port}"]
        cfg.bridge.connect = []
        self._conf = tempfile.NamedTemporaryFile("w", suffix=".json", prefix="droneulator-capture-")  # noqa: SIM115
        json.dump(to_dict(cfg), self._conf)
        self._conf.flush()
        log_path.parent.mkdir(parents=True, exist_ok=True)
        self._log = open(log_path, "a")  # noqa: SIM115
        cmd = [sys.executable, "-m", "droneulator.cli", "run", "--config", self._conf.name]
        cmd += ["--scene", cfg.scene, "--seed", str(cfg.seed)]
        self.proc = subprocess.Popen(
            cmd,
            stdout=self._log,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            preexec_fn=_die_with_parent,
            start_new_session=True,  # Ctrl-C reaches the capture, which then stops the simulator itself
        )
        self.log_path = log_path
        self.start_timeout = start_timeout

    @property
    def url(self) -> str:
        return f"ws://127.0.0.1:{self.api_port}"

    @property
    def zenoh_endpoint(self) -> str:
        return self.cfg.bridge.listen[0]

    def connect(self) -> DroneulatorClient:
        deadline = time.monotonic() + self.start_timeout
        while True:
            try:
                return DroneulatorClient(self.url, timeout=30.0)
            except OSError:
                if self.proc.poll() is not None or time.monotonic() > deadline:
                    tail = self.log_path.read_text().splitlines()[-20:]
                    raise RuntimeError("the simulator did not start:\n  " + "\n  ".join(tail)) from None
                time.sleep(0.2)

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._log.close()
        self._conf.close()


# --------------------------------------------------------------------------- flying
@dataclass
class LegStats:
    kind: str
    max_path_error_m: float = 0.0
    max_altitude_error_m: float = 0.0
    flight_sim_s: float = 0.0
    settle_sim_s: float = 0.0
    gotos: int = 0

    def merge(self, other: LegStats) -> None:
        self.max_path_error_m = max(self.max_path_error_m, other.max_path_error_m)
        self.max_altitude_error_m = max(self.max_altitude_error_m, other.max_altitude_error_m)
        self.flight_sim_s += other.flight_sim_s
        self.settle_sim_s += other.settle_sim_s
        self.gotos += other.gotos

    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "max_path_error_m": round(self.max_path_error_m, 5),
            "max_altitude_error_m": round(self.max_altitude_error_m, 5),
            "flight_sim_s": round(self.flight_sim_s, 3),
            "settle_sim_s": round(self.settle_sim_s, 3),
            "gotos": self.gotos,
        }


class CollisionError(RuntimeError):
    pass


class Flyer:
    """Sends gotos over the WebSocket API and judges arrival from the published odometry."""

    def __init__(
        self, client: DroneulatorClient, topics: Topics, cap: CaptureConfig, center: Sequence[float]
    ):
        self.client = client
        self.topics = topics
        self.cap = cap
        self.center = np.asarray(center, dtype=float)
        self.commanded: np.ndarray | None = None

    def _check_events(self) -> None:
        while (msg := self.client.next_message(timeout=0.0)) is not None:
            if msg.get("type") == "event" and msg["event"].get("type") == "collision":
                raise CollisionError(f"the vehicle collided at {msg['event'].get('position')}")

    def _in_tolerance(self, s: OdomSample, goal: np.ndarray, yaw: float) -> bool:
        c = self.cap
        return (
            float(np.linalg.norm(s.position - goal)) <= c.settle_position_m
            and float(np.linalg.norm(s.linear)) <= c.settle_speed_mps
            and abs(wrap_angle(yaw_of(s.quaternion) - yaw)) <= math.radians(c.settle_yaw_deg)
            and float(np.linalg.norm(s.angular)) <= math.radians(c.settle_rate_dps)
        )

    def goto(self, goal: np.ndarray, yaw: float, kind: str) -> tuple[LegStats, int]:
        """Fly one min-snap leg to ``goal``; returns its tracking statistics and the settle stamp (ns)."""
        start = self.commanded if self.commanded is not None else self.topics.latest_odom().position
        reply = self.client.goto(goal.tolist(), yaw=yaw, speed=self.cap.speed)
        t0 = round(reply["t"] * NS)
        stats = LegStats(kind, gotos=1)
        self.commanded = goal.copy()
        deadline = time.monotonic() + self.cap.leg_timeout_s
        run_start: int | None = None
        last = t0
        while True:
            self._check_events()
            samples = self.topics.odom_after(last, timeout=max(0.1, deadline - time.monotonic()))
            pts = np.array([s.position for s in samples])
            path_err, alt_err = segment_errors(pts, start, goal)
            stats.max_path_error_m = max(stats.max_path_error_m, float(path_err.max()))
            stats.max_altitude_error_m = max(stats.max_altitude_error_m, float(alt_err.max()))
            for s in samples:
                if not self._in_tolerance(s, goal, yaw):
                    run_start = None
                    continue
                if run_start is None:
                    run_start = s.stamp
                if s.stamp - run_start >= self.cap.settle_time_s * NS:
                    stats.flight_sim_s = (run_start - t0) / NS
                    stats.settle_sim_s = (s.stamp - run_start) / NS
                    return stats, s.stamp
            last = samples[-1].stamp
            if time.monotonic() > deadline:
                s = samples[-1]
                raise TimeoutError(
                    f"not settled at {goal.round(3).tolist()} within {self.cap.leg_timeout_s} s: odometry "
                    f"{s.position.round(3).tolist()}, speed {np.linalg.norm(s.linear):.3f} m/s"
                )

    def fly(self, waypoints: list[np.ndarray], kind: str) -> tuple[LegStats, int | None]:
        """Fly through ``waypoints`` (each a goto facing the tree); merged statistics, last settle stamp."""
        total = LegStats(kind)
        stamp = None
        for p in waypoints:
            stats, stamp = self.goto(p, facing_yaw(self.center, p), kind)
            total.merge(stats)
        return total, stamp

    def transit(self, view: Viewpoint, radius: float) -> tuple[LegStats, int | None]:
        """Reach ``view`` from anywhere outside the crown: out (or in) to the ring at the current azimuth
        and altitude, up or down to the ring, then along the circle, so the path never crosses the tree."""
        cur = self.topics.latest_odom().position
        az = math.atan2(cur[1] - self.center[1], cur[0] - self.center[0])
        pts = []
        if abs(math.hypot(*(cur[:2] - self.center[:2])) - radius) > self.cap.settle_position_m:
            pts.append(ring_point(self.center, radius, az, cur[2]))
        if abs(cur[2] - view.position[2]) > self.cap.settle_position_m:
            pts.append(ring_point(self.center, radius, az, view.position[2]))
        pts += arc_waypoints(self.center, radius, view.position[2], az, view.azimuth, self.cap.max_leg_deg)
        if not pts or np.linalg.norm(pts[-1] - np.array(view.position)) > 1e-6:
            pts.append(np.array(view.position))
        return self.fly(pts, "transit")


# --------------------------------------------------------------------------- the capture
def plan_settings(cfg: SimConfig, pitch_deg: float, cam: dict[str, Any]) -> dict[str, Any]:
    """What fixes the dataset's views: a resumed capture must use exactly these."""
    c = cfg.capture
    return {
        "scene": cfg.scene,
        "seed": cfg.seed,
        "views": c.views,
        "radius": c.radius,
        "altitudes": [float(a) for a in c.altitudes],
        "arc_deg": c.arc_deg,
        "pitch_deg": round(float(pitch_deg), 6),
        "width": int(cam["width"]),
        "height": int(cam["height"]),
        "hfov_deg": round(float(cam["hfov_deg"]), 6),
    }


def _info_dict(info: Any) -> dict[str, Any]:
    K = np.array(info.k, dtype=float).reshape(3, 3)
    return {
        "frame_id": info.header.frame_id,
        "width": int(info.width),
        "height": int(info.height),
        "K": K.tolist(),
        "distortion_model": info.distortion_model,
        "D": [float(d) for d in info.d],
        "hfov_deg": math.degrees(2 * math.atan(info.width / 2 / K[0, 0])),
    }


def _pose_dict(T: np.ndarray) -> dict[str, list[float]]:
    p, q = pose_from_transform(T)
    return {"position": p.tolist(), "quaternion_xyzw": q.tolist()}


def capture(
    cfg: SimConfig,
    out: Path,
    url: str | None = None,
    zenoh_endpoint: str | None = None,
    progress: bool = True,
    log: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Capture ``cfg.capture.views`` views of ``cfg.scene`` into ``out`` (resuming what is there).

    Without ``url`` a ``droneulator run`` child process is started with the capture camera and stopped
    at the end; with ``url`` the simulator at that WebSocket URL is used (its camera rig as it is) and
    its ROS topics are read from ``zenoh_endpoint`` (default: ``cfg.bridge.listen``).
    """
    out = Path(out)
    cap = cfg.capture
    wall0 = time.monotonic()
    from droneulator.scenes import get_scene

    scene = get_scene(cfg.scene, cfg.seed)
    center = np.asarray(scene.landmarks["tree"], dtype=float)
    look_at_z = float(np.asarray(scene.landmarks.get("crown_center", center))[2])
    mount = CameraConfig().position
    pitch = (
        cap.pitch_deg
        if cap.pitch_deg is not None
        else aim_pitch_deg(cap.radius, cap.altitudes, look_at_z, mount)
    )
    sim: SimulatorProcess | None = None
    client: DroneulatorClient | None = None
    node: RosZenohNode | None = None
    timings: dict[str, float] = {}
    try:
        if url is None:
            run_cfg = copy.deepcopy(cfg)
            run_cfg.render.cameras = [camera_for(cap, pitch)]
            run_cfg.render.camera_hz = cap.camera_hz
            run_cfg.bridge.jpeg_quality = cap.jpeg_quality
            sim = SimulatorProcess(run_cfg, out / "simulator.log")
            client = sim.connect()
            zenoh_endpoint = sim.zenoh_endpoint
        else:
            client = DroneulatorClient(url, timeout=30.0)
            zenoh_endpoint = zenoh_endpoint or cfg.bridge.listen[0]
            info = client.scene_info()
            if (info["name"], info["seed"]) != (cfg.scene, cfg.seed):
                log(
                    f"resetting the simulator from {info['name']} (seed {info['seed']}) "
                    f"to {cfg.scene} (seed {cfg.seed})"
                )
                client.reset(scene=cfg.scene, seed=cfg.seed)
        node = RosZenohNode.from_config(cfg.bridge, listen=(), connect=(zenoh_endpoint,))
        topics = Topics(node, cfg.bridge.namespace, cap.camera)
        client.subscribe(["events"])
        cam = _info_dict(topics.camera_info(timeout=60.0))
        T_base_opt = topics.tf.lookup(BASE_FRAME, cam["frame_id"], topics.latest_odom().stamp, timeout=30.0)
        pitch_used = math.degrees(math.asin(float(np.clip(T_base_opt[:3, 2] @ [0.0, 0.0, -1.0], -1, 1))))
        if url is not None:
            pitch = pitch_used
        dataset = CaptureDataset.open(out, plan_settings(cfg, pitch, cam))
        dataset.set_camera(cam)
        timings["startup_s"] = time.monotonic() - wall0

        plan = plan_viewpoints(center, cap.radius, cap.altitudes, cap.views, cap.arc_deg)
        todo = pending_views(plan, dataset.views)
        log(
            f"capture {cfg.scene} (seed {cfg.seed}): {len(plan)} views on {len(cap.altitudes)} ring(s), "
            f"radius {cap.radius} m, altitudes {cap.altitudes} m, pitch {pitch:.1f} deg, "
            f"{cam['width']}x{cam['height']}, {len(plan) - len(todo)} already in {out}"
        )
        t_sim0 = topics.latest_odom().stamp
        run: dict[str, Any] = {"started": time.strftime("%Y-%m-%d %H:%M:%S"), "captured": 0}
        flyer = Flyer(client, topics, cap, center)
        if todo:
            state = client.state()
            if state["mode"] in ("idle", "collided") or state["position"][2] < 0.3:
                t = time.monotonic()
                client.takeoff(altitude=float(todo[0].position[2]))
                client.wait_for_event("arrived", timeout=cap.leg_timeout_s)
                timings["takeoff_s"] = time.monotonic() - t
        t_fly = time.monotonic()
        previous: Viewpoint | None = None
        bar = tqdm(
            total=len(plan), initial=len(plan) - len(todo), unit="view", desc="capture", disable=not progress
        )
        try:
            for view in todo:
                adjacent = (
                    previous is not None
                    and previous.ring == view.ring
                    and view.index == previous.index + 1
                    and flyer.commanded is not None
                    and np.allclose(flyer.commanded, previous.position)
                )
                if adjacent:
                    pts = arc_waypoints(
                        center, cap.radius, view.position[2], previous.azimuth, view.azimuth, cap.max_leg_deg
                    )
                    stats, settled = flyer.fly(pts, "capture")
                else:
                    stats, settled = flyer.transit(view, cap.radius)
                assert settled is not None
                record, jpeg = _record(topics, view, cam, settled, stats)
                run["captured"] += 1
                run["wall_s"] = time.monotonic() - wall0
                run["sim_s"] = (settled - t_sim0) / NS
                dataset.add(record, jpeg, run)
                previous = view
                bar.set_postfix(
                    path_err=f"{stats.max_path_error_m:.3f}m", alt_err=f"{stats.max_altitude_error_m:.3f}m"
                )
                bar.update(1)
        finally:
            bar.close()
            timings["flight_s"] = time.monotonic() - t_fly
            run["wall_s"] = time.monotonic() - wall0
            with contextlib.suppress(TimeoutError):
                run["sim_s"] = (topics.latest_odom(timeout=1.0).stamp - t_sim0) / NS
            run["timings"] = {k: round(v, 3) for k, v in timings.items()}
            run["complete"] = len(dataset.views) == len(plan)
            if dataset.camera is not None:
                dataset.finish_run(run)
        meta = dataset.metadata(None)
        tr = meta["tracking"]
        log(
            f"captured {run['captured']} view(s) in {run['wall_s']:.1f} s wall ({run['sim_s']:.1f} s sim); "
            f"{len(dataset.views)}/{len(plan)} in {out}; max tracking error over {tr['capture_legs']} "
            f"capture legs: path {_fmt_m(tr['max_path_error_m'])}, "
            f"altitude {_fmt_m(tr['max_altitude_error_m'])}"
        )
        return meta
    finally:
        if node is not None:
            node.close()
        if client is not None:
            with contextlib.suppress(Exception):
                client.close()
        if sim is not None:
            sim.stop()


def _fmt_m(v: float | None) -> str:
    return "-" if v is None else f"{v:.3f} m"


def _record(
    topics: Topics, view: Viewpoint, cam: dict[str, Any], settled_ns: int, stats: LegStats
) -> tuple[dict[str, Any], bytes]:
    """The first frame after the vehicle settled, with its camera_info and TF poses at its stamp."""
    frame = topics.frame_after(settled_ns, timeout=30.0)
    info = _info_dict(topics.camera_info(frame.stamp))
    if info["K"] != cam["K"] or (info["width"], info["height"]) != (cam["width"], cam["height"]):
        raise RuntimeError(f"camera_info changed during the capture: {info} != {cam}")
    T_world_opt = topics.tf.lookup(WORLD_FRAME, frame.frame_id, frame.stamp)
    T_world_base = topics.tf.lookup(WORLD_FRAME, BASE_FRAME, frame.stamp)
    odom = topics.odom_at(frame.stamp)
    target = np.array(view.position)
    return (
        {
            "index": view.index,
            "image_id": view.index + 1,
            "name": view.name,
            "ring": view.ring,
            "azimuth_deg": math.degrees(view.azimuth),
            "stamp_ns": frame.stamp,
            "target": {"position": list(view.position), "yaw": view.yaw},
            "optical": _pose_dict(T_world_opt),
            "base_link": _pose_dict(T_world_base),
            "position_error_m": float(np.linalg.norm(T_world_base[:3, 3] - target)),
            "speed_mps": float(np.linalg.norm(odom.linear)),
            "leg": stats.to_dict(),
        },
        frame.jpeg,
    )
