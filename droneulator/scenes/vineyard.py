"""``vineyard``: trellised vine rows (posts, wires, stems, leaf hedge) with drivable grass alleys.

Rows run along +x. Landmarks describe the layout for planners (A* occupancy grids, row following):
``row_y`` row centre lines, ``row_x_min``/``row_x_max`` row ends, ``row_half_width`` half-thickness
of the hedge's collision slab, ``canopy_z`` its (bottom, top), ``alley_y`` alley centre lines,
``post_x`` post positions along each row, ``wire_z`` wire heights and ``trunks`` the vine stems.
"""

from __future__ import annotations

import math

import numpy as np

from droneulator.scenes import assemble_scene, register
from droneulator.scenes.base import Scene, SemanticClass
from droneulator.scenes.collision import Box, Capsule, wire
from droneulator.scenes.geometry import (
    PartBuilder,
    bent_path,
    box,
    crossed_cards,
    ground_with_skirt,
    soil_decals,
    tube,
)
from droneulator.scenes.textures import ATLAS_GRID, atlas_rect
from droneulator.scenes.trees import random_rotations

ROWS = 6
ROW_SPACING = 3.3
ROW_LENGTH = 30.0
POST_SPACING = 5.0
VINE_SPACING = 1.2
WIRE_Z = (0.8, 1.3, 1.8)
WIRE_RADIUS = 0.004
CANOPY_Z = (0.7, 2.0)
HEDGE_HALF_WIDTH = 0.35
CARDS_PER_METRE = 20


