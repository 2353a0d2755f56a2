"""Flight modes of the in-process Simulator on real scenes (real RotorPy models, no rendering)."""

import math

import numpy as np
import pytest

from droneulator.commands import CommandError
from droneulator.sim.simulator import Simulator


@pytest.fixture()
def sim():
    s = Simulator(scene="default", render=False)
    yield s
    s.close()


def airborne(sim: Simulator, height: float = 2.0) -> np.ndarray:
    p = sim.scene.spawn_position + [0.0, 0.0, height]
    sim.reset(position=p)
    return p


def test_hover_holds_position_within_2cm_for_10s(sim):
    p = airborne(sim)
    errs = []
    for _ in range(1000):
        sim.step()
        errs.append(np.linalg.norm(sim.state.position - p))
    assert sim.t == pytest.approx(10.0)
    assert max(errs) < 0.02


def test_takeoff_then_goto_reaches_waypoint_and_follows_min_snap(sim):
    events = []
    sim.takeoff(2.0)
    assert sim.run_until(lambda s: s.mode.value == "hold", 15, events)
    assert [e.type for e in events] == ["arrived"]
    start = sim.state.position
    target = start + [3.0, -2.0, 1.0]
    duration = sim.goto(target, yaw=1.2, speed=1.5)
    track, events = [], []
    while sim.mode.value == "goto":
        res = sim.step()
        events += res.events
        st = sim.state
        if st.reference is not None:
            track.append(np.linalg.norm(st.position - st.reference[0:3]))
        assert sim.t < 30
    assert events and events[-1].type == "arrived"
    assert sim.t >= duration  # never declared before the reference ends
    assert np.linalg.norm(sim.state.position - target) < 0.05
    assert abs(math.remainder(sim.state.yaw - 1.2, 2 * math.pi)) < 0.02
    assert max(track) < 0.10  # followed its reference closely the whole way
    sim.run(3.0)
    assert np.linalg.norm(sim.state.position - target) < 0.02


def test_velocity_mode_tracks_speed_and_yaw_rate_and_holds_altitude(sim):
    p = airborne(sim, 2.5)
    sim.velocity(1.5, 0.4)
    sim.run(4.0)  # filters settle
    speeds, rates, alts, yaws = [], [], [], []
    for _ in range(300):
        sim.step()
        st = sim.state
        speeds.append(np.hypot(*st.velocity[:2]))
        alts.append(st.position[2])
        yaws.append(st.yaw)
        heading = np.array([math.cos(st.yaw), math.sin(st.yaw)])
        rates.append(st.angular_velocity[2])
        assert float(heading @ st.velocity[:2]) > 1.4  # moving forward along the body x axis
    assert np.mean(speeds) == pytest.approx(1.5, abs=0.03)
    assert np.mean(rates) == pytest.approx(0.4, abs=0.01)
    yaw_rate = np.mean(np.diff(np.unwrap(yaws))) / 0.01
    assert yaw_rate == pytest.approx(0.4, abs=0.01)
    assert max(abs(a - p[2]) for a in alts) < 0.02
    sim.velocity(0.0, 0.0)
    sim.run(4.0)
    assert np.linalg.norm(sim.state.velocity) < 0.05


def test_motors_off_falls_and_rests_on_ground(sim):
    airborne(sim, 1.5)
    sim.motors_off()
    zs, events = [], []
    for _ in range(400):
        events += sim.step().events
        zs.append(sim.state.position[2])
    assert min(zs) >= -0.06  # the landing legs take the ~5 m/s touchdown within a few cm
    assert abs(sim.state.position[2]) < 1e-4  # and it rests at z = 0, not sunk and not bounced
    assert np.linalg.norm(sim.state.velocity) < 1e-4
    assert [e.type for e in events] == ["impact"]
    assert events[0].data["speed"] == pytest.approx(5.3, abs=0.1)


def test_resting_on_ground_before_takeoff(sim):
    sim.run(2.0)
    assert sim.mode.value == "idle"
    np.testing.assert_allclose(sim.state.position, sim.scene.spawn_position, atol=1e-9)


