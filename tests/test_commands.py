"""The one command path: ROS topics over a real Zenoh session get the WebSocket API's validation, flight
lock and simulation lock, and their rejections are logged once per burst with the error code."""

from __future__ import annotations

import logging
import math
import threading
import time

import pytest
import zenoh
from rosbags.typesys import Stores, get_typestore

from droneulator.commands import CommandPath, make_request
from droneulator.commands import path as path_module
from droneulator.config import load_config
from droneulator.ros import messages as M
from droneulator.ros.publishers import subscribe_commands
from droneulator.ros.zenoh_node import RosZenohNode, ZenohNodeConfig
from droneulator.runtime.launch import free_port
from droneulator.world import World

TS = get_typestore(Stores.ROS2_JAZZY)
T = TS.types


def twist(forward: float, yaw_rate: float = 0.0) -> bytes:
    v = T["geometry_msgs/msg/Vector3"]
    msg = T["geometry_msgs/msg/Twist"](linear=v(x=forward, y=0.0, z=0.0), angular=v(x=0.0, y=0.0, z=yaw_rate))
    return bytes(TS.serialize_cdr(msg, "geometry_msgs/msg/Twist"))


def goal(frame: str, xyz: tuple[float, float, float], q: tuple[float, float, float, float]) -> bytes:
    zero = T["builtin_interfaces/msg/Time"](sec=0, nanosec=0)
    msg = T["geometry_msgs/msg/PoseStamped"](
        header=T["std_msgs/msg/Header"](stamp=zero, frame_id=frame),
        pose=T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=xyz[0], y=xyz[1], z=xyz[2]),
            orientation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
        ),
    )
    return bytes(TS.serialize_cdr(msg, "geometry_msgs/msg/PoseStamped"))


class Rig:
    """A simulator behind a CommandPath, its ROS command subscriptions, and a plain Zenoh publisher."""

    def __init__(self) -> None:
        cfg = load_config(scene="default")
        self.sim = World(config=cfg, render=False)
        self.commands = CommandPath(self.sim)
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.node = RosZenohNode(ZenohNodeConfig(listen=(endpoint,), connect=()))
        subscribe_commands(self.node, cfg, self.commands)
        conf = zenoh.Config()
        conf.insert_json5("connect/endpoints", f'["{endpoint}"]')
        conf.insert_json5("scouting/multicast/enabled", "false")
        self.peer = zenoh.open(conf)
        self.cmd_vel = self.peer.declare_publisher("droneulator/cmd_vel")
        self.goal_pose = self.peer.declare_publisher("droneulator/goal_pose")
        self.position_cmd = self.peer.declare_publisher("droneulator/position_cmd")
        self.attitude = self.peer.declare_publisher("droneulator/setpoint_raw/attitude")
        self.motor_speed = self.peer.declare_publisher("droneulator/command/motor_speed")
        deadline = time.monotonic() + 10
        while not self.cmd_vel.matching_status.matching:
            assert time.monotonic() < deadline, "the command subscriptions never matched"
            time.sleep(0.02)

    def close(self) -> None:
        self.peer.close()
        self.node.close()
        self.sim.close()


@pytest.fixture()
def rig():
    r = Rig()
    yield r
    r.close()


def rejections(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name == "droneulator.commands"]


def wait(predicate, what: str, timeout: float = 5.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.02)


