"""ArduPilot SITL's JSON interface over real UDP, with a scripted peer sending the servo packets ArduPilot
sends and parsing the replies as SIM_JSON.cpp does (:mod:`scripted_ardupilot`), against a running link
stepping a real world."""

from __future__ import annotations

import json
import math
import threading
import time
from typing import Any

import numpy as np
import pytest
from scripted_ardupilot import (
    KEYTABLE,
    RecvBuffer,
    ScriptedArduCopterMavlink,
    ScriptedArduPilot,
    parse_sensors,
    rpy_factors,
    thrust_to_pwm,
)

from droneulator import frames as F
from droneulator.ardupilot import ARDUCOPTER_QUAD_X, ArduCopterMotors, ArduPilotFleet, ArduPilotLink
from droneulator.ardupilot import link as link_module
from droneulator.ardupilot.mixing import (
    ARDUCOPTER_OCTAQUAD_X_DEFS,
    ARDUCOPTER_QUAD_X_DEFS,
    ArduCopterOctaQuadMotors,
)
from droneulator.ardupilot.protocol import (
    SERVO_16,
    SERVO_32,
    FdmState,
    ProtocolError,
    ServoPacket,
    decode_servo,
)
from droneulator.commands import CommandPath, make_request
from droneulator.config import ArduPilotConfig, SiteConfig, VehicleSpec, load_config
from droneulator.px4.flight_lock import PX4FlightLock
from droneulator.px4.mixing import PX4_QUAD_X
from droneulator.sensors import Truth
from droneulator.vehicles.params import get_params
from droneulator.workflows.planning.guided import GuidedConfig, GuidedLink
from droneulator.world import World

HZ = 400  # the tests' world and peer rate (ArduCopter's own default is 1200)
DT_NS = 1_000_000_000 // HZ


def make_world(params: str = "px4_quadx", **cfg: Any) -> World:
    c = load_config(overrides=[f"vehicle.control_hz={HZ}", f"vehicle.params={params}"])
    c.ardupilot = ArduPilotConfig(base_port=0, **cfg)
    return World(c, scene="default", render=False)


def wait_until(pred: Any, timeout: float = 5.0) -> None:
    end = time.monotonic() + timeout
    while not pred():
        assert time.monotonic() < end, "timed out"
        time.sleep(0.005)


class Served:
    """An ArduPilotLink served from a background thread, as the dynamics server does; ``run_alone``: the
    world steps on its own while no ArduPilot is connected and the vehicle is not at rest."""

    def __init__(self, world: World, run_alone: bool = False) -> None:
        self.world, self.run_alone = world, run_alone
        self.lock = threading.Lock()
        self.link = ArduPilotLink(world)
        self.link.start()
        self.sim_events: list[Any] = []
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            res = self.link.serve_once(0.01, self.lock)
            if res is not None:
                self.sim_events.extend(res.events)
            elif self.run_alone and not self.link.connected:
                with self.lock:
                    v = self.world.vehicle()
                    if v.mode.value != "idle" or v.state.position[2] > 0.05:
                        self.sim_events.extend(self.world.step().events)

    def peer(self, **kw: Any) -> ScriptedArduPilot:
        return ScriptedArduPilot(self.link.port, rate_hz=HZ, **kw)

    def close(self) -> None:
        self._stop.set()
        self.thread.join(5.0)
        self.link.close()


@pytest.fixture(scope="module")
def world():
    w = make_world()
    w.step()  # compiles the step (seconds on a fresh clone) before any peer's frame waits on it
    w.reset()
    yield w
    w.close()


@pytest.fixture()
def served(world):
    world.reset()
    s = Served(world)
    yield s
    s.close()


def in_the_air(served: Served, position: Any) -> ScriptedArduPilot:
    """An ArduPilot with the rotors in a hover at ``position``: it connects on the ground (a new ArduPilot
    gets the rotors only there), then the world is reset in-process into a hover there."""
    peer = served.peer()
    peer.step([1000] * 4)
    assert served.link.in_control
    with served.lock:
        served.world.reset(position=position, airborne=True)
    return peer


def hover_pwm(served: Served) -> float:
    return float(served.link.motors.pwm_for_speed(served.world.vehicle().hover_speed))


