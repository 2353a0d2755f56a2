"""A one-vehicle in-process World with the real renderer on real scenes: lockstep timing, metric
depth and classes on known geometry, determinism, and the snapshot command."""

import json

import numpy as np
import pytest
from PIL import Image

from droneulator.cli import main
from droneulator.config import CameraConfig, load_config
from droneulator.frames import invert_transform, transform_points
from droneulator.scenes.base import SemanticClass
from droneulator.sensors.camera import project
from droneulator.world import World
from droneulator.world.world import NS


def small_config(scene: str, **cam) -> object:
    cfg = load_config(scene=scene)
    cfg.render.cameras = [CameraConfig(name="front", width=160, height=120, hfov_deg=90.0, **cam)]
    cfg.render.shadow_map_size = 1024
    return cfg


def test_frames_arrive_at_the_camera_rate_in_sim_time_without_skips():
    with World(config=small_config("default")) as world:
        uav = world.vehicle()
        world.reset(position=world.scene.spawn_position + [0, 0, 2.0])
        uav.velocity(1.0, 0.5)
        frames = world.run(2.0).frames
        assert len(frames) == 60
        period = round(NS / 30)
        assert [f.t_ns for f in frames] == [k * period for k in range(1, 61)]
        for f in frames:  # each frame was rendered from the state at exactly its stamp
            state = f.states[uav.name]
            assert state.t_ns == f.t_ns
            np.testing.assert_allclose(
                f.cameras[uav.name]["front"].T_world_optical[:3, 3],
                state.T_world_body[:3, 3] + state.T_world_body[:3, :3] @ [0.12, 0, 0],
            )


def test_trunk_is_classed_trunk_at_metric_depth_where_k_projects_it():
    with World(config=small_config("tree_inspection")) as world:
        tree = world.scene.landmarks["tree"]
        cam_pos = np.array([tree[0] - 5.0, tree[1], 1.0])
        world.reset(position=cam_pos - [0.12, 0, 0], yaw=0.0)  # camera looks along +x at the trunk
        frame = world.render().cameras[world.vehicle().name]["front"]
        point = np.array([tree[0], tree[1], 1.0])  # trunk axis at camera height
        p_opt = transform_points(invert_transform(frame.T_world_optical), point)
        u, v = np.round(project(frame.K, p_opt)).astype(int)
        assert (u, v) == (79, 59) or abs(u - 79.5) <= 1 and abs(v - 59.5) <= 1  # straight ahead: image centre
        assert frame.seg[v, u] == SemanticClass.TRUNK
        # depth at the trunk is the distance to the trunk surface: less than to its axis, more than 4 m
        assert 4.0 < frame.depth[v, u] < 5.0
        sky = frame.seg == SemanticClass.SKY
        assert sky.any() and np.all(np.isnan(frame.depth[sky])) and np.all(np.isfinite(frame.depth[~sky]))
        assert frame.seg[-1, u] == SemanticClass.GROUND
        # ground depth below the optical centre matches flat-ground geometry at 1 m height
        rows = np.arange(90, 120)
        expected = 1.0 * frame.K[1, 1] / (rows - frame.K[1, 2])
        np.testing.assert_allclose(frame.depth[rows, 20], expected, rtol=2e-3)


def test_same_seed_gives_identical_images():
    images = []
    for _ in range(2):
        with World(config=small_config("orchard")) as world:
            uav = world.vehicle()
            world.reset(position=world.scene.spawn_position + [0, 0, 1.5])
            uav.velocity(0.8, 0.2)
            f = world.run(0.5).frames[-1].cameras[uav.name]["front"]
            images.append((f.rgb.copy(), f.depth.copy(), f.seg.copy()))
    for a, b in zip(images[0], images[1], strict=True):
        np.testing.assert_array_equal(a, b)


def test_snapshot_command_writes_every_image(tmp_path):
    out = tmp_path / "snap"
    assert (
        main(
            [
                "snapshot",
                "--scene",
                "default",
                "--out",
                str(out),
                "--set",
                'render.cameras=[{"name": "front", "width": 200, "height": 150}]',
            ]
        )
        == 0
    )
    rgb = np.asarray(Image.open(out / "front_rgb.png"))
    depth = np.load(out / "front_depth.npy")
    seg = np.asarray(Image.open(out / "front_seg_ids.png"))
    info = json.loads((out / "front_camera_info.json").read_text())
    assert rgb.shape == (150, 200, 3) and depth.shape == (150, 200) and depth.dtype == np.float32
    assert seg.shape == (150, 200) and Image.open(out / "front_seg.png").mode == "RGB"
    assert (info["width"], info["height"]) == (200, 150) and info["frame_id"] == "front_optical_frame"
    K = np.array(info["K"]).reshape(3, 3)
    assert (
        K[0, 2] == pytest.approx(99.5) and K[1, 2] == pytest.approx(74.5) and K[0, 0] == pytest.approx(100.0)
    )
    assert np.all(np.isnan(depth[seg == SemanticClass.SKY]))
    assert np.all(np.isfinite(depth[seg != SemanticClass.SKY]))
    assert len(set(np.unique(seg)) & {SemanticClass.GROUND, SemanticClass.CANOPY, SemanticClass.SKY}) == 3


def test_cli_rejects_unknown_scene(capsys):
    assert main(["snapshot", "--scene", "moon", "--out", "unused"]) == 2
    assert "moon" in capsys.readouterr().err
