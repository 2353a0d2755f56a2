"""Domain randomisation: the draws (seeded, inside their ranges) and what the RL environments, single
and batched, fly with after each reset."""

from __future__ import annotations

import numpy as np
import pytest

from droneulator.config import RandomizeConfig, WindConfig, load_config
from droneulator.state import STATE
from droneulator.workflows.rl.env import VineyardNavEnv
from droneulator.workflows.rl.vector import VineyardNavVectorEnv


def test_draws_are_seeded_and_inside_their_ranges():
    spec = RandomizeConfig(enabled=True, wind_speed_m_s=(2.0, 4.0), gust_fraction=(0.5, 0.5), haze_prob=0.5)
    draws = [spec.draw(np.random.default_rng(s), WindConfig(roughness_m=0.1)) for s in range(200)]
    again = [spec.draw(np.random.default_rng(s), WindConfig(roughness_m=0.1)) for s in range(200)]
    assert draws == again
    speeds = np.array([d.wind.speed_m_s for d in draws])
    assert speeds.min() >= 2.0 and speeds.max() <= 4.0 and speeds.std() > 0.3
    assert all(d.wind.gust_speed_m_s == pytest.approx(0.5 * d.wind.speed_m_s) for d in draws)
    assert all(d.wind.roughness_m == 0.1 for d in draws)  # the base's other fields are kept
    assert {d.depth_model for d in draws} == {"ideal", "d435"}
    hazy = [d.visibility_m for d in draws if d.visibility_m is not None]
    assert 60 < len(hazy) < 140 and min(hazy) >= 150.0
    assert all(7.0 <= d.time_of_day_h <= 19.0 and 0.0 <= d.cloud_cover <= 1.0 for d in draws)


@pytest.mark.parametrize(
    ("override", "match"),
    [
        ("randomize.wind_speed_m_s=[5, 2]", "wind_speed_m_s"),
        ("randomize.cloud_cover=[0, 2]", "cloud_cover"),
        ('randomize.depth_models=["lidar"]', "depth_models"),
        ("randomize.haze_prob=1.5", "haze_prob"),
    ],
)
def test_bad_ranges_are_clear_errors(override, match):
    with pytest.raises(ValueError, match=match):
        load_config(overrides=[override])


def test_the_single_env_flies_each_episode_in_its_drawn_conditions():
    cfg = load_config(overrides=["randomize.enabled=true", "randomize.wind_speed_m_s=[3, 6]"])
    env = VineyardNavEnv(cfg, depth="raycast")
    try:
        seen = []
        for seed in (1, 2, 3, 4):
            env.reset(seed=seed)
            drawn = env.conditions
            world = env.backend.sim.world
            assert world.wind.configs[0] == drawn.wind and env.backend.depth_model == drawn.depth_model
            for _ in range(10):
                env.step(np.array([1.0, 0.0], dtype=np.float32))
            felt = world.states[0, 0, STATE.wind]
            assert np.linalg.norm(felt) > 0.3  # a 3-6 m/s wind at 1.5 m, sheltered or not
            seen.append((drawn.wind.speed_m_s, drawn.depth_model))
        assert len({s for s, _ in seen}) == 4
        env.reset(seed=1)
        other = VineyardNavEnv(cfg, depth="raycast")
        other.reset(seed=1)
        assert other.conditions == env.conditions  # the episode's seed draws its conditions
        other.close()
    finally:
        env.close()
    with pytest.raises(ValueError, match="mode='local'"):
        VineyardNavEnv(cfg, mode="remote")


def test_the_batched_env_draws_per_env_and_applies_each_envs_depth_model():
    cfg = load_config(overrides=["randomize.enabled=true", "randomize.depth_models=[\"ideal\", \"d435\"]"])
    env = VineyardNavVectorEnv(16, cfg)
    try:
        env.reset(seed=5)
        models = list(env._depth_models)
        assert set(models) == {"ideal", "d435"}
        speeds = env.worlds.wind.w20
        assert len(set(np.round(speeds, 6))) == 16 and speeds.min() >= 0.0 and speeds.max() <= 6.0
        # the same poses through each env's own preset: ideal rows exact, d435 rows noisy
        poses = np.repeat(np.eye(4)[None], 16, axis=0)
        poses[:, :3, 3] = env.worlds.states[0, STATE.x]
        ideal = env.depth_source.rows(poses, ["ideal"] * 16)
        mixed = env.depth_source.rows(poses, models)
        for b, m in enumerate(models):
            same = np.array_equal(mixed[b], ideal[b], equal_nan=True)
            assert same == (m == "ideal"), (b, m)
        for _ in range(20):
            env.step(np.tile([1.0, 0.0], (16, 1)).astype(np.float32))
        winds = env.worlds.states[:, STATE.wind]
        assert not np.allclose(winds[0], winds[1])
    finally:
        env.close()
