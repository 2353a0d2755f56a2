"""``droneulator score``: a reconstruction against the true tree, which no field survey has.

For the sparse model (``sparse/``, in the world frame: it was triangulated from the recorded poses and
bundle-adjusted with priors on them) and the dense cloud (``dense/fused.ply``), every point is given
the class of its nearest true surface (tree or ground, from ``truth/mesh.npz``) and its distance to
it (accuracy: median and 90th percentile). Points more than ``FAR_M`` from any true surface kept in
the truth (the distant background trees and rocks) are counted apart. Over all points, whatever
their class, the same accuracy is given for the points inside the truth's region (within the radius
of its ground around the tree, where every surface is in the truth), with the share of them more than
``FAR_M`` from every surface (wrong points: mismatches); points beyond that radius (the distant trees
the tree mask also covers) cannot be judged and are only counted. Completeness is the share of
the true surface, as samples ``spacing`` apart, that has a reconstructed point within ``radius``
(5 cm): over all of it, and over the part the cameras saw (a sample in front of the recorded depth
of at least two views: the inside of the crown is hidden behind its own leaves from every orbit).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image
from scipy.spatial import cKDTree

from droneulator.frames import transform_from_pose
from droneulator.workflows.photogrammetry.fusion import read_ply
from droneulator.workflows.photogrammetry.truth import (
    CLASS_NAMES,
    GROUND,
    TREE,
    SurfaceIndex,
    SurfaceSamples,
    load_truth,
    sample_surface,
)

#: points farther than this from every true surface are background (outside the truth's region)
FAR_M = 0.5
#: a sample is seen by a view when it lies no further than this behind the recorded depth (m, plus 1 %)
VISIBLE_TOL_M = 0.03


def truth_region(samples: SurfaceSamples) -> tuple[np.ndarray, float]:
    """Where the truth holds every surface: the horizontal centre of the tree's samples and the largest
    horizontal distance of a ground sample from it (the capture keeps the ground within its radius)."""
    center = samples.points[samples.score_class == TREE, :2].mean(axis=0)
    ground = samples.points[samples.score_class == GROUND, :2]
    extent = np.linalg.norm(ground - center, axis=1).max() if len(ground) else np.inf
    return center, float(extent)


def cloud_metrics(
    points: np.ndarray,
    index: SurfaceIndex,
    visible: np.ndarray | None,
    radius: float = 0.05,
    region: tuple[np.ndarray, float] | None = None,
) -> dict[str, Any]:
    """Accuracy and completeness of ``points`` (n, 3) against the sampled true surface, by class, and
    the accuracy of all points inside ``region`` (default :func:`truth_region`) whatever their class."""
    s = index.samples
    dist, nearest = index.query(points) if len(points) else (np.zeros(0), np.zeros(0, np.int64))
    cls = s.score_class[nearest] if len(points) else np.zeros(0, np.uint8)
    far = dist > FAR_M
    center, extent = region if region is not None else truth_region(s)
    inside = np.linalg.norm(points.reshape(-1, 3)[:, :2] - center, axis=1) <= extent
    d_in = dist[inside]
    out: dict[str, Any] = {
        "points": int(len(points)),
        "background_points": int(far.sum()),
        "far_share": float(far.mean()) if len(points) else None,
        "all": {
            "points_in_truth_region": int(inside.sum()),
            "points_beyond_truth_region": int((~inside).sum()),
            "truth_region_radius_m": extent,
            "points_within_radius": int((d_in <= radius).sum()),
            "accuracy_median_m": float(np.median(d_in)) if len(d_in) else None,
            "accuracy_p90_m": float(np.percentile(d_in, 90)) if len(d_in) else None,
            "far_points": int((d_in > FAR_M).sum()),
            "far_share": float((d_in > FAR_M).mean()) if len(d_in) else None,
        },
    }
    covered = np.zeros(len(s.points), dtype=bool)
    if len(points):
        d_cov, _ = cKDTree(points).query(s.points, k=1, distance_upper_bound=radius, workers=-1)
        covered = np.isfinite(d_cov)
    for c, name in CLASS_NAMES.items():
        mine = (cls == c) & ~far
        d = dist[mine]
        samples = s.score_class == c
        entry: dict[str, Any] = {
            "points": int(mine.sum()),
            "points_within_radius": int((d <= radius).sum()),
            "accuracy_median_m": float(np.median(d)) if len(d) else None,
            "accuracy_p90_m": float(np.percentile(d, 90)) if len(d) else None,
            "completeness": float(covered[samples].mean()) if samples.any() else None,
        }
        if visible is not None:
            seen = samples & visible
            entry["visible_share_of_surface"] = float(seen.sum() / max(samples.sum(), 1))
            entry["completeness_visible"] = float(covered[seen].mean()) if seen.any() else None
        out[name] = entry
    return out


def visible_samples(dataset: Path, samples: SurfaceSamples, min_views: int = 2) -> np.ndarray | None:
    """Samples in front of (or on) the recorded depth of at least ``min_views`` capture views; None when
    the dataset has no recorded depth."""
    poses = json.loads((dataset / "poses.json").read_text())
    K = np.array(poses["camera"]["K"], dtype=float)
    seen = np.zeros(len(samples.points), dtype=np.int32)
    used = 0
    for v in poses["views"]:
        path = dataset / "truth" / "depth" / f"{Path(v['name']).stem}.npz"
        if not path.is_file():
            continue
        with np.load(path) as z:
            depth = z["depth"].astype(np.float32)
        used += 1
        T = np.linalg.inv(
            transform_from_pose(np.array(v["optical"]["position"]), np.array(v["optical"]["quaternion_xyzw"]))
        )
        p = samples.points @ T[:3, :3].T + T[:3, 3]
        z = p[:, 2]
        front = z > 0.05
        u = np.full(len(z), -1, np.int64)
        r = np.full(len(z), -1, np.int64)
        u[front] = np.rint(K[0, 0] * p[front, 0] / z[front] + K[0, 2])
        r[front] = np.rint(K[1, 1] * p[front, 1] / z[front] + K[1, 2])
        h, w = depth.shape
        ok = front & (u >= 0) & (u < w) & (r >= 0) & (r < h)
        idx = np.nonzero(ok)[0]
        d = depth[r[idx], u[idx]]
        vis = ~np.isfinite(d) | (z[idx] <= d + VISIBLE_TOL_M + 0.01 * d)
        seen[idx[vis]] += 1
    return seen >= min_views if used else None


def sparse_points(dataset: Path) -> np.ndarray | None:
    path = dataset / "sparse"
    if not (path / "points3D.bin").is_file() and not (path / "points3D.txt").is_file():
        return None
    import pycolmap

    rec = pycolmap.Reconstruction(path)
    return np.array([p.xyz for p in rec.points3D.values()]).reshape(-1, 3)


def score(dataset: Path, spacing: float = 0.02, radius: float = 0.05, plots: bool = True) -> dict[str, Any]:
    """Score ``dataset``'s sparse and dense clouds against its true tree; writes ``score.json`` (and the
    error figure ``dense_error.png``) and returns the scores."""
    dataset = Path(dataset)
    samples = sample_surface(load_truth(dataset), spacing)
    index = SurfaceIndex(samples)
    region = truth_region(samples)
    visible = visible_samples(dataset, samples)
    result: dict[str, Any] = {
        "truth": {
            "samples": int(len(samples.points)),
            "spacing_m": spacing,
            "tree_samples": int((samples.score_class == TREE).sum()),
            "ground_samples": int((samples.score_class == GROUND).sum()),
            "visibility": "recorded depth of >= 2 views" if visible is not None else "no recorded depth",
        },
        "radius_m": radius,
    }
    sp = sparse_points(dataset)
    if sp is not None:
        result["sparse"] = cloud_metrics(sp, index, visible, radius, region)
    fused = dataset / "dense" / "fused.ply"
    if fused.is_file():
        pts, _ = read_ply(fused)
        result["dense"] = cloud_metrics(pts, index, visible, radius, region)
        if plots and len(pts):
            dist, nearest = index.query(pts)
            keep = (samples.score_class[nearest] == TREE) & (dist <= FAR_M)
            result["dense"]["figure"] = str(
                plot_errors(dataset, pts[keep], dist[keep], dataset / "dense_error.png")
            )
    (dataset / "score.json").write_text(json.dumps(result, indent=1))
    return result


def plot_errors(dataset: Path, points: np.ndarray, errors: np.ndarray, path: Path, vmax: float = 0.1) -> Path:
    """Two opposite capture views of the tree, each beside the dense tree points seen through the same
    camera and coloured by their distance to the true surface."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    poses = json.loads((dataset / "poses.json").read_text())
    K = np.array(poses["camera"]["K"], dtype=float)
    w, h = poses["camera"]["width"], poses["camera"]["height"]
    views = poses["views"]
    first = views[0]
    opposite = min(
        views, key=lambda v: abs(abs(((v["azimuth_deg"] - first["azimuth_deg"]) + 180) % 360 - 180) - 180)
    )
    fig, axs = plt.subplots(2, 2, figsize=(12, 9.5), dpi=100)
    for row, v in enumerate((first, opposite)):
        img = np.asarray(Image.open(dataset / "images" / v["name"]).convert("RGB"))
        T = np.linalg.inv(
            transform_from_pose(np.array(v["optical"]["position"]), np.array(v["optical"]["quaternion_xyzw"]))
        )
        p = points @ T[:3, :3].T + T[:3, 3]
        front = p[:, 2] > 0.1
        p, e = p[front], errors[front]
        u = K[0, 0] * p[:, 0] / p[:, 2] + K[0, 2]
        r = K[1, 1] * p[:, 1] / p[:, 2] + K[1, 2]
        order = np.argsort(-p[:, 2])  # far first, so the near side is drawn on top
        axs[row, 0].imshow(img)
        axs[row, 0].set_title(f"{v['name']} (rendered), azimuth {v['azimuth_deg']:.0f} deg")
        ax = axs[row, 1]
        ax.set_facecolor("0.15")
        sc = ax.scatter(
            u[order], r[order], c=e[order], s=0.6, cmap="turbo", vmin=0.0, vmax=vmax, linewidths=0
        )
        ax.set_xlim(0, w)
        ax.set_ylim(h, 0)
        ax.set_aspect("equal")
        ax.set_title(f"dense tree points through the same camera ({len(p)}), error")
        fig.colorbar(sc, ax=ax, fraction=0.035, label="distance to the true surface (m)")
        for a in axs[row]:
            a.set_xticks([])
            a.set_yticks([])
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def score_markdown(s: dict[str, Any]) -> str:
    """The score as a markdown section (appended to ``report.md``)."""
    lines = [
        "## Score against the true tree",
        "",
        f"True surface: {s['truth']['tree_samples']} tree and {s['truth']['ground_samples']} ground samples, "
        f"{s['truth']['spacing_m'] * 100:.0f} cm apart; visible part: {s['truth']['visibility']}. Accuracy: "
        "distance of each point to the true surface of its class (nearest surface); completeness: share of "
        f"the true surface within {s['radius_m'] * 100:.0f} cm of a point.",
        "",
        "| cloud | class | points | within radius | accuracy median / p90 | completeness (all / visible) |",
        "|---|---|---|---|---|---|",
    ]
    for cloud in ("sparse", "dense"):
        if cloud not in s:
            continue
        for name in CLASS_NAMES.values():
            e = s[cloud][name]
            acc = (
                f"{e['accuracy_median_m'] * 100:.1f} / {e['accuracy_p90_m'] * 100:.1f} cm"
                if e["accuracy_median_m"] is not None
                else "-"
            )
            vis = e.get("completeness_visible")
            comp = f"{e['completeness'] * 100:.1f} % / " + ("-" if vis is None else f"{vis * 100:.1f} %")
            lines.append(
                f"| {cloud} | {name} | {e['points']} | {e['points_within_radius']} | {acc} | {comp} |"
            )
        lines.append(
            f"| {cloud} | background (> {FAR_M} m from both) | {s[cloud]['background_points']} | | | |"
        )
        a = s[cloud].get("all")
        if a and a["accuracy_median_m"] is not None:
            lines.append(
                f"| {cloud} | all within {a['truth_region_radius_m']:.1f} m of the tree, any class "
                f"({a['far_share'] * 100:.2f} % > {FAR_M} m from every surface; "
                f"{a['points_beyond_truth_region']} points beyond, not judged) | "
                f"{a['points_in_truth_region']} | {a['points_within_radius']} | "
                f"{a['accuracy_median_m'] * 100:.1f} / {a['accuracy_p90_m'] * 100:.1f} cm | |"
            )
    if "dense" in s and s["dense"].get("figure"):
        lines += ["", f"![dense tree points coloured by error]({Path(s['dense']['figure']).name})"]
    return "\n".join(lines) + "\n"
