"""Workflow 3 for many vehicles: the PettingZoo parallel environment over the vineyard task."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test, parallel_seed_test

from droneulator.workflows.rl.env import VineyardNavEnv
from droneulator.workflows.rl.multi import VineyardMultiVectorEnv, VineyardNavParallelEnv

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


# ------------------------------------------------------------------ the vector form: W worlds x N agents
def _rollout(env, seed: int, actions: np.ndarray) -> dict[str, list[np.ndarray]]:
    out: dict[str, list[np.ndarray]] = {"obs": [env.reset(seed=seed)[0]], "reward": [], "terminated": [],
                                        "truncated": [], "position": []}  # fmt: skip
    for a in actions:
        obs, reward, terminated, truncated, info = env.step(a)
        for key, value in (("obs", obs), ("reward", reward), ("terminated", terminated),
                           ("truncated", truncated), ("position", info["position"])):  # fmt: skip
            out[key].append(value)
    return {key: np.array(value) for key, value in out.items()}


def test_each_world_of_the_vector_form_flies_as_that_world_alone():
    # short time limits: every agent's episode ends and restarts (and its world's rng draws again) meanwhile
    kw = {"time_limit_base_s": 0.5, "min_average_speed": 100.0}
    many = VineyardMultiVectorEnv(3, 2, **kw)
    alone = [VineyardMultiVectorEnv(1, 2, **kw) for _ in range(3)]
    try:
        assert many.num_envs == 6 and many.observation_space.shape == (6, 40)
        actions = np.random.default_rng(4).uniform(-1, 1, (70, 6, 2)).astype(np.float32)
        a = _rollout(many, 11, actions)
        assert a["terminated"].any() or a["truncated"].any()
        assert (a["truncated"].sum(axis=0) >= 1).all()  # every agent's episode ended at least once
        for w, env in enumerate(alone):
            b = _rollout(env, 11 + w, actions[:, 2 * w : 2 * w + 2])
            for key in a:
                mine = a[key][:, 2 * w : 2 * w + 2]
                np.testing.assert_array_equal(mine, b[key], err_msg=f"{key}, world {w}")
    finally:
        many.close()
        for env in alone:
            env.close()


def test_ray_cast_agents_see_each_other_as_the_renderer_draws_them():
    cast = VineyardMultiVectorEnv(1, 2, depth="raycast")
    drawn = VineyardMultiVectorEnv(1, 2, depth="render")
    try:
        a, _ = cast.reset(options={"tasks": FACING})
        b, _ = drawn.reset(options={"tasks": FACING})
        for row in range(2):  # the other vehicle 8 m ahead: a sphere of its radius against its mesh
            assert 0.7 < a[row, CENTRE].min() < 0.8
            assert abs(a[row, CENTRE].min() - b[row, CENTRE].min()) < 0.03
        np.testing.assert_allclose(a[:, 32:], b[:, 32:], atol=1e-6)
    finally:
        cast.close()
        drawn.close()


def test_agent_episodes_restart_one_agent_while_the_other_flies_on():
    env = VineyardMultiVectorEnv(1, 2)
    tasks = {"uav0": {"start": (0.0, 0.0, 0.0), "goal": (2.2, 0.0)}, "uav1": FACING["uav0"]}
    try:
        env.reset(seed=3, options={"tasks": tasks})
        slow = np.tile(env.tasks[0].command_to_action(0.5, 0.0), (2, 1))
        for _ in range(150):
            _, reward, terminated, _, info = env.step(slow)
            if terminated[0]:
                break
        assert terminated[0] and info["termination"][0] == "goal" and not terminated[1]
        before = info["position"][1].copy()
        obs, reward, terminated, truncated, info = env.step(slow)  # uav0 starts over: a new task
        assert reward[0] == 0.0 and not terminated[0] and not truncated[0]
        assert np.linalg.norm(info["position"][0][:2] - [2.2, 0.0]) > 1.0  # placed at a new start
        assert 0.0 < np.linalg.norm(info["position"][1] - before) < 0.2  # uav1 flew on, one frame
        assert reward[1] != 0.0 and info["t"][0] > 1.0  # the world's clock goes on
        assert math.dist(env.tasks[0].start[:2], info["position"][1][:2]) >= env.min_spacing
    finally:
        env.close()


def test_world_episodes_count_a_success_only_when_every_agent_reaches_its_goal():
    env = VineyardMultiVectorEnv(1, 2, episodes="world")
    both = {"uav0": {"start": (0.0, 0.0, 0.0), "goal": (2.2, 0.0)},
            "uav1": {"start": (-4.0, 0.0, 0.0), "goal": (-1.8, 0.0)}}  # fmt: skip

    def fly(tasks: dict, action: np.ndarray) -> tuple[bool, bool, list]:
        env.reset(seed=1, options={"tasks": tasks})
        reasons = []
        for _ in range(150):
            _, _, terminated, truncated, info = env.step(np.tile(action, (2, 1)))
            reasons += [r for r in info["termination"][terminated | truncated]]
            if info["world_over"][0]:
                return True, bool(info["world_success"][0]), reasons
        return False, False, reasons

    try:
        slow = env.tasks[0].command_to_action(0.3, 0.0)
        assert fly(both, slow) == (True, True, ["goal", "goal"])
        assert fly(FACING, np.array([1.0, 0.0])) == (True, False, ["collision", "collision"])
        assert not env.live.any() and not env.world.active[0].any()
        obs, reward, *_ = env.step(np.zeros((2, 2), dtype=np.float32))  # the world starts over
        assert env.live.all() and env.world.frame_t_ns()[0] == 0 and (reward == 0).all()
    finally:
        env.close()


def test_the_vector_forms_bad_input_is_a_clear_error_and_it_keeps_working():
    from droneulator.config import load_config

    for kwargs, match in (
        ({"num_worlds": 0}, "num_worlds"),
        ({"num_agents": 1.5}, "num_agents"),
        ({"depth": "lidar"}, "depth"),
        ({"episodes": "team"}, "episodes"),
        ({"autoreset_mode": "Disabled"}, "autoreset_mode must be"),
        ({"min_spacing": -1.0}, "min_spacing"),
        ({"neighbour_range": -1.0}, "neighbour_range"),
        ({"config": load_config(overrides=["randomize.enabled=true"])}, "randomisation"),
    ):
        with pytest.raises(ValueError, match=match):
            VineyardMultiVectorEnv(**kwargs)
    env = VineyardMultiVectorEnv(2, 2)
    try:
        with pytest.raises(RuntimeError, match="reset"):
            env.step(np.zeros((4, 2)))
        env.reset(seed=0)
        for bad in (np.zeros((2, 2)), np.full((4, 2), np.nan)):
            with pytest.raises(ValueError, match="actions must be"):
                env.step(bad)
        with pytest.raises(ValueError, match="seeds for 2 worlds"):
            env.reset(seed=[1, 2, 3])
        with pytest.raises(ValueError, match="unknown agents"):
            env.reset(options={"tasks": {"uav9": FACING["uav0"]}})
        obs, *_ = env.step(np.zeros((4, 2)))
        assert obs.shape == (4, 40) and np.isfinite(obs).all()
    finally:
        env.close()


def test_a_shared_policy_trains_on_worlds_of_two_agents_and_is_judged_by_world(tmp_path):
    from droneulator.workflows.rl.env import env_config
    from droneulator.workflows.rl.train import held_out_env, held_out_successes, train

    summary = train(None, tmp_path, steps=240, n_envs=2, agents=2, vec="native", progress=False,
                    overrides={"learning_starts": 100, "batch_size": 32})  # fmt: skip
    assert summary["agents"] == 2 and summary["steps"] >= 240
    assert summary["hyperparameters"]["gradient_steps"] == 4  # one update per agent transition
    from stable_baselines3 import SAC

    from droneulator.workflows.rl.evaluate import evaluate
    from droneulator.workflows.rl.heldout import EVAL_SEED

    seeds = [EVAL_SEED, EVAL_SEED + 1, EVAL_SEED + 2]
    policy = SAC.load(tmp_path / "model.zip", device="cpu", custom_objects={"replay_buffer_class": None})
    env = held_out_env(env_config(), 3, "raycast", agents=2)
    try:
        k = held_out_successes(policy, env, seeds)
        assert 0 <= k <= 3 and not env.live.reshape(3, 2).any(axis=1).all()
        names = env.agent_names
    finally:
        env.close()
    # ``evaluate`` judges the team model by team episodes: the same count as the stop check's (by world),
    # from each agent's own ending here, with every agent's flight and a map of them
    summary = evaluate(tmp_path / "model.zip", episodes=3, out=tmp_path / "eval")
    assert summary["agents"] == 2 and summary["seeds"] == seeds and summary["successes"] == k
    for e in summary["per_episode"]:
        assert len(e["agents"]) == 2 and e["success"] == all(a["termination"] == "goal" for a in e["agents"])
        for name, a in zip(names, e["agents"], strict=True):
            assert a["termination"] in ("goal", "collision", "out_of_bounds", "time_limit") and a["steps"] > 0
            if "collided_with" in a:  # only the other agent, and only by colliding
                assert a["collided_with"] in set(names) - {name} and a["termination"] == "collision"
    assert sum(summary["terminations"].values()) == 6
    assert (tmp_path / "eval" / "trajectories.png").stat().st_size > 10_000
    with pytest.raises(ValueError, match="team policy.*drop --url"):
        evaluate(tmp_path / "model.zip", episodes=1, out=tmp_path / "eval", mode="remote", url="ws://x:1")
    with pytest.raises(ValueError, match="agents"):
        train(None, tmp_path, steps=10, n_envs=2, agents=2, vec="dummy")


def _heading_frame(
    states: np.ndarray, positions: np.ndarray, me: int, other: int
) -> tuple[np.ndarray, np.ndarray]:
    """``other``'s horizontal offset (of ``positions``, the observation's instant) and velocity relative
    to ``me`` in ``me``'s heading frame, through SciPy's rotations (not the env's quaternion formula)."""
    from scipy.spatial.transform import Rotation

    yaw = Rotation.from_quat(states[me, 6:10]).as_euler("ZYX")[0]
    turn = Rotation.from_euler("z", -yaw)
    offset = turn.apply(positions[other] - positions[me])[:2]
    velocity = turn.apply(states[other, 3:6] - states[me, 3:6])[:2]
    return offset, velocity


def test_each_agent_observes_its_nearest_neighbour_within_range_in_its_heading_frame():
    from droneulator.workflows.rl.multi import NEIGHBOUR_SPEED

    # uav0 in the middle alley facing +x, uav1 one alley to its left (y = 3) facing -x: 3 m apart
    side = {"uav0": {"start": (0.0, 0.0, 0.0), "goal": (12.0, 0.0)},
            "uav1": {"start": (0.0, 3.0, math.pi), "goal": (-12.0, 3.0)}}  # fmt: skip
    env = VineyardMultiVectorEnv(1, 2)
    try:
        assert env.single_observation_space.shape == (40,)
        assert env.single_observation_space.low[35] == 0.0 and env.single_observation_space.low[36] == -1.0
        obs, _ = env.reset(options={"tasks": side})
        # each sees the other 3 m to its left (uav1 faces the other way: uav0 is on its left too)
        np.testing.assert_allclose(obs[:, 35:38], [[1.0, 0.0, 0.75], [1.0, 0.0, 0.75]], atol=1e-3)
        for _ in range(20):  # 1.25 m/s each: closing at 2.5, inside the block's 4 m/s
            obs, *_, info = env.step(np.array([[0.3, 0.0], [0.3, 0.0]], dtype=np.float32))
        states = env.world.states[0]  # a physics step past the camera instant: flying straight and level
        for me, other in ((0, 1), (1, 0)):
            offset, velocity = _heading_frame(states, info["position"], me, other)
            assert obs[me, 35] == 1.0 and np.hypot(*offset) < 4.0
            np.testing.assert_allclose(obs[me, 36:38], offset / 4.0, atol=2e-3)
            # the velocity a physics step later, still accelerating: within 4 cm/s
            np.testing.assert_allclose(obs[me, 38:40], velocity / NEIGHBOUR_SPEED, atol=0.01)
            assert velocity[0] < -1.0 and abs(velocity[1]) < 0.1  # flying past each other, both forward
        # head on 8 m apart: beyond the 4 m range, nothing observed
        obs, _ = env.reset(options={"tasks": FACING})
        np.testing.assert_array_equal(obs[:, 35:], 0.0)
    finally:
        env.close()
    depth_alone = VineyardMultiVectorEnv(1, 2, neighbour_range=0.0)
    try:
        obs, _ = depth_alone.reset(options={"tasks": side})
        assert obs.shape == (2, 35) and depth_alone.single_observation_space.shape == (35,)
    finally:
        depth_alone.close()


def test_the_teacher_gives_way_where_on_depth_alone_the_two_agents_touch():
    """Three team episodes in which the path teacher's two agents meet at a row end and touch when it
    flies on depth alone, and reach their goals when it gives way to the neighbour it observes."""
    from droneulator.workflows.rl.distil import PathTeacher
    from droneulator.workflows.rl.env import env_config

    seeds = [1_000_015, 1_000_025, 1_000_043]
    outcomes = {}
    for reach in (0.0, 4.0):
        cfg = env_config(neighbour_range=reach)
        env = VineyardMultiVectorEnv(3, 2, cfg, episodes="world")
        try:
            teacher = PathTeacher(cfg)
            obs, _ = env.reset(seed=seeds)
            first = np.full(6, "", dtype=object)
            while (first == "").any():
                forward, yaw_rate = teacher(obs)
                obs, _, terminated, truncated, info = env.step(
                    env.actuator.actions(np.column_stack([forward, yaw_rate]))
                )
                ended = (terminated | truncated) & (first == "")
                first[ended] = info["termination"][ended]
            outcomes[reach] = list(first)
        finally:
            env.close()
    assert outcomes[0.0] == ["collision"] * 6
    assert outcomes[4.0] == ["goal"] * 6


def test_training_worlds_can_send_agents_against_each_other_and_held_out_worlds_never_do():
    from droneulator.config import load_config
    from droneulator.workflows.rl.train import held_out_env

    cfg = load_config(overrides=["rl.encounters=1.0"])
    meeting = VineyardMultiVectorEnv(6, 2, cfg)
    plain = held_out_env(cfg, 6, "raycast", agents=2)
    try:
        assert (meeting.encounters, plain.encounters) == (1.0, 0.0)
        for env in (meeting, plain):
            env.reset(seed=40)
        met = 0
        for w in range(6):
            first, second = meeting.tasks[2 * w], meeting.tasks[2 * w + 1]
            # the second agent starts beside the first one's goal and aims beside its start
            met += math.dist(second.start[:2], first.goal) <= math.sqrt(2) + 1e-9 and (
                math.dist(second.goal, first.start[:2]) <= math.sqrt(2) + 1e-9
            )
            a, b = plain.tasks[2 * w], plain.tasks[2 * w + 1]
            near = math.dist(b.start[:2], a.goal), math.dist(b.goal, a.start[:2])
            assert max(near) > math.sqrt(2)
        assert met >= 5  # a draw that finds no free, reachable pair falls back to a plain task
    finally:
        meeting.close()
        plain.close()
    with pytest.raises(ValueError, match="rl.encounters"):
        load_config(overrides=["rl.encounters=1.5"])


def test_a_sac_team_trains_with_the_team_recipe_unless_its_flags_say_otherwise(tmp_path, capsys):
    """``train --agents 2`` (SAC) defaults to the recipe that met the team target (docs/rl.md): the giving-way
    teacher's demonstrations, cloning and the anchor, and training tasks where agents meet; a flag or a
    ``--set`` given wins, and what was chosen is said and recorded in the run."""
    import json

    from droneulator.cli import main
    from droneulator.cli.train import TEAM_ENCOUNTERS, TEAM_RECIPE, team_defaults
    from droneulator.config import load_config

    cfg, hyper = team_defaults(load_config(), {}, [])
    assert hyper == TEAM_RECIPE and cfg.rl.encounters == TEAM_ENCOUNTERS
    said = capsys.readouterr().out
    assert "--demonstrations 20000 --bc-steps 5000 --anchor 10 and rl.encounters=0.5" in said
    plain = ["rl.encounters=0"]
    cfg, hyper = team_defaults(load_config(overrides=plain), {"demonstrations": 0}, plain)
    assert hyper == {"demonstrations": 0} and cfg.rl.encounters == 0.0
    assert capsys.readouterr().out == ""  # nothing chosen, nothing said
    _, hyper = team_defaults(load_config(), {"demonstration_anchor": 2.0}, None)
    assert hyper == {**TEAM_RECIPE, "demonstration_anchor": 2.0}

    out = tmp_path / "team"  # through the command: the run records the choice
    argv = ["train", "--num-envs", "2", "--agents", "2", "--steps", "200", "--demonstrations", "150",
            "--bc-steps", "20", "--learning-starts", "100", "--no-progress", "--out", str(out)]  # fmt: skip
    assert main(argv) == 0
    assert "rl.encounters=0.5" in capsys.readouterr().out
    summary = json.loads((out / "train_summary.json").read_text())
    assert summary["agents"] == 2 and summary["hyperparameters"]["demonstrations"] == 150
    assert summary["hyperparameters"]["demonstration_bc_steps"] == 20
    assert summary["hyperparameters"]["demonstration_anchor"] == 0.0  # --demonstrations given: the flags rule
    assert json.loads((out / "config.json").read_text())["rl"]["encounters"] == TEAM_ENCOUNTERS
