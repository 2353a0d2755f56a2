"""Dense reconstruction of a capture from its sparse model: COLMAP's PatchMatch where pycolmap has CUDA,
else the CPU path of :mod:`.mvs` (plane-sweep depth maps) and :mod:`.fusion` (consistent points).

Both write ``DATASET/dense/fused.ply`` (world frame, the poses' ``map``); the report says which path
ran. The CPU path reads the poses from the sparse model (after bundle adjustment with pose priors, so
in the world frame of the recorded poses), the intrinsics from ``camera_info`` (OpenCV pixel
convention) and the sparse points to pick each view's neighbours and depth range. With
``mask="tree"`` only the tree's pixels (the segmentation the capture recorded, standing in for a
user's segmentation network) get a depth map.
"""

from __future__ import annotations

import json
import shutil
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from droneulator.workflows.photogrammetry.fusion import FusionOptions, fuse, write_ply
from droneulator.workflows.photogrammetry.mvs import (
    MvsOptions,
    View,
    depth_range,
    geometric_neighbors,
    in_frustum,
    load_view,
    plane_sweep,
    select_neighbors,
)
from droneulator.workflows.photogrammetry.patchmatch import patchmatch_refine, patchmatch_settings

#: a view needs this many sparse points for its own depth range and neighbours
MIN_SPARSE = 10
#: segmentation class ids that are the tree (trunk, branch, canopy, fruit; see scenes.base.SemanticClass)
TREE_CLASS_IDS = (2, 3, 4, 7)


@dataclass
class DenseOptions:
    mvs: MvsOptions = field(default_factory=MvsOptions)
    fusion: FusionOptions = field(default_factory=FusionOptions)
    #: "tree": depth only for the tree's pixels (segmentation), "none": every pixel
    mask: str = "tree"
    #: views whose depth maps each view is checked against in fusion
    fusion_neighbors: int = 8
    #: "auto": COLMAP's CUDA PatchMatch when pycolmap has CUDA, else the CPU plane sweep; "cpu": always CPU
    path: str = "auto"

    def __post_init__(self) -> None:
        if self.mask not in ("tree", "none"):
            raise ValueError(f"dense mask must be 'tree' or 'none', got {self.mask!r}")
        if self.path not in ("auto", "cpu"):
            raise ValueError(f"dense path must be 'auto' or 'cpu', got {self.path!r}")
        if self.fusion_neighbors < self.fusion.min_consistent:
            raise ValueError("fusion_neighbors must be at least fusion.min_consistent")


def tree_mask(segmentation_png: Path) -> np.ndarray:
    """Boolean mask of the tree's pixels in a recorded segmentation image (class ids)."""
    from PIL import Image

    with Image.open(segmentation_png) as img:
        ids = np.asarray(img)
    if ids.ndim != 2:
        raise ValueError(f"{segmentation_png}: expected a single-channel image of class ids")
    return np.isin(ids, TREE_CLASS_IDS)


def views_from_model(
    rec: Any, dataset: Path, K: np.ndarray, mask: str
) -> tuple[list[View], list[np.ndarray], np.ndarray]:
    """The sparse model's registered images as :class:`View` (sorted by name), the sparse point indices
    each one observes, and the sparse points (n, 3)."""
    ids = sorted(rec.points3D)
    points = np.array([rec.points3D[i].xyz for i in ids]).reshape(-1, 3)
    index_of = {pid: k for k, pid in enumerate(ids)}
    views, observed = [], []
    for image in sorted(rec.images.values(), key=lambda im: im.name):
        cfw = image.cam_from_world()
        T_cam_world = np.eye(4)
        T_cam_world[:3, :3] = cfw.rotation.matrix()
        T_cam_world[:3, 3] = np.asarray(cfw.translation)
        T = np.linalg.inv(T_cam_world)  # COLMAP's camera frame is the optical frame
        m = None
        if mask == "tree":
            seg = dataset / "segmentation" / f"{Path(image.name).stem}.png"
            if not seg.is_file():
                raise FileNotFoundError(f"{seg} is missing: capture again, or use the dense mask 'none'")
            m = tree_mask(seg)
        views.append(load_view(image.name, str(dataset / "images" / image.name), K, T, m))
        observed.append(
            np.array([index_of[p.point3D_id] for p in image.points2D if p.has_point3D()], dtype=np.int64)
        )
    return views, observed, points


