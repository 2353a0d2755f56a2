"""``droneulator train --algo distil``: the CTBR expert's labels round-trip through the env's actuator, the
expert reaches the goal, and a tiny DAgger run leaves a student that imitates the expert better than an
untrained one and that ``evaluate`` loads; SAC from demonstrations fills its replay buffer's warm-up with the
path teacher's velocity actions (which round-trip through the actuator) and trains on one or two agents."""

from __future__ import annotations

import json
from typing import Any

import numpy as np
import pytest

from droneulator.config import load_config
from droneulator.workflows.rl.distil import CTBRExpert, expert_successes, student_model, weighted_error
from droneulator.workflows.rl.env import env_config
from droneulator.workflows.rl.evaluate import trained_algorithm
from droneulator.workflows.rl.levels import Actuator
from droneulator.workflows.rl.train import train
from droneulator.workflows.rl.vector import VineyardNavVectorEnv


def _ctbr():
    cfg = load_config(None)
    cfg.rl.action = "ctbr"
    return env_config(cfg)


@pytest.mark.parametrize("scale", [None, 2.0])
def test_expert_commands_round_trip_through_the_actuator(scale):
    cfg = _ctbr()
    cfg.rl.max_thrust_to_weight = scale
    act = Actuator(cfg, 64)
    af = act.airframe
    rng = np.random.default_rng(0)
    commands = np.column_stack([
        rng.uniform(0.0, af.max_thrust, 64), rng.uniform(-1.0, 1.0, (64, 3)) * af.max_rate
    ])  # fmt: skip
    commands[0] = (af.weight, 0.0, 0.0, 0.0)  # hover is the zero action
    actions = act.actions(commands)
    np.testing.assert_array_equal(actions[0], 0.0)
    np.testing.assert_allclose(
        act.map(np.arange(64), actions.astype(np.float64)), commands, rtol=1e-6, atol=1e-5
    )
    np.testing.assert_array_equal(act.actions([[2 * af.max_thrust, 0.0, 0.0, 0.0]])[0, 0], 1.0)  # clipped
    attitude = load_config(None)
    attitude.rl.action = "attitude"
    with pytest.raises(ValueError, match="velocity and ctbr"):
        Actuator(env_config(attitude), 1).actions(commands)


def test_the_expert_flies_its_episodes_to_the_goal():
    assert expert_successes(_ctbr(), [11, 12, 13]) == 3


def test_a_tiny_distillation_imitates_the_expert(tmp_path):
    from stable_baselines3 import PPO

    cfg = _ctbr()
    hyper = {"rollout_steps": 100, "gradient_steps": 300}
    summary = train(cfg, tmp_path, steps=1600, seed=0, n_envs=8, algo="distil", vec="native",
                    progress=False, overrides=hyper)  # fmt: skip
    assert summary["steps"] == 1600 and len(summary["iterations"]) == 2
    assert trained_algorithm(tmp_path / "model.zip") == "distil"
    assert json.loads((tmp_path / "train_summary.json").read_text())["train_seeds"] == list(range(8))
    # states the expert visits from the training seeds, labelled by it
    env = VineyardNavVectorEnv(8, cfg)
    expert = CTBRExpert(cfg, env.actuator)
    obs, _ = env.reset(seed=0)
    seen, labels = [], []
    for _ in range(60):
        a = expert.actions(obs, env.states)
        seen.append(obs)
        labels.append(a)
        obs, *_ = env.step(a)
    env.close()
    x, y = np.concatenate(seen), np.concatenate(labels)
    weights = np.asarray(summary["label_weights"])
    student = PPO.load(tmp_path / "model.zip", device="cpu").policy
    untrained = student_model(_sb3_env(cfg), {"net_arch": [256, 256], "log_std_init": -2.0}, 1).policy
    assert weighted_error(student, x, y, weights) < 0.5 * weighted_error(untrained, x, y, weights)


def _sb3_env(cfg):
    from gymnasium.vector import AutoresetMode

    from droneulator.workflows.rl.sb3 import SB3VectorEnv

    return SB3VectorEnv(VineyardNavVectorEnv(1, cfg, autoreset_mode=AutoresetMode.SAME_STEP))


def test_distil_refuses_what_it_cannot_train(tmp_path):
    with pytest.raises(ValueError, match="rl.action=ctbr"):
        train(load_config(None), tmp_path, steps=10, n_envs=2, algo="distil", vec="native")
    with pytest.raises(ValueError, match="batched env"):
        train(_ctbr(), tmp_path, steps=10, n_envs=2, algo="distil", vec="dummy")
    with pytest.raises(ValueError, match="unknown distil hyperparameters"):
        train(_ctbr(), tmp_path, steps=10, n_envs=2, algo="distil", vec="native", overrides={"gamma": 0.9})


