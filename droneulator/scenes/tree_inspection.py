"""``tree_inspection``: one detailed fruit-bearing tree in a clearing, for photogrammetry orbits.

The tree stands at the origin. A ring of simpler trees and boulders far outside the flyable bounds
gives feature-rich background for image matching; a few small rocks lie in the clearing.
"""

from __future__ import annotations

import math

import numpy as np

from droneulator.scenes import assemble_scene, register
from droneulator.scenes.base import Scene, SemanticClass
from droneulator.scenes.collision import Ellipsoid
from droneulator.scenes.geometry import PartBuilder, blob, ground_with_skirt, soil_decals
from droneulator.scenes.trees import build_tree, shade_tree_params

HALF_BOUNDS = 20.0
#: the spacing of a fleet's row at the spawn, m (``Scene.spawn_points``'s)
FLEET_SPACING_M = 2.0


@register(
    "tree_inspection",
    "One detailed fruit tree at the origin in a clearing ringed by distant trees and rocks; landmarks give "
    "its position, height and crown radius",
)
def build_tree_inspection(seed: int, vegetation: float = 1.0) -> Scene:
    rng = np.random.default_rng([seed, 0x7EE])
    ground = PartBuilder("ground", "ground")
    ground.add(ground_with_skirt((-40.0, 40.0), (-40.0, 40.0)), SemanticClass.GROUND)
    soil = PartBuilder("soil", "soil", alpha_test=True)
    n_patches = 80
    soil.add(
        soil_decals(rng, rng.uniform(-45.0, 45.0, (n_patches, 2)), rng.uniform(1.5, 5.0, n_patches)),
        SemanticClass.GROUND,
    )
    soil.add(soil_decals(rng, rng.normal(0.0, 0.3, (3, 2)), rng.uniform(1.8, 2.6, 3)), SemanticClass.GROUND)
    bark = PartBuilder("bark", "bark")
    foliage = PartBuilder("foliage", "leaves", alpha_test=True)
    fruit = PartBuilder("fruit", "fruit")
    rocks = PartBuilder("rocks", "rock")

    hero_rng = np.random.default_rng([seed, 0x7EE, 0])
    params = shade_tree_params(hero_rng, detail=1.5, scale=0.85)
    params.fruit_count = int(hero_rng.integers(35, 50))
    params.fruit_radius = 0.045
    params.card_size = 0.75
    params.leaf_density = 1.2
    params.branch_count = int(hero_rng.integers(8, 11))
    hero = build_tree(np.zeros(3), params, hero_rng, bark, foliage, fruit, vegetation)
    prims: list = list(hero.primitives)

    # background ring: scenery only (no collision), so it is kept well outside the flyable bounds
    n_far = int(rng.integers(9, 13))
    for i in range(n_far):
        a = 2 * math.pi * (i + rng.uniform(-0.3, 0.3)) / n_far
        r = _outside_bounds(a, rng.uniform(32.0, 45.0), HALF_BOUNDS + 7.0)
        tree_rng = np.random.default_rng([seed, 0x7EE, 1 + i])
        build_tree(
            np.array([r * math.cos(a), r * math.sin(a), 0.0]),
            shade_tree_params(tree_rng, detail=0.6, scale=rng.uniform(0.8, 1.2)),
            tree_rng,
            bark,
            foliage,
            vegetation=vegetation,
        )
    for _ in range(int(rng.integers(6, 10))):
        a = rng.uniform(0, 2 * math.pi)
        r = _outside_bounds(a, rng.uniform(30.0, 40.0), HALF_BOUNDS + 4.0)
        size = rng.uniform(0.6, 1.6)
        radii = size * np.array([rng.uniform(1.0, 1.6), rng.uniform(0.8, 1.2), rng.uniform(0.5, 0.8)])
        rocks.add(
            blob(np.array([r * math.cos(a), r * math.sin(a), 0.0]), radii, rng, subdivisions=2),
            SemanticClass.ROCK,
        )
    # spawn on a random side of the tree, facing it
    yaw_to_tree = rng.uniform(-math.pi, math.pi)
    dist = hero.crown_radius + 6.0
    spawn = np.array([-dist * math.cos(yaw_to_tree), -dist * math.sin(yaw_to_tree), 0.0])
    # small rocks in the clearing, outside the usual orbit radius and away from the spawn
    spawn_dir = math.atan2(spawn[1], spawn[0])
    n_rocks = int(rng.integers(3, 6))
    while n_rocks > 0:
        a, r = rng.uniform(0, 2 * math.pi), rng.uniform(9.0, 11.0)
        if abs((a - spawn_dir + math.pi) % (2 * math.pi) - math.pi) < 0.8:
            continue
        n_rocks -= 1
        radii = rng.uniform(0.25, 0.5) * np.array([rng.uniform(1.0, 1.5), 1.0, rng.uniform(0.6, 0.9)])
        c = np.array([r * math.cos(a), r * math.sin(a), 0.0])
        rocks.add(blob(c, radii, rng, subdivisions=2), SemanticClass.ROCK)
        prims.append(Ellipsoid(c, radii * 1.15))

    scene = assemble_scene(
        "tree_inspection",
        seed,
        [ground.build(), soil.build(), bark.build(), foliage.build(), fruit.build(), rocks.build()],
        prims,
        spawn,
        yaw_to_tree,
        np.array([-HALF_BOUNDS, -HALF_BOUNDS, 0.0]),
        np.array([HALF_BOUNDS, HALF_BOUNDS, 15.0]),
        landmarks={
            "tree": np.zeros(3),
            "tree_height": np.array([hero.height]),
            "crown_radius": np.array([hero.crown_radius]),
            "crown_center": hero.crown_center,
            "trunks": hero.base[None, :],
        },
    )
    # a fleet stands in a row across the line to the tree, either side of the spawn in turn, so that its
    # vehicles start about as far from the tree as the first (and an orbit's halves about as far away)
    across = np.array([-math.sin(yaw_to_tree), math.cos(yaw_to_tree), 0.0])
    scene.spawn_candidates = [spawn + k * FLEET_SPACING_M * across for j in range(1, 5) for k in (j, -j)]
    return scene


def _outside_bounds(angle: float, radius: float, min_extent: float) -> float:
    """``radius`` pushed out along ``angle`` until the point lies ``min_extent`` beyond the square
    bounds' centre on some axis (i.e. at least ``min_extent - HALF_BOUNDS`` outside them)."""
    axis = max(abs(math.cos(angle)), abs(math.sin(angle)))
    return max(radius, min_extent / axis)
