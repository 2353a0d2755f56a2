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
    noise = np.array([d.depth_noise_scale for d in draws])
    dropout = np.array([d.depth_dropout_scale for d in draws])
    assert noise.min() >= 0.5 and noise.max() <= 2.0 and dropout.min() >= 0.5 and dropout.max() <= 1.5
    cfg = spec.apply(load_config(), draws[0])
    cam = cfg.render.cameras[0]
    assert (cam.depth_model, cam.depth_noise_scale, cam.depth_dropout_scale) == (
        draws[0].depth_model, draws[0].depth_noise_scale, draws[0].depth_dropout_scale
    )  # fmt: skip


def test_the_scene_is_drawn_for_a_run_and_per_episode_among_an_rl_environments_variants():
    from test_rl_vector import rollout_single, rollout_vector

    from droneulator.workflows.rl.env import env_config, scene_variants

    spec = ["randomize.enabled=true", "randomize.scene_seed=[10, 12]", "randomize.vegetation=[0.5, 1.5]"]
    cfg = load_config(overrides=spec)
    draws = [cfg.randomize.draw(np.random.default_rng(s)) for s in range(60)]
    assert {d.scene_seed for d in draws} == {10, 11, 12}
    assert all(0.5 <= d.vegetation <= 1.5 for d in draws) and np.std([d.vegetation for d in draws]) > 0.2
    run = cfg.randomize.apply(cfg, draws[0])  # a capture or a planning run: its scene
    assert (run.seed, run.vegetation) == (draws[0].scene_seed, draws[0].vegetation)
    assert (env_config(env_config(cfg)).seed, env_config(cfg).vegetation) == (cfg.seed, 1.0)  # idempotent
    variants = [(c.seed, c.vegetation) for c in scene_variants(env_config(cfg))]
    assert variants == [(c.seed, c.vegetation) for c in scene_variants(env_config(cfg))]  # from the seed
    assert len(variants) == cfg.randomize.scene_variants == 4
    assert {s for s, _ in variants} <= {10, 11, 12} and all(0.5 <= v <= 1.5 for _, v in variants)
    assert len(scene_variants(env_config(load_config()))) == 1  # no randomisation: the config's scene

    # calm and ideal otherwise, so that the batched env must equal the single env episode by episode
    calm_spec = [*spec, "randomize.wind_speed_m_s=[0, 0]", 'randomize.depth_models=["ideal"]']
    calm = load_config(overrides=calm_spec)
    n, steps = 3, 300
    actions = np.random.default_rng(7).uniform(-1, 1, (steps, n, 2)).astype(np.float32)
    venv = VineyardNavVectorEnv(n, calm)
    try:
        vec = rollout_vector(venv, 100, actions)
        assert len(venv._batches) >= 2  # the envs flew in several scenes
    finally:
        venv.close()
    env = VineyardNavEnv(calm, depth="raycast")
    try:
        for i in range(n):
            one = rollout_single(env, 100 + i, actions[:, i])
            np.testing.assert_allclose(np.array(vec["obs"])[:, i], np.array(one["obs"]), atol=1e-5, rtol=0)
            np.testing.assert_allclose(np.array(vec["reward"])[:, i], one["reward"], atol=1e-6, rtol=0)
            np.testing.assert_array_equal(np.array(vec["terminated"])[:, i], one["terminated"])
        flown = set()
        for seed in range(8):  # each reset: one of the variants, the world and its depth that scene's
            env.reset(seed=seed)
            scene = env.backend.scene
            assert (scene.seed, scene.vegetation) == (env.conditions.scene_seed, env.conditions.vegetation)
            assert env.scene is scene and (scene.seed, scene.vegetation) in variants
            flown.add((scene.seed, scene.vegetation))
        assert len(flown) >= 3
    finally:
        env.close()
    with pytest.raises(ValueError, match="randomize.scene_variants"):
        load_config(overrides=["randomize.scene_variants=0"])
    with pytest.raises(ValueError, match="randomize.vegetation"):
        load_config(overrides=["randomize.vegetation=[0, 1]"])


def test_depth_noise_and_dropouts_follow_their_factors_per_image():
    """A batch of the same wall at 4 m through the D435 model with per-image factors: the depth error's
    std follows the noise factor, and a thin post's dropouts follow the dropout factor."""
    from droneulator.config import CameraConfig
    from droneulator.config.camera_presets import DEPTH_PRESETS
    from droneulator.sensors.camera import intrinsics
    from droneulator.sensors.depth_models import apply_depth_model

    cam = CameraConfig(width=320, height=240, hfov_deg=90.0)
    K = intrinsics(cam)
    wall = np.full((3, 240, 320), 4.0, dtype=np.float32)
    wall[:, :, 200:202] = 2.0  # a 2 px post in front: a thin structure
    noise = np.array([0.5, 1.0, 2.0])
    dropout = np.array([0.0, 1.0, 10.0 / 7.0])  # 0, the preset's 0.7 and 1.0
    out = apply_depth_model(wall, DEPTH_PRESETS["d435"], K, np.random.default_rng(0), noise, dropout)
    err = np.nanstd((out - 4.0)[:, 20:-20, 20:150], axis=(1, 2))
    np.testing.assert_allclose(err / err[1], noise, rtol=0.08)
    lost = np.isnan(out[:, 20:-20, 200:202]).mean(axis=(1, 2))
    assert lost[0] < 0.02 and 0.4 < lost[1] < 0.95 and lost[2] > 0.98


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
            world = env.backend.world
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
        poses[:, :3, 3] = env.states[0, STATE.x]
        scales = env._depth_scales.copy()
        assert scales[:, 0].min() >= 0.5 and scales[:, 0].max() <= 2.0 and scales[:, 0].std() > 0.1
        ideal = env._batch(0).cameras.centre_rows(poses, ["ideal"] * 16, scales)
        mixed = env._batch(0).cameras.centre_rows(poses, models, scales)
        for b, m in enumerate(models):
            same = np.array_equal(mixed[b], ideal[b], equal_nan=True)
            assert same == (m == "ideal"), (b, m)
        for _ in range(20):
            env.step(np.tile([1.0, 0.0], (16, 1)).astype(np.float32))
        winds = env.states[:, STATE.wind]
        assert not np.allclose(winds[0], winds[1])
    finally:
        env.close()