def test_ros_commands_follow_the_api_rules_and_are_logged_once_per_burst(rig, caplog):
    caplog.set_level(logging.WARNING, logger="droneulator.commands")
    for _ in range(5):
        rig.cmd_vel.put(twist(math.nan))
    wait(lambda: rejections(caplog), "the NaN twist to be refused")
    time.sleep(0.3)
    (first,) = rejections(caplog)
    assert "/droneulator/cmd_vel velocity command rejected (invalid_argument)" in first
    assert "`forward` must be a finite number" in first

    for _ in range(3):  # valid values, but the motors are off: another code starts a new burst
        rig.cmd_vel.put(twist(1.0))
    wait(lambda: len(rejections(caplog)) >= 3, "the summary and the not_airborne rejection")
    summary, second = rejections(caplog)[1:3]
    assert summary == "4 more ROS /droneulator/cmd_vel velocity commands rejected (invalid_argument)"
    assert "rejected (not_airborne)" in second
    assert rig.sim.vehicle().mode.value == "idle"

    with rig.commands.lock:
        rig.sim.vehicle().takeoff(2.0)
    rig.commands.refuse_flight("PX4 SITL is in control")
    caplog.clear()
    for _ in range(10):
        rig.cmd_vel.put(twist(1.0))
    rig.goal_pose.put(goal("map", (1.0, 1.0, 2.0), (0.0, 0.0, 0.0, 1.0)))
    wait(lambda: any("goal_pose" in m for m in rejections(caplog)), "the refused goal")
    time.sleep(0.2)
    msgs = rejections(caplog)
    refused = "cmd_vel velocity command rejected (flight_locked): PX4 SITL is in control"
    assert sum(refused in m for m in msgs) == 1
    assert any("goal_pose goto command rejected (flight_locked)" in m for m in msgs)
    assert rig.sim.vehicle().mode.value == "takeoff"  # nothing ran

    rig.commands.allow_flight()
    rig.cmd_vel.put(twist(0.5, 0.1))
    wait(lambda: rig.sim.vehicle().mode.value == "velocity", "the twist to be accepted")


def test_goals_in_other_frames_or_with_a_zero_quaternion_are_refused(rig, caplog):
    caplog.set_level(logging.WARNING, logger="droneulator.commands")
    with rig.commands.lock:
        rig.sim.vehicle().takeoff(2.0)
    rig.goal_pose.put(goal("odom", (1.0, 1.0, 2.0), (0.0, 0.0, 0.0, 0.0)))
    wait(lambda: rejections(caplog), "the zero quaternion to be refused")
    assert "`yaw` must be a finite number" in rejections(caplog)[0]
    rig.goal_pose.put(goal("map", (1.0, 1.0, 500.0), (0.0, 0.0, 0.0, 1.0)))
    wait(lambda: len(rejections(caplog)) >= 2, "the out-of-bounds goal to be refused")
    assert "rejected (out_of_bounds)" in rejections(caplog)[1]
    rig.goal_pose.put(goal("base_link", (1.0, 1.0, 2.0), (0.0, 0.0, 0.0, 1.0)))
    wait(lambda: len(rejections(caplog)) >= 3, "the base_link goal to be refused")
    assert "goal in frame 'base_link': only map/odom" in rejections(caplog)[2]
    assert rig.sim.vehicle().mode.value == "takeoff"
    rig.goal_pose.put(goal("map", (1.0, 1.0, 2.0), (0.0, 0.0, 0.0, 1.0)))
    wait(lambda: rig.sim.vehicle().mode.value == "goto", "the valid goal to be flown")


def test_the_flight_lock_can_cover_chosen_ops():
    sim = World(scene="default", render=False)
    path = CommandPath(sim)
    path.refuse_flight("a PX4 is connected", ops=("reset",))
    assert path.execute(make_request("reset", {}))["error"]["code"] == "flight_locked"
    assert path.execute(make_request("takeoff", {}))["ok"]
    path.refuse_flight("PX4 flies")
    refused = path.execute(make_request("hold", {}))["error"]
    assert refused == {"code": "flight_locked", "message": "PX4 flies"}
    assert path.execute(make_request("state", {}))["ok"]
    path.allow_flight()
    assert path.execute(make_request("hold", {}))["ok"]
    with pytest.raises(ValueError):
        path.refuse_flight("x", ops=("state",))
    sim.close()


def setpoint(frame: str, xyz: tuple[float, float, float], yaw: float = 0.0) -> bytes:
    return bytes(M.serialize(M.position_command(0, frame, xyz, (0.2, 0.0, 0.0), (0.0, 0.0, 0.1), yaw, 0.1)))


