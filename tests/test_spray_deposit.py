"""The deposit picture the ``spray_deposit`` op sends (droneulator/spray/deposit.py), decoded here with
PIL and checked against the log scale computed here from its definition, cell by cell."""

from __future__ import annotations

import base64
import io
import json
import math

import numpy as np
from PIL import Image

from droneulator.ros import messages as M
from droneulator.spray.deposit import DepositImage, deposit_levels


def expected_level(ul_cm2: float) -> int:
    """The documented scale: 0 where nothing landed, 1..100 over log10 of 1e-4..10 uL/cm^2, truncated."""
    if not ul_cm2 > 0:
        return 0
    share = min(1.0, max(0.0, (math.log10(ul_cm2) + 4.0) / 5.0))
    return int(1 + share * 99)


def test_the_deposit_picture_decodes_to_the_grid_cell_by_cell() -> None:
    gx, gy = 7, 5  # x along the picture's columns, y along its rows
    deposit = np.zeros((gx, gy))
    wet = {(0, 0): 1e-6, (1, 0): 1e-4, (6, 0): 3e-3, (2, 3): 0.5, (6, 4): 10.0, (3, 4): 250.0}
    for (ix, iy), v in wet.items():
        deposit[ix, iy] = v
    image = DepositImage.of(deposit, 0.25, np.array([-1.0, 2.0]), version=3, t=1.5, stamp_ns=1_500_000_000)
    msg = json.loads(json.dumps(image.to_dict()))  # as it travels
    assert (msg["width"], msg["height"], msg["cell_m"], msg["origin"]) == (7, 5, 0.25, [-1.0, 2.0])
    assert msg["version"] == 3 and msg["t"] == 1.5 and msg["range_ul_cm2"] == [1e-4, 10.0]
    png = Image.open(io.BytesIO(base64.b64decode(msg["png"])))
    assert png.mode == "L" and png.size == (gx, gy)
    pixels = np.asarray(png)
    for iy in range(gy):
        for ix in range(gx):
            assert pixels[iy, ix] == expected_level(deposit[ix, iy]), (ix, iy)
    assert [pixels[0, 0], pixels[0, 1], pixels[4, 6], pixels[4, 3]] == [1, 1, 100, 100]
    assert np.count_nonzero(pixels) == len(wet)


def test_the_picture_and_the_ros_grid_carry_the_same_levels() -> None:
    rng = np.random.default_rng(0)
    deposit = np.where(rng.random((40, 30)) < 0.3, 10.0 ** rng.uniform(-6, 2, (40, 30)), 0.0)
    deposit[0, 0] = np.nan  # not a deposit: nothing drawn, and no error
    image = DepositImage.of(deposit, 0.5, (0.0, 0.0), 1, 0.0, 0)
    pixels = np.asarray(Image.open(io.BytesIO(base64.b64decode(image.png))))
    grid = M.occupancy_grid(0, "map", deposit_levels(deposit).astype(np.int8), 0.5, (0.0, 0.0))
    rows = np.asarray(grid.data).reshape(grid.info.height, grid.info.width)
    np.testing.assert_array_equal(pixels, rows)
    assert pixels[0, 0] == 0
