"""The native vector env ``gym.make_vec("droneulator/VineyardNav-v0", num_envs=B)``: equality with the
single env over long random rollouts with autoresets, Gymnasium's VectorEnv contract, seeding, errors."""

from __future__ import annotations

import gymnasium as gym
import numba
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode

import droneulator.workflows.rl as rl
from droneulator.workflows.rl.env import VineyardNavEnv
from droneulator.workflows.rl.vector import VineyardNavVectorEnv

INFO_KEYS = ("t", "position", "yaw", "command", "distance", "goal_distance", "termination", "is_success")


def rollout_vector(venv: VineyardNavVectorEnv, seed: int, actions: np.ndarray) -> dict[str, list]:
    obs, info = venv.reset(seed=seed)
    out: dict[str, list] = {"obs": [obs], "reward": [], "terminated": [], "truncated": [], "info": [info]}
    for a in actions:
        obs, reward, term, trunc, info = venv.step(a)
        out["obs"].append(obs)
        out["reward"].append(reward)
        out["terminated"].append(term)
        out["truncated"].append(trunc)
        out["info"].append(info)
    return out


def rollout_single(env: VineyardNavEnv, seed: int, actions: np.ndarray) -> dict[str, list]:
    """The single env driven as a NEXT_STEP vector env drives each of its envs: the step after an
    episode ends is a reset (no seed: the env's generator goes on), reward 0."""
    obs, info = env.reset(seed=seed)
    out: dict[str, list] = {"obs": [obs], "reward": [], "terminated": [], "truncated": [], "info": [info]}
    done = False
    for a in actions:
        if done:
            obs, info = env.reset()
            reward, term, trunc = 0.0, False, False
        else:
            obs, reward, term, trunc, info = env.step(a)
        done = term or trunc
        for key, value in (("obs", obs), ("reward", reward), ("terminated", term), ("truncated", trunc)):
            out[key].append(value)
        out["info"].append(info)
    return out


@pytest.mark.parametrize(("depth", "steps"), [("raycast", 250), ("render", 200)])
def test_each_env_equals_the_single_env_over_long_rollouts_with_autoresets(depth, steps):
    n = 4  # 1,000 env steps (800 with the slower rendered depth), autoresets among them
    actions = np.random.default_rng(7).uniform(-1, 1, (steps, n, 2)).astype(np.float32)
    venv = gym.make_vec(rl.ENV_ID, num_envs=n, depth=depth)
    assert isinstance(venv, VineyardNavVectorEnv)
    try:
        vec = rollout_vector(venv, 100, actions)
    finally:
        venv.close()
    env = VineyardNavEnv(depth=depth)
    episodes = 0
    try:
        for i in range(n):
            one = rollout_single(env, 100 + i, actions[:, i])
            np.testing.assert_allclose(np.array(vec["obs"])[:, i], np.array(one["obs"]), atol=1e-5, rtol=0)
            np.testing.assert_allclose(np.array(vec["reward"])[:, i], one["reward"], atol=1e-6, rtol=0)
            np.testing.assert_array_equal(np.array(vec["terminated"])[:, i], one["terminated"])
            np.testing.assert_array_equal(np.array(vec["truncated"])[:, i], one["truncated"])
            for k, info in enumerate(one["info"]):
                assert vec["info"][k]["termination"][i] == info["termination"]
                assert vec["info"][k]["t"][i] == pytest.approx(info["t"], abs=1e-9)
                np.testing.assert_allclose(vec["info"][k]["position"][i], info["position"], atol=1e-6)
                assert vec["info"][k]["distance"][i] == pytest.approx(info["distance"], abs=1e-6)
            episodes += sum(one["terminated"]) + sum(one["truncated"])
    finally:
        env.close()
    assert episodes >= steps // 125, "the rollouts must cross autoresets"


@pytest.fixture(scope="module")
def venv():
    e = VineyardNavVectorEnv(3, depth="raycast")
    yield e
    e.close()


