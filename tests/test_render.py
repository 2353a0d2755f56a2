"""Renderer checks on small synthetic scenes, against analytic depth, K and the frame helpers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from droneulator import frames
from droneulator.config import CameraConfig
from droneulator.render import CameraFrame, Renderer
from droneulator.scenes.base import CollisionModel, MeshPart, Scene, SemanticClass
from droneulator.sensors.camera import intrinsics, project

WHITE = np.full((4, 4, 4), 255, dtype=np.uint8)


def quad(
    corners: np.ndarray, cls: SemanticClass, texture: str = "white", alpha_test: bool = False
) -> MeshPart:
    """Two triangles over four corners (counter-clockwise seen from the front), uv over [0, 1]^2."""
    corners = np.asarray(corners, dtype=np.float32)
    n = np.cross(corners[1] - corners[0], corners[2] - corners[0])
    return MeshPart(
        name=f"quad_{int(cls)}",
        positions=corners,
        normals=np.tile(n / np.linalg.norm(n), (4, 1)).astype(np.float32),
        uvs=np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=np.float32),
        class_ids=np.full(4, cls, dtype=np.uint8),
        indices=np.array([[0, 1, 2], [0, 2, 3]], dtype=np.uint32),
        texture=texture,
        alpha_test=alpha_test,
    )


def ground(half: float = 100.0) -> MeshPart:
    return quad(
        [[-half, -half, 0], [half, -half, 0], [half, half, 0], [-half, half, 0]], SemanticClass.GROUND
    )


def cylinder(
    centre: tuple[float, float], radius: float, height: float, cls: SemanticClass, sides: int = 32
) -> MeshPart:
    ang = np.linspace(0, 2 * math.pi, sides, endpoint=False)
    ring = np.stack([np.cos(ang), np.sin(ang), np.zeros(sides)], 1)
    base = np.array([centre[0], centre[1], 0.0])
    pos = np.concatenate([base + radius * ring, base + radius * ring + [0, 0, height]])
    i = np.arange(sides)
    j = (i + 1) % sides
    idx = np.concatenate([np.stack([i, j, j + sides], 1), np.stack([i, j + sides, i + sides], 1)])
    return MeshPart(
        "cylinder",
        pos.astype(np.float32),
        np.concatenate([ring, ring]).astype(np.float32),
        np.zeros((2 * sides, 2), np.float32),
        np.full(2 * sides, cls, np.uint8),
        idx.astype(np.uint32),
        "white",
    )


def cube(centre: np.ndarray, side: float, cls: SemanticClass) -> MeshPart:
    """Axis-aligned cube with one quad (4 unshared vertices) per face."""
    faces = []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            u, v = (axis + 1) % 3, (axis + 2) % 3
            c = np.zeros((4, 3))
            c[:, axis] = sign
            c[:, u] = [-1, 1, 1, -1]
            c[:, v] = [-1, -1, 1, 1]
            if sign < 0:
                c = c[::-1]
            faces.append(quad(np.asarray(centre) + 0.5 * side * c, cls))
    return MeshPart(
        "cube",
        np.concatenate([f.positions for f in faces]),
        np.concatenate([f.normals for f in faces]),
        np.concatenate([f.uvs for f in faces]),
        np.concatenate([f.class_ids for f in faces]),
        np.concatenate([f.indices + 4 * k for k, f in enumerate(faces)]).astype(np.uint32),
        "white",
    )


def scene(parts: list[MeshPart], textures: dict[str, np.ndarray] | None = None) -> Scene:
    return Scene(
        name="test",
        seed=0,
        parts=parts,
        textures={"white": WHITE, **(textures or {})},
        collision=CollisionModel(np.ones((2, 2, 2)), np.zeros(3), 1.0),
        spawn_position=np.zeros(3),
        spawn_yaw=0.0,
        bounds_min=np.array([-10.0, -10.0, 0.0]),
        bounds_max=np.array([10.0, 10.0, 10.0]),
    )


def body(x: float, y: float, z: float, roll: float = 0.0, pitch: float = 0.0, yaw: float = 0.0) -> np.ndarray:
    return frames.transform_from_pose(np.array([x, y, z]), frames.quat_from_euler(roll, pitch, yaw))


def pixel_rays(cam: CameraConfig, T_wo: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World origin and (H, W, 3) world directions of every pixel's ray, scaled to optical z = 1."""
    v, u = np.mgrid[0 : cam.height, 0 : cam.width].astype(float)
    rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(intrinsics(cam)).T
    return T_wo[:3, 3], rays @ T_wo[:3, :3].T


