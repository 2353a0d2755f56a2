"""Which vehicles are near which: body contacts between vehicles, and a cell list in the horizontal plane
(for the wakes).

Every vehicle is a sphere of its collision radius (the radius it has against the scene). Contacts are
found through a dense grid of cells (or sweep and prune when the fleet is spread thin), the wakes' pairs
through a sorted list of square cells in x, y, so a world of
thousands of vehicles costs O(N) to O(N log N) a step, not O(N^2).
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
        keys[i] = cell_key(cells[i, 0], cells[i, 1])
    order = np.argsort(keys, kind="mergesort")
    return order, keys[order], cells


@numba.njit(cache=True)
def cell_key(ix: int, iy: int) -> int:
    """One integer per cell (ix, iy)."""
    # 2^21 cells a side round the origin: any real scene, at any cell size used here
    return (ix + (1 << 20)) * (1 << 21) + (iy + (1 << 20))


@numba.njit(cache=True)
def _overlap(pos: np.ndarray, radius: np.ndarray, i: int, j: int) -> bool:
    dx, dy, dz = pos[i, 0] - pos[j, 0], pos[i, 1] - pos[j, 1], pos[i, 2] - pos[j, 2]
    return math.sqrt(dx * dx + dy * dy + dz * dz) < radius[i] + radius[j]


@numba.njit(cache=True)
def _contacts(pos: np.ndarray, radius: np.ndarray, active: np.ndarray) -> np.ndarray:
    """Active rows binned into square cells of the largest contact distance on a dense grid (a bucket
    per cell, chained), each compared with its own cell and the cells beside it; when the fleet is
    spread too thin for a dense grid (more cells than 16 per vehicle), sweep and prune along x."""
    n = pos.shape[0]
    reach = 2.0 * radius.max()
    pairs = []
    x0, y0 = pos[:, 0].min(), pos[:, 1].min()
    nx = int((pos[:, 0].max() - x0) / reach) + 1
    ny = int((pos[:, 1].max() - y0) / reach) + 1
    if nx * ny <= 16 * n + 64:
        head = np.full(nx * ny, -1, dtype=np.int64)
        chain = np.full(n, -1, dtype=np.int64)
        cx = np.empty(n, dtype=np.int64)
        cy = np.empty(n, dtype=np.int64)
        for i in range(n):
            cx[i] = int((pos[i, 0] - x0) / reach)
            cy[i] = int((pos[i, 1] - y0) / reach)
            if active[i]:
                c = cx[i] * ny + cy[i]
                chain[i] = head[c]
                head[c] = i
        for i in range(n):
            if not active[i]:
                continue
            for gx in range(max(cx[i] - 1, 0), min(cx[i] + 2, nx)):
                for gy in range(max(cy[i] - 1, 0), min(cy[i] + 2, ny)):
                    j = head[gx * ny + gy]
                    while j >= 0:
                        if j > i and _overlap(pos, radius, i, j):
                            pairs.append((i, j))
                        j = chain[j]
    else:
        order = np.argsort(pos[:, 0], kind="mergesort")
        for a in range(n):
            i = order[a]
            if not active[i]:
                continue
            for b in range(a + 1, n):
                j = order[b]
                if pos[j, 0] - pos[i, 0] >= reach:
                    break
                if active[j] and _overlap(pos, radius, i, j):
                    pairs.append((min(i, j), max(i, j)))
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
