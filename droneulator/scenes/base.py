"""What every scene provides: triangle meshes with a semantic class per triangle, textures,
a collision model, a spawn pose and bounds. Everything is in the Z-up world frame (metres)."""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum

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
    #: named points of interest, e.g. the centre tree of tree_inspection
    landmarks: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def triangle_count(self) -> int:
        return sum(p.triangle_count for p in self.parts)

    def in_bounds(self, p: np.ndarray) -> bool:
        p = np.asarray(p, dtype=float)
        return bool(np.all(p >= self.bounds_min) and np.all(p <= self.bounds_max))
