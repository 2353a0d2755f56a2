"""Procedural scenes: registry, determinism, mesh validity, textures and collision."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from droneulator.scenes import get_scene, list_scenes
from droneulator.scenes.base import Scene, SemanticClass
from droneulator.scenes.collision import (
    CLAMP_DISTANCE,
    Box,
    Capsule,
    Ellipsoid,
    Sphere,
    build_collision,
    primitive_distance,
    sdf_lookup_many,
)
from droneulator.scenes.geometry import Mesh, box, cylinder, ground_grid, icosphere, tube

SCENES = ("default", "orchard", "planning", "tree_inspection", "vineyard")
BASE_CLASSES = {SemanticClass.GROUND, SemanticClass.TRUNK, SemanticClass.BRANCH, SemanticClass.CANOPY}
EXTRA_CLASSES = {
    "orchard": {SemanticClass.FRUIT},
    "vineyard": {SemanticClass.POST, SemanticClass.WIRE},
}
TRIANGLE_BUDGET = {"orchard": 150_000}
VEHICLE_RADIUS = 0.25


@pytest.fixture(scope="module", params=SCENES)
def scene(request: pytest.FixtureRequest) -> Scene:
    return get_scene(request.param, 0)


def test_registry_lists_every_scene() -> None:
    scenes = list_scenes()
    assert set(SCENES) <= set(scenes)
    assert all(isinstance(d, str) and d for d in scenes.values())


def test_unknown_scene_names_the_known_ones() -> None:
    with pytest.raises(ValueError) as err:
        get_scene("nope")
    for name in SCENES:
        assert name in str(err.value)


def test_get_scene_is_cached() -> None:
    assert get_scene("default", 0) is get_scene("default", 0)


def test_disk_cache_gives_the_built_scene_rebuilds_a_bad_file_and_keeps_its_limit(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from droneulator import scenes

    monkeypatch.setenv("DRONEULATOR_CACHE_DIR", str(tmp_path))
    scenes._load()
    builds: list[int] = []

    def build() -> Scene:
        builds.append(1)
        return scenes._REGISTRY["planning"][1](3)

    a = scenes._cached("planning", 3, build)
    b = scenes._cached("planning", 3, build)
    assert len(builds) == 1 and b is not a  # the second came from the file
    for pa, pb in zip(a.parts, b.parts, strict=True):
        for field in ("positions", "normals", "uvs", "class_ids", "indices"):
            np.testing.assert_array_equal(getattr(pa, field), getattr(pb, field))
    assert a.textures.keys() == b.textures.keys()
    for name in a.textures:
        np.testing.assert_array_equal(a.textures[name], b.textures[name])
    np.testing.assert_array_equal(a.collision.sdf, b.collision.sdf)
    assert a.landmarks.keys() == b.landmarks.keys() and (a.name, a.seed) == (b.name, b.seed)
    # a truncated file (a crash mid-write elsewhere) is built again and replaced
    (path,) = tmp_path.glob("planning-3-*.pkl")
    path.write_bytes(path.read_bytes()[:100])
    scenes._cached("planning", 3, build)
    assert len(builds) == 2 and scenes._cached("planning", 3, build) is not None and len(builds) == 2
    # the least recently used go beyond the limit
    monkeypatch.setattr(scenes, "CACHE_FILES", 2)
    for seed in (4, 5, 6):
        scenes._cached("planning", seed, lambda: a)
    assert sorted(p.name.split("-")[1] for p in tmp_path.glob("*.pkl")) == ["5", "6"]
    # off: built every time, nothing written
    monkeypatch.setenv("DRONEULATOR_CACHE_DIR", "off")
    scenes._cached("planning", 7, build)
    assert len(builds) == 3 and not list(tmp_path.glob("planning-7-*"))


@pytest.mark.parametrize("name", ["vineyard", "tree_inspection"])
def test_vegetation_density_scales_the_leaves_and_keeps_the_collision_model(name: str) -> None:
    def canopy(s: Scene) -> int:
        return sum(int((p.class_ids[p.indices[:, 0]] == SemanticClass.CANOPY).sum()) for p in s.parts)

    sparse, full, dense = (get_scene(name, 0, v) for v in (0.4, 1.0, 1.6))
    assert full is get_scene(name, 0) and full.vegetation == 1.0 and sparse.vegetation == 0.4
    assert canopy(sparse) < 0.75 * canopy(full) and canopy(dense) > 1.25 * canopy(full)
    np.testing.assert_array_equal(sparse.collision.sdf, full.collision.sdf)
    with pytest.raises(ValueError, match=r"vegetation must lie in \[0.1, 3\]"):
        get_scene(name, 0, 5.0)


def test_scene_builds_within_budget(scene: Scene) -> None:
    assert scene.parts
    assert 0 < scene.triangle_count <= TRIANGLE_BUDGET.get(scene.name, 100_000)
    names = [p.name for p in scene.parts]
    assert len(names) == len(set(names))


def test_required_classes_present(scene: Scene) -> None:
    present = {SemanticClass(int(c)) for p in scene.parts for c in np.unique(p.class_ids)}
    assert BASE_CLASSES | EXTRA_CLASSES.get(scene.name, set()) <= present
    assert SemanticClass.SKY not in present


def test_mesh_arrays_valid(scene: Scene) -> None:
    for p in scene.parts:
        n = len(p.positions)
        assert p.positions.dtype == np.float32 and p.positions.shape == (n, 3)
        assert p.normals.dtype == np.float32 and p.normals.shape == (n, 3)
        assert p.uvs.dtype == np.float32 and p.uvs.shape == (n, 2)
        assert p.class_ids.dtype == np.uint8 and p.class_ids.shape == (n,)
        assert p.indices.dtype == np.uint32 and p.indices.ndim == 2 and p.indices.shape[1] == 3
        assert int(p.indices.max()) < n
        assert np.all(np.isfinite(p.positions)) and np.all(np.isfinite(p.uvs))
        np.testing.assert_allclose(np.linalg.norm(p.normals, axis=1), 1.0, atol=1e-4)
        # class constant over every triangle (no vertex shared between classes)
        tri_cls = p.class_ids[p.indices]
        assert np.all(tri_cls == tri_cls[:, :1])
        assert p.texture in scene.textures


def test_textures_rgba_power_of_two(scene: Scene) -> None:
    for name, tex in scene.textures.items():
        assert tex.dtype == np.uint8 and tex.ndim == 3 and tex.shape[2] == 4, name
        h, w = tex.shape[:2]
        assert h & (h - 1) == 0 and w & (w - 1) == 0, name
        assert tex[..., :3].std() > 5.0, name  # has detail
    for p in scene.parts:
        alpha = scene.textures[p.texture][..., 3]
        if p.alpha_test:
            assert 0.2 < (alpha > 127).mean() < 0.9
        else:
            assert alpha.min() == 255


def test_same_seed_identical_other_seed_different() -> None:
    from droneulator.scenes import _REGISTRY

    for name in SCENES:
        a = get_scene(name, 0)
        again = _REGISTRY[name][1](0)
        assert [p.name for p in a.parts] == [p.name for p in again.parts]
        for pa, pb in zip(a.parts, again.parts, strict=True):
            for field in ("positions", "normals", "uvs", "class_ids", "indices"):
                np.testing.assert_array_equal(getattr(pa, field), getattr(pb, field))
        np.testing.assert_array_equal(a.collision.sdf, again.collision.sdf)
        np.testing.assert_array_equal(a.spawn_position, again.spawn_position)
        other = get_scene(name, 1)
        differs = any(
            pa.positions.shape != pb.positions.shape or not np.array_equal(pa.positions, pb.positions)
            for pa, pb in zip(a.parts, other.parts, strict=True)
        )
        assert differs, name


def test_spawn_bounds_and_heading(scene: Scene) -> None:
    sp = scene.spawn_position
    assert sp.shape == (3,) and sp[2] == 0.0
    assert scene.in_bounds(sp + [0, 0, 1.0])
    assert np.all(scene.bounds_max - scene.bounds_min > 10.0) and scene.bounds_min[2] == 0.0
    assert scene.bounds_max[2] >= 10.0
    # something to look at: a trunk within +-50 degrees of the spawn heading
    rel = scene.landmarks["trunks"][:, :2] - sp[:2]
    bearing = np.arctan2(rel[:, 1], rel[:, 0]) - scene.spawn_yaw
    bearing = (bearing + math.pi) % (2 * math.pi) - math.pi
    assert np.any(np.abs(bearing) < math.radians(50))


def test_collision_trunk_inside_spawn_free(scene: Scene) -> None:
    col = scene.collision
    for trunk in scene.landmarks["trunks"][:8]:
        assert col.distance(trunk + [0.0, 0.0, 1.0]) < 0.0
    for z in (0.5, 1.5, 3.0):
        assert col.distance(scene.spawn_position + [0.0, 0.0, z]) > VEHICLE_RADIUS
    assert col.distance(np.array([1e4, 0.0, 1.0])) == CLAMP_DISTANCE


def test_tree_inspection_landmarks() -> None:
    s = get_scene("tree_inspection")
    np.testing.assert_allclose(s.landmarks["tree"], [0.0, 0.0, 0.0])
    h, r = float(s.landmarks["tree_height"][0]), float(s.landmarks["crown_radius"][0])
    assert 3.0 < h < 12.0 and 1.0 < r < 6.0
    canopy = np.concatenate([p.positions[p.class_ids == SemanticClass.CANOPY] for p in s.parts])
    near = canopy[np.linalg.norm(canopy[:, :2], axis=1) < 15.0]
    assert float(near[:, 2].max()) == pytest.approx(h, abs=1e-3)
    assert float(np.linalg.norm(near[:, :2], axis=1).max()) == pytest.approx(r, abs=1e-3)
    assert s.collision.distance(np.array([0.0, 0.0, h * 0.6])) < 0.0  # crown is an obstacle
    assert np.linalg.norm(s.spawn_position[:2]) > r + 3.0


def test_vineyard_alleys_free() -> None:
    s = get_scene("vineyard")
    lm = s.landmarks
    for key in ("row_y", "row_x_min", "row_x_max", "row_half_width", "alley_y", "canopy_z"):
        assert key in lm
    xs = np.linspace(lm["row_x_min"][0], lm["row_x_max"][0], 41)
    for y in lm["alley_y"]:
        pts = np.stack([xs, np.full_like(xs, y), np.full_like(xs, 1.5)], 1)
        d = sdf_lookup_many(s.collision.sdf, s.collision.origin, s.collision.resolution, pts)
        assert d.min() > 0.5
    # and the rows themselves are obstacles at hedge height
    for y in lm["row_y"]:
        assert s.collision.distance(np.array([0.0, y, 1.5])) < 0.0
    width = np.diff(lm["row_y"]).min() - 2 * lm["row_half_width"][0]
    assert 2.4 <= width <= 3.2


def test_sdf_matches_primitives() -> None:
    prims = [
        Capsule(np.array([0.0, 0.0, 0.0]), np.array([0.3, 0.2, 3.0]), 0.2),
        Sphere(np.array([2.0, 0.0, 2.0]), 0.6),
        Ellipsoid(np.array([-2.0, 1.0, 1.0]), np.array([0.8, 0.5, 0.4])),
        Box(np.array([0.0, -2.0, 1.0]), np.array([1.0, 0.2, 1.0])),
    ]
    col = build_collision(prims, np.array([-6.0, -6.0, 0.0]), np.array([6.0, 6.0, 6.0]), resolution=0.1)
    rng = np.random.default_rng(0)
    pts = rng.uniform([-4, -4, 0], [4, 4, 5], (400, 3))
    exact = np.minimum(primitive_distance(prims, pts), CLAMP_DISTANCE)
    got = sdf_lookup_many(col.sdf, col.origin, col.resolution, pts)
    assert np.abs(got - exact).max() < 0.06
    assert col.distance(np.array([0.15, 0.1, 1.5])) < -0.1
    assert col.distance(np.array([2.0, 0.0, 2.0])) == pytest.approx(-0.6, abs=0.02)
    assert col.distance(np.array([50.0, 0.0, 1.0])) == CLAMP_DISTANCE
    assert col.distance(np.array([np.nan, 0.0, 1.0])) == CLAMP_DISTANCE


@pytest.mark.parametrize(
    "mesh",
    [
        tube(np.array([[0, 0, 0], [0.1, 0, 1], [0.4, 0.1, 2]]), np.array([0.3, 0.2, 0.1]), 8),
        cylinder(np.zeros(3), np.array([1.0, 0.5, 0.2]), 0.2, 0.1),
        box(np.zeros(3), np.array([0.5, 0.2, 1.0])),
        icosphere(np.zeros(3), 1.0, 2),
        ground_grid((-5, 5), (-5, 5), 1.0, 4.0, warp=0.1),
    ],
    ids=["tube", "cylinder", "box", "icosphere", "ground"],
)
def test_front_faces_agree_with_normals(mesh: Mesh) -> None:
    tri = mesh.positions[mesh.indices]
    face_n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    vert_n = mesh.normals[mesh.indices].sum(axis=1)
    keep = np.linalg.norm(face_n, axis=1) > 1e-9
    assert np.all((face_n[keep] * vert_n[keep]).sum(axis=1) > 0)
