"""Small procedural mesh builders and a :class:`PartBuilder` that batches them into a MeshPart.

Every builder returns a :class:`Mesh` of float64 arrays (positions, unit normals, uvs) and uint32
triangle indices; the PartBuilder converts to the float32/uint8 layout of :class:`MeshPart`. UVs are
in "metres over tile size" so a tiling texture keeps a sensible physical scale on every surface.
Triangles wind counter-clockwise seen from the side their normal points to.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from droneulator.scenes.base import MeshPart, SemanticClass
from droneulator.scenes.textures import ATLAS_GRID, atlas_rect


class Mesh(NamedTuple):
    positions: np.ndarray  # (N, 3)
    normals: np.ndarray  # (N, 3) unit
    uvs: np.ndarray  # (N, 2)
    indices: np.ndarray  # (M, 3) uint32


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 1e-12, n, 1.0)


def any_perpendicular(v: np.ndarray) -> np.ndarray:
    """A unit vector perpendicular to ``v`` (stable for any direction)."""
    v = _unit(np.asarray(v, dtype=float))
    helper = np.array([1.0, 0.0, 0.0]) if abs(v[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    return _unit(np.cross(v, helper))


def rotation_about(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues rotation matrix about a (normalised here) axis."""
    x, y, z = _unit(np.asarray(axis, dtype=float))
    c, s = math.cos(angle), math.sin(angle)
    C = 1.0 - c
    return np.array(
        [
            [c + x * x * C, x * y * C - z * s, x * z * C + y * s],
            [y * x * C + z * s, c + y * y * C, y * z * C - x * s],
            [z * x * C - y * s, z * y * C + x * s, c + z * z * C],
        ]
    )


def _grid_indices(rows: int, cols: int) -> np.ndarray:
    """Two triangles per cell of a (rows+1) x (cols+1) vertex lattice, row-major."""
    r, c = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
    v00 = (r * (cols + 1) + c).ravel()
    v01 = v00 + 1
    v10 = v00 + cols + 1
    v11 = v10 + 1
    return np.stack([np.stack([v00, v01, v11], 1), np.stack([v00, v11, v10], 1)], 1).reshape(-1, 3)


def concat(meshes: list[Mesh]) -> Mesh:
    """One mesh from several (indices re-based)."""
    offsets = np.cumsum([0] + [len(m.positions) for m in meshes[:-1]])
    return Mesh(
        np.concatenate([m.positions for m in meshes]),
        np.concatenate([m.normals for m in meshes]),
        np.concatenate([m.uvs for m in meshes]),
        np.concatenate([m.indices + np.uint32(o) for m, o in zip(meshes, offsets, strict=True)]).astype(
            np.uint32
        ),
    )


