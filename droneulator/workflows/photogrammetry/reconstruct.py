"""``droneulator reconstruct``: a sparse COLMAP model of a capture, built on its known camera poses.

Stages (pycolmap, CPU):

1. **features**: SIFT in every image, all sharing the PINHOLE camera converted from ``camera_info``;
2. **matching**: each image with its nearest neighbours by prior position (``spatial``: on a ring that
   means the views on either side, which are the ones that overlap), or every pair (``exhaustive``);
3. **triangulation** from the known poses (``pycolmap.triangulate_points`` with ``sparse_known`` as the
   reference: poses fixed, points triangulated, merged, filtered and refined);
4. **bundle adjustment with pose priors**: poses, points refined together while each camera centre is
   held to its recorded position by a Gaussian prior (``pycolmap.PosePrior`` with a covariance,
   ``create_pose_prior_bundle_adjuster``), mirroring RTK-grade localisation;
5. **point filtering** (:func:`filter_sparse`, COLMAP's ``point_filtering`` rules with pycolmap's
   ``ObservationManager``): observations above a reprojection error, points behind a camera, points
   under a triangulation angle and points seen in fewer than ``filter_min_track_length`` images go.
   A two-view point cannot be checked: guided matching pairs leaves along the epipolar line, and any
   such pair triangulates somewhere on the ray with a small reprojection error. Three views are asked
   for only where three fit in the angle SIFT matches across (:func:`auto_min_track_length`): on a
   12-view ring (30 degrees apart) almost no point is matched in three views, and the rule kept 24 of
   1,238 points; there two views are the most that can be asked, and a capture sparser still is warned of;
6. **dense**: COLMAP's PatchMatch stereo and fusion where pycolmap was built with CUDA, else the CPU
   plane sweep and fusion of :mod:`.dense` (the report says which ran), into ``DATASET/dense/fused.ply``;
7. **score** against the true tree the capture recorded (:mod:`.score`), when it is there.

With ``mask="tree"`` SIFT runs only on the tree's pixels (the segmentation the capture recorded, standing
in for a user's segmentation network: COLMAP reads one mask PNG per image), so the features and the
sparse points are on the tree rather than on the textured ground.

The model goes to ``DATASET/sparse/``, the report to ``report.json`` and ``report.md``, a top and side view
of the cameras and points to ``reconstruction.png``; the work files (database) to ``DATASET/colmap/``.
The report also checks the conventions end to end: the triangulated points are projected with the
*recorded* poses and ``camera_info`` K (OpenCV convention, no COLMAP code involved) and compared with the
SIFT keypoints converted back from COLMAP's pixel convention.
"""

from __future__ import annotations

import json
import math
import shutil
import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from droneulator.frames import transform_from_pose
from droneulator.workflows.photogrammetry.colmap_model import (
    COLMAP_PIXEL_OFFSET,
    colmap_pinhole_params,
    colmap_to_opencv_pixels,
    project_opencv,
)
from droneulator.workflows.photogrammetry.dense import DenseOptions, dense_cpu, dense_cuda, tree_mask
from droneulator.workflows.photogrammetry.score import score, score_markdown


