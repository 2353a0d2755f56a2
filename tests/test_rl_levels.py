"""The vineyard envs at every control level (``rl.action``): the checkers, a neutral action hovers, an
action moves what it names, the vector env is its single envs, a bad level is a clear error."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from pettingzoo.test import parallel_api_test

from droneulator.config import load_config
from droneulator.workflows.rl.env import VineyardNavEnv
from droneulator.workflows.rl.levels import Actuator
from droneulator.workflows.rl.multi import VineyardMultiVectorEnv, VineyardNavParallelEnv
from droneulator.workflows.rl.vector import VineyardNavVectorEnv

LEVELS = ("ctbr", "attitude", "rotors")
ALLEY = {"start": (-8.0, 0.0, 0.0), "goal": (8.0, 0.0)}  # the middle alley, facing +x along it
#: where the levels' observation holds the body rates and gravity's direction in the body frame
RATES, GRAVITY = slice(35, 38), slice(38, 41)


@pytest.fixture(scope="module", params=LEVELS)
def env(request):
    e = VineyardNavEnv(depth="raycast", action=request.param)
    yield e
    e.close()


def test_the_gymnasium_and_sb3_checkers_pass_and_the_spaces_fit_the_level(env):
    assert env.action_space.shape == (4,) and env.observation_space.shape == (44,)
    check_env(env, skip_render_check=True)
    sb3_checker = pytest.importorskip("stable_baselines3.common.env_checker")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # SB3 only warns about what it finds wrong
        sb3_checker.check_env(env, warn=True)


def test_a_neutral_action_hovers_for_a_second(env):
    obs, info = env.reset(options=ALLEY)
    z0 = info["position"][2]
    for _ in range(30):  # one second at the 30 Hz camera
        obs, _, terminated, truncated, info = env.step(np.zeros(4, dtype=np.float32))
        assert not (terminated or truncated)
    assert abs(info["position"][2] - z0) < 0.02
    np.testing.assert_allclose(obs[RATES], 0.0, atol=0.01)
    np.testing.assert_allclose(obs[GRAVITY], [0.0, 0.0, -1.0], atol=0.01)
    command = np.array(info["command"])
    vehicle = env.backend.vehicle
    if env.rl.action == "rotors":
        np.testing.assert_allclose(command, vehicle.hover_speed, rtol=1e-12)
    else:
        assert command[0] == pytest.approx(vehicle.quad_params["mass"] * 9.81, rel=1e-12)


@pytest.mark.parametrize("level", ["ctbr", "attitude"])
def test_a_positive_roll_action_rolls_the_vehicle_positive(level):
    env = VineyardNavEnv(depth="raycast", action=level)
    try:
        env.reset(options=ALLEY)
        action = np.array([0.0, 0.2, 0.0, 0.0], dtype=np.float32)
        rates = [env.step(action)[0][RATES][0] for _ in range(4)]
        obs, *_ = env.step(action)
    finally:
        env.close()
    if level == "ctbr":  # 0.2 of 720 deg/s: 2.5 rad/s, which the observation reads as 0.2
        assert min(rates) > 0.05 and rates[-1] == pytest.approx(0.2, abs=0.03)
    # rolled right side down (about body x, positive): gravity leans toward body -y
    assert obs[GRAVITY][1] < -0.05


@pytest.mark.parametrize("level", LEVELS)
def test_the_vector_env_is_its_single_envs(level):
    n, steps = 3, 30
    actions = np.random.default_rng(3).uniform(-0.05, 0.05, (steps, n, 4)).astype(np.float32)
    venv = VineyardNavVectorEnv(n, action=level)
    try:
        obs, info = venv.reset(seed=20)
        vec = [(obs, info["position"], np.zeros(n))]
        for a in actions:
            obs, reward, term, trunc, info = venv.step(a)
            vec.append((obs, info["position"], reward))
    finally:
        venv.close()
    env = VineyardNavEnv(depth="raycast", action=level)
    try:
        for i in range(n):
            obs, info = env.reset(seed=20 + i)
            one, done = [(obs, info["position"], 0.0)], False
            for a in actions[:, i]:  # as NEXT_STEP drives each env: after an end, a reset
                if done:
                    obs, info = env.reset()
                    one.append((obs, info["position"], 0.0))
                    done = False
                    continue
                obs, reward, term, trunc, info = env.step(a)
                one.append((obs, info["position"], reward))
                done = term or trunc
            for (vo, vp, vr), (so, sp, sr) in zip(vec, one, strict=True):
                np.testing.assert_allclose(vo[i], so, atol=1e-6, rtol=0)
                np.testing.assert_allclose(vp[i], sp, atol=1e-9, rtol=0)
                assert vr[i] == pytest.approx(sr, abs=1e-9)
    finally:
        env.close()


def test_the_multi_agent_envs_take_every_level():
    kw = {"time_limit_base_s": 0.5, "min_average_speed": 100.0}  # every agent leaves within the cycles
    for level in LEVELS:
        e = VineyardNavParallelEnv(depth="raycast", action=level, **kw)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("error")
                parallel_api_test(e, num_cycles=40)
        finally:
            e.close()
    core = VineyardMultiVectorEnv(2, 2, action="ctbr")
    try:
        obs, _ = core.reset(seed=1)
        z0 = core.world.states[..., 2].copy()
        for _ in range(15):
            obs, _, term, trunc, info = core.step(np.zeros((4, 4), dtype=np.float32))
        assert core.observation_space.contains(obs) and not (term | trunc).any()
        np.testing.assert_allclose(core.world.states[..., 2], z0, atol=0.02)
    finally:
        core.close()


def test_a_faster_camera_lets_the_policy_act_every_control_period():
    cfg = load_config(None, ["render.camera_hz=100"])
    env = VineyardNavEnv(cfg, depth="raycast", action="rotors")
    try:
        env.reset(options=ALLEY)
        _, _, _, _, info = env.step(np.zeros(4, dtype=np.float32))
    finally:
        env.close()
    assert info["t"] == pytest.approx(0.01, abs=1e-12)


def test_the_actions_span_the_airframe_or_the_rl_scale_within_it():
    weight = 0.5 * 9.81  # the Hummingbird: it lifts ten times that with every rotor at full speed
    full = Actuator(load_config(None, ["rl.action=ctbr"]), 1)
    command = full.map(np.array([0]), np.array([[1.0, 1.0, -1.0, 0.5]]))[0]
    assert command[0] == pytest.approx(full.airframe.max_thrust) and command[0] > 9.0 * weight
    np.testing.assert_allclose(command[1:], np.radians([720.0, -720.0, 270.0]), rtol=1e-12)
    scaled = Actuator(load_config(None, ["rl.action=ctbr", "rl.max_thrust_to_weight=2",
                                         "rl.max_body_rate_deg_s=[1000, 90, 90]"]), 1)  # fmt: skip
    command = scaled.map(np.array([0]), np.ones((1, 4)))[0]
    assert command[0] == pytest.approx(2.0 * weight, rel=1e-9)
    np.testing.assert_allclose(command[1:], np.radians([720.0, 90.0, 90.0]), rtol=1e-12)  # within flight's
    rotors = Actuator(load_config(None, ["rl.action=rotors", "rl.max_thrust_to_weight=2"]), 1)
    speeds = rotors.map(np.array([0]), np.ones((1, 4)))[0]
    np.testing.assert_allclose(rotors.airframe.k_eta * speeds**2, 0.5 * weight, rtol=1e-9)  # 2 x hover
    for bad in ("rl.max_thrust_to_weight=1", "rl.max_body_rate_deg_s=[90, 0, 90]"):
        with pytest.raises(ValueError, match=bad.split("=")[0]):
            load_config(None, [bad])


def test_a_bad_level_is_a_clear_config_error():
    message = "rl.action must be one of velocity, ctbr, attitude, rotors, got 'thrust'"
    with pytest.raises(ValueError, match=message):
        load_config(None, ["rl.action=thrust"])
    with pytest.raises(ValueError, match=message):
        VineyardNavVectorEnv(1, action="thrust")