# --------------------------------------------------------------------------- the wire format
def test_servo_packets_are_sim_jsons_structs_and_anything_else_is_refused():
    assert (SERVO_16.size, SERVO_32.size) == (40, 72)  # sizeof(servo_packet_16/32), packed
    pkt = ServoPacket(1200, 7, tuple(range(1000, 1016)))
    raw = pkt.encode()
    assert raw[:8] == bytes([0x1A, 0x48, 0xB0, 0x04, 7, 0, 0, 0])  # 18458, 1200, 7 little-endian
    assert decode_servo(raw) == pkt
    wide = ServoPacket(400, 2**32 - 1, tuple(range(32)))
    assert decode_servo(wide.encode()) == wide and wide.encode()[:2] == (29569).to_bytes(2, "little")
    for bad, why in [
        (raw[:-2], "has 40 bytes"),
        (b"\x00\x00" + raw[2:], "magic 0"),
        (b"", "no servo packet"),
        (ServoPacket(0, 1, (1000,) * 16).encode(), "frame_rate 0"),
    ]:
        with pytest.raises(ProtocolError, match=why):
            decode_servo(bad)


def test_the_reply_parses_as_sim_json_reads_it_in_ardupilots_frames():
    """Compact, newline-framed JSON; each value where SIM_JSON's strstr/sscanf parser looks for it; the
    truth in NED/FRD (nose east, rolled right, pitched down, climbing north-west)."""
    q = F.quat_from_euler(0.1, 0.2, 0.0)  # FLU in ENU: roll 0.1, pitch 0.2, facing east
    truth = Truth(
        1_500_000_000,
        np.array([1.0, 2.0, 3.0]),
        np.array([0.5, -0.25, 1.0]),
        q,
        np.array([0.01, 0.02, 0.03]),
        np.zeros(3),
        np.zeros(3),
        np.array([0.0, 0.0, 9.81]),
    )
    accel, gyro = truth.specific_force_frd, truth.gyro_frd
    raw = FdmState.from_truth(1.5, truth, accel, gyro, airspeed=4.5, ranges=(2.5,)).encode()
    text = raw.decode()
    assert text.startswith("\n") and text.endswith("\n") and text.count("\n") == 2
    assert ": " not in text and ", " not in text
    got = RecvBuffer().feed(raw)
    assert got is not None
    assert got["timestamp"] == 1.5
    np.testing.assert_allclose(got["position"], [2.0, 1.0, -3.0])  # north, east, down
    np.testing.assert_allclose(got["velocity"], [-0.25, 0.5, -1.0])
    np.testing.assert_allclose(got["imu.gyro"], [0.01, -0.02, -0.03])
    np.testing.assert_allclose(got["imu.accel_body"], [0.0, 0.0, -9.81])
    w, x, y, z = got["quaternion"]
    roll, pitch, yaw = F.quat_to_euler(np.array([x, y, z, w]))
    # FLU's +pitch about the left axis is nose down, FRD's about the right axis nose up; +roll (left side
    # up) is a right roll in both
    assert (roll, pitch) == pytest.approx((0.1, -0.2))
    assert yaw == pytest.approx(math.pi / 2)  # facing east: yaw 90 deg from north
    assert got["rng_1"] == 2.5 and got["airspeed"] == 4.5
    assert "attitude" not in got and "no_time_sync" not in got
    assert set(json.loads(text)) <= {k for _, k, _, _ in KEYTABLE} | {"imu"}


def test_the_scripted_parser_refuses_what_sim_json_refuses():
    """The peer's parser is SIM_JSON's: a space after the colon, a missing required key or no attitude
    drops the frame, and a line is taken only between two newlines."""
    good = (
        '{"timestamp":1,"imu":{"gyro":[0,0,0],"accel_body":[0,0,-9.8]},"position":[0,0,0],'
        '"attitude":[0,0,0],"velocity":[0,0,0]}'
    )
    assert parse_sensors(good) is not None
    assert parse_sensors(good.replace('"position":[', '"position": [')) is None
    assert parse_sensors(good.replace('"velocity"', '"speed_ned"')) is None
    assert parse_sensors(good.replace('"attitude"', '"euler"')) is None
    inbox = RecvBuffer()
    assert inbox.feed(good.encode() + b"\n") is None  # no newline before it yet
    assert inbox.feed(good.encode() + b"\n") is not None  # the first one's newline frames the second


