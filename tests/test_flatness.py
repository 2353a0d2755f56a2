"""Thrust and body rates from a flat reference (droneulator/controllers/flatness.py) against the flatness
maths: hover, a circle flown at a constant yaw rate (closed form), the attitude's own derivative along a
generic reference, and the CTBR tracker on its reference and in flight."""

from __future__ import annotations

import math

import numpy as np

from droneulator.config import load_config
from droneulator.controllers.flatness import CTBRTracker, flat_attitude, flat_ctbr
from droneulator.frames import matrix_to_quat, quat_from_yaw, quat_to_matrix
from droneulator.state import STATE
from droneulator.vehicles.dynamics import GRAVITY
from droneulator.world import World

MASS = 0.5


def test_hover_is_the_weight_and_no_rotation():
    for yaw in (0.0, 1.0, -2.5):
        ff = flat_ctbr(MASS, np.zeros(3), np.zeros(3), yaw, 0.0)
        assert ff.thrust == MASS * GRAVITY
        np.testing.assert_allclose(ff.body_rates, 0.0, atol=1e-15)
        np.testing.assert_allclose(ff.rotation, quat_to_matrix(quat_from_yaw(yaw)), atol=1e-15)
        # a pirouette in hover: only the body z rate
        spun = flat_ctbr(MASS, np.zeros(3), np.zeros(3), yaw, 1.5)
        np.testing.assert_allclose(spun.body_rates, [0.0, 0.0, 1.5], atol=1e-15)


def test_a_circle_at_the_yaw_rate_of_its_turn_has_the_closed_form_rates():
    """Radius rho at angular speed W, the heading turning with it (yaw = W t): the attitude is a fixed
    tilt turned about world z at W, so the body rates are W R^T e_z; at t = 0 (heading x, the centre at -x)
    the tilt is a pitch of theta = atan(rho W^2 / g): rates W (sin theta, 0, cos theta), thrust
    m sqrt((rho W^2)^2 + g^2)."""
    rho, w = 2.0, 3.0
    theta = math.atan2(rho * w * w, GRAVITY)
    for t in (0.0, 0.4, 1.3):
        c, s = math.cos(w * t), math.sin(w * t)
        acc = -rho * w * w * np.array([c, s, 0.0])
        jerk = rho * w**3 * np.array([s, -c, 0.0])
        ff = flat_ctbr(MASS, acc, jerk, w * t, w)
        assert math.isclose(ff.thrust, MASS * math.hypot(rho * w * w, GRAVITY), rel_tol=1e-14)
        np.testing.assert_allclose(ff.body_rates, w * np.array([math.sin(theta), 0.0, math.cos(theta)]),
                                   atol=1e-12)  # fmt: skip
        np.testing.assert_allclose(ff.body_rates, w * ff.rotation.T @ [0.0, 0.0, 1.0], atol=1e-12)


def _generic(t: float) -> tuple[np.ndarray, np.ndarray, float, float]:
    """A smooth reference with every axis and the yaw moving: acceleration, jerk, yaw, yaw rate."""
    acc = np.array([-4.0 * math.sin(2 * t), -9.0 * math.cos(3 * t), -0.5 * math.sin(t)])
    jerk = np.array([-8.0 * math.cos(2 * t), 27.0 * math.sin(3 * t), -0.5 * math.cos(t)])
    return acc, jerk, 0.8 * math.sin(1.7 * t), 0.8 * 1.7 * math.cos(1.7 * t)


