"""Analytic collision primitives and the signed distance grids built from them.

Each primitive is wood (hard: trunks, branches, stems, posts, wires, rocks; the default) or ``foliage``
(leaf clusters, a hedge's leaf slab). The scene's grid holds the distance to all of them, a second grid on
the same cells the distance to the wood alone, so a contact can tell a brush with leaves from a strike on
wood (:mod:`droneulator.world.step`).

Each primitive only updates the grid cells inside its bounding box padded by :data:`CLAMP_DISTANCE`;
everything farther than that from every primitive reads exactly ``CLAMP_DISTANCE`` (also returned
outside the grid), which keeps the build linear in the primitives' sizes instead of the world's.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numba
import numpy as np

#: Distances are clamped to this value (metres); it is also the answer outside the grid.
CLAMP_DISTANCE = 2.0


# --------------------------------------------------------------------------- primitives
@dataclass(frozen=True, eq=False)
class Capsule:
    """Segment ``a``-``b`` swept by a sphere of ``radius`` (trunks, branches, stems, wires)."""

    a: np.ndarray
    b: np.ndarray
    radius: float
    foliage: bool = False

    def bbox(self) -> tuple[np.ndarray, np.ndarray]:
        a, b = np.asarray(self.a, float), np.asarray(self.b, float)
        return np.minimum(a, b) - self.radius, np.maximum(a, b) + self.radius

    def distance(self, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
        # python floats keep float32 grids in float32 (numpy scalars would promote to float64)
        ax, ay, az = (float(v) for v in self.a)
        bx, by, bz = float(self.b[0]) - ax, float(self.b[1]) - ay, float(self.b[2]) - az
        dx, dy, dz = x - ax, y - ay, z - az
        dot = dx * bx + dy * by + dz * bz
        pa2 = dx * dx + dy * dy + dz * dz
        l2 = bx * bx + by * by + bz * bz
        if l2 < 1e-12:
            return np.sqrt(pa2) - self.radius
        t = np.clip(dot * (1.0 / l2), 0.0, 1.0)
        d2 = pa2 - t * (2.0 * dot - t * l2)
        return np.sqrt(np.maximum(d2, 0.0)) - self.radius


@dataclass(frozen=True, eq=False)
class Sphere:
    center: np.ndarray
    radius: float
    foliage: bool = False

    def bbox(self) -> tuple[np.ndarray, np.ndarray]:
        c = np.asarray(self.center, float)
        return c - self.radius, c + self.radius

    def distance(self, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
        cx, cy, cz = (float(v) for v in self.center)
        d = (x - cx) ** 2 + (y - cy) ** 2  # stays small (2-D) on grid axes
        d = d + (z - cz) ** 2
        np.sqrt(d, out=d)
        d -= self.radius
        return d


@dataclass(frozen=True, eq=False)
class Ellipsoid:
    """Axis-aligned ellipsoid (leaf clusters, crowns, rocks).

    Uses the ``k0 (k0 - 1) / k1`` approximation: exact on the surface and along the axes, a close
    bound elsewhere; good enough for collision margins.
    """

    center: np.ndarray
    radii: np.ndarray
    foliage: bool = False

    def bbox(self) -> tuple[np.ndarray, np.ndarray]:
        c, r = np.asarray(self.center, float), np.asarray(self.radii, float)
        return c - r, c + r

    def distance(self, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
        cx, cy, cz = (float(v) for v in self.center)
        rx, ry, rz = (float(v) for v in self.radii)
        qx, qy, qz = (x - cx) / rx, (y - cy) / ry, (z - cz) / rz
        k0 = np.sqrt(qx * qx + qy * qy + qz * qz)
        k1 = np.sqrt((qx / rx) ** 2 + (qy / ry) ** 2 + (qz / rz) ** 2)
        return k0 * (k0 - 1.0) / np.maximum(k1, 1e-9)


@dataclass(frozen=True, eq=False)
class Box:
    """Box of ``half_extents`` around ``center``, rotated by ``rotation`` (columns: box axes in world)."""

    center: np.ndarray
    half_extents: np.ndarray
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    foliage: bool = False

    def bbox(self) -> tuple[np.ndarray, np.ndarray]:
        ext = np.abs(np.asarray(self.rotation, float)) @ np.asarray(self.half_extents, float)
        c = np.asarray(self.center, float)
        return c - ext, c + ext

    def distance(self, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
        R = np.asarray(self.rotation, float).tolist()
        cx, cy, cz = (float(v) for v in self.center)
        h = [float(v) for v in self.half_extents]
        dx, dy, dz = x - cx, y - cy, z - cz
        q = [np.abs(dx * R[0][i] + dy * R[1][i] + dz * R[2][i]) - h[i] for i in range(3)]
        outside = np.sqrt(
            np.maximum(q[0], 0.0) ** 2 + np.maximum(q[1], 0.0) ** 2 + np.maximum(q[2], 0.0) ** 2
        )
        inside = np.minimum(np.maximum(np.maximum(q[0], q[1]), q[2]), 0.0)
        return outside + inside


Primitive = Capsule | Sphere | Ellipsoid | Box


def wire(a: np.ndarray, b: np.ndarray, radius: float = 0.003) -> Capsule:
    """A thin wire is a capsule; the vehicle's collision radius gives it its real clearance."""
    return Capsule(np.asarray(a, float), np.asarray(b, float), radius)


