"""Dense photogrammetry on the CPU and its scoring against the true tree.

The stereo and fusion tests render a textured plane exactly (ray-plane intersection, bilinear texture
lookup) from known cameras, so the true depth of every pixel is known; the scorer tests sample the
real tree_inspection mesh. The slow test runs capture -> sparse -> dense -> score end to end.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")

from droneulator.scenes import get_scene  # noqa: E402
from droneulator.workflows.photogrammetry.fusion import FusionOptions, fuse, read_ply, write_ply  # noqa: E402
from droneulator.workflows.photogrammetry.mvs import (  # noqa: E402
    MvsOptions,
    View,
    _forward_backward_error,
    depth_range,
    plane_homography,
    plane_sweep,
    select_neighbors,
)
from droneulator.workflows.photogrammetry.patchmatch import patchmatch_refine  # noqa: E402
from droneulator.workflows.photogrammetry.truth import (  # noqa: E402
    GROUND,
    TREE,
    SurfaceIndex,
    TruthMesh,
    sample_surface,
    truth_mesh,
)

W, H = 400, 300
K = np.array([[350.0, 0.0, (W - 1) / 2], [0.0, 350.0, (H - 1) / 2], [0.0, 0.0, 1.0]])
SLANT = np.radians(25)
P0 = np.zeros(3)
E1 = np.array([np.cos(SLANT), 0.0, np.sin(SLANT)])
E2 = np.array([0.0, 1.0, 0.0])


def _texture(n: int = 1024, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = np.zeros((n, n), np.float32)
    for s in (4, 16, 64):
        t += cv2.resize(
            rng.random((n // s, n // s)).astype(np.float32), (n, n), interpolation=cv2.INTER_CUBIC
        )
    return (t - t.min()) / (t.max() - t.min())


def _look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    T[:3, 3] = eye
    return T


def _render(
    T: np.ndarray, tex: np.ndarray, texel: float = 0.004, origin: np.ndarray = P0
) -> tuple[np.ndarray, np.ndarray]:
    """Grey image and true depth of the plane through ``origin`` spanned by E1, E2, textured with
    ``tex``."""
    n = np.cross(E1, E2)
    u, v = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1) @ T[:3, :3].T
    t = ((origin - T[:3, 3]) @ n) / (rays @ n)
    X = T[:3, 3] + t[..., None] * rays
    a = ((X - origin) @ E1 / texel + tex.shape[1] / 2).astype(np.float32)
    b = ((X - origin) @ E2 / texel + tex.shape[0] / 2).astype(np.float32)
    return cv2.remap(tex, a, b, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT), t


def _views(xs: list[float]) -> tuple[list[View], list[np.ndarray]]:
    tex = _texture()
    views, depths = [], []
    for i, x in enumerate(xs):
        T = _look_at(np.array([x, 0.3, 3.0]), np.zeros(3))
        g, z = _render(T, tex)
        rgb = np.repeat((g[..., None] * 255).astype(np.uint8), 3, axis=-1)
        views.append(View(f"{i}", K, T, g.astype(np.float32), rgb, np.ones((H, W), bool)))
        depths.append(z)
    return views, depths


def test_two_view_plane_sweep_recovers_a_rendered_textured_plane_within_1cm():
    views, depths = _views([-0.4, 0.4])
    dm = plane_sweep(views[0], [views[1]], 2.0, 4.5, MvsOptions(neighbors=1, best_k=1))
    err = np.abs(dm.depth - depths[0])
    valid = np.isfinite(err)
    assert valid.mean() > 0.8  # everything both cameras see, but the borders
    assert np.median(err[valid]) < 0.003
    assert np.percentile(err[valid], 95) < 0.01
    # a sweep that does not bracket the plane: at a strict NCC threshold only a few chance matches pass
    # (at the default, looser one many do: single-pair depths are only trusted after fusion)
    far = plane_sweep(views[0], [views[1]], 6.0, 9.0, MvsOptions(neighbors=1, best_k=1, min_ncc=0.6))
    assert np.isfinite(far.depth).mean() < 0.1


def _step_views(xs: list[float]) -> tuple[list[View], list[np.ndarray]]:
    """Views of two textured planes: a strip (|x| < 0.25 m along E1) 0.4 m in front of the plane through
    P0, with its own texture, so each view has two depth edges (the occlusion boundaries of a leaf)."""
    front = P0 + 0.4 * np.cross(E2, E1) / np.linalg.norm(np.cross(E2, E1))
    views, depths = [], []
    back_tex, front_tex = _texture(seed=0), _texture(seed=1)
    for i, x in enumerate(xs):
        T = _look_at(np.array([x, 0.3, 3.0]), np.zeros(3))
        gb, zb = _render(T, back_tex)
        gf, zf = _render(T, front_tex, origin=front)
        u, v = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
        rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
        Xf = T[:3, 3] + (rays @ T[:3, :3].T) * zf[..., None]
        on_strip = np.abs((Xf - front) @ E1) < 0.25
        g = np.where(on_strip, gf, gb).astype(np.float32)
        rgb = np.repeat((g[..., None] * 255).astype(np.uint8), 3, axis=-1)
        views.append(View(f"{i}", K, T, g, rgb, np.ones((H, W), bool)))
        depths.append(np.where(on_strip, zf, zb))
    return views, depths


def test_guided_aggregation_keeps_depth_edges_sharper_than_a_box_window():
    views, depths = _step_views([-0.3, 0.0, 0.3])
    truth = depths[1]
    grad = np.abs(np.diff(truth, axis=1)) > 0.1
    edge = np.zeros_like(truth, dtype=bool)
    edge[:, 1:] |= grad
    edge = cv2.dilate(edge.astype(np.uint8), np.ones((1, 13), np.uint8)) > 0  # 6 px either side
    errors = {}
    for name, o in {
        "box 9x9": MvsOptions(neighbors=2, window=9, guided_radius=0),
        "guided": MvsOptions(neighbors=2),
    }.items():
        dm = plane_sweep(views[1], [views[0], views[2]], 2.0, 4.5, o)
        ok = np.isfinite(dm.depth) & (np.abs(dm.depth - truth) < 0.01 * truth)
        errors[name] = ok[edge].mean()
        assert ok[~edge].mean() > 0.8  # away from the edges both recover the planes
    assert errors["guided"] > errors["box 9x9"] + 0.04, errors  # 0.84 against 0.76 when written


def test_depth_range_keeps_to_the_subject_not_the_background_behind_it():
    rng = np.random.default_rng(3)
    T = np.eye(4)  # camera at the origin looking along +z
    view = View("v", K, T, np.zeros((H, W), np.float32), np.zeros((H, W, 3), np.uint8), np.ones((H, W), bool))
    subject = np.column_stack([rng.uniform(-1, 1, (300, 2)), rng.uniform(4.0, 6.0, 300)])
    distant = np.column_stack([rng.uniform(-5, 5, (30, 2)), rng.uniform(35.0, 45.0, 30)])
    pts = np.vstack([subject, distant])
    _, hi_all = depth_range(view, pts, 0.15)
    assert hi_all > 35.0  # the distant trees (10 % of the points) stretch the plain percentile range
    lo, hi = depth_range(view, pts, 0.15, subject_factor=2.0)
    assert 3.0 < lo < 4.0 and 6.0 < hi < 7.5
    with pytest.raises(ValueError):
        MvsOptions(subject_depth_factor=0.5)


def test_default_fusion_keeps_points_two_views_agree_on_and_rejects_a_wrong_map():
    views, depths = _views([-0.5, -0.2, 0.1])
    wrong = (depths[2] * 1.08).astype(np.float32)
    maps = [depths[0].astype(np.float32), depths[1].astype(np.float32), wrong]
    everyone = [[j for j in range(3) if j != i] for i in range(3)]
    cloud = fuse(views, maps, everyone, FusionOptions())  # one agreeing view is enough
    assert len(cloud.points) > 0.5 * H * W
    assert not (cloud.source == 2).any()
    assert np.abs((cloud.points - P0) @ np.cross(E1, E2)).max() < 1e-6
    # two agreeing views demanded: with only two right maps nothing is fused
    assert len(fuse(views, maps, everyone, FusionOptions(min_consistent=2)).points) == 0


def test_fusion_keeps_consistent_depths_and_rejects_a_wrong_depth_map():
    views, depths = _views([-0.5, -0.2, 0.1, 0.4])
    wrong = depths[3] * 1.08  # a depth map 8 % off: it agrees with no other view
    maps = [d.astype(np.float32) for d in depths[:3]] + [wrong.astype(np.float32)]
    everyone = [[j for j in range(4) if j != i] for i in range(4)]
    cloud = fuse(views, maps, everyone, FusionOptions(min_consistent=2))
    assert len(cloud.points) > 0.5 * H * W
    assert not (cloud.source == 3).any()  # nothing fused from the wrong map
    n = np.cross(E1, E2)
    assert np.abs((cloud.points - P0) @ n).max() < 1e-6  # every fused point lies on the plane
    assert (cloud.support >= 2).all()
    # with three right maps of four, demanding three agreeing views keeps nothing
    assert len(fuse(views, maps, everyone, FusionOptions(min_consistent=3)).points) == 0


def test_fusion_tries_a_pixels_alternative_depth_and_rejects_a_wrong_one():
    views, depths = _views([-0.5, -0.2, 0.1])
    right = [d.astype(np.float32) for d in depths]
    everyone = [[j for j in range(3) if j != i] for i in range(3)]
    n = np.cross(E1, E2)
    nan = np.full((1, H, W), np.nan, np.float32)
    # view 0's best depth is 8 % off (no view agrees with it), its second hypothesis is the true depth
    maps = [right[0] * 1.08, right[1], right[2]]
    assert not (fuse(views, maps, everyone, FusionOptions()).source == 0).any()
    cloud = fuse(views, maps, everyone, FusionOptions(), [right[0][None], nan, nan])
    from_alt = (cloud.source == 0) & (cloud.hypothesis == 1)
    assert from_alt.sum() > 0.5 * H * W and (cloud.hypothesis[cloud.source == 0] == 1).all()
    assert np.abs((cloud.points - P0) @ n).max() < 1e-6  # every point from a true depth
    # a wrong alternative (15 % off) is rejected
    wrong = fuse(views, maps, everyone, FusionOptions(), [(right[0] * 0.85)[None], nan, nan])
    assert not (wrong.source == 0).any()
    # every view's best depth wrong, each its own way, the truth second everywhere: only when neighbours
    # agree through their alternatives too
    maps = [right[0] * 1.08, right[1] * 0.92, right[2] * 1.16]
    alts = [r[None] for r in right]
    assert len(fuse(views, maps, everyone, FusionOptions(), alts).points) == 0
    cloud = fuse(views, maps, everyone, FusionOptions(neighbor_alternatives=True), alts)
    assert len(cloud.points) > 0.5 * H * W and (cloud.hypothesis == 1).all()
    assert np.abs((cloud.points - P0) @ n).max() < 1e-6


def test_plane_sweep_keeps_the_second_cost_minimum_as_an_alternative_depth():
    views, depths = _step_views([-0.3, 0.0, 0.3])
    o = MvsOptions(neighbors=2, candidates=2)
    dm = plane_sweep(views[1], [views[0], views[2]], 2.0, 4.5, o)
    base = plane_sweep(views[1], [views[0], views[2]], 2.0, 4.5, MvsOptions(neighbors=2))
    np.testing.assert_array_equal(dm.depth, base.depth)  # the winner is unchanged
    assert base.alternatives is None and dm.alternatives.shape == (1, H, W)
    truth = depths[1]
    alt = dm.alternatives[0]
    assert np.isfinite(alt).mean() > 0.3
    assert not np.any(np.abs(alt - dm.depth) < 1e-6)  # never the winner again
    right = np.abs(dm.depth - truth) < 0.01 * truth
    alt_right = np.abs(alt - truth) < 0.01 * truth
    # where the winner is wrong, the alternative is sometimes right
    assert alt_right[~right & np.isfinite(dm.depth)].mean() > 0.05
    with pytest.raises(ValueError):
        MvsOptions(candidates=0)


def test_geometric_term_is_small_at_the_true_depth_and_capped_away_from_it():
    views, depths = _views([-0.4, 0.0])
    ref, src = views
    T = np.linalg.inv(ref.T_world_cam) @ src.T_world_cam
    N, kt = ref.K @ T[:3, :3] @ np.linalg.inv(src.K), ref.K @ T[:3, 3]
    centre = (slice(H // 3, 2 * H // 3), slice(W // 3, 2 * W // 3))
    z = float(np.median(depths[0][centre]))
    near = np.abs(depths[0] - z) < 0.005 * z  # the reference pixels the plane z passes through
    err = np.empty((H, W), np.float32)
    _forward_backward_error(plane_homography(ref, src, z), N, kt, depths[1].astype(np.float32), 3.0, err)
    assert near.sum() > 500 and np.median(err[near]) < 0.5
    _forward_backward_error(
        plane_homography(ref, src, 1.1 * z), N, kt, depths[1].astype(np.float32), 3.0, err
    )
    assert np.median(err[near]) == 3.0  # a plane 10 % off: capped
    no_depth = np.full((H, W), np.nan, np.float32)
    _forward_backward_error(plane_homography(ref, src, z), N, kt, no_depth, 3.0, err)
    assert (err == 3.0).all()


def test_patchmatch_recovers_a_slanted_planes_depth_and_normal_from_a_random_start():
    views, depths = _views([-0.4, 0.4])
    ref, src = views
    no_seed = np.full((H, W), np.nan, np.float32)  # every pixel starts at a random depth, fronto-parallel
    pm = patchmatch_refine(ref, [src], no_seed, 2.0, 4.5, iterations=4, best_k=1)
    err = np.abs(pm.depth - depths[0])
    valid = np.isfinite(err)
    assert valid.mean() > 0.8  # everything both cameras see, but the borders
    assert (err[valid] < 0.01 * depths[0][valid]).mean() > 0.85
    assert np.median(err[valid]) < 0.003
    # the plane's normal in the reference optical frame, facing the camera, 18 degrees off the optical axis
    n = np.linalg.inv(ref.T_world_cam)[:3, :3] @ np.cross(E1, E2)
    n = -n if n[2] > 0 else n
    angle = np.degrees(np.arccos(np.clip(pm.normal[valid] @ n, -1.0, 1.0)))
    assert np.median(angle) < 12.0, np.median(angle)  # a fronto-parallel plane: 18 degrees
    # started from the truth, it stays there
    kept = patchmatch_refine(ref, [src], depths[0].astype(np.float32), 2.0, 4.5, iterations=1, best_k=1)
    assert np.median(np.abs(kept.depth - depths[0])[np.isfinite(kept.depth)]) < 0.003
    with pytest.raises(ValueError):
        MvsOptions(patchmatch_iterations=-1)


def test_ply_round_trip(tmp_path: Path):
    rng = np.random.default_rng(0)
    pts, rgb = rng.normal(size=(100, 3)), rng.integers(0, 256, (100, 3)).astype(np.uint8)
    write_ply(tmp_path / "c.ply", pts, rgb)
    back, back_rgb = read_ply(tmp_path / "c.ply")
    np.testing.assert_allclose(back, pts, atol=1e-6)
    np.testing.assert_array_equal(back_rgb, rgb)


def test_neighbours_prefer_views_sharing_points_at_a_useful_angle():
    rng = np.random.default_rng(2)
    points = rng.uniform(-1, 1, (200, 3))
    centers = np.array([[6.0, 0, 0], [6.0, 0.05, 0], [5.5, 2.2, 0], [-6.0, 0, 0]])
    seen = [np.arange(200), np.arange(200), np.arange(200), np.arange(100, 200)]
    nb = select_neighbors(centers, seen, points, MvsOptions(neighbors=2, min_angle_deg=5, max_angle_deg=50))
    assert nb[0][0] == 2  # 20 degrees away beats the 0.5 degree twin
    assert 3 not in nb[0]  # the opposite view is past the largest angle


@pytest.fixture(scope="module")
def tree_truth() -> tuple[TruthMesh, SurfaceIndex]:
    scene = get_scene("tree_inspection", 0)
    mesh = truth_mesh(scene, float(scene.landmarks["crown_radius"][0]) + 1.0, 9.0)
    return mesh, SurfaceIndex(sample_surface(mesh, spacing=0.02))


def test_scorer_gives_zero_on_the_true_mesh_and_the_offset_for_offset_points(tree_truth):
    mesh, index = tree_truth
    assert {TREE, GROUND} <= set(np.unique(mesh.score_class))
    fresh = sample_surface(mesh, spacing=0.05, seed=7)  # other samples than the index's
    d, nearest = index.query(fresh.points)
    assert np.median(d) < 1e-9  # on a sampled triangle's surfel: exactly on the surface
    # curved bark and fruit, and leaf-card edges between samples, come within a fraction of the spacing
    assert np.percentile(d, 99) < 0.25 * index.samples.spacing
    assert (index.samples.score_class[nearest] == fresh.score_class).mean() > 0.99
    # bark and fruit: offset along the outward... either side of a closed surface is 3 cm from it
    solid = np.isin(fresh.semantic, (2, 7)) | (fresh.score_class == GROUND)
    offset = fresh.points[solid] + 0.03 * fresh.normals[solid]
    d_off, _ = index.query(offset)
    assert np.median(np.abs(d_off - 0.03)) < 1e-3
    # points in the air well above the ground and away from the tree are far from everything
    d_air, _ = index.query(np.array([[8.0, 0.0, 3.0], [0.0, -8.0, 2.0]]))
    np.testing.assert_allclose(d_air, [3.0, 2.0], atol=0.02)


def test_scorer_judges_every_point_near_the_tree_and_counts_the_distant_ones_apart(tree_truth):
    from droneulator.workflows.photogrammetry.score import cloud_metrics, truth_region

    _, index = tree_truth
    s = index.samples
    center, extent = truth_region(s)
    assert 9.0 < extent < 11.0  # ground triangles with their centre within 9 m of the trunk
    on = s.points[:: max(1, len(s.points) // 900)][:900]  # on the tree and the ground
    air = np.tile([center[0] + 4.0, center[1], 4.0], (150, 1))  # 4 m out, 4 m up: > 0.5 m from all
    distant = np.tile([center[0] + 30.0, center[1], 5.0], (50, 1))  # a distant tree: not judged
    m = cloud_metrics(np.concatenate([on, air, distant]), index, None)
    a = m["all"]
    assert (a["points_in_truth_region"], a["points_beyond_truth_region"]) == (1050, 50)
    assert a["far_points"] == 150 and a["far_share"] == pytest.approx(150 / 1050)
    assert a["accuracy_median_m"] < 1e-6 and a["accuracy_p90_m"] > 1.0  # the floating seventh
    assert m["background_points"] == 200 and m["far_share"] == pytest.approx(200 / 1100)


def test_leaf_cards_are_sampled_only_where_they_are_opaque(tree_truth):
    mesh, index = tree_truth
    s = index.samples
    canopy = s.semantic == 4
    cards = mesh.alpha_index >= 0
    area = 0.5 * np.linalg.norm(
        np.cross(mesh.triangles[:, 1] - mesh.triangles[:, 0], mesh.triangles[:, 2] - mesh.triangles[:, 0]),
        axis=1,
    )
    # the leaf atlas is partly transparent: fewer samples than the cards' area would give
    assert 0.1 < canopy.sum() * s.spacing**2 / area[cards & (mesh.semantic == 4)].sum() < 0.9


@pytest.mark.slow
def test_capture_sparse_dense_and_score_end_to_end(tmp_path: Path):
    pytest.importorskip("pycolmap")
    from droneulator.config import load_config
    from droneulator.scenes import get_scene
    from droneulator.workflows.photogrammetry.capture import aim_pitch, capture
    from droneulator.workflows.photogrammetry.dense import DenseOptions
    from droneulator.workflows.photogrammetry.mvs import MvsOptions as Mvs
    from droneulator.workflows.photogrammetry.reconstruct import ReconstructOptions, reconstruct

    out = tmp_path / "ds"
    cfg = load_config(
        None,
        ["capture.views=8", "capture.width=320", "capture.height=240", "capture.arc_deg=60",
         "capture.altitudes=[4.0]", "render.shadow_map_size=1024"],
        scene="tree_inspection",
    )  # fmt: skip
    # the camera's aim at the crown from the scene's own landmarks, so no probe run is started to ask the
    # simulator for them (test_photogrammetry's end-to-end capture covers the probe)
    scene = get_scene(cfg.scene, cfg.seed)
    landmarks = {k: v.tolist() for k, v in scene.landmarks.items()}
    cfg.capture.pitch_deg = aim_pitch(cfg.capture, {"landmarks": landmarks})
    meta = capture(cfg, out, progress=False)
    assert meta["complete"]
    assert (out / "truth" / "mesh.npz").is_file()
    assert len(list((out / "segmentation").glob("*.png"))) == 8
    assert len(list((out / "truth" / "depth").glob("*.npz"))) == 8
    opts = ReconstructOptions(max_features=2048, dense_options=DenseOptions(mvs=Mvs(scale=1.0, planes=96)))
    report = reconstruct(out, opts)
    assert report["sift_mask"]["mask"] == "tree" and 0.05 < report["sift_mask"]["mean_tree_share"] < 0.95
    assert report["dense"]["ran"] and report["dense"]["path"] in ("cpu-plane-sweep", "colmap-cuda-patchmatch")
    pts, rgb = read_ply(out / "dense" / "fused.ply")
    assert len(pts) == report["dense"]["dense_points"] > 500
    s = report["score"]
    assert s["sparse"]["tree"]["points"] > 0.5 * s["sparse"]["points"]  # SIFT masked to the tree
    # the sparse filter ran and what it kept lies on the true surface: of the points near the tree (where
    # the truth holds every surface) almost none are more than 0.5 m from it (0 of 203 measured; 15.6 %
    # before the filter on a 36-view capture); a 320x240 pixel is about 2 cm on the crown
    f = report["sparse_filter"]
    assert f["after"]["points"] == report["sparse_points"] == s["sparse"]["points"] < f["before"]["points"]
    assert f["removed_points"]["short_track"] > 0
    sparse_all = s["sparse"]["all"]
    assert sparse_all["points_in_truth_region"] > 50 and sparse_all["far_share"] < 0.02
    assert sparse_all["accuracy_median_m"] < 0.05 and sparse_all["accuracy_p90_m"] < 0.25
    assert s["dense"]["tree"]["points"] > 500
    assert s["dense"]["tree"]["accuracy_median_m"] < 0.05
    assert 0 < s["dense"]["tree"]["completeness_visible"] <= 1
    assert json.loads((out / "score.json").read_text())["dense"]["points"] == len(pts)
    assert (out / "dense_error.png").stat().st_size > 20_000
    md = (out / "report.md").read_text()
    assert "Score against the true tree" in md and "sparse points before filtering" in md
    assert "| sparse | all within" in md
