"""Commands below the SE(3) controller (docs/control.md): rotor speeds, collective thrust and body rates,
collective thrust and attitude, in the core against RotorPy itself, with their limits and the timeout of a
stream, then as WebSocket ops through a real server, refused under a real PX4 link's flight lock."""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from rotorpy.vehicles.multirotor import Multirotor
from test_api import Rig
from test_px4 import Peer, Served, make_sim, wait_until

from droneulator.api import ApiError, ApiServer, DroneulatorClient
from droneulator.commands import CommandPath
from droneulator.commands.errors import CommandError
from droneulator.config import VehicleSpec, load_config
from droneulator.controllers.flight import TRACK_TIMEOUT, Mode
from droneulator.controllers.inner import RATE_INTEGRAL_ERROR, SP_INTEGRAL, attitude_into, rates_into
from droneulator.controllers.se3 import FastSE3Control
from droneulator.frames import quat_from_euler
from droneulator.px4.flight_lock import PX4FlightLock
from droneulator.px4.link import PX4Fleet
from droneulator.state import STATE
from droneulator.vehicles.dynamics import pack_state, unpack_state
from droneulator.vehicles.params import get_params
from droneulator.world import World

rng = np.random.default_rng(11)


def hovering(overrides: tuple[str, ...] = (), z: float = 5.0) -> World:
    """A one-vehicle world (no renderer), its vehicle hovering at ``z`` over the default scene's spawn."""
    world = World(load_config(overrides=list(overrides)), scene="default", render=False)
    world.reset(position=[0.0, 0.0, z], yaw=0.3)
    return world


def weight(world: World) -> float:
    return float(world.vehicle().quad_params["mass"]) * 9.81


def angle_between(a: np.ndarray, b: np.ndarray) -> float:
    """Rotation angle (deg) between two attitudes."""
    return math.degrees(2.0 * math.acos(min(1.0, abs(float(np.dot(a, b))))))


# --------------------------------------------------------------------------- the core against RotorPy
def test_rotor_speeds_flown_are_rotorpys_multirotor_with_cmd_motor_speeds():
    """Ten periods of random rotor speeds through World.step fly RotorPy's own Multirotor (its equations
    integrated by SciPy's DOP853 at rtol = atol = 1e-13) to 1e-9 in every state field. The world's RK4 steps
    10 us here (vehicle.substeps = 1000): at the default 1 ms its error against the 5 ms motor lag is
    about 1e-3 rad/s in the rotor speeds, an integrator difference, not a model one."""
    with hovering(("vehicle.substeps=1000",)) as world:
        uav = world.vehicle()
        st = unpack_state(uav.s.copy())
        ref = Multirotor(uav.quad_params, initial_state=st, control_abstraction="cmd_motor_speeds",
                         aero=True, enable_ground=False,
                         integrator_kwargs={"method": "DOP853", "rtol": 1e-13, "atol": 1e-13})  # fmt: skip
        for _ in range(10):
            cmd = uav.hover_speed + rng.uniform(-150.0, 150.0, 4)
            uav.rotors(cmd)
            world.step()
            assert uav.mode == Mode.ROTORS
            np.testing.assert_array_equal(world._cmds[0, 0], cmd)  # applied as given
            st = ref.step(st, {"cmd_motor_speeds": cmd}, 0.01)
            np.testing.assert_allclose(uav.s, pack_state(st), rtol=0, atol=1e-9)
        assert abs(uav.s[STATE.rotor_speeds] - cmd).max() < 30.0  # the motors followed the last command