def test_land_ends_idle_on_the_ground(sim):
    airborne(sim, 2.0)
    events = []
    sim.land()
    assert sim.run_until(lambda s: s.mode.value == "idle", 20, events)
    assert [e.type for e in events] == ["landed"]  # a gentle touchdown: no impact event
    sim.run(1.0)
    assert abs(sim.state.position[2]) < 1e-4  # resting on its legs at z = 0
    np.testing.assert_allclose(sim.specific_force, [0.0, 0.0, 9.81], atol=1e-3)


def test_flying_into_a_trunk_raises_a_collision_event():
    sim = Simulator(scene="tree_inspection", render=False)
    tree = sim.scene.landmarks["tree"]
    start = np.array([tree[0] - 6.0, tree[1], 1.0])
    sim.reset(position=start, yaw=0.0)  # facing +x, towards the trunk
    sim.velocity(1.5, 0.0)
    events = []
    assert sim.run_until(lambda s: s.mode.value == "collided", 15, events)
    assert [e.type for e in events] == ["collision"]
    st = sim.state
    assert np.linalg.norm(st.velocity) == 0.0  # the vehicle stops
    assert st.position[0] < tree[0]
    assert sim.scene.collision.distance(st.position) < sim.config.vehicle.collision_radius + 0.05
    sim.run(1.0)  # stays stopped, no repeated events
    assert sim.collisions == 1
    sim.velocity(-1.0, 0.0)  # a new command backs away
    sim.run(2.0)
    assert sim.state.position[0] < st.position[0] - 0.5


def test_bad_commands_are_rejected_and_change_nothing(sim):
    with pytest.raises(CommandError) as e:
        sim.velocity(1.0, 0.0)
    assert e.value.code == "not_airborne"
    airborne(sim)
    before = sim.state.position
    cases = [
        (lambda: sim.goto([float("nan"), 0, 1]), "invalid_argument"),
        (lambda: sim.goto([0, 0]), "invalid_argument"),
        (lambda: sim.goto("here"), "invalid_argument"),
        (lambda: sim.goto([0, 0, -1.0]), "below_ground"),
        (lambda: sim.goto([1e6, 0, 2.0]), "out_of_bounds"),
        (lambda: sim.goto([0, 0, 2.0], speed=-1), "out_of_range"),
        (lambda: sim.goto([0, 0, 2.0], yaw=float("inf")), "invalid_argument"),
        (lambda: sim.velocity(float("nan"), 0.0), "invalid_argument"),
        (lambda: sim.velocity(100.0, 0.0), "out_of_range"),
        (lambda: sim.takeoff(-3.0), "below_ground"),
    ]
    for call, code in cases:
        with pytest.raises(CommandError) as e:
            call()
        assert e.value.code == code, e.value.message
    assert sim.mode.value == "hold"
    sim.run(1.0)
    assert np.linalg.norm(sim.state.position - before) < 0.02


def test_same_seed_same_flight():
    runs = []
    for _ in range(2):
        s = Simulator(scene="default", seed=3, render=False)
        s.takeoff(1.5)
        s.run(3.0)
        s.velocity(1.0, 0.2)
        s.run(2.0)
        runs.append(s.s.copy())
    np.testing.assert_array_equal(runs[0], runs[1])


def test_direct_rotor_speeds_hover_and_acceleration(sim):
    """External rotor commands (the PX4 path): hover speed holds altitude; motors off falls at g."""
    p = airborne(sim, 3.0)
    sim.set_rotor_speeds([sim.vehicle.hover_speed] * 4)
    assert sim.mode.value == "external"
    sim.run(0.5)
    assert abs(sim.state.position[2] - p[2]) < 0.01
    np.testing.assert_allclose(sim.acceleration, 0.0, atol=0.05)
    sim.set_rotor_speeds([0.0] * 4)
    sim.run(0.2)
    assert sim.acceleration[2] == pytest.approx(-9.81, abs=0.3)
    with pytest.raises(CommandError):
        sim.set_rotor_speeds([1.0, float("nan"), 1.0, 1.0])
    sim.hold()
    assert sim.mode.value == "hold"
