"""Faults (docs/faults.md): a rotor's loss of efficiency in the compiled physics, the sensor faults in the
sensor data PX4 gets, the events of a schedule, the op's refusals, a cut command link, randomisation."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from droneulator.api.protocol import handle_request
from droneulator.commands.ops import OPS, execute, make_request
from droneulator.config import FaultSpec, PX4Config, RandomizeConfig, SiteConfig, from_dict, load_config
from droneulator.config.faults import fault_markdown
from droneulator.frames import geodetic_to_enu
from droneulator.px4.hil import HilEncoder
from droneulator.sensors import SensorSuite, Truth
from droneulator.state import STATE, STATE_SIZE
from droneulator.vehicles.dynamics import FastMultirotor, hover_speed, pack_params, state_derivative
from droneulator.vehicles.params import get_params
from droneulator.world import World

NS = 1_000_000_000
DOCS = Path(__file__).resolve().parents[1] / "docs"


@pytest.fixture(scope="module")
def world():
    with World(load_config(scene="default"), render=False) as w:
        yield w


def _op(world: World, op: str, **args: object) -> dict:
    return execute(world, make_request(op, args))


# --------------------------------------------------------------------------- the rotors
def test_rotor_efficiency_scales_each_rotors_thrust_and_yaw_moment_as_a_hand_calculation():
    q = get_params("hummingbird")
    p, geom, dirs = pack_params(q, aero=False, ground=False)
    s = np.zeros(STATE_SIZE)
    s[STATE.x] = (0.0, 0.0, 10.0)
    s[STATE.q] = (0.0, 0.0, 0.0, 1.0)
    w = 1.1 * hover_speed(p)
    s[STATE.rotor_speeds] = w  # at the commanded speed: no motor lag
    eff = np.array([1.0, 0.5, 1.0, 1.0])
    ds = state_derivative(s, np.full(4, w), p, geom, dirs, eff)
    thrust = q["k_eta"] * w * w * eff  # each rotor's, N, along body z
    assert ds[5] == pytest.approx(thrust.sum() / q["mass"] - 9.81, abs=1e-9)
    moment = np.array([(geom[:, 1] * thrust).sum(), -(geom[:, 0] * thrust).sum(),
                       (dirs * q["k_m"] * w * w * eff).sum()])  # fmt: skip
    inertia = np.array([[q["Ixx"], q["Ixy"], q["Ixz"]], [q["Ixy"], q["Iyy"], q["Iyz"]],
                        [q["Ixz"], q["Iyz"], q["Izz"]]])  # fmt: skip
    np.testing.assert_allclose(ds[10:13], np.linalg.solve(inertia, moment), rtol=0, atol=1e-9)
    healthy = state_derivative(s, np.full(4, w), p, geom, dirs)
    assert ds[5] < healthy[5] and abs(healthy[10]) < 1e-9 < abs(ds[10])
    # the integrator reads the same factors (FastMultirotor's row)
    fast = FastMultirotor(q, aero=False, enable_ground=False)
    fast.rotor_efficiency[:] = eff
    s2 = s.copy()
    fast.step(s2, np.full(4, w), 1e-3)
    assert s2[5] == pytest.approx(ds[5] * 1e-3, rel=1e-3)


def test_a_hovering_vehicle_with_a_rotor_at_half_efficiency_tilts_yaws_and_drops(world):
    """Open loop at the healthy hover speeds: the healthy vehicle stays, the faulty one falls, rolls or
    pitches towards the weak rotor and yaws against the weak rotor's lost reaction torque."""
    v = world.vehicle()
    ends = []
    for fault in (False, True):
        world.reset(position=[0.0, 0.0, 5.0], yaw=0.0)
        if fault:
            assert _op(world, "fault", kind="rotor", rotor=1, efficiency=0.5)["ok"]
        v.rotors(np.full(4, v.hover_speed))
        world.run(0.3)
        ends.append(v.state)
    healthy, faulty = ends
    assert abs(healthy.position[2] - 5.0) < 1e-3 and np.abs(healthy.angular_velocity).max() < 1e-3
    # a quarter of the thrust of one rotor of four lost: about g/8 down at first
    assert faulty.position[2] < 5.0 - 0.03
    assert np.abs(faulty.angular_velocity[:2]).max() > 0.5
    direction = world.table.directions[world._pidx[0], 1]
    assert np.sign(faulty.angular_velocity[2]) == -np.sign(direction)