def render_one(sc: Scene, cam: CameraConfig, T_wb: np.ndarray) -> CameraFrame:
    """One frame, copied out of the renderer's reused buffers."""
    with Renderer(sc, [cam], shadow_map_size=512) as r:
        f = r.render(T_wb)[cam.name]
        return CameraFrame(f.name, f.rgb.copy(), f.depth.copy(), f.seg.copy(), f.K, f.T_world_optical)


def test_plane_facing_camera_depth_exact_and_misses_nan() -> None:
    cam = CameraConfig(position=(0.0, 0.0, 0.0))
    wall = quad([[10, 50, -50], [10, -50, -50], [10, -50, 50], [10, 50, 50]], SemanticClass.ROCK)
    f = render_one(scene([wall]), cam, body(0, 0, 2))
    assert f.rgb.shape == (480, 640, 3) and f.depth.dtype == np.float32 and f.seg.dtype == np.uint8
    np.testing.assert_allclose(f.depth, 10.0, atol=1e-3)
    assert (f.seg == SemanticClass.ROCK).all()

    half_wall = quad([[10, 0, -50], [10, -50, -50], [10, -50, 50], [10, 0, 50]], SemanticClass.ROCK)
    f = render_one(scene([half_wall]), cam, body(0, 0, 2))
    left, right = f.depth[:, :310], f.depth[:, 330:]  # the wall's edge projects to the centre column
    assert np.isnan(left).all() and (f.seg[:, :310] == SemanticClass.SKY).all()
    np.testing.assert_allclose(right, 10.0, atol=1e-3)
    assert (f.seg[:, 330:] == SemanticClass.ROCK).all()


def test_tilted_camera_and_plane_depth_matches_analytic() -> None:
    cam = CameraConfig(position=(0.1, 0.05, -0.02), rpy_deg=(4.0, 25.0, -8.0), hfov_deg=80.0)
    T_wb = body(1.0, -2.0, 3.0, roll=0.05, pitch=0.1, yaw=0.6)
    # A 12 m square plane through p0 with a tilted normal.
    p0, n = np.array([8.0, 3.0, 0.5]), np.array([-0.5, -0.3, 0.8])
    n /= np.linalg.norm(n)
    a = np.cross(n, [0, 0, 1.0])
    a /= np.linalg.norm(a)
    b = np.cross(n, a)
    plane = quad(
        [p0 - 6 * a - 6 * b, p0 + 6 * a - 6 * b, p0 + 6 * a + 6 * b, p0 - 6 * a + 6 * b],
        SemanticClass.GROUND,
    )
    f = render_one(scene([plane]), cam, T_wb)

    T_wo = frames.T_world_optical(T_wb, frames.camera_mount(np.array(cam.position), cam.rpy))
    np.testing.assert_allclose(f.T_world_optical, T_wo)
    o, d = pixel_rays(cam, T_wo)
    t = ((p0 - o) @ n) / (d @ n)
    hit = o + t[..., None] * d
    extent = np.maximum(np.abs((hit - p0) @ a), np.abs((hit - p0) @ b))
    inside = (t > 0) & (extent < 5.95)
    outside = (t < 0) | (extent > 6.05)
    assert inside.mean() > 0.3 and outside.mean() > 0.05
    np.testing.assert_allclose(f.depth[inside], t[inside], atol=1e-3)
    assert np.isnan(f.depth[outside]).all() and (f.seg[outside] == SemanticClass.SKY).all()
    assert (f.seg[inside] == SemanticClass.GROUND).all()


