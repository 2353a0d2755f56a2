"""A fleet through every interface: the command path, ROS 2 names in both key modes and both TF
conventions, one PX4 SITL instance per vehicle, and ``droneulator run --vehicles`` end to end.

Decoding is independent of the publishers' code: plain Zenoh sessions and rosbags' own CDR
deserialiser; PX4 is played by ``tests/test_px4.Peer`` (pymavlink, booting like PX4).
"""

from __future__ import annotations

import dataclasses
import math
import socket
import threading
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh
from rosbags.typesys import Stores, get_typestore
from test_px4 import Peer, by_type

from droneulator.api.client import ApiError
from droneulator.cli import build_parser
from droneulator.cli.plan import resolve_vehicle
from droneulator.commands import CommandPath, make_request
from droneulator.config import CameraConfig, VehicleSpec, fleet, load_config
from droneulator.frames import enu_to_geodetic, ned_to_enu, quat_to_matrix
from droneulator.px4.link import PX4Fleet
from droneulator.recording.recorder import Recorder, run_recorder_config
from droneulator.recording.replay import ReplayConfig, replay
from droneulator.ros.publishers import FramePublisher, StatePublisher
from droneulator.ros.topics import battery_state_topic, vehicle_names
from droneulator.ros.zenoh_node import RosZenohNode, ZenohNodeConfig
from droneulator.runtime.dynamics_server import lockstep_may_step
from droneulator.runtime.launch import free_port, launch_run
from droneulator.runtime.preflight import StartupError
from droneulator.sensors import Truth
from droneulator.sensors.baro import isa_pressure_pa
from droneulator.sensors.mag import earth_field_ned
from droneulator.sensors.suite import Schedule
from droneulator.workflows.rl.env import env_config
from droneulator.workflows.rl.remote import RemoteBackend
from droneulator.world import World

TS = get_typestore(Stores.ROS2_JAZZY)
SMALL = CameraConfig(name="front", width=160, height=120)


def two_vehicle_config(**sections: Any) -> Any:
    cfg = load_config(scene="default")
    cfg.vehicles = fleet(2)
    cfg.render.cameras = [SMALL]
    cfg.render.shadows = False
    for key, value in sections.items():
        setattr(cfg, key, value)
    return cfg


def consecutive_ports(n: int) -> int:
    """A base port with ``base .. base + n - 1`` all free now (PX4 instance k listens on base + k)."""
    for _ in range(50):
        base = free_port()
        socks = []
        try:
            for k in range(n):
                s = socket.socket()
                socks.append(s)
                s.bind(("127.0.0.1", base + k))
            return base
        except OSError:
            continue
        finally:
            for s in socks:
                s.close()
    raise RuntimeError("no run of free ports")


# --------------------------------------------------------------------------- the command path
def test_flight_ops_name_their_vehicle_and_the_flight_lock_is_per_vehicle() -> None:
    with World(two_vehicle_config(), render=False) as world:
        path = CommandPath(world)

        def run(op: str, **args: Any) -> dict[str, Any]:
            return path.execute(make_request(op, args))

        a, b = (world.vehicles[n].state.position.copy() for n in ("uav0", "uav1"))
        info = run("scene_info")["result"]
        assert [v["name"] for v in info["vehicles"]] == ["uav0", "uav1"]
        assert info["vehicles"][1]["cameras"] == ["front"]
        unknown = run("takeoff", vehicle="uav7")["error"]
        assert unknown["code"] == "invalid_argument" and "uav0, uav1" in unknown["message"]

        path.refuse_flight("PX4 flies uav1", vehicle="uav1")
        assert run("takeoff", altitude=2.0, vehicle="uav1")["error"] == {
            "code": "flight_locked",
            "message": "PX4 flies uav1",
        }
        assert run("reset")["error"]["code"] == "flight_locked"  # it would move uav1 too
        assert run("takeoff", altitude=2.0)["ok"]  # the default vehicle, uav0, still flies
        assert path.flight_locked is None and path.flight_locked_for("uav1") == "PX4 flies uav1"
        path.allow_flight("uav1")
        assert run("takeoff", altitude=3.0, vehicle="uav1")["ok"]

        events: list[Any] = []
        arrived = lambda w: {e.vehicle for e in events if e.type == "arrived"} == {"uav0", "uav1"}  # noqa: E731
        assert world.run_until(arrived, 30.0, events)
        # crossing gotos at two heights: each flies to where the other took off
        assert run("goto", position=[*b[:2], 2.0], speed=2.0, vehicle="uav0")["ok"]
        assert run("goto", position=[*a[:2], 3.0], speed=2.0, vehicle="uav1")["ok"]
        events.clear()
        assert world.run_until(arrived, 60.0, events)
        assert not [e for e in events if e.type == "collision"]
        states = run("state", vehicle="*")["result"]
        assert set(states["vehicles"]) == {"uav0", "uav1"}
        assert np.linalg.norm(np.array(states["vehicles"]["uav0"]["position"]) - [*b[:2], 2.0]) < 0.1
        assert np.linalg.norm(np.array(states["vehicles"]["uav1"]["position"]) - [*a[:2], 3.0]) < 0.1
        assert run("state", vehicle="uav1")["result"]["vehicle"] == "uav1"
        assert run("state")["result"]["vehicle"] == "uav0"