# --------------------------------------------------------------------------- the sensors
def _truth(t_s: float) -> Truth:
    return Truth(round(t_s * NS), np.array([3.0, -2.0, 10.0]), np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]),
                 np.zeros(3), np.zeros(3), np.zeros(3), np.array([0.0, 0.0, 9.81]))  # fmt: skip


def _pair(*faults: FaultSpec) -> tuple[SensorSuite, SensorSuite]:
    """Two suites of one seed, the second with ``faults`` (started at t = 0)."""
    clean, faulty = SensorSuite(PX4Config(), 7), SensorSuite(PX4Config(), 7)
    faulty.faults.set([(f, 0) for f in faults])
    return clean, faulty


def _enu(sample, site: SiteConfig) -> np.ndarray:
    return geodetic_to_enu(sample.lat_deg, sample.lon_deg, sample.alt_msl_m, *site.geodetic)


def test_sensor_faults_move_the_samples_by_what_they_set():
    bias = FaultSpec(kind="imu_bias", accel=(0.3, -0.2, 0.1), gyro=(0.01, 0.0, -0.02))
    spoof = FaultSpec(kind="gps_spoofing", drift=(1.0, 0.5, 0.0), offset=(2.0, 0.0, 0.0))
    drift = FaultSpec(kind="baro_drift", rate=0.4)
    mag = FaultSpec(kind="mag_interference", field=(0.1, 0.0, -0.05))
    clean, faulty = _pair(bias, spoof, drift, mag)
    site = SiteConfig()
    for t in (0.0, 1.0, 2.5):
        truth = _truth(t)
        (a0, g0), (a1, g1) = clean.imu(truth), faulty.imu(truth)
        np.testing.assert_allclose(a1 - a0, bias.accel, atol=1e-12)
        np.testing.assert_allclose(g1 - g0, bias.gyro, atol=1e-12)
        np.testing.assert_allclose(faulty.mag(truth) - clean.mag(truth), mag.field, atol=1e-12)
        b0, b1 = clean.baro(truth), faulty.baro(truth)
        assert b1.pressure_alt_m - b0.pressure_alt_m == pytest.approx(0.4 * t, abs=1e-6)
        assert t == 0 or b1.pressure_hpa < b0.pressure_hpa  # higher up, lower pressure
        f0, f1 = clean.gps(truth), faulty.gps(truth)
        shift = _enu(f1, site) - _enu(f0, site)
        np.testing.assert_allclose(shift, np.array(spoof.offset) + np.array(spoof.drift) * t, atol=1e-3)
        np.testing.assert_allclose(f1.vel_ned - f0.vel_ned, [0.5, 1.0, 0.0], atol=1e-12)


def test_gps_loss_stops_the_fixes_and_jamming_degrades_them():
    clean, lost = _pair(FaultSpec(kind="gps_loss"))
    _, jammed = _pair(FaultSpec(kind="gps_jamming", noise_m=8.0, satellites=3))
    assert lost.gps(_truth(0.2)) is None and "gps" not in lost.latest
    fix, bad = clean.gps(_truth(0.2)), jammed.gps(_truth(0.2))
    assert bad.satellites == 3 and bad.eph_m > 8.0 > fix.eph_m and bad.epv_m > 8.0
    lost.faults.set([])
    assert lost.gps(_truth(0.4)) is not None


def _hil(suite: SensorSuite, t_s: float) -> dict[str, object]:
    rx = mavlink.MAVLink(None)
    return {m.get_type(): m for m in rx.parse_buffer(HilEncoder(suite, PX4Config(), SiteConfig()).batch(
        _truth(t_s))) or []}  # fmt: skip