@register(
    "vineyard",
    f"{ROWS} trellised vine rows ({ROW_LENGTH:.0f} m long, {ROW_SPACING} m apart) with posts, wires and "
    "leaf hedges; ~2.6 m grass alleys for navigation/RL",
)
def build_vineyard(seed: int, vegetation: float = 1.0) -> Scene:
    rng = np.random.default_rng([seed, 0x71E])
    ground = PartBuilder("ground", "ground")
    bark = PartBuilder("bark", "bark")
    foliage = PartBuilder("foliage", "vine_leaves", alpha_test=True)
    posts = PartBuilder("posts", "wood")
    wires = PartBuilder("wires", "wire")
    row_y = (np.arange(ROWS) - (ROWS - 1) / 2) * ROW_SPACING
    x0, x1 = -ROW_LENGTH / 2, ROW_LENGTH / 2
    post_x = np.arange(x0, x1 + 1e-6, POST_SPACING)
    prims: list = []
    stems: list[np.ndarray] = []
    for y in row_y:
        # posts: end posts thicker and taller
        for i, px in enumerate(post_x):
            end = i in (0, len(post_x) - 1)
            half = np.array([0.06, 0.06, 1.1]) if end else np.array([0.04, 0.04, 1.0])
            lean = rng.normal(0, 0.015, 2)
            R = _tilt(lean)
            c = np.array([px + rng.normal(0, 0.03), y, half[2] - 0.1])
            posts.add(box(c, half, R, tile=0.5), SemanticClass.POST)
            prims.append(Box(c, half, R))
        # wires: a sagging tube per span, one straight capsule per row for collision
        for wz in WIRE_Z:
            for a, b in zip(post_x[:-1], post_x[1:], strict=True):
                t = np.linspace(0.0, 1.0, 5)
                sag = 0.025 * 4 * t * (1 - t)
                path = np.stack([a + (b - a) * t, np.full_like(t, y), wz - sag], 1)
                wires.add(tube(path, np.full(len(t), WIRE_RADIUS), sides=4, tile=0.2), SemanticClass.WIRE)
            prims.append(wire(np.array([x0, y, wz]), np.array([x1, y, wz]), WIRE_RADIUS))
        # vines: crooked stem to the cordon wire, two cordon arms along it, a few upright shoots
        for vx in np.arange(x0 + VINE_SPACING / 2, x1, VINE_SPACING):
            base = np.array([vx + rng.normal(0, 0.05), y + rng.normal(0, 0.03), -0.05])
            stem = bent_path(
                base, np.array([0.0, 0.0, 1.0]), WIRE_Z[0] - 0.02, 4, np.zeros(3), 0.0, rng, 0.07
            )
            bark.add(tube(stem, np.linspace(0.045, 0.03, len(stem)), sides=6, tile=0.3), SemanticClass.TRUNK)
            prims += [Capsule(stem[0], stem[2], 0.045), Capsule(stem[2], stem[4], 0.04)]
            stems.append(np.array([base[0], base[1], 0.0]))
            for sgn in (-1.0, 1.0):
                arm = bent_path(
                    stem[-1],
                    np.array([sgn, 0.0, 0.08]),
                    VINE_SPACING / 2 - 0.02,
                    3,
                    np.zeros(3),
                    0.0,
                    rng,
                    0.06,
                )
                bark.add(
                    tube(arm, np.linspace(0.028, 0.015, len(arm)), sides=4, tile=0.3), SemanticClass.BRANCH
                )
                for k in range(2):
                    sp = arm[1 + k]
                    shoot = bent_path(
                        sp,
                        np.array([rng.normal(0, 0.15), rng.normal(0, 0.1), 1.0]),
                        rng.uniform(0.8, 1.1),
                        3,
                        np.array([0.0, 1.0, 0.0]),
                        rng.normal(0, 0.2),
                        rng,
                        0.1,
                    )
                    r_shoot = np.linspace(0.012, 0.0, len(shoot))
                    bark.add(tube(shoot, r_shoot, sides=3, tile=0.3), SemanticClass.BRANCH)
        # leaf hedge: crossed cards filling a slab around the wires. The designed count always comes from
        # the layout's generator (so the rest of the layout, and its collision model, is the same at any
        # vegetation density); a sparser hedge keeps a share of them, a denser one adds cards of its own
        designed = int(CARDS_PER_METRE * (x1 - x0))
        cards = [_leaf_cards(rng, designed, x0, x1, y)]
        n = int(CARDS_PER_METRE * vegetation * (x1 - x0))
        if n > designed:
            extra = np.random.default_rng([seed, 0x71E, int(np.argmin(np.abs(row_y - y))), 0xDE75E])
            cards.append(_leaf_cards(extra, n - designed, x0, x1, y))
        columns = zip(*cards, strict=True)
        centers, rotations, sizes, rects, shade = (np.concatenate(parts)[:n] for parts in columns)
        foliage.add(crossed_cards(centers, rotations, sizes, rects, shade), SemanticClass.CANOPY)
        cz = (CANOPY_Z[0] + CANOPY_Z[1]) / 2
        prims.append(
            Box(
                np.array([0.0, y, cz]),
                np.array([(x1 - x0) / 2 + 0.15, HEDGE_HALF_WIDTH, (CANOPY_Z[1] - CANOPY_Z[0]) / 2]),
                foliage=True,
            )
        )
    half_x, half_y = 30.0, 30.0
    ground.add(ground_with_skirt((-half_x, half_x), (-half_y, half_y)), SemanticClass.GROUND)
    # bare, weeded strips under the vines and a few wheel-worn spots in the alleys
    soil = PartBuilder("soil", "soil", alpha_test=True)
    for y in row_y:
        xs = np.arange(x0 - 1.0, x1 + 1.1, 0.9)
        xy = np.stack([xs + rng.normal(0, 0.15, len(xs)), y + rng.normal(0, 0.1, len(xs))], 1)
        soil.add(soil_decals(rng, xy, rng.uniform(1.1, 1.6, len(xs))), SemanticClass.GROUND)
    n_spots = 20
    soil.add(
        soil_decals(
            rng,
            rng.uniform([-half_x, -half_y], [half_x, half_y], (n_spots, 2)),
            rng.uniform(1.0, 3.0, n_spots),
        ),
        SemanticClass.GROUND,
    )
    alley_y = (row_y[:-1] + row_y[1:]) / 2
    spawn = np.array([x0 - 5.0, alley_y[len(alley_y) // 2], 0.0])
    return assemble_scene(
        "vineyard",
        seed,
        [ground.build(), soil.build(), bark.build(), foliage.build(), posts.build(), wires.build()],
        prims,
        spawn,
        0.0,
        np.array([x0 - 10.0, row_y[0] - 8.0, 0.0]),
        np.array([x1 + 10.0, row_y[-1] + 8.0, 15.0]),
        landmarks={
            "row_y": row_y,
            "row_x_min": np.array([x0]),
            "row_x_max": np.array([x1]),
            "row_half_width": np.array([HEDGE_HALF_WIDTH]),
            "canopy_z": np.array(CANOPY_Z),
            "alley_y": alley_y,
            "post_x": post_x,
            "wire_z": np.array(WIRE_Z),
            "trunks": np.array(stems),
        },
    )


def _leaf_cards(
    rng: np.random.Generator, n: int, x0: float, x1: float, y: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``n`` leaf cards of the hedge of the row at ``y``: centres, rotations, sizes, atlas rectangles and
    shading normals, drawn in this order from ``rng``."""
    centers = np.stack(
        [
            rng.uniform(x0 - 0.1, x1 + 0.1, n),
            y + rng.normal(0, 0.09, n),
            rng.uniform(CANOPY_Z[0] + 0.35, CANOPY_Z[1] - 0.25, n),
        ],
        1,
    )
    sizes = rng.uniform(0.45, 0.6, n)
    out = np.stack([np.zeros(n), np.sign(centers[:, 1] - y + 1e-9), np.zeros(n)], 1)
    shade = out * 0.6 + np.array([0.0, 0.0, 0.5]) + rng.normal(0, 0.25, (n, 3))
    rects = atlas_rect(rng.integers(0, ATLAS_GRID * ATLAS_GRID, n))
    rotations = _flattened(random_rotations(rng, n))
    return centers, rotations, sizes, rects, shade


def _tilt(lean: np.ndarray) -> np.ndarray:
    """Rotation tilting +z by small angles (radians) about x then y (leaning posts)."""
    cx, sx = math.cos(lean[0]), math.sin(lean[0])
    cy, sy = math.cos(lean[1]), math.sin(lean[1])
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    return ry @ rx


def _flattened(R: np.ndarray) -> np.ndarray:
    """Bias random card orientations toward the row's vertical plane so the hedge stays thin and
    its faces look at the alleys, while keeping enough variety to read as foliage."""
    target = np.array([0.0, 1.0, 0.0])
    n = R[:, :, 2]
    blend = n * 0.4 + np.sign(n @ target + 1e-9)[:, None] * target * 0.6
    blend /= np.linalg.norm(blend, axis=1, keepdims=True)
    v = R[:, :, 1] - (R[:, :, 1] * blend).sum(1, keepdims=True) * blend
    v /= np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-9)
    u = np.cross(v, blend)
    return np.stack([u, v, blend], axis=2)
