"""Stage 3 of a capture: recording from the ROS 2 topics over Zenoh.

:class:`TopicRecorder` subscribes to odometry, ``/tf``, ``/tf_static``, the colour camera, its
segmentation and depth images and its camera_info, exactly as any ROS 2 client would. The
segmentation stands in for a user's segmentation network (it masks SIFT to the tree), the depth is
ground truth for scoring only (which true-surface samples the cameras saw).

:class:`TfBuffer` answers pose lookups at an image's stamp the way tf2 does: static edges as they
are, the ``odom -> base_link`` edge interpolated between its samples (linear in position, slerp in
rotation). :func:`record_view` turns the first frame after the vehicle settled into the view's
record: stamp, optical and base_link poses in ``map``, errors.

The topic names and the TF frame prefix come from the vehicle's entry in the API's ``scene_info``
(:func:`vehicle_streams`): a fleet publishes each vehicle under its own namespace and frame prefix, and
each vehicle's recorder reads only its own.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from droneulator.frames import pose_from_transform, quat_slerp, transform_from_pose
from droneulator.ros.topics import (
    BASE_FRAME,
    MAP_FRAME,
    TYPES,
    decode_depth,
    header_ns,
    vehicle_names,
)
from droneulator.ros.zenoh_node import RosZenohNode
from droneulator.workflows.photogrammetry.plan import Viewpoint

#: odometry samples and TF transforms per frame a recorder keeps: 20 min of sim time at a triggered
#: capture's 25 Hz, which its lockstep simulator, rendering nothing between views, runs through at tens of
#: times real time while the capture records a view
HISTORY = 30_000


class TfBuffer:
    """A small tf2-like buffer: static edges, and timed dynamic edges interpolated at a stamp."""

    def __init__(self, history: int = HISTORY) -> None:
        self._lock = threading.Condition()
        self._static: dict[str, tuple[str, np.ndarray]] = {}
        self._dynamic: dict[str, tuple[str, deque[tuple[int, np.ndarray, np.ndarray]]]] = {}
        self._history = history

    @staticmethod
    def _unpack(tr: Any) -> tuple[str, str, int, np.ndarray, np.ndarray]:
        t, r = tr.transform.translation, tr.transform.rotation
        return (
            tr.header.frame_id,
            tr.child_frame_id,
            header_ns(tr),
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
        q = quat_slerp(q0, q1, f)
        return parent, transform_from_pose(p0 + f * (p1 - p0), q)

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


@dataclass
class AuxFrames:
    """The segmentation (PNG of class ids, as published) and depth (metres, NaN: no return) images that
    share a colour frame's stamp."""

    segmentation_png: bytes
    depth: np.ndarray


def vehicle_streams(
    vehicle: dict[str, Any], camera: str, namespace: str, fleet: bool, fleet_tf: str = "prefix"
) -> tuple[dict[str, str], str]:
    """The topics a capture reads of one vehicle and camera (keys as :data:`TYPES`) and the vehicle's TF
    frame prefix, from its ``scene_info`` entry (``vehicle``), else from the naming rules of
    :func:`~droneulator.ros.topics.vehicle_names` (``namespace``, ``fleet``, ``fleet_tf``)."""
    topics = vehicle.get("topics")
    if topics is None:
        names = vehicle_names(namespace, vehicle["name"], fleet, fleet_tf)
        topics, prefix = names.describe([camera])["topics"], names.frame_prefix
    else:
        prefix = str(vehicle.get("tf_prefix", ""))
    cameras = topics.get("cameras", {})
    if camera not in cameras:
        raise ValueError(
            f"vehicle {vehicle['name']!r} has no camera {camera!r} (cameras: {', '.join(cameras) or 'none'})"
        )
    keys = ("odom", "tf", "tf_static")
    return {**{k: topics[k] for k in keys}, **cameras[camera]}, prefix


#: colour frames, and segmentation and depth images, a recorder keeps (1.6 s at capture's default 10 Hz)
_FRAMES_KEPT = 16