def dense_cpu(
    rec: Any, dataset: Path, K: np.ndarray, opts: DenseOptions, log: Callable[[str], None] = print
) -> dict[str, Any]:
    """Plane-sweep depth maps and fusion on the CPU; writes ``dense/fused.ply`` and returns the report."""
    out = dataset / "dense"
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    t0 = time.perf_counter()
    full, observed, points = views_from_model(rec, dataset, K, opts.mask)
    views = [v.scaled(opts.mvs.scale) for v in full]
    centers = np.array([v.center for v in views])
    neighbors = select_neighbors(centers, observed, points, opts.mvs)
    fusion_nb = select_neighbors(centers, observed, points, opts.mvs, count=opts.fusion_neighbors)
    # views that see too few sparse points: the points in their frustum for the depth range, and the
    # camera geometry for the neighbours
    seen = [
        points[o] if len(o) >= MIN_SPARSE else in_frustum(v, points)
        for v, o in zip(views, observed, strict=True)
    ]
    centres = [np.median(p, axis=0) if len(p) >= MIN_SPARSE else None for p in seen]
    geometric = geometric_neighbors(views, centres, opts.mvs)
    for i in range(len(views)):
        for nb, count in ((neighbors, opts.mvs.neighbors), (fusion_nb, opts.fusion_neighbors)):
            nb[i] += [j for j in geometric[i] if j not in nb[i]][: max(0, count - len(nb[i]))]
    t_load = time.perf_counter() - t0
    depths: list[np.ndarray] = []
    alternatives: list[np.ndarray | None] = []
    per_view: list[dict[str, Any]] = []
    pm_time = 0.0
    t0 = time.perf_counter()
    # the photometric pass, then (geom_weight > 0) the pass checked against the neighbours' first depths
    for geometric_pass in (False, True) if opts.mvs.geom_weight > 0 else (False,):
        first = depths
        depths, alternatives, per_view = [], [], []
        for i, v in enumerate(views):
            rng = depth_range(v, seen[i], opts.mvs.depth_margin, opts.mvs.subject_depth_factor)
            if rng is None or not neighbors[i] or not v.mask.any():
                depths.append(np.full(v.shape, np.nan, np.float32))
                alternatives.append(None)
                per_view.append({"name": v.name, "pixels": 0, "skipped": True})
                continue
            priors = [first[j] for j in neighbors[i]] if geometric_pass else None
            sources = [views[j] for j in neighbors[i]]
            dm = plane_sweep(v, sources, rng[0], rng[1], opts.mvs, priors)
            if opts.mvs.patchmatch_iterations > 0:
                t_pm = time.perf_counter()
                dm.depth = patchmatch_refine(
                    v, sources, dm.depth, rng[0], rng[1], **patchmatch_settings(opts.mvs)
                ).depth
                pm_time += time.perf_counter() - t_pm
            depths.append(dm.depth)
            alternatives.append(dm.alternatives)
            per_view.append(
                {
                    "name": v.name,
                    "neighbors": [views[j].name for j in neighbors[i]],
                    "depth_range_m": [round(rng[0], 3), round(rng[1], 3)],
                    "pixels": int(np.isfinite(dm.depth).sum()),
                    "masked_pixels": int(v.mask.sum()),
                }
            )
    t_stereo = time.perf_counter() - t0
    log(f"dense (CPU plane sweep): {len(views)} depth maps in {t_stereo:.1f} s")
    t0 = time.perf_counter()
    cloud = fuse(views, depths, fusion_nb, opts.fusion, alternatives)
    for k, pv in enumerate(per_view):
        pv["fused_points"] = int((cloud.source == k).sum())
    write_ply(out / "fused.ply", cloud.points, cloud.colors)
    t_fusion = time.perf_counter() - t0
    np.savez_compressed(
        out / "depth_maps.npz",
        **{Path(v.name).stem: d.astype(np.float16) for v, d in zip(views, depths, strict=True)},
    )
    log(f"fusion: {len(cloud.points)} points in {t_fusion:.1f} s")
    report = {
        "ran": True,
        "path": "cpu-plane-sweep",
        "description": "OpenCV plane-sweep stereo (NCC, fronto-parallel planes) and geometric-consistency "
        "fusion on the CPU",
        "dense_points": int(len(cloud.points)),
        "fused_ply": str(out / "fused.ply"),
        "resolution": list(views[0].shape[::-1]) if views else None,
        "mask": opts.mask,
        "times_s": {
            "load": round(t_load, 3),
            "stereo": round(t_stereo, 3),
            "fusion": round(t_fusion, 3),
            "patchmatch": round(pm_time, 3),
            "total": round(t_load + t_stereo + t_fusion, 3),
        },
        "options": asdict(opts),
        "views": per_view,
    }
    (out / "dense.json").write_text(json.dumps(report, indent=1))
    return report


def dense_cuda(pycolmap: Any, dataset: Path, sparse: Path, images: Path) -> dict[str, Any]:
    """COLMAP's PatchMatch stereo and fusion (pycolmap built with CUDA); ``dense/fused.ply`` in the world
    frame (undistortion keeps the sparse model's frame)."""
    work = dataset / "colmap" / "dense"
    shutil.rmtree(work, ignore_errors=True)
    t0 = time.perf_counter()
    pycolmap.undistort_images(work, sparse, images)
    pycolmap.patch_match_stereo(work)
    fused = pycolmap.stereo_fusion(work / "fused.ply", work, output_type="PLY")
    out = dataset / "dense"
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    shutil.copyfile(work / "fused.ply", out / "fused.ply")
    return {
        "ran": True,
        "path": "colmap-cuda-patchmatch",
        "description": "COLMAP PatchMatch stereo and stereo fusion on the GPU (pycolmap with CUDA)",
        "dense_points": fused.num_points3D(),
        "fused_ply": str(out / "fused.ply"),
        "times_s": {"total": round(time.perf_counter() - t0, 3)},
    }