def primitive_distance(primitives: list[Primitive], points: np.ndarray) -> np.ndarray:
    """Exact (unclamped) distance from each of the (N, 3) ``points`` to the union of ``primitives``."""
    pts = np.asarray(points, dtype=float).reshape(-1, 3)
    out = np.full(len(pts), np.inf)
    for p in primitives:
        out = np.minimum(out, p.distance(pts[:, 0], pts[:, 1], pts[:, 2]))
    return out


# --------------------------------------------------------------------------- grid build
def build_collision(
    primitives: list[Primitive],
    bounds_min: np.ndarray,
    bounds_max: np.ndarray,
    resolution: float = 0.1,
    max_cells: int | None = 8_000_000,
) -> CollisionModel:
    """Signed distance grid (metres, negative inside, clamped at :data:`CLAMP_DISTANCE`), with the wood's
    alone on the same cells.

    The grid spans the primitives' padded bounding box intersected with the padded flyable bounds
    (primitives entirely outside are dropped), so far-away scenery costs nothing and empty sky above
    the trees is not stored. Each primitive is evaluated only on the cells of its padded bounding box
    and min-reduced into the grid. If the grid would exceed ``max_cells`` (memory: 4 bytes a cell)
    the resolution is coarsened in 0.05 m steps until it fits.
    """
    pad = CLAMP_DISTANCE + resolution
    lo_b = np.asarray(bounds_min, float) - pad
    hi_b = np.asarray(bounds_max, float) + pad
    kept: list[tuple[Primitive, np.ndarray, np.ndarray]] = []
    for p in primitives:
        lo, hi = p.bbox()
        lo, hi = lo - pad, hi + pad
        if np.all(hi > lo_b) and np.all(lo < hi_b):
            kept.append((p, np.maximum(lo, lo_b), np.minimum(hi, hi_b)))
    if not kept:
        origin = np.asarray(bounds_min, float)
        empty = np.full((2, 2, 2), CLAMP_DISTANCE, np.float32)
        return CollisionModel(empty, origin, resolution, empty.copy())
    lo = np.min([k[1] for k in kept], axis=0)
    hi = np.max([k[2] for k in kept], axis=0)
    if max_cells is not None:
        while np.prod(np.ceil((hi - lo) / resolution) + 2) > max_cells:
            resolution = round(resolution + 0.05, 6)
    origin = np.floor(lo / resolution) * resolution
    shape = np.maximum(np.ceil((hi - origin) / resolution).astype(int) + 1, 2)
    sdf = np.full(tuple(shape), CLAMP_DISTANCE, dtype=np.float32)
    wood = np.full(tuple(shape), CLAMP_DISTANCE, dtype=np.float32)
    axes = [(origin[i] + np.arange(shape[i]) * resolution).astype(np.float32) for i in range(3)]
    for prim, plo, phi in kept:
        i0 = np.clip(np.floor((plo - origin) / resolution).astype(int), 0, shape - 1)
        i1 = np.clip(np.ceil((phi - origin) / resolution).astype(int) + 1, 1, shape)
        x = axes[0][i0[0] : i1[0], None, None]
        y = axes[1][None, i0[1] : i1[1], None]
        z = axes[2][None, None, i0[2] : i1[2]]
        cells = (slice(i0[0], i1[0]), slice(i0[1], i1[1]), slice(i0[2], i1[2]))
        d = prim.distance(x, y, z)
        np.minimum(sdf[cells], d, out=sdf[cells])
        if not prim.foliage:
            np.minimum(wood[cells], d, out=wood[cells])
    return CollisionModel(sdf, origin, resolution, wood)


