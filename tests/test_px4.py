"""PX4 SITL link over real TCP, with a pymavlink peer playing PX4's ``simulator_mavlink`` side."""

from __future__ import annotations

import contextlib
import errno
import logging
import math
import socket
import threading
import time
from collections import deque
from typing import Any

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from droneulator import frames as F
from droneulator.config import PX4Config, load_config
from droneulator.px4 import MotorMap, PX4Link, px4_rotor_order
from droneulator.px4.handover import Handover, loss_action
from droneulator.px4.hil import SENSOR_ACCEL, SENSOR_BARO, SENSOR_GYRO, SENSOR_MAG
from droneulator.px4.link import BOOT_GRACE_S
from droneulator.px4.transport import CANDIDATE_TIMEOUT_S, LINK_SILENCE_S
from droneulator.sensors import SensorSuite, Truth
from droneulator.vehicles.params import get_params
from droneulator.world import World

ALL_FIELDS = SENSOR_ACCEL | SENSOR_GYRO | SENSOR_MAG | SENSOR_BARO
STEP_US = 4000  # 250 Hz lockstep
BOOT_GRACE = BOOT_GRACE_S  # the link's (answered_at_once patches it)


def isa_hpa(alt_msl: float) -> float:
    """ISA troposphere, written independently of the implementation under test."""
    return 1013.25 * (1.0 - 0.0065 * alt_msl / 288.15) ** 5.25588


def make_sim(
    params: str, px4: PX4Config | None = None, seed: int = 0, sensors: list[str] | None = None
) -> World:
    """A 250 Hz one-vehicle world of airframe ``params``, its sensors reading ``px4`` (noise, biases)."""
    cfg = load_config(overrides=["vehicle.control_hz=250", f"vehicle.params={params}"], seed=seed)
    if px4 is not None:
        cfg.px4 = px4
    if sensors is not None:
        cfg.vehicle.sensors = sensors
    return World(cfg, scene="default", render=False)


def px4_cfg(**kw: Any) -> PX4Config:
    return PX4Config(**{"base_port": 0, "speed_factor": 0.0, **kw})


def wait_until(pred: Any, timeout: float = 5.0) -> None:
    end = time.monotonic() + timeout
    while not pred():
        assert time.monotonic() < end, "timed out"
        time.sleep(0.005)


class Served:
    """A PX4Link served from a background thread, as the dynamics server does."""

    def __init__(self, sim: World, cfg: PX4Config | None = None, run_alone: bool = False) -> None:
        """``run_alone``: step the simulation while no PX4 is connected and the vehicle is not at rest
        (as the dynamics server does); otherwise time stands still without PX4."""
        self.sim = sim
        self.run_alone = run_alone
        self.lock = threading.Lock()
        self.link = PX4Link(sim, cfg or px4_cfg())
        self.link.start()
        self._stop = threading.Event()
        #: the simulator's events (impact, landed, ...) from every step the link took
        self.sim_events: list[Any] = []
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            res = self.link.serve_once(0.02, self.lock)
            if res is not None:
                self.sim_events.extend(res.events)
            elif self.run_alone and not self.link.connected:
                with self.lock:  # no PX4: the simulator runs on its own, as the dynamics server does
                    if self.sim.vehicle().mode.value != "idle" or self.sim.vehicle().state.position[2] > 0.05:
                        self.sim_events.extend(self.sim.step().events)

    def reset(self, **kw: Any) -> None:
        wait_until(lambda: not self.link.connected)
        with self.lock:
            self.sim.reset(**kw)

    def close(self) -> None:
        self._stop.set()
        self.thread.join(5.0)
        self.link.close()


def px4_in_the_air(served: Served, position: Any) -> Peer:
    """A PX4 with the rotors at ``position`` in the air: it connects with the vehicle on the ground (a
    new PX4 gets the rotors only there), then the simulation is reset in-process, under the lock, into
    a hover at ``position``, as if PX4 had flown it there."""
    served.reset()
    peer = Peer(served.link.port)
    peer.next()
    assert served.link.in_control
    with served.lock:
        served.sim.reset(position=position, airborne=True)
    return peer


#: how long a stand-in waits for the simulator's answer before it calls the lockstep stalled: PX4 itself
#: waits for ever (its simulator_mavlink logs a poll timeout each second without data), and a minute tells
#: a lost answer from a machine too loaded to give one within 5 s (one suite run in nine, with a core busy)
STALL_S = 60.0


class Peer:
    """Plays PX4: connects as the TCP client, sends HIL_ACTUATOR_CONTROLS, reads the sensor stream."""

    def __init__(self, port: int, connect_timeout: float = 30.0, px4: bool = True) -> None:
        """``px4``: send the HEARTBEAT PX4's simulator_mavlink sends the moment it connects (False: a
        client that has not said what it is)."""
        end = time.monotonic() + connect_timeout
        while True:  # as PX4's simulator_mavlink: retry until the simulator listens
            try:
                self.sock = socket.create_connection(("127.0.0.1", port), timeout=5.0)
                break
            except ConnectionRefusedError:
                if time.monotonic() > end:
                    raise
                time.sleep(0.01)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.mav = mavlink.MAVLink(None, 1, 1)
        self.rx = mavlink.MAVLink(None)
        self.inbox: deque[Any] = deque()
        self.t_us = 0
        if px4:
            kind, autopilot = mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4
            self.send(self.mav.heartbeat_encode(kind, autopilot, 0, 0, 0))

    def send(self, msg: Any) -> None:
        self.sock.sendall(msg.pack(self.mav))

    def hello(self) -> None:
        """What PX4 sends on connecting: a HEARTBEAT and a request for HIL_STATE_QUATERNION."""
        self.send(self.mav.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, 0, 0, 0))
        self.send(self.mav.command_long_encode(0, 0, 511, 0, 115, 5000, 0, 0, 0, 0, 0))

    def actuators(self, u: Any, armed: bool = True, lockstep: bool = True) -> None:
        controls = [float(x) for x in u] + [0.0] * (16 - len(u))
        self.send(
            self.mav.hil_actuator_controls_encode(self.t_us, controls, 1 | (128 * armed), int(lockstep))
        )

    def _fill(self, timeout: float) -> None:
        self.sock.settimeout(timeout)
        data = self.sock.recv(65536)
        if not data:
            raise ConnectionError("the simulator closed the connection")
        for m in self.rx.parse_buffer(data) or []:
            self.inbox.append(m)

    def next(self, kind: str = "HIL_SENSOR", timeout: float = STALL_S) -> list[Any]:
        """Messages up to and including the next ``kind`` (TimeoutError after ``timeout`` s without it)."""
        out: list[Any] = []
        end = time.monotonic() + timeout
        while True:
            while self.inbox:
                m = self.inbox.popleft()
                out.append(m)
                if m.get_type() == "HIL_SENSOR":
                    self.t_us = m.time_usec
                if m.get_type() == kind:
                    return out
            self._fill(max(0.01, end - time.monotonic()))

    def step(self, u: Any = (0.0,) * 4, **kw: Any) -> list[Any]:
        self.actuators(u, **kw)
        return self.next()

    def drain(self, duration: float) -> list[Any]:
        out: list[Any] = []
        end = time.monotonic() + duration
        while (left := end - time.monotonic()) > 0:
            try:
                self._fill(left)
            except TimeoutError:
                break
        while self.inbox:
            out.append(self.inbox.popleft())
        return out

    def close(self) -> None:
        self.sock.close()


