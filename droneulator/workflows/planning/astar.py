"""26-connected 3-D A* on the inflated occupancy grid: the guide path of the B-spline optimiser."""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def _push(heap_f: np.ndarray, heap_n: np.ndarray, size: int, f: float, node: int) -> int:
    i = size
    heap_f[i] = f
    heap_n[i] = node
    while i > 0:
        p = (i - 1) // 2
        if heap_f[p] <= heap_f[i]:
            break
        heap_f[p], heap_f[i] = heap_f[i], heap_f[p]
        heap_n[p], heap_n[i] = heap_n[i], heap_n[p]
        i = p
    return size + 1


@numba.njit(cache=True, nogil=True)
def _pop(heap_f: np.ndarray, heap_n: np.ndarray, size: int) -> tuple[int, int]:
    node = heap_n[0]
    size -= 1
    heap_f[0] = heap_f[size]
    heap_n[0] = heap_n[size]
    i = 0
    while True:
        a, b, m = 2 * i + 1, 2 * i + 2, i
        if a < size and heap_f[a] < heap_f[m]:
            m = a
        if b < size and heap_f[b] < heap_f[m]:
            m = b
        if m == i:
            break
        heap_f[m], heap_f[i] = heap_f[i], heap_f[m]
        heap_n[m], heap_n[i] = heap_n[i], heap_n[m]
        i = m
    return node, size


@numba.njit(cache=True, nogil=True)
def _astar(blocked: np.ndarray, start: np.ndarray, goal: np.ndarray, lo: np.ndarray, hi: np.ndarray,
           max_expansions: int, weight: float) -> np.ndarray:  # fmt: skip
    """A* restricted to the index box [lo, hi) of ``blocked``: work arrays are the box's size only."""
    li, lj, lk = lo[0], lo[1], lo[2]
    nx, ny, nz = hi[0] - li, hi[1] - lj, hi[2] - lk
    n = nx * ny * nz
    g = np.full(n, np.inf)
    parent = np.full(n, -1, dtype=np.int64)
    closed = np.zeros(n, dtype=np.bool_)
    cap = 8 * max_expansions + 27  # a full heap drops pushes (the path may then be missed)
    heap_f = np.empty(cap)
    heap_n = np.empty(cap, dtype=np.int64)
    gi, gj, gk = goal[0] - lo[0], goal[1] - lo[1], goal[2] - lo[2]
    s = ((start[0] - lo[0]) * ny + start[1] - lo[1]) * nz + start[2] - lo[2]
    t = (gi * ny + gj) * nz + gk
    g[s] = 0.0
    size = _push(heap_f, heap_n, 0, 0.0, s)
    expansions = 0
    while size > 0 and expansions < max_expansions:
        node, size = _pop(heap_f, heap_n, size)
        if closed[node]:
            continue
        if node == t:
            break
        closed[node] = True
        expansions += 1
        i, j, k = node // (ny * nz), (node // nz) % ny, node % nz
        for di in range(-1, 2):
            for dj in range(-1, 2):
                for dk in range(-1, 2):
                    if di == 0 and dj == 0 and dk == 0:
                        continue
                    a, b, c = i + di, j + dj, k + dk
                    if not (0 <= a < nx and 0 <= b < ny and 0 <= c < nz) or blocked[a + li, b + lj, c + lk]:
                        continue
                    m = (a * ny + b) * nz + c
                    if closed[m] or size >= cap:
                        continue
                    ng = g[node] + math.sqrt(di * di + dj * dj + dk * dk)
                    if ng < g[m]:
                        g[m] = ng
                        parent[m] = node
                        h = math.sqrt((a - gi) ** 2 + (b - gj) ** 2 + (c - gk) ** 2)
                        size = _push(heap_f, heap_n, size, ng + weight * h, m)
    if parent[t] < 0 and s != t:
        return np.empty((0, 3), dtype=np.int64)
    count = 1
    m = t
    while m != s:
        m = parent[m]
        count += 1
    out = np.empty((count, 3), dtype=np.int64)
    m = t
    for q in range(count - 1, -1, -1):
        out[q, 0], out[q, 1], out[q, 2] = m // (ny * nz) + lo[0], (m // nz) % ny + lo[1], m % nz + lo[2]
        if q > 0:
            m = parent[m]
    return out


def astar(
    blocked: np.ndarray,
    start: np.ndarray,
    goal: np.ndarray,
    max_expansions: int = 200_000,
    margin: int | None = None,
    weight: float = 1.0001,
) -> np.ndarray:
    """Shortest 26-connected voxel path from ``start`` to ``goal`` (grid indices) through free voxels.

    ``blocked`` is a 3-D grid, non-zero (True) where a voxel is blocked; the map's int32 inflation
    count is searched as it is, without building a boolean copy of the whole grid.

    Returns the (N, 3) index path including both ends, or an empty array when there is none within
    ``max_expansions``. ``start`` and ``goal`` must be inside the grid and free. With ``margin``
    (voxels), the search first runs in the box spanned by start and goal grown by ``margin`` on
    every side (its work arrays are the box's size, not the grid's: the cost of a replanning
    cycle), and only falls back to the whole grid when the box holds no path. ``weight`` > 1
    inflates the heuristic (weighted A*): fewer expansions, a path at most ``weight`` times longer.
    """
    blocked = np.asarray(blocked)
    if blocked.ndim != 3:
        raise ValueError(f"A* needs a 3-D grid, got shape {blocked.shape}")
    if blocked.dtype not in (np.bool_, np.int32):
        blocked = blocked.astype(np.bool_)  # the compiled search is specialised for bool and int32 only
    blocked = np.ascontiguousarray(blocked)
    start, goal = np.asarray(start, dtype=np.int64), np.asarray(goal, dtype=np.int64)
    shape = np.array(blocked.shape, dtype=np.int64)
    for name, p in (("start", start), ("goal", goal)):
        if p.shape != (3,) or np.any(p < 0) or np.any(p >= shape):
            raise ValueError(f"A* {name} {p} is outside the grid {blocked.shape}")
        if blocked[tuple(p)]:
            raise ValueError(f"A* {name} {p} is occupied")
    if margin is not None and margin < 0:
        raise ValueError(f"A* margin {margin} must be >= 0")
    if weight < 1.0:
        raise ValueError(f"A* heuristic weight {weight} must be >= 1 (else it is not A*)")
    zero = np.zeros(3, dtype=np.int64)
    if margin is not None:
        lo = np.maximum(np.minimum(start, goal) - margin, 0)
        hi = np.minimum(np.maximum(start, goal) + margin + 1, shape)
        if np.any(lo > 0) or np.any(hi < shape):
            path = _astar(blocked, start, goal, lo, hi, int(max_expansions), float(weight))
            if len(path):
                return path
    return _astar(blocked, start, goal, zero, shape, int(max_expansions), float(weight))