# --------------------------------------------------------------------------- motor mapping
def test_arducopters_quad_x_table_is_pxs_layout_and_the_rotor_order_follows_the_airframe():
    assert [(m.number, m.name, m.spin) for m in ARDUCOPTER_QUAD_X] == [
        (1, "front-right", "CCW"),
        (2, "rear-left", "CCW"),
        (3, "front-left", "CW"),
        (4, "rear-right", "CW"),
    ]
    assert ARDUCOPTER_QUAD_X == PX4_QUAD_X
    assert ArduCopterMotors(get_params("px4_quadx")).order == (0, 1, 2, 3)
    # hummingbird r1 front-left CW, r2 front-right CCW, r3 rear-right CW, r4 rear-left CCW
    assert ArduCopterMotors(get_params("hummingbird")).order == (1, 3, 0, 2)
    mirrored = get_params("hummingbird")
    mirrored["rotor_directions"] = -np.asarray(mirrored["rotor_directions"])
    with pytest.raises(ValueError, match="ArduPilot would yaw"):
        ArduCopterMotors(mirrored)


def test_pwm_maps_through_arducopters_thrust_curve_to_rotor_thrust():
    """A PWM that ArduCopter outputs for thrust fraction t gives the rotor t of full thrust, whatever
    MOT_THST_EXPO; below MOT_SPIN_MIN no thrust; the disarmed PWM reads disarmed."""
    qp = get_params("px4_quadx")
    for expo in (0.65, 0.0, 1.0, -0.3):
        m = ArduCopterMotors(qp, ArduPilotConfig(thrust_expo=expo))
        t = np.array([0.0, 0.1, 0.4, 0.7, 1.0])
        pwm = np.array([thrust_to_pwm(x, expo=expo) for x in t])
        w = np.array([m.rotor_speeds([p] * 4)[0] for p in pwm])
        w_min, w_max = qp["rotor_speed_min"], qp["rotor_speed_max"]
        np.testing.assert_allclose(((w - w_min) / (w_max - w_min)) ** 2, t, atol=2e-3)  # 1 us PWM steps
        np.testing.assert_allclose(m.pwm_for_speed(w), pwm, atol=1e-6)
    m = ArduCopterMotors(qp)
    assert np.all(m.rotor_speeds([1100] * 4) == qp["rotor_speed_min"])  # MOT_SPIN_ARM 0.10 < SPIN_MIN
    assert not m.armed([1000] * 4) and not m.armed([0] * 4) and m.armed([1100, 1000, 1000, 1000])


# --------------------------------------------------------------------------- lockstep
def test_each_new_frame_steps_the_world_once_and_is_answered_at_rest(served, world):
    peer = served.peer()
    try:
        with served.lock:
            t0 = world.t_ns
        replies = [peer.step([1000] * 4) for _ in range(40)]
        assert world.t_ns == t0 + 40 * DT_NS
        assert [r["timestamp"] for r in replies] == pytest.approx([(k + 1) / HZ for k in range(40)])
        last = replies[-1]
        np.testing.assert_allclose(last["imu.accel_body"], [0.0, 0.0, -9.81], atol=0.05)
        np.testing.assert_allclose(last["imu.gyro"], [0.0, 0.0, 0.0], atol=0.01)
        np.testing.assert_allclose(last["position"], F.enu_to_ned(world.vehicle().state.position), atol=1e-6)
        assert abs(last["position"][2]) < 0.05 and served.link.in_control and not served.link.armed
        events = [e.type for e in served.link.take_events()]
        assert events == ["ardupilot_connected"]
    finally:
        peer.close()


def test_a_repeated_frame_gets_the_same_reply_and_no_step_and_a_reset_count_reconnects(
    served, world, monkeypatch
):
    """SIM_JSON repeats a frame whose reply it lost (after 1 s): the same bytes come back and the world does
    not step; a repeat sooner than RESEND_AFTER_S crossed the reply and is not answered. A frame count
    that goes back is a restarted SITL: lost, connected anew, clock from zero."""
    peer = served.peer()
    try:
        for _ in range(5):
            peer.step([1000] * 4)
        peer.send_frame(frame_count=peer.frame_counter - 1)  # at once: it crossed the reply
        assert peer.quiet(0.2) and served.link.resent == 0
        monkeypatch.setattr(link_module, "RESEND_AFTER_S", 0.0)
        raw: list[bytes] = []
        for _ in range(3):
            with served.lock:
                t = world.t_ns
            peer.send_frame(frame_count=peer.frame_counter - 1)  # the frame answered last, again
            data, _ = peer.sock.recvfrom(65000)
            raw.append(data)
            with served.lock:
                assert world.t_ns == t
        assert raw[0] == raw[1] == raw[2] and json.loads(raw[0])["timestamp"] == pytest.approx(5 / HZ)
        assert served.link.resent == 3
        served.link.take_events()
        peer.frame_counter = 0  # SITL restarted: its frame_counter starts again
        first = peer.step([1000] * 4)
        assert first["timestamp"] == pytest.approx(1 / HZ)
        assert [e.type for e in served.link.take_events()] == [
            "ardupilot_disconnected",
            "ardupilot_connected",
        ]
    finally:
        peer.close()