def by_type(msgs: list[Any], kind: str) -> list[Any]:
    return [m for m in msgs if m.get_type() == kind]


def first_batch(served: Served, **reset: Any) -> dict[str, Any]:
    """Reset the vehicle, connect, and return the messages sent on connection by type."""
    served.reset(**reset)
    peer = Peer(served.link.port)
    batch = {m.get_type(): m for m in peer.next()}
    peer.close()
    return batch


@pytest.fixture(autouse=True)
def answered_at_once(monkeypatch: pytest.MonkeyPatch) -> None:
    """The peers here play a PX4 that answers its first sensor batch at once, but a peer on a busy core
    may take longer than BOOT_GRACE_S (50 ms of wall time), and the link then free-runs, as it must for
    a PX4 that boots: steps no test asked for (more batches than actuator messages, a hover with its
    motors off before the first output). The boot grace's own test keeps it (:data:`BOOT_GRACE`)."""
    monkeypatch.setattr("droneulator.px4.link.BOOT_GRACE_S", 30.0)


@pytest.fixture(scope="module")
def sim():
    s = make_sim("px4_quadx")
    yield s
    s.close()


@pytest.fixture()
def served(sim):
    sim.reset()
    s = Served(sim)
    yield s
    s.close()


# --------------------------------------------------------------------------- mixing and sensors
def test_motor_order_is_derived_from_geometry_and_spin():
    assert px4_rotor_order(get_params("px4_quadx")) == (0, 1, 2, 3)
    # hummingbird r1 front-left CW, r2 front-right CCW, r3 rear-right CW, r4 rear-left CCW
    assert px4_rotor_order(get_params("hummingbird")) == (1, 3, 0, 2)
    mirrored = get_params("hummingbird")
    mirrored["rotor_directions"] = -np.asarray(mirrored["rotor_directions"])
    with pytest.raises(ValueError, match="wrong way"):
        px4_rotor_order(mirrored)
    plus = get_params("hummingbird")
    plus["rotor_pos"] = {
        f"r{i}": 0.2 * np.array([math.cos(a), math.sin(a), 0.0]) for i, a in enumerate([0, 1.57, 3.14, 4.71])
    }
    with pytest.raises(ValueError, match="not an X frame"):
        px4_rotor_order(plus)


def test_output_to_speed_map_and_bad_values(caplog):
    hb = get_params("hummingbird")  # rotor_speed 0 .. 1500 rad/s
    mm = MotorMap(hb)  # PX4's default THR_MDL_FAC = 0: thrust linear in the output
    thrust = hb["k_eta"] * mm.output_to_speed([0.0, 0.25, 0.5, 1.0]) ** 2
    np.testing.assert_allclose(thrust / thrust[-1], [0.0, 0.25, 0.5, 1.0])
    gazebo = MotorMap(hb, thrust_model_factor=1.0)  # speed linear in the output (Gazebo-classic Iris)
    np.testing.assert_allclose(gazebo.output_to_speed([0.0, 0.5, 1.0]), [0.0, 750.0, 1500.0])
    for m in (mm, gazebo, MotorMap(hb, 0.3)):
        np.testing.assert_allclose(m.speed_to_output(m.output_to_speed([0.0, 0.37, 1.0])), [0.0, 0.37, 1.0])
    np.testing.assert_allclose(gazebo.rotor_speeds([0.1, 0.2, 0.3, 0.4]), [450.0, 150.0, 600.0, 300.0])
    with caplog.at_level(logging.ERROR, logger="droneulator.px4"):
        np.testing.assert_allclose(gazebo.rotor_speeds([1.5, -0.2, 0.3, 0.4]), [450.0, 1500.0, 600.0, 0.0])
        assert "outside [0, 1]" in caplog.text
        np.testing.assert_allclose(
            gazebo.rotor_speeds([float("nan"), 0.2, float("inf"), 0.4]), [450.0, 1500.0, 600.0, 300.0]
        )
        assert "not finite" in caplog.text  # motors 1 and 3 hold their last valid outputs, 1.0 and 0.3


def test_sensor_models_in_px4_frames():
    cfg = PX4Config(
        accel_noise=0, gyro_noise=0, mag_noise=0, baro_noise_hpa=0, gps_noise_m=0, gps_vel_noise=0
    )
    cfg.gps_vertical_noise_m = cfg.gps_jitter_m = cfg.gps_vel_vertical_noise = 0.0
    sensors = SensorSuite(cfg)
    z3 = np.zeros(3)
    north_level = F.quat_from_yaw(math.pi / 2)  # nose north: FRD body axes = NED axes
    t = Truth(4000, z3, np.array([0.0, 2.0, -0.5]), north_level, np.array([0.1, 0.2, 0.3]), z3, z3)
    accel, gyro = sensors.imu(t)
    np.testing.assert_allclose(accel, [0, 0, -9.81], atol=1e-12)
    np.testing.assert_allclose(gyro, [0.1, -0.2, -0.3], atol=1e-12)
    np.testing.assert_allclose(sensors.mag(t), sensors.models["mag"].field_ned, atol=1e-12)
    g = sensors.gps(t)  # flying north and climbing
    np.testing.assert_allclose(g.vel_ned, [2.0, 0.0, 0.5], atol=1e-12)
    assert g.course_deg == pytest.approx(0.0) and g.ground_speed == pytest.approx(2.0)
    rolled = F.quat_multiply(north_level, F.quat_from_euler(0.3, 0.0, 0.0))  # right wing down in FRD
    accel, _ = sensors.imu(Truth(0, z3, z3, rolled, z3, z3, z3))
    np.testing.assert_allclose(accel, [0.0, -9.81 * math.sin(0.3), -9.81 * math.cos(0.3)], atol=1e-9)


def _px4_fifo_counts(values: list[float], scale: float) -> np.ndarray:
    """What PX4's SimulatorMavlink stores: float32 value / float32 FIFO scale, cast to int16_t."""
    counts = np.trunc(np.float32(values) / np.float32(scale)).astype(np.int64)  # C's float -> int
    return ((counts + 32768) % 65536) - 32768  # two's complement, as the int16_t store wraps


