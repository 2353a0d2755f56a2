"""The compiled dynamics, controller and trajectory evaluation against RotorPy itself."""

import numpy as np
import pytest
from rotorpy.controllers.quadrotor_control import SE3Control
from rotorpy.trajectories.minsnap import MinSnap
from rotorpy.vehicles.multirotor import Multirotor

from droneulator.controllers.se3 import FastSE3Control
from droneulator.frames import yaw_of
from droneulator.state import pack_flat
from droneulator.trajectories.minsnap import PolyTrajectory, goto_trajectory, rest_to_rest
from droneulator.vehicles.dynamics import STATE, FastMultirotor, pack_state, state_derivative, unpack_state
from droneulator.vehicles.params import PARAMETER_SETS, get_params

rng = np.random.default_rng(1)


def random_state(hover: float) -> dict:
    """A random airborne state (on the ground the contact model departs from RotorPy's on purpose)."""
    q = rng.normal(size=4)
    return {
        "x": rng.normal(size=3) * [1, 1, 0.3] + [0, 0, 2],
        "v": rng.normal(size=3),
        "q": q / np.linalg.norm(q),
        "w": rng.normal(size=3),
        "wind": rng.normal(size=3),
        "rotor_speeds": hover + 100 * rng.normal(size=4),
    }


@pytest.mark.parametrize("name", list(PARAMETER_SETS))
@pytest.mark.parametrize("aero", [True, False])
def test_state_derivative_equals_rotorpy(name, aero):
    qp = get_params(name)
    ref = Multirotor(qp, aero=aero, enable_ground=True)
    fast = FastMultirotor(qp, aero=aero)
    for _ in range(20):
        st = random_state(fast.hover_speed)
        cmd = fast.hover_speed + 200 * rng.normal(size=4)
        expect = ref._s_dot_fn(0.0, Multirotor._pack_state(st), cmd)
        got = state_derivative(pack_state(st), cmd, fast.params, fast.geometry, fast.directions)
        np.testing.assert_allclose(got, expect, rtol=1e-9, atol=1e-9)


def test_contact_forces_vanish_above_the_ground():
    """Feet 0.1 mm above the ground: no contact force at all (the derivative is the ground-free
    model's bit for bit, and RotorPy's); 1 mm below: the legs push and friction acts."""
    qp = get_params("hummingbird")
    ref = Multirotor(qp, enable_ground=True)
    fast, free = FastMultirotor(qp), FastMultirotor(qp, enable_ground=False)
    depth = fast.contact.foot_depth
    st = {
        "x": np.array([0.0, 0.0, depth + 1e-4]),
        "v": np.array([0.3, 0.0, -0.5]),
        "q": np.array([0, 0, 0, 1.0]),
        "w": np.zeros(3),
        "wind": np.zeros(3),
        "rotor_speeds": np.full(4, 300.0),
    }  # thrust below weight, descending
    got = state_derivative(pack_state(st), np.zeros(4), fast.params, fast.geometry, fast.directions)
    np.testing.assert_array_equal(
        got, state_derivative(pack_state(st), np.zeros(4), free.params, free.geometry, free.directions)
    )
    np.testing.assert_allclose(got, ref._s_dot_fn(0, Multirotor._pack_state(st), np.zeros(4)), atol=1e-12)
    assert got[5] < -5.0  # falling
    st["x"][2] = depth - 1e-3
    below = state_derivative(pack_state(st), np.zeros(4), fast.params, fast.geometry, fast.directions)
    # four legs of stiffness m w^2 / 4 compressed 1 mm, plus the compression damping against 0.5 m/s
    w = 2 * np.pi * fast.contact.frequency_hz
    push = w**2 * 1e-3 + 2 * fast.contact.damping_ratio * w * 0.5
    assert below[5] - got[5] == pytest.approx(push, rel=1e-9)
    assert below[3] - got[3] < 0  # friction opposes the sliding


@pytest.mark.parametrize("name", ["hummingbird", "crazyflie", "crazyflie_brushless", "px4_quadx"])
def test_se3_controller_equals_rotorpy(name):
    qp = get_params(name)
    ref, fast = SE3Control(qp), FastSE3Control(qp)
    # the gains and allocation it computes itself (without importing RotorPy's controller) are RotorPy's
    assert (fast.mass, fast.kp_att, fast.kd_att, fast.k_eta) == (ref.mass, ref.kp_att, ref.kd_att, ref.k_eta)
    for mine, theirs in ((fast.inertia, ref.inertia), (fast.kp_pos, ref.kp_pos), (fast.kd_pos, ref.kd_pos)):
        np.testing.assert_array_equal(mine, theirs)
    np.testing.assert_allclose(fast.TM_to_f, ref.TM_to_f, rtol=1e-15, atol=0)
    traj = MinSnap(
        np.array([[0, 0, 1.0], [2, 1, 2.0], [3, -1, 1.5]]),
        yaw_angles=np.array([0, 1.0, -0.5]),
        v_avg=1.0,
        verbose=False,
    )
    for _ in range(50):
        st = random_state(1000.0)
        fo = traj.update(rng.uniform(0, 6))
        np.testing.assert_allclose(
            fast.motor_speeds(pack_state(st), pack_flat(fo)),
            ref.update(0.0, st, fo)["cmd_motor_speeds"],
            rtol=1e-10,
            atol=1e-8,
        )