def test_px4_gets_the_imu_bias_in_hil_sensor_and_no_hil_gps_while_the_gps_is_lost():
    clean, faulty = _pair(FaultSpec(kind="imu_bias", accel=(0.3, -0.2, 0.1), gyro=(0.01, 0.0, -0.02)),
                          FaultSpec(kind="gps_loss"))  # fmt: skip
    a, b = _hil(clean, 1.0), _hil(faulty, 1.0)
    assert "HIL_GPS" in a and "HIL_GPS" not in b
    s0, s1 = a["HIL_SENSOR"], b["HIL_SENSOR"]
    accel = np.array([s1.xacc - s0.xacc, s1.yacc - s0.yacc, s1.zacc - s0.zacc])
    gyro = np.array([s1.xgyro - s0.xgyro, s1.ygyro - s0.ygyro, s1.zgyro - s0.zgyro])
    np.testing.assert_allclose(accel, [0.3, -0.2, 0.1], atol=0.01)  # PX4's int16 FIFO steps: 4.8 mm/s^2
    np.testing.assert_allclose(gyro, [0.01, 0.0, -0.02], atol=2e-3)


# --------------------------------------------------------------------------- events, the op, the link
def test_a_scheduled_fault_starts_and_ends_with_events_at_its_times():
    cfg = from_dict(type(load_config()), {"faults": [
        {"at": 0.5, "duration": 0.3, "kind": "gps_loss"},
        {"at": 0.2, "kind": "rotor", "rotor": 2, "efficiency": 0.8},
    ]})  # fmt: skip
    with World(cfg, render=False) as w:
        w.reset(position=[0.0, 0.0, 3.0])
        v = w.vehicle()
        events = []
        w.run_until(lambda x: x.t >= 0.6, 2.0, events)
        assert {f["kind"] for f in v.state.to_dict()["faults"]} == {"rotor", "gps_loss"}
        assert v.rig.suite.faults.gps_lost and w.rotor_efficiency[0, 0, 2] == 0.8
        w.run_until(lambda x: x.t >= 1.0, 2.0, events)
        got = [(e.type, e.data["kind"], e.t) for e in events if e.type.startswith("fault")]
        assert got == [("fault_started", "rotor", 0.2), ("fault_started", "gps_loss", 0.5),
                       ("fault_ended", "gps_loss", 0.8)]  # fmt: skip
        ended = next(e for e in events if e.type == "fault_ended")
        assert ended.vehicle == "uav0" and ended.data["reason"] == "expired"
        assert not v.rig.suite.faults.gps_lost
        w.reset()  # a reset ends the faults of the episode and arms the schedule again
        assert "faults" not in v.state.to_dict() and w.rotor_efficiency[0, 0, 2] == 1.0
        w.run(0.25)
        assert w.rotor_efficiency[0, 0, 2] == 0.8


@pytest.mark.parametrize(
    ("args", "code"),
    [
        ({"kind": "meteor"}, "invalid_argument"),
        ({"kind": "rotor", "rotor": 4, "efficiency": 0.5}, "out_of_range"),
        ({"kind": "rotor", "rotor": -1}, "out_of_range"),
        ({"kind": "rotor", "rotor": 0, "efficiency": 1.5}, "out_of_range"),
        ({"kind": "rotor", "efficiency": 0.5}, "invalid_argument"),
        ({"kind": "gps_loss", "efficiency": 0.5}, "invalid_argument"),
        ({"kind": "mag_interference"}, "invalid_argument"),
        ({"kind": "gps_jamming", "satellites": 99}, "out_of_range"),
        ({"kind": "rotor", "rotor": 0, "vehicle": "uav9"}, "invalid_argument"),
    ],
)
def test_the_fault_op_refuses_bad_input_and_the_simulation_goes_on(world, args, code):
    world.reset(position=[0.0, 0.0, 3.0])
    reply = _op(world, "fault", **args)
    assert not reply["ok"] and reply["error"]["code"] == code, reply
    assert not world.faults.active
    world.step()
    assert _op(world, "fault_clear", kind="meteor")["error"]["code"] == "invalid_argument"


