"""Which vehicles are near which: a cell list in the horizontal plane, and body contacts between vehicles.

Every vehicle is a sphere of its collision radius (the radius it has against the scene). Pairs are found
through a grid of square cells in x, y, so a world of thousands of vehicles costs O(N log N) a step,
not O(N^2).
"""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True)
def cell_list(xy: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows sorted by their grid cell: ``(order, keys, cells)`` where ``keys[k]`` is the cell key of row
    ``order[k]`` (ascending) and ``cells`` each row's integer cell (ix, iy)."""
    n = xy.shape[0]
    cells = np.empty((n, 2), dtype=np.int64)
    keys = np.empty(n, dtype=np.int64)
    for i in range(n):
        cells[i, 0] = int(math.floor(xy[i, 0] / cell))
        cells[i, 1] = int(math.floor(xy[i, 1] / cell))
        keys[i] = _key(cells[i, 0], cells[i, 1])
    order = np.argsort(keys, kind="mergesort")
    return order, keys[order], cells


@numba.njit(cache=True)
def _key(ix: int, iy: int) -> int:
    # 2^21 cells a side round the origin: any real scene, at any cell size used here
    return (ix + (1 << 20)) * (1 << 21) + (iy + (1 << 20))


@numba.njit(cache=True)
def neighbours(order: np.ndarray, keys: np.ndarray, cells: np.ndarray, i: int, out: np.ndarray) -> int:
    """Write the rows in row ``i``'s cell and the eight around it into ``out``; returns how many."""
    m = 0
    for dx in range(-1, 2):
        for dy in range(-1, 2):
            k = _key(cells[i, 0] + dx, cells[i, 1] + dy)
            lo = np.searchsorted(keys, k)
            while lo < keys.shape[0] and keys[lo] == k:
                if m < out.shape[0]:
                    out[m] = order[lo]
                m += 1
                lo += 1
    return m


@numba.njit(cache=True)
def _contacts(pos: np.ndarray, radius: np.ndarray, active: np.ndarray) -> np.ndarray:
    n = pos.shape[0]
    found = np.empty((0, 2), dtype=np.int64)
    if n < 2:
        return found
    cell = 2.0 * radius.max()
    order, keys, cells = cell_list(pos[:, 0:2], cell)
    near = np.empty(n, dtype=np.int64)
    pairs = []
    for i in range(n):
        if not active[i]:
            continue
        m = min(neighbours(order, keys, cells, i, near), n)
        for k in range(m):
            j = near[k]
            if j <= i or not active[j]:
                continue
            dx, dy, dz = pos[i, 0] - pos[j, 0], pos[i, 1] - pos[j, 1], pos[i, 2] - pos[j, 2]
            if math.sqrt(dx * dx + dy * dy + dz * dz) < radius[i] + radius[j]:
                pairs.append((i, j))
    if len(pairs) == 0:
        return found
    out = np.empty((len(pairs), 2), dtype=np.int64)
    for k in range(len(pairs)):
        out[k, 0], out[k, 1] = pairs[k]
    return out


def contacts(positions: np.ndarray, radius: np.ndarray, active: np.ndarray) -> list[tuple[int, int]]:
    """Pairs ``(i, j)``, ``i < j``, of active rows whose spheres overlap (centres closer than the sum of
    their radii), each pair once, sorted; a row in several pairs appears in each."""
    pairs = _contacts(np.ascontiguousarray(positions, dtype=np.float64), np.asarray(radius, dtype=np.float64),
                      np.asarray(active, dtype=np.bool_))  # fmt: skip
    return sorted((int(a), int(b)) for a, b in pairs)
