"""What the simulator publishes to ROS 2 and what it takes from it, one class per concern.

* :class:`StatePublisher`: ``/clock``, ``/<ns>/odom``, ``/tf`` and ``/tf_static``. It runs in the process
  that owns the vehicle state (the dynamics server), right after the physics step that produced the
  state, so odometry never waits for another process.
* :class:`FramePublisher`: every camera's images, camera_info and optical-frame pose (the bridge process).
* :func:`subscribe_commands`: ``/<ns>/cmd_vel``, ``/<ns>/goal_pose`` and ``/<ns>/position_cmd`` into the
  one :class:`~droneulator.commands.path.CommandPath`, with the WebSocket API's validation and flight lock.

Everything is stamped with the simulator's monotonic clock (:attr:`VehicleState.stamp_ns`), which
never runs backwards, not even across a reset.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from droneulator.frames import (
    T_link_optical,
    T_world_optical,
    pose_from_transform,
    transform_from_pose,
    yaw_of,
)
from droneulator.frames_numba import body_to_world, world_to_body
from droneulator.imaging import encode_jpeg, encode_png
from droneulator.ros import messages as M
from droneulator.ros.topics import BASE_FRAME, MAP_FRAME, ODOM_FRAME, TYPES, optical_frame, topic_names
from droneulator.ros.topics import vehicle_topics as _vehicle_topics
from droneulator.sensors.camera import Camera

if TYPE_CHECKING:
    import zenoh

    from droneulator.commands import CommandPath
    from droneulator.config import CameraConfig, SimConfig
    from droneulator.ros.zenoh_node import RosZenohNode
    from droneulator.sim.simulator import VehicleState

_IDENTITY_Q = np.array([0.0, 0.0, 0.0, 1.0])
_IMAGES = ("rgb", "depth", "seg")


class CameraImages(Protocol):
    """One camera's images at one instant: a renderer's frame, or the runtime's shared-memory views."""

    rgb: np.ndarray
    depth: np.ndarray
    seg: np.ndarray


def static_transforms(cameras: list[CameraConfig]) -> list[tuple[str, str, np.ndarray, np.ndarray]]:
    """(parent, child, translation, quaternion): map -> odom (identity) and, per camera,
    base_link -> <cam>_link -> <cam>_optical_frame."""
    tfs = [(MAP_FRAME, ODOM_FRAME, np.zeros(3), _IDENTITY_Q)]
    for cam in cameras:
        link = f"{cam.name}_link"
        tfs.append((BASE_FRAME, link, *pose_from_transform(Camera(cam).T_body_link)))
        tfs.append((link, optical_frame(cam.name), *pose_from_transform(T_link_optical())))
    return tfs


class StatePublisher:
    """``/clock``, odometry (odom -> base_link, twist in base_link), TF, the latched static TF, and
    ``odom_world``: the same odometry with the twist in the odom (world) frame, as EGO-Planner and
    other planners built on its simulator read it (not REP 105, hence a topic of its own)."""

    def __init__(self, node: RosZenohNode, cfg: SimConfig) -> None:
        topics = _vehicle_topics(cfg.bridge.namespace)
        self.clock = node.publisher(topics["clock"], TYPES["clock"])
        self.odom = node.publisher(topics["odom"], TYPES["odom"])
        self.odom_world = node.publisher(topics["odom_world"], TYPES["odom_world"])
        self.tf = node.publisher(topics["tf"], TYPES["tf"])
        self.tf_static = node.publisher(topics["tf_static"], TYPES["tf_static"])
        self._static = static_transforms(cfg.render.cameras)
        self._pack = M.StatePacker(ODOM_FRAME, BASE_FRAME)

    def publish(self, st: VehicleState) -> None:
        """Publish one state: odometry first (the latency-critical stream), then ``/clock`` and TF.

        The fixed-layout packer makes this a few microseconds (rosbags' generic serialiser takes ~0.1 ms).
        """
        t, p, q = st.stamp_ns, st.position, st.quaternion
        v_body = world_to_body(q, st.velocity)
        self.odom.publish(self._pack.odometry(t, p, q, v_body, st.angular_velocity), t)
        self.clock.publish(self._pack.clock(t), t)
        self.tf.publish(self._pack.transform(t, p, q), t)
        w_world = body_to_world(q, st.angular_velocity)
        self.odom_world.publish(self._pack.odometry(t, p, q, st.velocity, w_world), t)

    def publish_static(self, stamp_ns: int) -> None:
        """The static transforms stamped ``stamp_ns`` (re-sent periodically and at every reset)."""
        tfs = [M.transform_stamped(stamp_ns, parent, child, p, q) for parent, child, p, q in self._static]
        self.tf_static.publish(M.serialize(M.tf_message(tfs)), stamp_ns)