# --------------------------------------------------------------------------- triggered cameras
def test_triggered_cameras_shoot_once_when_asked_with_every_body_in_view() -> None:
    """``render.camera_trigger=command``: no frame until ``trigger``; then one frame set at the end of the
    next control period, of the asking vehicle's rig only, drawn as the camera rate draws it (the other
    vehicle's body in view); at the camera rate, and for an unknown vehicle, ``trigger`` is refused."""
    cfg = two_vehicle_config()
    cfg.render.camera_trigger = "command"
    with World(cfg) as world:
        path = CommandPath(world)
        st = world.vehicles["uav0"].state
        yaw = st.yaw
        ahead = st.position + 1.5 * np.array([math.cos(yaw), math.sin(yaw), 0.0])
        world.reset(position=ahead, yaw=yaw, vehicle="uav1")  # in front of uav0's camera
        assert world.step(30).frames == []
        reply = path.execute(make_request("trigger", {"vehicle": "uav0"}))["result"]
        assert reply["frame_stamp_ns"] == reply["stamp_ns"] + world.control_period_ns
        res = world.step(3)
        (shot,) = res.frames
        assert shot.t_ns + (world.stamp_ns - world.t_ns) == reply["frame_stamp_ns"]
        assert list(shot.cameras) == ["uav0"] and list(shot.cameras["uav0"]) == ["front"]
        mine = shot.cameras["uav0"]["front"]
        rate = world.render().cameras["uav0"]["front"]  # the same instant, every rig
        assert np.array_equal(mine.depth, rate.depth, equal_nan=True) and np.array_equal(mine.rgb, rate.rgb)
        alone = world.cameras.renderer.render_rigs({"uav0": world.vehicles["uav0"].state.T_world_body})
        body = ~np.isclose(alone["uav0"]["front"].depth, mine.depth, equal_nan=True)
        assert body.sum() > 20 and np.nanmax(mine.depth[body]) < 1.5  # uav1, 1.5 m ahead, drawn
        path.execute(make_request("trigger", {"vehicle": "uav1"}))
        world.reset()
        assert world.step(5).frames == []  # a reset drops the shot asked for before it
        unknown = path.execute(make_request("trigger", {"vehicle": "uav7"}))["error"]
        assert unknown["code"] == "invalid_argument" and "uav0, uav1" in unknown["message"]
    with World(two_vehicle_config(), render=False, external_cameras=True) as world:
        refused = CommandPath(world).execute(make_request("trigger", {}))["error"]
        assert refused["code"] == "unsupported" and "render.camera_trigger=command" in refused["message"]


def test_a_triggered_frame_in_flight_holds_the_lockstep_clock() -> None:
    """Lockstep steps while fewer than the window of frames are in flight, and never while a triggered one
    is (in either stage)."""
    rate = ("render", {}, None)
    assert lockstep_may_step({}, 2) and lockstep_may_step({1: rate}, 2)
    assert not lockstep_may_step({1: rate, 2: ("publish", {}, None)}, 2)
    for stage in ("render", "publish"):
        assert not lockstep_may_step({1: (stage, {}, ("uav1",))}, 2)