def test_full_scale_imu_values_fit_px4s_int16_fifo_without_wrapping(sim):
    """+16 g and +2000 deg/s are 32768 FIFO counts, one past int16: the link sends at most 32767."""
    g_scale, w_scale = 9.80665 / 2048.0, math.radians(2000.0 / 32768.0)
    assert _px4_fifo_counts([16 * 9.80665], g_scale)[0] == -32768  # what the unclipped value became
    bias = {"accel_bias": (500.0, -500.0, 0.0), "gyro_bias": (100.0, -100.0, 0.0), "accel_noise": 0.0}
    biased = make_sim("px4_quadx", px4_cfg(**bias, gyro_noise=0.0))  # the vehicle's IMU reads the biases
    served = Served(biased)
    try:
        s = first_batch(served)["HIL_SENSOR"]
    finally:
        served.close()
        biased.close()
    accel = _px4_fifo_counts([s.xacc, s.yacc, s.zacc], g_scale)
    gyro = _px4_fifo_counts([s.xgyro, s.ygyro, s.zgyro], w_scale)
    assert accel[0] == 32767 and accel[1] == -32768  # saturated both ways, no sign flip
    assert gyro[0] == 32767 and gyro[1] == -32768
    assert accel[2] == round(-9.80665 / g_scale)  # unsaturated axes untouched (-1 g, at rest)
    assert gyro[2] == 0


# --------------------------------------------------------------------------- the link over TCP
def test_connection_sends_every_sensor_then_rests_on_ground_in_lockstep(served, sim):
    peer = Peer(served.link.port)
    peer.hello()
    first = peer.next()
    assert [m.get_type() for m in first] == ["HEARTBEAT", "HIL_GPS", "HIL_STATE_QUATERNION", "HIL_SENSOR"]
    sensor = first[-1]
    assert sensor.time_usec == STEP_US  # PX4 takes time 0 for "never": the clock starts at one step
    assert sensor.fields_updated == ALL_FIELDS and sensor.id == 0
    assert first[1].fix_type == 3 and first[1].satellites_visible == 10
    accels, gyros = [], []
    for k in range(60):
        batch = peer.step(armed=False)
        s = batch[-1]
        assert s.time_usec == STEP_US * (k + 2)
        accels.append([s.xacc, s.yacc, s.zacc])
        gyros.append([s.xgyro, s.ygyro, s.zgyro])
    np.testing.assert_allclose(np.mean(accels, axis=0), [0.0, 0.0, -9.81], atol=0.01)
    np.testing.assert_allclose(np.mean(gyros, axis=0), 0.0, atol=0.001)
    assert np.std(np.array(accels)[:, 2]) == pytest.approx(0.02, rel=0.3)  # PX4Config.accel_noise
    # the magnetometer reads the NED field rotated into the body (FRD)
    R = F.quat_to_matrix(F.quat_enu_flu_to_ned_frd(sim.vehicle().state.quaternion))
    mag = R.T @ served.link.sensors.models["mag"].field_ned
    np.testing.assert_allclose([sensor.xmag, sensor.ymag, sensor.zmag], mag, atol=0.01)
    uav = sim.vehicle()
    assert uav.mode.value == "idle" and uav.state.position[2] == 0.0  # disarmed: motors off
    peer.close()


def test_pressure_falls_with_altitude_per_isa_and_latitude_grows_northwards(served, sim):
    home = served.link.world.config.site
    spawn = sim.scene.spawn_position
    low = first_batch(served, position=spawn)
    high = first_batch(served, position=spawn + [0.0, 0.0, 12.0], airborne=True)
    north = first_batch(served, position=spawn + [0.0, 10.0, 0.0])
    for batch, z in ((low, 0.0), (high, 12.0)):
        s, alt = batch["HIL_SENSOR"], home.altitude_m + z
        assert s.abs_pressure == pytest.approx(isa_hpa(alt), abs=0.05)
        assert s.pressure_alt == pytest.approx(alt, abs=0.5)
        assert s.temperature == pytest.approx(15.0 - 0.0065 * alt, abs=0.01)
    assert isa_hpa(home.altitude_m) - isa_hpa(home.altitude_m + 12.0) == pytest.approx(1.43, abs=0.02)
    assert high["HIL_SENSOR"].abs_pressure < low["HIL_SENSOR"].abs_pressure - 1.2
    d_lat = (north["HIL_GPS"].lat - low["HIL_GPS"].lat) * 1e-7
    assert math.radians(d_lat) * F.EARTH_RADIUS_M == pytest.approx(10.0, abs=2.0)
    assert abs(north["HIL_GPS"].lon - low["HIL_GPS"].lon) * 1e-7 < 3e-5  # within ~2 m
    assert low["HIL_GPS"].alt == pytest.approx(home.altitude_m * 1000, abs=2500)
    assert low["HIL_STATE_QUATERNION"].lat == round(home.latitude_deg * 1e7)  # ground truth: no noise


def test_state_quaternion_is_frd_to_ned_with_matching_yaw(served, sim):
    for yaw_enu, yaw_ned in ((math.pi / 2, 0.0), (0.0, math.pi / 2), (1.0, math.pi / 2 - 1.0)):
        q = first_batch(served, yaw=yaw_enu)["HIL_STATE_QUATERNION"].attitude_quaternion
        roll, pitch, yaw = F.quat_to_euler(F.wxyz_to_xyzw(np.array(q)))
        assert abs(F.wrap_angle(yaw - yaw_ned)) < 1e-6 and abs(roll) < 1e-6 and abs(pitch) < 1e-6
    q = first_batch(served, yaw=math.pi / 2)["HIL_STATE_QUATERNION"].attitude_quaternion
    np.testing.assert_allclose(np.abs(q), [1.0, 0.0, 0.0, 0.0], atol=1e-6)  # nose north = identity