def test_position_commands_follow_the_api_rules_and_the_flight_lock(rig, caplog):
    caplog.set_level(logging.WARNING, logger="droneulator.commands")
    rig.position_cmd.put(setpoint("world", (0.0, 0.0, 2.0)))
    wait(lambda: rejections(caplog), "the setpoint on the ground to be refused")
    assert "/droneulator/position_cmd track command rejected (not_airborne)" in rejections(caplog)[0]

    with rig.commands.lock:
        rig.sim.vehicle().takeoff(2.0)
    rig.commands.refuse_flight("PX4 SITL is in control")
    caplog.clear()
    for _ in range(20):
        rig.position_cmd.put(setpoint("world", (0.5, 0.0, 2.0)))
    wait(lambda: rejections(caplog), "the locked setpoints to be refused")
    time.sleep(0.3)
    refused = "position_cmd track command rejected (flight_locked): PX4 SITL is in control"
    assert sum(refused in m for m in rejections(caplog)) == 1  # once per burst
    assert rig.sim.vehicle().mode.value == "takeoff"

    rig.commands.allow_flight()
    caplog.clear()
    rig.position_cmd.put(setpoint("base_link", (0.5, 0.0, 2.0)))
    rig.position_cmd.put(setpoint("odom", (0.5, 0.0, 500.0)))
    rig.position_cmd.put(setpoint("map", (0.5, 0.0, 2.0), yaw=math.nan))
    wait(lambda: len(rejections(caplog)) >= 4, "the burst summary and the three bad setpoints")
    summary, *msgs = rejections(caplog)
    assert summary == "19 more ROS /droneulator/position_cmd track commands rejected (flight_locked)"
    assert "setpoint in frame 'base_link': only world/map/odom" in msgs[0]
    assert "rejected (out_of_bounds)" in msgs[1]
    assert "`yaw` must be a finite number" in msgs[2]
    assert rig.sim.vehicle().mode.value == "takeoff"

    rig.position_cmd.put(setpoint("world", (0.5, 0.25, 2.0), yaw=0.5))
    wait(lambda: rig.sim.vehicle().mode.value == "track", "the setpoint to be tracked")
    with rig.commands.lock:
        rig.sim.step()  # the first control tick after the setpoint: its reference is the setpoint itself
        ref = rig.sim.vehicle().state.reference
    assert ref[0:3].tolist() == [0.5, 0.25, 2.0] and ref[3:6].tolist() == [0.2, 0.0, 0.0]
    assert ref[6:9].tolist() == [0.0, 0.0, 0.1] and (ref[9], ref[10]) == (0.5, 0.1)


def test_attitude_targets_and_motor_speeds_fly_rates_attitude_and_rotors(rig, caplog):
    """MAVROS's AttitudeTarget and Gazebo's Actuators over Zenoh reach the three ops below the SE(3)
    controller, with their rules and the flight lock."""
    caplog.set_level(logging.WARNING, logger="droneulator.commands")
    uav = rig.sim.vehicle()
    with rig.commands.lock:
        rig.sim.reset(position=[0.0, 0.0, 3.0])
    hover_share = uav.thrust / uav.max_thrust  # hovering at rest: the thrust balances the weight

    def put(pub, msg) -> None:
        pub.put(bytes(M.serialize(msg)))

    put(rig.attitude, M.attitude_target(0, "", hover_share, body_rate=(0.1, 0.2, 1.0), type_mask=128 | 1))
    wait(lambda: uav.mode.value == "rates", "the body rates to be taken")
    assert uav.flight._inner[0] == pytest.approx(uav.thrust, rel=1e-6)  # normalised (float32) to N
    assert uav.flight._inner[1:4].tolist() == pytest.approx([0.0, 0.2, 1.0])  # roll rate ignored: 0

    q = M.attitude_target(0, "", hover_share, (0.0, 0.0, math.sin(0.25), math.cos(0.25)))
    put(rig.attitude, q)
    wait(lambda: uav.mode.value == "attitude", "the attitude to be taken")
    assert uav.flight._inner[1:5].tolist() == pytest.approx([0.0, 0.0, math.sin(0.25), math.cos(0.25)])

    put(rig.motor_speed, M.actuators(0, velocity=[400.0, 410.0, 420.0, 430.0]))
    wait(lambda: uav.mode.value == "rotors", "the rotor speeds to be taken")
    assert uav.flight._rotors.tolist() == [400.0, 410.0, 420.0, 430.0]
    put(rig.motor_speed, M.actuators(0, normalized=[0.25, 0.25, 0.25, 1.0]))
    wait(lambda: uav.flight._rotors[3] == 1500.0, "the normalised thrusts to be taken")
    assert uav.flight._rotors.tolist() == [750.0, 750.0, 750.0, 1500.0]

    caplog.clear()
    put(rig.motor_speed, M.actuators(0, velocity=[400.0] * 4, normalized=[0.5] * 4))
    wait(lambda: rejections(caplog), "speeds and thrusts at once to be refused")
    put(rig.motor_speed, M.actuators(0, velocity=[400.0] * 4))  # taken: the burst of rejections ends
    wait(lambda: uav.flight._rotors[3] == 400.0, "the rotor speeds to be taken")
    put(rig.motor_speed, M.actuators(0, velocity=[400.0] * 3))
    put(rig.attitude, M.attitude_target(0, "", 0.5, type_mask=64))
    put(rig.attitude, M.attitude_target(0, "", 1.5, type_mask=128))
    wait(lambda: len(rejections(caplog)) >= 4, "the four bad commands to be refused")
    msgs = "\n".join(rejections(caplog))
    assert "command/motor_speed rotors command rejected (invalid_argument): `rotor_speeds` must be" in msgs
    assert "rejected (invalid_argument): four rotor speeds in velocity" in msgs
    assert "attitude command rejected (invalid_argument): a setpoint without thrust" in msgs
    assert "rates command rejected (out_of_range)" in msgs

    rig.commands.refuse_flight("PX4 SITL is in control")
    caplog.clear()
    put(rig.attitude, M.attitude_target(0, "", 0.2, type_mask=128))
    put(rig.motor_speed, M.actuators(0, velocity=[400.0] * 4))
    wait(lambda: len(rejections(caplog)) >= 2, "the locked commands to be refused")
    assert all("(flight_locked): PX4 SITL is in control" in m for m in rejections(caplog))
    assert uav.flight._rotors[3] == 400.0  # nothing ran
    rig.commands.allow_flight()


