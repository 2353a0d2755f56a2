"""Ground truth for scoring a reconstruction: the true surfaces around the captured tree.

The simulator knows its scene, so :func:`truth_mesh` takes the triangles of the tree (trunk, branches,
leaf cards, fruit) and of the ground and rocks within ``ground_radius`` of it from the scene itself,
in the world (``map``) frame of the recorded poses, with what the renderer needs to decide which
parts of an alpha-tested leaf card are solid: each triangle's texture coordinates and the alpha
channel of its texture. The capture writes it to ``DATASET/truth/mesh.npz``.

:func:`sample_surface` turns the mesh into dense surface samples (area-weighted, alpha-tested like the
renderer does at full resolution), and :class:`SurfaceIndex` measures the distance of any point to that
surface as the distance to the nearest *surfel* (a small disc around each sample, in the triangle's
plane): exact for points on the surface or offset along its normal, whatever the sample spacing.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from droneulator.scenes.base import Scene, SemanticClass

#: score classes: what a reconstructed point or a true-surface sample belongs to
TREE, GROUND = 1, 2
CLASS_NAMES = {TREE: "tree", GROUND: "ground"}
TREE_CLASSES = (SemanticClass.TRUNK, SemanticClass.BRANCH, SemanticClass.CANOPY, SemanticClass.FRUIT)
GROUND_CLASSES = (SemanticClass.GROUND, SemanticClass.ROCK)


@dataclass
class TruthMesh:
    """Triangles (n, 3, 3) in the world frame, their uvs (n, 3, 2), score class (n,) and semantic class
    (n,), and for alpha-tested ones the index into ``alphas`` (-1: opaque)."""

    triangles: np.ndarray
    uvs: np.ndarray
    score_class: np.ndarray
    semantic: np.ndarray
    alpha_index: np.ndarray
    alphas: list[np.ndarray]

    def save(self, path: Path) -> None:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp.npz")
        np.savez_compressed(
            tmp,
            triangles=self.triangles.astype(np.float32),
            uvs=self.uvs.astype(np.float32),
            score_class=self.score_class.astype(np.uint8),
            semantic=self.semantic.astype(np.uint8),
            alpha_index=self.alpha_index.astype(np.int16),
            **{f"alpha_{i}": a for i, a in enumerate(self.alphas)},
        )
        tmp.replace(path)

    @classmethod
    def load(cls, path: Path) -> TruthMesh:
        with np.load(path) as z:
            n_alpha = sum(1 for k in z.files if k.startswith("alpha_") and k != "alpha_index")
            return cls(
                z["triangles"].astype(np.float64),
                z["uvs"].astype(np.float64),
                z["score_class"],
                z["semantic"],
                z["alpha_index"].astype(int),
                [z[f"alpha_{i}"] for i in range(n_alpha)],
            )


def truth_mesh(scene: Scene, tree_radius: float, ground_radius: float) -> TruthMesh:
    """The tree at the scene's ``tree`` landmark (triangles within ``tree_radius`` of its axis) and the
    ground and rocks within ``ground_radius`` of it, from ``scene``'s own meshes."""
    if "tree" not in scene.landmarks:
        raise ValueError(f"scene {scene.name!r} has no 'tree' landmark: no tree to score against")
    center = np.asarray(scene.landmarks["tree"], dtype=float)[:2]
    tris, uvs, sc, sem, ai, alphas = [], [], [], [], [], []
    alpha_of: dict[str, int] = {}
    for part in scene.parts:
        t = part.positions[part.indices].astype(np.float64)
        cls = part.class_ids[part.indices[:, 0]]
        r = np.linalg.norm(t.mean(axis=1)[:, :2] - center, axis=1)
        is_tree = np.isin(cls, TREE_CLASSES) & (r < tree_radius)
        is_ground = np.isin(cls, GROUND_CLASSES) & (r < ground_radius)
        keep = is_tree | is_ground
        if not keep.any():
            continue
        if part.alpha_test:
            if part.texture not in alpha_of:
                alpha_of[part.texture] = len(alphas)
                alphas.append(np.ascontiguousarray(scene.textures[part.texture][:, :, 3]))
            index = alpha_of[part.texture]
        else:
            index = -1
        tris.append(t[keep])
        uvs.append(part.uvs[part.indices[keep]].astype(np.float64))
        sc.append(np.where(is_tree[keep], TREE, GROUND).astype(np.uint8))
        sem.append(cls[keep])
        ai.append(np.full(int(keep.sum()), index))
    return TruthMesh(
        np.concatenate(tris), np.concatenate(uvs), np.concatenate(sc), np.concatenate(sem),
        np.concatenate(ai), alphas,
    )  # fmt: skip


