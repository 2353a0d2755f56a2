"""Local planner core: occupancy from rendered depth, A*, the EGO-style B-spline optimiser, the planner."""

from __future__ import annotations

import time

import numpy as np
import pytest

from droneulator import frames
from droneulator.config import CameraConfig
from droneulator.render import Renderer
from droneulator.scenes.base import CollisionModel, MeshPart, Scene, SemanticClass
from droneulator.workflows.planning.config import PlannerConfig
from droneulator.workflows.planning.mapping import LocalMap

WALL_X = 4.0


def quad(corners: list[list[float]]) -> MeshPart:
    """Two triangles over four corners, counter-clockwise seen from the front."""
    c = np.asarray(corners, dtype=np.float32)
    n = np.cross(c[1] - c[0], c[2] - c[0])
    return MeshPart(
        name="quad",
        positions=c,
        normals=np.tile(n / np.linalg.norm(n), (4, 1)).astype(np.float32),
        uvs=np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=np.float32),
        class_ids=np.full(4, SemanticClass.ROCK, dtype=np.uint8),
        indices=np.array([[0, 1, 2], [0, 2, 3]], dtype=np.uint32),
        texture="white",
    )


def wall_depth() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Depth of a wall (x = WALL_X, |y| <= 3, 0 <= z <= 4) seen from (0, 0, 1.5) looking along +x."""
    wall = quad([[WALL_X, 3, 0], [WALL_X, -3, 0], [WALL_X, -3, 4], [WALL_X, 3, 4]])
    sc = Scene(
        name="wall",
        seed=0,
        parts=[wall],
        textures={"white": np.full((4, 4, 4), 255, dtype=np.uint8)},
        collision=CollisionModel(np.ones((2, 2, 2)), np.zeros(3), 1.0),
        spawn_position=np.zeros(3),
        spawn_yaw=0.0,
        bounds_min=np.array([-10.0, -10.0, 0.0]),
        bounds_max=np.array([10.0, 10.0, 10.0]),
    )
    cam = CameraConfig(position=(0.0, 0.0, 0.0))
    T_wb = frames.transform_from_pose(np.array([0.0, 0.0, 1.5]), frames.quat_from_yaw(0.0))
    with Renderer(sc, [cam], shadows=False) as r:
        f = r.render(T_wb, rgb=False)[cam.name]
        return f.depth.copy(), f.T_world_optical, f.K


@pytest.fixture(scope="module")
def wall() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return wall_depth()


def test_rendered_wall_becomes_occupied_and_space_before_it_free(wall) -> None:
    depth, T_wo, K = wall
    assert np.isnan(depth).any() and np.isfinite(depth).any()  # sky above the wall: no returns
    cfg = PlannerConfig()
    m = LocalMap(cfg, centre=np.array([0.0, 0.0, 1.5]))
    m.update(depth, T_wo, K)
    assert not m.occupied_grid().any()  # one hit (p 0.7) stays below the occupied threshold (0.8)
    m.update(depth, T_wo, K)
    occ = m.point(np.argwhere(m.occupied_grid()))
    assert len(occ) > 500
    # every occupied voxel lies on the wall, within one voxel
    assert np.all(np.abs(occ[:, 0] - WALL_X) <= cfg.resolution)
    assert np.all(np.abs(occ[:, 1]) <= 3 + cfg.resolution) and np.all(occ[:, 2] >= -cfg.resolution)
    # the wall is covered wherever it is within max_ray_length: every (y, z) cell has a voxel
    ys, zs = np.meshgrid(np.arange(-1.95, 2.0, 0.1), np.arange(0.55, 2.5, 0.1))
    cells = {(round(y, 2), round(z, 2)) for y, z in zip(occ[:, 1], occ[:, 2], strict=True)}
    assert all((round(y, 2), round(z, 2)) in cells for y, z in zip(ys.ravel(), zs.ravel(), strict=True))
    # free space in front: observed (log-odds < 0), not occupied, not inflated beyond the margin
    xs, ys, zs = np.meshgrid(np.arange(0.55, 3.3, 0.1), np.arange(-1.45, 1.5, 0.1), np.arange(1.05, 2.0, 0.1))
    front = np.stack([xs.ravel(), ys.ravel(), zs.ravel()], 1)
    x = front[:, 0]
    in_view = (np.abs(front[:, 1]) < x - 0.15) & (np.abs(front[:, 2] - 1.5) < 0.75 * x - 0.15)
    front = front[in_view]
    assert len(front) > 1000
    idx = m.index(front)
    assert np.all(m.logodds[idx[:, 0], idx[:, 1], idx[:, 2]] < 0)
    assert not m.is_occupied(front, inflated=True).any()
    # inflation: within vehicle radius + margin of the wall is blocked, further out is not
    assert m.is_occupied(np.array([WALL_X - 0.35, 0.0, 1.5]))
    assert not m.is_occupied(np.array([WALL_X - 0.35, 0.0, 1.5]), inflated=False)
    assert not m.is_occupied(np.array([WALL_X - cfg.inflation - 0.25, 0.0, 1.5]))
    # behind the wall nothing was seen
    assert m.logodds[tuple(m.index([WALL_X + 0.5, 0.0, 1.5]))] == 0


def test_map_scrolls_and_keeps_what_it_saw(wall) -> None:
    depth, T_wo, K = wall
    cfg = PlannerConfig()
    m = LocalMap(cfg, centre=np.array([0.0, 0.0, 1.5]))
    m.update(depth, T_wo, K)
    m.update(depth, T_wo, K)
    before = m.occupied_grid().sum()
    inflated = m.inflated_grid().sum()
    assert m.recenter(np.array([3.0, 0.5, 1.5]))
    assert np.allclose(m.centre, [3.0, 0.5, 1.5], atol=cfg.resolution)
    assert m.occupied_grid().sum() == before and m.inflated_grid().sum() == inflated
    assert m.is_occupied(np.array([WALL_X - 0.35, 0.0, 1.5]))
    assert not m.recenter(np.array([3.5, 0.5, 1.5]))  # within recenter_distance: no scroll
    m.recenter(np.array([30.0, 0.0, 1.5]))  # far away: everything forgotten
    assert not m.occupied_grid().any() and not m.inflated_grid().any()


def test_map_rejects_bad_input(wall) -> None:
    depth, T_wo, K = wall
    m = LocalMap(PlannerConfig())
    with pytest.raises(ValueError, match="float32"):
        m.update(depth.astype(np.float64), T_wo, K)
    with pytest.raises(ValueError, match="4x4"):
        m.update(depth, T_wo[:3], K)
    with pytest.raises(ValueError, match="pixel_skip"):
        PlannerConfig(pixel_skip=0)


def test_map_update_time_640x480(wall) -> None:
    """Measured, not asserted tightly (the CPU is shared): printed for the report."""
    depth, T_wo, K = wall
    m = LocalMap(PlannerConfig(), centre=np.array([0.0, 0.0, 1.5]))
    m.update(depth, T_wo, K)  # compile
    times = []
    for _ in range(10):
        t0 = time.perf_counter()
        m.update(depth, T_wo, K)
        times.append(time.perf_counter() - t0)
    print(f"map update 640x480, skip 4: median {1e3 * np.median(times):.2f} ms")
    assert np.median(times) < 0.2