def test_commands_never_interleave_with_a_step():
    """A command from any source waits for the simulation lock held by the stepping loop."""
    sim = World(scene="default", render=False)
    path = CommandPath(sim)
    done = threading.Event()
    with path.lock:
        worker = threading.Thread(target=lambda: (path.execute(make_request("takeoff", {})), done.set()))
        worker.start()
        time.sleep(0.2)
        assert not done.is_set() and sim.vehicle().mode.value == "idle"
    worker.join(5)
    assert done.is_set() and sim.vehicle().mode.value == "takeoff"
    sim.close()


def test_a_command_goes_before_the_stepping_loops_next_step(monkeypatch):
    """The stepping loop takes the lock again the moment it lets go. With a plain lock a waiting command
    waited while it did so again and again (a takeoff asked at t = 0 of a lockstep run ran at t = 3.5 s);
    on the loop's side of the simulation lock the loop lets every waiting command go first, so each of
    these commands runs before the loop's second step after it asked."""
    monkeypatch.setattr(path_module, "LOOP_YIELD_S", 60.0)  # judge the order, not the machine's speed
    sim = World(scene="default", render=False)
    path = CommandPath(sim)
    steps, stop = [0], threading.Event()

    def loop() -> None:
        while not stop.is_set():
            with path.lock.loop:
                steps[0] += 1
                sim.step()

    stepper = threading.Thread(target=loop)
    stepper.start()
    try:
        late = []
        for _ in range(30):
            asked = steps[0]
            with path.lock:
                late.append(steps[0] - asked)
            time.sleep(0.002)
        assert max(late) <= 1, late
        assert path.execute(make_request("takeoff", {}))["ok"]
    finally:
        stop.set()
        stepper.join(5)
        sim.close()


def test_a_sources_burst_of_rejections_goes_on_while_another_sources_interleave(caplog):
    """Grouped by source: a second topic's rejections do not end the first one's burst (each would log a
    line per sample when two topics alternate), a new code from the same source does at once."""
    from droneulator.logs import LogThrottle

    caplog.set_level(logging.WARNING, logger="test.throttle")
    throttle = LogThrottle(logging.getLogger("test.throttle"), gap=60.0, one_at_a_time=True,
                           group=lambda key: key[0])  # fmt: skip
    for source, code in [("a", "x"), ("b", "x"), ("a", "x"), ("b", "x"), ("a", "x"), ("a", "y")]:
        more = f"{{n}} more {source} {code}"
        throttle.log((source, code), logging.WARNING, f"{source} {code}", summary=more)
    assert [r.getMessage() for r in caplog.records] == ["a x", "b x", "2 more a x", "a y"]