@dataclass
class SurfaceSamples:
    """Points on the true surface with their triangle's unit normal, score class and semantic class."""

    points: np.ndarray
    normals: np.ndarray
    score_class: np.ndarray
    semantic: np.ndarray
    #: mean distance between neighbouring samples (m)
    spacing: float


def sample_surface(mesh: TruthMesh, spacing: float = 0.02, seed: int = 0) -> SurfaceSamples:
    """About one sample per ``spacing``² of surface, uniformly over the triangles' area; samples on a
    transparent texel of an alpha-tested triangle are dropped (the renderer discards them too)."""
    if not spacing > 0:
        raise ValueError("spacing must be positive")
    rng = np.random.default_rng(seed)
    t = mesh.triangles
    e1, e2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    cross = np.cross(e1, e2)
    area = 0.5 * np.linalg.norm(cross, axis=1)
    expected = area / spacing**2
    count = np.floor(expected + rng.random(len(t))).astype(np.int64)
    tri = np.repeat(np.arange(len(t)), count)
    a, b = rng.random(len(tri)), rng.random(len(tri))
    flip = a + b > 1
    a[flip], b[flip] = 1 - a[flip], 1 - b[flip]
    pts = t[tri, 0] + a[:, None] * e1[tri] + b[:, None] * e2[tri]
    uv = mesh.uvs[tri]
    uv = uv[:, 0] + a[:, None] * (uv[:, 1] - uv[:, 0]) + b[:, None] * (uv[:, 2] - uv[:, 0])
    keep = np.ones(len(tri), dtype=bool)
    for i, alpha in enumerate(mesh.alphas):
        sel = mesh.alpha_index[tri] == i
        h, w = alpha.shape
        col = np.floor(np.mod(uv[sel, 0], 1.0) * w).astype(int) % w
        row = np.floor(np.mod(uv[sel, 1], 1.0) * h).astype(int) % h
        keep[sel] = alpha[row, col] >= 128
    normals = cross / np.maximum(np.linalg.norm(cross, axis=1, keepdims=True), 1e-12)
    tri = tri[keep]
    return SurfaceSamples(pts[keep], normals[tri], mesh.score_class[tri], mesh.semantic[tri], spacing)


class SurfaceIndex:
    """Distance from points to the sampled true surface, as the distance to the nearest surfel (a disc of
    radius ``1.25 * spacing`` around each sample in its triangle's plane) among the ``k`` nearest samples."""

    def __init__(self, samples: SurfaceSamples, k: int = 8) -> None:
        self.samples = samples
        self.k = k
        self.radius = 1.25 * samples.spacing
        self.tree = cKDTree(samples.points)

    def query(self, points: np.ndarray, chunk: int = 200_000) -> tuple[np.ndarray, np.ndarray]:
        """Distance (n,) to the nearest surfel and the index of that surfel's sample (n,)."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        dist = np.empty(len(points))
        index = np.empty(len(points), dtype=np.int64)
        for s in range(0, len(points), chunk):
            p = points[s : s + chunk]
            _, nn = self.tree.query(p, k=self.k, workers=-1)
            nn = nn.reshape(len(p), -1)
            v = p[:, None, :] - self.samples.points[nn]
            n = self.samples.normals[nn]
            dn = np.einsum("ijk,ijk->ij", v, n)
            tangential = np.linalg.norm(v - dn[..., None] * n, axis=2)
            d = np.hypot(dn, np.maximum(tangential - self.radius, 0.0))
            best = np.argmin(d, axis=1)
            rows = np.arange(len(p))
            dist[s : s + chunk] = d[rows, best]
            index[s : s + chunk] = nn[rows, best]
        return dist, index


def load_truth(dataset: Path) -> TruthMesh:
    path = Path(dataset) / "truth" / "mesh.npz"
    if not path.is_file():
        raise FileNotFoundError(
            f"{path} is missing: the dataset was captured before ground truth was recorded "
            "(capture it again with this version of `droneulator capture`)"
        )
    return TruthMesh.load(path)