@pytest.mark.parametrize("name", ["hummingbird", "crazyflie", "crazyflie_brushless"])
def test_the_inner_loops_are_rotorpys_cmd_ctbr_and_cmd_ctatt(name):
    """The rate loop's first command is RotorPy's ``cmd_ctbr`` plus the gyroscopic moment (equal to it at
    rest) through RotorPy's allocation; the attitude loop is RotorPy's ``cmd_ctatt`` with the same gains."""
    qp = get_params(name)
    ctrl = FastSE3Control(qp)  # no thrust bounds: no yaw desaturation, RotorPy's plain allocation
    k_w = float(ctrl.k_w[0])
    ctbr = Multirotor({**qp, "k_w": k_w}, control_abstraction="cmd_ctbr")
    ctbm = Multirotor(qp, control_abstraction="cmd_ctbm")
    ctatt = Multirotor({**qp, "kp_att": ctrl.kp_att, "kd_att": ctrl.kd_att}, control_abstraction="cmd_ctatt")
    J = ctrl.inertia
    out, R = np.empty(4), np.empty((3, 3))
    for _ in range(20):
        q = rng.normal(size=4)
        st = {"x": np.zeros(3), "v": np.zeros(3), "q": q / np.linalg.norm(q), "w": rng.normal(size=3),
              "wind": np.zeros(3), "rotor_speeds": np.zeros(4)}  # fmt: skip
        thrust = float(qp["mass"]) * 9.81 * rng.uniform(0.5, 1.5)
        w_cmd = rng.normal(size=3)
        sp = np.zeros(SP_INTEGRAL + 3)
        sp[0], sp[1:4] = thrust, w_cmd
        rates_into(pack_state(st), sp, ctrl.gains(), out, 0.01)
        moment = J @ (k_w * (w_cmd - st["w"])) + np.cross(st["w"], J @ st["w"])
        want = ctbm.get_cmd_motor_speeds(st, {"cmd_thrust": thrust, "cmd_moment": moment})
        np.testing.assert_allclose(out, want, rtol=1e-10, atol=1e-8)
        integrand = np.clip(w_cmd - st["w"], -RATE_INTEGRAL_ERROR, RATE_INTEGRAL_ERROR)
        np.testing.assert_allclose(sp[SP_INTEGRAL:], integrand * 0.01, rtol=1e-12)  # the integral ran
        at_rest = {**st, "w": np.zeros(3)}
        sp[SP_INTEGRAL:] = 0.0
        rates_into(pack_state(at_rest), sp, ctrl.gains(), out, 0.01)
        want = ctbr.get_cmd_motor_speeds(at_rest, {"cmd_thrust": thrust, "cmd_w": w_cmd})
        np.testing.assert_allclose(out, want, rtol=1e-10, atol=1e-8)

        q_cmd = rng.normal(size=4)
        q_cmd /= np.linalg.norm(q_cmd)
        attitude_into(pack_state(st), np.array([thrust, *q_cmd]), ctrl.gains(), out, R)
        want = ctatt.get_cmd_motor_speeds(st, {"cmd_thrust": thrust, "cmd_q": q_cmd})
        np.testing.assert_allclose(out, want, rtol=1e-10, atol=1e-8)


# --------------------------------------------------------------------------- flying the levels
def test_a_constant_body_rate_command_gives_that_rate():
    with hovering() as world:
        uav = world.vehicle()
        thrust = weight(world)
        spun = []
        for _ in range(100):  # a pirouette at 2 rad/s
            uav.rates(thrust, [0.0, 0.0, 2.0])
            world.step()
            spun.append(uav.state.angular_velocity.copy())
        spun_ = np.array(spun)
        assert spun_[:, 2].max() < 2.2  # under 10 % overshoot
        assert np.abs(spun_[60:, 2] - 2.0).max() < 0.02 and np.abs(spun_[:, :2]).max() < 0.02
        assert abs(uav.state.position[2] - 5.0) < 0.1  # level: the thrust still carries the weight
        world.reset(position=[0.0, 0.0, 5.0], yaw=0.3)
        rolled = []
        for _ in range(40):  # a roll at 3 rad/s, for a little over a turn
            uav.rates(2.0 * thrust, [3.0, 0.0, 0.0])
            world.step()
            rolled.append(uav.state.angular_velocity.copy())
        late = np.array(rolled[16:])
        assert np.abs(late[:, 0] - 3.0).max() < 0.1 and np.abs(late[:, 1:]).max() < 0.1
        assert uav.mode == Mode.RATES


def test_an_attitude_command_reaches_the_attitude_by_angles_or_quaternion():
    roll, pitch, yaw = 0.3, -0.2, 1.0
    want = quat_from_euler(roll, pitch, yaw)
    for how in ("angles", "quaternion"):
        with hovering() as world:
            uav = world.vehicle()
            thrust = weight(world) / (math.cos(roll) * math.cos(pitch))
            errors = []
            for _ in range(100):
                if how == "angles":
                    uav.attitude(thrust, roll=roll, pitch=pitch, yaw=yaw)
                else:
                    uav.attitude(thrust, list(-want))  # -q is the same attitude
                world.step()
                errors.append(angle_between(uav.state.quaternion, want))
            assert errors[0] > 10.0 and max(errors[70:]) < 0.2, errors[::10]
            assert abs(uav.state.velocity[2]) < 0.2  # the tilted thrust still carries the weight
            assert uav.mode == Mode.ATTITUDE


