"""Other vehicles' bodies as spheres in the ray-cast depth (DepthCaster.sphere_centre_row and the merged
centre rows and sector minima), against an independent numpy ray-sphere intersection, a real scene and the
OpenGL renderer drawing a sphere mesh."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

pytest.importorskip("gymnasium")

from droneulator import frames  # noqa: E402
from droneulator.config import CameraConfig  # noqa: E402
from droneulator.render.raycast import DepthCaster, sector_edges  # noqa: E402
from droneulator.render.renderer import Renderer  # noqa: E402
from droneulator.scenes import get_scene  # noqa: E402
from droneulator.scenes.base import CollisionModel, MeshPart, Scene, SemanticClass  # noqa: E402
from droneulator.sensors.camera import intrinsics  # noqa: E402

#: odd width and height: the centre pixel looks along the optical axis
AXIS_CAMERA = CameraConfig("axis", 129, 9, 90.0, far=10.0)
RL_CAMERA = CameraConfig("rl_depth", 128, 9, 90.0, far=10.0)
MOUNTED = CameraConfig(
    "mounted", 96, 31, 80.0, position=(0.1, 0.03, -0.04), rpy_deg=(4.0, 25.0, -8.0), far=12.0
)


def pose(x: float, y: float, z: float, yaw: float, pitch: float = 0.0, roll: float = 0.0) -> np.ndarray:
    return frames.transform_from_pose(np.array([x, y, z]), frames.quat_from_euler(roll, pitch, yaw))


def empty_scene(parts: list[MeshPart] | None = None) -> Scene:
    return Scene(
        "test",
        0,
        parts or [],
        {"white": np.full((4, 4, 4), 255, np.uint8)},
        CollisionModel(np.ones((2, 2, 2)), np.zeros(3), 1.0),
        np.zeros(3),
        0.0,
        np.array([-10.0, -10.0, 0.0]),
        np.array([10.0, 10.0, 10.0]),
    )


def optical(cam: CameraConfig, T_wb: np.ndarray) -> np.ndarray:
    """The camera's optical frame in the world, from its mount (REP 103 optical axes)."""
    return T_wb @ frames.camera_mount(np.array(cam.position), cam.rpy) @ frames.T_link_optical()


def reference_row(
    cam: CameraConfig, T_wb: np.ndarray, centres: np.ndarray, radii: np.ndarray, row: int | None = None
) -> np.ndarray:
    """Independent z-depth of the spheres along image row ``row`` (default H // 2) of one pose: pinhole rays
    through pixel centres, optical frame from the mount (frames.camera_mount, REP 103 optical axes), the
    quadratic solved in its textbook form, the first root in [near, far), the camera inside a sphere
    ignoring it."""
    v = cam.height // 2 if row is None else row
    K = intrinsics(cam)
    T_wo = optical(cam, T_wb)
    u = np.arange(cam.width, dtype=float)
    d_opt = np.stack([(u - K[0, 2]) / K[0, 0], np.full_like(u, (v - K[1, 2]) / K[1, 1]), np.ones_like(u)], 1)
    d = d_opt @ T_wo[:3, :3].T  # world directions, optical z = 1 per unit t
    o = T_wo[:3, 3]
    out = np.full(cam.width, np.inf)
    for c, r in zip(centres, radii, strict=True):
        if not (r > 0 and np.isfinite(c).all()) or np.linalg.norm(o - c) <= r:
            continue
        A = (d * d).sum(1)
        Bq = 2.0 * d @ (o - c)
        Cq = (o - c) @ (o - c) - r * r
        disc = Bq * Bq - 4 * A * Cq
        ok = disc >= 0
        sq = np.sqrt(np.where(ok, disc, 0.0))
        t0, t1 = (-Bq - sq) / (2 * A), (-Bq + sq) / (2 * A)
        t = np.where(t0 >= cam.near, t0, np.where(t1 >= cam.near, t1, np.inf))
        t = np.where(ok & (t < cam.far), t, np.inf)
        out = np.minimum(out, t)
    return np.where(np.isfinite(out), out, np.nan)