def test_vector_env_contract_spaces_infos_and_seeding(venv):
    assert venv.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
    assert venv.num_envs == 3
    assert venv.single_observation_space.shape == (35,)
    assert venv.observation_space.shape == (3, 35) and venv.action_space.shape == (3, 2)
    obs, info = venv.reset(seed=5)
    assert obs.dtype == np.float32 and venv.observation_space.contains(obs)
    for key in INFO_KEYS:
        assert len(info[key]) == 3 and info[f"_{key}"].all(), key
    actions = venv.action_space.sample()
    obs2, reward, term, trunc, info = venv.step(actions)
    assert venv.observation_space.contains(obs2)
    assert reward.shape == term.shape == trunc.shape == (3,)
    assert term.dtype == bool and trunc.dtype == bool
    assert info["command"].shape == (3, 2) and np.all(info["t"] > 0)
    # the same seed reproduces observations; a list of seeds seeds each env
    again, _ = venv.reset(seed=5)
    np.testing.assert_array_equal(again, obs)
    listed, _ = venv.reset(seed=[5, 6, 7])
    np.testing.assert_array_equal(listed, obs)
    other, _ = venv.reset(seed=6)
    np.testing.assert_array_equal(other[:2], obs[1:])


def run_until_done(env: VineyardNavVectorEnv) -> tuple[int, dict, np.ndarray]:
    """Fly env 0 straight into the vine row beside it until an episode ends; returns its index."""
    env.reset(options={"start": (-8.0, 0.0, np.pi / 2), "goal": (8.0, 0.0)})
    for _ in range(300):
        obs, reward, term, trunc, info = env.step(np.tile([1.0, 0.0], (env.num_envs, 1)))
        if (term | trunc).any():
            return int(np.flatnonzero(term | trunc)[0]), info, obs
    raise AssertionError("no episode ended")


def test_next_step_autoreset_resets_on_the_step_after_the_end(venv):
    i, info, final = run_until_done(venv)
    assert info["termination"][i] == "collision"
    obs, reward, term, trunc, info = venv.step(np.ones((3, 2)))  # the action is ignored for a resetting env
    assert reward[i] == 0.0 and not term[i] and not trunc[i]
    assert info["t"][i] == 0.0 and info["termination"][i] is None
    assert info["command"][i].tolist() == [0.0, 0.0]
    assert not np.array_equal(obs[i], final[i])
    # the next step flies the new episode
    _, _, _, _, info = venv.step(np.zeros((3, 2)))
    assert info["t"][i] > 0.0


def test_same_step_autoreset_returns_the_final_observation_in_info():
    env = VineyardNavVectorEnv(2, depth="raycast", autoreset_mode=AutoresetMode.SAME_STEP)
    try:
        assert env.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP
        i, info, obs = run_until_done(env)
        assert info["_final_obs"][i] and info["_final_info"][i]
        assert info["final_info"]["termination"][i] == "collision"
        assert info["final_obs"][i].shape == (35,)
        assert not np.array_equal(info["final_obs"][i], obs[i])
        # the returned observation and info are the new episode's
        assert info["t"][i] == 0.0 and info["termination"][i] is None
        _, reward, term, trunc, info = env.step(np.zeros((2, 2)))
        assert info["t"][i] > 0.0
    finally:
        env.close()