def test_normalised_thrusts_and_what_is_refused_or_clipped():
    with hovering() as world:
        uav = world.vehicle()
        lo, hi = (float(uav.quad_params[k]) for k in ("rotor_speed_min", "rotor_speed_max"))
        lim = uav.control_limits()
        assert lim["rotor_speed"] == [lo, hi] and lim["max_thrust"] == pytest.approx(uav.max_thrust)
        assert lim["thrust_to_weight"] == pytest.approx(uav.max_thrust / weight(world))
        refused = [
            (lambda: uav.rotors([hi + 1.0, 0.0, 0.0, 0.0]), "out_of_range"),
            (lambda: uav.rotors([-1.0, 0.0, 0.0, 0.0]), "out_of_range"),
            (lambda: uav.rotors([0.5, 0.5, 0.5, 1.2], normalized=True), "out_of_range"),
            (lambda: uav.rotors([1.0, 1.0, 1.0]), "invalid_argument"),
            (lambda: uav.rotors([1.0, math.nan, 1.0, 1.0]), "invalid_argument"),
            (lambda: uav.rates(uav.max_thrust * 1.01, [0.0, 0.0, 0.0]), "out_of_range"),
            (lambda: uav.rates(-0.1, [0.0, 0.0, 0.0]), "out_of_range"),
            (lambda: uav.rates(1.5, [0.0, 0.0, 0.0], normalized=True), "out_of_range"),
            (lambda: uav.rates(5.0, [0.0, math.radians(721.0), 0.0]), "out_of_range"),
            (lambda: uav.rates(5.0, [0.0, 0.0, math.radians(541.0)]), "out_of_range"),
            (lambda: uav.rates(5.0, [0.0, math.inf, 0.0]), "invalid_argument"),
            (lambda: uav.attitude(5.0, roll=math.radians(61.0)), "out_of_range"),
            (lambda: uav.attitude(5.0, [0.0, 0.0, 0.0, 0.5]), "invalid_argument"),
            (lambda: uav.attitude(5.0, [0.0, 0.0, 0.0, 1.0], roll=0.1), "invalid_argument"),
            (lambda: uav.attitude(math.nan, roll=0.1), "invalid_argument"),
        ]
        for command, code in refused:
            with pytest.raises(CommandError) as e:
                command()
            assert e.value.code == code, e.value.message
        assert uav.mode == Mode.HOLD  # a refused command changes nothing

        uav.rotors([0.0, 0.25, 1.0, 1.0], normalized=True)  # thrust shares: speeds hi * sqrt(u)
        np.testing.assert_allclose(uav.flight._rotors, [lo, hi / 2, hi, hi])
        uav.rates(0.5, [0.0, 0.0, 0.0], normalized=True)
        assert uav.flight._inner[0] == pytest.approx(uav.max_thrust / 2)

        # a hard roll at no thrust asks for negative rotor speeds: the rotors stop at their range
        commanded, flown = [], []
        for _ in range(20):
            uav.rates(0.0, [10.0, 0.0, 0.0])
            world.step()
            commanded.append(world._cmds[0, 0].copy())
            flown.append(uav.s[STATE.rotor_speeds].copy())
        assert np.min(commanded) < lo and np.max(commanded) > 0.0
        assert np.min(flown) >= lo and np.max(flown) <= hi


def test_a_stream_that_stops_holds_the_vehicle_and_on_the_ground_stops_the_motors():
    with hovering() as world:
        uav = world.vehicle()
        for _ in range(30):  # pitching forward and speeding up
            uav.attitude(weight(world) / math.cos(0.3), pitch=0.3)
            world.step()
        events = []
        while not any(e.type == "attitude_timeout" for e in events):
            events += world.step().events
            assert world.t < 0.3 + TRACK_TIMEOUT + 0.02
        (timeout,) = [e for e in events if e.type == "attitude_timeout"]
        assert timeout.data["age"] > TRACK_TIMEOUT and uav.mode == Mode.HOLD
        assert np.linalg.norm(uav.state.velocity) > 1.0  # it was still moving when the stream stopped
        world.run(5.0)
        assert np.linalg.norm(uav.state.position - timeout.data["position"]) < 0.05
        assert np.linalg.norm(uav.state.velocity) < 0.05 and uav.mode == Mode.HOLD

        world.reset()  # on the ground: rotors at idle, then nothing more
        for _ in range(5):
            uav.rotors([0.02] * 4, normalized=True)
            world.step()
        assert uav.mode == Mode.ROTORS
        events = world.run(1.0).events
        assert [e.type for e in events] == ["rotors_timeout"] and uav.mode == Mode.IDLE
        assert np.all(world._cmds[0, 0] == 0.0)


