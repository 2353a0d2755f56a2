"""Workflow 3 for many vehicles: the PettingZoo parallel environment over the vineyard task."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test, parallel_seed_test

from droneulator.workflows.rl.env import VineyardNavEnv
from droneulator.workflows.rl.multi import VineyardNavParallelEnv

# the middle alley (y = 0): uav0 at x = -4 facing +x, uav1 at x = +4 facing -x, 8 m apart head on
FACING = {
    "uav0": {"start": (-4.0, 0.0, 0.0), "goal": (12.0, 0.0)},
    "uav1": {"start": (4.0, 0.0, math.pi), "goal": (-12.0, 0.0)},
}
CENTRE = slice(14, 18)  # the strip's four middle sectors: straight ahead


@pytest.fixture(scope="module")
def env():
    e = VineyardNavParallelEnv()
    yield e
    e.close()


def wiggle(k: int, agent: int = 0) -> np.ndarray:
    """A fixed, varied action sequence (float32, like the action space's samples)."""
    return np.array([math.sin(0.3 * k + agent), math.cos(0.2 * k - agent)], dtype=np.float32)


def test_pettingzoo_api_and_seed_tests_pass():
    # time limits of 17..29 steps (0.5 s plus d0 / 100 m/s): the agents leave one by one within the cycles
    kw = {"time_limit_base_s": 0.5, "min_average_speed": 100.0}
    e = VineyardNavParallelEnv(**kw)
    try:
        assert e.metadata == {"name": "droneulator_vineyard_nav_v0", "render_modes": []}
        assert e.possible_agents == ["uav0", "uav1"] and e.max_num_agents == 2
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # the API test only warns about keys for live and dead agents
            parallel_api_test(e, num_cycles=40)
        assert e.agents == []  # every episode ended (time limit or crash) within the cycles
    finally:
        e.close()
    parallel_seed_test(lambda: VineyardNavParallelEnv(**kw), num_cycles=5)


def test_seeding_reproduces_tasks_and_episodes_and_agents_start_and_aim_apart(env):
    def episode(seed: int) -> tuple[dict, list[dict], list[dict]]:
        obs, _ = env.reset(seed=seed)
        tasks = {a: (env.tasks[a].start.copy(), env.tasks[a].goal.copy()) for a in env.possible_agents}
        trace, rewards = [obs], []
        for k in range(30):
            actions = {a: wiggle(k, i) for i, a in enumerate(env.possible_agents) if a in env.agents}
            obs, reward, *_ = env.step(actions)
            trace.append(obs)
            rewards.append(reward)
            if not env.agents:
                break
        return tasks, trace, rewards

    a, b, c = episode(21), episode(21), episode(22)
    for agent in env.possible_agents:
        np.testing.assert_array_equal(a[0][agent][0], b[0][agent][0])
        np.testing.assert_array_equal(a[0][agent][1], b[0][agent][1])
        assert not np.array_equal(a[0][agent][1], c[0][agent][1])
    assert len(a[1]) == len(b[1]) and a[2] == b[2]
    for x, y in zip(a[1], b[1], strict=True):
        assert x.keys() == y.keys()
        for agent in x:
            np.testing.assert_array_equal(x[agent], y[agent])
    for seed in range(8):
        env.reset(seed=seed)
        (s0, g0), (s1, g1) = ((env.tasks[n].start[:2], env.tasks[n].goal) for n in env.possible_agents)
        assert math.dist(s0, s1) >= env.min_spacing and math.dist(g0, g1) >= env.min_spacing


def test_one_agent_is_the_single_agent_env():
    single, multi = VineyardNavEnv(), VineyardNavParallelEnv(num_agents=1)
    try:
        assert multi.possible_agents == ["uav0"]
        assert multi.observation_space("uav0") == single.observation_space
        assert multi.action_space("uav0") == single.action_space
        assert multi.observation_space("uav0") is multi.observation_space("uav0")
        for seed in (3, 8):
            obs_s, info_s = single.reset(seed=seed)
            obs_m, info_m = multi.reset(seed=seed)
            np.testing.assert_array_equal(multi.tasks["uav0"].start, single.start)
            np.testing.assert_array_equal(multi.tasks["uav0"].goal, single.goal)
            np.testing.assert_allclose(obs_m["uav0"], obs_s, atol=1e-6)
            assert info_m["uav0"]["distance"] == pytest.approx(info_s["distance"])
            for k in range(45):
                obs_s, r_s, term_s, trunc_s, info_s = single.step(wiggle(k))
                obs_m, r_m, term_m, trunc_m, info_m = multi.step({"uav0": wiggle(k)})
                np.testing.assert_allclose(obs_m["uav0"], obs_s, atol=1e-6)
                assert r_m["uav0"] == pytest.approx(r_s, abs=1e-9)
                assert (term_m["uav0"], trunc_m["uav0"]) == (term_s, trunc_s)
                np.testing.assert_allclose(info_m["uav0"]["position"], info_s["position"], atol=1e-9)
                if term_s or trunc_s:
                    assert multi.agents == []
                    break
    finally:
        single.close()
        multi.close()


def test_agents_see_each_other_and_flying_into_each_other_ends_both_with_the_penalty(env):
    obs, _ = env.reset(options={"tasks": FACING})
    for agent in env.possible_agents:
        # the other vehicle 8 m ahead, its near side a bit closer; alone, nothing within 10 m ahead
        assert 0.7 < obs[agent][CENTRE].min() < 0.8
    for _ in range(120):
        obs, reward, terminated, truncated, info = env.step({a: np.array([1.0, 0.0]) for a in env.agents})
        if not env.agents:
            break
    assert terminated == {"uav0": True, "uav1": True} and truncated == {"uav0": False, "uav1": False}
    for agent, other in (("uav0", "uav1"), ("uav1", "uav0")):
        assert info[agent]["termination"] == "collision" and info[agent]["collided_with"] == [other]
        assert -31.0 < reward[agent] < -29.0
        assert abs(info[agent]["position"][0]) < 0.5  # they met in the middle
    # both left the world: not flown, touched or seen, rotors stopped
    assert not env.world.active[0].any() and not env.world.states[0, :, 16:20].any()
    with pytest.raises(RuntimeError, match="reset"):
        env.step({})


def test_a_done_agent_leaves_the_world_and_the_others_fly_on(env):
    tasks = {"uav0": {"start": (0.0, 0.0, 0.0), "goal": (2.2, 0.0)}, "uav1": FACING["uav0"]}
    obs, _ = env.reset(options={"tasks": tasks})
    assert obs["uav1"][CENTRE].min() < 0.45  # uav0, 4 m ahead of it
    with pytest.raises(ValueError, match="missing"):
        env.step({"uav0": np.zeros(2)})
    hover = env.tasks["uav1"].command_to_action(0.0, 0.0)
    for _ in range(60):
        obs, reward, terminated, _, info = env.step({"uav0": np.array([0.2, 0.0]), "uav1": hover})
        if "uav0" not in env.agents:
            break
    assert terminated["uav0"] and info["uav0"]["termination"] == "goal" and 100.0 < reward["uav0"] < 101.0
    assert env.agents == ["uav1"] and not terminated["uav1"]
    obs, *_ = env.step({"uav0": np.zeros(2), "uav1": hover})  # a done agent's action is ignored
    assert list(obs) == ["uav1"]
    assert obs["uav1"][CENTRE].min() > 0.95  # uav0 gone from the alley ahead: nothing within 9.5 m
    assert not env.world.active[0, 0] and env.world.active[0, 1]
    with pytest.raises(ValueError, match="unknown agents"):
        env.reset(options={"tasks": {"uav7": FACING["uav0"]}})