@pytest.mark.alone
def test_free_runs_until_the_first_actuator_message_then_waits_for_each(sim, monkeypatch):
    monkeypatch.setattr("droneulator.px4.link.BOOT_GRACE_S", BOOT_GRACE)
    sim.reset()
    served = Served(sim, px4_cfg(speed_factor=1.0))
    peer = Peer(served.link.port)
    peer.hello()
    t0 = time.monotonic()
    boot = by_type(peer.drain(0.6), "HIL_SENSOR")  # PX4 booting: no actuator messages yet
    while len(boot) < 3 and time.monotonic() < t0 + 30:  # a busy core may have stepped fewer by now
        boot += by_type(peer.drain(0.1), "HIL_SENSOR")
    wall = time.monotonic() - t0
    times = [m.time_usec for m in boot]
    assert np.all(np.diff(times) == STEP_US)
    # free-running: steps no PX4 answered (a link waiting for PX4 sends one batch), paced at real time
    # (speed_factor 1: never ahead of the wall clock; how far behind it falls is the machine's load)
    assert len(boot) >= 3 and (times[-1] - times[0]) / 1e6 < 1.2 * wall
    assert not served.link.lockstep
    peer.t_us = times[-1]
    t_send = sim.t_ns  # samples up to here were stepped before PX4 spoke (a backlog on a loaded machine)
    peer.actuators([0.0] * 4, armed=False)  # PX4 is up: lockstep starts
    wait_until(lambda: served.link.lockstep)
    # free steps taken while the message was on its way (a few; more on a loaded machine), then from the
    # moment the link read it, one step: the message's own (read until it is here; a busy core delays it)
    started = served.link.lockstep_started_ns
    assert started is not None and t_send <= started
    raced: list[Any] = []
    end = time.monotonic() + 10
    while not any(m.time_usec * 1000 > started for m in raced) and time.monotonic() < end:
        raced += [m for m in by_type(peer.drain(0.1), "HIL_SENSOR") if m.time_usec * 1000 > t_send]
    assert len(raced) >= 1 and len([m for m in raced if m.time_usec * 1000 > started]) == 1
    t_stop = sim.t_ns
    assert not by_type(peer.drain(0.4), "HIL_SENSOR") and sim.t_ns == t_stop  # no actuators: time stops
    s = peer.step(armed=False)[-1]  # one actuator message, one step
    assert s.time_usec * 1000 == sim.t_ns == t_stop + sim.control_period_ns
    peer.close()
    served.close()


def test_a_link_behind_the_wall_clock_still_reads_the_first_lockstep_answer(sim, monkeypatch):
    """A simulator that falls behind real time while PX4 boots (a loaded machine: the dynamics server's
    loop serves the link between waits for frames) has a free-running step due at every serve; the link
    must still read PX4's socket, or PX4's first lockstep answer is never seen and the clock runs on
    through it (a suite run with a core busy: 0.67 s of sim time in 0.5 s after the answer)."""
    monkeypatch.setattr("droneulator.px4.link.BOOT_GRACE_S", BOOT_GRACE)
    sim.reset()
    link = PX4Link(sim, px4_cfg(speed_factor=1.0))
    link.start()
    stop = threading.Event()

    def serve() -> None:  # a serve without waiting every 20 ms: five times slower than the 4 ms steps
        while not stop.is_set():
            link.serve_once(0.0)
            time.sleep(0.02)

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    peer = Peer(link.port)
    try:
        peer.hello()
        peer.next()  # the first batch; the link free-runs once the boot grace is over, behind real time
        wait_until(lambda: sim.t_ns >= 5 * sim.control_period_ns, 10)
        assert not link.lockstep
        peer.actuators([0.0] * 4, armed=False)
        wait_until(lambda: link.lockstep, 10)
        # the answer (to an older batch: PX4 catching up) steps once, then time waits for the next one
        started = link.lockstep_started_ns
        assert started is not None
        after: list[Any] = []
        end = time.monotonic() + 10
        while not after and time.monotonic() < end:
            after = [m for m in by_type(peer.drain(0.1), "HIL_SENSOR") if m.time_usec * 1000 > started]
        assert len(after) == 1
        t_held = sim.t_ns
        assert not by_type(peer.drain(0.3), "HIL_SENSOR") and sim.t_ns == t_held
    finally:
        stop.set()
        thread.join(5.0)
        peer.close()
        link.close()


def test_px4_without_lockstep_free_runs_on_its_latest_outputs(sim, caplog, monkeypatch):
    # free-running starts when the boot grace ends, outputs or not: a second for the peer's first output
    # (the hover is set up after the first batch, and a hover with no output yet falls)
    monkeypatch.setattr("droneulator.px4.link.BOOT_GRACE_S", 1.0)
    start = sim.scene.spawn_position + [0.0, 0.0, 3.0]
    sim.reset()
    # at a quarter of real time: the outputs of a PX4 sending at 50 Hz of wall time stay fresh (0.2 s of sim
    # time, ACTUATOR_TIMEOUT_NS) through 0.8 s of wall time, and a catch-up of the link's free-running
    # clock (MAX_LAG_S, 0.25 s of wall time) is 0.06 s of sim time: at real time either passes the
    # timeout when a busy core holds the peer or the link back, and the motors go off mid-hover
    served = Served(sim, px4_cfg(speed_factor=0.25))
    peer = px4_in_the_air(served, start)
    u = float(served.link.motor_map.speed_to_output(sim.vehicle().hover_speed))
    msgs: list[Any] = []
    sent, end = 0, time.monotonic() + 30
    while (sent < 20 or len(by_type(msgs, "HIL_SENSOR")) <= 20) and time.monotonic() < end:
        peer.actuators([u] * 4, lockstep=False)  # a PX4 built without lockstep, at 50 Hz of wall time
        sent += 1
        msgs += peer.drain(0.02)
    # free-running on the latest outputs: steps no lockstep message asked for
    assert len(by_type(msgs, "HIL_SENSOR")) > 20 and not served.link.lockstep
    assert sim.vehicle().mode.value == "external" and abs(sim.vehicle().state.position[2] - start[2]) < 0.01
    with caplog.at_level(logging.WARNING, logger="droneulator.px4"):
        # PX4 went quiet: after 0.2 s of sim time the motors stop (Gazebo's rule), and the vehicle falls
        def fallen() -> bool:
            uav = sim.vehicle()
            return uav.mode.value == "idle" and uav.state.position[2] < start[2] - 0.1

        end = time.monotonic() + 30
        while not fallen() and time.monotonic() < end:
            peer.drain(0.1)
        assert fallen()
        assert "motors off" in caplog.text
    peer.close()
    served.close()


def test_hover_outputs_hold_altitude(served, sim):
    start = sim.scene.spawn_position + [0.0, 0.0, 3.0]
    peer = px4_in_the_air(served, start)
    u = float(served.link.motor_map.speed_to_output(sim.vehicle().hover_speed))
    assert u == pytest.approx(0.49, abs=0.01)  # SIH quad-X: hover at ~half thrust, as PX4 assumes
    zs, accel = [], []
    for _ in range(500):  # 2 s
        s = peer.step([u] * 4)[-1]
        zs.append(sim.vehicle().state.position[2])
        accel.append([s.xacc, s.yacc, s.zacc])
    assert sim.vehicle().mode.value == "external" and served.link.armed
    assert max(abs(z - start[2]) for z in zs) < 0.02
    np.testing.assert_allclose(np.mean(accel, axis=0), [0.0, 0.0, -9.81], atol=0.02)  # thrust balances g
    peer.close()


