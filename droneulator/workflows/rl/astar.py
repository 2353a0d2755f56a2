"""Occupancy grid of a scene at flight altitude, A* shortest paths and goal distance fields on it.

The grid is built once per scene from its collision SDF: a node is occupied where the distance to
the scene geometry, within a thin altitude band, is below the inflation radius (the vehicle's
collision radius plus a safety margin), so a path through free nodes keeps the vehicle clear.
Moves are 8-connected (straight 1 cell, diagonal sqrt 2 cells) and a diagonal move may not cut the
corner of an occupied node.

The reward needs the shortest-path distance to the goal at every step, so each episode runs one
Dijkstra search from the goal over the whole grid (:class:`DistanceField`; bucketed, 2 ms for the
vineyard's 160k nodes, which batched learning resets hundreds of times a second); a step is then a
bilinear lookup. Occupied nodes are filled with the value of their nearest free node plus the
straight distance to it, so the lookup stays finite and continuous when the vehicle grazes an
inflated obstacle.
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass, field

import numba
import numpy as np
from scipy import ndimage

from droneulator.scenes.base import Scene

SQRT2 = math.sqrt(2.0)
#: neighbour offsets: four straight moves, then four diagonal ones
_MOVES = np.array([[1, 0], [-1, 0], [0, 1], [0, -1], [1, 1], [1, -1], [-1, 1], [-1, -1]], dtype=np.int64)


@numba.njit(cache=True)
def _can_move(free: np.ndarray, i: int, j: int, di: int, dj: int) -> bool:
    nx, ny = free.shape
    a, b = i + di, j + dj
    if a < 0 or b < 0 or a >= nx or b >= ny or not free[a, b]:
        return False
    return di == 0 or dj == 0 or (free[i + di, j] and free[i, j + dj])


@numba.njit(cache=True)
def _move_masks(free: np.ndarray) -> np.ndarray:
    """Per node, a bit per allowed move (bit m: :data:`_MOVES` row m; zero for occupied nodes): the graph
    every distance field searches, built once per grid."""
    nx, ny = free.shape
    masks = np.zeros(nx * ny, dtype=np.uint8)
    for i in range(nx):
        for j in range(ny):
            if free[i, j]:
                bits = 0
                for m in range(8):
                    if _can_move(free, i, j, _MOVES[m, 0], _MOVES[m, 1]):
                        bits |= 1 << m
                masks[i * ny + j] = bits
    return masks


@numba.njit(cache=True, nogil=True)
def _dijkstra(
    masks: np.ndarray, ny: int, sources: np.ndarray, source_cost: np.ndarray
) -> tuple[np.ndarray, np.ndarray, float]:
    """Cost (in cells) from every node to the nearest source, each node's next node toward it, and the
    largest finite cost.

    ``masks``: :func:`_move_masks` of a grid ``ny`` nodes high; ``sources`` are flat node indices
    starting at ``source_cost`` (below 2 cells); ``next`` (int32) is -1 at sources and at unreachable
    nodes.

    Dijkstra with buckets one cell wide (Dial's) instead of a heap, nine times faster: every move costs
    at least one cell, so no node of a bucket can improve another of the same bucket, and the buckets
    are swept in order; a move costs at most sqrt 2 < 2 cells, so three buckets are live at a time (a
    node of level L queues into levels L + 1 and L + 2 only). Each node is settled once and so queued at
    most 8 times in all. The distances equal a heap's exactly.
    """
    n_nodes = masks.shape[0]
    offsets = np.array([ny, -ny, 1, -1, ny + 1, ny - 1, -ny + 1, -ny - 1], dtype=np.int64)
    costs = np.array([1.0, 1.0, 1.0, 1.0, SQRT2, SQRT2, SQRT2, SQRT2])
    dist = np.full(n_nodes, np.inf)
    nxt = np.full(n_nodes, -1, dtype=np.int32)
    cap = 8 * n_nodes + sources.shape[0]
    nodes = np.empty((3, cap), dtype=np.int32)
    keys = np.empty((3, cap))
    size = np.zeros(3, dtype=np.int64)
    for k in range(sources.shape[0]):
        dist[sources[k]] = min(dist[sources[k]], source_cost[k])
    for k in range(sources.shape[0]):
        c = sources[k]
        b = int(dist[c]) % 3
        nodes[b, size[b]], keys[b, size[b]] = c, dist[c]
        size[b] += 1
    level, empty, far = 0, 0, 0.0
    while empty < 3:
        b = level % 3
        level += 1
        if size[b] == 0:
            empty += 1
            continue
        empty = 0
        k = 0
        while k < size[b]:
            c, d = nodes[b, k], keys[b, k]
            k += 1
            if d > dist[c]:
                continue
            far = max(far, d)
            bits = masks[c]
            for m in range(8):
                if (bits >> m) & 1:
                    n = c + offsets[m]
                    nd = d + costs[m]
                    if nd < dist[n]:
                        dist[n] = nd
                        nxt[n] = c
                        # level - 1 is this bucket's: nd's level is one or two above it
                        t = b + int(nd) - level + 1
                        t = t - 3 if t >= 3 else t
                        nodes[t, size[t]], keys[t, size[t]] = n, nd
                        size[t] += 1
        size[b] = 0
    return dist, nxt, far


@numba.njit(cache=True)
def _astar(free: np.ndarray, si: int, sj: int, gi: int, gj: int) -> tuple[float, np.ndarray]:
    """A* from node (si, sj) to (gi, gj) with the octile heuristic (consistent, so the first time
    the goal is popped its cost is optimal). Returns the cost in cells (inf if unreachable) and the
    path as an (N, 2) array of node indices from start to goal."""
    nx, ny = free.shape
    g = np.full(nx * ny, np.inf)
    parent = np.full(nx * ny, -1, dtype=np.int64)
    start, goal = si * ny + sj, gi * ny + gj
    g[start] = 0.0
    dx, dy = abs(si - gi), abs(sj - gj)
    heap = [(float(max(dx, dy) - min(dx, dy)) + SQRT2 * min(dx, dy), np.int64(start))]
    while heap:
        _, c = heapq.heappop(heap)
        if c == goal:
            break
        i, j = c // ny, c % ny
        for m in range(8):
            di, dj = _MOVES[m, 0], _MOVES[m, 1]
            if not _can_move(free, i, j, di, dj):
                continue
            n = (i + di) * ny + (j + dj)
            ng = g[c] + (SQRT2 if m >= 4 else 1.0)
            if ng < g[n]:
                g[n] = ng
                parent[n] = c
                dx, dy = abs(i + di - gi), abs(j + dj - gj)
                heapq.heappush(heap, (ng + (max(dx, dy) - min(dx, dy)) + SQRT2 * min(dx, dy), n))
    if not np.isfinite(g[goal]):
        return np.inf, np.zeros((0, 2), dtype=np.int64)
    count = 1
    c = goal
    while c != start:
        c = parent[c]
        count += 1
    path = np.empty((count, 2), dtype=np.int64)
    c = goal
    for k in range(count - 1, -1, -1):
        path[k, 0], path[k, 1] = c // ny, c % ny
        c = parent[c]
    return g[goal], path


@numba.njit(cache=True)
def bilinear(values: np.ndarray, fx: float, fy: float) -> float:
    """``values`` (a node grid) at continuous node coordinates, bilinearly; used by
    :meth:`DistanceField.distance` and the batched env's compiled step alike."""
    nx, ny = values.shape
    i = min(max(int(math.floor(fx)), 0), nx - 2)
    j = min(max(int(math.floor(fy)), 0), ny - 2)
    tx, ty = fx - i, fy - j
    a = values[i, j] * (1.0 - tx) + values[i + 1, j] * tx
    b = values[i, j + 1] * (1.0 - tx) + values[i + 1, j + 1] * tx
    return a * (1.0 - ty) + b * ty


@dataclass
class OccupancyGrid:
    """Free/occupied nodes of a horizontal slice: node (i, j) sits at ``origin + (i, j) * resolution``."""

    free: np.ndarray  # (nx, ny) bool
    origin: np.ndarray  # (2,) world x, y of node (0, 0)
    resolution: float
    #: for every node, the nearest free node (indices) and the straight distance to it (metres)
    nearest: np.ndarray = field(init=False, repr=False)
    clearance_to_free: np.ndarray = field(init=False, repr=False)
    #: the search graph of the distance fields (:func:`_move_masks`)
    move_masks: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.free = np.ascontiguousarray(self.free, dtype=np.bool_)
        self.origin = np.asarray(self.origin, dtype=float)
        if self.free.ndim != 2 or min(self.free.shape) < 2:
            raise ValueError("an occupancy grid needs at least 2 x 2 nodes")
        if not self.free.any():
            raise ValueError("the occupancy grid has no free node")
        d, idx = ndimage.distance_transform_edt(~self.free, return_indices=True)
        self.nearest = idx
        self.clearance_to_free = d * self.resolution
        self.move_masks = _move_masks(self.free)

    @property
    def shape(self) -> tuple[int, int]:
        return self.free.shape

    def extent(self) -> tuple[float, float, float, float]:
        """(x_min, x_max, y_min, y_max) of the node centres, for plotting."""
        nx, ny = self.shape
        return (
            self.origin[0],
            self.origin[0] + (nx - 1) * self.resolution,
            self.origin[1],
            self.origin[1] + (ny - 1) * self.resolution,
        )

    def fractional(self, p: np.ndarray) -> tuple[float, float]:
        """Continuous node coordinates of world point ``p`` (x, y)."""
        return (float(p[0]) - self.origin[0]) / self.resolution, (
            float(p[1]) - self.origin[1]
        ) / self.resolution

    def node(self, p: np.ndarray) -> tuple[int, int]:
        """The node nearest to world point ``p``, clamped to the grid."""
        fx, fy = self.fractional(p)
        nx, ny = self.shape
        return min(max(round(fx), 0), nx - 1), min(max(round(fy), 0), ny - 1)

    def point(self, i: int, j: int) -> np.ndarray:
        return self.origin + np.array([i, j], dtype=float) * self.resolution

    def inside(self, p: np.ndarray) -> bool:
        x0, x1, y0, y1 = self.extent()
        return x0 <= p[0] <= x1 and y0 <= p[1] <= y1

    def is_free(self, p: np.ndarray) -> bool:
        """True if ``p`` lies on the grid and its four surrounding nodes are all free."""
        if not self.inside(p):
            return False
        fx, fy = self.fractional(p)
        nx, ny = self.shape
        i, j = min(int(fx), nx - 2), min(int(fy), ny - 2)
        return bool(self.free[i : i + 2, j : j + 2].all())

    def shortest_path(self, start: np.ndarray, goal: np.ndarray) -> tuple[float, np.ndarray]:
        """A* between the nodes nearest ``start`` and ``goal``: length (m, inf if none) and the (N, 2)
        world points of the path."""
        si, sj = self.node(start)
        gi, gj = self.node(goal)
        if not (self.free[si, sj] and self.free[gi, gj]):
            return math.inf, np.zeros((0, 2))
        cost, path = _astar(self.free, si, sj, gi, gj)
        return float(cost) * self.resolution, self.origin + path * self.resolution

    def distance_field(self, goal: np.ndarray) -> DistanceField:
        return DistanceField(self, goal)


@numba.njit(cache=True, nogil=True)
def _fill(
    cells: np.ndarray, far: float, free: np.ndarray, ni: np.ndarray, nj: np.ndarray, clearance: np.ndarray,
    res: float,
) -> tuple[np.ndarray, np.ndarray]:
    """A distance field's values and reachability from the search's flat costs in cells (``inf``: not
    reached; ``far``: the largest reached), in one pass: metres on free nodes (unreached ones 10 m beyond
    the farthest reached), and on occupied nodes the value of their nearest free node plus the straight
    distance to it."""
    nx, ny = free.shape
    values = np.empty((nx, ny))
    reachable = np.empty((nx, ny), dtype=np.bool_)
    beyond = far * res + 10.0
    for i in range(nx):
        for j in range(ny):
            d = cells[i * ny + j] * res
            reachable[i, j] = math.isfinite(d)
            if free[i, j]:
                values[i, j] = d if math.isfinite(d) else beyond
            else:
                a, b = ni[i, j], nj[i, j]
                e = cells[a * ny + b] * res
                values[i, j] = (e if math.isfinite(e) else beyond) + clearance[i, j]
    return values, reachable


class DistanceField:
    """Shortest-path distance (m) from every point of the grid to ``goal``, by one Dijkstra search.

    The search starts from the (free) nodes around the goal at their straight distance to it, so the
    field is zero at the goal itself rather than at the nearest node.
    """

    def __init__(self, grid: OccupancyGrid, goal: np.ndarray) -> None:
        self.grid = grid
        self.goal = np.asarray(goal, dtype=float)[:2].copy()
        nx, ny = grid.shape
        fx, fy = grid.fractional(self.goal)
        i0, j0 = min(max(int(math.floor(fx)), 0), nx - 2), min(max(int(math.floor(fy)), 0), ny - 2)
        sources, cost = [], []
        for i in (i0, i0 + 1):
            for j in (j0, j0 + 1):
                if grid.free[i, j]:
                    sources.append(i * ny + j)
                    cost.append(math.hypot(fx - i, fy - j))
        if not sources:
            i, j = grid.node(self.goal)
            raise ValueError(f"goal {self.goal.tolist()} is not in free space (node {i}, {j} is occupied)")
        dist, nxt, far = _dijkstra(grid.move_masks, ny, np.array(sources, dtype=np.int64), np.array(cost))
        self.next = nxt.reshape(nx, ny)
        self.values, self.reachable = _fill(
            dist, far, grid.free, grid.nearest[0], grid.nearest[1], grid.clearance_to_free, grid.resolution
        )

    def distance(self, p: np.ndarray) -> float:
        """Bilinearly interpolated distance to the goal from world point ``p``; off the grid, the
        distance from the nearest grid point plus the straight distance to it."""
        g = self.grid
        nx, ny = g.shape
        fx, fy = g.fractional(p)
        cx, cy = min(max(fx, 0.0), nx - 1.0), min(max(fy, 0.0), ny - 1.0)
        outside = math.hypot(fx - cx, fy - cy) * g.resolution
        return float(bilinear(self.values, cx, cy)) + outside

    def is_reachable(self, p: np.ndarray) -> bool:
        i, j = self.grid.node(p)
        return bool(self.grid.free[i, j] and self.reachable[i, j])

    def lookahead(self, p: np.ndarray, length: float) -> np.ndarray:
        """A carrot on the shortest path from ``p``: the farthest path node at most ``length`` metres
        along it that is still in straight line of sight through free space (the goal when nearer).

        The line-of-sight test keeps the chord from ``p`` to the carrot off the inflated obstacles, so
        steering at it never cuts the corner of a row end; it also straightens the 8-connected path.
        """
        g = self.grid
        i, j = g.node(p)
        if not g.free[i, j]:
            i, j = int(g.nearest[0][i, j]), int(g.nearest[1][i, j])
        if not self.reachable[i, j]:
            return self.goal.copy()
        fx, fy = g.fractional(p)
        if not g.free[g.node(p)]:
            fx, fy = float(i), float(j)
        a, b, reached = carrot(g.free, self.next, i, j, fx, fy, length / g.resolution)
        return self.goal.copy() if reached else g.point(a, b)


@numba.njit(cache=True)
def _line_of_sight(free: np.ndarray, fx: float, fy: float, tx: float, ty: float) -> bool:
    """True if every node nearest to a sample (every half cell) of the segment is free."""
    n = int(math.ceil(2.0 * math.hypot(tx - fx, ty - fy))) + 1
    for k in range(n + 1):
        s = k / n
        if not free[int(round(fx + (tx - fx) * s)), int(round(fy + (ty - fy) * s))]:
            return False
    return True


@numba.njit(cache=True)
def carrot(
    free: np.ndarray, nxt: np.ndarray, i: int, j: int, fx: float, fy: float, length: float
) -> tuple[int, int, bool]:
    """Walk the next-node chain from (i, j) up to ``length`` cells; returns the farthest node in line
    of sight from (fx, fy) and whether the walk reached the goal with the goal in sight."""
    ny = free.shape[1]
    best_i, best_j = i, j
    travelled = 0.0
    while travelled < length:
        n = nxt[i, j]
        if n < 0:
            return best_i, best_j, best_i == i and best_j == j
        a, b = n // ny, n % ny
        travelled += SQRT2 if a != i and b != j else 1.0
        i, j = a, b
        if not _line_of_sight(free, fx, fy, float(i), float(j)):
            break
        best_i, best_j = i, j
    return best_i, best_j, False


def occupancy_from_scene(
    scene: Scene, altitude: float, inflation: float, resolution: float = 0.1, band: float = 0.15
) -> OccupancyGrid:
    """Occupancy of the scene's flyable bounds at ``altitude``: occupied where the collision SDF at
    ``altitude`` or ``altitude +- band`` (altitude is held, not exact) is below ``inflation``, and
    within ``inflation`` of the horizontal bounds."""
    from droneulator.scenes.collision import sdf_lookup_many

    lo, hi = scene.bounds_min[:2], scene.bounds_max[:2]
    n = np.floor((hi - lo) / resolution + 1e-9).astype(int) + 1
    xs = lo[0] + np.arange(n[0]) * resolution
    ys = lo[1] + np.arange(n[1]) * resolution
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    col = scene.collision
    clearance = np.full(X.shape, np.inf)
    for z in (altitude - band, altitude, altitude + band):
        pts = np.stack([X.ravel(), Y.ravel(), np.full(X.size, z)], axis=1)
        d = sdf_lookup_many(col.sdf, col.origin, col.resolution, pts).reshape(X.shape)
        np.minimum(clearance, d, out=clearance)
    border = np.minimum.reduce([X - lo[0], hi[0] - X, Y - lo[1], hi[1] - Y])
    free = (clearance >= inflation) & (border >= inflation)
    return OccupancyGrid(free, lo.copy(), resolution)
