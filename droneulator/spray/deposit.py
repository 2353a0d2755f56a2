"""The ground deposit as levels and as a small picture: what the ROS grid and the ``spray_deposit`` op carry.

Both use one log scale (:func:`deposit_levels`): 0 where nothing landed, 1..100 over log10 of
:data:`DEPOSIT_LOG_RANGE` (1e-4 to 10 uL/cm^2). The op sends the levels as an
8-bit greyscale PNG (one pixel a cell, its value the level), base64 in the JSON reply, with the grid's
origin, cell and size, so a browser draws it in the world frame with a colour map of its own. A grid of
a few hundred cells a side compresses to a few kB, mostly zeros.
"""

from __future__ import annotations

import base64
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from droneulator.imaging import encode_png

#: the deposit grid's scale (the ROS grid's and the UI's): cell values 1..100 span log10 of the deposit
#: from 1e-4 to 1e1 uL/cm^2 (0: none)
DEPOSIT_LOG_RANGE = (-4.0, 1.0)


def deposit_levels(deposit_ul_cm2: np.ndarray) -> np.ndarray:
    """uint8 levels of a deposit (uL/cm^2, any shape): 0 where nothing landed, else 1..100 over log10 of
    :data:`DEPOSIT_LOG_RANGE` (below its bottom 1, above its top 100)."""
    lo, hi = DEPOSIT_LOG_RANGE
    d = np.asarray(deposit_ul_cm2, dtype=float)
    out = np.zeros(d.shape, np.uint8)
    wet = d > 0  # the logarithm only where something landed: most of a field's grid is dry
    out[wet] = 1 + np.clip((np.log10(d[wet]) - lo) / (hi - lo), 0.0, 1.0) * 99
    return out


def levels_png(levels: np.ndarray) -> bytes:
    """An 8-bit greyscale PNG of ``levels`` indexed ``[x, y]``: pixel row ``r`` is the cells at y index ``r``
    (row 0 at the grid's origin: the ROS grid's order, south up when shown as is), column ``c`` x index
    ``c``."""
    return encode_png(np.ascontiguousarray(np.asarray(levels, dtype=np.uint8).T))


@dataclass(frozen=True)
class DepositImage:
    """One ground deposit as the ``spray_deposit`` op sends it (see the module docstring)."""

    #: increases each time the deposit changed (across resets too): the ``since`` of the next request
    version: int
    #: episode time (s) and ROS stamp (ns) it was taken at
    t: float
    stamp_ns: int
    #: cells along x (the PNG's columns) and along y (its rows)
    width: int
    height: int
    #: the side of a cell (m) and the world x, y (m) of the grid's corner at cell (0, 0)
    cell_m: float
    origin: tuple[float, float]
    #: the deposits (uL/cm^2) that levels 1 and 100 stand for (log scale between)
    range_ul_cm2: tuple[float, float]
    #: the levels as a base64 greyscale PNG
    png: str

    @classmethod
    def of(
        cls, deposit_ul_cm2: np.ndarray, cell: float, origin: Any, version: int, t: float, stamp_ns: int
    ) -> DepositImage:
        """The picture of a deposit grid (uL/cm^2, ``[x, y]``) with its cell (m) and origin (m)."""
        levels = deposit_levels(deposit_ul_cm2)
        gx, gy = levels.shape
        lo, hi = DEPOSIT_LOG_RANGE
        ox, oy = (float(v) for v in np.asarray(origin, dtype=float)[:2])
        return cls(
            version=version,
            t=float(t),
            stamp_ns=int(stamp_ns),
            width=int(gx),
            height=int(gy),
            cell_m=float(cell),
            origin=(ox, oy),
            range_ul_cm2=(10.0**lo, 10.0**hi),
            png=base64.b64encode(levels_png(levels)).decode("ascii"),
        )

    def to_dict(self) -> dict[str, Any]:
        return {**asdict(self), "origin": list(self.origin), "range_ul_cm2": list(self.range_ul_cm2)}