@dataclass
class ReconstructOptions:
    #: SIFT features per image (8192, COLMAP's default, suits 1024x768 on a CPU)
    max_features: int = 8192
    #: SIFT detection threshold (COLMAP's default 0.0067; lower finds more features on the shaded leaves)
    #: (the three SIFT settings below took the tree's sparse points from 28 to 1,135 on an 18-view
    #: 640x480 capture, against COLMAP's defaults)
    sift_peak_threshold: float = 0.003
    #: Lowe's ratio test (COLMAP's default 0.8): the leaf atlas repeats on every card, so a looser ratio
    #: keeps matches that the known-pose verification then checks against the epipolar geometry
    sift_max_ratio: float = 0.9
    #: COLMAP's guided matching: once a pair's geometry is verified, match again along its epipolar lines,
    #: where the ratio test only competes with the few candidates on the line
    guided_matching: bool = True
    #: "spatial" (nearest neighbours by prior position) or "exhaustive"
    matcher: str = "spatial"
    spatial_neighbors: int = 12
    #: "known_poses": keep the matches that agree with the recorded relative pose of each pair (guided
    #: verification); "ransac": COLMAP's own two-view RANSAC, not told the poses
    verification: str = "ransac"
    #: guided verification: largest distance of a match from its epipolar line, pixels
    max_epipolar_error_px: float = 2.0
    #: standard deviation of each camera-centre prior, metres
    prior_position_std_m: float = 0.01
    #: observations further than this from their point's projection are dropped while triangulating
    max_reproj_error_px: float = 4.0
    #: after bundle adjustment (:func:`filter_sparse`): observations further than this from their
    #: point's projection are dropped (COLMAP's point_filtering default is 4 px; the points' errors have a
    #: median of about 0.4 px and a robust standard deviation of about 0.46 px, so 2 px is 3.5 above it)
    filter_max_reproj_error_px: float = 2.0
    #: ... then points whose rays meet at less than this angle, degrees (COLMAP's default)
    filter_min_tri_angle_deg: float = 1.5
    #: ... then points seen in fewer images (COLMAP's default is 2): on a 36-view capture 1,787 of the
    #: 1,795 points near the tree but more than 0.5 m from its true surface had two-view tracks.
    #: None: from the views' spacing (:func:`auto_min_track_length`: 3 where three views lie within
    #: 45 degrees, as on rings of 16 views or more, else 2)
    filter_min_track_length: int | None = None
    #: refine camera rotations in bundle adjustment (default: keep the recorded attitudes, which position
    #: priors alone do not hold: with few points the rotations drift to fit keypoint noise)
    refine_rotations: bool = False
    #: "tree": SIFT only on the tree's pixels (recorded segmentation), "none": on the whole image
    mask: str = "tree"
    #: run dense reconstruction (CUDA PatchMatch where pycolmap has CUDA, else the CPU plane sweep)
    dense: bool = True
    dense_options: DenseOptions = field(default_factory=DenseOptions)
    #: score the clouds against the true tree when the dataset has it
    score: bool = True
    num_threads: int = -1

    def __post_init__(self) -> None:
        if self.mask not in ("tree", "none"):
            raise ValueError(f"mask must be 'tree' or 'none', got {self.mask!r}")
        if self.verification not in ("known_poses", "ransac"):
            raise ValueError(f"verification must be 'known_poses' or 'ransac', got {self.verification!r}")
        if self.matcher not in ("spatial", "exhaustive"):
            raise ValueError(f"matcher must be 'spatial' or 'exhaustive', got {self.matcher!r}")
        if self.spatial_neighbors < 1 or self.max_features < 64 or not self.prior_position_std_m > 0:
            raise ValueError(
                "spatial_neighbors >= 1, max_features >= 64 and prior_position_std_m > 0 required"
            )
        short = self.filter_min_track_length is not None and self.filter_min_track_length < 2
        if short or not self.filter_max_reproj_error_px > 0:
            raise ValueError("filter_min_track_length >= 2 and filter_max_reproj_error_px > 0 required")
        if not 0 <= self.filter_min_tri_angle_deg < 90:
            raise ValueError("filter_min_tri_angle_deg must lie in [0, 90) degrees")


#: the widest angle between views that SIFT matches the tree's leaves across: a point is asked to be in
#: three images only where three views fit in it (an 18-view ring's three neighbours span 40 degrees)
MATCH_SPAN_DEG = 45.0