def test_trunk_sky_and_ground_classes() -> None:
    cam = CameraConfig(position=(0.0, 0.0, 0.0))
    sc = scene([ground(), cylinder((5.0, 0.0), 0.3, 4.0, SemanticClass.TRUNK)])
    T_wb = body(0, 0, 1.5)
    f = render_one(sc, cam, T_wb)
    T_wo = f.T_world_optical
    u, v = np.round(
        project(f.K, frames.transform_points(frames.invert_transform(T_wo), [5.0, 0.0, 1.5]))
    ).astype(int)
    assert f.seg[v, u] == SemanticClass.TRUNK
    assert f.depth[v, u] == pytest.approx(4.7, abs=5e-3)  # front of the trunk, on the optical axis
    assert f.seg[0, 0] == SemanticClass.SKY and np.isnan(f.depth[0, 0])
    assert f.seg[-1, 0] == SemanticClass.GROUND and np.isfinite(f.depth[-1, 0])
    sky_rgb = f.rgb[0, 0].astype(int)
    assert sky_rgb[2] > sky_rgb[0]  # blue-ish sky gradient


@pytest.mark.parametrize(
    ("cam", "T_wb"),
    [
        (CameraConfig(rpy_deg=(3.0, 12.0, -5.0)), body(0.0, 0.0, 1.0, roll=0.1, pitch=-0.05, yaw=0.3)),
        (
            CameraConfig(width=333, height=211, hfov_deg=60.0, position=(0.0, 0.1, -0.05)),
            body(0.5, 0.3, 1.2, yaw=-0.2),
        ),
    ],
)
def test_projected_point_matches_rendered_blob(cam: CameraConfig, T_wb: np.ndarray) -> None:
    centre = np.array([6.0, 2.0, 2.2])
    f = render_one(scene([ground(), cube(centre, 0.15, SemanticClass.FRUIT)]), cam, T_wb)
    np.testing.assert_allclose(f.K, intrinsics(cam))
    p_opt = frames.transform_points(frames.invert_transform(f.T_world_optical), centre)
    expected = project(f.K, p_opt)
    vs, us = np.nonzero(f.seg == SemanticClass.FRUIT)
    assert len(us) > 10
    assert abs(us.mean() - expected[0]) < 1.0 and abs(vs.mean() - expected[1]) < 1.0
    assert abs(us.mean() - (cam.width - 1) / 2) > 20  # off-centre both ways: catches flips and mirrors
    assert abs(vs.mean() - (cam.height - 1) / 2) > 10


def test_camera_pitched_down_and_custom_intrinsics() -> None:
    down = CameraConfig(
        name="down", width=160, height=120, hfov_deg=70.0, position=(0.0, 0.0, -0.1), rpy_deg=(0.0, 90.0, 0.0)
    )
    front = CameraConfig(name="front", width=320, height=240, hfov_deg=100.0)
    with Renderer(scene([ground()]), [down, front], shadow_map_size=256) as r:
        out = r.render(body(2.0, 1.0, 3.0, yaw=0.7))
        d = out["down"]
        assert d.depth.shape == (120, 160) and d.rgb.shape == (120, 160, 3)
        np.testing.assert_allclose(d.depth, 2.9, atol=1e-3)  # straight down: every pixel at the height
        np.testing.assert_allclose(d.K, intrinsics(down))
        assert d.K[0, 0] == pytest.approx(80.0 / math.tan(math.radians(35.0)))
        optical_z = d.T_world_optical[:3, 2]
        np.testing.assert_allclose(optical_z, [0.0, 0.0, -1.0], atol=1e-9)
        f = out["front"]
        assert f.depth.shape == (240, 320)
        assert (f.seg[:100] == SemanticClass.SKY).all() and (f.seg[140:] == SemanticClass.GROUND).all()


