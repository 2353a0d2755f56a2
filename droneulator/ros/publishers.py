"""What the simulator publishes to ROS 2 and what it takes from it, one class per concern.

Each vehicle's names come from :func:`~droneulator.ros.topics.vehicle_names` (a world of one keeps the
single-vehicle names; a fleet gets ``/<ns>/<vehicle>/...`` and prefixed or namespaced TF).

* :class:`StatePublisher`: ``/clock``, ``/<ns>/odom``, ``/tf`` and ``/tf_static``, and each vehicle's
  sensor topics (``imu``, ``gps/fix``, ``air_pressure``, ``magnetic_field``: the readings of its noisy
  sensor models). It runs in the process that owns the vehicle state (the dynamics server), right after
  the physics step that produced the state, so odometry never waits for another process.
* :class:`FramePublisher`: every camera's images, camera_info and optical-frame pose (the bridge process).
* :func:`subscribe_commands`: ``/<ns>/cmd_vel``, ``/<ns>/goal_pose``, ``/<ns>/position_cmd``,
  ``/<ns>/setpoint_raw/attitude`` and ``/<ns>/command/motor_speed`` into the one
  :class:`~droneulator.commands.path.CommandPath`, with the WebSocket API's validation and flight lock.

Everything is stamped with the simulator's monotonic clock (:attr:`VehicleState.stamp_ns`), which
never runs backwards, not even across a reset.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable, Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from droneulator.frames import (
    T_link_optical,
    T_world_optical,
    frd_to_flu,
    pose_from_transform,
    transform_from_pose,
    yaw_of,
)
from droneulator.frames_numba import body_to_world, world_to_body
from droneulator.imaging import encode_jpeg, encode_png
from droneulator.ros import messages as M
from droneulator.ros.topics import (
    CLOCK,
    MAP_FRAME,
    NS_PER_S,
    SENSOR_TOPICS,
    SPRAY_FIELDS,
    TYPES,
    VehicleNames,
    battery_state_topic,
    faults_topic,
    spray_deposit_topic,
    spray_state_topic,
    vehicle_names,
)
from droneulator.sensors.camera import Camera
from droneulator.sensors.mag import TESLA_PER_GAUSS
from droneulator.spray.deposit import deposit_levels

if TYPE_CHECKING:
    import zenoh

    from droneulator.commands import CommandPath
    from droneulator.config import CameraConfig, SimConfig
    from droneulator.ros.zenoh_node import RosZenohNode
    from droneulator.sensors.suite import Reading
    from droneulator.vehicles.vehicle import VehicleState

_IDENTITY_Q = np.array([0.0, 0.0, 0.0, 1.0])
_IMAGES = ("rgb", "depth", "seg")


class CameraImages(Protocol):
    """One camera's images at one instant: a renderer's frame, or the runtime's shared-memory views."""

    rgb: np.ndarray
    depth: np.ndarray
    seg: np.ndarray


def static_transforms(
    cameras: list[CameraConfig], names: VehicleNames | None = None
) -> list[tuple[str, str, np.ndarray, np.ndarray]]:
    """(parent, child, translation, quaternion): map -> odom (identity) and, per camera,
    base_link -> <cam>_link -> <cam>_optical_frame, with the frame ids of ``names`` (default: one
    vehicle's, unprefixed)."""
    n = names or vehicle_names("droneulator", "uav0", fleet=False)
    tfs = [(MAP_FRAME, n.odom_frame, np.zeros(3), _IDENTITY_Q)]
    for cam in cameras:
        link = n.link_frame(cam.name)
        tfs.append((n.base_frame, link, *pose_from_transform(Camera(cam).T_body_link)))
        tfs.append((link, n.optical_frame(cam.name), *pose_from_transform(T_link_optical())))
    return tfs


def fleet_names(cfg: SimConfig) -> dict[str, VehicleNames]:
    """Every vehicle's topic and frame names, by vehicle name (today's names for a world of one)."""
    specs = cfg.vehicle_specs()
    b = cfg.bridge
    return {v.name: vehicle_names(b.namespace, v.name, len(specs) > 1, b.fleet_tf) for v in specs}