def test_sphere_ahead_depth_is_distance_minus_radius_and_side_columns_match() -> None:
    caster = DepthCaster(empty_scene(), AXIS_CAMERA)
    T = pose(1.0, -2.0, 1.5, 0.7)
    cam_pos = (T @ np.array([*AXIS_CAMERA.position, 1.0]))[:3]
    ahead = np.array([math.cos(0.7), math.sin(0.7), 0.0])
    dist, r = 4.0, 0.6
    centres, radii = (cam_pos + dist * ahead)[None, None], np.array([[r]])
    row = caster.sphere_centre_row(T[None], centres, radii)
    assert row.shape == (1, 129) and row.dtype == np.float32
    assert abs(row[0, 64] - (dist - r)) < 1e-4
    ref = reference_row(AXIS_CAMERA, T, centres[0], radii[0])
    hit = ~np.isnan(ref)
    assert 10 < hit.sum() < 129  # the sphere covers some columns, not all
    np.testing.assert_array_equal(np.isnan(row[0]), ~hit)
    np.testing.assert_allclose(row[0][hit], ref[hit], rtol=2e-6, atol=1e-5)
    # the silhouette: columns off the sphere (beyond its angular radius) miss it
    K = intrinsics(AXIS_CAMERA)
    ang = np.abs(np.arctan((np.arange(129) - K[0, 2]) / K[0, 0]))
    half = math.asin(r / dist)
    assert hit[ang < half - 0.01].all() and not hit[ang > half + 0.01].any()


def test_behind_beyond_far_padding_and_own_body() -> None:
    caster = DepthCaster(empty_scene(), AXIS_CAMERA)
    T = pose(0.0, 0.0, 2.0, 0.0)
    cam = np.array([AXIS_CAMERA.position[0], 0.0, 2.0])
    cases = {
        "behind": ([cam + [-3.0, 0, 0]], [0.5]),
        "beyond far": ([cam + [10.8, 0, 0]], [0.5]),  # nearest point 10.3 m > far 10 m
        "padding": ([cam + [3.0, 0, 0], cam + [2.0, 0.1, 0]], [0.0, -1.0]),
        "non-finite": ([[np.nan, 0.0, 2.0], cam + [3.0, 0, 0]], [0.5, np.nan]),
        "own body": ([[0.0, 0.0, 2.0]], [0.3]),  # the camera (0.12 m ahead) inside its own sphere
    }
    for name, (c, r) in cases.items():
        row = caster.sphere_centre_row(T[None], np.array(c)[None], np.array(r)[None])
        assert np.isnan(row).all(), name
    # padded and own-body spheres beside a real one change nothing
    real = cam + [3.0, 0, 0]
    c = np.array([[0.0, 0.0, 2.0], real, [np.nan] * 3, real])[None]
    r = np.array([[0.3, 0.5, 0.5, 0.0]])
    row = caster.sphere_centre_row(T[None], c, r)
    alone = caster.sphere_centre_row(T[None], real[None, None], np.array([[0.5]]))
    np.testing.assert_array_equal(row, alone)
    assert abs(alone[0, 64] - 2.5) < 1e-4
    # straddling far: the part nearer than far is seen, the rest is NaN
    row = caster.sphere_centre_row(T[None], (cam + [10.2, 0, 0])[None, None], np.array([[0.5]]))
    assert abs(row[0, 64] - 9.7) < 1e-4
    ref = reference_row(AXIS_CAMERA, T, (cam + [10.2, 0, 0])[None], np.array([0.5]))
    np.testing.assert_array_equal(np.isnan(row[0]), np.isnan(ref))
    # the near plane (5 cm) cuts the sphere's front: its far side is seen (the renderer culls no faces)
    row = caster.sphere_centre_row(T[None], (cam + [0.2, 0, 0])[None, None], np.array([[0.17]]))
    assert abs(row[0, 64] - 0.37) < 1e-4


def test_mount_pitch_and_batches_per_pose() -> None:
    caster = DepthCaster(empty_scene(), [RL_CAMERA, MOUNTED])
    rng = np.random.default_rng(3)
    poses = np.array(
        [pose(0.5, 1.0, 2.0, 0.3, 0.1, -0.05), pose(-3.0, 2.0, 1.0, -2.0), pose(4, -4, 3, 1.2, -0.2)]
    )
    # spheres along the mounted camera's centre-row rays (independent optical frames), 1, 3 and 0 per pose
    centres = np.full((3, 3, 3), np.nan)
    radii = np.zeros((3, 3))
    K = intrinsics(MOUNTED)
    counts = [1, 3, 0]
    for b, n in enumerate(counts):
        T_wo = optical(MOUNTED, poses[b])
        for k in range(n):
            u = rng.uniform(10, 86)
            ray = T_wo[:3, :3] @ np.array([(u - K[0, 2]) / K[0, 0], (15 - K[1, 2]) / K[1, 1], 1.0])
            centres[b, k] = T_wo[:3, 3] + rng.uniform(1.5, 8.0) * ray
            radii[b, k] = rng.uniform(0.2, 0.8)
    # pose 2's slots: a padded one with a centre ahead, and a non-finite one
    centres[2, 0] = poses[2][:3, 3] + poses[2][:3, 0] * 3
    rows = caster.sphere_centre_row(poses, centres, radii, "mounted")
    assert rows.shape == (3, 96)
    for b, n in enumerate(counts):
        ref = reference_row(MOUNTED, poses[b], centres[b], radii[b])
        np.testing.assert_array_equal(np.isnan(rows[b]), np.isnan(ref))
        np.testing.assert_allclose(rows[b], ref, rtol=2e-6, atol=1e-5)
        assert (~np.isnan(rows[b])).any() == (n > 0)
        # each pose alone gives its own row: no spheres leak between poses
        one = slice(b, b + 1)
        alone = caster.sphere_centre_row(poses[one], centres[one, :n], radii[one, :n], "mounted")
        np.testing.assert_array_equal(alone[0], rows[b])
    # the mount matters: the same spheres in the unmounted camera look different
    other = DepthCaster(empty_scene(), CameraConfig("mounted", 96, 31, 80.0, far=12.0))
    assert not np.array_equal(np.isnan(other.sphere_centre_row(poses, centres, radii)), np.isnan(rows))
    # whole images: each row as the reference's
    full = caster.sphere_depth(poses[:2], centres[:2], radii[:2], "mounted")
    assert full.shape == (2, 31, 96)
    for v in (0, 7, 15, 30):
        ref = reference_row(MOUNTED, poses[1], centres[1], radii[1], row=v)
        np.testing.assert_allclose(full[1, v], ref, rtol=2e-6, atol=1e-5)
    np.testing.assert_array_equal(full[:, 15], rows[:2])