def view_spacing_deg(T_world_optical: Mapping[str, np.ndarray]) -> float:
    """The median, over the views, of the angle between a view's optical axis and its nearest
    neighbour's (degrees): 20 on an 18-view ring, 30 on a 12-view one."""
    axes = np.array([T[:3, 2] for T in T_world_optical.values()], dtype=float)
    if len(axes) < 2:
        raise ValueError("the spacing of the views needs at least two views")
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    cos = np.clip(axes @ axes.T, -1.0, 1.0)
    np.fill_diagonal(cos, -2.0)
    return float(np.median(np.degrees(np.arccos(cos.max(axis=1)))))


def auto_min_track_length(spacing_deg: float, most: int = 3) -> int:
    """The track length a sparse point is asked for on views ``spacing_deg`` apart: as many views as fit
    in :data:`MATCH_SPAN_DEG` (1 + span // spacing), at least 2 and at most ``most``."""
    fit = 1 + math.floor(MATCH_SPAN_DEG / max(spacing_deg, 1e-9) + 1e-9)
    return max(2, min(most, fit))


def sparse_views_warning(spacing_deg: float) -> str | None:
    """A warning when neighbouring views lie further apart than SIFT matches; None otherwise."""
    if spacing_deg <= MATCH_SPAN_DEG:
        return None
    return (
        f"neighbouring views are {spacing_deg:.0f} degrees apart, more than the {MATCH_SPAN_DEG:.0f} SIFT "
        "matches the tree across: few points can be triangulated; capture more views "
        f"(at least {math.ceil(360.0 / MATCH_SPAN_DEG)} a ring, 18 for three-view tracks)"
    )


def _pycolmap() -> Any:
    try:
        import pycolmap
    except ImportError as exc:  # pragma: no cover - depends on the installed extras
        raise RuntimeError(
            "droneulator reconstruct needs pycolmap: pip install 'droneulator[colmap]'"
        ) from exc
    return pycolmap


# --------------------------------------------------------------------------- convention checks
def known_pose_reprojection(
    rec: Any, K: np.ndarray, T_world_optical: dict[str, np.ndarray]
) -> dict[str, float | int]:
    """Project ``rec``'s 3D points with the *recorded* poses (by image name) and the OpenCV K, and compare
    with the observed keypoints moved back to the OpenCV pixel convention. Pure numpy: it checks that the
    pose and pixel conventions used to write the model agree with what COLMAP triangulated."""
    errors = []
    for image in rec.images.values():
        if image.name not in T_world_optical:
            continue
        pts2d = image.get_observation_points2D()
        if not len(pts2d):
            continue
        uv = colmap_to_opencv_pixels(np.array([p.xy for p in pts2d]))
        X = np.array([rec.points3D[p.point3D_id].xyz for p in pts2d])
        errors.append(np.linalg.norm(project_opencv(K, T_world_optical[image.name], X) - uv, axis=1))
    e = np.concatenate(errors) if errors else np.array([np.nan])
    return {
        "observations": int(np.isfinite(e).sum()),
        "mean_px": float(np.nanmean(e)),
        "median_px": float(np.nanmedian(e)),
        "p95_px": float(np.nanpercentile(e, 95)),
    }


def model_convention_error(rec: Any, points_world: np.ndarray, observations: dict[str, np.ndarray]) -> float:
    """Mean pixel distance between where pycolmap projects ``points_world`` (n, 3) through ``rec``'s cameras
    and poses, and ``observations`` (image name -> (n, 2) OpenCV pixels, NaN where unseen) moved to COLMAP's
    pixel convention. Near zero when a model was written with the right conventions."""
    errors = []
    for image in rec.images.values():
        uv_cv = observations[image.name]
        cam = rec.cameras[image.camera_id]
        p_cam = np.array([image.cam_from_world() * x for x in points_world])
        uv = np.array(cam.img_from_cam(p_cam))[:, :2]
        uv[p_cam[:, 2] <= 0] = np.nan
        errors.append(np.linalg.norm(uv - (uv_cv + COLMAP_PIXEL_OFFSET), axis=1))
    e = np.concatenate(errors)
    return float(np.inf) if np.isnan(e).any() else float(e.mean())


