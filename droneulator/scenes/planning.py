"""``planning``: one broad central tree with clutter round it, for the local-planning benchmark.

The central tree stands at the origin with its crown from about 1 m to 5 m, so at the benchmark's
flight altitude (2.5 m) it blocks the straight line from the start on the -x side to goals on the
+x side. Two young fruit trees flank it on the far side (near the outer routes) and a few boulders
lie in the clearing. The vehicle spawns at (-9, 0) facing +x. Landmarks: ``tree`` (base),
``crown_radius``, ``crown_center``, ``tree_height``, ``trunks`` (every tree base), ``start``.
"""

from __future__ import annotations

import numpy as np

from droneulator.scenes import assemble_scene, register
from droneulator.scenes.base import Scene, SemanticClass
from droneulator.scenes.collision import Ellipsoid
from droneulator.scenes.geometry import PartBuilder, blob, ground_with_skirt, soil_decals
from droneulator.scenes.trees import TreeParams, build_tree, fruit_tree_params

HALF_BOUNDS = 15.0
START = np.array([-9.0, 0.0, 0.0])
#: the two young trees beside the far-side routes
CLUTTER_TREES = ((3.5, 5.6), (3.0, -5.8))
BOULDERS = ((-4.0, 3.8), (-3.5, -4.2), (6.5, 1.5), (9.0, -2.5))


@register(
    "planning",
    "One broad tree at the origin between a start on the -x side and goals on the +x side, flanked by two "
    "young trees and boulders: the local-planning benchmark's course",
)
def build_planning(seed: int, vegetation: float = 1.0) -> Scene:
    rng = np.random.default_rng([seed, 0x91A])
    ground = PartBuilder("ground", "ground")
    ground.add(ground_with_skirt((-30.0, 30.0), (-30.0, 30.0)), SemanticClass.GROUND)
    soil = PartBuilder("soil", "soil", alpha_test=True)
    n_patches = 50
    soil.add(
        soil_decals(rng, rng.uniform(-30.0, 30.0, (n_patches, 2)), rng.uniform(1.5, 4.0, n_patches)),
        SemanticClass.GROUND,
    )
    bark = PartBuilder("bark", "bark")
    foliage = PartBuilder("foliage", "leaves", alpha_test=True)
    fruit = PartBuilder("fruit", "fruit")
    rocks = PartBuilder("rocks", "rock")

    hero_rng = np.random.default_rng([seed, 0x91A, 0])
    hero_params = TreeParams(
        height=float(hero_rng.uniform(5.0, 5.6)),
        crown_radius=float(hero_rng.uniform(2.0, 2.3)),
        trunk_radius=0.2,
        crown_base=0.2,
        branch_count=int(hero_rng.integers(7, 9)),
        branch_levels=2,
        leaf_density=1.1,
        card_size=0.75,
        detail=1.0,
        crown_aspect=0.9,
    )
    hero = build_tree(np.zeros(3), hero_params, hero_rng, bark, foliage, fruit, vegetation)
    prims: list = list(hero.primitives)
    trunks = [hero.base]
    for i, (x, y) in enumerate(CLUTTER_TREES):
        tree_rng = np.random.default_rng([seed, 0x91A, 1 + i])
        params = fruit_tree_params(tree_rng)
        tree = build_tree(np.array([x, y, 0.0]), params, tree_rng, bark, foliage, fruit, vegetation)
        prims += tree.primitives
        trunks.append(tree.base)
    for x, y in BOULDERS:
        radii = rng.uniform(0.35, 0.6) * np.array([rng.uniform(1.0, 1.4), 1.0, rng.uniform(0.6, 0.8)])
        c = np.array([x, y, 0.0])
        rocks.add(blob(c, radii, rng, subdivisions=2), SemanticClass.ROCK)
        prims.append(Ellipsoid(c, radii * 1.15))

    return assemble_scene(
        "planning",
        seed,
        [ground.build(), soil.build(), bark.build(), foliage.build(), fruit.build(), rocks.build()],
        prims,
        START,
        0.0,
        np.array([-HALF_BOUNDS, -HALF_BOUNDS, 0.0]),
        np.array([HALF_BOUNDS, HALF_BOUNDS, 12.0]),
        landmarks={
            "tree": np.zeros(3),
            "tree_height": np.array([hero.height]),
            "crown_radius": np.array([hero.crown_radius]),
            "crown_center": hero.crown_center,
            "trunks": np.array(trunks),
            "start": START.copy(),
        },
    )