def test_poly_trajectory_equals_minsnap_update():
    ms = MinSnap(
        np.array([[0, 0, 1.0], [3, 2, 2.5], [5, -1, 1.5]]),
        yaw_angles=np.array([0, 1.0, -0.5]),
        v_avg=1.5,
        verbose=False,
    )
    pt = PolyTrajectory(ms.x_poly, ms.yaw_poly, ms.t_keyframes)
    for t in np.linspace(-1, ms.t_keyframes[-1] + 1, 101):
        fo, got = ms.update(t), pt.flat(t)
        np.testing.assert_allclose(got, pack_flat(fo), atol=1e-9)


def test_rest_to_rest_boundary_conditions():
    tr = rest_to_rest(np.array([0.0, 0, 1]), np.array([0.05, 0, 1]), 0.0, 1.0, 2.0)
    start, end, mid = tr.flat(0).copy(), tr.flat(2.0).copy(), tr.flat(1.0).copy()
    np.testing.assert_allclose(start[[0, 3, 6, 9, 10]], [0, 0, 0, 0, 0], atol=1e-12)
    np.testing.assert_allclose(end[[0, 3, 6, 9, 10]], [0.05, 0, 0, 1.0, 0], atol=1e-12)
    assert np.isclose(mid[3], 35 / 16 * 0.05 / 2.0)  # peak speed of the 7th-order profile


def test_goto_trajectory_peak_speed_and_short_yaw():
    tr = goto_trajectory(np.zeros(3), np.zeros(3), 3.0, np.array([4.0, 0, 0]), -3.0, speed=2.0)
    speeds = [np.linalg.norm(tr.flat(t)[3:6]) for t in np.linspace(0, tr.duration, 201)]
    assert max(speeds) == pytest.approx(2.0, rel=0.02)
    assert tr.flat(tr.duration)[9] == pytest.approx(3.0 + (2 * np.pi - 6.0))  # the short way round


@pytest.mark.parametrize("max_tilt_deg", [None, 45.0])
def test_closed_loop_matches_rotorpy_integration_within_1cm(max_tilt_deg):
    """10 s of min-snap tracking: compiled RK4 vs RotorPy's solve_ivp loop, same controller (with the
    default thrust bounds too: a flyable trajectory never reaches them)."""
    qp = get_params("hummingbird")
    traj = MinSnap(
        np.array([[0, 0, 1.0], [3, 2, 2.5], [5, -1, 1.5], [1, 1, 1]]),
        yaw_angles=np.array([0, 1.0, -0.5, 0.3]),
        v_avg=1.5,
        verbose=False,
    )
    init = {
        "x": np.array([0, 0, 1.0]),
        "v": np.zeros(3),
        "q": np.array([0, 0, 0, 1.0]),
        "w": np.zeros(3),
        "wind": np.zeros(3),
        "rotor_speeds": np.full(4, 1788.53),
    }
    ref_v, ref_c = Multirotor(qp, initial_state=init, enable_ground=True), SE3Control(qp)
    fast_v, fast_c = FastMultirotor(qp, substep=1e-3), FastSE3Control(qp, max_tilt_deg, 0.2)
    st, s = {k: v.copy() for k, v in init.items()}, pack_state(init)
    err = []
    for i in range(1000):
        fo = traj.update(i * 0.01)
        st = ref_v.step(st, ref_c.update(i * 0.01, st, fo), 0.01)
        assert not fast_v.step(s, fast_c.motor_speeds(s, pack_flat(fo)), 0.01)
        err.append(np.linalg.norm(st["x"] - s[STATE.x]))
    assert max(err) < 0.01
    assert np.linalg.norm(unpack_state(s)["x"] - traj.update(10.0)["x"]) < 0.1  # it really flew the path


def _hover_at_10m(vehicle: FastMultirotor, v: np.ndarray) -> np.ndarray:
    """Packed state: level at 10 m, moving at ``v``, rotors at hover speed."""
    state = {"x": np.array([0, 0, 10.0]), "v": v, "q": np.array([0, 0, 0, 1.0]), "w": np.zeros(3)}
    return pack_state({**state, "wind": np.zeros(3), "rotor_speeds": np.full(4, vehicle.hover_speed)})


