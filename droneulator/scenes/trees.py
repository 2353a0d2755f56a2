"""Procedural broadleaf trees: curved tapered trunk, recursive bent branches, leaf-card clusters.

A tree is grown inside a crown envelope (an ellipsoid above a clear trunk): primary branches leave
the trunk with golden-angle azimuths and reach toward the envelope, secondary (and optionally
tertiary) branches fork off them, and clusters of crossed alpha-tested leaf cards sit around every
branch tip and along the outer part of the branches, so the crown has depth, gaps and visible wood
rather than reading as a ball on a stick. Each tree also returns its collision primitives: capsules
for trunk and branches and spheres for the leaf clusters. The canopy is an obstacle where leaves and
wood are drawn and nowhere else: no solid core between the clusters, which cameras (and a depth-only
planner) would see as free space and the vehicle would collide with.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from droneulator.scenes.base import SemanticClass
from droneulator.scenes.collision import Capsule, Primitive, Sphere
from droneulator.scenes.geometry import (
    PartBuilder,
    any_perpendicular,
    bent_path,
    crossed_cards,
    icospheres,
    rotation_about,
    tube,
)
from droneulator.scenes.textures import ATLAS_GRID, atlas_rect

GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))


@dataclass
class TreeParams:
    """Shape and level of detail of one tree (lengths in metres)."""

    height: float = 5.0
    crown_radius: float = 2.0
    #: trunk radius just above the root flare
    trunk_radius: float = 0.16
    #: crown (first primary branch) starts at this fraction of the height
    crown_base: float = 0.35
    branch_count: int = 6
    #: 2 = primary + secondary branches, 3 adds twigs
    branch_levels: int = 2
    #: multiplier on leaf cards per cluster
    leaf_density: float = 1.0
    #: side of one leaf card (each card is two crossed quads)
    card_size: float = 0.7
    fruit_count: int = 0
    fruit_radius: float = 0.04
    #: geometric detail: scales tube sides/segments and fruit tessellation (0.5 distant .. 1.5 hero)
    detail: float = 1.0
    #: crown height / (2 * crown_radius): > 1 is an upright crown, < 1 a spreading one
    crown_aspect: float = 1.0


@dataclass
class TreeInfo:
    """What a scene needs to know about a built tree."""

    base: np.ndarray
    #: measured from the generated geometry (top of the highest leaf card)
    height: float
    #: measured: farthest horizontal reach of the foliage from the trunk base
    crown_radius: float
    crown_center: np.ndarray
    trunk_radius: float
    primitives: list[Primitive] = field(default_factory=list)


def random_rotations(rng: np.random.Generator, k: int) -> np.ndarray:
    """(k, 3, 3) uniformly random rotation matrices (from normalised Gaussian quaternions)."""
    q = rng.normal(size=(k, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    x, y, z, w = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        1,
    )


@dataclass
class _Branch:
    path: np.ndarray
    radii: np.ndarray
    level: int


class _TreeGrower:
    def __init__(self, base: np.ndarray, p: TreeParams, rng: np.random.Generator) -> None:
        self.base = np.asarray(base, dtype=float)
        self.p = p
        self.rng = rng
        z0 = p.height * p.crown_base
        self.crown_center = self.base + np.array([0.0, 0.0, (z0 + p.height) / 2])
        rz = min((p.height - z0) / 2, p.crown_radius * p.crown_aspect)
        self.crown_radii = np.array([p.crown_radius, p.crown_radius, max(rz, 0.3)])
        self.branches: list[_Branch] = []

    def sides(self, n: int) -> int:
        return max(3, round(n * self.p.detail))

    def segs(self, n: int) -> int:
        return max(1, round(n * self.p.detail))

    def reach(self, start: np.ndarray, d: np.ndarray) -> float:
        """Distance from ``start`` along ``d`` to the crown envelope (ray/ellipsoid intersection)."""
        r = self.crown_radii
        o, v = (start - self.crown_center) / r, d / r
        a, b, c = v @ v, 2 * o @ v, o @ o - 1.0
        disc = b * b - 4 * a * c
        if disc <= 0:
            return 0.3 * self.p.crown_radius
        return max((-b + math.sqrt(disc)) / (2 * a), 0.2 * self.p.crown_radius)

    def grow(self) -> None:
        p, rng = self.p, self.rng
        # trunk: a slightly leaning leader up to ~85 % of the height, nearly straight for its first
        # metre (so "the trunk at 1 m" is where the landmark says) and wobblier above
        tilt = float(np.clip(rng.normal(0, 0.03), -0.04, 0.04))
        a = rng.uniform(0, 2 * math.pi)
        up = rotation_about(np.array([math.cos(a), math.sin(a), 0.0]), tilt) @ np.array([0.0, 0.0, 1.0])
        n = self.segs(8)
        length = p.height * 0.85 + 0.15
        n_low = max(1, n // 3)
        low_len = min(1.4, 0.4 * length)
        lower = bent_path(self.base - [0, 0, 0.15], up, low_len, n_low, np.zeros(3), 0.0, rng, wobble=0.01)
        d_top = lower[-1] - lower[-2]
        upper = bent_path(lower[-1], d_top, length - low_len, n - n_low, np.zeros(3), 0.0, rng, wobble=0.05)
        trunk = np.concatenate([lower, upper[1:]])
        s = np.linspace(0, 1, n + 1)
        z = trunk[:, 2] - self.base[2]
        radii = p.trunk_radius * (1.0 - 0.65 * s) * (1.0 + 0.45 * np.exp(-np.maximum(z, 0) / 0.25))
        radii[-1] *= 0.6
        self.branches.append(_Branch(trunk, radii, 0))
        # primary branches between the crown base and the top, lower ones flatter
        heights = np.sort(rng.uniform(p.crown_base, 0.8, p.branch_count)) * p.height
        az0 = rng.uniform(0, 2 * math.pi)
        for i, h in enumerate(heights):
            frac = (h / p.height - p.crown_base) / max(0.8 - p.crown_base, 1e-3)
            start = self._on_path(trunk, h + self.base[2])
            r_parent = np.interp(h + self.base[2], trunk[:, 2], radii)
            az = az0 + i * GOLDEN_ANGLE + rng.normal(0, 0.2)
            elev = math.radians(rng.uniform(25, 40) + 25 * frac)
            d = np.array([math.cos(az) * math.cos(elev), math.sin(az) * math.cos(elev), math.sin(elev)])
            length = 0.85 * self.reach(start, d)
            self._branch(start, d, length, r_parent * rng.uniform(0.5, 0.65), level=1)

    @staticmethod
    def _on_path(path: np.ndarray, z: float) -> np.ndarray:
        return np.array([np.interp(z, path[:, 2], path[:, k]) for k in range(3)])

    def _branch(self, start: np.ndarray, d: np.ndarray, length: float, r0: float, level: int) -> None:
        p, rng = self.p, self.rng
        n = self.segs({1: 5, 2: 3, 3: 2}[level])
        horiz = np.cross(d, [0.0, 0.0, 1.0])
        bend_axis = horiz if np.linalg.norm(horiz) > 1e-6 else any_perpendicular(d)
        # branches curve upward (phototropism) except long low ones, which sag a little
        bend = rng.uniform(-0.25, 0.45) if level == 1 else rng.uniform(-0.2, 0.4)
        path = bent_path(start, d, length, n, -bend_axis, bend, rng, wobble=0.08)
        radii = np.linspace(r0, r0 * 0.25, n + 1)
        self.branches.append(_Branch(path, radii, level))
        if level >= p.branch_levels:
            return
        kids = int(rng.integers(2, 4)) if level == 1 else int(rng.integers(1, 3))
        ts = np.sort(rng.uniform(0.3, 0.85, kids))
        for j, t in enumerate(ts):
            idx = t * n
            k = min(int(idx), n - 1)
            pt = path[k] + (path[k + 1] - path[k]) * (idx - k)
            pd = path[k + 1] - path[k]
            pd /= np.linalg.norm(pd)
            side = any_perpendicular(pd)
            side = rotation_about(pd, rng.uniform(0, 2 * math.pi)) @ side
            ang = math.radians(rng.uniform(30, 55)) * (1 if j % 2 == 0 else -1)
            cd = rotation_about(np.cross(pd, side), ang) @ pd
            cd[2] += 0.25  # gentle upward bias
            cd /= np.linalg.norm(cd)
            child_len = min(length * rng.uniform(0.35, 0.55), 0.95 * self.reach(pt, cd))
            r_here = np.interp(t, np.linspace(0, 1, n + 1), radii)
            self._branch(pt, cd, max(child_len, 0.15), r_here * 0.6, level + 1)

    # ------------------------------------------------------------------ output
    def emit(self, bark: PartBuilder, foliage: PartBuilder, fruit: PartBuilder | None) -> TreeInfo:
        p, rng = self.p, self.rng
        prims: list[Primitive] = []
        sides_by_level = {0: self.sides(12), 1: self.sides(7), 2: self.sides(5), 3: self.sides(4)}
        for br in self.branches:
            cls = SemanticClass.TRUNK if br.level == 0 else SemanticClass.BRANCH
            radii = br.radii.copy()
            if br.level > 0:
                radii[-1] = 0.0
            bark.add(tube(br.path, radii, sides_by_level[br.level], tile=0.5, v_offset=rng.random()), cls)
            # collision: trunk every two segments, branches as 1-2 chords (leaf clusters cover the rest)
            if br.level == 0:
                step = 2
            elif br.level == 1:
                step = max(1, (len(br.path) - 1) // 2)
            else:
                step = len(br.path) - 1
            for a in range(0, len(br.path) - 1, step):
                b = min(a + step, len(br.path) - 1)
                prims.append(Capsule(br.path[a], br.path[b], float(max(br.radii[a], 0.02))))
        # leaf clusters: every branch tip plus points along the outer half of primaries and the leader top
        centers, radii = [], []
        scale = float(np.clip(0.34 * p.crown_radius, 0.35, 0.95))
        for br in self.branches:
            if br.level == 0:
                centers.append(br.path[-1])
                radii.append(scale * 1.2)
                continue
            centers.append(br.path[-1])
            radii.append(scale * rng.uniform(0.85, 1.15))
            if br.level == 1 or (br.level == 2 and p.branch_levels == 2):
                k = len(br.path) - 1
                for t in (0.55, 0.8) if br.level == 1 else (0.5,):
                    centers.append(br.path[int(round(t * k))])
                    radii.append(scale * rng.uniform(0.7, 0.95))
        centers_a, radii_a = np.array(centers), np.array(radii)
        cards_per = np.maximum(2, np.round(p.leaf_density * 11.0 * (radii_a / scale) ** 2)).astype(int)
        owner = np.repeat(np.arange(len(centers_a)), cards_per)
        k = len(owner)
        u = rng.normal(size=(k, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        dist = radii_a[owner] * rng.random(k) ** 0.5
        card_c = centers_a[owner] + u * dist[:, None]
        card_c[:, 2] = np.maximum(card_c[:, 2], self.base[2] + p.height * p.crown_base * 0.8)
        sizes = p.card_size * rng.uniform(0.8, 1.2, k)
        rots = random_rotations(rng, k)
        out_crown = (card_c - self.crown_center) / self.crown_radii
        out_crown /= np.maximum(np.linalg.norm(out_crown, axis=1, keepdims=True), 1e-6)
        shade = out_crown * 0.75 + u * 0.25 + rng.normal(0, 0.15, (k, 3))
        rects = atlas_rect(rng.integers(0, ATLAS_GRID * ATLAS_GRID, k))
        cards = crossed_cards(card_c, rots, sizes, rects, shade)
        foliage.add(cards, SemanticClass.CANOPY)
        margin = 0.25 * p.card_size
        prims += [Sphere(c, float(r + margin), foliage=True) for c, r in zip(centers_a, radii_a, strict=True)]
        if fruit is not None and p.fruit_count > 0:
            owner_f = rng.integers(0, len(centers_a), p.fruit_count)
            d = rng.normal(size=(p.fruit_count, 3))
            d[:, 2] = -np.abs(d[:, 2]) * 0.6  # hang on the lower side of the clusters
            d /= np.linalg.norm(d, axis=1, keepdims=True)
            fc = centers_a[owner_f] + d * (radii_a[owner_f] * rng.uniform(0.6, 1.0, p.fruit_count))[:, None]
            fc[:, 2] = np.maximum(fc[:, 2], self.base[2] + 0.5)
            fr = p.fruit_radius * rng.uniform(0.85, 1.15, p.fruit_count)
            fruit.add(
                icospheres(fc, fr, subdivisions=1 if p.detail >= 1.2 else 0, tile=0.1), SemanticClass.FRUIT
            )
        top = float(cards.positions[:, 2].max())
        horiz = np.linalg.norm(cards.positions[:, :2] - self.base[:2], axis=1)
        return TreeInfo(
            self.base.copy(),
            top - float(self.base[2]),
            float(horiz.max()),
            self.crown_center.copy(),
            p.trunk_radius,
            prims,
        )


def build_tree(
    base: np.ndarray,
    params: TreeParams,
    rng: np.random.Generator,
    bark: PartBuilder,
    foliage: PartBuilder,
    fruit: PartBuilder | None = None,
    vegetation: float = 1.0,
) -> TreeInfo:
    """Grow one tree standing at ``base`` (on the ground) into the given part builders.

    ``bark`` receives trunk (TRUNK) and branches (BRANCH), ``foliage`` the alpha-tested leaf cards
    (CANOPY, uv rectangles into a leaf atlas), ``fruit`` small spheres (FRUIT) if given. ``vegetation``
    scales the leaf cards per cluster (the scene's vegetation density: a sparse or a dense crown).
    """
    if vegetation != 1.0:
        params = dataclasses.replace(params, leaf_density=params.leaf_density * vegetation)
    grower = _TreeGrower(base, params, rng)
    grower.grow()
    return grower.emit(bark, foliage, fruit)


def fruit_tree_params(rng: np.random.Generator, fruit: bool = True, detail: float = 1.0) -> TreeParams:
    """A pruned orchard tree (apple-like): low clear trunk, round open crown, fruit."""
    h = rng.uniform(3.3, 4.0)
    return TreeParams(
        height=h,
        crown_radius=rng.uniform(1.1, 1.3),
        trunk_radius=rng.uniform(0.12, 0.15),
        crown_base=rng.uniform(0.2, 0.26),
        branch_count=int(rng.integers(5, 7)),
        branch_levels=2,
        leaf_density=0.7,
        card_size=0.72,
        fruit_count=int(rng.integers(12, 19)) if fruit else 0,
        detail=detail,
        crown_aspect=1.0,
    )


def shade_tree_params(rng: np.random.Generator, detail: float = 1.0, scale: float = 1.0) -> TreeParams:
    """A free-grown field tree (oak/maple-like): taller clear trunk, broad crown."""
    h = rng.uniform(6.5, 9.0) * scale
    return TreeParams(
        height=h,
        crown_radius=h * rng.uniform(0.3, 0.38),
        trunk_radius=0.035 * h,
        crown_base=rng.uniform(0.28, 0.36),
        branch_count=int(rng.integers(6, 9)),
        branch_levels=3 if detail >= 1.2 else 2,
        leaf_density=1.0,
        card_size=0.9 * scale,
        detail=detail,
        crown_aspect=rng.uniform(0.85, 1.1),
    )