# --------------------------------------------------------------------------- tubes and cones
def tube(
    path: np.ndarray,
    radii: np.ndarray,
    sides: int = 8,
    tile: float = 0.5,
    v_offset: float = 0.0,
) -> Mesh:
    """Tapered tube along a polyline (bent branches, trunks, wires).

    Rings are oriented with parallel-transport frames so the tube does not twist at bends. ``u`` wraps
    an integer number of times around the circumference (seamless bark) and ``v`` is arc length over
    ``tile`` metres. A zero last radius closes the tube to a point.
    """
    path = np.asarray(path, dtype=float)
    radii = np.asarray(radii, dtype=float)
    k = len(path)
    seg = np.diff(path, axis=0)
    seg_t = _unit(seg)
    tang = np.empty_like(path)
    tang[0], tang[-1] = seg_t[0], seg_t[-1]
    if k > 2:
        tang[1:-1] = _unit(seg_t[:-1] + seg_t[1:])
    frames_n = np.empty_like(path)
    n = any_perpendicular(tang[0])
    for i in range(k):
        n = n - np.dot(n, tang[i]) * tang[i]
        nn = np.linalg.norm(n)
        n = n / nn if nn > 1e-9 else any_perpendicular(tang[i])
        frames_n[i] = n
    frames_b = np.cross(tang, frames_n)
    theta = np.linspace(0.0, 2.0 * math.pi, sides + 1)
    cos_t, sin_t = np.cos(theta), np.sin(theta)
    radial = cos_t[None, :, None] * frames_n[:, None, :] + sin_t[None, :, None] * frames_b[:, None, :]
    # tilt normals by the taper so shading reads as a cone, not a stack of cylinders
    lengths = np.linalg.norm(seg, axis=1)
    arc = np.concatenate([[0.0], np.cumsum(lengths)])
    slope = np.gradient(radii, arc) if k > 1 and arc[-1] > 0 else np.zeros(k)
    normals = _unit(radial - slope[:, None, None] * tang[:, None, :])
    positions = path[:, None, :] + radii[:, None, None] * radial
    wraps = max(1, round(2.0 * math.pi * float(radii.max()) / tile))
    u = np.broadcast_to(theta / (2.0 * math.pi) * wraps, (k, sides + 1))
    v = np.broadcast_to((arc / tile + v_offset)[:, None], (k, sides + 1))
    uvs = np.stack([u, v], axis=-1)
    indices = _grid_indices(k - 1, sides)  # rows along the path, columns CCW about it: outward-facing
    return Mesh(
        positions.reshape(-1, 3), normals.reshape(-1, 3), uvs.reshape(-1, 2), indices.astype(np.uint32)
    )


def cylinder(
    p0: np.ndarray, p1: np.ndarray, r0: float, r1: float | None = None, sides: int = 8, tile: float = 0.5
) -> Mesh:
    """Straight (optionally tapered) open cylinder from ``p0`` to ``p1``."""
    r1 = r0 if r1 is None else r1
    return tube(np.stack([np.asarray(p0, float), np.asarray(p1, float)]), np.array([r0, r1]), sides, tile)


def cone(base: np.ndarray, apex: np.ndarray, radius: float, sides: int = 8, tile: float = 0.5) -> Mesh:
    """Open cone with its base circle at ``base`` and tip at ``apex``."""
    return cylinder(base, apex, radius, 0.0, sides, tile)


def bent_path(
    start: np.ndarray,
    direction: np.ndarray,
    length: float,
    segments: int,
    bend_axis: np.ndarray,
    bend_angle: float,
    rng: np.random.Generator | None = None,
    wobble: float = 0.0,
) -> np.ndarray:
    """Polyline of ``segments`` equal steps whose heading turns by ``bend_angle`` in total about
    ``bend_axis`` (a smooth arc), plus optional random heading wobble per step (radians)."""
    pts = [np.asarray(start, dtype=float)]
    d = _unit(np.asarray(direction, dtype=float))
    step = length / segments
    turn = rotation_about(bend_axis, bend_angle / segments) if np.linalg.norm(bend_axis) > 1e-9 else np.eye(3)
    for _ in range(segments):
        if rng is not None and wobble > 0:
            tilt_axis = rotation_about(d, rng.uniform(0, 2 * math.pi)) @ any_perpendicular(d)
            d = rotation_about(tilt_axis, rng.normal(0.0, wobble)) @ d
        pts.append(pts[-1] + d * step)
        d = _unit(turn @ d)
    return np.array(pts)