def _worst_reference_steps(ctrl: FastSE3Control, trials: int = 150) -> tuple[float, float]:
    """Largest tilt (degrees) and altitude lost below the lower of start and reference (m) over random
    reference jumps: 3 m sideways and 1.5 m up or down (1 sigma), random velocities and headings."""
    qp = get_params("hummingbird")
    vehicle, rs = FastMultirotor(qp, enable_ground=False), np.random.default_rng(7)
    lo, hi = qp["rotor_speed_min"], qp["rotor_speed_max"]
    tilt, drop = 0.0, 0.0
    for _ in range(trials):
        s = _hover_at_10m(vehicle, rs.normal(size=3) * 2)
        flat = np.zeros(11)
        flat[0:3] = [0, 0, 10.0] + rs.normal(size=3) * [3, 3, 1.5]
        flat[3:6] = rs.normal(size=3)
        flat[9] = rs.uniform(-np.pi, np.pi)
        for _ in range(300):
            vehicle.step(s, np.clip(ctrl.motor_speeds(s, flat), lo, hi), 0.01)
            x, y = s[STATE.q][0], s[STATE.q][1]
            tilt = max(tilt, np.degrees(np.arccos(np.clip(1 - 2 * (x * x + y * y), -1, 1))))
            drop = max(drop, min(flat[2], 10.0) - s[STATE.x][2])
    return tilt, drop


def test_thrust_bounds_keep_the_vehicle_upright_when_the_reference_jumps():
    """RotorPy's SE(3) controller asks for any force the position error gives: a reference metres away
    and below tips the vehicle past 90 degrees, and it flies itself metres down (the planning
    benchmark saw an 8 m/s impact after an emergency stop). With PX4-like bounds (tilt <= 45 degrees,
    lift >= 0.2 g) no jump turns it over and none costs more than a few metres of overshoot."""
    qp = get_params("hummingbird")
    tilt, drop = _worst_reference_steps(FastSE3Control(qp))
    assert tilt > 120 and drop > 5  # the case this is about
    tilt, drop = _worst_reference_steps(FastSE3Control(qp, max_tilt_deg=45.0, min_lift=0.2))
    assert tilt < 80 and drop < 3
    with pytest.raises(ValueError, match="max_tilt_deg"):
        FastSE3Control(qp, max_tilt_deg=90.0)


def _altitude_range_after_a_yaw_step(ctrl: FastSE3Control, step: float = 2.0) -> tuple[float, float]:
    """Altitude range (m) over 4 s of hovering at 10 m after the yaw reference jumps by ``step`` rad,
    and the heading error at the end (rad)."""
    qp = get_params("hummingbird")
    vehicle = FastMultirotor(qp, enable_ground=False)
    lo, hi = qp["rotor_speed_min"], qp["rotor_speed_max"]
    s = _hover_at_10m(vehicle, np.zeros(3))
    flat, z = np.zeros(11), []
    flat[2], flat[9] = 10.0, step
    for _ in range(400):
        vehicle.step(s, np.clip(ctrl.motor_speeds(s, flat), lo, hi), 0.01)
        z.append(s[STATE.x][2])
    return float(np.ptp(z)), abs(float(np.remainder(yaw_of(s[STATE.q]) - step + np.pi, 2 * np.pi) - np.pi))


def test_yaw_gives_way_to_thrust_when_a_rotor_saturates():
    """Told to face 2 rad away, RotorPy's controller asks two rotors for negative thrust; clipped, the
    others' extra thrust lifts the vehicle (0.7 m here; the planning benchmark's vehicle rose from 2.5
    to 3.5 m at its goal, above the planner's ceiling). The bounded controller scales the yaw moment down
    first, as PX4's mixer does: the altitude holds and the turn is still made."""
    qp = get_params("hummingbird")
    assert _altitude_range_after_a_yaw_step(FastSE3Control(qp))[0] > 0.5  # the case this is about
    rise, heading = _altitude_range_after_a_yaw_step(FastSE3Control(qp, max_tilt_deg=45.0, min_lift=0.2))
    assert rise < 0.05 and heading < 0.02


def test_motors_off_rests_on_ground():
    """Dropped from 1 m with the motors off: the legs stop it within a few cm, it settles level at
    z = 0 (the legs carry exactly the weight there) and does not move afterwards."""
    qp = get_params("hummingbird")
    fast = FastMultirotor(qp)
    s = pack_state(
        {
            "x": np.array([0, 0, 1.0]),
            "v": np.zeros(3),
            "q": np.array([0, 0, 0, 1.0]),
            "w": np.zeros(3),
            "rotor_speeds": np.zeros(4),
        }
    )
    zs = []
    for _ in range(300):
        fast.step(s, np.zeros(4), 0.01)
        zs.append(s[2])
    assert -0.06 < min(zs) < -0.02  # the legs compress a few cm under a 4.4 m/s touchdown
    assert max(zs[zs.index(min(zs)) :]) <= 1e-4  # and never throw it back up
    assert abs(s[STATE.x][2]) < 1e-4 and np.allclose(s[STATE.v], 0.0, atol=1e-4)
    rest = s.copy()
    for _ in range(100):
        fast.step(s, np.zeros(4), 0.01)
    np.testing.assert_array_equal(s[STATE.x][:2], rest[STATE.x][:2])  # no sliding
    assert abs(s[STATE.x][2]) <= abs(rest[STATE.x][2])  # no sinking: the last 0.02 mm creep back
    np.testing.assert_allclose(s[STATE.q], [0, 0, 0, 1.0], atol=1e-9)