@pytest.fixture(scope="module")
def vineyard() -> tuple[DepthCaster, np.ndarray, tuple[np.ndarray, np.ndarray]]:
    scene = get_scene("vineyard", 0, 1.0)
    caster = DepthCaster(scene, RL_CAMERA)
    rng = np.random.default_rng(5)
    lm = scene.landmarks
    B, K = 12, 4
    alleys = lm["alley_y"]
    poses = np.array(
        [
            pose(rng.uniform(-12, 12), alleys[b % len(alleys)], rng.uniform(0.8, 2.0), rng.uniform(-3, 3))
            for b in range(B)
        ]
    )
    centres = np.zeros((B, K, 3))
    radii = np.zeros((B, K))
    for b in range(B):
        n = b % (K + 1)  # 0 .. K vehicles in view
        fwd, left = poses[b][:3, 0], poses[b][:3, 1]
        for k in range(n):
            dist = rng.uniform(0.8, 6.0)
            centres[b, k] = poses[b][:3, 3] + dist * fwd + rng.uniform(-0.8, 0.8) * dist * left
            radii[b, k] = rng.uniform(0.15, 0.4)
        centres[b, 0] = poses[b][:3, 3] if n == 0 else centres[b, 0]  # own body where no other
        radii[b, 0] = 0.3 if n == 0 else radii[b, 0]
    return caster, poses, (centres, radii)