def test_a_frame_waiting_for_its_step_is_not_answered_twice_and_32_channels_work(world):
    """Two vehicles, two instances: once both are connected the world steps when both sent their frame
    (a link without an ArduPilot does not hold the clock); the first one's repeat of its waiting frame
    is ignored."""
    c = load_config(overrides=[f"vehicle.control_hz={HZ}"])
    c.vehicles = [
        VehicleSpec(name=f"uav{k}", params="px4_quadx", controlled_by="ardupilot") for k in range(2)
    ]
    c.ardupilot = ArduPilotConfig(base_port=0)
    with World(c, scene="default", render=False) as w:
        w.step()  # compiles a two-vehicle world's step before a peer's frame waits on it
        w.reset()
        fleet = ArduPilotFleet.of(w)
        assert [(link.vehicle.name, link.instance) for link in fleet.links] == [("uav0", 0), ("uav1", 1)]
        fleet.start()
        lock, stop = threading.Lock(), threading.Event()

        def serve() -> None:
            while not stop.is_set():
                fleet.serve_once(0.01, lock)

        thread = threading.Thread(target=serve, daemon=True)
        thread.start()
        peers = [
            ScriptedArduPilot(link.port, rate_hz=HZ, channels=16 + 16 * k)
            for k, link in enumerate(fleet.links)
        ]
        try:
            peers[0].step([1000] * 4)  # connects, the world steps alone: uav1 has no ArduPilot yet
            peers[1].send_frame([1000] * 4)  # connects: now both must send
            assert peers[1].quiet(0.3)
            with lock:
                t0 = w.t_ns
            peers[0].send_frame([1000] * 4)
            got = [p.receive() for p in peers]
            with lock:
                assert w.t_ns == t0 + DT_NS
            peers[0].send_frame([1000] * 4)
            peers[0].send_frame([1000] * 4, frame_count=peers[0].frame_counter)  # repeated while it waits
            assert peers[0].quiet(0.3)
            with lock:
                assert w.t_ns == t0 + DT_NS  # uav1's ArduPilot has not sent: no step
            peers[1].send_frame([1000] * 4)
            got = [p.receive() for p in peers]
            assert [g is not None and g["timestamp"] for g in got] == pytest.approx([3 / HZ, 2 / HZ])
            assert peers[0].quiet(0.2) and w.t_ns == t0 + 2 * DT_NS
            for k, g in enumerate(got):
                assert g is not None
                np.testing.assert_allclose(g["position"], F.enu_to_ned(w.vehicle(f"uav{k}").state.position))
        finally:
            stop.set()
            thread.join(5)
            for p in peers:
                p.close()
            fleet.close()


def test_hover_with_a_scripted_mixer_holds_altitude(served, world):
    """A scripted ArduCopter (altitude PD on the reply's NED position, its thrust through ArduCopter's
    output chain) takes off and hovers at 2 m; the accelerometer reads 1 g of thrust."""
    peer = served.peer()
    try:
        w_min, w_max = (
            world.vehicle().quad_params["rotor_speed_min"],
            world.vehicle().quad_params["rotor_speed_max"],
        )
        t_hover = ((world.vehicle().hover_speed - w_min) / (w_max - w_min)) ** 2
        state = peer.step([1000] * 4)
        zs, acc = [], []
        for k in range(4 * HZ):  # 4 s
            z, vz = -state["position"][2], -state["velocity"][2]
            t = t_hover * (1.0 + 1.5 * (2.0 - z) - 1.2 * vz)
            state = peer.step([thrust_to_pwm(t)] * 4)
            if k >= 3 * HZ:
                zs.append(-state["position"][2])
                acc.append(state["imu.accel_body"])
        assert served.link.armed and world.vehicle().mode.value == "external"
        assert max(abs(z - 2.0) for z in zs) < 0.1
        np.testing.assert_allclose(np.mean(acc, axis=0), [0.0, 0.0, -9.81], atol=0.1)
    finally:
        peer.close()