class TopicRecorder:
    """Subscriptions to one vehicle's odometry, TF, colour camera and camera_info, decoded by rosbags.

    ``names``: the topics by :data:`TYPES` key (:func:`vehicle_streams`); ``frame_prefix``: the
    vehicle's TF frame prefix; ``tf``: a buffer already fed with the vehicle's TF topics (vehicles that
    share ``/tf`` share one), else this recorder subscribes to them into a buffer of its own."""

    def __init__(
        self, node: RosZenohNode, names: dict[str, str], frame_prefix: str = "", tf: TfBuffer | None = None
    ) -> None:
        self.names = names
        self.frame_prefix = frame_prefix
        self.base_frame = frame_prefix + BASE_FRAME
        self.tf = tf if tf is not None else TfBuffer()
        self._cond = threading.Condition()
        self._odom: deque[OdomSample] = deque(maxlen=HISTORY)
        self._infos: dict[int, Any] = {}
        self._frames: deque[Frame] = deque(maxlen=_FRAMES_KEPT)
        self._seg: dict[int, bytes] = {}
        self._depth: dict[int, Any] = {}
        handlers: dict[str, Callable[[Any], None]] = {
            "odom": self._on_odom,
            "info_rgb": self._on_info,
            "rgb": self._on_rgb,
            "seg": lambda m: self._keep(self._seg, header_ns(m), bytes(m.data)),
            "depth": lambda m: self._keep(self._depth, header_ns(m), m),
        }
        if tf is None:
            handlers["tf"] = self.tf.on_tf
            handlers["tf_static"] = lambda m: self.tf.on_tf(m, static=True)
        for key, handler in handlers.items():
            node.subscribe(names[key], TYPES[key], handler)

    def _on_odom(self, msg: Any) -> None:
        p, q = msg.pose.pose.position, msg.pose.pose.orientation
        v, w = msg.twist.twist.linear, msg.twist.twist.angular
        s = OdomSample(
            header_ns(msg),
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
            self._infos[header_ns(msg)] = msg
            if len(self._infos) > 64:
                for k in sorted(self._infos)[:-32]:
                    del self._infos[k]
            self._cond.notify_all()

    def _keep(self, store: dict[int, Any], stamp: int, value: Any) -> None:
        with self._cond:
            store[stamp] = value
            if len(store) > _FRAMES_KEPT:
                for k in sorted(store)[:-_FRAMES_KEPT]:
                    del store[k]
            self._cond.notify_all()

    def view_after(self, t_ns: int, timeout: float) -> tuple[Frame, AuxFrames]:
        """The first colour frame stamped at or after ``t_ns`` whose segmentation and depth images (same
        stamp) have arrived too, with them. A frame whose companions were already let go (a consumer that
        fell behind a hovering vehicle's stream) is passed over for the next complete one."""

        def complete() -> tuple[Frame, bytes, Any] | None:
            for f in self._frames:
                if f.stamp >= t_ns and f.stamp in self._seg and f.stamp in self._depth:
                    return f, self._seg[f.stamp], self._depth[f.stamp]
            return None

        what = f"camera frame with segmentation and depth after {t_ns} ns"
        frame, png, depth = self._wait(complete, timeout, what)
        return frame, AuxFrames(png, decode_depth(depth))

    def _on_rgb(self, msg: Any) -> None:
        with self._cond:
            self._frames.append(Frame(header_ns(msg), msg.header.frame_id, bytes(msg.data)))
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

        def newer() -> list[OdomSample]:  # from the newest back: the check runs at every sample
            out = []
            for s in reversed(self._odom):
                if s.stamp <= t_ns:
                    break
                out.append(s)
            return out[::-1]

        return self._wait(newer, timeout, "odometry")

    def latest_odom(self, timeout: float = 30.0) -> OdomSample:
        return self._wait(lambda: self._odom[-1] if self._odom else None, timeout, "odometry")

    def odom_at(self, t_ns: int, timeout: float = 5.0) -> OdomSample:
        """The odometry sample nearest ``t_ns`` once a later one has arrived."""
        samples = self._wait(lambda: self._odom[-1].stamp >= t_ns and list(self._odom), timeout, "odometry")
        return min(samples, key=lambda s: abs(s.stamp - t_ns))

    def camera_info(self, t_ns: int | None = None, timeout: float = 5.0) -> Any:
        """camera_info stamped ``t_ns`` (the latest one when None)."""
        if t_ns is None:
            return self._wait(
                lambda: self._infos[max(self._infos)] if self._infos else None, timeout, "camera_info"
            )
        return self._wait(lambda: self._infos.get(t_ns), timeout, f"camera_info at {t_ns} ns")


def camera_info_dict(info: Any) -> dict[str, Any]:
    """What the dataset keeps of a ``sensor_msgs/CameraInfo``: frame, size, K, distortion, field of view."""
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


def pose_dict(T: np.ndarray) -> dict[str, list[float]]:
    p, q = pose_from_transform(T)
    return {"position": p.tolist(), "quaternion_xyzw": q.tolist()}


def record_view(
    topics: TopicRecorder,
    view: Viewpoint,
    cam: dict[str, Any],
    settled_ns: int,
    leg: dict[str, Any],
    vehicle: str = "uav0",
) -> tuple[dict[str, Any], bytes, AuxFrames]:
    """The first frame after ``vehicle`` settled at ``view``, with its camera_info and the TF poses at
    its stamp: the view's record (``leg``: the flight statistics that brought it there; ``vehicle``, the
    frame id and topic of the image), its JPEG and the segmentation and depth images of the same stamp."""
    frame, aux = topics.view_after(settled_ns, timeout=30.0)
    info = camera_info_dict(topics.camera_info(frame.stamp))
    if info["K"] != cam["K"] or (info["width"], info["height"]) != (cam["width"], cam["height"]):
        raise RuntimeError(f"camera_info changed during the capture: {info} != {cam}")
    T_world_opt = topics.tf.lookup(MAP_FRAME, frame.frame_id, frame.stamp)
    T_world_base = topics.tf.lookup(MAP_FRAME, topics.base_frame, frame.stamp)
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
            "vehicle": vehicle,
            "frame_id": frame.frame_id,
            "topic": topics.names["rgb"],
            "target": {"position": list(view.position), "yaw": view.yaw},
            "optical": pose_dict(T_world_opt),
            "base_link": pose_dict(T_world_base),
            "position_error_m": float(np.linalg.norm(T_world_base[:3, 3] - target)),
            "speed_mps": float(np.linalg.norm(odom.linear)),
            "leg": leg,
        },
        frame.jpeg,
        aux,
    )
