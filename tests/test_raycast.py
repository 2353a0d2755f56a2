"""DepthCaster (BVH ray casting) against the OpenGL renderer on llvmpipe, against analytic depth, and its
BVH against brute force.

Measured on the poses below (RL camera 128x9, 90 deg, far 10 m), pixels with a return in both:
vineyard, 40 poses: 99.93 % within 1 mm (median difference 2.4e-7 m), NaN pattern 99.989 % equal, 23
pixels differ (17 with an alpha-tested first surface, 22 beside a depth edge, none neither), the 32-sector
strip equal within 1e-3 in 39 of 40 poses (one sector off in the other); tree_inspection, 24 poses:
99.95 % within 1 mm, NaN pattern 99.996 % equal, 7 pixels differ (all on leaf cards and beside an edge),
every strip equal. The thresholds below leave some margin under those figures.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy.ndimage import maximum_filter, minimum_filter

pytest.importorskip("gymnasium")

from droneulator import frames  # noqa: E402
from droneulator.config import CameraConfig  # noqa: E402
from droneulator.render.raycast import DepthCaster  # noqa: E402
from droneulator.render.renderer import Renderer  # noqa: E402
from droneulator.scenes import get_scene  # noqa: E402
from droneulator.scenes.base import CollisionModel, MeshPart, Scene, SemanticClass  # noqa: E402
from droneulator.sensors.camera import Camera, intrinsics  # noqa: E402
from droneulator.workflows.rl.env import depth_strip, strips  # noqa: E402

RL_CAMERA = CameraConfig("rl_depth", 128, 9, 90.0, far=10.0)


def pose(x: float, y: float, z: float, yaw: float, pitch: float = 0.0, roll: float = 0.0) -> np.ndarray:
    return frames.transform_from_pose(np.array([x, y, z]), frames.quat_from_euler(roll, pitch, yaw))


def vineyard_poses(scene: Scene, seed: int = 0) -> np.ndarray:
    """Along the rows beside the hedge (grazing leaf cards), facing the hedge, at row ends close to the end
    post looking along the posts and wires, beside inner posts, and anywhere in the bounds."""
    rng = np.random.default_rng(seed)
    lm = scene.landmarks
    rows, alleys, post_x, wire_z = lm["row_y"], lm["alley_y"], lm["post_x"], lm["wire_z"]
    out = []
    for k in range(8):
        y = rows[k % len(rows)] + (0.6 + 0.3 * rng.random()) * (1 if k % 2 else -1)
        yaw = (0.0 if k < 4 else math.pi) + rng.normal(0, 0.08)
        out.append(pose(rng.uniform(-12, 12), y, rng.uniform(0.9, 1.9), yaw))
    for k in range(6):
        yaw = (math.pi / 2) * (1 if k % 2 else -1) + rng.normal(0, 0.2)
        out.append(pose(rng.uniform(-12, 12), alleys[k % len(alleys)], rng.uniform(0.8, 2.0), yaw))
    for k in range(6):
        side = 1 if k % 2 else -1
        x = side * (15.0 + rng.uniform(0.3, 0.8))
        z = rng.choice(wire_z) + rng.normal(0, 0.05)
        out.append(pose(x, rows[k % len(rows)] + rng.normal(0, 0.1), z, (math.pi if side > 0 else 0.0)))
    for k in range(4):
        out.append(pose(post_x[1 + k] - 0.5, rows[k] + 0.45, rng.uniform(0.9, 1.6), rng.uniform(-0.4, 0.4)))
    lo, hi = scene.bounds_min, scene.bounds_max
    for _ in range(16):
        p = (rng.uniform(lo[0], hi[0]), rng.uniform(lo[1], hi[1]), rng.uniform(0.5, 3.0))
        out.append(pose(*p, rng.uniform(-math.pi, math.pi), rng.normal(0, 0.15), rng.normal(0, 0.1)))
    return np.array(out)


def tree_poses(scene: Scene, n: int = 24, seed: int = 1) -> np.ndarray:
    """An orbit round the crown at 2.8-7 m, each pose looking at the crown centre."""
    rng = np.random.default_rng(seed)
    c = scene.landmarks["crown_center"]
    out = []
    for k in range(n):
        ang = 2 * math.pi * k / n
        r = rng.uniform(2.8, 7.0)
        p = np.array([c[0] + r * math.cos(ang), c[1] + r * math.sin(ang), rng.uniform(1.0, 5.5)])
        to = c - p
        pitch = -math.atan2(to[2], math.hypot(to[0], to[1])) + rng.normal(0, 0.05)  # positive looks down
        out.append(pose(*p, math.atan2(to[1], to[0]) + rng.normal(0, 0.1), pitch))
    return np.array(out)


def near_edge(depth: np.ndarray, far: float) -> np.ndarray:
    """Pixels whose 3x3 neighbourhood spans a depth discontinuity (over 5 cm + 2 %; NaN counts as far
    beyond the far plane)."""
    d = np.where(np.isnan(depth), 2 * far, depth)
    span = maximum_filter(d, size=(1, 3, 3), mode="nearest") - minimum_filter(
        d, size=(1, 3, 3), mode="nearest"
    )
    return span > 0.05 + 0.02 * np.minimum(d, far)


def opaque(scene: Scene) -> Scene:
    """``scene`` with every part opaque: its caster finds the first surface along each ray."""
    return dataclasses.replace(scene, parts=[dataclasses.replace(p, alpha_test=False) for p in scene.parts])


CASES = {
    "vineyard": (vineyard_poses, 0.998, 0.9995),
    "tree_inspection": (tree_poses, 0.998, 0.9995),
}


@pytest.fixture(scope="module", params=list(CASES))
def compared(request: pytest.FixtureRequest) -> dict:
    name = request.param
    make_poses, within_mm, nan_rate = CASES[name]
    scene = get_scene(name, 0)
    poses = make_poses(scene)
    caster = DepthCaster(scene, [RL_CAMERA])
    depth, tri = caster.trace(poses)
    first = DepthCaster(opaque(scene), [RL_CAMERA]).trace(poses)[1]
    gl = np.empty_like(depth)
    seg = np.empty(depth.shape, dtype=np.uint8)
    with Renderer(scene, [RL_CAMERA], shadows=False) as r:
        for k, T in enumerate(poses):
            f = r.render(T, rgb=False)[RL_CAMERA.name]
            gl[k], seg[k] = f.depth, f.seg
    return {
        "name": name,
        "poses": poses,
        "caster": caster,
        "depth": depth,
        "tri": tri,
        "first": first,
        "gl": gl,
        "seg": seg,
        "within_mm": within_mm,
        "nan_rate": nan_rate,
    }


def test_depth_matches_renderer(compared: dict) -> None:
    depth, gl, tri, first = compared["depth"], compared["gl"], compared["tri"], compared["first"]
    caster: DepthCaster = compared["caster"]
    assert depth.shape == gl.shape == (len(compared["poses"]), 9, 128) and depth.dtype == np.float32
    hit, gl_hit = ~np.isnan(depth), ~np.isnan(gl)
    both = hit & gl_hit
    assert both.mean() > 0.2  # the views see something
    assert (hit == gl_hit).mean() >= compared["nan_rate"]
    err = np.abs(depth - gl)
    assert (err[both] <= 1e-3).mean() >= compared["within_mm"]
    # where both agree they agree to float precision (the renderer's z is float32 eye-space z)
    assert np.median(err[both]) < 1e-5
    # disagreements only where the first surface is alpha-tested or beside a depth edge
    bad = (hit != gl_hit) | (both & (err > 1e-3))
    on_alpha = (first >= 0) & caster.alpha_tested[np.maximum(first, 0)]
    edge = near_edge(depth, RL_CAMERA.far) | near_edge(gl, RL_CAMERA.far)
    assert not (bad & ~on_alpha & ~edge).any()
    # the triangle seen carries the renderer's segmentation class
    cls = caster.triangle_class[np.maximum(tri, 0)]
    assert (cls == compared["seg"])[both & ~bad].mean() >= 0.9999


def test_strips_agree(compared: dict) -> None:
    """The 32-sector RL strip of both, for every pose: all sectors within 1e-3 (1 cm at the 10 m clip) for
    the large majority of poses, and at most one sector off in any pose."""
    depth, gl = compared["depth"], compared["gl"]
    a = np.array([depth_strip(d, RL_CAMERA.far) for d in depth])
    b = np.array([depth_strip(d, RL_CAMERA.far) for d in gl])
    off = np.abs(a - b) > 1e-3
    assert (~off.any(axis=1)).mean() >= 0.9
    assert off.sum(axis=1).max() <= 1


def test_centre_row_and_threads_agree(compared: dict) -> None:
    caster: DepthCaster = compared["caster"]
    poses = np.repeat(compared["poses"], 4, axis=0)  # enough rays to split over threads
    row = caster.centre_row(poses)
    assert row.shape == (len(poses), 128) and row.dtype == np.float32
    np.testing.assert_array_equal(row, np.repeat(compared["depth"][:, 9 // 2], 4, axis=0))
    single = DepthCaster(caster.scene, [RL_CAMERA], threads=1)
    np.testing.assert_array_equal(single.centre_row(poses), row)


@pytest.mark.parametrize("sectors", [32, 7, 1, 128])
def test_centre_row_minima_are_the_centre_rows_sector_minima(compared: dict, sectors: int) -> None:
    """The nearest return of each sector, cast with the sector's rays bounding each other, equals the
    full centre row's sector minima exactly (NaN only where the whole sector has no return), with one
    thread and with two; and the RL strip from it equals the strip of the whole row."""
    caster: DepthCaster = compared["caster"]
    poses = np.repeat(compared["poses"], 4, axis=0)
    row = caster.centre_row(poses)
    edges = np.linspace(0, 128, sectors + 1).round().astype(int)
    expected = np.fmin.reduceat(row, edges[:-1], axis=1)
    got = caster.centre_row_minima(poses, sectors)
    assert got.shape == (len(poses), sectors) and got.dtype == np.float32
    np.testing.assert_array_equal(got, expected)
    single = DepthCaster(caster.scene, [RL_CAMERA], threads=1)
    np.testing.assert_array_equal(single.centre_row_minima(poses, sectors), expected)
    if sectors == 32:
        strip = np.array([depth_strip(np.tile(r, (9, 1)), RL_CAMERA.far) for r in row])
        np.testing.assert_array_equal(strips(got, RL_CAMERA.far), strip)


# --------------------------------------------------------------------------- exact geometry
def quad(corners: list, cls: SemanticClass, texture: str = "white", alpha: bool = False) -> MeshPart:
    corners = np.asarray(corners, dtype=np.float32)
    n = np.cross(corners[1] - corners[0], corners[2] - corners[0])
    return MeshPart(
        f"quad_{int(cls)}_{texture}",
        corners,
        np.tile(n / np.linalg.norm(n), (4, 1)).astype(np.float32),
        np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=np.float32),
        np.full(4, cls, dtype=np.uint8),
        np.array([[0, 1, 2], [0, 2, 3]], dtype=np.uint32),
        texture,
        alpha,
    )


def small_scene(parts: list[MeshPart], textures: dict[str, np.ndarray] | None = None) -> Scene:
    return Scene(
        "test",
        0,
        parts,
        {"white": np.full((4, 4, 4), 255, np.uint8), **(textures or {})},
        CollisionModel(np.ones((2, 2, 2)), np.zeros(3), 1.0),
        np.zeros(3),
        0.0,
        np.array([-10.0, -10.0, 0.0]),
        np.array([10.0, 10.0, 10.0]),
    )


def test_analytic_planes_near_far_and_alpha_card() -> None:
    ground = quad([[-50, -50, 0], [50, -50, 0], [50, 50, 0], [-50, 50, 0]], SemanticClass.GROUND)
    wall = quad([[6, 50, -1], [6, -50, -1], [6, -50, 20], [6, 50, 20]], SemanticClass.POST)
    leaf = np.zeros((64, 64, 4), dtype=np.uint8)
    leaf[:, 32:] = (40, 160, 40, 255)  # right half of the card kept, left half discarded
    card = quad(
        [[2, 0.5, 1.5], [2, -0.5, 1.5], [2, -0.5, 2.5], [2, 0.5, 2.5]], SemanticClass.CANOPY, "leaf", True
    )
    sc = small_scene([ground, wall, card], {"leaf": leaf})
    down = CameraConfig("down", 64, 48, 70.0, position=(0.0, 0.0, 0.0), rpy_deg=(0.0, 90.0, 0.0))
    front = CameraConfig("front", 160, 120, 90.0, position=(0.0, 0.0, 0.0))
    short = CameraConfig("short", 160, 120, 90.0, position=(0.0, 0.0, 0.0), far=5.0)
    caster = DepthCaster(sc, [down, front, short])
    # straight down from 3.7 m over open ground: z-depth 3.7 in every pixel (not the range along the ray)
    d = caster.depth(pose(-5.0, 3.0, 3.7, 0.3)[None], "down")[0]
    np.testing.assert_allclose(d, 3.7, rtol=1e-6)
    # level in front of the wall 6 m away, the leaf card 2 m away: its kept half at 2 m, through its
    # discarded half the wall at 6 m, the ground below (z-depth of the ground point in the optical frame)
    T = pose(0.0, 0.0, 2.0, 0.0)
    d = caster.depth(T[None], "front")[0]
    K = intrinsics(front)
    v, u = np.mgrid[0:120, 0:160]
    x, y = (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]  # optical rays (x right, y down, z = 1)
    z_ground = np.where(y > 0, 2.0 / np.where(y > 0, y, 1.0), np.inf)
    z_wall = np.where(y <= 0.5, 6.0, np.inf)  # the wall spans world z -1..20 at 6 m: 2 - 6 y >= -1
    card = (np.abs(x * 2.0) < 0.5) & (np.abs(y * 2.0) < 0.5)
    kept = card & (x > 0)  # the texture's kept half is the card's half at world y < 0: image right
    expected = np.where(kept, 2.0, np.minimum(z_ground, z_wall))
    # away from the card's outline and its kept/discarded boundary (a texel or two wide there)
    clean = (np.abs(np.abs(x * 2.0) - 0.5) > 0.02) & (np.abs(np.abs(y * 2.0) - 0.5) > 0.02)
    clean &= ~(card & (np.abs(x * 2.0) < 0.03))
    np.testing.assert_allclose(d[clean], expected[clean], rtol=1e-6)
    with Renderer(sc, [front, short], shadows=False) as r:
        views = r.render(T, rgb=False)
        gl, gl_short = views["front"].depth.copy(), views["short"].depth.copy()
    np.testing.assert_allclose(d[clean], gl[clean], rtol=1e-5)
    # far plane at 5 m: the wall and the ground beyond 5 m are gone (NaN), as in the renderer
    d_short = caster.depth(T[None], "short")[0]
    assert np.array_equal(np.isnan(d_short[clean]), (expected >= 5.0)[clean])
    assert np.array_equal(np.isnan(d_short[clean]), np.isnan(gl_short[clean]))
    # the card 3 cm ahead, nearer than the near plane (5 cm), is not seen: the wall and ground behind are
    d_near = caster.depth(pose(1.97, 0.0, 2.0, 0.0)[None], "front")[0]
    np.testing.assert_allclose(d_near, np.minimum(z_ground, 6.0 - 1.97), rtol=1e-6)


def test_empty_scene_and_bad_input() -> None:
    sc = small_scene([])
    caster = DepthCaster(sc, RL_CAMERA)
    assert np.isnan(caster.depth(pose(0, 0, 1, 0)[None])).all()
    assert caster.centre_row(np.zeros((0, 4, 4))).shape == (0, 128)
    assert caster.centre_row_minima(np.zeros((0, 4, 4)), 32).shape == (0, 32)
    assert np.isnan(caster.centre_row_minima(pose(0, 0, 1, 0)[None], 32)).all()
    for sectors in (0, 129):
        with pytest.raises(ValueError, match="sectors must be between 1 and the image width 128"):
            caster.centre_row_minima(pose(0, 0, 1, 0)[None], sectors)
    with pytest.raises(ValueError, match=r"\(B, 4, 4\)"):
        caster.depth(pose(0, 0, 1, 0))
    with pytest.raises(ValueError, match=r"\(B, 4, 4\)"):
        caster.centre_row(np.zeros((2, 3, 4)))
    bad = np.stack([pose(0, 0, 1, 0), pose(0, 0, 1, 0)])
    bad[1, 0, 3] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        caster.depth(bad)
    bad[1, 0, 3] = np.inf
    with pytest.raises(ValueError, match="non-finite"):
        caster.centre_row(bad)
    with pytest.raises(ValueError, match="unknown camera"):
        caster.depth(bad[:1], "front")
    with pytest.raises(ValueError, match="unique"):
        DepthCaster(sc, [RL_CAMERA, RL_CAMERA])


# --------------------------------------------------------------------------- BVH against brute force
def brute_force(P: np.ndarray, origin: np.ndarray, dirs: np.ndarray, near: float, far: float) -> tuple:
    """Nearest triangle of ``P`` (T, 3, 3) along each ray ``origin + t dirs[i]`` with near <= t < far, by
    testing every triangle (Moller-Trumbore in float64, numpy): its index (-1: none) and t."""
    v0, e1, e2 = P[:, 0], P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]
    s = origin - v0  # (T, 3)
    q = np.cross(s, e1)  # (T, 3)
    best = np.full(len(dirs), -1)
    best_t = np.full(len(dirs), np.inf)
    for i, d in enumerate(dirs):
        p = np.cross(d, e2)  # (T, 3)
        det = (e1 * p).sum(1)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            u = (s * p).sum(1) / det
            v = (q @ d) / det
            t = (e2 * q).sum(1) / det
            ok = (det != 0) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= near) & (t < far)
        if ok.any():
            k = np.flatnonzero(ok)[np.argmin(t[ok])]
            best[i], best_t[i] = k, t[k]
    return best, best_t


def test_bvh_matches_brute_force() -> None:
    """400 random triangles (clustered and overlapping, some thin, some large) and 1,536 rays from two
    poses: every ray finds the triangle and the depth that testing all triangles finds."""
    rng = np.random.default_rng(7)
    centres = rng.uniform(-6, 6, (400, 3)) * np.array([1, 1, 0.25]) + np.array([0, 0, 1.5])
    scale = np.where(rng.random(400) < 0.05, 1.5, rng.uniform(0.03, 0.4, 400))[:, None, None]
    P = (centres[:, None, :] + scale * rng.normal(size=(400, 3, 3))).astype(np.float32)
    P[::37, 2] = P[::37, 1]  # a few degenerate (zero-area) triangles
    n = np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    part = MeshPart(
        "soup",
        P.reshape(-1, 3),
        np.repeat(n, 3, axis=0).astype(np.float32),
        np.zeros((1200, 2), np.float32),
        np.full(1200, SemanticClass.POST, dtype=np.uint8),
        np.arange(1200, dtype=np.uint32).reshape(400, 3),
        "white",
        False,
    )
    cam = CameraConfig("probe", 32, 24, 100.0, far=9.0)
    caster = DepthCaster(small_scene([part]), cam)
    poses = np.stack([pose(-5.0, 0.3, 1.4, 0.1, 0.05), pose(0.2, -0.4, 1.6, 2.0, -0.1, 0.2)])
    depth, tri = caster.trace(poses)
    K = intrinsics(cam)
    v, u = np.mgrid[0 : cam.height, 0 : cam.width]
    q = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones(u.shape)], -1).reshape(-1, 3)
    mount = Camera(cam).T_body_link @ frames.T_link_optical()
    for k, T in enumerate(poses):
        T_wo = T @ mount
        want, t = brute_force(P.astype(np.float64), T_wo[:3, 3], q @ T_wo[:3, :3].T, cam.near, cam.far)
        assert 0.2 < (want >= 0).mean() < 0.95  # rays that hit and rays that miss
        np.testing.assert_array_equal(tri[k].ravel(), want)
        hit = want >= 0
        np.testing.assert_allclose(depth[k].ravel()[hit], t[hit], rtol=1e-6)
        assert np.isnan(depth[k].ravel()[~hit]).all()