def test_a_px4_vehicle_that_brushes_a_canopy_is_pushed_out_and_flies_on():
    """A vehicle PX4 flies defaults to the physical contact model (docs/contact.md): drifting into a crown at
    hover outputs, the leaves push it back out; the link steps it on, never held in ``collided``."""
    cfg = load_config(overrides=["vehicle.control_hz=250", "vehicle.params=px4_quadx", "px4.enabled=true"])
    world = World(cfg, scene="default", render=False)
    uav = world.vehicle()
    assert uav.contact_model == "physical"
    world.step()  # compiled before a peer waits on it
    trunk = np.asarray(world.scene.landmarks["trunks"][0], dtype=float)
    served = Served(world)
    try:
        peer = px4_in_the_air(served, trunk + [-3.5, 0.0, 4.4])
        u = float(served.link.motor_map.speed_to_output(uav.hover_speed))
        peer.step([u] * 4)
        with served.lock:
            uav.s[3:6] = [1.5, 0.0, 0.0]
        xs = [float(uav.state.position[0]) for _ in range(500) if peer.step([u] * 4)]  # 2 s
        hits = [e for e in served.sim_events if e.type == "collision"]
        assert [(e.data["contact"], e.data["model"]) for e in hits] == [("foliage", "physical")]
        assert uav.mode.value == "external" and served.link.in_control
        assert max(xs) - xs[0] > 0.3 and xs[-1] < max(xs) - 0.05  # in, then pushed back out
        assert abs(xs[-1] - xs[-2]) > 1e-4  # still moving: never frozen
        peer.close()
    finally:
        served.close()
        world.close()


# PX4 quad-X: body rate signs (FRD roll p, pitch q, yaw r) from extra thrust on one motor
QUAD_X_RESPONSE = {
    1: (-1, +1, +1),  # front-right, CCW: rolls left, pitches nose up, yaws right (reaction torque)
    2: (+1, -1, +1),  # rear-left, CCW
    3: (+1, +1, -1),  # front-left, CW
    4: (-1, -1, -1),  # rear-right, CW
}


@pytest.mark.parametrize("params", ["px4_quadx", "hummingbird"])
def test_one_motor_step_gives_the_quad_x_torque_signs(params, sim):
    s = sim if params == "px4_quadx" else make_sim(params)
    served = Served(s)
    try:
        u = float(served.link.motor_map.speed_to_output(s.vehicle().hover_speed))
        for motor, signs in QUAD_X_RESPONSE.items():
            peer = px4_in_the_air(served, s.scene.spawn_position + [0.0, 0.0, 3.0])
            for _ in range(5):
                peer.step([u] * 4)
            cmd = [u] * 4
            cmd[motor - 1] += 0.05
            for _ in range(20):
                batch = peer.step(cmd)
            truth = by_type(batch, "HIL_STATE_QUATERNION")[-1]
            rates = np.array([truth.rollspeed, truth.pitchspeed, truth.yawspeed])
            assert np.all(np.sign(rates) == signs), (motor, rates)
            assert np.all(np.abs(rates) > 1e-3)
            fastest = int(np.argmax(s.vehicle().state.rotor_speeds))
            assert fastest == served.link.motor_map.order[motor - 1]
            peer.close()
    finally:
        served.close()
        if s is not sim:
            s.close()


def test_messages_arrive_at_their_rates(served, sim):
    peer = Peer(served.link.port)
    msgs = peer.next()
    for _ in range(500):  # 2 s of sim time
        msgs += peer.step(armed=False)
    sensor = by_type(msgs, "HIL_SENSOR")
    assert len(sensor) == 501 and len(by_type(msgs, "HIL_STATE_QUATERNION")) == 501
    assert np.all(np.diff([m.time_usec for m in sensor]) == STEP_US)
    gps = [m.time_usec for m in by_type(msgs, "HIL_GPS")]
    assert len(gps) == 21 and np.all(np.diff(gps) == 100_000)  # gps_hz = 10 in sim time
    beats = by_type(msgs, "HEARTBEAT")
    assert len(beats) == 3 and all(b.autopilot == mavlink.MAV_AUTOPILOT_INVALID for b in beats)  # 1 Hz
    seqs = np.array([m.get_seq() for m in msgs])  # one sender: every message the next number, mod 256
    assert len(seqs) > 1000 and np.all(np.diff(seqs) % 256 == 1), seqs[:10]
    n_mag = sum(bool(m.fields_updated & SENSOR_MAG == SENSOR_MAG) for m in sensor)
    n_baro = sum(bool(m.fields_updated & SENSOR_BARO == SENSOR_BARO) for m in sensor)
    assert abs(n_mag - 200) <= 2 and abs(n_baro - 100) <= 2  # 100 Hz and 50 Hz
    assert all(m.fields_updated & (SENSOR_ACCEL | SENSOR_GYRO) == SENSOR_ACCEL | SENSOR_GYRO for m in sensor)
    peer.close()


def test_dropped_connection_resumes_where_it_stopped(served, sim):
    peer = Peer(served.link.port)
    peer.next()
    for _ in range(20):
        last = peer.step(armed=False)[-1]
    peer.close()
    wait_until(lambda: not served.link.connected)
    t_drop = sim.t_ns
    time.sleep(0.2)
    assert sim.t_ns == t_drop == last.time_usec * 1000  # no PX4, no time
    peer = Peer(served.link.port)
    again = peer.next()[-1]
    assert again.time_usec == last.time_usec and again.fields_updated == ALL_FIELDS
    for k in range(20):
        assert peer.step(armed=False)[-1].time_usec == last.time_usec + STEP_US * (k + 1)
    peer.close()


def test_a_second_client_is_refused_while_the_first_streams(served, sim, caplog):
    caplog.set_level(logging.INFO, logger="droneulator.px4")
    first = Peer(served.link.port)
    first.hello()
    t = first.next()[-1].time_usec
    intruder = Peer(served.link.port)  # connects while the first PX4 is stepping
    with contextlib.suppress(BrokenPipeError, ConnectionResetError):  # the refusal may already have come
        intruder.hello()
    for k in range(100):
        assert first.step(armed=False)[-1].time_usec == t + STEP_US * (k + 1)
    with pytest.raises(ConnectionError):  # closed by the simulator, without a byte
        intruder.next(timeout=2.0)
    assert "refused a PX4 connection" in caplog.text and served.link.connected
    t = first.step(armed=False)[-1].time_usec  # the first PX4 keeps the link and the clock
    assert t * 1000 == sim.t_ns
    intruder.close()
    first.close()


