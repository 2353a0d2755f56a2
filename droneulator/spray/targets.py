"""What a droplet can land on: the canopy's leaves (by plant and by third of its height) and the woody
parts (trunks and branches, posts, wires), as interception densities on a grid built from the scene's own
meshes.

Each cell holds the projected area per volume (1/m) a droplet's path meets, from the triangles inside:

* leaves (``CANOPY`` and ``FRUIT`` triangles): the one-sided area of each leaf card times the share of
  its texture that is leaf (the alpha test the renderer applies, sampled at points spread over the
  card), times the leaves' mean projection ``G`` (0.5 for a spherical leaf angle distribution): the
  turbid-medium canopy of radiative transfer and of spray models such as AGDISP's canopy;
* woody parts (``TRUNK``, ``BRANCH``, ``POST``, ``WIRE``): their surface area over 4 (a convex body's mean
  projected area is a quarter of its surface).

A parcel crossing a cell over a path ``ds`` is intercepted with probability ``1 - exp(-a ds)`` and
captured with the impaction efficiency on top (:mod:`droneulator.spray.kernel`). Each leaf cell
belongs to the nearest plant (the scene's ``trunks`` landmark; clusters of the canopy's columns when a
scene has none) and to the lower, middle or upper third of that plant's canopy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from droneulator.scenes.base import MeshPart, Scene, SemanticClass

#: the grid's cell (m): fine enough for a vine hedge's 0.7 m width, coarse enough to hold leaves
CELL_M = 0.2
#: sample points per triangle per (CELL_M / 2)^2 of its area (at least this many per triangle)
SAMPLES_PER_TRIANGLE = 8
#: woody classes, in the order the ledger keeps their deposits
WOOD_CLASSES = (SemanticClass.TRUNK, SemanticClass.BRANCH, SemanticClass.POST, SemanticClass.WIRE)
WOOD_NAMES = ("trunks", "branches", "posts", "wires")
LEAF_CLASSES = (SemanticClass.CANOPY, SemanticClass.FRUIT)


@dataclass
class SprayTargets:
    """The interception grids of a scene (``origin`` is cell (0, 0, 0)'s corner)."""

    origin: np.ndarray
    cell: float
    #: (nx, ny, nz) float32: leaves' projected area per volume (1/m)
    leaf: np.ndarray
    #: (nx, ny, nz) float32: woody parts' projected area per volume (1/m)
    wood: np.ndarray
    #: (nx, ny, nz) int32: the plant a leaf cell belongs to (-1: none)
    plant: np.ndarray
    #: (nx, ny, nz) int8: its third, 0 lower, 1 middle, 2 upper (-1: none)
    third: np.ndarray
    #: (nx, ny, nz) int8: the woody class of a wood cell (index into WOOD_NAMES; -1: none)
    wood_class: np.ndarray
    #: (plants, 3) their positions on the ground, (plants,) their canopy's one-sided leaf area (m^2)
    plants: np.ndarray
    leaf_area: np.ndarray

    @property
    def plant_count(self) -> int:
        return int(self.plants.shape[0])

    @classmethod
    def empty(cls) -> SprayTargets:
        """No canopy: droplets meet only the ground (a bare field, the trials' collector lines)."""
        z3 = np.zeros((2, 2, 2), np.float32)
        m1 = np.full((2, 2, 2), -1, np.int32)
        return cls(
            np.zeros(3),
            CELL_M,
            z3,
            z3.copy(),
            m1,
            m1.astype(np.int8),
            m1.astype(np.int8),
            np.zeros((0, 3)),
            np.zeros(0),
        )

    @classmethod
    def of(cls, scene: Scene, leaf_projection: float = 0.5) -> SprayTargets:
        samples = [_samples(scene, part) for part in scene.parts]
        pts = np.concatenate([s[0] for s in samples])
        area = np.concatenate([s[1] for s in samples])
        cls_ = np.concatenate([s[2] for s in samples])
        keep = np.isin(cls_, [*LEAF_CLASSES, *WOOD_CLASSES]) & (area > 0)
        pts, area, cls_ = pts[keep], area[keep], cls_[keep]
        if len(pts) == 0:
            return cls.empty()
        origin = np.floor(pts.min(0) / CELL_M) * CELL_M - CELL_M
        origin[2] = min(origin[2], 0.0)
        shape = tuple(np.ceil((pts.max(0) - origin) / CELL_M).astype(int) + 2)
        idx = np.floor((pts - origin) / CELL_M).astype(int)
        flat = np.ravel_multi_index(idx.T, shape)
        volume = CELL_M**3
        is_leaf = np.isin(cls_, LEAF_CLASSES)
        is_fruit = cls_ == SemanticClass.FRUIT
        # leaves: one-sided area x G; fruit (closed bodies) and wood: surface / 4
        weight = np.where(is_leaf & ~is_fruit, leaf_projection * area, 0.25 * area)
        leaf = np.bincount(flat[is_leaf], weight[is_leaf], np.prod(shape)).reshape(shape) / volume
        wood = np.bincount(flat[~is_leaf], weight[~is_leaf], np.prod(shape)).reshape(shape) / volume
        wood_class = np.full(shape, -1, np.int8)
        best = np.zeros(shape)
        for k, c in enumerate(WOOD_CLASSES):
            sel = cls_ == c
            a = np.bincount(flat[sel], area[sel], np.prod(shape)).reshape(shape)
            better = a > best
            wood_class[better] = k
            best = np.maximum(best, a)
        one_sided = np.bincount(flat[is_leaf & ~is_fruit], area[is_leaf & ~is_fruit], np.prod(shape))
        plants, plant = _plants(scene, leaf > 0, origin)
        third = np.full(shape, -1, np.int8)
        ids = plant.ravel()
        z = np.broadcast_to(np.arange(shape[2]), shape).ravel()
        for p in range(len(plants)):
            cells = np.flatnonzero(ids == p)
            if len(cells) == 0:
                continue
            lo, hi = z[cells].min(), z[cells].max() + 1
            third.ravel()[cells] = np.clip(((z[cells] - lo) * 3) // max(hi - lo, 1), 0, 2)
        leaf_area = np.bincount(ids[ids >= 0], one_sided[ids >= 0], len(plants))
        return cls(
            origin,
            CELL_M,
            leaf.astype(np.float32),
            wood.astype(np.float32),
            plant,
            third,
            wood_class,
            plants,
            leaf_area,
        )


def _samples(scene: Scene, part: MeshPart) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points spread over ``part``'s triangles, each with the (opaque) area it stands for and its class."""
    tri = part.indices.astype(np.int64)
    p = part.positions.astype(np.float64)[tri]  # (M, 3, 3)
    a = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    k = np.maximum(SAMPLES_PER_TRIANGLE, np.ceil(a / (CELL_M / 2) ** 2).astype(int))
    k = np.minimum(k, 4096)
    rep = np.repeat(np.arange(len(tri)), k)
    rng = np.random.default_rng([scene.seed, 0x5B7A])
    r1, r2 = rng.random(len(rep)), rng.random(len(rep))
    s = np.sqrt(r1)
    w0, w1, w2 = 1.0 - s, s * (1.0 - r2), s * r2
    pts = w0[:, None] * p[rep, 0] + w1[:, None] * p[rep, 1] + w2[:, None] * p[rep, 2]
    share = (a / k)[rep]
    if part.alpha_test:
        uv = part.uvs.astype(np.float64)[tri][rep]
        uvs = w0[:, None] * uv[:, 0] + w1[:, None] * uv[:, 1] + w2[:, None] * uv[:, 2]
        tex = scene.textures[part.texture]
        h, w = tex.shape[:2]
        # GL's repeat wrap, v up from the image's bottom row
        col = np.floor((uvs[:, 0] % 1.0) * w).astype(int) % w
        row = (h - 1 - np.floor((uvs[:, 1] % 1.0) * h).astype(int)) % h
        share = share * (tex[row, col, 3] >= 128)
    return pts, share, part.class_ids[tri[rep, 0]].astype(np.int64)


def _plants(scene: Scene, leafy: np.ndarray, origin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Plant positions and each leafy cell's plant: the nearest ``trunks`` landmark, else the clusters
    of the canopy's occupied columns."""
    shape = leafy.shape
    ii, jj, kk = np.nonzero(leafy)
    centres = np.column_stack([origin[0] + (ii + 0.5) * CELL_M, origin[1] + (jj + 0.5) * CELL_M])
    trunks = scene.landmarks.get("trunks")
    if trunks is not None and len(trunks):
        plants = np.asarray(trunks, float).reshape(-1, 3)
        _, nearest = cKDTree(plants[:, :2]).query(centres)
    else:
        labels, count = ndimage.label(leafy.any(axis=2))
        nearest = labels[ii, jj] - 1
        plants = np.zeros((count, 3))
        for p in range(count):
            sel = nearest == p
            plants[p, :2] = centres[sel].mean(0)
    plant = np.full(shape, -1, np.int32)
    plant[ii, jj, kk] = nearest
    return plants, plant