def test_bad_input_is_a_clear_error_and_the_env_keeps_working(venv):
    with pytest.raises(ValueError, match="num_envs"):
        VineyardNavVectorEnv(0)
    with pytest.raises(ValueError, match="depth"):
        VineyardNavVectorEnv(1, depth="lidar")
    with pytest.raises(ValueError, match="autoreset_mode"):
        VineyardNavVectorEnv(1, autoreset_mode=AutoresetMode.DISABLED)
    fresh = VineyardNavVectorEnv(1)
    try:
        with pytest.raises(RuntimeError, match="reset"):
            fresh.step(np.zeros((1, 2)))
    finally:
        fresh.close()
    venv.reset(seed=1)
    with pytest.raises(ValueError, match="shape"):
        venv.step(np.zeros((2, 2)))
    with pytest.raises(ValueError, match="finite"):
        venv.step(np.array([[np.nan, 0.0]] * 3))
    with pytest.raises(ValueError, match="seeds"):
        venv.reset(seed=[1, 2])
    obs, *_ = venv.step(np.zeros((3, 2)))
    assert venv.observation_space.contains(obs)


def test_threads_bound_the_compiled_steps_give_the_same_results_and_leave_the_callers_setting():
    """``threads=1`` (what a Ray actor of one CPU passes): the compiled steps run on one thread, the
    rollout equals the one on every core, and the calling thread's numba setting is as it was."""
    for bad in (0, numba.config.NUMBA_NUM_THREADS + 1):
        with pytest.raises(ValueError, match="threads must be 1 to"):
            VineyardNavVectorEnv(1, threads=bad)
    caller = numba.get_num_threads()
    one, every = VineyardNavVectorEnv(3, threads=1), VineyardNavVectorEnv(3)
    seen: list[int] = []
    step_frame = one.worlds.step_frame

    def spy(*args, **kwargs):
        seen.append(numba.get_num_threads())
        return step_frame(*args, **kwargs)

    one.worlds.step_frame = spy
    try:
        actions = np.random.default_rng(3).uniform(-1, 1, (80, 3, 2))
        a, b = rollout_vector(one, 7, actions), rollout_vector(every, 7, actions)
    finally:
        one.close()
        every.close()
    assert seen and set(seen) == {1}
    assert numba.get_num_threads() == caller
    for key in ("obs", "reward", "terminated", "truncated"):
        np.testing.assert_array_equal(np.array(a[key]), np.array(b[key]))


# --------------------------------------------------------------------------- batched training
@pytest.mark.slow
def test_short_batched_ppo_run_writes_model_logs_and_checks_and_evaluate_draws_figures(tmp_path):
    import json

    from PIL import Image

    from droneulator.cli import main

    out = tmp_path / "run"
    args = ["train", "--num-envs", "16", "--algo", "ppo", "--steps", "4096", "--out", str(out)]
    args += ["--no-progress", "--checkpoint-every", "2048", "--seed", "2", "--stop-at", "1.0"]
    assert main([*args, "--check-every", "4096", "--check-episodes", "10"]) == 0  # 50 by default
    for name in ("model.zip", "monitor.csv", "progress.csv", "config.json", "train_summary.json"):
        assert (out / name).stat().st_size > 0, name
    assert list((out / "tb").glob("events.out.tfevents.*"))
    assert list((out / "checkpoints").glob("ppo_*_steps.zip"))
    summary = json.loads((out / "train_summary.json").read_text())
    assert summary["algo"] == "ppo" and summary["vec"] == "native" and summary["depth"] == "raycast"
    assert summary["steps"] >= 4096 and summary["n_envs"] == 16
    assert summary["train_seeds"] == list(range(2, 18))
    assert [c["steps"] for c in summary["checks"]] == [4096]
    assert all(0 <= c["successes"] <= 10 and c["episodes"] == 10 for c in summary["checks"])
    for c in summary["checks"]:  # each check's rate with its 95 % Wilson interval
        low, high = c["success_interval_95"]
        assert 0.0 <= low <= c["success_rate"] <= high <= 1.0 and high - low > 0.2  # 10 episodes say little
    checked = summary["check_seeds"]
    assert summary["check_episodes"] == 10 and checked == list(range(2_500_000, 2_500_010))
    monitor = (out / "monitor.csv").read_text().splitlines()
    assert monitor[1].startswith("r,l,t") and len(monitor) > 2  # episodes of the batched envs were logged

    # SAC (the default) on the batched env: one gradient step per transition
    sac = tmp_path / "sac"
    args = ["train", "--num-envs", "8", "--steps", "160", "--learning-starts", "80", "--out", str(sac)]
    assert main([*args, "--no-progress"]) == 0
    summary = json.loads((sac / "train_summary.json").read_text())
    assert summary["algo"] == "sac" and summary["hyperparameters"]["gradient_steps"] == 8
    assert (sac / "model.zip").stat().st_size > 0

    assert main(["evaluate", str(out), "--episodes", "2"]) == 0  # a PPO model, evaluated by the single env
    result = json.loads((out / "evaluation.json").read_text())
    assert result["episodes"] == 2 and result["seeds"] == [1_000_000, 1_000_001]
    assert result["stop_check_seeds"] == checked and len(result["success_interval_95"]) == 2
    for png in ("trajectories.png", "training_curves.png"):
        with Image.open(out / png) as img:
            assert img.format == "PNG" and img.size[0] > 500


