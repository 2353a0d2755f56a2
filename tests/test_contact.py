"""Ground contact, the accelerometer's specific force, IMU saturation and impact events.

Real one-vehicle Worlds on real scenes (no rendering); the accelerometer is read the way the PX4 link reads
it, through :class:`~droneulator.sensors.truth.Truth` and the registered IMU model.
"""

import dataclasses
import math

import numpy as np
import pytest

from droneulator.config import PX4Config, load_config
from droneulator.frames import quat_from_euler, quat_multiply, quat_to_matrix
from droneulator.sensors.imu import G0, Imu
from droneulator.sensors.suite import SensorSuite
from droneulator.sensors.truth import Truth
from droneulator.vehicles.dynamics import STATE, GroundContact
from droneulator.vehicles.vehicle import Vehicle
from droneulator.world import World

G = 9.81
IMU_RANGE = 16 * G0  # the +-16 g PX4 stores accelerometer samples in


def make_world(
    params: str = "px4_quadx", hz: float = 250.0, scene: str = "default", **vehicle
) -> tuple[World, Vehicle]:
    """A one-vehicle world and its vehicle."""
    sets = [f"vehicle.control_hz={hz}", f"vehicle.params={params}"]
    sets += [f"vehicle.{k}={v}" for k, v in vehicle.items()]
    world = World(scene=scene, render=False, config=load_config(overrides=sets))
    return world, world.vehicle()


def tilt_deg(q: np.ndarray) -> float:
    """Angle between the body z axis and the world vertical."""
    return math.degrees(math.acos(min(1.0, quat_to_matrix(q)[2, 2])))


def drop_height(uav: Vehicle, speed: float) -> float:
    """Height to release the vehicle from (motors off) so its feet touch down at about ``speed``."""
    return uav.contact.foot_depth + speed**2 / (2 * G)


def descend(world: World, uav: Vehicle, speed: float) -> dict:
    """A PX4-style landing: track a reference that accelerates at 2 m/s^2 to ``speed`` and keeps
    descending through the ground; hold the rotors on it for 1 s after touchdown, then cut them.
    IMU samples are taken the way the PX4 link takes them."""
    accel, ramp = 2.0, speed / 2.0
    start = world.scene.spawn_position + [0.0, 0.0, 1.0 + 1.5 * speed + 0.5 * accel * ramp**2]
    world.reset(position=start)
    imu = SensorSuite(PX4Config(), seed=1)
    flat = np.zeros(11)
    flat[0:2], flat[9] = start[:2], uav.state.yaw
    foot = uav.contact.foot_depth
    out = {"events": [], "peak": 0.0, "clean_peak": 0.0, "top": -1.0, "touchdown": None}
    while world.t < 30.0:
        t = world.t
        fall = 0.5 * accel * min(t, ramp) ** 2 + speed * max(0.0, t - ramp)
        flat[2] = start[2] - fall
        flat[5] = -min(accel * t, speed)
        flat[8] = -accel if t < ramp else 0.0
        if flat[2] < -0.3:  # PX4 keeps asking to descend after contact; cap the wind-up
            flat[2], flat[5], flat[8] = -0.3, 0.0, 0.0
        td = out["touchdown"]
        off = td is not None and t > td[0] + 1.0
        uav.set_rotor_speeds(np.zeros(4) if off else uav.flight.se3.motor_speeds(uav.s, flat))
        before = uav.state.velocity[2]
        out["events"] += world.step().events
        if td is None and uav.state.position[2] < foot:
            out["touchdown"] = (world.t, -before)
        if out["touchdown"] is not None:
            a, _ = imu.imu(Truth.from_sim(uav))
            out["peak"] = max(out["peak"], float(np.max(np.abs(a))))
            out["clean_peak"] = max(out["clean_peak"], float(np.max(np.abs(uav.specific_force))))
            out["top"] = max(out["top"], uav.state.position[2] - foot)  # feet above the ground
        if off and world.t > out["touchdown"][0] + 3.0:
            break
    out["state"] = uav.state
    return out