def test_merged_rows_and_sector_minima_in_a_real_scene(
    vineyard: tuple[DepthCaster, np.ndarray, tuple[np.ndarray, np.ndarray]],
) -> None:
    caster, poses, spheres = vineyard
    scene_row = caster.centre_row(poses)
    body_row = caster.sphere_centre_row(poses, *spheres)
    merged = caster.centre_row(poses, spheres=spheres)
    np.testing.assert_array_equal(merged, np.fmin(scene_row, body_row))
    # the bodies are in front of the scene somewhere, and the scene stays visible elsewhere
    nearer = body_row < np.nan_to_num(scene_row, nan=np.inf)
    assert nearer.sum() > 50 and (~np.isnan(scene_row) & ~nearer).sum() > 500
    for b in range(len(poses)):
        ref = reference_row(RL_CAMERA, poses[b], spheres[0][b], spheres[1][b])
        np.testing.assert_allclose(body_row[b], ref, rtol=2e-6, atol=1e-5)
    for sectors in (32, 7, 1, 128):
        edges = sector_edges(RL_CAMERA.width, sectors)[:-1]
        got = caster.centre_row_minima(poses, sectors, spheres=spheres)
        np.testing.assert_array_equal(got, np.fmin.reduceat(merged, edges, axis=1))
        scene_minima = caster.centre_row_minima(poses, sectors)
        np.testing.assert_array_equal(got, np.fmin(scene_minima, np.fmin.reduceat(body_row, edges, axis=1)))
    full = caster.depth(poses[:3], spheres=(spheres[0][:3], spheres[1][:3]))
    np.testing.assert_array_equal(full[:, RL_CAMERA.height // 2], merged[:3])


def test_pipeline_and_depth_strips_pass_spheres(
    vineyard: tuple[DepthCaster, np.ndarray, tuple[np.ndarray, np.ndarray]],
) -> None:
    from droneulator.config import SimConfig
    from droneulator.render.pipeline import CameraPipeline
    from droneulator.workflows.rl.env import strips
    from droneulator.workflows.rl.vector import STRIP_SAMPLES, depth_strips

    caster, poses, spheres = vineyard
    cfg = SimConfig()
    cfg.render.cameras = [RL_CAMERA]
    pipe = CameraPipeline(caster.scene, cfg, source="raycast")
    pipe.caster = caster
    merged = caster.centre_row(poses, spheres=spheres)
    np.testing.assert_array_equal(pipe.centre_rows(poses, spheres=spheres), merged)
    minima = caster.centre_row_minima(poses, STRIP_SAMPLES, spheres=spheres)
    np.testing.assert_array_equal(pipe.sector_minima(poses, STRIP_SAMPLES, spheres), minima)
    presets, scales = ["ideal"] * len(poses), np.ones((len(poses), 2))
    got = depth_strips(pipe, poses, presets, scales, RL_CAMERA.far, spheres)
    np.testing.assert_array_equal(got, strips(minima, RL_CAMERA.far))
    assert not np.array_equal(got, depth_strips(pipe, poses, presets, scales, RL_CAMERA.far))
    # a noisy preset: whole images with the bodies in them, then the depth model
    noisy_cfg = SimConfig()
    noisy_cfg.render.cameras = [dataclasses.replace(RL_CAMERA, depth_model="d435")]
    noisy = CameraPipeline(caster.scene, noisy_cfg, source="raycast")
    noisy.caster = caster
    rows = noisy.centre_rows(poses, spheres=spheres)
    body = caster.sphere_centre_row(poses, *spheres)
    scene = np.nan_to_num(caster.centre_row(poses), nan=np.inf)
    front = body < scene - 0.5
    ok = front & ~np.isnan(rows)
    assert front.sum() > 50 and ok.sum() > 0.5 * front.sum()
    err = np.abs(rows[ok] - body[ok])
    assert np.median(err / body[ok]) < 0.08  # the preset's stereo error
    assert (err < np.abs(rows[ok] - scene[ok])).mean() > 0.9  # the body is seen, not the scene behind
    # the renderer draws the bodies itself
    with CameraPipeline(empty_scene(), cfg) as drawn:
        with pytest.raises(ValueError, match="draws the other vehicles' bodies itself"):
            drawn.centre_rows(poses[:1], spheres=(spheres[0][:1], spheres[1][:1]))
        with pytest.raises(ValueError, match="draws the other vehicles' bodies itself"):
            drawn.depth(poses[:1], spheres=(spheres[0][:1], spheres[1][:1]))


def uv_sphere(centre: np.ndarray, r: float, lon: int = 128, lat: int = 64) -> MeshPart:
    """A UV sphere mesh (vertices on the sphere, so its faces lie inside it by at most ~r (pi/lat)^2 / 2)."""
    th, ph = np.meshgrid(np.linspace(0, np.pi, lat + 1), np.linspace(0, 2 * np.pi, lon + 1), indexing="ij")
    p = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1).reshape(-1, 3)
    idx = []
    for i in range(lat):
        for j in range(lon):
            a, b = i * (lon + 1) + j, (i + 1) * (lon + 1) + j
            idx += [[a, b, a + 1], [a + 1, b, b + 1]]
    n = len(p)
    return MeshPart(
        "sphere",
        (centre + r * p).astype(np.float32),
        p.astype(np.float32),
        np.zeros((n, 2), np.float32),
        np.full(n, SemanticClass.POST, np.uint8),
        np.array(idx, dtype=np.uint32),
        "white",
        False,
    )


def test_spheres_match_the_renderer_drawing_a_sphere_mesh() -> None:
    cam = CameraConfig("front", 160, 120, 90.0, position=(0.0, 0.0, 0.0), rpy_deg=(0.0, 10.0, 0.0), far=10.0)
    centre, r = np.array([2.4, 0.4, 1.7]), 1.0
    T = pose(0.0, 0.0, 2.0, 0.1)
    with Renderer(empty_scene([uv_sphere(centre, r)]), [cam], shadows=False) as ren:
        gl = ren.render(T, rgb=False)["front"].depth.copy()
    got = DepthCaster(empty_scene(), cam).sphere_depth(T[None], centre[None, None], np.array([[r]]))[0]
    hit, gl_hit = ~np.isnan(got), ~np.isnan(gl)
    assert 0.15 < hit.mean() < 0.9
    # the same silhouette but for a pixel ring where the mesh's polygon edge lies inside the sphere
    assert (hit != gl_hit).sum() <= 8
    both = hit & gl_hit
    # the mesh lies inside the sphere: at most ~1.5 mm deeper at the faces' centres (more at grazing rays)
    err = gl[both] - got[both]
    assert err.min() > -1e-4
    assert np.median(err) < 1.5e-3 and (err < 3e-3).mean() > 0.97