def test_a_cut_link_delivers_no_command_so_the_stream_times_out_into_a_hold(world):
    world.reset(position=[0.0, 0.0, 3.0])
    assert _op(world, "track", position=[0.0, 0.0, 3.2])["ok"]
    started = _op(world, "fault", kind="link_cut", duration=2.0)
    assert started["ok"] and started["result"]["fault"]["kind"] == "link_cut"
    refused = _op(world, "track", position=[0.0, 0.0, 3.2])
    assert refused["error"]["code"] == "link_cut"
    events = []
    world.run_until(lambda w: w.t >= 1.0, 2.0, events)
    kinds = [e.type for e in events]
    assert kinds[0] == "fault_started" and "track_timeout" in kinds
    assert world.vehicle().mode.value == "hold"
    cleared = _op(world, "fault_clear", vehicle="uav0")
    assert cleared["ok"] and cleared["result"]["cleared"] == [started["result"]["fault"]["id"]]
    assert _op(world, "track", position=[0.0, 0.0, 3.2])["ok"]
    assert world.step().events[0].type == "fault_ended"


def test_fault_clear_by_id_over_the_wire_clears_only_that_fault(world):
    """Found by benchmarks/fuzz.py: the filter was named `id`, the request's own id, so over JSON it
    never reached the op (every fault was cleared) and the reply carried the fault id, not the
    request's (a client waiting for its reply timed out). No op may name a field `id` or `op`."""
    assert not [(o.name, a.name) for o in OPS.values() for a in o.args if a.name in ("id", "op")]
    world.reset(position=[0.0, 0.0, 3.0])
    first = _op(world, "fault", kind="gps_loss")["result"]["fault"]["id"]
    second = _op(world, "fault", kind="baro_drift")["result"]["fault"]["id"]
    reply = handle_request(world, json.dumps({"id": "r1", "op": "fault_clear", "fault_id": first}))
    assert reply["id"] == "r1" and reply["result"]["cleared"] == [first], reply
    assert list(world.faults.active) == [second]
    world.reset(position=[0.0, 0.0, 3.0])


def test_a_camera_dropout_drops_the_vehicles_frames():
    with World(load_config(scene="default"), render=False, external_cameras=True) as w:
        w.inject_fault(FaultSpec(kind="camera_dropout", duration=0.1))
        assert w.camera_dropouts() == {"uav0"}
        w.run(0.2)
        assert w.camera_dropouts() == set()


# --------------------------------------------------------------------------- randomisation
def test_randomisation_draws_a_rotor_fault_and_a_config_carries_it():
    rnd = RandomizeConfig(enabled=True, rotor_fault_prob=1.0, rotor_efficiency=(0.6, 0.7))
    draw = rnd.draw(np.random.default_rng(3))
    weak = [e for e in draw.rotor_efficiency if e < 1.0]
    assert len(weak) == 1 and 0.6 <= weak[0] <= 0.7
    cfg = rnd.apply(load_config(), draw)
    assert [(f.kind, f.efficiency) for f in cfg.faults] == [("rotor", weak[0])]
    calm = RandomizeConfig(enabled=True).draw(np.random.default_rng(3))
    assert calm.rotor_efficiency == (1.0, 1.0, 1.0, 1.0)
    with pytest.raises(ValueError, match="rotor_fault_prob"):
        RandomizeConfig(rotor_fault_prob=2.0)
    with pytest.raises(ValueError, match="needs `kind`"):
        from_dict(type(load_config()), {"faults": [{"at": 1.0}]})


def test_the_single_and_vector_envs_fly_their_episodes_on_the_drawn_rotor_efficiency():
    from droneulator.workflows.rl.env import VineyardNavEnv
    from droneulator.workflows.rl.vector import VineyardNavVectorEnv

    cfg = load_config(overrides=["randomize.enabled=true", "randomize.rotor_fault_prob=1.0",
                                 "randomize.rotor_efficiency=[0.6, 0.7]"])  # fmt: skip
    single = VineyardNavEnv(cfg, depth="raycast")
    vector = VineyardNavVectorEnv(2, config=cfg, depth="raycast")
    try:
        single.reset(seed=4)
        vector.reset(seed=4)
        for eff in (single.backend.world.rotor_efficiency[0, 0], *vector.worlds.rotor_efficiency[:, 0]):
            weak = eff[eff < 1.0]
            assert len(weak) == 1 and 0.6 <= weak[0] <= 0.7, eff
    finally:
        single.close()
        vector.close()