# --------------------------------------------------------------------------- touchdowns
@pytest.mark.parametrize("speed", [0.2, 0.7, 1.2, 2.0])
def test_controlled_touchdown_stays_in_imu_range_and_settles(speed):
    """0.2-2 m/s touchdowns at PX4's 250 Hz with thrust near hover: the accelerometer stays well
    inside +-16 g, the vehicle does not bounce more than a few cm, then rests at z = 0."""
    world, uav = make_world()
    r = descend(world, uav, speed)
    assert r["touchdown"][1] == pytest.approx(speed, rel=0.15)
    assert r["clean_peak"] < 10 * G  # the legs stop it over several cm, not in one step
    assert r["peak"] < IMU_RANGE * 0.999  # never at the rail: nothing for PX4 to wrap or clip
    assert r["top"] < 0.05
    st = r["state"]
    assert abs(st.position[2]) < 1e-3 and np.linalg.norm(st.velocity) < 1e-3
    assert tilt_deg(st.quaternion) < 0.1
    np.testing.assert_allclose(st.position[:2], world.scene.spawn_position[:2], atol=0.01)
    impacts = [e for e in r["events"] if e.type == "impact"]
    assert len(impacts) == (1 if speed > 1.5 else 0)


@pytest.mark.parametrize("speed", [0.2, 0.7, 1.2, 2.0])
def test_motors_off_drop_stops_within_a_few_cm_without_bounce(speed):
    world, uav = make_world(hz=100.0, params="hummingbird")
    world.reset(position=world.scene.spawn_position + [0.0, 0.0, drop_height(uav, speed)], airborne=False)
    zs, peak = [], 0.0
    while world.t < 3.0:
        world.step()
        zs.append(uav.state.position[2])
        peak = max(peak, float(np.linalg.norm(uav.specific_force)))
    low = int(np.argmin(zs))
    assert zs[low] > -0.05  # the legs compress at most a few cm
    assert max(zs[low:]) < 1e-3  # and came back to rest without leaving the ground
    assert peak < 12 * G
    assert abs(zs[-1]) < 1e-3 and np.linalg.norm(uav.state.velocity) < 1e-3


@pytest.mark.parametrize("params", ["hummingbird", "crazyflie", "px4_quadx"])
def test_tilted_sliding_touchdown_neither_launches_nor_slides_away(params):
    """Motors off, 20 degrees of bank, 1.5 m/s sideways and 1.5 m/s down: friction stops the slide
    within a few tens of cm, the legs level the vehicle, and it stays where it stopped."""
    world, uav = make_world(params=params, hz=100.0)
    start = world.scene.spawn_position + [0.0, 0.0, drop_height(uav, 1.5)]
    world.reset(position=start, airborne=False)
    uav.s[STATE.q] = quat_from_euler(math.radians(20), math.radians(-8), 0.7)
    uav.s[STATE.v] = [1.5, 0.5, -0.0]
    zs = []
    while world.t < 6.0:
        world.step()
        zs.append(uav.state.position[2])
    low = int(np.argmin(zs))
    assert max(zs[low:]) < 0.02  # no launch
    st = uav.state
    slide = np.linalg.norm(st.position[:2] - start[:2])
    assert slide < 1.2  # the ballistic part is ~0.5 m, friction stops the rest within ~0.3 m
    assert tilt_deg(st.quaternion) < 1.0 and abs(st.position[2]) < 2e-3
    assert np.linalg.norm(st.velocity) < 2e-3 and np.linalg.norm(st.angular_velocity) < 0.01
    rest = st.position.copy()
    world.run(2.0)
    np.testing.assert_allclose(uav.state.position[:2], rest[:2], atol=2e-4)  # a resting vehicle stays


def test_upside_down_vehicle_rests_on_its_hubs_instead_of_falling_through():
    world, uav = make_world(params="hummingbird", hz=100.0)
    world.reset(position=world.scene.spawn_position + [0.0, 0.0, 0.5], airborne=False)
    uav.s[STATE.q] = quat_multiply(uav.s[STATE.q], quat_from_euler(math.pi, 0.0, 0.0))
    world.run(4.0)
    st = uav.state
    assert tilt_deg(st.quaternion) > 179.0
    # the hubs' legs compress as the feet do, so the origin (in the hub plane) rests that deep
    assert st.position[2] == pytest.approx(-uav.contact.foot_depth, abs=1e-3)
    np.testing.assert_allclose(uav.specific_force, [0.0, 0.0, -G], atol=0.01)  # the ground pushes "down"


def test_resting_vehicle_with_motors_off_is_exactly_still():
    """Spawned on the ground, the legs carry exactly the weight: nothing moves, and the
    accelerometer reads the contact force, +9.81 up (PX4 FRD: -9.81 on z)."""
    world, uav = make_world(params="px4_quadx")
    world.reset(yaw=0.8)
    before = uav.s.copy()
    world.run(5.0)
    np.testing.assert_array_equal(uav.s, before)
    np.testing.assert_allclose(uav.specific_force, [0.0, 0.0, G], atol=1e-9)
    np.testing.assert_allclose(Truth.from_sim(uav).specific_force_frd, [0.0, 0.0, -G], atol=1e-9)
    np.testing.assert_allclose(uav.acceleration, 0.0, atol=1e-12)


