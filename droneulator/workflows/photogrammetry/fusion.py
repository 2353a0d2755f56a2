"""Fusion of per-view depth maps into one coloured point cloud, keeping only geometrically consistent
depths, and the PLY files it is written to.

A reference pixel's 3D point is projected into each of its fusion neighbours. A neighbour *agrees*
when its own depth at that pixel (a) differs from the point's depth in the neighbour by less than
``max_depth_error`` (relative) and (b) back-projected and projected into the reference lands within
``max_reproj_px`` of the pixel it started from (the forward-backward check of COLMAP's fusion). A pixel
is fused when at least ``min_consistent`` neighbours agree: its point is the mean of its own and the
agreeing 3D points, its colour the mean of theirs, and the agreeing neighbour pixels are marked used
so that the same surface point is not fused again from another view. A depth map that is wrong
finds no agreement and contributes nothing.
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

    def __post_init__(self) -> None:
        if self.min_consistent < 1 or not self.max_depth_error > 0 or not self.max_reproj_px > 0:
            raise ValueError("fusion needs min_consistent >= 1, max_depth_error > 0 and max_reproj_px > 0")


@dataclass
class FusedCloud:
    """Fused points (n, 3) in the world frame, colours (n, 3) uint8 RGB, the index of the reference
    view each came from (n,), and how many other views agreed with it (n,)."""

    points: np.ndarray
    colors: np.ndarray
    source: np.ndarray
    support: np.ndarray


def fuse(
    views: list[View], depths: list[np.ndarray], neighbors: list[list[int]], opts: FusionOptions
) -> FusedCloud:
    """Fuse ``depths[i]`` (NaN: none; the size of ``views[i]``) checking each view's pixels against the
    depth maps of ``neighbors[i]``."""
    if len(views) != len(depths) or len(views) != len(neighbors):
        raise ValueError("fuse needs one depth map and one neighbour list per view")
    for v, d in zip(views, depths, strict=True):
        if d.shape != v.shape:
            raise ValueError(f"{v.name}: depth map {d.shape} and image {v.shape} differ in size")
    used = [np.zeros(d.shape, dtype=bool) for d in depths]
    pts_out, col_out, src_out, sup_out = [], [], [], []
    for i, (ref, depth) in enumerate(zip(views, depths, strict=True)):
        d = np.where(used[i], np.nan, depth)
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
            nb, dj = views[j], depths[j]
            uv, z = project(nb, X)
            h, w = dj.shape
            u = np.rint(uv[:, 0]).astype(np.int64, copy=False) if len(uv) else np.zeros(0, np.int64)
            v = np.rint(uv[:, 1]).astype(np.int64, copy=False) if len(uv) else np.zeros(0, np.int64)
            inside = (z > 0) & np.isfinite(uv).all(axis=1) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
            idx = np.nonzero(inside)[0]
            dn = dj[v[idx], u[idx]].astype(np.float64)
            ok = np.isfinite(dn) & (np.abs(z[idx] - dn) < opts.max_depth_error * dn)
            idx, dn = idx[ok], dn[ok]
            # forward-backward: the neighbour's own point, seen from the reference
            K = nb.K
            p_cam = np.column_stack(
                [(u[idx] - K[0, 2]) / K[0, 0] * dn, (v[idx] - K[1, 2]) / K[1, 1] * dn, dn]
            )
            Y = p_cam @ nb.T_world_cam[:3, :3].T + nb.T_world_cam[:3, 3]
            uv_back, _ = project(ref, Y)
            err = np.linalg.norm(uv_back - rc[idx][:, ::-1], axis=1)
            good = err < opts.max_reproj_px
            idx, Y = idx[good], Y[good]
            acc[idx] += Y
            col[idx] += nb.rgb[v[idx], u[idx]]
            count[idx] += 1
            hits.append((j, idx, v[idx], u[idx]))
        keep = count >= opts.min_consistent
        if not keep.any():
            continue
        for j, idx, vj, uj in hits:
            sel = keep[idx]
            used[j][vj[sel], uj[sel]] = True
        n = (count[keep] + 1)[:, None]
        pts_out.append(acc[keep] / n)
        col_out.append(np.clip(np.rint(col[keep] / n), 0, 255).astype(np.uint8))
        src_out.append(np.full(int(keep.sum()), i, dtype=np.int32))
        sup_out.append(count[keep].astype(np.int32))
    if not pts_out:
        return FusedCloud(
            np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros(0, np.int32), np.zeros(0, np.int32)
        )
    return FusedCloud(
        np.concatenate(pts_out), np.concatenate(col_out), np.concatenate(src_out), np.concatenate(sup_out)
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