class _VehicleOut:
    """One vehicle's state publishers and message packer."""

    def __init__(self, names: VehicleNames, odom: Any, odom_world: Any, tf: Any, wind: Any) -> None:
        self.names, self.odom, self.odom_world, self.tf, self.wind = names, odom, odom_world, tf, wind
        self.pack = M.StatePacker(names.odom_frame, names.base_frame)
        #: sensor kind -> publisher, for the noisy sensors the vehicle carries
        self.sensors: dict[str, Any] = {}
        self.sensor_pack: M.SensorPacker | None = None
        #: sensor kind -> ``seq`` of the reading last published
        self.sent: dict[str, int] = {}
        #: the spray state's publisher (``spray.enabled``)
        self.spray: Any = None
        #: the battery's publisher (``battery.enabled``)
        self.battery: Any = None
        #: the active faults' publisher, what it last sent and when (stamp ns)
        self.faults: Any = None
        self.faults_sent: tuple[str, int] | None = None


def sensor_variances(cfg: SimConfig) -> dict[str, float]:
    """The variances the sensor messages carry (REP 145: the noise models' own): gyroscope (rad/s)^2 and
    accelerometer (m/s^2)^2 per axis at the physics rate (every step is one IMU sample), magnetometer
    T^2 per axis, pressure Pa^2, from ``cfg.px4``'s presets and overrides."""
    px4 = cfg.px4
    imu = px4.imu_error(cfg.vehicle.control_hz)
    return {
        "gyro": float(imu.gyro_sigma) ** 2,
        "accel": float(imu.accel_sigma) ** 2,
        "mag": (px4.mag_error() * TESLA_PER_GAUSS) ** 2,
        "pressure": (px4.baro_error() * 100.0) ** 2,
    }


def nav_sat_status(fix_type: int) -> int:
    """sensor_msgs/NavSatStatus ``status`` of a MAVLink GPS_FIX_TYPE: RTK float or fixed (5, 6) is a
    ground-based augmented fix, DGPS (4) an SBAS one, 2D/3D (2, 3) a plain fix, less none."""
    if fix_type >= 5:
        return M.STATUS_GBAS_FIX
    if fix_type == 4:
        return M.STATUS_SBAS_FIX
    return M.STATUS_FIX if fix_type >= 2 else M.STATUS_NO_FIX