# --------------------------------------------------------------------------- specific force
def test_specific_force_in_hover_and_in_free_fall():
    world, uav = make_world(params="hummingbird", hz=100.0)
    world.reset(position=world.scene.spawn_position + [0.0, 0.0, 15.0])
    world.run(2.0)
    np.testing.assert_allclose(uav.specific_force, [0.0, 0.0, G], atol=0.02)  # thrust carries the weight
    np.testing.assert_allclose(Truth.from_sim(uav).specific_force_frd, [0.0, 0.0, -G], atol=0.02)
    np.testing.assert_allclose(uav.acceleration, 0.0, atol=0.02)
    uav.motors_off()
    world.run(0.3)  # the rotors spin down within a few motor time constants (5 ms)
    for _ in range(50):
        world.step()
        st = uav.state
        # only the body drag acts: c_Dz v|v| / m along body z against the fall, nothing sideways
        drag = uav.quad_params["c_Dz"] * st.velocity[2] ** 2 / uav.quad_params["mass"]
        assert uav.specific_force[2] == pytest.approx(drag, rel=0.05, abs=1e-3)
        np.testing.assert_allclose(uav.specific_force[:2], 0.0, atol=1e-9)
        assert uav.acceleration[2] == pytest.approx(-G + drag, abs=0.02)
    assert 0.3 < drag < 3.0  # the fall is fast enough for the drag to show


def test_specific_force_mean_matches_the_velocity_change_over_each_period():
    """Through a touchdown the period-mean specific force is the velocity change over the period plus
    gravity: the contact force, averaged as an IMU's output filter would, not a one-step spike."""
    world, uav = make_world(params="hummingbird", hz=100.0)
    world.reset(position=world.scene.spawn_position + [0.0, 0.0, drop_height(uav, 1.0)], airborne=False)
    dt = world.control_period_ns / 1e9
    for _ in range(200):
        v0 = uav.state.velocity
        world.step()
        st = uav.state
        # level throughout: body z is world z, so f_z = dv_z/dt + g over the period
        assert uav.specific_force[2] == pytest.approx((st.velocity[2] - v0[2]) / dt + G, abs=1e-6)


# --------------------------------------------------------------------------- impact events
def test_impact_event_above_the_threshold_and_none_below():
    world, uav = make_world(params="hummingbird", hz=100.0)
    spawn = world.scene.spawn_position
    events = []
    world.reset(position=spawn + [0.0, 0.0, drop_height(uav, 1.3)], airborne=False)
    world.run_until(lambda w: False, 1.5, events)
    assert events == []
    world.reset(position=spawn + [0.0, 0.0, drop_height(uav, 1.8)], airborne=False)
    world.run_until(lambda w: False, 1.5, events)
    assert [e.type for e in events] == ["impact"]
    e = events[0].to_dict()
    assert e["speed"] == pytest.approx(1.8, abs=0.03)
    assert e["t"] == pytest.approx(1.8 / G, abs=0.015)  # the fall time
    np.testing.assert_allclose(e["position"], spawn + [0, 0, uav.contact.foot_depth], atol=0.02)
    raised, raised_uav = make_world(params="hummingbird", hz=100.0, impact_speed=2.0)
    raised.reset(position=spawn + [0.0, 0.0, drop_height(raised_uav, 1.8)], airborne=False)
    assert not raised.run_until(lambda w: False, 1.5, events) and len(events) == 1


def test_impact_event_under_external_rotor_commands():
    """Any mode: an autopilot cutting the motors in flight (the PX4 restart case) raises it too."""
    world, uav = make_world(params="px4_quadx")
    world.reset(position=world.scene.spawn_position + [0.0, 0.0, 4.0])
    uav.set_rotor_speeds([0.0] * 4)
    events = []
    world.run_until(lambda w: False, 2.0, events)
    assert [e.type for e in events] == ["impact"] and events[0].data["speed"] > 8.0


