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
