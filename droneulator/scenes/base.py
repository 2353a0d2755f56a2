"""What every scene provides: triangle meshes with a semantic class per triangle, textures,
a collision model, a spawn pose and bounds. Everything is in the Z-up world frame (metres)."""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any

import numpy as np

from droneulator.scenes.collision import CollisionModel


class SemanticClass(IntEnum):
    """Class ids written to the segmentation image (uint8 per pixel)."""

    SKY = 0
    GROUND = 1
    TRUNK = 2
    BRANCH = 3
    CANOPY = 4
    POST = 5
    WIRE = 6
    FRUIT = 7
    ROCK = 8
    #: another vehicle of the world (its body, arms and rotors)
    VEHICLE = 9


#: RGB palette for the segmentation PNG, indexed by class id (documented in docs/segmentation.md).
SEGMENTATION_PALETTE: dict[SemanticClass, tuple[int, int, int]] = {
    SemanticClass.SKY: (70, 130, 180),
    SemanticClass.GROUND: (152, 118, 84),
    SemanticClass.TRUNK: (102, 51, 0),
    SemanticClass.BRANCH: (204, 102, 0),
    SemanticClass.CANOPY: (0, 170, 0),
    SemanticClass.POST: (128, 128, 128),
    SemanticClass.WIRE: (255, 255, 0),
    SemanticClass.FRUIT: (220, 20, 60),
    SemanticClass.ROCK: (90, 90, 110),
    SemanticClass.VEHICLE: (255, 0, 255),
}


def palette_lut() -> np.ndarray:
    """(256, 3) uint8 lookup table from class id to palette colour (unknown ids are black)."""
    lut = np.zeros((256, 3), dtype=np.uint8)
    for cls, rgb in SEGMENTATION_PALETTE.items():
        lut[int(cls)] = rgb
    return lut


@dataclass
class MeshPart:
    """A batch of triangles sharing one texture.

    ``class_ids`` is per vertex but constant over every triangle (vertices are not shared between
    triangles of different classes), so it is a per-triangle class after flat interpolation.
    ``alpha_test``: texels with alpha < 0.5 are discarded (leaf cards).
    """

    name: str
    positions: np.ndarray  # (N, 3) float32, world Z-up
    normals: np.ndarray  # (N, 3) float32, unit
    uvs: np.ndarray  # (N, 2) float32, texture coordinates (repeat)
    class_ids: np.ndarray  # (N,) uint8, SemanticClass
    indices: np.ndarray  # (M, 3) uint32
    texture: str  # key into Scene.textures
    alpha_test: bool = False

    @property
    def triangle_count(self) -> int:
        return int(self.indices.shape[0])


@dataclass
class Scene:
    name: str
    seed: int
    parts: list[MeshPart]
    textures: dict[str, np.ndarray]  # name -> (H, W, 4) uint8 RGBA, power-of-two sides
    collision: CollisionModel
    spawn_position: np.ndarray  # (3,) on the ground, z = 0
    spawn_yaw: float
    bounds_min: np.ndarray  # (3,) flyable volume
    bounds_max: np.ndarray
    sun_direction: np.ndarray = field(default_factory=lambda: np.array([0.4, 0.3, 0.85]))
    sky_color: tuple[float, float, float] = (0.53, 0.72, 0.92)
    #: the scene's own light settings (``LightConfig`` field -> value, e.g. ``{"time_of_day_h": 8.0}``):
    #: what a config's null light fields take; empty: the fixed ``sun_direction`` and a clear sky
    light: dict[str, Any] = field(default_factory=dict)
    #: named points of interest, e.g. the centre tree of tree_inspection
    landmarks: dict[str, np.ndarray] = field(default_factory=dict)
    #: the density its leaves were built with (1: as designed; :func:`droneulator.scenes.get_scene`)
    vegetation: float = 1.0

    #: where further vehicles stand, in order, before the free points of :meth:`spawn_points` (e.g. one
    #: per orchard row); on the ground, z = 0
    spawn_candidates: list[np.ndarray] = field(default_factory=list)

    @property
    def triangle_count(self) -> int:
        return sum(p.triangle_count for p in self.parts)

    def spawn_points(self, n: int, spacing: float = 2.0, clearance: float = 1.5) -> list[np.ndarray]:
        """``n`` ground points for ``n`` vehicles: the spawn first, then the scene's candidates, then free
        points on a grid round the spawn, nearest first; each at least ``spacing`` m from the others and
        ``clearance`` m from the scene up to 3 m above the ground, inside the flyable bounds.

        Raises ValueError when the scene has no room for ``n``."""
        from droneulator.scenes.collision import sdf_lookup_many

        col = self.collision
        heights = np.linspace(0.3, 3.0, 4)

        def free(p: np.ndarray) -> bool:
            if np.any(p[:2] < self.bounds_min[:2]) or np.any(p[:2] > self.bounds_max[:2]):
                return False
            column = np.column_stack([np.full(4, p[0]), np.full(4, p[1]), heights])
            return bool(sdf_lookup_many(col.sdf, col.origin, col.resolution, column).min() >= clearance)

        chosen = [np.asarray(self.spawn_position, dtype=float)]
        side = spacing * np.arange(-12, 13)
        grid = np.array([[x, y, 0.0] for x in side for y in side]) + chosen[0] * [1.0, 1.0, 0.0]
        grid = grid[np.argsort(np.linalg.norm(grid - chosen[0], axis=1), kind="stable")]
        taken = np.empty((len(self.spawn_candidates) + len(grid) + 1, 2))  # the chosen points' x, y
        taken[0] = chosen[0][:2]
        for p in [*map(np.asarray, self.spawn_candidates), *grid]:
            if len(chosen) >= n:
                break
            near = np.hypot(*(taken[: len(chosen)] - p[:2]).T).min()
            if near >= spacing - 1e-9 and free(p):
                taken[len(chosen)] = p[:2]
                chosen.append(np.array([p[0], p[1], 0.0]))
        if len(chosen) < n:
            raise ValueError(
                f"scene {self.name!r} has room near its spawn for {len(chosen)} vehicles {spacing:g} m "
                f"apart, not {n}: give the others a spawn"
            )
        return chosen[:n]

    def in_bounds(self, p: np.ndarray) -> bool:
        p = np.asarray(p, dtype=float)
        return bool(np.all(p >= self.bounds_min) and np.all(p <= self.bounds_max))