@pytest.mark.alone
@pytest.mark.slow
def test_a_triggered_run_publishes_one_frame_set_of_the_asking_vehicle_with_its_states(
    tmp_path: Path,
) -> None:
    """Through the runtime (dynamics server, render server, bridge): nothing is published on the camera
    topics until ``trigger``; then the asking vehicle's images, camera_info and pose, stamped as the reply
    said, with its odometry and TF of that stamp, and nothing of the other vehicle; the frame holds the
    clock until it is published. With nothing to render, lockstep runs no faster than
    ``runtime.max_speed``."""
    cfg = two_vehicle_config()
    cfg.render.camera_trigger = "command"
    cfg.runtime.state_hz = 25.0  # the triggered instant brings its own states
    cfg.runtime.max_speed = 8.0
    latency_log = tmp_path / "latency.log"  # when each state was stepped and each image published (wall)
    cfg.bridge.latency_log = str(latency_log)
    run = launch_run(cfg)
    got: dict[str, list[int]] = defaultdict(list)

    def on_sample(sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        leaf = key.split("/", 2)[2] if key.count("/") >= 2 else key
        typename = _ros2dds_type(key)
        msg = TS.deserialize_cdr(sample.payload.to_bytes(), typename)
        if typename == "tf2_msgs/msg/TFMessage":
            for tr in msg.transforms:
                got[f"tf {tr.child_frame_id}"].append(tr.header.stamp.sec * 10**9 + tr.header.stamp.nanosec)
            return
        name, t = f"{key.split('/')[1]} {leaf}", msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
        got[name].append(t)

    session = zenoh.open(_client_of(run.zenoh_endpoint))
    subs = [session.declare_subscriber(k, on_sample) for k in ("droneulator/*/**", "tf")]
    try:
        with run.client() as c:
            assert c.scene_info()["camera_trigger"] == "command"
            c.subscribe(["events"])
            c.takeoff(1.5, vehicle="uav1")
            arrived_ns = round(c.wait_for_event("arrived", timeout=60, vehicle="uav1")["t"] * 1e9)
            # every odometry of the flight here (the last one 25 Hz publishes at or before the arrival)
            _until(lambda: got["uav1 odom"] and got["uav1 odom"][-1] > arrived_ns - 40_000_000, 30,
                   lambda: f"arrived at {arrived_ns}; {_latest(got)}")  # fmt: skip
            time.sleep(0.5)
            images = [k for k in got if "front/" in k]
            flown = [t for t in got["uav1 odom"] if t <= arrived_ns]
            assert images == [] and len(flown) > 25, _latest(got)  # flown, odometry at 25 Hz, no image
            stamp = c.trigger(vehicle="uav1")["frame_stamp_ns"]
            streams = ("color/image_raw/compressed", "depth/image_raw", "segmentation/image_raw/compressed",
                       "color/camera_info", "pose")  # fmt: skip
            _until(lambda: all(got[f"uav1 front/{s}"] for s in streams), 30)
            time.sleep(0.5)
            for s in streams:
                assert got[f"uav1 front/{s}"] == [stamp]
            assert not [k for k in got if k.startswith("uav0 front/")]
            assert stamp in got["uav1 odom"] and stamp in got["uav0 odom"]  # every state of that instant
            assert stamp in got["tf uav1/base_link"]
            assert np.median(np.diff(got["uav1 odom"])) == 40_000_000  # else the 25 Hz schedule
            # the clock held while the frame was rendered and published: no state of a later instant was
            # stepped before the bridge published the frame's last image (at 8x, a render of tens of ms
            # would otherwise step dozens). Judged by stamps on one wall clock (the latency log: the
            # dynamics server's step, the bridge's publish), not by the order odometry and images arrive
            # here: they are streams of two processes, and after the hold the clock catches up at full
            # speed, so on a busy core odometry of later instants may overtake the image on its way
            log_lines = [line.split() for line in latency_log.read_text().splitlines()]
            published = max(int(w) for s, t, w in log_lines if s != "odom" and int(t) == stamp)
            later = [int(w) for s, t, w in log_lines if s == "odom" and int(t) > stamp]
            assert later and min(later) > published
            # no faster than max_speed, from a reset (sim time back to 0: the pacing starts again there,
            # owing nothing). Not from any instant: after a wait (the frame's hold, a step late on a busy
            # core) the clock makes up to MAX_SPEED_CATCH_UP_S of it up at full speed (test_pacing.py)
            wall0 = time.monotonic()
            c.reset()
            time.sleep(1.0)
            t1, wall1 = c.state()["t"], time.monotonic()
            assert 0 < t1 <= 8.0 * (wall1 - wall0) + 0.01, (t1, wall1 - wall0)  # a control period at most
        # the consumers that need the camera rate refuse such a run in one line
        with pytest.raises(StartupError, match="the planner needs depth at the camera rate"):
            resolve_vehicle(build_parser().parse_args(["plan", "--url", run.url]))
        with pytest.raises(ValueError, match="steps one depth frame per step"):
            RemoteBackend(env_config(), run.url, run.zenoh_endpoint)
    finally:
        for sub in subs:
            sub.undeclare()
        session.close()
        run.stop()


# --------------------------------------------------------------------------- ROS names
def test_one_vehicle_keeps_its_names_and_a_fleet_gets_namespaces_and_tf_frames() -> None:
    one = vehicle_names("droneulator", "uav0", fleet=False)
    assert (one.topics()["odom"], one.tf, one.base_frame) == ("/droneulator/odom", "/tf", "base_link")
    assert one.camera_topics("front")["depth"] == "/droneulator/front/depth/image_raw"
    prefix = vehicle_names("droneulator", "uav1", fleet=True)
    assert prefix.topics()["odom"] == "/droneulator/uav1/odom" and prefix.tf == "/tf"
    assert (prefix.odom_frame, prefix.optical_frame("front")) == ("uav1/odom", "uav1/front_optical_frame")
    nav2 = vehicle_names("droneulator", "uav1", fleet=True, fleet_tf="namespace")
    assert (nav2.tf, nav2.tf_static, nav2.base_frame) == (
        "/droneulator/uav1/tf",
        "/droneulator/uav1/tf_static",
        "base_link",
    )
    with pytest.raises(ValueError, match="fleet_tf"):
        vehicle_names("droneulator", "uav1", fleet=True, fleet_tf="both")
    with pytest.raises(ValueError, match="fleet_tf"):
        load_config(overrides=["bridge.fleet_tf=nav"])


def _type_of(key: str, key_mode: str) -> tuple[str, str]:
    """(ROS topic, type) of a Zenoh key, parsed here from the key conventions themselves."""
    if key_mode == "ros2dds":
        return "/" + key, ""
    parts = key.split("/")  # <domain>/<topic...>/<pkg>::msg::dds_::<Type>_/<hash>
    pkg, _, _, name = parts[-2].split("::")
    return "/" + "/".join(parts[1:-2]), f"{pkg}/msg/{name[:-1]}"


@pytest.mark.parametrize(("key_mode", "fleet_tf"), [("ros2dds", "prefix"), ("rmw_zenoh", "namespace")])
def test_every_vehicles_topics_decode_with_their_frames_and_stamps(key_mode: str, fleet_tf: str) -> None:
    cfg = two_vehicle_config()
    cfg.bridge.key_mode, cfg.bridge.fleet_tf = key_mode, fleet_tf
    ep = f"tcp/127.0.0.1:{free_port()}"
    zc = ZenohNodeConfig(mode="router", listen=(ep,), connect=(), key_mode=key_mode)  # type: ignore[arg-type]
    node = RosZenohNode(zc)
    sub_cfg = zenoh.Config()
    sub_cfg.insert_json5("mode", '"client"')
    sub_cfg.insert_json5("connect/endpoints", f'["{ep}"]')
    session = zenoh.open(sub_cfg)
    got: dict[str, list[tuple[str, Any]]] = defaultdict(list)
    lock = threading.Lock()
    probed = threading.Event()

    def on_sample(sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        if key == "test_probe":
            probed.set()
            return
        if "@" in key:
            return
        with lock:
            got[key].append(sample.payload.to_bytes())

    sub = session.declare_subscriber("**", on_sample)
    try:
        states, frames = StatePublisher(node, cfg), FramePublisher(node, cfg, zenoh.CongestionControl.BLOCK)
        deadline = time.monotonic() + 10.0  # the subscriber's declaration reaches the node (slow under load)
        while not probed.is_set() and time.monotonic() < deadline:
            node.session.put("test_probe", b"")
            probed.wait(0.1)
        assert probed.is_set(), "the subscriber never heard the node"
        with World(cfg) as world:
            world.vehicle("uav1").place([*world.vehicle("uav1").state.position[:2], 1.0], 0.3, airborne=True)
            shot = world.render()
            states.publish_static(shot.t_ns)
            states.publish_states(shot.states)
            frames.publish(shot.states, shot.cameras)
            for v in world.vehicle_list:  # as the dynamics server samples a vehicle it flies itself
                v.rig.suite.sample_due(Truth.from_sim(v), Schedule())
            home = world.config.site
            field_ned = earth_field_ned(world.config.px4, home)
            states.publish_sensors(shot.states, {n: v.rig.suite.latest for n, v in world.vehicles.items()})
        end = time.monotonic() + 10
        # per vehicle odom, odom_world, wind, battery, faults, 4 sensor and 7 camera keys; /clock and the tf
        # keys (shared /tf and /tf_static with prefixed frames, each vehicle's own two in Nav2's convention);
        # a count short of them ends the wait before the last images arrive, which a loaded machine shows
        keys = 2 * (5 + 4 + 7) + 1 + (2 if fleet_tf == "prefix" else 4)
        while time.monotonic() < end and len(got) < keys:
            time.sleep(0.05)
    finally:
        sub.undeclare()
        session.close()
        node.close()
    assert len(got) == keys, sorted(got)
    decoded: dict[str, Any] = {}
    for key, payloads in got.items():
        topic, typename = _type_of(key, key_mode)
        if not typename:
            typename = _ros2dds_type(topic)
        decoded[topic] = TS.deserialize_cdr(payloads[-1], typename)
    ns = {v: vehicle_names("droneulator", v, True, fleet_tf) for v in ("uav0", "uav1")}
    stamp = shot.t_ns
    for v, names in ns.items():
        odom = decoded[names.topics()["odom"]]
        assert (odom.header.frame_id, odom.child_frame_id) == (names.odom_frame, names.base_frame)
        assert odom.header.stamp.sec * 10**9 + odom.header.stamp.nanosec == stamp
        assert np.allclose([odom.pose.pose.position.x, odom.pose.pose.position.y],
                           shot.states[v].position[:2])  # fmt: skip
        cam = names.camera_topics("front")
        for key in ("depth", "rgb", "seg", "info_depth"):
            assert decoded[cam[key]].header.frame_id == names.optical_frame("front")
        assert decoded[cam["pose"]].header.frame_id == names.odom_frame
        depth = decoded[cam["depth"]]
        assert (depth.width, depth.height) == (SMALL.width, SMALL.height)
        # the sensor topics: in the vehicle's base_link (FLU), stamped with the instant sampled, SI units
        t = names.topics()
        imu, mag = decoded[t["imu"]], decoded[t["magnetic_field"]]
        baro, fix = decoded[t["air_pressure"]], decoded[t["gps_fix"]]
        battery = decoded[battery_state_topic(names.namespace)]
        assert battery.voltage == pytest.approx(shot.states[v].battery["voltage"], rel=1e-6)
        for msg in (imu, mag, baro, fix, battery):
            assert msg.header.frame_id == names.base_frame
            assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == stamp
        st = shot.states[v]
        R = quat_to_matrix(st.quaternion)  # body FLU -> world ENU
        accel = [imu.linear_acceleration.x, imu.linear_acceleration.y, imu.linear_acceleration.z]
        np.testing.assert_allclose(accel, R.T @ [0.0, 0.0, 9.81], atol=0.1)  # at rest: +g up, 5 sigma
        assert imu.orientation_covariance[0] == -1 and imu.linear_acceleration_covariance[0] == 0.02**2
        field_body = R.T @ ned_to_enu(field_ned) * 1e-4  # the WMM field (gauss, NED) in base_link, tesla
        got_field = [mag.magnetic_field.x, mag.magnetic_field.y, mag.magnetic_field.z]
        np.testing.assert_allclose(got_field, field_body, atol=5 * 0.002e-4)
        isa = isa_pressure_pa(home.altitude_m + st.position[2])
        assert baro.fluid_pressure == pytest.approx(isa, abs=5.0)  # Pa: 0.01 hPa noise, 5 sigma
        lat, lon, alt = enu_to_geodetic(st.position, *home.geodetic)
        assert (fix.status.status, fix.position_covariance_type) == (0, 2)
        assert (fix.latitude, fix.longitude, fix.altitude) == (
            pytest.approx(lat, abs=1e-6), pytest.approx(lon, abs=1e-6), pytest.approx(alt, abs=0.2),
        )  # fmt: skip
    children = set()
    for topic in {n.tf for n in ns.values()}:
        children |= {t.child_frame_id for t in _all_tf(got, topic, key_mode)}
    statics = set()
    for topic in {n.tf_static for n in ns.values()}:
        statics |= {(t.header.frame_id, t.child_frame_id) for t in _all_tf(got, topic, key_mode)}
    if fleet_tf == "prefix":  # one /tf, distinct frames under one map
        assert children == {"uav0/base_link", "uav1/base_link"}
        assert {("map", "uav0/odom"), ("map", "uav1/odom"), ("uav1/base_link", "uav1/front_link"),
                ("uav1/front_link", "uav1/front_optical_frame")} <= statics  # fmt: skip
    else:  # Nav2: each vehicle's own tf topics, unprefixed frames
        assert children == {"base_link"} and ("map", "odom") in statics
        assert len({n.tf for n in ns.values()}) == 2
    assert "/clock" in decoded


def test_the_bridges_encoder_threads_publish_the_bytes_of_one_thread_in_stamp_order() -> None:
    """``bridge.encode_threads`` encodes a frame set's images at once; what goes out must not change: the
    same JPEG and PNG bytes as one thread, every topic's messages in the order of their stamps, and the
    images decode to the rendered pixels."""
    import cv2

    cfg = two_vehicle_config()
    with World(cfg) as world:
        world.vehicle("uav1").place([*world.vehicle("uav1").state.position[:2], 1.5], 0.4, airborne=True)
        shot = world.render()
    sets = [  # three frame sets of the same pictures, 10 ms apart
        {v: dataclasses.replace(st, stamp_ns=st.stamp_ns + k * 10_000_000) for v, st in shot.states.items()}
        for k in range(3)
    ]
    got: dict[int, dict[str, list[bytes]]] = {}
    for threads in (1, 4):
        cfg.bridge.encode_threads = threads
        ep = f"tcp/127.0.0.1:{free_port()}"
        node = RosZenohNode(ZenohNodeConfig(mode="router", listen=(ep,), connect=()))
        sub_cfg = zenoh.Config()
        sub_cfg.insert_json5("mode", '"client"')
        sub_cfg.insert_json5("connect/endpoints", f'["{ep}"]')
        session = zenoh.open(sub_cfg)
        payloads: dict[str, list[bytes]] = defaultdict(list)
        lock, probed = threading.Lock(), threading.Event()

        def on_sample(sample: zenoh.Sample, payloads=payloads, lock=lock, probed=probed) -> None:
            key = str(sample.key_expr)
            if key == "test_probe":
                probed.set()
            elif "@" not in key:
                with lock:
                    payloads[key].append(sample.payload.to_bytes())

        sub = session.declare_subscriber("**", on_sample)
        frames = FramePublisher(node, cfg, zenoh.CongestionControl.BLOCK)
        try:
            assert frames.encode_threads == threads
            deadline = time.monotonic() + 10.0
            while not probed.is_set() and time.monotonic() < deadline:
                node.session.put("test_probe", b"")
                probed.wait(0.1)
            assert probed.is_set(), "the subscriber never heard the node"
            for states in sets:
                frames.publish(states, shot.cameras)
            end = time.monotonic() + 20.0  # 2 vehicles x 7 camera keys, 3 messages each
            while time.monotonic() < end and sum(map(len, payloads.values())) < 42:
                time.sleep(0.05)
        finally:
            frames.close()
            sub.undeclare()
            session.close()
            node.close()
        got[threads] = dict(payloads)
    counts = {k: len(p) for k, p in got[1].items()}
    assert len(counts) == 14 and set(counts.values()) == {3}, counts
    assert got[4] == got[1]  # byte for byte, message for message, in the same order
    for key, msgs in got[4].items():
        topic, typename = _type_of(key, "ros2dds")
        decoded = [TS.deserialize_cdr(m, typename or _ros2dds_type(topic)) for m in msgs]
        stamps = [d.header.stamp.sec * 10**9 + d.header.stamp.nanosec for d in decoded]
        vehicle = "uav0" if "uav0" in key else "uav1"
        assert stamps == [states[vehicle].stamp_ns for states in sets], key
        im = shot.cameras[vehicle]["front"]
        if key.endswith("color/image_raw/compressed"):
            rgb = cv2.cvtColor(cv2.imdecode(decoded[0].data, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
            assert np.abs(rgb.astype(float) - im.rgb.astype(float)).mean() < 3.0
        elif key.endswith("segmentation/image_raw/compressed"):
            np.testing.assert_array_equal(cv2.imdecode(decoded[0].data, cv2.IMREAD_UNCHANGED), im.seg)


def _ros2dds_type(topic: str) -> str:
    from droneulator.ros.topics import TYPES

    leaf = {
        "odom": "odom", "odom_world": "odom_world", "wind": "wind", "tf": "tf", "tf_static": "tf_static",
        "clock": "clock", "imu": "imu", "fix": "gps_fix", "air_pressure": "air_pressure",
        "magnetic_field": "magnetic_field", "battery": "battery", "faults": "faults",
        "pose": "pose", "camera_info": "info_rgb", "image_raw": "depth", "compressed": "rgb",
    }  # fmt: skip
    return TYPES[leaf[topic.rsplit("/", 1)[-1]]]


def _all_tf(got: dict[str, list[Any]], topic: str, key_mode: str) -> list[Any]:
    out = []
    for key, payloads in got.items():
        if _type_of(key, key_mode)[0] == topic:
            for raw in payloads:
                out += TS.deserialize_cdr(raw, "tf2_msgs/msg/TFMessage").transforms
    return out


# --------------------------------------------------------------------------- PX4, one instance per vehicle
def test_two_px4_instances_step_one_world_together() -> None:
    """Vehicle k listens on base_port + k; the world steps only when every PX4 in lockstep has answered,
    and each PX4 gets its own vehicle's sensor data."""
    base = consecutive_ports(2)
    cfg = two_vehicle_config()
    cfg.vehicles = [VehicleSpec(name=f"uav{k}", params="px4_quadx", controlled_by="px4") for k in range(2)]
    cfg.vehicle.control_hz = 250.0
    cfg.px4.base_port, cfg.px4.speed_factor = base, 0.0
    with World(cfg, render=False) as world:
        px4 = PX4Fleet.of(world)
        assert [(link.vehicle.name, link.instance) for link in px4.links] == [("uav0", 0), ("uav1", 1)]
        px4.start()
        stop = threading.Event()
        lock = threading.Lock()

        def serve() -> None:
            while not stop.is_set():
                px4.serve_once(0.01, lock)

        thread = threading.Thread(target=serve, daemon=True)
        thread.start()
        peers = [Peer(base + k) for k in range(2)]
        try:
            assert [link.port for link in px4.links] == [base, base + 1]
            for p in peers:
                p.hello()
            boot = [p.next("HIL_STATE_QUATERNION") for p in peers]
            for k, msgs in enumerate(boot):
                q = by_type(msgs, "HIL_STATE_QUATERNION")[-1]
                pos = world.vehicle(f"uav{k}").state.position
                lat, lon, _ = enu_to_geodetic(pos, *cfg.site.geodetic)
                assert abs(q.lat - round(lat * 1e7)) <= 2 and abs(q.lon - round(lon * 1e7)) <= 2
            for p in peers:
                p.step((0.0,) * 4, armed=False)  # both in lockstep now
            for p in peers:
                p.drain(0.3)
            with lock:
                t0 = world.t_ns
            peers[0].actuators((0.0,) * 4, armed=False)
            time.sleep(0.3)
            with lock:
                assert world.t_ns == t0  # uav1's PX4 has not answered: no step
            peers[1].actuators((0.0,) * 4, armed=False)
            times = [p.next()[-1].time_usec for p in peers]
            assert times == [(t0 + 4_000_000) // 1000] * 2
        finally:
            stop.set()
            thread.join(5)
            for p in peers:
                p.close()
            px4.close()


# --------------------------------------------------------------------------- droneulator run, end to end
@pytest.mark.slow
def test_a_two_vehicle_run_through_api_ros_px4_and_recording(tmp_path: Path) -> None:
    """uav1 flown by PX4 instance 1 (a scripted peer) while uav0 flies on the API; a ROS cmd_vel to uav1
    is refused; then both fly crossing gotos on the API; one recording holds every vehicle's topics and
    replays them all."""
    base = consecutive_ports(2)
    cfg = two_vehicle_config()
    cfg.vehicles = [VehicleSpec(name="uav0"), VehicleSpec(name="uav1", controlled_by="px4")]
    cfg.px4.base_port = base
    run = launch_run(cfg)
    bag = tmp_path / "fleet.mcap"
    recorder = Recorder(bag, run_recorder_config(run.config.bridge, run.zenoh_endpoint))
    recorder.start()
    peer = None
    try:
        with run.client() as c:
            info = c.scene_info()
            uav0, uav1 = info["vehicles"]
            assert uav0["topics"]["odom"] == "/droneulator/uav0/odom" and uav0["tf_prefix"] == "uav0/"
            assert uav1["controlled_by"] == "px4" and uav1["px4_port"] == base + 1 and "px4_port" not in uav0
            assert uav1["topics"]["cameras"]["front"]["depth"] == "/droneulator/uav1/front/depth/image_raw"
            c.subscribe(["events"])
            peer = Peer(base + 1)  # PX4 instance 1: its simulator port is 4560 + 1 in a default setup
            peer.hello()
            peer.next()
            peer.step((0.0,) * 4, armed=False)
            peer.drain(0.3)
            with pytest.raises(ApiError) as e:
                c.takeoff(2.0, vehicle="uav1")
            assert e.value.code == "flight_locked" and "uav1" in e.value.message
            with pytest.raises(ApiError) as e:
                c.reset()
            assert e.value.code == "flight_locked"
            c.takeoff(2.0, vehicle="uav0")  # the API still flies uav0
            session = zenoh.open(_client_of(run.zenoh_endpoint))
            ros: dict[str, list[Any]] = defaultdict(list)  # uav1's IMU and magnetometer topics
            leaves = {"imu": "sensor_msgs/msg/Imu", "magnetic_field": "sensor_msgs/msg/MagneticField"}
            subs = [
                session.declare_subscriber(f"droneulator/uav1/{leaf}", _recorder(ros, leaf, typename))
                for leaf, typename in leaves.items()
            ]
            pub = session.declare_publisher("droneulator/uav1/cmd_vel")
            pub.put(bytes(TS.serialize_cdr(_twist(1.0), "geometry_msgs/msg/Twist")))
            hil = {}  # HIL_SENSOR PX4 got, by sim time (ns)
            for _ in range(12):  # up to 12 s of sim time, stepped by PX4's lockstep messages
                for _ in range(250):
                    for m in by_type(peer.step((0.0,) * 4, armed=False), "HIL_SENSOR"):
                        hil[m.time_usec * 1000] = m
                if c.state(vehicle="uav0")["mode"] == "hold":
                    break
            arrived = c.wait_for_event("arrived", timeout=30, vehicle="uav0")
            assert arrived["command"] == "takeoff"
            refused = "/droneulator/uav1/cmd_vel velocity command rejected (flight_locked)"
            assert any(refused in line for line in run.log.lines())
            assert c.state(vehicle="uav1")["position"][2] < 0.05  # disarmed PX4: resting
            pub.undeclare()
            for sub in subs:
                sub.undeclare()
            session.close()
            _same_sample_as_px4(ros, hil)
            peer.close()  # PX4 leaves with its vehicle on the ground: the API may fly it again
            peer = None
            a, b = (np.array(c.state(vehicle=v)["position"]) for v in ("uav0", "uav1"))
            _until(lambda: _flies(c, "uav1"), 10)
            c.wait_for_event("arrived", timeout=60, vehicle="uav1")
            c.goto([*b[:2], 2.0], speed=2.0, vehicle="uav0")
            c.goto([*a[:2], 3.0], speed=2.0, vehicle="uav1")
            got = {c.wait_for_event("arrived", timeout=90)["vehicle"] for _ in range(2)}
            assert got == {"uav0", "uav1"}
            both = c.state(vehicle="*")["vehicles"]
            assert np.linalg.norm(np.array(both["uav1"]["position"]) - [*a[:2], 3.0]) < 0.15
    finally:
        if peer is not None:
            peer.close()
        stats = recorder.close()
        run.stop()
    topics = set(stats.written)
    for v in ("uav0", "uav1"):
        for leaf in (
            "odom",
            "odom_world",
            "wind",
            "front/color/image_raw/compressed",
            "front/depth/image_raw",
            "front/segmentation/image_raw/compressed",
            "front/color/camera_info",
            "front/pose",
            "imu",
            "gps/fix",
            "air_pressure",
            "magnetic_field",
        ):
            assert f"/droneulator/{v}/{leaf}" in topics
    assert {"/clock", "/tf", "/tf_static"} <= topics
    counts = replay(bag, ReplayConfig(listen=(f"tcp/127.0.0.1:{free_port()}",), rate=1000.0))
    assert {t for t, n in counts.items() if n} == topics


def _recorder(into: dict[str, list[Any]], leaf: str, typename: str) -> Any:
    def on_sample(sample: zenoh.Sample) -> None:
        into[leaf].append(TS.deserialize_cdr(sample.payload.to_bytes(), typename))

    return on_sample


def _same_sample_as_px4(ros: dict[str, list[Any]], hil: dict[int, Any]) -> None:
    """The ROS IMU of a PX4 vehicle is the HIL_SENSOR sample its PX4 got at that instant, value for value
    (float32 on the wire, FRD -> FLU: y and z change sign), not a second draw; the magnetometer too."""
    stamp = lambda m: m.header.stamp.sec * 10**9 + m.header.stamp.nanosec  # noqa: E731
    imus = [(m, hil[stamp(m)]) for m in ros["imu"] if stamp(m) in hil]
    assert len(imus) > 100, (len(ros["imu"]), len(hil))
    for m, h in imus:
        assert m.header.frame_id == "uav1/base_link"
        a, w = m.linear_acceleration, m.angular_velocity
        assert [a.x, a.y, a.z, w.x, w.y, w.z] == [h.xacc, -h.yacc, -h.zacc, h.xgyro, -h.ygyro, -h.zgyro]
    assert np.mean([m.linear_acceleration.z for m, _ in imus]) == pytest.approx(9.81, abs=0.01)  # at rest
    mags = [(m, hil[stamp(m)]) for m in ros["magnetic_field"] if stamp(m) in hil]
    fresh = [(m, h) for m, h in mags if h.fields_updated & 0b111000000]  # a new sample in that HIL_SENSOR
    assert len(fresh) > 50
    for m, h in fresh:
        f = m.magnetic_field
        np.testing.assert_allclose([f.x, f.y, f.z], np.array([h.xmag, -h.ymag, -h.zmag]) * 1e-4, rtol=1e-6)


def _flies(c: Any, vehicle: str) -> bool:
    try:
        c.takeoff(3.0, vehicle=vehicle)
        return True
    except ApiError as e:
        if e.code != "flight_locked":
            raise
        return False


def _until(pred: Any, timeout: float, what: Any = lambda: "") -> None:
    end = time.monotonic() + timeout
    while not pred():
        assert time.monotonic() < end, f"timed out {what()}"
        time.sleep(0.1)


def _latest(got: dict[str, list[int]]) -> str:
    """How many samples of each stream came, and the last one's stamp (for a failure's message)."""
    return "; ".join(f"{k}: {len(v)}, last {v[-1]}" for k, v in sorted(got.items()) if v)


def _client_of(endpoint: str) -> zenoh.Config:
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"client"')
    cfg.insert_json5("connect/endpoints", f'["{endpoint}"]')
    return cfg


def _twist(forward: float) -> Any:
    T = TS.types
    v = T["geometry_msgs/msg/Vector3"]
    return T["geometry_msgs/msg/Twist"](linear=v(x=forward, y=0.0, z=0.0), angular=v(x=0.0, y=0.0, z=0.0))


def test_a_px4_catching_up_on_its_boot_backlog_steps_once_on_the_latest_answer() -> None:
    """While PX4 boots the link free-runs and sends sensor data PX4 answers later, in a burst; each answer
    carries the time of the batch it answers. Stepping once per stale answer kept that backlog for the
    whole flight (a real PX4 booting slowly flew on outputs 2 s old and flipped): the link steps only on
    the answer to its latest batch, with the newest outputs."""
    base = consecutive_ports(1)
    cfg = load_config(scene="default")
    cfg.vehicle.control_hz, cfg.vehicle.params = 250.0, "px4_quadx"
    cfg.px4.enabled = True
    cfg.px4.base_port, cfg.px4.speed_factor = base, 0.0
    with World(cfg, render=False) as world:
        px4 = PX4Fleet.of(world)
        px4.start()
        stop, lock = threading.Event(), threading.Lock()

        def serve() -> None:
            while not stop.is_set():
                px4.serve_once(0.01, lock)

        thread = threading.Thread(target=serve)
        thread.start()
        peer = Peer(base)
        try:
            peer.hello()
            time.sleep(0.4)  # "booting": the link free-runs at 1x and queues batches on the socket
            batches = by_type(peer.drain(0.2), "HIL_SENSOR")
            assert len(batches) > 20
            for _ in range(5):
                for m in batches:  # PX4 answers every batch it has read, oldest first
                    peer.t_us = m.time_usec
                    peer.actuators((0.0,) * 4, armed=False)
                batches = by_type(peer.drain(0.3), "HIL_SENSOR")
                if len(batches) == 1:
                    break
            assert len(batches) == 1  # caught up: one step, on the answer to the latest batch only
            t_us = batches[0].time_usec
            with lock:
                assert t_us == world.t_ns // 1000
            for k in range(1, 4):  # and lockstep goes on, one step per answer
                peer.t_us = t_us + 4000 * (k - 1)
                assert peer.step((0.0,) * 4, armed=False)[-1].time_usec == t_us + 4000 * k
        finally:
            stop.set()
            thread.join(5)
            peer.close()
            px4.close()