# --------------------------------------------------------------------------- the pipeline
def _reference(pycolmap: Any, db_path: Path, known: Any) -> Any:
    """The known poses re-keyed on the database's camera, rig, frame and image ids (matched by name):
    the feature extractor numbers images in the order its threads finish them."""
    ref = pycolmap.Reconstruction()
    db = pycolmap.Database.open(db_path)
    try:
        for cam in db.read_all_cameras():
            ref.add_camera(cam)
        for rig in db.read_all_rigs():
            ref.add_rig(rig)
        frames = {f.frame_id: f for f in db.read_all_frames()}
        for image in db.read_all_images():
            frame = frames[image.frame_id]
            frame.rig_from_world = known.find_image_with_name(image.name).cam_from_world()
            ref.add_frame(frame)
            ref.add_image(image)
            ref.register_frame(frame.frame_id)
    finally:
        db.close()
    return ref


def _write_priors(pycolmap: Any, db_path: Path, known: Any, std: float) -> list[Any]:
    db = pycolmap.Database.open(db_path)
    try:
        db.clear_pose_priors()
        for image in db.read_all_images():
            prior = pycolmap.PosePrior()
            prior.corr_data_id = pycolmap.data_t(
                pycolmap.sensor_t(pycolmap.SensorType.CAMERA, image.camera_id), image.image_id
            )
            prior.position = known.find_image_with_name(image.name).projection_center()
            prior.position_covariance = np.eye(3) * std**2
            prior.coordinate_system = pycolmap.PosePriorCoordinateSystem.CARTESIAN
            db.write_pose_prior(prior)
        return db.read_all_pose_priors()
    finally:
        db.close()


def _pose_drift(rec: Any, known: Any) -> dict[str, float]:
    """How far bundle adjustment moved each camera from its recorded pose (centre in m, rotation in deg)."""
    dt, dr = [], []
    for image in rec.images.values():
        k = known.find_image_with_name(image.name)
        dt.append(float(np.linalg.norm(image.projection_center() - k.projection_center())))
        R = image.cam_from_world().rotation.matrix() @ k.cam_from_world().rotation.matrix().T
        dr.append(math.degrees(math.acos(float(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0)))))
    return {
        "max_position_m": max(dt),
        "mean_position_m": float(np.mean(dt)),
        "max_rotation_deg": max(dr),
        "mean_rotation_deg": float(np.mean(dr)),
    }


def _stats(rec: Any) -> dict[str, Any]:
    rec.update_point_3d_errors()
    return {
        "registered_images": rec.num_reg_images(),
        "sparse_points": rec.num_points3D(),
        "observations": rec.compute_num_observations(),
        "mean_track_length": rec.compute_mean_track_length(),
        "mean_observations_per_image": rec.compute_mean_observations_per_reg_image(),
        "mean_reprojection_error_px": rec.compute_mean_reprojection_error(),
    }


def filter_sparse(
    pycolmap: Any, rec: Any, max_reproj_error_px: float, min_tri_angle_deg: float, min_track_length: int
) -> dict[str, Any]:
    """Filter ``rec``'s points in place with pycolmap's own rules, in COLMAP's order: observations with a
    reprojection error above ``max_reproj_error_px`` (a point left with one goes), observations behind
    their camera, points triangulated at less than ``min_tri_angle_deg``, then points in fewer than
    ``min_track_length`` images. Returns the points and observations before, the points each rule
    removed, and what is left."""
    obs = pycolmap.ObservationManager(rec)
    before = {"points": rec.num_points3D(), "observations": rec.compute_num_observations()}
    counts = [rec.num_points3D()]
    obs.filter_points3D_with_large_reprojection_error(max_reproj_error_px, set(rec.point3D_ids()))
    counts.append(rec.num_points3D())
    obs.filter_observations_with_negative_depth()
    counts.append(rec.num_points3D())
    obs.filter_points3D_with_small_triangulation_angle(min_tri_angle_deg, set(rec.point3D_ids()))
    counts.append(rec.num_points3D())
    obs.filter_points3D_with_short_tracks(min_track_length)
    counts.append(rec.num_points3D())
    rules = ("reprojection_error", "negative_depth", "triangulation_angle", "short_track")
    removed = {rule: a - b for rule, a, b in zip(rules, counts, counts[1:], strict=False)}
    rec.update_point_3d_errors()
    return {
        "rules": {
            "max_reproj_error_px": max_reproj_error_px,
            "min_tri_angle_deg": min_tri_angle_deg,
            "min_track_length": min_track_length,
        },
        "before": before,
        "removed_points": removed,
        "after": {"points": rec.num_points3D(), "observations": rec.compute_num_observations()},
    }