def test_many_vehicles_each_fly_their_own_level():
    cfg = load_config()
    cfg.vehicles = [VehicleSpec(name="uav0", spawn=(0.0, 0.0, 3.0)),
                    VehicleSpec(name="uav1", spawn=(3.0, 0.0, 3.0), yaw=0.0)]  # fmt: skip
    with World(cfg, scene="default", render=False) as world:
        world.reset(position=[0.0, 0.0, 3.0], yaw=0.0)
        a, b = world.vehicles["uav0"], world.vehicles["uav1"]
        for _ in range(50):
            a.rates(weight(world), [0.0, 0.0, 1.0])
            b.attitude(weight(world) / math.cos(0.2), roll=0.2, yaw=0.0)
            world.step()
        assert abs(a.state.angular_velocity[2] - 1.0) < 0.02
        assert angle_between(b.state.quaternion, quat_from_euler(0.2, 0.0, 0.0)) < 0.5
        assert list(world.mode[0]) == [3, 4]  # the compiled step's RATES and ATTITUDE


# --------------------------------------------------------------------------- the WebSocket ops
@pytest.fixture(scope="module")
def rig() -> Iterator[Rig]:
    with Rig() as r:
        yield r


def test_the_ops_over_a_real_server(rig):
    with DroneulatorClient(rig.server.url, timeout=5.0) as c:
        info = c.scene_info()["vehicles"][0]["limits"]
        assert info["rotor_speed"] == [0.0, 1500.0] and info["stream_timeout"] == TRACK_TIMEOUT
        c.reset(position=[0.0, 0.0, 3.0], yaw=0.0)
        c.subscribe(["events"])
        thrust = 0.5 * 9.81  # the Hummingbird's weight
        end = time.monotonic() + 1.0
        while time.monotonic() < end:  # about 5 s of sim time at the rig's pace
            assert c.rates(thrust, [0.0, 0.0, 1.5])["t"] >= 0
            time.sleep(0.02)
        st = c.state()
        assert st["mode"] == "rates" and abs(st["angular_velocity"][2] - 1.5) < 0.05
        assert c.wait_for_event("rates_timeout", timeout=10)["age"] > TRACK_TIMEOUT
        assert c.state()["mode"] == "hold"

        for _ in range(40):
            c.attitude(thrust / math.cos(0.25), roll=0.25, yaw=0.5)
            time.sleep(0.02)
        st = c.state()
        assert st["mode"] == "attitude"
        assert angle_between(np.array(st["quaternion"]), quat_from_euler(0.25, 0.0, 0.5)) < 1.0
        c.wait_for_event("attitude_timeout", timeout=10)

        hover = math.sqrt(thrust / (4 * 5.57e-06))
        c.rotors([hover] * 4)
        assert c.state()["mode"] == "rotors"
        c.wait_for_event("rotors_timeout", timeout=10)
        for op, args, code in [
            ("rotors", {"rotor_speeds": [1.0, 2.0, 3.0]}, "invalid_argument"),
            ("rotors", {"rotor_speeds": [2000.0, 0.0, 0.0, 0.0]}, "out_of_range"),
            ("rates", {"thrust": 60.0, "body_rates": [0.0, 0.0, 0.0]}, "out_of_range"),
            ("rates", {"thrust": 5.0}, "invalid_argument"),
            ("attitude", {"thrust": 5.0, "roll": 1.2}, "out_of_range"),
            ("attitude", {"thrust": 5.0, "quaternion": [0, 0, 0, 1], "yaw": 0.0}, "invalid_argument"),
        ]:
            with pytest.raises(ApiError) as e:
                c.request(op, **args)
            assert e.value.code == code, (op, args, e.value.message)