def test_alpha_tested_card_writes_only_kept_texels() -> None:
    leaf = np.zeros((64, 64, 4), dtype=np.uint8)
    leaf[:, 32:] = (40, 160, 40, 255)  # right half opaque, left half transparent
    card = quad(
        [[2, 0.5, 1.5], [2, -0.5, 1.5], [2, -0.5, 2.5], [2, 0.5, 2.5]], SemanticClass.CANOPY, "leaf", True
    )
    cam = CameraConfig(position=(0.0, 0.0, 0.0))
    f = render_one(scene([card], {"leaf": leaf}), cam, body(0, 0, 2))
    # The card spans u, v in [240, 400) x [160, 320); its transparent half is the left one in the image.
    assert (f.seg[170:310, 250:310] == SemanticClass.SKY).all() and np.isnan(f.depth[170:310, 250:310]).all()
    assert (f.seg[170:310, 330:390] == SemanticClass.CANOPY).all()
    np.testing.assert_allclose(f.depth[170:310, 330:390], 2.0, atol=1e-3)


def test_deterministic_and_depth_seg_mode_agrees() -> None:
    leaf = np.zeros((64, 64, 4), dtype=np.uint8)
    leaf[8:56, 8:56] = (50, 150, 50, 255)
    rng = np.random.default_rng(1)
    grass = np.concatenate([rng.integers(60, 140, (128, 128, 3)), np.full((128, 128, 1), 255)], 2).astype(
        np.uint8
    )
    g = ground(20.0)
    g.texture, g.uvs = "grass", g.uvs * 10
    cards = [
        quad(
            c + np.array([[0, 0, 0], [0.4, 0.2, 0], [0.4, 0.2, 0.4], [0, 0, 0.4]]),
            SemanticClass.CANOPY,
            "leaf",
            True,
        )
        for c in rng.uniform([3, -2, 0.5], [8, 2, 2.5], (40, 3))
    ]
    sc = scene(
        [g, cylinder((5.0, 0.5), 0.2, 3.0, SemanticClass.TRUNK), *cards], {"leaf": leaf, "grass": grass}
    )
    cam = CameraConfig(width=320, height=240)
    T_wb = body(0.0, 0.0, 1.8, yaw=0.1)
    with Renderer(sc, [cam], shadow_map_size=512) as r:
        a = r.render(T_wb)["front"]
        a = (a.rgb.copy(), a.depth.copy(), a.seg.copy())
        b = r.render(T_wb)["front"]
        geo = r.render(T_wb, rgb=False)["front"]
        assert geo.rgb is None
        np.testing.assert_array_equal(geo.seg, a[2])
        np.testing.assert_array_equal(geo.depth, a[1])
    with Renderer(sc, [cam], shadow_map_size=512) as r2:
        c = r2.render(T_wb)["front"]
    with Renderer(sc, [cam], shadows=False) as r3:
        unshadowed = r3.render(T_wb)["front"].rgb.astype(int)
    for x, y, z in zip(a, (b.rgb, b.depth, b.seg), (c.rgb, c.depth, c.seg), strict=True):
        np.testing.assert_array_equal(x, y)
        np.testing.assert_array_equal(x, z)
    assert (a[2] == SemanticClass.CANOPY).sum() > 100 and (a[2] == SemanticClass.TRUNK).sum() > 100
    darkening = (unshadowed - a[0].astype(int))[a[2] == SemanticClass.GROUND]
    assert darkening.min() >= 0 and (darkening.sum(axis=1) > 30).mean() > 0.02  # shadows only darken


def test_two_live_renderers_keep_their_own_contexts() -> None:
    cam = CameraConfig(width=160, height=120, position=(0.0, 0.0, 0.0))
    T_wb = body(0, 0, 2)
    near_wall = quad([[4, 50, -50], [4, -50, -50], [4, -50, 50], [4, 50, 50]], SemanticClass.ROCK)
    with Renderer(scene([near_wall]), [cam]) as a, Renderer(scene([ground()]), [cam]) as b:
        np.testing.assert_allclose(a.render(T_wb)["front"].depth, 4.0, atol=1e-3)
        assert (b.render(T_wb)["front"].seg[-1] == SemanticClass.GROUND).all()
        np.testing.assert_allclose(a.render(T_wb)["front"].depth, 4.0, atol=1e-3)
    with pytest.raises(RuntimeError):
        a.render(T_wb)