# --------------------------------------------------------------------------- boxes and spheres
def box(
    center: np.ndarray, half_extents: np.ndarray, rotation: np.ndarray | None = None, tile: float = 0.5
) -> Mesh:
    """Closed box with flat-shaded faces (24 vertices), optionally rotated about its centre."""
    h = np.asarray(half_extents, dtype=float)
    R = np.eye(3) if rotation is None else np.asarray(rotation, dtype=float)
    positions, normals, uvs, indices = [], [], [], []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            n = np.zeros(3)
            n[axis] = sign
            a, b = [(axis + 1) % 3, (axis + 2) % 3]
            if sign < 0:
                a, b = b, a
            ea, eb = np.zeros(3), np.zeros(3)
            ea[a], eb[b] = 1.0, 1.0
            corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=float)
            pts = n * h[axis] + corners[:, :1] * ea * h[a] + corners[:, 1:] * eb * h[b]
            base = len(positions) * 4
            positions.append(pts)
            normals.append(np.tile(n, (4, 1)))
            uvs.append(np.stack([(corners[:, 0] + 1) * h[a], (corners[:, 1] + 1) * h[b]], 1) / tile)
            indices.append(np.array([[base, base + 1, base + 2], [base, base + 2, base + 3]]))
    pos = np.concatenate(positions) @ R.T + np.asarray(center, dtype=float)
    nor = np.concatenate(normals) @ R.T
    return Mesh(pos, nor, np.concatenate(uvs), np.concatenate(indices).astype(np.uint32))


def _icosahedron() -> tuple[np.ndarray, np.ndarray]:
    t = (1.0 + math.sqrt(5.0)) / 2.0
    v = np.array(
        [
            [-1, t, 0],
            [1, t, 0],
            [-1, -t, 0],
            [1, -t, 0],
            [0, -1, t],
            [0, 1, t],
            [0, -1, -t],
            [0, 1, -t],
            [t, 0, -1],
            [t, 0, 1],
            [-t, 0, -1],
            [-t, 0, 1],
        ],
        dtype=float,
    )
    f = np.array(
        [
            [0, 11, 5],
            [0, 5, 1],
            [0, 1, 7],
            [0, 7, 10],
            [0, 10, 11],
            [1, 5, 9],
            [5, 11, 4],
            [11, 10, 2],
            [10, 7, 6],
            [7, 1, 8],
            [3, 9, 4],
            [3, 4, 2],
            [3, 2, 6],
            [3, 6, 8],
            [3, 8, 9],
            [4, 9, 5],
            [2, 4, 11],
            [6, 2, 10],
            [8, 6, 7],
            [9, 8, 1],
        ]
    )
    return _unit(v), f


_ICO_CACHE: dict[int, tuple[np.ndarray, np.ndarray]] = {}


