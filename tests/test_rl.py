"""Workflow 3: the vineyard navigation environment, its A* reward, SAC training/evaluation, remote mode."""

from __future__ import annotations

import json
import math

import gymnasium as gym
import numpy as np
import pytest
from PIL import Image

import droneulator.workflows.rl as rl
from droneulator.vehicles.dynamics import STATE
from droneulator.workflows.rl.astar import OccupancyGrid
from droneulator.workflows.rl.env import VineyardNavEnv, depth_strip, env_config, runtime_overrides
from droneulator.world import World

ALLEY = [-8.0, 0.0, 0.0]  # in the middle alley (y = 0), facing +x along it
GOAL_FAR = [8.0, 0.0]


@pytest.fixture(scope="module")
def env():
    e = gym.make(rl.ENV_ID)
    yield e
    e.close()


def expected_strip(depth: np.ndarray, clip: float = 10.0) -> np.ndarray:
    """Reference strip written independently: centre row, NaN -> clip, min over 32 equal sectors."""
    row = depth[depth.shape[0] // 2].astype(np.float64)
    row = np.where(np.isnan(row), clip, np.minimum(row, clip))
    return row.reshape(32, -1).min(axis=1) / clip


# --------------------------------------------------------------------------- A*
def test_astar_and_distance_field_on_a_known_grid():
    # 5 x 5 nodes, 0.5 m apart; a wall at i = 2 leaves a gap at j = 4 only
    free = np.ones((5, 5), dtype=bool)
    free[2, 0:4] = False
    grid = OccupancyGrid(free, np.array([-1.0, 2.0]), 0.5)
    start, goal = grid.point(0, 0), grid.point(4, 0)
    length, path = grid.shortest_path(start, goal)
    # (0,0) -d-> (1,1) -> (1,2) -> (1,3) -> (1,4) -> (2,4) -> (3,4) -d-> (4,3) -> (4,2) -> (4,1) -> (4,0):
    # 8 straight + 2 diagonal moves; (1,3) -> (2,4) would cut the corner of the occupied (2,3)
    assert length == pytest.approx(0.5 * (8 + 2 * math.sqrt(2)))
    np.testing.assert_allclose(path[0], start)
    np.testing.assert_allclose(path[-1], goal)
    assert all(grid.free[grid.node(p)] for p in path)
    field = grid.distance_field(goal)
    assert field.distance(start) == pytest.approx(length)
    assert field.distance(grid.point(3, 0)) == pytest.approx(0.5)
    assert field.distance(grid.point(2, 4)) == pytest.approx(0.5 * (4 + math.sqrt(2)))
    assert field.distance(goal) == pytest.approx(0.0)
    # bilinear between (4, 0) and (4, 1), and off the grid: plus the straight distance to it
    assert field.distance(grid.point(4, 0) + [0.0, 0.25]) == pytest.approx(0.25)
    assert field.distance(grid.point(4, 0) + [1.0, 0.0]) == pytest.approx(1.0)
    # the carrot on the path stays in line of sight: from (0, 0) it cannot see past the wall's gap
    carrot = field.lookahead(start, 10.0)
    assert grid.node(carrot)[0] <= 2
    # open grid: octile distance
    open_grid = OccupancyGrid(np.ones((6, 6), dtype=bool), np.zeros(2), 1.0)
    octile = open_grid.shortest_path(np.zeros(2), np.array([3.0, 2.0]))[0]
    assert octile == pytest.approx(1 + 2 * math.sqrt(2))
    # enclosed goal: unreachable
    walled = np.ones((6, 6), dtype=bool)
    walled[3, :] = False
    g2 = OccupancyGrid(walled, np.zeros(2), 1.0)
    assert math.isinf(g2.shortest_path(np.zeros(2), np.array([5.0, 5.0]))[0])
    # its field from (0, 0): the far side (never reached) reads 10 m beyond the farthest reached node,
    # (2, 5) at 3 + 2 sqrt 2; a wall node reads its nearest free node's value plus the metre to it
    f2 = g2.distance_field(np.zeros(2))
    far = 3 + 2 * math.sqrt(2)
    assert f2.reachable[:3].all() and not f2.reachable[3:].any()
    assert f2.values[:3].max() == pytest.approx(far) and f2.values[2, 5] == pytest.approx(far)
    np.testing.assert_allclose(f2.values[4:], far + 10.0)
    for j in range(6):
        assert f2.values[3, j] in (pytest.approx(f2.values[2, j] + 1.0), pytest.approx(far + 11.0))
    assert not f2.is_reachable(np.array([5.0, 5.0])) and f2.is_reachable(np.array([2.0, 5.0]))


def test_learning_envs_fly_rl_substeps_and_stay_on_the_finer_flight():
    """At the velocity level the learning envs integrate with 4 RK4 sub-steps a control period (the
    levels below keep ``vehicle.substeps``): random commands fly within a micrometre of 100 sub-steps."""
    from droneulator.config import SimConfig
    from droneulator.config.rl import VELOCITY_SUBSTEPS
    from droneulator.workflows.rl.multi import VineyardMultiVectorEnv

    assert env_config().vehicle.substeps == VELOCITY_SUBSTEPS == 4
    assert env_config(env_config()).vehicle.substeps == 4  # applying it twice changes nothing
    assert env_config(action="ctbr").vehicle.substeps == SimConfig().vehicle.substeps == 10
    assert env_config(substeps=7).vehicle.substeps == 7
    assert "vehicle.substeps=4" in runtime_overrides(env_config())  # the remote backend flies the same
    for bad in (0, -1, 2.5, True, "4"):
        with pytest.raises(ValueError, match="rl.substeps"):
            env_config(substeps=bad)

    def positions(substeps: int) -> np.ndarray:
        env = VineyardMultiVectorEnv(4, 1, substeps=substeps)
        assert env.world.config.vehicle.substeps == substeps
        env.reset(seed=3)
        rng = np.random.default_rng(1)
        out = []
        for _ in range(60):  # 2 s
            out.append(env.step(rng.uniform(-1, 1, (4, 2)).astype(np.float32))[4]["position"])
        env.close()
        return np.array(out)

    coarse, fine = positions(4), positions(100)
    err = np.abs(coarse - fine).max()
    assert 0.0 < err < 1e-6, err
    assert np.linalg.norm(np.diff(fine, axis=0), axis=2).sum(axis=0).min() > 0.3  # each flew a path


def test_depth_strip_normalisation():
    depth = np.full((3, 64), 20.0, dtype=np.float32)
    depth[1, :2] = np.nan
    depth[1, 2:4] = 2.5
    depth[1, 10] = 0.5
    depth[0, :] = 0.1  # not the centre row
    s = depth_strip(depth, 10.0)
    assert s.shape == (32,) and s.dtype == np.float32
    assert s[0] == 1.0 and s[1] == pytest.approx(0.25) and s[5] == pytest.approx(0.05) and s[31] == 1.0


# --------------------------------------------------------------------------- environment
def test_spaces_and_action_mapping(env):
    u = env.unwrapped
    assert env.observation_space.shape == (35,) and env.action_space.shape == (2,)
    np.testing.assert_allclose(env.action_space.low, -1.0)
    assert u.action_to_command(np.array([-1.0, -1.0])) == pytest.approx((-2.0, -1.5))
    assert u.action_to_command(np.array([1.0, 1.0])) == pytest.approx((3.0, 1.5))
    assert u.action_to_command(np.array([0.0, 0.0])) == pytest.approx((0.5, 0.0))
    np.testing.assert_allclose(u.command_to_action(3.0, -1.5), [1.0, -1.0])


def test_progress_toward_the_goal_is_rewarded_and_away_penalised(env):
    for action, sign in ((1.0, 1), (-1.0, -1)):
        env.reset(seed=0, options={"start": ALLEY, "goal": GOAL_FAR})
        rewards = [env.step(np.array([action, 0.0]))[1] for _ in range(30)]
        assert all(sign * r > 0 for r in rewards[10:]), rewards  # once the vehicle has sped up
        assert rewards[-1] * sign > 0.05
        d = env.unwrapped.initial_distance - env.unwrapped.field.distance(env.unwrapped.kinematics.position)
        assert sum(rewards) == pytest.approx(d - 30 * 0.01, abs=1e-6)  # lambda = 1, step penalty 0.01


def test_flying_into_a_vine_row_ends_the_episode_with_minus_30(env):
    obs, _ = env.reset(seed=0, options={"start": [0.0, 0.0, math.pi / 2], "goal": GOAL_FAR})
    assert obs[:32].max() < 0.2  # the hedge, ~1.2 m ahead, fills the strip
    for _ in range(90):
        obs, reward, terminated, truncated, info = env.step(np.array([1.0, 0.0]))
        if terminated or truncated:
            break
    assert terminated and not truncated and info["termination"] == "collision"
    assert -31.0 < reward < -29.0
    assert env.unwrapped.backend.vehicle.mode == "collided"
    assert 1.0 < info["position"][1] < 1.3  # stopped against the hedge face (y = 1.3) minus the radius


def test_reaching_the_goal_gives_plus_100(env):
    env.reset(seed=0, options={"start": [0.0, 0.0, 0.0], "goal": [2.2, 0.0]})
    for _ in range(60):
        _, reward, terminated, truncated, info = env.step(np.array([0.2, 0.0]))
        if terminated or truncated:
            break
    assert terminated and info["termination"] == "goal" and info["is_success"]
    assert 100.0 < reward < 101.0
    assert info["goal_distance"] <= 1.5


def test_depth_strip_is_the_centre_row_of_the_rendered_image(env):
    u = env.unwrapped
    obs, _ = env.reset(seed=5)
    cfg = env_config()
    with World(config=cfg) as world:  # a world's own camera pipeline (RGB + depth) at the same pose
        uav = world.vehicle()
        kin = u.kinematics
        world.reset(position=kin.position, yaw=kin.yaw)
        depth = world.render().cameras[uav.name]["front"].depth
        assert depth.shape == (cfg.rl.camera_height, cfg.rl.camera_width)
        np.testing.assert_allclose(obs[:32], expected_strip(depth), atol=1e-6)
        for _ in range(15):
            obs, *_ = env.step(np.array([0.3, 0.5]))
        kin = u.kinematics
        uav.s[STATE.x], uav.s[STATE.q] = kin.position, kin.quaternion  # the full attitude, rolled and pitched
        depth = world.render().cameras[uav.name]["front"].depth
        np.testing.assert_allclose(obs[:32], expected_strip(depth), atol=1e-6)
    assert (obs[:32] < 1.0).any()  # vines in view, not only misses


def test_seeding_makes_episodes_reproducible(env):
    actions = [np.array([math.sin(0.3 * k), math.cos(0.2 * k)]) for k in range(40)]

    def episode(seed: int) -> tuple[np.ndarray, list[float], np.ndarray]:
        obs, _ = env.reset(seed=seed)
        trace, rewards = [obs], []
        for a in actions:
            obs, r, terminated, truncated, _ = env.step(a)
            trace.append(obs)
            rewards.append(r)
            if terminated or truncated:
                break
        return np.array(trace), rewards, env.unwrapped.goal.copy()

    a, b, c = episode(11), episode(11), episode(12)
    np.testing.assert_array_equal(a[0], b[0])
    assert a[1] == b[1]
    np.testing.assert_array_equal(a[2], b[2])
    assert not np.array_equal(a[2], c[2])


def test_sampled_tasks_are_free_reachable_and_mostly_across_rows(env):
    u = env.unwrapped
    across = 0
    for seed in range(30):
        env.reset(seed=seed)
        assert u.grid.is_free(u.start[:2]) and u.grid.is_free(u.goal)
        assert u.rl.min_separation <= u.initial_distance <= u.rl.max_path_length
        lane = lambda p: int(np.argmin(np.abs(u.lanes - p[1])))  # noqa: E731
        in_rows = all(u.row_x[0] < p[0] < u.row_x[1] for p in (u.start, u.goal))
        across += in_rows and lane(u.start) != lane(u.goal)
    assert across >= 12


def test_gymnasium_and_sb3_env_checkers_pass(env):
    from gymnasium.utils.env_checker import check_env

    check_env(env.unwrapped, skip_render_check=True)
    sb3_checker = pytest.importorskip("stable_baselines3.common.env_checker")
    sb3_checker.check_env(env.unwrapped, warn=True)


# --------------------------------------------------------------------------- training and evaluation
@pytest.mark.slow
def test_short_training_run_writes_logs_and_model_and_evaluate_writes_figures(tmp_path):
    pytest.importorskip("stable_baselines3")
    from droneulator.cli import main

    out = tmp_path / "run"
    args = ["train", "--steps", "600", "--learning-starts", "100", "--envs", "2", "--out", str(out)]
    assert main([*args, "--checkpoint-every", "300", "--seed", "3"]) == 0  # with the progress bar
    for name in ("model.zip", "monitor.csv", "progress.csv", "config.json", "train_summary.json"):
        assert (out / name).stat().st_size > 0, name
    assert list((out / "tb").glob("events.out.tfevents.*"))
    assert len(list((out / "checkpoints").glob("sac_*_steps.zip"))) == 2
    summary = json.loads((out / "train_summary.json").read_text())
    assert summary["steps"] >= 600 and summary["n_envs"] == 2 and summary["vec"] == "subproc"
    assert summary["train_seeds"] == [3, 4]

    assert main(["evaluate", str(out / "model.zip"), "--episodes", "2", "--seed", "3"]) == 2  # seeds used
    assert main(["evaluate", str(out), "--episodes", "2"]) == 0  # the run folder names its model.zip
    result = json.loads((out / "evaluation.json").read_text())
    assert result["episodes"] == 2 and len(result["per_episode"]) == 2
    assert result["seeds"] == [1_000_000, 1_000_001] and 0.0 <= result["success_rate"] <= 1.0
    low, high = result["success_interval_95"]  # 2 episodes: a wide 95 % Wilson interval
    assert low <= result["success_rate"] <= high and high - low > 0.6
    assert result["stop_check_seeds"] == [] and result["warning"] is None  # no stop check in this run
    for png in ("trajectories.png", "training_curves.png"):
        with Image.open(out / png) as img:
            assert img.format == "PNG" and img.size[0] > 500


# --------------------------------------------------------------------------- remote mode
@pytest.mark.slow
def test_remote_mode_against_a_running_simulator():
    from droneulator.config import load_config
    from droneulator.runtime.launch import launch_run

    extra = [a for o in runtime_overrides(env_config()) for a in ("--set", o)]  # as a user starts it
    with launch_run(load_config(scene="vineyard"), extra) as run:
        env = VineyardNavEnv(mode="remote", url=run.url, zenoh=run.zenoh_endpoint)
        try:
            obs, info = env.reset(seed=0, options={"start": ALLEY, "goal": GOAL_FAR})
            assert obs.shape == (35,) and env.observation_space.contains(obs)
            np.testing.assert_allclose(info["position"], [-8.0, 0.0, 1.5], atol=0.05)
            assert obs[:32].min() < 0.5  # the hedges on both sides of the alley
            for _ in range(8):
                obs, reward, terminated, truncated, info = env.step(np.array([0.6, 0.0]))
                assert env.observation_space.contains(obs) and not terminated
            # it flew along the alley (a hover stays within 0.05 m; 0.29 m in 8 frames with a core kept busy)
            assert info["position"][0] > -8.0 + 0.15
            assert env.kinematics.mode == "velocity" and obs[33] > -0.2  # moving forward
            assert reward > 0.0
        finally:
            env.close()