def test_a_paused_px4_keeps_its_link_against_a_stray_connection_and_flies_on(served, sim, caplog):
    """A debugger pause (SIGSTOP) makes PX4 silent; a client that never shows it is a PX4 gets no
    byte and cannot take the link, and PX4 resumes into it (its simulator_mavlink never reconnects)."""
    caplog.set_level(logging.INFO, logger="droneulator.px4")
    first = Peer(served.link.port)
    first.hello()
    first.next()
    t = first.step(armed=False)[-1].time_usec
    time.sleep(LINK_SILENCE_S + 0.5)  # paused: its last sensor data unanswered
    stray = Peer(served.link.port, px4=False)
    stray.send(stray.mav.heartbeat_encode(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0))
    with pytest.raises(TimeoutError):
        stray.next(timeout=1.0)  # nothing is streamed to it
    assert stray.inbox == deque() and served.link.connected
    for k in range(50):  # PX4 resumes: the same link, the clock goes on where it stopped
        assert first.step(armed=False)[-1].time_usec == t + STEP_US * (k + 1)
    with pytest.raises(ConnectionError):
        stray.next(timeout=2.0)  # closed once PX4 answered again
    assert "is alive and keeps the link" in caplog.text
    assert [e.type for e in served.link.take_events()] == ["px4_connected"]
    stray.close()
    first.close()


def test_a_silent_px4_is_replaced_by_the_next_one_that_shows_it_is_a_px4(served, sim, caplog):
    caplog.set_level(logging.INFO, logger="droneulator.px4")
    first = Peer(served.link.port)
    first.hello()
    first.next()
    t = first.step(armed=False)[-1].time_usec
    time.sleep(LINK_SILENCE_S + 0.3)  # the first PX4 died without closing its socket
    stray = Peer(served.link.port, px4=False)  # a port scanner: connects, says nothing
    with pytest.raises(ConnectionError):
        stray.next(timeout=CANDIDATE_TIMEOUT_S + 1.0)  # given nothing, then closed
    assert stray.inbox == deque() and "no PX4 HEARTBEAT within" in caplog.text
    newer = Peer(served.link.port, px4=False)
    with pytest.raises(TimeoutError):
        newer.next(timeout=0.5)  # sent nothing until it shows it is a PX4
    newer.hello()  # PX4's first message on connecting: HEARTBEAT from MAV_AUTOPILOT_PX4
    assert newer.next()[-1].time_usec == t
    assert newer.step(armed=False)[-1].time_usec == t + STEP_US
    with pytest.raises(ConnectionError):
        first.next(timeout=2.0)
    assert "silent for" in caplog.text
    kinds = [(e.type, e.data.get("holding")) for e in served.link.take_events()]
    assert kinds == [("px4_connected", False), ("px4_disconnected", None), ("px4_connected", False)]
    for p in (newer, stray, first):
        p.close()


def test_a_stray_client_on_an_empty_port_gets_nothing_and_owns_nothing(served, sim, caplog):
    """With no PX4 connected, a client that never shows it is a PX4 is not taken for one (a real PX4
    found it locked the API's flight commands for as long as it stayed open): it is sent nothing, the
    link stays unconnected, it is closed after CANDIDATE_TIMEOUT_S, and a PX4 arriving meanwhile gets
    the link at once; the stray is closed all the same."""
    caplog.set_level(logging.INFO, logger="droneulator.px4")
    served.reset()
    stray = Peer(served.link.port, px4=False)
    with pytest.raises(TimeoutError):
        stray.next(timeout=0.5)
    assert not served.link.connected and not served.link.in_control
    px4 = Peer(served.link.port)  # sends PX4's HEARTBEAT on connecting
    px4.next()
    assert served.link.connected and served.link.in_control
    with pytest.raises(ConnectionError):
        stray.next(timeout=CANDIDATE_TIMEOUT_S + 1.0)  # given nothing, then closed
    assert stray.inbox == deque()
    wait_until(lambda: "closed the waiting connection" in caplog.text)
    assert [e.type for e in served.link.take_events()] == ["px4_connected"]
    stray.close()
    px4.close()
    # the disconnection's event itself, not only the flag: under load it came after the flag (run 84) and
    # was then taken for one of the lone stray's below
    gone: list = []
    wait_until(lambda: gone.extend(served.link.take_events()) or "px4_disconnected" in [e.type for e in gone])
    assert not served.link.connected
    # alone, a stray is closed once CANDIDATE_TIMEOUT_S has passed without a PX4 HEARTBEAT
    served.reset()
    stray = Peer(served.link.port, px4=False)
    with pytest.raises(ConnectionError):
        stray.next(timeout=CANDIDATE_TIMEOUT_S + 1.0)
    assert stray.inbox == deque()
    wait_until(lambda: "no PX4 HEARTBEAT within" in caplog.text)
    assert not served.link.connected and served.link.take_events() == []
    stray.close()


def test_a_quiet_link_is_kept_while_the_simulator_is_the_one_that_waits(served, sim):
    """PX4 owes nothing while no sensor data was sent since its last message (the simulator paused,
    e.g. for a slow renderer): however long that lasts, a newcomer does not take the link."""
    first = Peer(served.link.port)
    first.next()
    with served.lock:  # the simulator stalls before sending the next data; PX4's reply is queued
        first.actuators([0.0] * 4, armed=False)
        time.sleep(LINK_SILENCE_S + 0.3)
        intruder = Peer(served.link.port)
        time.sleep(0.1)
    with pytest.raises(ConnectionError):
        intruder.next(timeout=2.0)
    assert first.next()[-1].time_usec * 1000 == sim.t_ns and served.link.connected
    intruder.close()
    first.close()


def _climb(peer: Peer, sim: World, link: PX4Link, altitude: float) -> None:
    """Fly as an armed PX4 would in a take-off: equal outputs from an altitude loop on the truth."""
    hover = link.motor_map.speed_to_output(sim.vehicle().hover_speed)
    for _ in range(5000):
        z, vz = sim.vehicle().state.position[2], sim.vehicle().state.velocity[2]
        u = float(np.clip(hover * (1.0 + 0.6 * (altitude - z) - 0.8 * vz), 0.1, 0.9))
        peer.step([u] * 4)
        if abs(z - altitude) < 0.05 and abs(vz) < 0.05:
            return
    raise AssertionError(f"no hover at {altitude} m: z = {sim.vehicle().state.position[2]:.2f} m")