def test_landing_on_a_rock_gives_one_collision_and_no_launch():
    """tree_inspection's clearing has rocks in the collision model (SDF): landing onto one stops
    the vehicle against it once; it stays there, held, not thrown up."""
    world, uav = make_world(params="hummingbird", hz=100.0, scene="tree_inspection")
    col = world.scene.collision
    ring = [
        np.array([r * math.cos(a), r * math.sin(a), 0.05])
        for r in np.arange(8.4, 11.9, 0.1)
        for a in np.arange(0.0, 2 * math.pi, 0.1 / r)
    ]
    rock = min(ring, key=col.distance)
    assert col.distance(rock) < -0.05  # inside a rock
    world.reset(position=[rock[0], rock[1], 2.0])
    world.run(1.0)
    events = []
    uav.land()
    assert world.run_until(lambda w: uav.mode.value == "collided", 15, events)
    world.run_until(lambda w: False, 3.0, events)
    assert [e.type for e in events] == ["collision"]
    st = uav.state
    assert st.position[2] > 0.2 and col.distance(st.position) >= world.config.vehicle.collision_radius
    stopped = st.position.copy()
    world.run(2.0)
    np.testing.assert_array_equal(uav.state.position, stopped)
    np.testing.assert_allclose(uav.specific_force, [0.0, 0.0, G], atol=1e-9)  # held by the rock


# --------------------------------------------------------------------------- IMU saturation
def test_imu_saturates_at_16g_and_2000dps_after_noise():
    cfg = PX4Config(accel_noise=0.5, gyro_noise=0.1)
    imu = Imu(cfg, np.random.default_rng(0))
    assert imu.accel_range == pytest.approx(16 * 9.80665)
    assert imu.gyro_range == pytest.approx(math.radians(2000))
    z3 = np.zeros(3)
    level = np.array([0.0, 0.0, 0.0, 1.0])
    hard = Truth(0, z3, z3, level, np.array([50.0, -1.0, 0.0]), z3, z3, np.array([-300.0, 20.0, 160.0]))
    accels, gyros = zip(*(imu.sample(hard) for _ in range(200)), strict=True)
    accels, gyros = np.array(accels), np.array(gyros)
    # FRD: x stays, y and z flip. Saturated axes sit at the rail; the others keep their noise.
    np.testing.assert_array_equal(accels[:, 0], -imu.accel_range)
    np.testing.assert_array_equal(accels[:, 2], -imu.accel_range)
    assert np.std(accels[:, 1]) == pytest.approx(0.5, rel=0.2)
    assert np.mean(accels[:, 1]) == pytest.approx(-20, abs=0.2)
    np.testing.assert_array_equal(gyros[:, 0], imu.gyro_range)
    assert np.std(gyros[:, 1]) == pytest.approx(0.1, rel=0.2)
    assert np.mean(gyros[:, 1]) == pytest.approx(1.0, abs=0.05)
    # just under the rail, noise pushes some samples onto it and none beyond
    near = Truth(0, z3, z3, level, z3, z3, z3, np.array([0.0, 0.0, imu.accel_range - 0.3]))
    z = np.array([imu.sample(near)[0][2] for _ in range(400)])
    assert z.min() == -imu.accel_range and np.mean(z == -imu.accel_range) > 0.2


def test_imu_ranges_are_configurable_and_checked():
    cfg = PX4Config(accel_noise=0.0, gyro_noise=0.0)
    imu = Imu(cfg, np.random.default_rng(0), accel_range_g=8.0, gyro_range_dps=500.0)
    z3 = np.zeros(3)
    level, up = np.array([0, 0, 0, 1.0]), np.array([0.0, 0.0, 1.0])
    accel, gyro = imu.sample(Truth(0, z3, z3, level, 20.0 * up, z3, z3, 100.0 * up))
    np.testing.assert_allclose(accel, [0.0, 0.0, -8 * G0])
    np.testing.assert_allclose(gyro, [0.0, 0.0, -math.radians(500)])
    with pytest.raises(ValueError, match="accel_range_g"):
        Imu(cfg, np.random.default_rng(0), accel_range_g=0.0)
    with pytest.raises(ValueError, match="gyro_range_dps"):
        Imu(cfg, np.random.default_rng(0), gyro_range_dps=float("nan"))


# --------------------------------------------------------------------------- configuration
def test_contact_parameters_come_from_the_config_and_bad_values_are_refused():
    _, uav = make_world(params="hummingbird", hz=100.0, contact_frequency_hz=5.0, ground_friction=0.8)
    assert uav.contact == dataclasses.replace(GroundContact(), frequency_hz=5.0, friction=0.8)
    assert uav.contact.foot_depth == pytest.approx(G / (2 * math.pi * 5.0) ** 2)
    for key, value in [
        ("contact_frequency_hz", 0),
        ("contact_damping_ratio", -1),
        ("friction_slip_speed", 0),
        ("impact_speed", float("nan")),
        ("ground_friction", -0.1),
    ]:
        with pytest.raises(ValueError, match=f"vehicle.{key}"):
            load_config(overrides=[f"vehicle.{key}={value}"])
    with pytest.raises(ValueError, match="frequency_hz"):
        GroundContact(frequency_hz=-3.0)