def test_docs_list_every_kind_as_the_code_checks_them():
    assert fault_markdown().split("\n", 2)[2] in (DOCS / "faults.md").read_text()


class _Node:
    """A ROS node that keeps what is published, by topic."""

    def __init__(self) -> None:
        self.sent: dict[str, list[tuple[bytes, int]]] = {}

    def publisher(self, topic: str, typename: str) -> object:
        sent = self.sent.setdefault(topic, [])

        class Pub:
            def publish(self, payload: bytes, t: int) -> None:
                sent.append((bytes(payload), t))

        return Pub()


def test_ros_carries_the_active_faults_on_a_change_and_once_a_second(world):
    from droneulator.ros.messages import decode
    from droneulator.ros.publishers import StatePublisher
    from droneulator.ros.topics import TYPES, faults_topic

    world.reset(position=[0.0, 0.0, 3.0])
    node = _Node()
    pub = StatePublisher(node, world.config)  # type: ignore[arg-type]
    pub.publish_states(world.states_now())
    world.inject_fault(FaultSpec(kind="imu_bias", accel=(0.1, 0.0, 0.0)))
    world.step()
    pub.publish_states(world.states_now())
    pub.publish_states(world.states_now())  # unchanged within a second: not again
    topic = faults_topic("droneulator")
    sent = [json.loads(decode(TYPES["faults"], raw).data) for raw, _ in node.sent[topic]]
    assert len(sent) == 2 and sent[0] == [] and [f["kind"] for f in sent[1]] == ["imu_bias"]
    assert sent[1][0]["accel"] == [0.1, 0.0, 0.0]


def test_the_ros_fault_topic_runs_the_op_for_its_vehicle(world):
    from types import SimpleNamespace

    from droneulator.commands.path import CommandPath
    from droneulator.ros.publishers import subscribe_commands

    handlers = {}
    node = SimpleNamespace(subscribe=lambda topic, typename, cb: handlers.__setitem__(topic, cb))
    subscribe_commands(node, world.config, CommandPath(world))  # type: ignore[arg-type]
    world.reset(position=[0.0, 0.0, 3.0])
    on_fault = handlers["/droneulator/fault"]
    on_fault(SimpleNamespace(data='{"kind": "rotor", "rotor": 3, "efficiency": 0.25}'))
    on_fault(SimpleNamespace(data='{"kind": "rotor", "rotor": 9}'))  # refused (logged), nothing changes
    on_fault(SimpleNamespace(data="not json"))
    assert [(f.spec.kind, f.spec.rotor) for f in world.faults.active.values()] == [("rotor", 3)]
    assert world.rotor_efficiency[0, 0].tolist() == [1.0, 1.0, 1.0, 0.25]


@pytest.mark.parametrize("efficiency", [0.5, 0.05])
def test_the_controller_drives_a_weak_rotor_as_the_model_says_and_saturates_when_it_cannot(world, efficiency):
    """Holding, the SE(3) controller brings the weak rotor to the speed that gives its share of the weight,
    ``w_hover / sqrt(efficiency)`` (the same reaction torque: no yaw left), or, when that is beyond the
    airframe's top speed, drives it to the top and the vehicle falls."""
    v = world.vehicle()
    world.reset(position=[0.0, 0.0, 5.0], yaw=0.0)
    world.inject_fault(FaultSpec(kind="rotor", rotor=1, efficiency=efficiency))
    need, top = v.hover_speed / np.sqrt(efficiency), float(v.quad_params["rotor_speed_max"])
    most = 0.0
    for _ in range(25):
        world.run(0.1)
        most = max(most, float(world._cmds[0, 0, 1]))
    speeds, st = v.s[STATE.rotor_speeds], v.state
    if need < top:
        assert speeds[1] == pytest.approx(need, rel=0.01)
        np.testing.assert_allclose(np.delete(speeds, 1), v.hover_speed, rtol=0.01)
        assert abs(st.angular_velocity[2]) < 0.05 and st.position[2] > 4.7
    else:
        # it asks the weak rotor for nearly all it has and cuts the others to stay level: it falls
        assert most > 0.95 * top and st.position[2] < 0.5