def _hovering(served: Served, w: World, pwm: float) -> ScriptedArduPilot:
    """A fresh ArduPilot with the rotors, in a hover at 3 m on ``pwm``, the last one gone."""
    wait_until(lambda: not served.link.connected, 5.0)
    with served.lock:
        w.reset()
    peer = in_the_air(served, w.scene.spawn_position + [0.0, 0.0, 3.0])
    for _ in range(5):
        peer.step([pwm] * 4)
    return peer


@pytest.mark.parametrize("params", ["px4_quadx", "hummingbird"])
def test_roll_pitch_yaw_commands_mixed_as_arducopter_turn_the_body_that_way(params, world, quick_loss):
    """A roll, pitch or yaw command mixed by ArduCopter's quad-X factors (``AP_MotorsMatrix::add_motor``:
    thrust_i = hover + c * factor_i, out through its thrust curve) turns the vehicle the right way about
    that axis alone (the reply's gyro, FRD: + is roll right, nose up, yaw right); one motor's extra PWM
    speeds up the RotorPy rotor the motor table names."""
    w = world if params == "px4_quadx" else make_world(params)
    w.reset()
    served = Served(w)
    try:
        qp = w.vehicle().quad_params
        t_hover = (
            (w.vehicle().hover_speed - qp["rotor_speed_min"])
            / (qp["rotor_speed_max"] - qp["rotor_speed_min"])
        ) ** 2
        factors = np.array([rpy_factors(angle, yaw) for _, angle, yaw in ARDUCOPTER_QUAD_X_DEFS])
        for axis in range(3):
            peer = _hovering(served, w, float(thrust_to_pwm(t_hover)))
            cmd = thrust_to_pwm(t_hover + 0.04 * factors[:, axis] / np.max(np.abs(factors[:, axis])))
            for _ in range(HZ // 10):  # 0.1 s
                state = peer.step(cmd)
            rates = np.array(state["imu.gyro"])
            assert rates[axis] > 0.01, (axis, rates)
            assert rates[axis] > 3 * np.max(np.abs(np.delete(rates, axis))), (axis, rates)
            peer.close()
        hover = hover_pwm(served)
        for number, _, _ in ARDUCOPTER_QUAD_X_DEFS:
            peer = _hovering(served, w, hover)
            cmd = [hover] * 4
            cmd[number - 1] += 40
            for _ in range(10):
                peer.step(cmd)
            assert int(np.argmax(w.vehicle().state.rotor_speeds)) == served.link.motors.order[number - 1]
            peer.close()
    finally:
        served.close()
        if w is not world:
            w.close()


def test_the_sprayers_coaxial_pairs_fly_on_arducopters_octa_quad_x_table():
    """sprayer40 (four coaxial pairs, one rotor each) gets ArduCopter's OctaQuad X: motors 1-4 the upper
    ring, a quad X, 5-8 under them spinning the other way; each pair-rotor is its corner's."""
    m = ArduCopterOctaQuadMotors(get_params("sprayer40"))
    # sprayer40: r1 front-left CW, r2 front-right CCW, r3 rear-right CW, r4 rear-left CCW (pair-rotors)
    assert m.table() == [
        (1, "front-right upper", "CCW", "r2"),
        (2, "front-left upper", "CW", "r1"),
        (3, "rear-left upper", "CCW", "r4"),
        (4, "rear-right upper", "CW", "r3"),
        (5, "front-left lower", "CCW", "r1"),
        (6, "front-right lower", "CW", "r2"),
        (7, "rear-right lower", "CCW", "r3"),
        (8, "rear-left lower", "CW", "r4"),
    ]
    assert [d[3] for d in ARDUCOPTER_OCTAQUAD_X_DEFS] == [1, 7, 5, 3, 8, 2, 4, 6]  # testing order
    assert not m.armed([1000] * 8 + [0] * 8) and m.armed([1000] * 7 + [1100])


@pytest.mark.parametrize("channels", [16, 32])
def test_octa_quad_x_hover_yaw_and_roll_give_each_pair_its_thrust_and_torque(channels, quick_loss):
    """The PWM ArduCopter's OctaQuad X mixer sends (factors of ``add_motor``, out through its thrust curve),
    in 16- or 32-channel packets: hover holds the sprayer level with four equal pair speeds; a yaw command
    (each pair's CCW motor up, its CW motor down: the pairs' thrust unchanged) speeds up the CCW
    pair-rotors, slows the CW ones and yaws the body right; a roll command speeds up the left pairs and
    rolls it right (the reply's gyro, FRD)."""
    w = make_world("sprayer40")
    w.step()  # compiles the step before the peer's first frame waits on it
    w.reset()
    served = Served(w)
    try:
        m = served.link.motors
        assert isinstance(m, ArduCopterOctaQuadMotors)
        qp = w.vehicle().quad_params
        t_hover = (w.vehicle().hover_speed / qp["rotor_speed_max"]) ** 2
        factors = np.array([rpy_factors(angle, yaw) for _, angle, yaw, _ in ARDUCOPTER_OCTAQUAD_X_DEFS])
        ccw = np.sign(qp["rotor_directions"]) < 0
        left = np.array([p[1] > 0 for p in qp["rotor_pos"].values()])
        for axis, faster in ((None, None), (2, ccw), (0, left)):
            wait_until(lambda: not served.link.connected, 5.0)
            with served.lock:
                w.reset()
            peer = served.peer(channels=channels)
            peer.step([1000] * 8)
            with served.lock:
                w.reset(position=w.scene.spawn_position + [0.0, 0.0, 3.0], airborne=True)
            thrust = np.full(8, t_hover)
            if axis is not None:
                thrust += 0.05 * factors[:, axis] / np.max(np.abs(factors[:, axis]))
            cmd = thrust_to_pwm(thrust)
            for _ in range(HZ // 5):  # 0.2 s
                state = peer.step(cmd)
            rates = np.array(state["imu.gyro"])
            speeds = m.rotor_speeds(cmd)
            if axis is None:
                np.testing.assert_allclose(speeds, w.vehicle().hover_speed, rtol=2e-3)
                assert np.max(np.abs(rates)) < 0.01, rates
            else:
                assert np.all(speeds[faster] > speeds[~faster] * 1.02), (axis, speeds)
                assert rates[axis] > 0.01, (axis, rates)
                assert rates[axis] > 3 * np.max(np.abs(np.delete(rates, axis))), (axis, rates)
            peer.close()
    finally:
        served.close()
        w.close()


# --------------------------------------------------------------------------- one ArduPilot per port
def test_a_second_sender_is_refused_while_the_first_streams(served, world):
    first, second = served.peer(), served.peer()
    try:
        for _ in range(5):
            first.step([1000] * 4)
        second.send_frame([1300] * 4)
        assert second.quiet(0.3)
        first.step([1000] * 4)
        events = served.link.take_events()
        refused = [e for e in events if e.type == "ardupilot_refused"]
        assert len(refused) == 1 and refused[0].data["address"] == "{}:{}".format(*second.address)
        assert served.link.peer == "{}:{}".format(*first.address) and not served.link.armed
    finally:
        first.close()
        second.close()


# --------------------------------------------------------------------------- loss rules and hand-over
@pytest.fixture()
def quick_loss(monkeypatch):
    monkeypatch.setattr(link_module, "LINK_SILENCE_S", 0.3)


@pytest.mark.parametrize("on_loss", ["land", "hold", "fall"])
def test_an_ardupilot_lost_in_the_air_and_restarted_never_drops_the_vehicle_unless_told_to(
    on_loss, quick_loss
):
    """ArduPilot stops sending at 3 m (killed): after LINK_SILENCE_S it is lost and ``on_loss`` applies.
    A restarted ArduPilot connects with the vehicle in the air: its arm there is refused and its outputs
    not applied; once the vehicle is down and it is disarmed, it gets the rotors."""
    w = make_world(on_loss=on_loss)
    served = Served(w, run_alone=True)
    link = served.link
    try:
        first = in_the_air(served, w.scene.spawn_position + [0.0, 0.0, 3.0])
        hover = hover_pwm(served)
        for _ in range(20):
            first.step([hover] * 4)
        assert link.in_control and w.vehicle().mode.value == "external"
        link.take_events()
        served.sim_events.clear()
        first.close()  # killed
        taken: list[Any] = []
        wait_until(lambda: taken.extend(link.take_events()) or any(e.type == "ardupilot_lost" for e in taken))
        lost = [e for e in taken if e.type == "ardupilot_lost"]
        assert len(lost) == 1 and lost[0].data["action"] == on_loss
        assert w.vehicle().mode.value == {"land": "land", "hold": "hold", "fall": "idle"}[on_loss]

        restarted = served.peer()
        restarted.step([1000] * 4)
        if on_loss != "fall" or w.vehicle().state.position[2] > 0.05:
            assert link.holding and not link.in_control
        for _ in range(20):
            restarted.step([1100] * 4)  # armed at MOT_SPIN_ARM: refused in the air
        events = link.take_events()
        if on_loss != "fall":
            assert [e.type for e in events].count("ardupilot_arm_refused") == 1
            assert w.vehicle().mode.value != "external" and w.vehicle().state.position[2] > 1.0
        if on_loss == "hold":
            assert abs(w.vehicle().state.position[2] - 3.0) < 0.1
            with served.lock:
                w.vehicle().land()  # what an API user does to hand the vehicle to the new ArduPilot
        for _ in range(30 * HZ):  # disarmed while it comes down
            restarted.step([1000] * 4)
            if w.vehicle().mode.value == "idle" and w.vehicle().state.position[2] < 0.05:
                break
        for _ in range(5):
            restarted.step([1000] * 4)
        assert link.in_control and not link.holding
        for _ in range(40):  # armed on the ground: its outputs spin the rotors now
            restarted.step([1300] * 4)
        assert w.vehicle().mode.value == "external" and np.all(w.vehicle().state.rotor_speeds > 0.0)
        impacts = [e for e in served.sim_events if e.type == "impact"]
        assert (len(impacts) >= 1) == (on_loss == "fall")
        restarted.close()
    finally:
        served.close()
        w.close()


# --------------------------------------------------------------------------- the flight lock
def test_the_flight_lock_refuses_internal_ops_while_ardupilot_flies(served, world):
    commands = CommandPath(world, served.lock)
    lock = PX4FlightLock(commands, ArduPilotFleet([served.link]))
    assert commands.execute(make_request("takeoff", {}))["ok"]
    with served.lock:
        world.reset()
    peer = served.peer()
    try:
        peer.step([1000] * 4)
        lock.update()
        refused = commands.execute(make_request("takeoff", {}))["error"]
        assert (
            refused["code"] == "flight_locked"
            and "ArduPilot SITL is in control of uav0" in refused["message"]
        )
        assert commands.execute(make_request("reset", {}))["error"]["code"] == "flight_locked"
        assert commands.execute(make_request("state", {}))["ok"]
    finally:
        peer.close()


def test_config_hands_vehicles_to_ardupilot_beside_px4_but_not_the_first_vehicle_to_both():
    c = load_config(overrides=["ardupilot.enabled=true"])
    assert c.ardupilot_instances() == {"uav0": 0} and c.px4_instances() == {}
    c = load_config(overrides=["ardupilot.instance=2"])
    c.vehicles = [VehicleSpec(name="a"), VehicleSpec(name="b", controlled_by="ardupilot")]
    assert c.ardupilot_instances() == {"b": 3}
    c.vehicles.append(VehicleSpec(name="c", controlled_by="px4"))
    assert c.ardupilot_instances() == {"b": 3} and c.px4_instances() == {"c": 2}
    with pytest.raises(ValueError, match="would hand the first vehicle"):
        load_config(overrides=["ardupilot.enabled=true", "px4.enabled=true"])
    c.vehicles[0] = VehicleSpec(name="a", controlled_by="ardupilot")
    c.px4.enabled, c.vehicles[2] = True, VehicleSpec(name="c")  # --px4 on a list whose first is ArduPilot's
    with pytest.raises(ValueError, match=r"first vehicle \(flown by ardupilot\) to px4"):
        c.check_autopilots()
    with pytest.raises(ValueError, match="ardupilot.on_loss must be one of land, hold, fall"):
        ArduPilotConfig(on_loss="crash")
    with pytest.raises(ValueError, match="MOT_SPIN_MIN"):
        ArduPilotConfig(spin_min=0.9, spin_max=0.5)


# --------------------------------------------------------------------------- plan --ardupilot: GUIDED
def test_guided_link_flies_planner_setpoints_in_guided_through_the_ekf_origin():
    """``plan --ardupilot``'s autopilot against a scripted ArduCopter MAVLink: GUIDED, arm, take off, then
    the planner's ENU samples as NED targets from the EKF origin (GPS_GLOBAL_ORIGIN, 10 m north of the
    site and 1 m up); stale samples hold the last position; on close, LAND."""
    site = SiteConfig()
    lat0, lon0, alt0 = site.geodetic
    # 10 m north and 1 m up, in GPS_GLOBAL_ORIGIN's 1e-7 degree steps
    origin_geo = (round((lat0 + 10.0 / 111_195.0) * 1e7) * 1e-7, lon0, alt0 + 1.0)
    origin = F.geodetic_to_enu(*origin_geo, *site.geodetic)
    peer = ScriptedArduCopterMavlink(origin_geo)
    link = GuidedLink(GuidedConfig(base_port=peer.port, takeoff_alt_m=2.0, on_stop="land", stale_s=0.3))
    try:
        assert link.estimate() is None
        link.engage()
        wait_until(link.engaged.is_set, 15.0)
        assert link.failed is None and link.mode == "GUIDED" and peer.armed
        m = peer.m
        flow = [c for c in peer.commands if c in (m.MAV_CMD_DO_SET_MODE, 400, m.MAV_CMD_NAV_TAKEOFF)]
        assert flow == [m.MAV_CMD_DO_SET_MODE, m.MAV_CMD_COMPONENT_ARM_DISARM, m.MAV_CMD_NAV_TAKEOFF]
        est = link.estimate()
        assert est is not None
        np.testing.assert_allclose(origin, [0.0, 10.0, 1.0], atol=0.01)
        np.testing.assert_allclose(est.position, origin + [0.0, 0.0, 2.0], atol=0.35)
        goal = origin + np.array([3.0, 2.0, 4.0])
        end = time.monotonic() + 3.0
        while time.monotonic() < end:
            link.setpoint(0.0, goal, np.array([0.5, 0.0, 0.0]), np.zeros(3), 0.0, 0.0)
            time.sleep(0.02)
        last = peer.targets[-1]
        assert (last.x, last.y, last.z) == pytest.approx((2.0, 3.0, -4.0), abs=1e-4)  # north, east, down
        assert (last.vx, last.vy, last.vz) == pytest.approx((0.0, 0.5, 0.0))
        assert last.yaw == pytest.approx(math.pi / 2) and last.coordinate_frame == m.MAV_FRAME_LOCAL_NED
        est = link.estimate()
        assert est is not None and np.linalg.norm(est.position - goal) < 0.05
        time.sleep(0.8)  # no sample for stale_s: position-only holds at the last one
        held = peer.targets[-1]
        assert held.type_mask & 0b111111000 == 0b111111000 and (held.x, held.y) == pytest.approx((2.0, 3.0))
        assert len(peer.targets) > 50 and peer.missed == 0  # every message the next sequence number
    finally:
        link.close()
        assert peer.mode == ScriptedArduCopterMavlink.LAND
        peer.close()


def test_plan_takes_the_ardupilot_instance_from_the_config(tmp_path):
    """`droneulator plan --vehicle NAME --ardupilot`: vehicle k is ArduPilot instance ardupilot.instance + k,
    reached on MAVLink TCP 5760 + 10 (instance); a vehicle ArduPilot does not fly is refused."""
    from droneulator.cli import build_parser
    from droneulator.cli.plan import _guided_link, resolve_vehicle
    from droneulator.config import to_dict
    from droneulator.runtime.preflight import StartupError

    cfg = load_config(scene="planning")
    cfg.ardupilot.instance = 1
    cfg.vehicles = [VehicleSpec("uav0"), VehicleSpec("uav1", controlled_by="ardupilot")]
    path = tmp_path / "run.json"
    path.write_text(json.dumps(to_dict(cfg)))
    parse = build_parser().parse_args
    args = parse(["plan", "--config", str(path), "--vehicle", "uav1", "--ardupilot"])
    vehicle, run_cfg = resolve_vehicle(args)
    assert vehicle.ardupilot() == 2
    with pytest.raises(StartupError, match=r"no ArduCopter MAVLink on tcp://127.0.0.1:5780"):
        _guided_link(args, vehicle, run_cfg)
    args = parse(["plan", "--config", str(path), "--vehicle", "uav0", "--ardupilot"])
    with pytest.raises(StartupError, match="ArduPilot does not fly vehicle 'uav0'"):
        _guided_link(args, resolve_vehicle(args)[0], run_cfg)