@pytest.mark.parametrize("on_loss", ["land", "hold", "fall"])
def test_a_px4_lost_in_the_air_and_restarted_never_drops_the_vehicle_unless_told_to(sim, on_loss):
    """PX4 dies at 5 m (its socket closes, as on SIGKILL) and restarts as a real PX4 boots: believing
    it is landed, disarmed, then armed at idle. ``land`` lands clear of the scene and ``hold`` hovers,
    with no impact, and the new PX4's arm in the air is refused; ``fall`` drops like a stone. Once the
    vehicle is on the ground with PX4 disarmed, PX4 gets the rotors."""
    sim.reset()
    served = Served(sim, px4_cfg(on_loss=on_loss), run_alone=True)
    link = served.link
    try:
        first = Peer(link.port)
        first.hello()
        first.next()
        for _ in range(10):
            first.step([0.0] * 4)  # armed on the ground: PX4 has the rotors
        assert link.in_control and not link.holding
        _climb(first, sim, link, 5.0)
        assert sim.vehicle().mode.value == "external"
        link.take_events()
        served.sim_events.clear()
        first.close()  # PX4 killed in the hover
        wait_until(lambda: not link.connected)
        t_lost = sim.t
        # the link's thread changes the mode, then records the event: wait for the event itself
        taken: list = []
        wait_until(lambda: taken.extend(link.take_events()) or any(e.type == "px4_lost" for e in taken))
        assert sim.vehicle().mode.value != "external"
        lost = [e for e in taken if e.type == "px4_lost"]
        assert len(lost) == 1 and lost[0].data["action"] == on_loss

        restarted = Peer(link.port)  # the restarted PX4 connects
        restarted.hello()
        restarted.next()
        assert link.holding and not link.in_control
        idle = [0.05] * 4  # PX4 armed on what it believes is the ground: idle outputs
        for _ in range(250):
            restarted.step(armed=False)
        for _ in range(500):  # the user arms it: refused in the air
            restarted.step(idle)
            if sim.vehicle().mode.value == "idle" and sim.vehicle().state.position[2] < 0.05:
                break
        events = link.take_events()
        if on_loss != "fall":
            assert link.holding and sim.vehicle().state.position[2] > 1.0
            assert [e.type for e in events].count("px4_arm_refused") == 1
        if on_loss == "hold":
            assert sim.vehicle().mode.value == "hold" and abs(sim.vehicle().state.position[2] - 5.0) < 0.1
            with served.lock:
                sim.vehicle().land()  # what an API user does to hand the vehicle to the new PX4
        for _ in range(6000):  # disarmed while it comes down (PX4's land detector, or the user)
            restarted.step(armed=False)
            if sim.vehicle().mode.value == "idle" and sim.vehicle().state.position[2] < 0.05:
                break
        assert sim.vehicle().state.position[2] < 0.05
        for _ in range(5):
            restarted.step(armed=False)
        assert link.in_control and not link.holding
        if on_loss != "fall":  # a falling vehicle may be down before the new PX4 connects
            assert "px4_in_control" in [e.type for e in link.take_events()]
        for _ in range(50):  # armed on the ground: its idle outputs now spin the rotors
            restarted.step(idle)
        assert sim.vehicle().mode.value == "external" and np.all(sim.vehicle().state.rotor_speeds > 0.0)
        impacts = [e for e in served.sim_events if e.type == "impact"]
        if on_loss == "fall":
            h = 5.0 - 0.0
            assert len(impacts) >= 1
            first_hit = impacts[0]
            assert first_hit.data["speed"] == pytest.approx(math.sqrt(2 * 9.81 * h), rel=0.1)
            assert first_hit.t - t_lost == pytest.approx(math.sqrt(2 * h / 9.81), rel=0.1)
        else:
            assert impacts == [], impacts
        restarted.close()
    finally:
        served.close()


def test_a_bad_on_loss_is_refused_with_the_choices():
    with pytest.raises(ValueError, match="px4.on_loss must be one of land, hold, fall"):
        PX4Config(on_loss="crash")
    with pytest.raises(ValueError, match="on_loss"):
        load_config(overrides=["px4.on_loss=drop"])


def test_the_loss_rule_and_the_hand_over_decide_from_height_arming_and_landing_alone():
    """The policy as pure decisions: a loss on the ground rests whatever ``on_loss`` says; a held PX4
    armed in the air is refused once (said once, again only after it disarmed), and gets the rotors
    down, disarmed or arming there."""
    assert [loss_action(0.04, rule) for rule in ("land", "hold", "fall")] == ["rest"] * 3
    assert [loss_action(3.0, rule) for rule in ("land", "hold", "fall")] == ["land", "hold", "fall"]
    h = Handover()
    h.connect(on_the_ground=False)
    assert h.holding
    assert [h.command(armed=True, down=False) for _ in range(2)] == ["refuse", "wait"]
    assert h.command(armed=True, down=True) == "wait" and h.holding  # refused until it disarms
    assert h.command(armed=False, down=False) == "wait" and not h.arm_refused
    assert h.command(armed=True, down=False) == "refuse"
    assert h.command(armed=False, down=True) == "hand_over" and not h.holding
    h.connect(on_the_ground=False)
    assert h.command(armed=True, down=True) == "hand_over"  # armed on the ground, never refused
    h.connect(on_the_ground=True)
    assert not h.holding


def test_the_landing_spot_keeps_clear_of_the_scene():
    """Above a tree crown the simulator does not land straight down through it."""
    cfg = load_config(overrides=["vehicle.control_hz=250"])
    s = World(cfg, scene="tree_inspection", render=False)
    try:
        col = s.scene.collision
        grid = np.stack(np.meshgrid(np.arange(-8, 8, 0.5), np.arange(-8, 8, 0.5), [3.0]), -1).reshape(-1, 3)
        d = [col.distance(p) for p in grid]
        assert min(d) < 0  # the crown is there
        above = grid[int(np.argmin(d))] + [0.0, 0.0, 4.0]
        s.reset(position=above)
        xy = s.vehicle().landing_spot()
        column = np.array([[xy[0], xy[1], z] for z in np.linspace(0.75, above[2], 60)])
        assert min(col.distance(p) for p in column) >= 0.5 + cfg.vehicle.collision_radius
        assert np.linalg.norm(xy - above[:2]) > 0.5  # it moved off the crown
        s.vehicle().safe_land()
        events: list[Any] = []
        assert s.run_until(lambda sim: sim.vehicle().mode.value == "idle", 60.0, events)
        assert s.vehicle().state.position[2] < 0.05 and s.vehicle().collisions == 0
        assert np.linalg.norm(s.vehicle().state.position[:2] - xy) < 0.2
        assert [e.type for e in events if e.type in ("impact", "collision")] == []
    finally:
        s.close()