def test_a_vehicle_px4_flies_refuses_the_ops_with_flight_locked():
    """A real PX4 link (a scripted PX4 connects and takes the rotors) locks the ops over the server."""
    sim = make_sim("hummingbird")
    served = Served(sim)
    commands = CommandPath(sim, served.lock)
    lock = PX4FlightLock(commands, PX4Fleet([served.link]))
    server = ApiServer(commands, port=0)
    server.start()
    peer: Any = None
    try:
        with DroneulatorClient(server.url, timeout=5.0) as c:
            peer = Peer(served.link.port)
            peer.next()
            assert served.link.in_control
            with served.lock:
                lock.update()
            for op, args in [
                ("rotors", {"rotor_speeds": [100.0] * 4}),
                ("rates", {"thrust": 5.0, "body_rates": [0.0, 0.0, 0.0]}),
                ("attitude", {"thrust": 5.0, "roll": 0.1}),
            ]:
                with pytest.raises(ApiError) as e:
                    c.request(op, **args)
                assert e.value.code == "flight_locked" and "PX4" in e.value.message
            assert sim.vehicle().mode in (Mode.IDLE, Mode.EXTERNAL)  # PX4 owns the rotors, untouched
            peer.close()  # PX4 leaves with the vehicle on the ground: the API flies it again
            peer = None
            wait_until(lambda: not served.link.connected)
            with served.lock:
                lock.update()
            c.rotors([0.0] * 4)
            assert sim.vehicle().mode == Mode.ROTORS
    finally:
        if peer is not None:
            peer.close()
        server.stop()
        served.close()
        sim.close()



# --------------------------------------------------------------------------- many worlds, row by row
def test_batched_rows_fly_the_levels_exactly_as_a_vehicle_commanded_alone():
    """World.rotors_rows / rates_rows / attitude_rows (learning's batched worlds) run the same compiled
    inner loops as Vehicle.rotors / rates / attitude: three worlds, one level each, equal bit for bit
    to three one-world runs driven through World.step."""
    starts = np.array([[[0.0, 0.0, 4.0]], [[1.0, 2.0, 3.0]], [[-1.0, 1.0, 5.0]]])
    yaws = np.array([[0.2], [-0.4], [1.0]])
    many = World(load_config(), scene="default", render=False, worlds=3)
    many.place(None, starts, yaws)
    thrust = weight(many)
    q = quat_from_euler(0.2, -0.1, 0.5)
    hover = many.vehicle().hover_speed
    speeds = [hover + 20.0, hover - 20.0, hover + 20.0, hover - 20.0]  # a yawing torque
    many.rates_rows([0], [0], [thrust], [[0.5, 0.0, 1.0]])
    many.attitude_rows([1], [0], [thrust * 1.05], [q])
    many.rotors_rows([2], [0], [speeds])
    alone = []
    for w in range(3):
        one = World(load_config(), scene="default", render=False, external_cameras=True)
        one.reset(position=starts[w, 0], yaw=float(yaws[w, 0]))
        alone.append(one)
    commands = [lambda u: u.rates(thrust, [0.5, 0.0, 1.0]), lambda u: u.attitude(thrust * 1.05, list(q)),
                lambda u: u.rotors(speeds)]  # fmt: skip
    for _ in range(15):
        many.step_frame()
        for w, one in enumerate(alone):
            while one.t_ns < many.clocks[w]:
                commands[w](one.vehicle())
                one.step()
            np.testing.assert_array_equal(many.states[w, 0], one.states[0, 0])
    assert many.mode[:, 0].tolist() == [3, 4, 2]
    assert abs(many.states[0, 0, 12] - 1.0) < 0.1 and many.states[2, 0, 12] != 0.0
    assert angle_between(many.states[1, 0, STATE.q], q) < 10.0  # from 53 degrees, turning 0.9 rad of yaw
    with pytest.raises(ValueError, match="rotor speeds must lie"):
        many.rotors_rows([0], [0], [[2000.0, 0.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match="thrust must lie"):
        many.rates_rows([0], [0], [1000.0], [[0.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match="tilted at most"):
        many.attitude_rows([0], [0], [thrust], [quat_from_euler(1.2, 0.0, 0.0)])
    assert many.mode[:, 0].tolist() == [3, 4, 2]  # refused: nothing changed
    for one in (many, *alone):
        one.close()
