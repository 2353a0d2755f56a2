"""Fusion of per-view depth maps into one coloured point cloud, keeping only geometrically consistent
depths, and the PLY files it is written to.

A reference pixel's 3D point is projected into each of its fusion neighbours. A neighbour *agrees*
when its own depth at that pixel (a) differs from the point's depth in the neighbour by less than
``max_depth_error`` (relative) and (b) back-projected and projected into the reference lands within
``max_reproj_px`` of the pixel it started from (the forward-backward check of COLMAP's fusion). A pixel
is fused when at least ``min_consistent`` neighbours agree: its point is the mean of its own and the
agreeing 3D points, its colour the mean of theirs, and the agreeing neighbour pixels are marked used
so that the same surface point is not fused again from another view. A depth map that is wrong
finds no agreement and contributes nothing. With several depth hypotheses per pixel (the plane
sweep's next best cost minima) a pixel whose best depth finds no agreement tries the next one.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from droneulator.workflows.photogrammetry.mvs import View, backproject, project


@dataclass
class FusionOptions:
    #: least number of other views whose depth maps agree with a pixel's depth: one, since much of the
    #: crown (leaves seen between others) is seen by two cameras only; a wrong depth still finds no
    #: other view that agrees with it
    min_consistent: int = 1
    #: largest relative depth difference of an agreeing view
    max_depth_error: float = 0.02
    #: largest forward-backward reprojection error of an agreeing view, pixels (at stereo resolution)
    max_reproj_px: float = 2.0
    #: least number of agreeing views for a pixel's alternative depth hypotheses (``mvs.candidates`` > 1)
    min_consistent_alternative: int = 1
    #: a neighbour agrees through any of its depth hypotheses, not only its best one (more points, and
    #: more wrong ones: see docs/photogrammetry.md)
    neighbor_alternatives: bool = False

    def __post_init__(self) -> None:
        if self.min_consistent < 1 or not self.max_depth_error > 0 or not self.max_reproj_px > 0:
            raise ValueError("fusion needs min_consistent >= 1, max_depth_error > 0 and max_reproj_px > 0")
        if self.min_consistent_alternative < 1:
            raise ValueError("fusion needs min_consistent_alternative >= 1")


@dataclass
class FusedCloud:
    """Fused points (n, 3) in the world frame, colours (n, 3) uint8 RGB, the index of the reference
    view each came from (n,), how many other views agreed with it (n,) and which of its reference
    pixel's depth hypotheses it is (n,; 0: the best)."""

    points: np.ndarray
    colors: np.ndarray
    source: np.ndarray
    support: np.ndarray
    hypothesis: np.ndarray