class StatePublisher:
    """``/clock``, and per vehicle odometry (odom -> base_link, twist in base_link), TF, the latched
    static TF, and ``odom_world``: the same odometry with the twist in the odom (world) frame, as
    EGO-Planner and other planners built on its simulator read it (not REP 105, hence a topic of its
    own). Names per vehicle from :func:`fleet_names`."""

    def __init__(self, node: RosZenohNode, cfg: SimConfig) -> None:
        self.clock = node.publisher(CLOCK, TYPES["clock"])
        pubs: dict[str, Any] = {}  # one publisher per topic: vehicles that share /tf share it

        def pub(topic: str, key: str) -> Any:
            if topic not in pubs:
                pubs[topic] = node.publisher(topic, TYPES[key])
            return pubs[topic]

        self.vehicles: dict[str, _VehicleOut] = {}
        #: static transforms by tf_static topic: one message per topic holds every vehicle's on it
        self._static: dict[str, list[tuple[str, str, np.ndarray, np.ndarray]]] = {}
        self._static_pubs: dict[str, Any] = {}
        var = sensor_variances(cfg)
        for spec, (name, names) in zip(cfg.vehicle_specs(), fleet_names(cfg).items(), strict=True):
            t = names.topics()
            out = self.vehicles[name] = _VehicleOut(
                names,
                pub(t["odom"], "odom"),
                pub(t["odom_world"], "odom_world"),
                pub(t["tf"], "tf"),
                pub(t["wind"], "wind"),
            )
            if cfg.spray.enabled:
                out.spray = pub(spray_state_topic(names.namespace), "spray")
            if spec.battery is not None and spec.battery.enabled:
                out.battery = pub(battery_state_topic(names.namespace), "battery")
            out.faults = pub(faults_topic(names.namespace), "faults")
            for kind in spec.sensors or ():
                if kind in SENSOR_TOPICS:
                    key = SENSOR_TOPICS[kind]
                    out.sensors[kind] = pub(t[key], key)
            if out.sensors:
                out.sensor_pack = M.SensorPacker(
                    names.base_frame, var["gyro"], var["accel"], var["mag"], var["pressure"]
                )
            assert spec.cameras is not None
            self._static.setdefault(t["tf_static"], []).extend(static_transforms(spec.cameras, names))
            self._static_pubs[t["tf_static"]] = pub(t["tf_static"], "tf_static")
        self._clock_pack = next(iter(self.vehicles.values())).pack
        self._deposit = (
            node.publisher(spray_deposit_topic(cfg.bridge.namespace), TYPES["spray_deposit"])
            if cfg.spray.enabled
            else None
        )

    def publish(self, st: VehicleState) -> None:
        """Publish one vehicle's state (see :meth:`publish_states`)."""
        self.publish_states({st.vehicle: st})

    def publish_states(self, states: Mapping[str, VehicleState]) -> None:
        """Publish the states of one instant: every odometry first (the latency-critical stream), then
        ``/clock`` once, then TF, ``odom_world``, the true wind (``wind``, in ``odom``), the spray state and
        the battery (``sensor_msgs/BatteryState``) of the vehicles that have them, and each vehicle's active
        faults (``/<ns>/faults``, on a change and once a second).

        The fixed-layout packer makes this a few microseconds a vehicle (rosbags' generic serialiser
        takes ~0.1 ms).
        """
        t = 0
        for name, st in states.items():
            out = self.vehicles[name]
            t, p, q = st.stamp_ns, st.position, st.quaternion
            v_body = world_to_body(q, st.velocity)
            out.odom.publish(out.pack.odometry(t, p, q, v_body, st.angular_velocity), t)
        self.clock.publish(self._clock_pack.clock(t), t)
        for name, st in states.items():
            out = self.vehicles[name]
            t, p, q = st.stamp_ns, st.position, st.quaternion
            out.tf.publish(out.pack.transform(t, p, q), t)
            w_world = body_to_world(q, st.angular_velocity)
            out.odom_world.publish(out.pack.odometry(t, p, q, st.velocity, w_world), t)
            if st.wind is not None:
                out.wind.publish(out.pack.vector(t, st.wind), t)
            if st.spray is not None and out.spray is not None:
                values = [float(st.spray[k]) for k in SPRAY_FIELDS]
                out.spray.publish(M.serialize(M.labelled_array(SPRAY_FIELDS, values)), t)
            if st.battery is not None and out.battery is not None:
                b = st.battery
                msg = M.battery_state(t, out.names.base_frame, b["voltage"], b["current"],
                                      b["remaining_mah"] / 1000.0, b["capacity_mah"] / 1000.0, b["soc"],
                                      b["cells"], b["empty"])  # fmt: skip
                out.battery.publish(M.serialize(msg), t)
            self._publish_faults(out, st)

    @staticmethod
    def _publish_faults(out: _VehicleOut, st: VehicleState) -> None:
        """The vehicle's active faults (a JSON list) when they changed, and once a second."""
        t = st.stamp_ns
        text = json.dumps(st.faults or [], separators=(",", ":"))
        last = out.faults_sent
        if last is None or last[0] != text or not 0 <= t - last[1] < NS_PER_S:
            out.faults.publish(M.serialize(M.string(text)), t)
            out.faults_sent = (text, t)

    def publish_deposit(self, t_ns: int, deposit_ul_cm2: np.ndarray, cell: float, origin_xy: Any) -> None:
        """The ground deposit (uL/cm^2 per cell, ``[x, y]``) as an occupancy grid in ``map``: 0 where
        nothing landed, 1..100 over log10 of :data:`~droneulator.spray.deposit.DEPOSIT_LOG_RANGE`
        (:func:`~droneulator.spray.deposit.deposit_levels`)."""
        if self._deposit is None:
            return
        values = deposit_levels(deposit_ul_cm2).astype(np.int8)
        self._deposit.publish(M.serialize(M.occupancy_grid(t_ns, MAP_FRAME, values, cell, origin_xy)), t_ns)

    def publish_sensors(
        self, states: Mapping[str, VehicleState], readings: Mapping[str, Mapping[str, Reading]]
    ) -> None:
        """Publish each vehicle's newest sensor readings (``readings[vehicle][kind]``, a
        :class:`~droneulator.sensors.suite.SensorSuite`'s ``latest``) not published yet, for the sensors
        it carries, in its base_link frame (FLU, REP 103; converted from the models' FRD by
        :func:`~droneulator.frames.frd_to_flu`):

        * ``imu``: sensor_msgs/Imu, rates (rad/s) and specific force (m/s^2: +9.81 on z at rest), no
          orientation (REP 145: ``orientation_covariance[0] = -1``), the noise variances on the diagonals;
        * ``magnetic_field``: sensor_msgs/MagneticField in tesla;
        * ``air_pressure``: sensor_msgs/FluidPressure in Pa with its variance;
        * ``gps/fix``: sensor_msgs/NavSatFix (frame base_link: the antenna is at the body origin) with
          the fix's status, and eph^2, eph^2, epv^2 as the diagonal ENU covariance.

        Each is stamped with the sim instant of the truth it was drawn from (a GPS fix: the instant it
        describes, ``gps_delay_s`` before it was sent), on the same clock as ``states`` (``stamp_ns``).
        """
        for name, st in states.items():
            out = self.vehicles[name]
            got = readings.get(name)
            if not out.sensors or not got:
                continue
            pack = out.sensor_pack
            assert pack is not None
            offset = st.stamp_ns - st.t_ns  # stamp clock - episode clock since the last reset
            for kind, pub in out.sensors.items():
                r = got.get(kind)
                if r is None or r.seq == out.sent.get(kind) or r.t_ns > st.t_ns:
                    continue  # nothing new, or drawn before a reset
                out.sent[kind] = r.seq
                t = offset + r.t_ns
                if kind == "imu":
                    accel, gyro = r.value
                    pub.publish(pack.imu(t, frd_to_flu(gyro), frd_to_flu(accel)), t)
                elif kind == "mag":
                    pub.publish(pack.magnetic_field(t, frd_to_flu(r.value) * TESLA_PER_GAUSS), t)
                elif kind == "baro":
                    pub.publish(pack.fluid_pressure(t, r.value.pressure_hpa * 100.0), t)
                else:
                    g = r.value
                    t = offset + g.time_ns
                    cov = (g.eph_m**2, g.eph_m**2, g.epv_m**2)
                    status = nav_sat_status(g.fix_type)
                    frame = out.names.base_frame
                    fix = M.nav_sat_fix(t, frame, g.lat_deg, g.lon_deg, g.alt_msl_m, cov, status)
                    pub.publish(M.serialize(fix), t)

    def publish_static(self, stamp_ns: int) -> None:
        """The static transforms stamped ``stamp_ns`` (re-sent periodically and at every reset)."""
        for topic, static in self._static.items():
            tfs = [M.transform_stamped(stamp_ns, parent, child, p, q) for parent, child, p, q in static]
            self._static_pubs[topic].publish(M.serialize(M.tf_message(tfs)), stamp_ns)