# --------------------------------------------------------------------------- queries
@numba.njit(cache=True)
def sdf_lookup(sdf: np.ndarray, origin: np.ndarray, resolution: float, p: np.ndarray) -> float:
    """Trilinearly interpolated distance at world point ``p``; ``CLAMP_DISTANCE`` outside the grid."""
    fx = (p[0] - origin[0]) / resolution
    fy = (p[1] - origin[1]) / resolution
    fz = (p[2] - origin[2]) / resolution
    nx, ny, nz = sdf.shape
    # written so that NaN coordinates also fall through to the clamp value
    if not (fx >= 0.0 and fy >= 0.0 and fz >= 0.0 and fx <= nx - 1 and fy <= ny - 1 and fz <= nz - 1):
        return CLAMP_DISTANCE
    i = min(int(fx), nx - 2)
    j = min(int(fy), ny - 2)
    k = min(int(fz), nz - 2)
    tx, ty, tz = fx - i, fy - j, fz - k
    c00 = sdf[i, j, k] * (1.0 - tx) + sdf[i + 1, j, k] * tx
    c10 = sdf[i, j + 1, k] * (1.0 - tx) + sdf[i + 1, j + 1, k] * tx
    c01 = sdf[i, j, k + 1] * (1.0 - tx) + sdf[i + 1, j, k + 1] * tx
    c11 = sdf[i, j + 1, k + 1] * (1.0 - tx) + sdf[i + 1, j + 1, k + 1] * tx
    c0 = c00 * (1.0 - ty) + c10 * ty
    c1 = c01 * (1.0 - ty) + c11 * ty
    return c0 * (1.0 - tz) + c1 * tz


@numba.njit(cache=True)
def sdf_lookup_many(sdf: np.ndarray, origin: np.ndarray, resolution: float, points: np.ndarray) -> np.ndarray:
    """:func:`sdf_lookup` for each row of an (N, 3) float64 array (ray marching, batched agents)."""
    out = np.empty(points.shape[0])
    for n in range(points.shape[0]):
        out[n] = sdf_lookup(sdf, origin, resolution, points[n])
    return out


@numba.njit(cache=True)
def sdf_gradient(sdf: np.ndarray, origin: np.ndarray, resolution: float, p: np.ndarray) -> np.ndarray:
    """Central-difference gradient of the distance at ``p`` (points away from obstacles; zero in
    clamped free space): the contact normal of the physical contact model (vehicles/dynamics.py)."""
    g = np.zeros(3)
    h = 0.5 * resolution
    q = p.copy()
    for a in range(3):
        q[a] = p[a] + h
        d1 = sdf_lookup(sdf, origin, resolution, q)
        q[a] = p[a] - h
        d0 = sdf_lookup(sdf, origin, resolution, q)
        q[a] = p[a]
        g[a] = (d1 - d0) / (2.0 * h)
    return g


class CollisionModel:
    """Signed distance to scene geometry on a regular grid, built once per scene.

    ``distance(p)`` is the trilinearly interpolated distance (metres) from world point ``p`` to the
    nearest obstacle surface, negative inside obstacles; ``wood`` the same grid for the wood alone (None:
    every obstacle is wood). The ground plane z = 0 is handled by the vehicle's ground contact, not here.
    """

    def __init__(
        self, sdf: np.ndarray, origin: np.ndarray, resolution: float, wood: np.ndarray | None = None
    ) -> None:
        self.sdf = np.ascontiguousarray(sdf, dtype=np.float32)
        self.origin = np.asarray(origin, dtype=np.float64)
        self.resolution = float(resolution)
        self.wood = self.sdf if wood is None else np.ascontiguousarray(wood, dtype=np.float32)
        if self.wood.shape != self.sdf.shape:
            raise ValueError(f"the wood grid {self.wood.shape} must match the scene grid {self.sdf.shape}")

    def distance(self, p: np.ndarray) -> float:
        return float(sdf_lookup(self.sdf, self.origin, self.resolution, np.asarray(p, dtype=np.float64)))

    def wood_distance(self, p: np.ndarray) -> float:
        """:meth:`distance` to the wood alone (trunks, branches, posts, wires, rocks; no leaves)."""
        return float(sdf_lookup(self.wood, self.origin, self.resolution, np.asarray(p, dtype=np.float64)))