def _agreeing(
    ref: View, X: np.ndarray, rc: np.ndarray, nb: View, layers: np.ndarray, opts: FusionOptions
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Which of the reference points ``X`` (n, 3; from pixels ``rc``) neighbour ``nb`` agrees with, through
    the depth hypotheses ``layers`` (m, H, W) it holds per pixel (the one nearest the point's depth):
    their indices into ``X``, the neighbour's own points (world) and its pixels' rows and columns."""
    uv, z = project(nb, X)
    h, w = layers.shape[1:]
    u = np.rint(uv[:, 0]).astype(np.int64, copy=False) if len(uv) else np.zeros(0, np.int64)
    v = np.rint(uv[:, 1]).astype(np.int64, copy=False) if len(uv) else np.zeros(0, np.int64)
    inside = (z > 0) & np.isfinite(uv).all(axis=1) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    idx = np.nonzero(inside)[0]
    cand = layers[:, v[idx], u[idx]].astype(np.float64)
    with np.errstate(invalid="ignore"):
        rel = np.abs(z[idx][None] - cand) / cand
    rel = np.where(np.isfinite(rel), rel, np.inf)
    pick = np.argmin(rel, axis=0) if len(layers) > 1 else np.zeros(len(idx), np.int64)
    dn = cand[pick, np.arange(len(idx))]
    ok = rel[pick, np.arange(len(idx))] < opts.max_depth_error
    idx, dn = idx[ok], dn[ok]
    # forward-backward: the neighbour's own point, seen from the reference
    K = nb.K
    p_cam = np.column_stack([(u[idx] - K[0, 2]) / K[0, 0] * dn, (v[idx] - K[1, 2]) / K[1, 1] * dn, dn])
    Y = p_cam @ nb.T_world_cam[:3, :3].T + nb.T_world_cam[:3, 3]
    uv_back, _ = project(ref, Y)
    good = np.linalg.norm(uv_back - rc[idx][:, ::-1], axis=1) < opts.max_reproj_px
    idx = idx[good]
    return idx, Y[good], v[idx], u[idx]


def fuse(
    views: list[View],
    depths: list[np.ndarray],
    neighbors: list[list[int]],
    opts: FusionOptions,
    alternatives: list[np.ndarray | None] | None = None,
) -> FusedCloud:
    """Fuse ``depths[i]`` (NaN: none; the size of ``views[i]``) checking each view's pixels against the
    depth maps of ``neighbors[i]``. With ``alternatives[i]`` (m, H, W: other depth hypotheses per pixel,
    best first, NaN: none) a pixel whose depth finds too few agreeing views tries its alternatives in
    turn (``opts.min_consistent_alternative``); with ``opts.neighbor_alternatives`` a neighbour agrees
    through whichever of its hypotheses is nearest the point, else through its best one."""
    if len(views) != len(depths) or len(views) != len(neighbors):
        raise ValueError("fuse needs one depth map and one neighbour list per view")
    if alternatives is not None and len(alternatives) != len(views):
        raise ValueError("fuse needs one set of alternatives per view")
    layers = []
    for k, (v, d) in enumerate(zip(views, depths, strict=True)):
        if d.shape != v.shape:
            raise ValueError(f"{v.name}: depth map {d.shape} and image {v.shape} differ in size")
        alt = None if alternatives is None else alternatives[k]
        if alt is not None and alt.shape[1:] != d.shape:
            raise ValueError(f"{v.name}: alternatives {alt.shape} and depth map {d.shape} differ in size")
        layers.append(d[None] if alt is None or not len(alt) else np.concatenate([d[None], alt]))
    used = [np.zeros(d.shape, dtype=bool) for d in depths]
    pts_out, col_out, src_out, sup_out, hyp_out = [], [], [], [], []
    for i, ref in enumerate(views):
        for h, hyp in enumerate(layers[i]):
            d = np.where(used[i], np.nan, hyp)
            X, rc = backproject(ref, d)
            if not len(X):
                continue
            acc = X.copy()
            col = ref.rgb[rc[:, 0], rc[:, 1]].astype(np.float64)
            count = np.zeros(len(X), dtype=np.int64)
            hits: list[tuple[int, np.ndarray, np.ndarray, np.ndarray]] = []
            for j in neighbors[i]:
                if j == i:
                    continue
                nb_layers = layers[j] if opts.neighbor_alternatives else layers[j][:1]
                idx, Y, vj, uj = _agreeing(ref, X, rc, views[j], nb_layers, opts)
                acc[idx] += Y
                col[idx] += views[j].rgb[vj, uj]
                count[idx] += 1
                hits.append((j, idx, vj, uj))
            keep = count >= (opts.min_consistent if h == 0 else opts.min_consistent_alternative)
            if not keep.any():
                continue
            # a kept pixel is not tried again with its next hypothesis
            used[i][rc[keep, 0], rc[keep, 1]] = True
            for j, idx, vj, uj in hits:
                sel = keep[idx]
                used[j][vj[sel], uj[sel]] = True
            n = (count[keep] + 1)[:, None]
            pts_out.append(acc[keep] / n)
            col_out.append(np.clip(np.rint(col[keep] / n), 0, 255).astype(np.uint8))
            src_out.append(np.full(int(keep.sum()), i, dtype=np.int32))
            sup_out.append(count[keep].astype(np.int32))
            hyp_out.append(np.full(int(keep.sum()), h, dtype=np.int8))
    if not pts_out:
        empty = np.zeros(0, np.int32)
        return FusedCloud(np.zeros((0, 3)), np.zeros((0, 3), np.uint8), empty, empty, empty.astype(np.int8))
    return FusedCloud(
        np.concatenate(pts_out),
        np.concatenate(col_out),
        np.concatenate(src_out),
        np.concatenate(sup_out),
        np.concatenate(hyp_out),
    )


# --------------------------------------------------------------------------- PLY
_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip


def write_ply(path: Path, points: np.ndarray, colors: np.ndarray) -> None:
    """Binary little-endian PLY with float x, y, z and uchar red, green, blue per vertex."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    colors = np.asarray(colors, dtype=np.uint8).reshape(-1, 3)
    if len(points) != len(colors):
        raise ValueError(f"{len(points)} points but {len(colors)} colours")
    rec = np.empty(len(points), dtype=[("xyz", "<f4", 3), ("rgb", "u1", 3)])
    rec["xyz"] = points
    rec["rgb"] = colors
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(points)}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
    )
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(rec.tobytes())
    tmp.replace(path)


def read_ply(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Vertices (n, 3) and colours (n, 3) uint8 (None when absent) of a binary little-endian PLY whose
    first element is ``vertex`` (ours, and COLMAP's ``fused.ply``)."""
    data = Path(path).read_bytes()
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply") or end < 0:
        raise ValueError(f"{path} is not a PLY file")
    lines = data[:end].decode("ascii").splitlines()
    if "format binary_little_endian 1.0" not in lines:
        raise ValueError(f"{path}: only binary_little_endian PLY is read")
    count, fields, in_vertex = 0, [], False
    for line in lines:
        parts = line.split()
        if parts[:1] == ["element"]:
            if in_vertex:
                break
            in_vertex = parts[1] == "vertex"
            count = int(parts[2]) if in_vertex else count
        elif parts[:1] == ["property"] and in_vertex:
            if parts[1] == "list" or parts[1] not in _PLY_TYPES:
                raise ValueError(f"{path}: unsupported vertex property {line!r}")
            fields.append((parts[2], "<" + _PLY_TYPES[parts[1]]))
    rec = np.frombuffer(data, dtype=np.dtype(fields), count=count, offset=end + len(b"end_header\n"))
    xyz = np.column_stack([rec["x"], rec["y"], rec["z"]]).astype(np.float64)
    names = rec.dtype.names or ()
    rgb = (
        np.column_stack([rec["red"], rec["green"], rec["blue"]]).astype(np.uint8) if "red" in names else None
    )
    return xyz, rgb