class FramePublisher:
    """Every camera's JPEG colour, 32FC1 depth, PNG segmentation, their camera_info, and the pose of its
    optical frame in ``odom`` (``geometry_msgs/PoseStamped`` on ``/<ns>/<cam>/pose``, what EGO-Planner's
    grid map takes with ``pose_type`` 1), all stamped with the same instant.

    ``congestion_control`` is the Zenoh policy for the images: ``BLOCK`` in lockstep (nothing a
    subscriber asked for is lost; the simulation clock waits for the slowest one), ``DROP`` in real
    time (a slow subscriber never holds the simulation back).
    """

    def __init__(
        self,
        node: RosZenohNode,
        cfg: SimConfig,
        congestion_control: zenoh.CongestionControl,
    ) -> None:
        self.jpeg_quality = cfg.bridge.jpeg_quality
        policy = congestion_control
        self.cams = []
        for cam in cfg.render.cameras:
            names = topic_names(cfg.bridge.namespace, cam.name)
            pubs = {
                k: node.publisher(names[k], TYPES[k], congestion_control=policy if k in _IMAGES else None)
                for k in names
            }
            camera = Camera(cam)
            self.cams.append((cam, optical_frame(cam.name), camera.K, camera.T_body_link, pubs))

    def publish(self, st: VehicleState, images: dict[str, CameraImages], mark: Any = None) -> None:
        """Publish one frame set, every image stamped ``st.stamp_ns`` with its optical frame id.

        ``mark(stream, stamp_ns)``, if given, is called just before each image is encoded (latency logs).
        """
        t = st.stamp_ns
        T_world_body = transform_from_pose(st.position, st.quaternion)
        for cam, frame_id, K, mount, pubs in self.cams:
            im = images[cam.name]
            info = M.serialize(M.camera_info(t, frame_id, cam.width, cam.height, K))
            for key in ("info_rgb", "info_depth", "info_seg"):
                pubs[key].publish(info, t)
            cam_p, cam_q = pose_from_transform(T_world_optical(T_world_body, mount))
            pubs["pose"].publish(M.serialize(M.pose_stamped(t, ODOM_FRAME, cam_p, cam_q)), t)
            if mark is not None:
                mark("rgb", t)
            jpeg = encode_jpeg(im.rgb, self.jpeg_quality)
            pubs["rgb"].publish(M.serialize(M.compressed_image(t, frame_id, "jpeg", jpeg)), t)
            if mark is not None:
                mark("depth", t)
            pubs["depth"].publish(M.serialize(M.image(t, frame_id, im.depth)), t)
            png = encode_png(im.seg)
            pubs["seg"].publish(M.serialize(M.compressed_image(t, frame_id, "png", png)), t)


def subscribe_commands(node: RosZenohNode, cfg: SimConfig, commands: CommandPath) -> None:
    """``cmd_vel`` -> ``velocity``, ``goal_pose`` -> ``goto`` and ``position_cmd`` -> ``track``, through
    the one command path.

    A PositionCommand's ``kx``/``kv`` gains, ``trajectory_id`` and ``trajectory_flag`` are not used: the
    simulator's SE(3) gains apply. Its frame may be ``world`` (EGO-Planner's name for it), ``map``,
    ``odom`` or empty: all are the simulator's world frame.

    Values are passed on unchecked: the command path validates them exactly as it validates a
    WebSocket request (NaN, ranges, bounds, flight lock), and logs a rejection once per burst.
    """
    topics = _vehicle_topics(cfg.bridge.namespace)
    src_vel, src_goal = f"ROS {topics['cmd_vel']}", f"ROS {topics['goal_pose']}"
    src_track = f"ROS {topics['position_cmd']}"

    def on_cmd_vel(msg: Any) -> None:
        args = {"forward": float(msg.linear.x), "yaw_rate": float(msg.angular.z)}
        commands.submit(src_vel, "velocity", args)

    def on_goal_pose(msg: Any) -> None:
        frame = msg.header.frame_id
        if frame not in ("", MAP_FRAME, ODOM_FRAME):
            commands.reject(src_goal, "goto", "invalid_argument", f"goal in frame {frame!r}: only map/odom")
            return
        p, q = msg.pose.position, msg.pose.orientation
        quat = np.array([q.x, q.y, q.z, q.w], dtype=float)
        norm = float(np.linalg.norm(quat))
        yaw = yaw_of(quat) if math.isfinite(norm) and norm > 1e-6 else math.nan  # nan: rejected as invalid
        commands.submit(src_goal, "goto", {"position": [float(p.x), float(p.y), float(p.z)], "yaw": yaw})

    def on_position_cmd(msg: Any) -> None:
        frame = msg.header.frame_id
        if frame not in ("", "world", MAP_FRAME, ODOM_FRAME):
            commands.reject(
                src_track, "track", "invalid_argument", f"setpoint in frame {frame!r}: only world/map/odom"
            )
            return
        p, v, a = msg.position, msg.velocity, msg.acceleration
        args = {
            "position": [float(p.x), float(p.y), float(p.z)],
            "velocity": [float(v.x), float(v.y), float(v.z)],
            "acceleration": [float(a.x), float(a.y), float(a.z)],
            "yaw": float(msg.yaw),
            "yaw_rate": float(msg.yaw_dot),
        }
        commands.submit(src_track, "track", args)

    node.subscribe(topics["cmd_vel"], TYPES["cmd_vel"], on_cmd_vel)
    node.subscribe(topics["goal_pose"], TYPES["goal_pose"], on_goal_pose)
    node.subscribe(topics["position_cmd"], TYPES["position_cmd"], on_position_cmd)