def write_masks(dataset: Path, names: list[str], out: Path) -> float:
    """COLMAP feature masks (``NAME.png``: 255 on the tree, 0 elsewhere) from the recorded segmentation;
    returns the mean share of tree pixels."""
    from PIL import Image

    out.mkdir(parents=True, exist_ok=True)
    shares = []
    for name in names:
        seg = dataset / "segmentation" / f"{Path(name).stem}.png"
        if not seg.is_file():
            raise FileNotFoundError(
                f"{seg} is missing: this capture has no segmentation to mask SIFT with "
                "(capture it again, or reconstruct with --mask none)"
            )
        m = tree_mask(seg)
        shares.append(float(m.mean()))
        Image.fromarray((m * 255).astype(np.uint8)).save(out / f"{name}.png")
    return float(np.mean(shares))


def reconstruct(
    dataset: Path, opts: ReconstructOptions | None = None, log: Callable[[str], None] = print
) -> dict[str, Any]:
    """Reconstruct ``dataset`` (a ``droneulator capture`` folder); returns the report (also written)."""
    pycolmap = _pycolmap()
    opts = opts or ReconstructOptions()
    dataset = Path(dataset)
    images_dir = dataset / "images"
    work = dataset / "colmap"
    times: dict[str, float] = {}
    t_all = time.perf_counter()

    def stage(name: str, t0: float) -> None:
        times[name] = time.perf_counter() - t0
        log(f"{name}: {times[name]:.1f} s")

    poses = json.loads((dataset / "poses.json").read_text())
    K = np.array(poses["camera"]["K"], dtype=float)
    T_known = {
        v["name"]: transform_from_pose(
            np.array(v["optical"]["position"]), np.array(v["optical"]["quaternion_xyzw"])
        )
        for v in poses["views"]
    }
    known = pycolmap.Reconstruction(dataset / "sparse_known")
    if known.num_images() < 2:
        raise ValueError(f"{dataset} holds {known.num_images()} image(s): at least 2 are needed")
    camera = known.cameras[1]
    if not np.allclose(camera.params, colmap_pinhole_params(K), atol=1e-9):
        raise ValueError(
            f"sparse_known camera {list(camera.params)} does not match camera_info K {K.tolist()}"
        )
    names = sorted(im.name for im in known.images.values())
    spacing = view_spacing_deg(T_known)
    min_track = opts.filter_min_track_length or auto_min_track_length(spacing)
    sparse_warning = sparse_views_warning(spacing)
    if sparse_warning is not None:
        log(f"warning: {sparse_warning}")
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    db_path = work / "database.db"

    t0 = time.perf_counter()
    db = pycolmap.Database.open(db_path)
    db.write_camera(camera, use_camera_id=True)
    db.close()
    reader = pycolmap.ImageReaderOptions()
    reader.existing_camera_id = camera.camera_id
    tree_share = None
    if opts.mask == "tree":
        tree_share = write_masks(dataset, names, work / "masks")
        reader.mask_path = str(work / "masks")
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.sift.max_num_features = opts.max_features
    extraction.sift.peak_threshold = opts.sift_peak_threshold
    extraction.num_threads = opts.num_threads
    pycolmap.extract_features(
        db_path,
        images_dir,
        image_names=names,
        camera_mode=pycolmap.CameraMode.SINGLE,
        reader_options=reader,
        extraction_options=extraction,
    )
    stage("features", t0)

    t0 = time.perf_counter()
    priors = _write_priors(pycolmap, db_path, known, opts.prior_position_std_m)
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = opts.num_threads
    matching.sift.max_ratio = opts.sift_max_ratio
    matching.guided_matching = opts.guided_matching
    verification = pycolmap.TwoViewGeometryOptions()
    if opts.verification == "known_poses":
        matching.skip_geometric_verification = True
    else:
        # never settle for a homography: the textured ground makes most pairs look planar, and COLMAP then
        # keeps only the ground's homography inliers, dropping every match on the tree
        verification.max_H_inlier_ratio = 1.0
    if opts.matcher == "spatial":
        pairing = pycolmap.SpatialPairingOptions()
        pairing.max_num_neighbors = min(opts.spatial_neighbors, len(names) - 1)
        pairing.ignore_z = False
        pairing.max_distance = 1e6
        pycolmap.match_spatial(
            db_path, matching_options=matching, pairing_options=pairing, verification_options=verification
        )
    else:
        pycolmap.match_exhaustive(db_path, matching_options=matching, verification_options=verification)
    reference = _reference(pycolmap, db_path, known)
    if opts.verification == "known_poses":
        verification.ransac.max_error = opts.max_epipolar_error_px
        pycolmap.guided_geometric_verification(
            reference, db_path, two_view_geometry_options=verification, num_threads=opts.num_threads
        )
    db = pycolmap.Database.open(db_path)
    pairs = {"matched": db.num_matched_image_pairs(), "verified": db.num_verified_image_pairs()}
    db.close()
    stage("matching", t0)

    t0 = time.perf_counter()
    mapper = pycolmap.IncrementalPipelineOptions()
    mapper.num_threads = opts.num_threads
    mapper.mapper.filter_max_reproj_error = opts.max_reproj_error_px
    tri_dir = work / "triangulated"
    rec = pycolmap.triangulate_points(
        _reference(pycolmap, db_path, known), db_path, images_dir, tri_dir, False, mapper
    )
    triangulated = _stats(rec)
    stage("triangulation", t0)

    t0 = time.perf_counter()
    ba = pycolmap.BundleAdjustmentOptions()
    ba.refine_focal_length = False
    ba.refine_principal_point = False
    ba.refine_extra_params = False
    ba.refine_sensor_from_rig = False
    ba.constant_rig_from_world_rotation = not opts.refine_rotations
    ba.print_summary = False
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in rec.reg_image_ids():
        config.add_image(image_id)
    prior_opts = pycolmap.PosePriorBundleAdjustmentOptions()
    prior_opts.prior_position_fallback_stddev = opts.prior_position_std_m
    summary = pycolmap.create_pose_prior_bundle_adjuster(ba, prior_opts, config, priors, rec).solve()
    adjusted = _stats(rec)
    drift = _pose_drift(rec, known)
    stage("bundle_adjustment", t0)

    t0 = time.perf_counter()
    point_filter = filter_sparse(
        pycolmap,
        rec,
        opts.filter_max_reproj_error_px,
        opts.filter_min_tri_angle_deg,
        min_track,
    )
    point_filter["rules"]["view_spacing_deg"] = round(spacing, 3)
    point_filter["rules"]["min_track_length_from"] = (
        "options" if opts.filter_min_track_length else f"view spacing ({MATCH_SPAN_DEG:g} degree span)"
    )
    stats = _stats(rec)
    stage("filter", t0)
    log(
        f"filter: {point_filter['before']['points']} -> {stats['sparse_points']} sparse points "
        f"(removed: {', '.join(f'{k} {v}' for k, v in point_filter['removed_points'].items())})"
    )

    t0 = time.perf_counter()
    sparse = dataset / "sparse"
    shutil.rmtree(sparse, ignore_errors=True)
    sparse.mkdir(parents=True)
    rec.write(sparse)
    stage("write", t0)
    times["sparse_total"] = time.perf_counter() - t_all

    consistency = known_pose_reprojection(rec, K, T_known)
    t0 = time.perf_counter()
    plot_path = dataset / "reconstruction.png"
    plot_reconstruction(rec, plot_path, title=f"{dataset.name}: {stats['sparse_points']} points")
    stage("plot", t0)

    if not opts.dense:
        dense: dict[str, Any] = {"ran": False, "reason": "dense stereo was turned off (--no-dense)"}
    elif pycolmap.has_cuda and opts.dense_options.path == "auto":
        t0 = time.perf_counter()
        dense = dense_cuda(pycolmap, dataset, sparse, images_dir)
        stage("dense", t0)
    else:
        t0 = time.perf_counter()
        dense = dense_cpu(rec, dataset, K, opts.dense_options, log=log)
        dense["cuda_available"] = bool(pycolmap.has_cuda)
        stage("dense", t0)
    times["total"] = time.perf_counter() - t_all
    scores = None
    if opts.score and (dataset / "truth" / "mesh.npz").is_file():
        t0 = time.perf_counter()
        scores = score(dataset)
        stage("score", t0)

    report = {
        "dataset": str(dataset),
        "images": len(names),
        **stats,
        "triangulated_before_ba": triangulated,
        "after_ba_before_filter": adjusted,
        "sparse_filter": point_filter,
        "warnings": [sparse_warning] if sparse_warning else [],
        "known_pose_reprojection": consistency,
        "pose_drift_after_ba": drift,
        "ba_termination": str(getattr(summary, "termination_type", "")),
        "image_pairs": pairs,
        "times_s": {k: round(v, 3) for k, v in times.items()},
        "dense": dense,
        "sift_mask": {"mask": opts.mask, "mean_tree_share": tree_share},
        "score": scores,
        "options": asdict(opts),
        "pycolmap": {"version": pycolmap.__version__, "has_cuda": bool(pycolmap.has_cuda)},
        "outputs": {"sparse": str(sparse), "plot": str(plot_path), "database": str(db_path)},
    }
    (dataset / "report.json").write_text(json.dumps(report, indent=1))
    (dataset / "report.md").write_text(report_markdown(report))
    log(
        f"{stats['registered_images']}/{len(names)} images, {stats['sparse_points']} points, mean track "
        f"{stats['mean_track_length']:.2f}, reprojection {stats['mean_reprojection_error_px']:.3f} px "
        f"(known poses: {consistency['mean_px']:.3f} px), sparse in {times['sparse_total']:.1f} s; "
        f"dense: {'ran' if dense['ran'] else dense['reason']}"
    )
    return report