def unit_icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit-sphere vertices and faces of an icosphere (cached; callers must not modify)."""
    if subdivisions not in _ICO_CACHE:
        v, f = _icosahedron()
        for _ in range(subdivisions):
            edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
            uniq, inverse = np.unique(edges, axis=0, return_inverse=True)
            mids = _unit(v[uniq[:, 0]] + v[uniq[:, 1]])
            m = inverse.reshape(3, -1).T + len(v)  # midpoint index of edges (01, 12, 20) per face
            a, b, c = f[:, 0], f[:, 1], f[:, 2]
            m01, m12, m20 = m[:, 0], m[:, 1], m[:, 2]
            f = np.concatenate(
                [np.stack(x, 1) for x in ((a, m01, m20), (b, m12, m01), (c, m20, m12), (m01, m12, m20))]
            )
            v = np.concatenate([v, mids])
        _ICO_CACHE[subdivisions] = (v, f)
    return _ICO_CACHE[subdivisions]


def _sphere_uv(n: np.ndarray, radius: np.ndarray | float, tile: float) -> np.ndarray:
    """Longitude/latitude UVs scaled to metres over ``tile`` (seam and poles vanish in noise textures)."""
    lon = np.arctan2(n[:, 1], n[:, 0])
    lat = np.arcsin(np.clip(n[:, 2], -1, 1))
    r = np.asarray(radius, dtype=float)
    return np.stack([lon * r, lat * r], 1) / tile


def icosphere(center: np.ndarray, radius: float, subdivisions: int = 1, tile: float = 0.2) -> Mesh:
    """Smooth-shaded sphere (fruit)."""
    v, f = unit_icosphere(subdivisions)
    return Mesh(
        v * radius + np.asarray(center, float), v.copy(), _sphere_uv(v, radius, tile), f.astype(np.uint32)
    )


def icospheres(centers: np.ndarray, radii: np.ndarray, subdivisions: int = 1, tile: float = 0.2) -> Mesh:
    """Many spheres in one mesh, vectorised (fruit of a whole tree)."""
    centers = np.asarray(centers, dtype=float).reshape(-1, 3)
    radii = np.broadcast_to(np.asarray(radii, dtype=float), (len(centers),))
    v, f = unit_icosphere(subdivisions)
    pos = centers[:, None, :] + radii[:, None, None] * v[None]
    nor = np.broadcast_to(v, pos.shape)
    uv = (_sphere_uv(v, 1.0, tile)[None] * radii[:, None, None]).reshape(-1, 2)
    idx = (f[None] + (np.arange(len(centers)) * len(v))[:, None, None]).reshape(-1, 3)
    return Mesh(pos.reshape(-1, 3), nor.reshape(-1, 3), uv, idx.astype(np.uint32))


def blob(
    center: np.ndarray,
    radii: np.ndarray,
    rng: np.random.Generator,
    subdivisions: int = 2,
    roughness: float = 0.25,
    tile: float = 0.5,
) -> Mesh:
    """Randomly displaced ellipsoid (rocks): low-frequency bumps from a few random cosine lobes."""
    v, f = unit_icosphere(subdivisions)
    lobes = _unit(rng.normal(size=(6, 3)))
    weights = rng.uniform(-1.0, 1.0, 6) * roughness / 2.0
    bump = 1.0 + (np.clip(v @ lobes.T, 0, None) ** 3) @ weights
    radii = np.asarray(radii, dtype=float)
    pos = v * bump[:, None] * radii
    # flatten the bottom so it sits on the ground
    pos[:, 2] = np.maximum(pos[:, 2], -0.3 * radii[2])
    pos = pos + np.asarray(center, float)
    tri = pos[f]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    vn = np.zeros_like(pos)
    for k in range(3):
        np.add.at(vn, f[:, k], fn)
    return Mesh(pos, _unit(vn), _sphere_uv(v, float(radii.mean()), tile), f.astype(np.uint32))


# --------------------------------------------------------------------------- cards and ground
def quads(
    centers: np.ndarray,
    axis_u: np.ndarray,
    axis_v: np.ndarray,
    normals: np.ndarray | None = None,
    uv_rects: np.ndarray | None = None,
) -> Mesh:
    """Many independent quads (leaf cards), vectorised.

    ``axis_u``/``axis_v`` are the (K, 3) half-edge vectors of each quad; ``uv_rects`` (K, 4) are
    ``(u0, v0, u1, v1)`` texture rectangles (default the full texture). ``normals`` (K, 3) override
    the geometric face normal, e.g. with directions out of a crown for soft foliage shading.
    """
    centers = np.asarray(centers, dtype=float).reshape(-1, 3)
    k = len(centers)
    au, av = np.asarray(axis_u, float).reshape(-1, 3), np.asarray(axis_v, float).reshape(-1, 3)
    su = np.array([-1.0, 1.0, 1.0, -1.0])
    sv = np.array([-1.0, -1.0, 1.0, 1.0])
    pos = centers[:, None, :] + su[None, :, None] * au[:, None, :] + sv[None, :, None] * av[:, None, :]
    nrm = _unit(np.cross(au, av)) if normals is None else _unit(np.asarray(normals, float).reshape(-1, 3))
    nor = np.broadcast_to(nrm[:, None, :], (k, 4, 3))
    if uv_rects is None:
        uv_rects = np.tile([0.0, 0.0, 1.0, 1.0], (k, 1))
    r = np.asarray(uv_rects, dtype=float)
    uu = np.where(su[None, :] < 0, r[:, :1], r[:, 2:3])
    vv = np.where(sv[None, :] < 0, r[:, 1:2], r[:, 3:4])
    uvs = np.stack([uu, vv], -1)
    base = (np.arange(k) * 4)[:, None, None]
    idx = (np.array([[[0, 1, 2], [0, 2, 3]]]) + base).reshape(-1, 3)
    return Mesh(pos.reshape(-1, 3), nor.reshape(-1, 3), uvs.reshape(-1, 2), idx.astype(np.uint32))


def leaf_card(center: np.ndarray, normal: np.ndarray, up: np.ndarray, size: float) -> Mesh:
    """One square leaf card of side ``size`` facing ``normal`` with texture v along ``up``."""
    n = _unit(np.asarray(normal, float))
    v = _unit(np.asarray(up, float) - np.dot(up, n) * n)
    u = np.cross(v, n)
    return quads(np.asarray(center, float)[None], u[None] * size / 2, v[None] * size / 2)


def crossed_cards(
    centers: np.ndarray,
    rotations: np.ndarray,
    sizes: np.ndarray,
    uv_rects: np.ndarray | None = None,
    shade_normals: np.ndarray | None = None,
) -> Mesh:
    """Two perpendicular quads per card (an "X" seen from above): reads as a volume from any side.

    ``rotations`` (K, 3, 3) orient each card (columns: first plane's u, shared v, first plane's normal).
    """
    centers = np.asarray(centers, dtype=float).reshape(-1, 3)
    R = np.asarray(rotations, dtype=float).reshape(-1, 3, 3)
    half = (np.asarray(sizes, dtype=float).reshape(-1) / 2)[:, None]
    ex, ey, ez = R[:, :, 0], R[:, :, 1], R[:, :, 2]
    rects = None if uv_rects is None else np.concatenate([uv_rects, uv_rects])
    shade = None if shade_normals is None else np.concatenate([shade_normals, shade_normals])
    return quads(
        np.concatenate([centers, centers]),
        np.concatenate([ex * half, ez * half]),
        np.concatenate([ey * half, ey * half]),
        shade,
        rects,
    )


def ground_grid(
    x_range: tuple[float, float],
    y_range: tuple[float, float],
    cell: float,
    tile: float,
    warp: float = 0.0,
    warp_wavelength: float = 45.0,
    fade: float = 6.0,
) -> Mesh:
    """Flat z = 0 grid (normals +z) with uvs = xy / tile plus an optional smooth warp (in tiles).

    The warp bends the tiling so repeats of the ground texture are never identical copies, which
    keeps feature matchers from confusing one tile with the next. It fades to zero over ``fade``
    metres at the grid's border so an unwarped neighbouring grid joins without a seam.
    """
    nx = max(1, round((x_range[1] - x_range[0]) / cell))
    ny = max(1, round((y_range[1] - y_range[0]) / cell))
    xs = np.linspace(x_range[0], x_range[1], nx + 1)
    ys = np.linspace(y_range[0], y_range[1], ny + 1)
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    pos = np.stack([X, Y, np.zeros_like(X)], -1).reshape(-1, 3)
    nor = np.tile([0.0, 0.0, 1.0], (len(pos), 1))
    k = 2.0 * math.pi / warp_wavelength
    edge = np.minimum(np.minimum(X - x_range[0], x_range[1] - X), np.minimum(Y - y_range[0], y_range[1] - Y))
    amp = warp * np.clip(edge / fade, 0.0, 1.0) if fade > 0 else np.full_like(X, warp)
    wu = amp * (np.sin(k * Y * 0.83 + 1.3) + 0.6 * np.sin(k * (X + Y) * 0.57 + 0.4))
    wv = amp * (np.sin(k * X * 0.91 + 2.1) + 0.6 * np.sin(k * (X - Y) * 0.61 + 3.0))
    uvs = np.stack([X / tile + wu, Y / tile + wv], -1).reshape(-1, 2)
    idx = _grid_indices(nx, ny)[:, ::-1]  # rows along x, columns along y: flip to face +z
    return Mesh(pos, nor, uvs, idx.astype(np.uint32))


def ground_with_skirt(
    x_range: tuple[float, float],
    y_range: tuple[float, float],
    skirt: float = 150.0,
    cell: float = 2.0,
    tile: float = 8.0,
    warp: float = 0.1,
) -> Mesh:
    """Finely gridded, warped field surrounded by four coarse strips out to ``skirt`` metres, so the
    ground reaches the horizon at a small triangle cost."""
    x0, x1 = x_range
    y0, y1 = y_range
    coarse = 10.0
    strips = [
        ((x0 - skirt, x0), (y0 - skirt, y1 + skirt)),
        ((x1, x1 + skirt), (y0 - skirt, y1 + skirt)),
        ((x0, x1), (y0 - skirt, y0)),
        ((x0, x1), (y1, y1 + skirt)),
    ]
    meshes = [ground_grid(x_range, y_range, cell, tile, warp)]
    meshes += [
        ground_grid(xr, yr, coarse, tile, warp * 3, warp_wavelength=150.0, fade=20.0) for xr, yr in strips
    ]
    return concat(meshes)


def soil_decals(rng: np.random.Generator, xy: np.ndarray, sizes: np.ndarray) -> Mesh:
    """Flat, randomly rotated ``soil``-atlas quads lying 1-3 cm above the ground at ``xy`` (K, 2).

    Big bare-earth patches are placed as decals rather than painted into the tiling ground texture so
    that they never repeat on a lattice. Each decal gets its own height to avoid z-fighting.
    """
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    k = len(xy)
    ang = rng.uniform(0, 2 * math.pi, k)
    aspect = rng.uniform(0.6, 1.0, k)
    half = np.asarray(sizes, dtype=float).reshape(-1) / 2
    au = np.stack([np.cos(ang), np.sin(ang), np.zeros(k)], 1) * half[:, None]
    av = np.stack([-np.sin(ang), np.cos(ang), np.zeros(k)], 1) * (half * aspect)[:, None]
    centers = np.concatenate([xy, rng.uniform(0.01, 0.03, (k, 1))], 1)
    rects = atlas_rect(rng.integers(0, ATLAS_GRID * ATLAS_GRID, k))
    return quads(centers, au, av, None, rects)


# --------------------------------------------------------------------------- part builder
class PartBuilder:
    """Accumulates meshes drawn with one texture, each tagged with a semantic class, into a MeshPart.

    Each added mesh keeps its own vertices, so no vertex is shared between triangles of different
    classes and the per-vertex class id is constant over every triangle.
    """

    def __init__(self, name: str, texture: str, alpha_test: bool = False) -> None:
        self.name = name
        self.texture = texture
        self.alpha_test = alpha_test
        self._meshes: list[Mesh] = []
        self._classes: list[np.ndarray] = []

    def add(self, mesh: Mesh, cls: SemanticClass) -> None:
        if len(mesh.indices) == 0:
            return
        self._meshes.append(mesh)
        self._classes.append(np.full(len(mesh.positions), int(cls), dtype=np.uint8))

    @property
    def triangle_count(self) -> int:
        return sum(len(m.indices) for m in self._meshes)

    def build(self) -> MeshPart:
        if not self._meshes:
            raise ValueError(f"part {self.name!r} is empty")
        m = concat(self._meshes)
        length = np.linalg.norm(m.normals, axis=1, keepdims=True)
        normals = np.where(length > 1e-6, m.normals / np.maximum(length, 1e-6), [0.0, 0.0, 1.0]).astype(
            np.float32
        )
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        return MeshPart(
            name=self.name,
            positions=np.ascontiguousarray(m.positions, dtype=np.float32),
            normals=np.ascontiguousarray(normals),
            uvs=np.ascontiguousarray(m.uvs, dtype=np.float32),
            class_ids=np.concatenate(self._classes),
            indices=np.ascontiguousarray(m.indices, dtype=np.uint32),
            texture=self.texture,
            alpha_test=self.alpha_test,
        )
