"""``orchard``: rows of pruned fruit trees with grass alleys, for row following and fruit counting."""

from __future__ import annotations

import numpy as np

from droneulator.scenes import assemble_scene, register
from droneulator.scenes.base import Scene, SemanticClass
from droneulator.scenes.geometry import PartBuilder, ground_with_skirt, soil_decals
from droneulator.scenes.trees import build_tree, fruit_tree_params

ROWS = 4
TREES_PER_ROW = 8
ROW_SPACING = 5.0
TREE_SPACING = 3.0


@register(
    "orchard",
    f"{ROWS} rows x {TREES_PER_ROW} fruit trees ({ROW_SPACING} m rows, {TREE_SPACING} m "
    "spacing) with grass alleys; spawn at the head of the middle alley",
)
def build_orchard(seed: int, vegetation: float = 1.0) -> Scene:
    rng = np.random.default_rng([seed, 0x0C4])
    ground = PartBuilder("ground", "ground")
    bark = PartBuilder("bark", "bark")
    foliage = PartBuilder("foliage", "leaves", alpha_test=True)
    fruit = PartBuilder("fruit", "fruit")
    # rows run along +x; row r sits at y = (r - (ROWS-1)/2) * ROW_SPACING
    row_y = (np.arange(ROWS) - (ROWS - 1) / 2) * ROW_SPACING
    tree_x = (np.arange(TREES_PER_ROW) - (TREES_PER_ROW - 1) / 2) * TREE_SPACING
    prims: list = []
    infos = []
    for r, y in enumerate(row_y):
        for i, x in enumerate(tree_x):
            tree_rng = np.random.default_rng([seed, 0x0C4, r, i])
            jitter = np.array([rng.normal(0, 0.08), rng.normal(0, 0.05), 0.0])
            info = build_tree(
                np.array([x, y, 0.0]) + jitter,
                fruit_tree_params(tree_rng, detail=0.8),
                tree_rng,
                bark,
                foliage,
                fruit,
                vegetation,
            )
            prims += info.primitives
            infos.append(info)
    half_x, half_y = 30.0, 25.0
    ground.add(ground_with_skirt((-half_x, half_x), (-half_y, half_y)), SemanticClass.GROUND)
    # bare strips under the rows (as in a sprayed orchard) and a few worn spots in the alleys
    soil = PartBuilder("soil", "soil", alpha_test=True)
    for y in row_y:
        xs = np.arange(tree_x[0] - 1.5, tree_x[-1] + 1.6, 1.1)
        xy = np.stack([xs + rng.normal(0, 0.2, len(xs)), y + rng.normal(0, 0.15, len(xs))], 1)
        soil.add(soil_decals(rng, xy, rng.uniform(1.6, 2.3, len(xs))), SemanticClass.GROUND)
    n_spots = 25
    soil.add(
        soil_decals(
            rng,
            rng.uniform([-half_x, -half_y], [half_x, half_y], (n_spots, 2)),
            rng.uniform(1.0, 3.5, n_spots),
        ),
        SemanticClass.GROUND,
    )
    # spawn at the head of a central alley, looking down it with trees on both sides
    spawn = np.array([tree_x[0] - 6.0, 0.0 if ROWS % 2 == 0 else ROW_SPACING / 2, 0.0])
    return assemble_scene(
        "orchard",
        seed,
        [ground.build(), soil.build(), bark.build(), foliage.build(), fruit.build()],
        prims,
        spawn,
        0.0,
        np.array([-half_x, -half_y, 0.0]),
        np.array([half_x, half_y, 15.0]),
        landmarks={
            "trunks": np.array([t.base for t in infos]),
            "tree_heights": np.array([t.height for t in infos]),
            "crown_radii": np.array([t.crown_radius for t in infos]),
            "row_y": row_y,
            "row_x_min": np.array([tree_x[0]]),
            "row_x_max": np.array([tree_x[-1]]),
            "row_half_width": np.array([max(t.crown_radius for t in infos)]),
            "alley_y": (row_y[:-1] + row_y[1:]) / 2,
        },
    )