def test_train_rejects_bad_batched_settings_in_one_line(capsys):
    from droneulator.cli import main

    assert main(["train", "--num-envs", "0"]) == 2
    assert "--num-envs must be at least 1" in capsys.readouterr().err
    assert main(["train", "--num-envs", "4", "--algo", "ppo", "--learning-starts", "10"]) == 2
    assert "SAC setting" in capsys.readouterr().err
    assert main(["train", "--num-envs", "4", "--stop-at", "1.5"]) == 2
    assert "stop_at" in capsys.readouterr().err
    for bad in (["--agents", "2"], ["--num-envs", "4", "--agents", "0"]):
        assert main(["train", *bad]) == 2
        assert "--agents must be at least 1, and more than one need --num-envs" in capsys.readouterr().err


def test_a_batched_world_that_hits_a_row_stays_there_and_takes_no_command():
    from droneulator.workflows.rl.env import env_config
    from droneulator.world import World
    from droneulator.world.step import FLAT, VELOCITY

    worlds = World(env_config(), render=False, worlds=2)
    # world 0 faces the vine row beside its alley, world 1 flies along the alley
    worlds.place(np.arange(2), np.array([[-8.0, 0.0, 1.5], [-8.0, 0.0, 1.5]]), np.array([np.pi / 2, 0.0]))
    worlds.velocity(None, np.array([2.0, 2.0]), np.zeros(2))
    for _ in range(90):
        _, hit = worlds.step_frame()
        if hit[0, 0]:
            break
    assert hit[0, 0] and not hit[1, 0] and worlds.active[:, 0].tolist() == [False, True]
    assert worlds.mode[:, 0].tolist() == [VELOCITY, VELOCITY]
    stopped = worlds.states[0, 0].copy()
    assert np.allclose(stopped[3:6], 0.0)  # stopped where it touched, level
    assert np.allclose(stopped[6:8], 0.0)
    t0 = worlds.frame_t_ns().copy()
    states, hit = worlds.step_frame()
    assert np.array_equal(states[0, 0], stopped) and not hit[0, 0]  # not integrated further
    assert (worlds.frame_t_ns() - t0).tolist() == [worlds.camera_period_ns] * 2  # its clock goes on
    with pytest.raises(ValueError, match="collided"):
        worlds.velocity(np.array([0]), np.array([1.0]), np.array([0.0]))
    worlds.velocity(np.array([1]), np.array([1.0]), np.array([0.0]))  # the other world flies on
    with pytest.raises(ValueError, match="\\|forward\\|"):
        worlds.velocity(np.array([1]), np.array([99.0]), np.array([0.0]))
    worlds.place([0], [[-8.0, 0.0, 1.5]], [0.0])  # placed again: it holds, then takes commands
    assert worlds.active[0, 0] and worlds.mode[0, 0] == FLAT
    worlds.velocity([0], [1.0], [0.0])