def test_the_body_rates_are_the_derivative_of_the_attitude():
    """Along a generic reference the body rates are vee(R^T dR/dt) of the flat attitude (central
    differences, h = 1e-5 s): the yaw rate formula is exact, not the small-tilt ``r = yaw_rate``."""
    h = 1e-5
    worst_r_approx = 0.0
    for t in np.linspace(0.0, 4.0, 17):
        acc, jerk, yaw, yaw_rate = _generic(t)
        ff = flat_ctbr(MASS, acc, jerk, yaw, yaw_rate)
        plus, minus = (
            flat_attitude(_generic(t + h)[0], _generic(t + h)[2]),
            flat_attitude(_generic(t - h)[0], _generic(t - h)[2]),
        )
        W = ff.rotation.T @ (plus - minus) / (2 * h)
        np.testing.assert_allclose(ff.body_rates, [W[2, 1], W[0, 2], W[1, 0]], atol=1e-6)
        np.testing.assert_allclose(W + W.T, 0.0, atol=1e-6)
        assert math.isclose(ff.thrust, MASS * float(np.linalg.norm(acc + [0, 0, GRAVITY])), rel_tol=1e-14)
        worst_r_approx = max(worst_r_approx, abs(ff.body_rates[2] - yaw_rate))
    assert worst_r_approx > 0.1  # the reference is tilted enough for the exact formula to matter


def test_the_tracker_on_its_reference_commands_the_feed_forward_and_clips_to_the_limits():
    acc, jerk, yaw, yaw_rate = _generic(0.7)
    ff = flat_ctbr(MASS, acc, jerk, yaw, yaw_rate)
    p, v = np.array([1.0, 2.0, 3.0]), np.array([0.5, -0.2, 0.1])
    tracker = CTBRTracker(MASS, max_thrust=50.0, max_rates=np.full(3, 20.0))
    thrust, rates = tracker.command(p, v, matrix_to_quat(ff.rotation), (p, v, acc, jerk, yaw, yaw_rate))
    assert math.isclose(thrust, ff.thrust, rel_tol=1e-12)
    np.testing.assert_allclose(rates, ff.body_rates, atol=1e-12)
    small = CTBRTracker(MASS, max_thrust=1.0, max_rates=np.full(3, 0.1))
    thrust, rates = small.command(p, v, matrix_to_quat(ff.rotation), (p, v, acc, jerk, yaw, yaw_rate))
    assert thrust == 1.0 and np.all(np.abs(rates) <= 0.1) and np.any(np.abs(rates) == 0.1)


def test_the_tracker_flies_a_circle_through_the_rates_command():
    """A 2 m circle at 1.5 rad/s (4.5 m/s^2), the heading turning with it, without drag (the model the
    feed-forward is exact for), flown through ``Vehicle.rates`` at 100 Hz: within 2 cm after one turn."""
    rho, w, z = 2.0, 1.5, 5.0
    with World(load_config(overrides=["vehicle.aero=false"]), scene="default", render=False) as world:
        world.reset(position=[rho, 0.0, z], yaw=math.pi / 2)
        uav = world.vehicle()
        uav.s[STATE.v] = [0.0, rho * w, 0.0]  # on the circle at its speed, level: the first period tilts it
        limits = uav.control_limits()
        tracker = CTBRTracker(MASS, limits["max_thrust"], np.array(limits["max_body_rate"]), k_att=20.0)
        errors = []
        for _ in range(round(2 * 2 * math.pi / w / 0.01)):
            t = world.t
            c, s = math.cos(w * t), math.sin(w * t)
            ref = (rho * np.array([c, s, 0.0]) + [0.0, 0.0, z], rho * w * np.array([-s, c, 0.0]),
                   -rho * w * w * np.array([c, s, 0.0]), rho * w**3 * np.array([s, -c, 0.0]),
                   w * t + math.pi / 2, w)  # fmt: skip
            uav.rates(*tracker.command(uav.s[STATE.x], uav.s[STATE.v], uav.s[STATE.q], ref))
            world.step()
            c, s = math.cos(w * world.t), math.sin(w * world.t)
            errors.append(float(np.linalg.norm(uav.s[STATE.x] - [rho * c, rho * s, z])))
        assert max(errors[len(errors) // 2 :]) < 0.02, max(errors)
        assert uav.mode.value == "rates"