def report_markdown(r: dict[str, Any]) -> str:
    t = r["times_s"]
    c = r["known_pose_reprojection"]
    d = r["pose_drift_after_ba"]
    f = r.get("sparse_filter")  # absent from reports written before the filter
    lines = [
        f"# Reconstruction of `{r['dataset']}`",
        "",
        "| metric | value |",
        "|---|---|",
        f"| images registered | {r['registered_images']} / {r['images']} |",
        f"| sparse points | {r['sparse_points']} |",
        *(
            [
                f"| sparse points before filtering | {f['before']['points']} (removed: "
                + ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in f["removed_points"].items())
                + f"; rules: reprojection <= {f['rules']['max_reproj_error_px']:g} px, triangulation "
                f"angle >= {f['rules']['min_tri_angle_deg']:g} deg, track >= "
                f"{f['rules']['min_track_length']} images"
                + (
                    f", views {f['rules']['view_spacing_deg']:.1f} deg apart"
                    if "view_spacing_deg" in f["rules"]
                    else ""
                )
                + ") |"
            ]
            if f
            else []
        ),
        f"| observations | {r['observations']} |",
        f"| mean track length | {r['mean_track_length']:.2f} |",
        f"| mean reprojection error | {r['mean_reprojection_error_px']:.3f} px |",
        f"| reprojection with the recorded poses and camera_info K | mean {c['mean_px']:.3f} px, "
        f"median {c['median_px']:.3f} px, p95 {c['p95_px']:.3f} px |",
        f"| camera drift from the priors after BA | max {d['max_position_m'] * 1000:.1f} mm, "
        f"{d['max_rotation_deg']:.3f} deg |",
        f"| image pairs matched / verified | {r['image_pairs']['matched']} / "
        f"{r['image_pairs']['verified']} |",
        "",
        "| stage | time (s) |",
        "|---|---|",
        *(f"| {k} | {v:.1f} |" for k, v in t.items()),
        "",
        "SIFT mask: "
        + (
            f"tree only (the recorded segmentation, standing in for a segmentation network; the tree is "
            f"{r['sift_mask']['mean_tree_share'] * 100:.0f} % of the pixels on average)"
            if r.get("sift_mask", {}).get("mask") == "tree"
            else "none (whole images)"
        ),
        "",
        "Dense: "
        + (
            f"{r['dense']['dense_points']} fused points, path `{r['dense']['path']}` "
            f"({r['dense']['description']})"
            if r["dense"]["ran"]
            else r["dense"]["reason"]
        ),
        "",
        *([score_markdown(r["score"])] if r.get("score") else []),
        *(f"**Warning:** {w}\n" for w in r.get("warnings", [])),
        f"pycolmap {r['pycolmap']['version']} (CUDA: {r['pycolmap']['has_cuda']}); "
        f"options: `{json.dumps(r['options'])}`",
        "",
    ]
    return "\n".join(lines)


