"""Flight modes of a one-vehicle in-process World on real scenes (real RotorPy models, no rendering)."""

import math

import numpy as np
import pytest

from droneulator.commands import CommandError
from droneulator.vehicles.vehicle import Vehicle
from droneulator.world import World


@pytest.fixture()
def world():
    w = World(scene="default", render=False)
    yield w
    w.close()


@pytest.fixture()
def uav(world: World) -> Vehicle:
    return world.vehicle()


def airborne(world: World, height: float = 2.0) -> np.ndarray:
    p = world.scene.spawn_position + [0.0, 0.0, height]
    world.reset(position=p)
    return p


def test_hover_holds_position_within_2cm_for_10s(world, uav):
    p = airborne(world)
    errs = []
    for _ in range(1000):
        world.step()
        errs.append(np.linalg.norm(uav.state.position - p))
    assert world.t == pytest.approx(10.0)
    assert max(errs) < 0.02


def test_takeoff_then_goto_reaches_waypoint_and_follows_min_snap(world, uav):
    events = []
    uav.takeoff(2.0)
    assert world.run_until(lambda w: uav.mode.value == "hold", 15, events)
    assert [e.type for e in events] == ["arrived"]
    start = uav.state.position
    target = start + [3.0, -2.0, 1.0]
    duration = uav.goto(target, yaw=1.2, speed=1.5)
    track, events = [], []
    while uav.mode.value == "goto":
        res = world.step()
        events += res.events
        st = uav.state
        if st.reference is not None:
            track.append(np.linalg.norm(st.position - st.reference[0:3]))
        assert world.t < 30
    assert events and events[-1].type == "arrived"
    assert world.t >= duration  # never declared before the reference ends
    assert np.linalg.norm(uav.state.position - target) < 0.05
    assert abs(math.remainder(uav.state.yaw - 1.2, 2 * math.pi)) < 0.02
    assert max(track) < 0.10  # followed its reference closely the whole way
    world.run(3.0)
    assert np.linalg.norm(uav.state.position - target) < 0.02


def test_velocity_mode_tracks_speed_and_yaw_rate_and_holds_altitude(world, uav):
    p = airborne(world, 2.5)
    uav.velocity(1.5, 0.4)
    world.run(4.0)  # filters settle
    speeds, rates, alts, yaws = [], [], [], []
    for _ in range(300):
        world.step()
        st = uav.state
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
    uav.velocity(0.0, 0.0)
    world.run(4.0)
    assert np.linalg.norm(uav.state.velocity) < 0.05


def test_motors_off_falls_and_rests_on_ground(world, uav):
    airborne(world, 1.5)
    uav.motors_off()
    zs, events = [], []
    for _ in range(400):
        events += world.step().events
        zs.append(uav.state.position[2])
    assert min(zs) >= -0.06  # the landing legs take the ~5 m/s touchdown within a few cm
    assert abs(uav.state.position[2]) < 1e-4  # and it rests at z = 0, not sunk and not bounced
    assert np.linalg.norm(uav.state.velocity) < 1e-4
    assert [e.type for e in events] == ["impact"]
    assert events[0].data["speed"] == pytest.approx(5.3, abs=0.1)


def test_resting_on_ground_before_takeoff(world, uav):
    world.run(2.0)
    assert uav.mode.value == "idle"
    np.testing.assert_allclose(uav.state.position, world.scene.spawn_position, atol=1e-9)


def test_land_ends_idle_on_the_ground(world, uav):
    airborne(world, 2.0)
    events = []
    uav.land()
    assert world.run_until(lambda w: uav.mode.value == "idle", 20, events)
    assert [e.type for e in events] == ["landed"]  # a gentle touchdown: no impact event
    world.run(1.0)
    assert abs(uav.state.position[2]) < 1e-4  # resting on its legs at z = 0
    np.testing.assert_allclose(uav.specific_force, [0.0, 0.0, 9.81], atol=1e-3)


def test_flying_into_a_trunk_raises_a_collision_event():
    world = World(scene="tree_inspection", render=False)
    uav = world.vehicle()
    tree = world.scene.landmarks["tree"]
    start = np.array([tree[0] - 6.0, tree[1], 1.0])
    world.reset(position=start, yaw=0.0)  # facing +x, towards the trunk
    uav.velocity(1.5, 0.0)
    events = []
    assert world.run_until(lambda w: uav.mode.value == "collided", 15, events)
    assert [e.type for e in events] == ["collision"]
    st = uav.state
    assert np.linalg.norm(st.velocity) == 0.0  # the vehicle stops
    assert st.position[0] < tree[0]
    assert world.scene.collision.distance(st.position) < world.config.vehicle.collision_radius + 0.05
    world.run(1.0)  # stays stopped, no repeated events
    assert uav.collisions == 1
    uav.velocity(-1.0, 0.0)  # a new command backs away
    world.run(2.0)
    assert uav.state.position[0] < st.position[0] - 0.5


def test_bad_commands_are_rejected_and_change_nothing(world, uav):
    with pytest.raises(CommandError) as e:
        uav.velocity(1.0, 0.0)
    assert e.value.code == "not_airborne"
    airborne(world)
    before = uav.state.position
    cases = [
        (lambda: uav.goto([float("nan"), 0, 1]), "invalid_argument"),
        (lambda: uav.goto([0, 0]), "invalid_argument"),
        (lambda: uav.goto("here"), "invalid_argument"),
        (lambda: uav.goto([0, 0, -1.0]), "below_ground"),
        (lambda: uav.goto([1e6, 0, 2.0]), "out_of_bounds"),
        (lambda: uav.goto([0, 0, 2.0], speed=-1), "out_of_range"),
        (lambda: uav.goto([0, 0, 2.0], yaw=float("inf")), "invalid_argument"),
        (lambda: uav.velocity(float("nan"), 0.0), "invalid_argument"),
        (lambda: uav.velocity(100.0, 0.0), "out_of_range"),
        (lambda: uav.takeoff(-3.0), "below_ground"),
    ]
    for call, code in cases:
        with pytest.raises(CommandError) as e:
            call()
        assert e.value.code == code, e.value.message
    assert uav.mode.value == "hold"
    world.run(1.0)
    assert np.linalg.norm(uav.state.position - before) < 0.02


def test_same_seed_same_flight():
    runs = []
    for _ in range(2):
        w = World(scene="default", seed=3, render=False)
        v = w.vehicle()
        v.takeoff(1.5)
        w.run(3.0)
        v.velocity(1.0, 0.2)
        w.run(2.0)
        runs.append(v.s.copy())
    np.testing.assert_array_equal(runs[0], runs[1])


def test_direct_rotor_speeds_hover_and_acceleration(world, uav):
    """External rotor commands (the PX4 path): hover speed holds altitude; motors off falls at g."""
    p = airborne(world, 3.0)
    uav.set_rotor_speeds([uav.hover_speed] * 4)
    assert uav.mode.value == "external"
    world.run(0.5)
    assert abs(uav.state.position[2] - p[2]) < 0.01
    np.testing.assert_allclose(uav.acceleration, 0.0, atol=0.05)
    uav.set_rotor_speeds([0.0] * 4)
    world.run(0.2)
    assert uav.acceleration[2] == pytest.approx(-9.81, abs=0.3)
    with pytest.raises(CommandError):
        uav.set_rotor_speeds([1.0, float("nan"), 1.0, 1.0])
    uav.hold()
    assert uav.mode.value == "hold"