def test_the_command_line_refuses_distil_without_its_level_or_batched_env(capsys, tmp_path):
    from droneulator.cli import main

    out = str(tmp_path / "run")
    for args, message in (
        (["--num-envs", "2"], "distil trains a ctbr policy (--set rl.action=ctbr)"),
        (["--set", "rl.action=ctbr"], "distil trains on the batched env (--num-envs B)"),
        (["--set", "rl.action=ctbr", "--num-envs", "2", "--ray", "local"], "not with --ray"),
    ):
        assert main(["train", "--algo", "distil", "--out", out, *args]) == 2
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1, (args, err)


def test_teacher_velocity_actions_round_trip_through_the_actuator():
    cfg = env_config()
    act = Actuator(cfg, 64)
    rng = np.random.default_rng(1)
    forward = rng.uniform(cfg.rl.forward_min, cfg.rl.forward_max, 64)
    commands = np.column_stack([forward, rng.uniform(-1.0, 1.0, 64) * cfg.rl.max_yaw_rate])
    actions = act.actions(commands)
    assert actions.dtype == np.float32 and actions.shape == (64, 2)
    np.testing.assert_allclose(act.map(np.arange(64), actions.astype(np.float64)), commands, atol=1e-5)
    np.testing.assert_array_equal(act.actions([[99.0, -99.0]]), [[1.0, -1.0]])  # clipped to the space


def test_the_teacher_gives_way_to_a_neighbour_on_a_collision_course_only():
    from droneulator.workflows.rl.distil import PathTeacher

    cfg = env_config()
    teacher = PathTeacher(cfg)
    base = np.zeros(35, dtype=np.float32)
    base[:32] = 1.0  # nothing ahead, heading straight at the steering target
    reach, speed = cfg.rl.neighbour_range, 4.0

    def block(x: float, y: float, vx: float, vy: float, seen: float = 1.0) -> np.ndarray:
        return np.array([seen, x / reach, y / reach, vx / speed, vy / speed], dtype=np.float32)

    cases = {
        "alone": block(0, 0, 0, 0, seen=0.0),
        "head on": block(1.5, 0.0, -3.0, 0.0),  # 1.5 m ahead, closing at 3 m/s
        "from the right": block(1.2, -1.2, -1.5, 1.5),  # ahead right, coming across
        "from the left": block(1.2, 1.2, -1.5, -1.5),
        "behind": block(-1.5, 0.0, 3.0, 0.0),  # closing from behind: the one behind gives way
        "passing clear": block(1.5, 2.5, -3.0, 0.0),  # 2.5 m abeam at closest
    }
    obs = np.stack([np.concatenate([base, b]) for b in cases.values()])
    forward, yaw_rate = teacher(obs)
    got = {name: (forward[i], yaw_rate[i]) for i, name in enumerate(cases)}
    alone_forward, alone_turn = got["alone"]
    assert alone_forward == pytest.approx(2.0) and alone_turn == pytest.approx(0.0)
    for name in ("behind", "passing clear"):
        assert got[name] == pytest.approx(got["alone"]), name
    for name, turn in (("head on", -1), ("from the left", -1), ("from the right", 1)):
        assert got[name][0] < 0.8 * alone_forward, name  # slows down
        assert np.sign(got[name][1]) == turn, name  # and turns away: right unless it comes from the right
    assert teacher(base[None])[0] == pytest.approx(alone_forward)  # the single-agent observation
    with pytest.raises(ValueError, match="35 or 40 entries"):
        teacher(np.zeros((1, 38), dtype=np.float32))


def _quiet(model: Any) -> None:
    """A logger that writes nothing: left to itself, SB3's ``learn`` makes an empty ``SB3-<time>`` folder in
    the temporary directory each call (``droneulator train`` sets its own, writing to the run's folder)."""
    from stable_baselines3.common.logger import Logger

    model.set_logger(Logger(None, []))


