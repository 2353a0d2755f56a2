"""``default``: an open, textured meadow with a handful of free-standing trees around the spawn."""

from __future__ import annotations

import math

import numpy as np

from droneulator.scenes import assemble_scene, register
from droneulator.scenes.base import Scene, SemanticClass
from droneulator.scenes.geometry import PartBuilder, ground_with_skirt, soil_decals
from droneulator.scenes.trees import build_tree, shade_tree_params

HALF_SIZE = 30.0


@register("default", "Open 60 m x 60 m meadow with 4-6 scattered broadleaf trees; spawn in the clear centre")
def build_default(seed: int, vegetation: float = 1.0) -> Scene:
    rng = np.random.default_rng([seed, 0xDEF])
    ground = PartBuilder("ground", "ground")
    ground.add(ground_with_skirt((-HALF_SIZE, HALF_SIZE), (-HALF_SIZE, HALF_SIZE)), SemanticClass.GROUND)
    soil = PartBuilder("soil", "soil", alpha_test=True)
    n_patches = 45
    soil.add(
        soil_decals(
            rng,
            rng.uniform(-HALF_SIZE - 10, HALF_SIZE + 10, (n_patches, 2)),
            rng.uniform(1.5, 5.0, n_patches),
        ),
        SemanticClass.GROUND,
    )
    bark = PartBuilder("bark", "bark")
    foliage = PartBuilder("foliage", "leaves", alpha_test=True)
    # 4-6 trees on a ring around the spawn, at least 9 m apart (rejection sampling, bounded)
    n_trees = int(rng.integers(4, 7))
    spots: list[np.ndarray] = []
    for _ in range(500):
        r, a = rng.uniform(9.0, 17.0), rng.uniform(0, 2 * math.pi)
        p = np.array([r * math.cos(a), r * math.sin(a), 0.0])
        if all(np.linalg.norm(p - q) > 9.0 for q in spots):
            spots.append(p)
            if len(spots) == n_trees:
                break
    prims: list = []
    infos = []
    for i, base in enumerate(spots):
        tree_rng = np.random.default_rng([seed, 0xDEF, i])
        params = shade_tree_params(tree_rng, detail=1.0, scale=0.8)
        info = build_tree(base, params, tree_rng, bark, foliage, vegetation=vegetation)
        prims += info.primitives
        infos.append(info)
    nearest = min(spots, key=lambda q: float(np.linalg.norm(q[:2])))
    spawn = np.zeros(3)
    yaw = math.atan2(nearest[1], nearest[0])
    return assemble_scene(
        "default",
        seed,
        [ground.build(), soil.build(), bark.build(), foliage.build()],
        prims,
        spawn,
        yaw,
        np.array([-HALF_SIZE, -HALF_SIZE, 0.0]),
        np.array([HALF_SIZE, HALF_SIZE, 15.0]),
        landmarks={
            "trunks": np.array([t.base for t in infos]),
            "tree_heights": np.array([t.height for t in infos]),
            "crown_radii": np.array([t.crown_radius for t in infos]),
        },
    )