def encode_threads(setting: int) -> int:
    """The bridge's encoder threads for ``bridge.encode_threads``: the setting, or for 0 one per CPU this
    process may run on, up to 8."""
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    return setting or min(8, cpus)


class FramePublisher:
    """Every camera's JPEG colour, 32FC1 depth, PNG segmentation, their camera_info, and the pose of its
    optical frame in ``odom`` (``geometry_msgs/PoseStamped`` on ``<cam>/pose``, what EGO-Planner's
    grid map takes with ``pose_type`` 1), for every vehicle, all stamped with the same instant.

    A frame set's JPEG and PNG images are encoded at once by ``bridge.encode_threads`` threads (Pillow lets
    go of the GIL while it encodes) while this thread publishes them in the order of one thread: on a GPU,
    where frames are cheap, one thread encoding them was what held a fleet back (docs/architecture.md).

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
        #: threads encoding images (``bridge.encode_threads``; 0: one per CPU, up to 8)
        self.encode_threads = threads = encode_threads(cfg.bridge.encode_threads)
        self._encoder = ThreadPoolExecutor(threads, thread_name_prefix="encode") if threads > 1 else None
        policy = congestion_control
        #: vehicle -> [(camera, optical frame id, odom frame id, K, mount, publishers)]
        self.cams: dict[str, list[tuple[CameraConfig, str, str, np.ndarray, np.ndarray, dict[str, Any]]]] = {}
        for spec, (name, vn) in zip(cfg.vehicle_specs(), fleet_names(cfg).items(), strict=True):
            assert spec.cameras is not None
            rig = self.cams.setdefault(name, [])
            for cam in spec.cameras:
                topics = vn.camera_topics(cam.name)
                pubs = {
                    k: node.publisher(t, TYPES[k], congestion_control=policy if k in _IMAGES else None)
                    for k, t in topics.items()
                }
                camera = Camera(cam)
                frame = vn.optical_frame(cam.name)
                rig.append((cam, frame, vn.odom_frame, camera.K, camera.T_body_link, pubs))

    def publish(
        self,
        states: Mapping[str, VehicleState],
        images: Mapping[str, Mapping[str, CameraImages]],
        mark: Any = None,
    ) -> None:
        """Publish one frame set: every vehicle's (``states`` by name) cameras (``images[vehicle][camera]``),
        every image stamped with its vehicle's ``stamp_ns`` and its optical frame id.

        ``mark(stream, stamp_ns)``, if given, is called as each colour image goes to the encoders and
        before each depth image is published (latency logs).
        """
        encoded: dict[tuple[str, str], tuple[Future[bytes], Future[bytes]]] = {}
        for vehicle, st in states.items():  # every image of the set goes to the encoders first
            for cam, *_ in self.cams[vehicle]:
                im = images[vehicle][cam.name]
                if mark is not None:
                    mark("rgb", st.stamp_ns)
                encoded[vehicle, cam.name] = (
                    self._encode(encode_jpeg, im.rgb, self.jpeg_quality),
                    self._encode(encode_png, im.seg),
                )
        for vehicle, st in states.items():
            t = st.stamp_ns
            T_world_body = transform_from_pose(st.position, st.quaternion)
            for cam, frame_id, odom_frame, K, mount, pubs in self.cams[vehicle]:
                im = images[vehicle][cam.name]
                info = M.serialize(M.camera_info(t, frame_id, cam.width, cam.height, K, cam.distortion))
                for key in ("info_rgb", "info_depth", "info_seg"):
                    pubs[key].publish(info, t)
                cam_p, cam_q = pose_from_transform(T_world_optical(T_world_body, mount))
                pubs["pose"].publish(M.serialize(M.pose_stamped(t, odom_frame, cam_p, cam_q)), t)
                jpeg, png = (f.result() for f in encoded[vehicle, cam.name])
                pubs["rgb"].publish(M.serialize(M.compressed_image(t, frame_id, "jpeg", jpeg)), t)
                if mark is not None:
                    mark("depth", t)
                pubs["depth"].publish(M.serialize(M.image(t, frame_id, im.depth)), t)
                pubs["seg"].publish(M.serialize(M.compressed_image(t, frame_id, "png", png)), t)

    def _encode(self, fn: Callable[..., bytes], *args: Any) -> Future[bytes]:
        """``fn(*args)`` on an encoder thread, or here and now with one thread."""
        if self._encoder is not None:
            return self._encoder.submit(fn, *args)
        done: Future[bytes] = Future()
        done.set_result(fn(*args))
        return done

    def close(self) -> None:
        """Stop the encoder threads (after the frame set in hand)."""
        if self._encoder is not None:
            self._encoder.shutdown()


#: mavros_msgs/AttitudeTarget's type_mask bits for the orientation and the thrust
ATTITUDE_IGNORE_ORIENTATION, ATTITUDE_IGNORE_THRUST = 128, 64


def subscribe_commands(node: RosZenohNode, cfg: SimConfig, commands: CommandPath) -> None:
    """Every vehicle's ``cmd_vel`` -> ``velocity``, ``goal_pose`` -> ``goto``, ``position_cmd`` ->
    ``track``, ``setpoint_raw/attitude`` -> ``rates`` or ``attitude`` and ``command/motor_speed`` ->
    ``rotors``, and ``fault`` (a std_msgs/String holding the ``fault`` op's fields as a JSON object, the
    vehicle the topic's; docs/faults.md) -> ``fault``, through the one command path, each commanding its
    own vehicle.

    An AttitudeTarget is MAVROS's ``setpoint_raw/attitude`` (ENU world, FLU body, thrust normalised to
    [0, 1] of the largest): with ``IGNORE_ATTITUDE`` (128) in its ``type_mask`` its body rates (those not
    ignored; an ignored one is 0) go to ``rates``, else its orientation goes to ``attitude`` (its body
    rates unused); one with ``IGNORE_THRUST`` (64) is refused, the simulator needs a thrust. An
    Actuators message carries four rotor speeds in ``velocity`` (rad/s) or four thrusts in ``normalized``
    ([0, 1] of a rotor's largest), not both. (Actuators rather than a Float64MultiArray: it names the unit
    by its field, carries a stamp, and is what ros_gz bridges to Gazebo's multicopter motor model, so a
    controller written for Gazebo's multicopters speaks it already.)

    A PositionCommand's ``kx``/``kv`` gains, ``trajectory_id`` and ``trajectory_flag`` are not used: the
    simulator's SE(3) gains apply. Its frame may be ``world`` (EGO-Planner's name for it), ``map``,
    the vehicle's ``odom`` or empty: all are the simulator's world frame (a vehicle's odom frame
    coincides with the map).

    Values are passed on unchecked: the command path validates them exactly as it validates a
    WebSocket request (NaN, ranges, bounds, flight lock), and logs a rejection once per burst.
    """
    for vehicle, names in fleet_names(cfg).items():
        _subscribe_vehicle(node, names, vehicle, commands)


def _subscribe_vehicle(node: RosZenohNode, names: VehicleNames, vehicle: str, commands: CommandPath) -> None:
    topics = names.topics()
    src_vel, src_goal = f"ROS {topics['cmd_vel']}", f"ROS {topics['goal_pose']}"
    src_track = f"ROS {topics['position_cmd']}"
    src_att, src_motor = f"ROS {topics['attitude_target']}", f"ROS {topics['motor_speed']}"
    goal_frames = ("", MAP_FRAME, names.odom_frame)
    setpoint_frames = ("world", *goal_frames)  # "world": EGO-Planner's name for it

    def on_cmd_vel(msg: Any) -> None:
        args = {"forward": float(msg.linear.x), "yaw_rate": float(msg.angular.z), "vehicle": vehicle}
        commands.submit(src_vel, "velocity", args)

    def on_goal_pose(msg: Any) -> None:
        frame = msg.header.frame_id
        if frame not in goal_frames:
            allowed = f"{MAP_FRAME}/{names.odom_frame}"
            commands.reject(src_goal, "goto", "invalid_argument", f"goal in frame {frame!r}: only {allowed}")
            return
        p, q = msg.pose.position, msg.pose.orientation
        quat = np.array([q.x, q.y, q.z, q.w], dtype=float)
        norm = float(np.linalg.norm(quat))
        yaw = yaw_of(quat) if math.isfinite(norm) and norm > 1e-6 else math.nan  # nan: rejected as invalid
        position = [float(p.x), float(p.y), float(p.z)]
        commands.submit(src_goal, "goto", {"position": position, "yaw": yaw, "vehicle": vehicle})

    def on_position_cmd(msg: Any) -> None:
        frame = msg.header.frame_id
        if frame not in setpoint_frames:
            allowed = f"world/{MAP_FRAME}/{names.odom_frame}"
            why = f"setpoint in frame {frame!r}: only {allowed}"
            commands.reject(src_track, "track", "invalid_argument", why)
            return
        p, v, a = msg.position, msg.velocity, msg.acceleration
        args = {
            "position": [float(p.x), float(p.y), float(p.z)],
            "velocity": [float(v.x), float(v.y), float(v.z)],
            "acceleration": [float(a.x), float(a.y), float(a.z)],
            "yaw": float(msg.yaw),
            "yaw_rate": float(msg.yaw_dot),
            "vehicle": vehicle,
        }
        commands.submit(src_track, "track", args)

    def on_attitude_target(msg: Any) -> None:
        mask = int(msg.type_mask)
        thrust = float(msg.thrust)
        if mask & ATTITUDE_IGNORE_THRUST:
            op = "rates" if mask & ATTITUDE_IGNORE_ORIENTATION else "attitude"
            commands.reject(src_att, op, "invalid_argument", "a setpoint without thrust (IGNORE_THRUST)")
        elif mask & ATTITUDE_IGNORE_ORIENTATION:
            r = msg.body_rate
            axes = zip((1, 2, 4), (r.x, r.y, r.z), strict=True)
            rates = [0.0 if mask & bit else float(v) for bit, v in axes]
            args = {"thrust": thrust, "body_rates": rates, "normalized": True, "vehicle": vehicle}
            commands.submit(src_att, "rates", args)
        else:
            q = msg.orientation
            quat = [float(q.x), float(q.y), float(q.z), float(q.w)]
            args = {"thrust": thrust, "quaternion": quat, "normalized": True, "vehicle": vehicle}
            commands.submit(src_att, "attitude", args)

    def on_motor_speed(msg: Any) -> None:
        speeds, shares = list(msg.velocity), list(msg.normalized)
        if bool(speeds) == bool(shares):
            why = "four rotor speeds in velocity (rad/s) or four thrusts in normalized, one of them"
            commands.reject(src_motor, "rotors", "invalid_argument", why)
            return
        args = {"rotor_speeds": [float(v) for v in speeds or shares], "normalized": bool(shares)}
        commands.submit(src_motor, "rotors", {**args, "vehicle": vehicle})

    node.subscribe(topics["cmd_vel"], TYPES["cmd_vel"], on_cmd_vel)
    node.subscribe(topics["goal_pose"], TYPES["goal_pose"], on_goal_pose)
    node.subscribe(topics["position_cmd"], TYPES["position_cmd"], on_position_cmd)
    node.subscribe(topics["attitude_target"], TYPES["attitude_target"], on_attitude_target)
    def on_fault(msg: Any) -> None:
        try:
            args = json.loads(msg.data)
        except ValueError as e:
            commands.reject(src_fault, "fault", "parse_error", f"not JSON: {e}")
            return
        if not isinstance(args, dict) or "vehicle" in args:
            commands.reject(src_fault, "fault", "invalid_argument", "a JSON object of the fault op's fields "
                            "(its vehicle is the topic's)")  # fmt: skip
            return
        commands.submit(src_fault, "fault", {**args, "vehicle": vehicle})

    src_fault = f"ROS {topics['fault']}"
    node.subscribe(topics["motor_speed"], TYPES["motor_speed"], on_motor_speed)
    node.subscribe(topics["fault"], TYPES["fault"], on_fault)