def plot_reconstruction(rec: Any, path: Path, title: str = "", max_points: int = 60000) -> None:
    """Top view (x-y) and side view (x-z) of the sparse points (their colours) and the cameras."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pts = np.array([p.xyz for p in rec.points3D.values()]).reshape(-1, 3)
    rgb = np.array([p.color for p in rec.points3D.values()]).reshape(-1, 3) / 255.0
    if len(pts) > max_points:
        keep = np.random.default_rng(0).choice(len(pts), max_points, replace=False)
        pts, rgb = pts[keep], rgb[keep]
    centers = np.array([im.projection_center() for im in rec.images.values()]).reshape(-1, 3)
    axes_z = np.array([im.viewing_direction() for im in rec.images.values()]).reshape(-1, 3)
    # the tree and the cameras: drop far background points so the axes stay readable
    extent = np.max(np.linalg.norm(centers[:, :2] - centers[:, :2].mean(0), axis=1)) if len(centers) else 1.0
    near = np.linalg.norm(pts[:, :2] - centers[:, :2].mean(0), axis=1) < 2.5 * extent if len(pts) else []
    fig, axs = plt.subplots(1, 2, figsize=(13, 6), dpi=110)
    for ax, (i, j), label in ((axs[0], (0, 1), "top view (x, y)"), (axs[1], (0, 2), "side view (x, z)")):
        if len(pts):
            ax.scatter(pts[near, i], pts[near, j], s=1.5, c=rgb[near], linewidths=0)
        ax.scatter(centers[:, i], centers[:, j], s=14, c="red", marker="^", label="cameras")
        ax.quiver(
            centers[:, i], centers[:, j], axes_z[:, i], axes_z[:, j], color="red", width=0.003, scale=25
        )
        ax.set_aspect("equal")
        ax.set_xlabel(["x", "y", "z"][i] + " (m)")
        ax.set_ylabel(["x", "y", "z"][j] + " (m)")
        ax.set_title(label)
        ax.grid(alpha=0.3)
    axs[0].legend(loc="upper right")
    fig.suptitle(title)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