def test_sac_from_demonstrations_fills_the_buffer_with_the_teachers_actions(tmp_path):
    from stable_baselines3.common.callbacks import BaseCallback

    from droneulator.workflows.rl.distil import PathTeacher
    from droneulator.workflows.rl.train import demonstrated_sac, make_vec_env, teacher_actions

    cfg = env_config()
    venv = make_vec_env(cfg, 2, "native", agents=2)
    try:
        cls = demonstrated_sac(cfg, steps=80, noise=0.0, bc_steps=5, seed=0)
        model = cls("MlpPolicy", venv, seed=0, device="cpu", learning_starts=40, batch_size=16, n_steps=1)
        _quiet(model)
        cloned: dict[int, bool] = {}

        class Watch(BaseCallback):
            def _on_step(self) -> bool:
                cloned[self.num_timesteps] = self.model.bc_loss is not None
                return True

        model.learn(total_timesteps=120, callback=Watch())
        # cloned in the last teacher step: a held-out check at the hand-over (80) flies the cloned actor
        assert not cloned[76] and cloned[80]
        buf = model.replay_buffer
        teacher, act = PathTeacher(cfg), Actuator(cfg, 1)
        obs, actions = buf.observations[:20].reshape(-1, 40), buf.actions[:20].reshape(-1, 2)
        np.testing.assert_allclose(actions, teacher_actions(teacher, act, obs), atol=1e-6)
        later = buf.actions[20:30].reshape(-1, 2)  # the actor's, once the teacher handed over
        wanted = teacher_actions(teacher, act, buf.observations[20:30].reshape(-1, 40))
        assert not np.allclose(later, wanted, atol=1e-3)
        assert model.bc_loss is not None and np.isfinite(model.bc_loss)
    finally:
        venv.close()
    summary = train(None, tmp_path, steps=160, n_envs=2, agents=2, vec="native", progress=False,
                    overrides={"learning_starts": 40, "batch_size": 16, "demonstrations": 80,
                               "demonstration_bc_steps": 5})  # fmt: skip
    written = json.loads((tmp_path / "train_summary.json").read_text())
    assert written["hyperparameters"]["demonstrations"] == 80 and summary["steps"] >= 160
    assert np.isfinite(written["demonstration_bc_loss"])
    with pytest.raises(ValueError, match="velocity"):
        train(_ctbr(), tmp_path, steps=10, n_envs=2, vec="native", overrides={"demonstrations": 10})


def test_the_command_line_takes_demonstrations_for_sac_only(capsys):
    from droneulator.cli import main

    assert main(["train", "--num-envs", "4", "--algo", "ppo", "--demonstrations", "10"]) == 2
    assert "SAC settings" in capsys.readouterr().err
    assert main(["train", "--num-envs", "4", "--algo", "ppo", "--anchor", "1"]) == 2
    assert "--anchor are SAC settings, not ppo's" in capsys.readouterr().err
    for flags in (["--anchor", "1"], ["--bc-steps", "10"]):  # nothing to clone or anchor to
        assert main(["train", "--num-envs", "4", *flags]) == 2
        assert "set demonstrations (--demonstrations N) as well" in capsys.readouterr().err


def _teacher_gap(anchor: float) -> tuple[float, float | None]:
    """SAC from 40 demonstration steps on 2 worlds x 2 agents, then 60 of its own with ``anchor``: the mean
    squared distance of its deterministic actions from the teacher's on every observation it stored."""
    from droneulator.workflows.rl.distil import PathTeacher
    from droneulator.workflows.rl.train import demonstrated_sac, make_vec_env, teacher_actions

    cfg = env_config()
    venv = make_vec_env(cfg, 2, "native", agents=2)
    try:
        cls = demonstrated_sac(cfg, steps=40 * 4, noise=0.0, bc_steps=0, seed=0, anchor=anchor)
        model = cls("MlpPolicy", venv, seed=0, device="cpu", learning_starts=20, batch_size=32, n_steps=1,
                    gradient_steps=4, learning_rate=3e-3)  # fmt: skip
        _quiet(model)
        model.learn(total_timesteps=100 * 4)
        obs = model.replay_buffer.observations[:100].reshape(-1, 40)
        own, _ = model.predict(obs, deterministic=True)
        wanted = teacher_actions(PathTeacher(cfg), Actuator(cfg, 1), obs)
        return float(((own - wanted) ** 2).sum(axis=1).mean()), model.anchor_loss
    finally:
        venv.close()


def test_the_anchor_keeps_sacs_actor_near_the_teacher():
    free, none = _teacher_gap(0.0)
    anchored, last = _teacher_gap(20.0)
    assert none is None and last is not None and np.isfinite(last)
    assert anchored < 0.5 * free, (anchored, free)
    with pytest.raises(ValueError, match="demonstration_anchor"):
        _teacher_gap(-1.0)