def test_on_the_ground_a_disarmed_px4_replacing_an_armed_one_stops_the_motors(served, sim):
    first = Peer(served.link.port)
    first.next()
    for _ in range(20):
        first.step([0.2] * 4)  # armed on the ground, motors turning below hover thrust
    spinning = sim.vehicle().state.rotor_speeds
    assert sim.vehicle().mode.value == "external" and np.all(spinning > 100.0)
    first.close()
    wait_until(lambda: not served.link.connected)
    restarted = Peer(served.link.port)
    restarted.next()
    assert served.link.in_control
    for _ in range(50):
        restarted.step(armed=False)
    uav = sim.vehicle()
    assert uav.mode.value == "idle" and uav.state.position[2] == pytest.approx(0.0, abs=0.01)
    assert np.all(sim.vehicle().state.rotor_speeds < 0.05 * spinning)  # spun down (motor lag)
    restarted.close()


def test_start_on_a_taken_port_fails_and_listens_nowhere(sim):
    with socket.socket() as taken:
        taken.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        link = PX4Link(sim, px4_cfg(host="127.0.0.1", base_port=taken.getsockname()[1]))
        with pytest.raises(OSError) as err:
            link.start()
        assert err.value.errno == errno.EADDRINUSE
        with pytest.raises(RuntimeError, match="not listening"):
            _ = link.port


def test_garbage_and_bad_actuator_values_are_rejected_and_the_link_keeps_working(served, sim, caplog):
    caplog.set_level(logging.ERROR, logger="droneulator.px4")
    peer = Peer(served.link.port)
    peer.next()
    garbage = bytes(np.random.default_rng(3).integers(0, 256, 300, dtype=np.uint8)) + b"\xfd\xff\x00\x00"
    peer.sock.sendall(garbage)  # ends inside a bogus frame header claiming 267 bytes
    t = peer.step(armed=False)[-1].time_usec
    assert "not valid MAVLink" in caplog.text
    u = float(served.link.motor_map.speed_to_output(sim.vehicle().hover_speed))
    s = peer.step([float("nan"), u, u, u])[-1]
    assert s.time_usec == t + STEP_US and "not finite" in caplog.text
    s = peer.step([1.5, -0.2, u, u])[-1]
    assert s.time_usec == t + 2 * STEP_US and "outside [0, 1]" in caplog.text
    assert np.all(np.isfinite(sim.vehicle().state.rotor_speeds))
    for _ in range(5):
        s = peer.step(armed=False)[-1]
    assert s.time_usec == t + 7 * STEP_US and served.link.connected
    peer.close()


def test_same_seed_gives_identical_sensor_streams(monkeypatch):
    # lockstep from the first batch on: a PX4 that has not answered within BOOT_GRACE_S of wall time gets
    # the link free-running (as Gazebo does), and how many steps it free-ran before the peer's first answer
    # (before or after the reset to the hover) was the wall clock's: the first run in a process, with its
    # kernels compiling, gave another stream than the second
    monkeypatch.setattr("droneulator.px4.link.BOOT_GRACE_S", 30.0)

    def run(seed: int) -> list[bytes]:
        sim = make_sim("px4_quadx", seed=seed)
        served = Served(sim)
        peer = px4_in_the_air(served, sim.scene.spawn_position + [0.0, 0.0, 3.0])
        msgs = []
        u = float(served.link.motor_map.speed_to_output(sim.vehicle().hover_speed))
        for k in range(60):
            msgs += peer.step([u + 0.02 * math.sin(0.3 * k), u, u, u - 0.02 * math.sin(0.3 * k)])
        peer.close()
        served.close()
        sim.close()
        return [bytes(m.get_msgbuf()) for m in msgs]

    a, b, c = run(5), run(5), run(6)
    assert a == b
    assert a != c and len(a) == len(c)


def test_split_frames_and_a_corrupted_copy_before_a_valid_frame_are_handled(served, sim, caplog):
    """pymavlink frames the stream: a message split over TCP segments is stepped once complete, and
    a corrupted copy (bad checksum) in front of a valid message costs bytes, not the message."""
    caplog.set_level(logging.ERROR, logger="droneulator.px4")
    peer = Peer(served.link.port)
    peer.next()
    t = peer.step(armed=False)[-1].time_usec  # lockstep from here: one step per actuator message
    frame = peer.mav.hil_actuator_controls_encode(t, [0.0] * 16, 1, 1).pack(peer.mav)
    peer.sock.sendall(frame[:7])
    time.sleep(0.05)
    assert by_type(peer.drain(0.05), "HIL_SENSOR") == []  # half a frame steps nothing
    peer.sock.sendall(frame[7:])
    assert peer.next()[-1].time_usec == t + STEP_US
    frame = peer.mav.hil_actuator_controls_encode(t, [0.0] * 16, 1, 1).pack(peer.mav)
    corrupt = frame[:-1] + bytes([frame[-1] ^ 0xFF])
    peer.sock.sendall(corrupt + frame)
    assert peer.next()[-1].time_usec == t + 2 * STEP_US
    assert "not valid MAVLink" in caplog.text and served.link.connected
    peer.close()


def test_a_vehicle_without_gps_sends_no_fix_and_one_without_a_magnetometer_is_refused(monkeypatch):
    """The link sends what the vehicle's rig carries: no GPS, no HIL_GPS; no airspeed sensor, zero
    airspeeds; PX4 cannot fly without a magnetometer, so that rig is refused."""
    monkeypatch.setattr("droneulator.px4.link.BOOT_GRACE_S", BOOT_GRACE)  # reads a batch of the boot

    def messages(sensors: list[str] | None) -> list[Any]:
        sim = make_sim("px4_quadx", sensors=sensors)
        sim.config.vehicle.wind, sim.config.vehicle.wind_velocity = "constant", (3.0, 0.0, 0.0)
        sim.reset()  # in a 3 m/s breeze: a true airspeed to report
        served = Served(sim)
        try:
            peer = px4_in_the_air(served, sim.scene.spawn_position + [0.0, 0.0, 3.0])
            msgs = peer.next()
            u = float(served.link.motor_map.speed_to_output(sim.vehicle().hover_speed))
            for _ in range(100):  # 0.4 s: four GPS periods at 10 Hz
                msgs += peer.step([u] * 4)
            peer.close()
        finally:
            served.close()
            sim.close()
        return msgs

    full, bare = messages(None), messages(["imu", "mag", "baro"])
    assert len(by_type(full, "HIL_GPS")) >= 4 and not by_type(bare, "HIL_GPS")
    assert min(m.true_airspeed for m in by_type(full, "HIL_STATE_QUATERNION")[-50:]) > 250  # cm/s
    assert all(m.ind_airspeed == 0 == m.true_airspeed for m in by_type(bare, "HIL_STATE_QUATERNION"))
    sim = make_sim("px4_quadx", sensors=["imu", "baro", "gps"])
    with pytest.raises(ValueError, match="has no mag: PX4 needs imu, mag, baro"):
        PX4Link(sim, px4_cfg())
    sim.close()
