"""Batched depth by ray casting: the renderer's depth images for many body poses at once, on the CPU.

:class:`DepthCaster` casts one ray per pixel centre against the scene's triangles (its own BVH and
numba kernel, no other dependency) and returns what
:meth:`Renderer.render(T_world_body, rgb=False)[camera].depth <droneulator.render.Renderer.render>`
returns for each pose:

* optical-frame z in metres (not the range along the ray), float32; pixel ``(u, v)`` looks along
  ``K^-1 (u, v, 1)`` (pixel centres on integer coordinates, row 0 at the top);
* NaN where nothing lies between the near and far planes (GL clips there; a surface nearer than
  ``near`` is not seen and the ray goes on behind it);
* the vehicle's own body is not drawn (the renderer draws a body only in *other* vehicles' cameras);
  other vehicles can be added as spheres (their collision spheres, per pose: :meth:`DepthCaster.sphere_depth`
  and the ``spheres`` argument of :meth:`DepthCaster.centre_row` and the like), intersected analytically
  along the same rays and merged per pixel with the scene's depth (the nearer).

The rays run in optical-z units (direction ``R (x, y, 1)``), so the distance along a ray is the depth;
each hit is refined in float64 against the hit triangle's plane, which is what the renderer's
interpolated eye-space z gives to float32 precision. Alpha-tested parts (leaf cards, soil decals)
repeat the renderer's fragment test ``alpha * (1 + 0.25 lod) < 0.5`` as llvmpipe evaluates it: texture
coordinates and their quad derivatives (coarse: a 2x2 pixel quad shares the differences of its top-left
pixel with its right and lower neighbours, extrapolated on the triangle's plane) from the triangle's
plane, the shader's ``lod`` from them, and the texture's alpha trilinearly filtered as llvmpipe's 8-bit
sampler does (its mip chain, ``log2`` approximation, 8-bit weights and rounding). A hit on a discarded
texel is ignored and the ray goes on (the nearest hit the test keeps, or an opaque one, is the pixel's).

How: a binned-SAH BVH over the triangles (float32 boxes, built once per caster) and one kernel
(:func:`_trace`) that takes the rays an image row at a time: they share their origin and lie in one
plane, so each BVH node is visited once per row with the run of rays that reached it, narrowed by
vectorised slab tests, nearer child first; at a leaf each triangle is tested (Moller-Trumbore in
float64) against the run, and a candidate nearer than the ray's best hit on an alpha-tested triangle
goes through the alpha test there. Rows are dealt in turn to the threads of numba's pool (the kernel
releases the GIL).
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from typing import Any

import numba
import numpy as np
from PIL import Image

from droneulator import frames
from droneulator.config import CameraConfig
from droneulator.render.renderer import MAX_TEXTURE_SIZE
from droneulator.scenes.base import Scene
from droneulator.sensors.camera import Camera

#: BVH build: bins per axis of the binned SAH; the cost of visiting a node in triangle tests (the kernel
#: tests a leaf's triangles against a row's rays several at a time, so large leaves pay); a node of at
#: most LEAF_MIN triangles is a leaf, one of at most LEAF_MAX a leaf when the SAH finds no cheaper split.
BINS = 16
NODE_COST = 3.0
LEAF_MIN = 2
LEAF_MAX = 16
#: Rays a vectorised loop of the kernel takes at a time.
LANES = 8
#: The lowest and the highest set bit of each LANES-bit mask.
_FIRST = np.array([(m & -m).bit_length() - 1 for m in range(1 << LANES)], dtype=np.int64)
_LAST = np.array([m.bit_length() - 1 for m in range(1 << LANES)], dtype=np.int64)
#: Rays per thread below which a batch is not split across threads.
MIN_RAYS_PER_THREAD = 1024
#: Bodies as spheres for the depth: centres (B, K, 3, world) and radii (B, K), K per pose (pad: radius 0).
Spheres = tuple[np.ndarray, np.ndarray]


def _aligned(shape: tuple[int, int]) -> np.ndarray:
    """A zeroed C-contiguous float32 array whose data start on a 64-byte (cache line) boundary."""
    n = shape[0] * shape[1]
    buf = np.zeros(n + 16, dtype=np.float32)
    skip = (-buf.ctypes.data % 64) // 4
    return buf[skip : skip + n].reshape(shape)


def _pyramid(alpha: np.ndarray) -> list[np.ndarray]:
    """The mip chain of an 8-bit square power-of-two alpha image as llvmpipe's ``glGenerateMipmap``
    builds it (exactly: each level halves the width, then the height, averaging pairs rounded up)."""
    levels = [alpha.astype(np.int32)]
    a = levels[0]
    while a.shape[0] > 1 or a.shape[1] > 1:
        if a.shape[1] > 1:
            a = (a[:, 0::2] + a[:, 1::2] + 1) >> 1
        if a.shape[0] > 1:
            a = (a[0::2] + a[1::2] + 1) >> 1
        levels.append(a)
    return [lv.astype(np.uint8) for lv in levels]


@numba.njit(cache=True, nogil=True, inline="always")
def _lerp8(a: int, b: int, w: int) -> int:
    """llvmpipe's 8-bit lerp with an 8-bit weight, rounded."""
    return a + (((b - a) * w + 128) >> 8)


@numba.njit(cache=True, nogil=True)
def _bilinear(
    pyr: np.ndarray, base: int, offsets: np.ndarray, size: int, level: int, s: float, t: float
) -> int:
    """8-bit bilinear sample (repeat wrap) of one mip level, with llvmpipe's 8-bit texel fractions
    (``size`` a power of two)."""
    sz = max(size >> level, 1)
    mask = sz - 1
    sx = np.int64(np.rint(s * sz * 256.0)) - 128
    sy = np.int64(np.rint(t * sz * 256.0)) - 128
    i0, wx = (sx >> 8) & mask, sx & 255
    j0, wy = (sy >> 8) & mask, sy & 255
    i1, j1 = (i0 + 1) & mask, (j0 + 1) & mask
    o = base + offsets[level]
    top = _lerp8(np.int64(pyr[o + j0 * sz + i0]), np.int64(pyr[o + j0 * sz + i1]), wx)
    bot = _lerp8(np.int64(pyr[o + j1 * sz + i0]), np.int64(pyr[o + j1 * sz + i1]), wx)
    return _lerp8(top, bot, wy)


@numba.njit(cache=True, nogil=True)
def _fast_log2(x: float) -> float:
    """llvmpipe's ``lp_build_fast_log2``: exponent plus mantissa - 1 (piecewise linear)."""
    m, e = math.frexp(x)
    return (e - 2) + 2.0 * m


@numba.njit(cache=True, nogil=True, inline="always")
def _pixel_uv(
    k: int, b: int, x: float, y: float, R: np.ndarray, C: np.ndarray, geo: np.ndarray
) -> tuple[float, float]:
    """Texture coordinates where the ray of pose ``b`` along optical ``(x, y, 1)`` (a pixel's) meets
    triangle ``k``'s plane (extrapolated beyond the triangle, as the rasteriser's helper pixels are);
    ``geo``: per triangle its plane (n, n . P0) and its texture-coordinate map (2 rows of 4)."""
    dx = R[b, 0, 0] * x + R[b, 0, 1] * y + R[b, 0, 2]
    dy = R[b, 1, 0] * x + R[b, 1, 1] * y + R[b, 1, 2]
    dz = R[b, 2, 0] * x + R[b, 2, 1] * y + R[b, 2, 2]
    cx, cy, cz = C[b, 0], C[b, 1], C[b, 2]
    nd = geo[k, 0] * dx + geo[k, 1] * dy + geo[k, 2] * dz
    t = (geo[k, 3] - (geo[k, 0] * cx + geo[k, 1] * cy + geo[k, 2] * cz)) / nd
    x, y, z = cx + t * dx, cy + t * dy, cz + t * dz
    s = geo[k, 4] * x + geo[k, 5] * y + geo[k, 6] * z + geo[k, 7]
    r = geo[k, 8] * x + geo[k, 9] * y + geo[k, 10] * z + geo[k, 11]
    return s, r


@numba.njit(cache=True, nogil=True, inline="always")
def _quad(
    k: int,
    b: int,
    u0: int,
    v0: int,
    xs: np.ndarray,
    ys: np.ndarray,
    R: np.ndarray,
    C: np.ndarray,
    geo: np.ndarray,
    size: int,
) -> tuple[float, float, float, float, float, float, float, float]:
    """Triangle ``k``'s texture coordinates at the top-left, top-right and bottom-left pixels of the 2x2
    pixel quad at (u0, v0) (even; ``xs``, ``ys``: the optical x of each pixel column, y of each row), the
    largest texel step across the quad (the shader's ``lod`` is its log2) and the sampler's lod."""
    s00, t00 = _pixel_uv(k, b, xs[u0], ys[v0], R, C, geo)
    s10, t10 = _pixel_uv(k, b, xs[u0 + 1], ys[v0], R, C, geo)
    s01, t01 = _pixel_uv(k, b, xs[u0], ys[v0 + 1], R, C, geo)
    dxs, dxt = (s10 - s00) * size, (t10 - t00) * size
    dys, dyt = (s01 - s00) * size, (t01 - t00) * size
    texels = max(max(abs(dxs), abs(dys)), max(abs(dxt), abs(dyt)))
    # the sampler's lod: rho^2 = max over x, y of the squared texel step, fast log2, halved
    rho2 = max(dxs * dxs + dxt * dxt, dys * dys + dyt * dyt)
    if not math.isfinite(rho2):
        rho2 = 0.0
    lod = 0.5 * _fast_log2(rho2) if rho2 > 0.0 else -1.0
    return s00, t00, s10, t10, s01, t01, texels, lod


@numba.njit(cache=True, nogil=True, inline="always")
def _kept(
    k: int,
    b: int,
    u: int,
    v: int,
    quad: tuple[float, float, float, float, float, float, float, float],
    xs: np.ndarray,
    ys: np.ndarray,
    R: np.ndarray,
    C: np.ndarray,
    geo: np.ndarray,
    layer: int,
    pyr: np.ndarray,
    offsets: np.ndarray,
    size: int,
) -> bool:
    """Whether the fragment of alpha-tested triangle ``k`` at pixel (u, v) survives the renderer's
    ``alpha * (1 + 0.25 lod) < 0.5`` discard (quad derivatives, llvmpipe's trilinear sampler); ``quad``:
    :func:`_quad` of the pixel's quad."""
    s00, t00, s10, t10, s01, t01, texels, lod = quad
    # the quad's top-left, top-right and bottom-left pixels, then this one (the bottom-right one alone is
    # none of them)
    if v & 1 == 0:
        s, t = (s00, t00) if u & 1 == 0 else (s10, t10)
    elif u & 1 == 0:
        s, t = s01, t01
    else:
        s, t = _pixel_uv(k, b, xs[u], ys[v], R, C, geo)
    if not (math.isfinite(s) and math.isfinite(t)):
        return True
    base = layer * offsets[offsets.shape[0] - 1]
    last = offsets.shape[0] - 2
    if lod <= 0.0:
        alpha = _bilinear(pyr, base, offsets, size, 0, s, t)
    else:
        level = int(math.floor(lod))
        if level >= last:
            alpha = _bilinear(pyr, base, offsets, size, last, s, t)
        else:
            w = int((lod - level) * 256.0)
            a0 = _bilinear(pyr, base, offsets, size, level, s, t)
            a1 = _bilinear(pyr, base, offsets, size, level + 1, s, t)
            alpha = _lerp8(a0, a1, w)
    if alpha >= 128:  # kept whatever the lod (128 / 255 > 0.5)
        return True
    # the shader's own lod (GLSL log2 of the largest texel step), clamped at 0
    shader_lod = max(math.log2(texels), 0.0) if texels > 0.0 else 0.0
    if not math.isfinite(shader_lod):
        shader_lod = 0.0
    return (alpha / 255.0) * (1.0 + 0.25 * shader_lod) >= 0.5


@numba.njit(cache=True, nogil=True)
def _half_area(b: np.ndarray) -> float:
    """Half the surface area of box ``b`` (min xyz, max xyz), 0 when empty."""
    dx, dy, dz = b[3] - b[0], b[4] - b[1], b[5] - b[2]
    if dx < 0.0 or dy < 0.0 or dz < 0.0:
        return 0.0
    return dx * dy + dy * dz + dz * dx


@numba.njit(cache=True, nogil=True)
def _build_bvh(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """Binned-SAH BVH over the boxes ``lo``..``hi`` (n, 3) of n >= 1 triangles: per node its box (min xyz,
    max xyz), ``first`` (interior: its first child, the second follows it; leaf: its first entry of
    ``order``) and ``count`` (leaf: its triangles, interior: 0); ``order``, the triangles in leaf order;
    the tree's depth in levels."""
    n = lo.shape[0]
    cen = 0.5 * (lo + hi)
    order = np.arange(n)
    cap = max(2 * n - 1, 1)
    box = np.empty((cap, 6))
    first = np.zeros(cap, np.int64)
    count = np.zeros(cap, np.int64)
    stack = np.empty((cap, 4), np.int64)  # node, its triangles' range in order, its depth
    stack[0] = (0, 0, n, 1)
    sp, nodes, levels = 1, 1, 1
    bin_box = np.empty((BINS, 6))
    bin_n = np.empty(BINS, np.int64)
    right_area = np.empty(BINS)
    while sp:
        sp -= 1
        node, s, e, level = stack[sp, 0], stack[sp, 1], stack[sp, 2], stack[sp, 3]
        levels = max(levels, level)
        cmin = np.full(3, np.inf)
        cmax = np.full(3, -np.inf)
        for a in range(3):
            box[node, a], box[node, a + 3] = np.inf, -np.inf
        for i in range(s, e):
            t = order[i]
            for a in range(3):
                box[node, a] = min(box[node, a], lo[t, a])
                box[node, a + 3] = max(box[node, a + 3], hi[t, a])
                cmin[a] = min(cmin[a], cen[t, a])
                cmax[a] = max(cmax[a], cen[t, a])
        m = e - s
        first[node], count[node] = s, m
        if m <= LEAF_MIN:
            continue
        # the cheapest split between bins along any axis (in triangle tests, relative to the node's area)
        best, best_axis, best_bin = np.inf, -1, 0
        for a in range(3):
            ext = cmax[a] - cmin[a]
            if ext <= 0.0:
                continue
            scale = BINS / ext
            bin_n[:] = 0
            bin_box[:, :3] = np.inf
            bin_box[:, 3:] = -np.inf
            for i in range(s, e):
                t = order[i]
                k = min(int((cen[t, a] - cmin[a]) * scale), BINS - 1)
                bin_n[k] += 1
                for c in range(3):
                    bin_box[k, c] = min(bin_box[k, c], lo[t, c])
                    bin_box[k, c + 3] = max(bin_box[k, c + 3], hi[t, c])
            acc = np.full(6, np.inf)
            acc[3:] = -np.inf
            for k in range(BINS - 1, 0, -1):
                for c in range(3):
                    acc[c] = min(acc[c], bin_box[k, c])
                    acc[c + 3] = max(acc[c + 3], bin_box[k, c + 3])
                right_area[k] = _half_area(acc)
            acc[:3] = np.inf
            acc[3:] = -np.inf
            left = 0
            for k in range(BINS - 1):
                for c in range(3):
                    acc[c] = min(acc[c], bin_box[k, c])
                    acc[c + 3] = max(acc[c + 3], bin_box[k, c + 3])
                left += bin_n[k]
                if left == 0 or left == m:
                    continue
                cost = _half_area(acc) * left + right_area[k + 1] * (m - left)
                if cost < best:
                    best, best_axis, best_bin = cost, a, k
        area = _half_area(box[node])
        if best_axis < 0:
            if m <= LEAF_MAX:  # coincident centroids: split in two halves only when large
                continue
            mid = s + m // 2
        else:
            if m <= LEAF_MAX and NODE_COST + best / max(area, 1e-300) >= m:
                continue
            a = best_axis
            scale = BINS / (cmax[a] - cmin[a])
            i, j = s, e - 1
            while i <= j:
                if min(int((cen[order[i], a] - cmin[a]) * scale), BINS - 1) <= best_bin:
                    i += 1
                else:
                    order[i], order[j] = order[j], order[i]
                    j -= 1
            mid = i
        c = nodes
        nodes += 2
        first[node], count[node] = c, 0
        stack[sp] = (c + 1, mid, e, level + 1)
        stack[sp + 1] = (c, s, mid, level + 1)
        sp += 2
    return box[:nodes], first[:nodes], count[:nodes], order, levels


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _trace(
    part: int,
    parts: int,
    row_pose: np.ndarray,
    row_v: np.ndarray,
    width: int,
    R: np.ndarray,
    C: np.ndarray,
    K: np.ndarray,
    near: float,
    far: float,
    node: np.ndarray,
    node_int: np.ndarray,
    levels: int,
    tri: np.ndarray,
    tri_int: np.ndarray,
    geo: np.ndarray,
    pyr: np.ndarray,
    offsets: np.ndarray,
    size: int,
    share: np.ndarray,
    depth: np.ndarray,
    hit: np.ndarray,
) -> None:
    """Cast the image rows ``part``, ``part + parts``, ... (pose index ``row_pose``, pixel row ``row_v``,
    pixels ``0 .. width - 1``, written from ``row * width`` on) through the BVH: per pixel the nearest
    triangle between ``near`` and ``far`` whose fragment the alpha test keeps, its depth refined on its
    plane and its index (NaN and -1 where there is none).

    A row's rays share their origin and lie in one plane, so the rays meeting a box are (all but) a
    contiguous run: a node is visited once per row with the run of rays that reached it, narrowed to the
    first and last of them that meet its box (branch-free loops over the run, which the compiler
    vectorises). ``node``: the BVH (see :meth:`DepthCaster._build_bvh`), ``tri``: the triangles in its
    leaf order, ``geo``: their planes and texture-coordinate maps."""
    fx, fy, cx, cy = K[0], K[1], K[2], K[3]
    # per ray of the row, padded for the loops over LANES rays at a time (unsigned indices: no wraparound)
    dx, dy, dz = np.zeros(width + LANES), np.zeros(width + LANES), np.zeros(width + LANES)
    ix, iy, iz = np.zeros(width + LANES), np.zeros(width + LANES), np.zeros(width + LANES)
    t_best = np.zeros(width + LANES)
    best = np.empty(width, np.int64)
    stack = np.empty((levels + 1, 3), np.int64)
    # optical x of each pixel column, y of each row, one beyond for the helper pixels of a quad
    xs = (np.arange(width + 1) - cx) / fx
    ys = (np.arange(row_v.max() + 2) - cy) / fy
    for row in range(part, row_pose.shape[0], parts):
        b = row_pose[row]
        v = row_v[row]
        y = ys[v]
        ox, oy, oz = C[b, 0], C[b, 1], C[b, 2]
        for r in range(width):
            x = xs[r]
            dx[r] = R[b, 0, 0] * x + R[b, 0, 1] * y + R[b, 0, 2]
            dy[r] = R[b, 1, 0] * x + R[b, 1, 1] * y + R[b, 1, 2]
            dz[r] = R[b, 2, 0] * x + R[b, 2, 1] * y + R[b, 2, 2]
            ix[r] = 1.0 / dx[r] if abs(dx[r]) > 1e-200 else math.copysign(1e200, dx[r])
            iy[r] = 1.0 / dy[r] if abs(dy[r]) > 1e-200 else math.copysign(1e200, dy[r])
            iz[r] = 1.0 / dz[r] if abs(dz[r]) > 1e-200 else math.copysign(1e200, dz[r])
            t_best[r] = far
            best[r] = -1
        stack[0, 0], stack[0, 1], stack[0, 2] = 1, 0, width - 1
        sp = 1
        while sp:
            sp -= 1
            n, lo, hi = stack[sp, 0], stack[sp, 1], stack[sp, 2]
            while node_int[n, 7] == 0:
                # the first and the last ray of the run that meet each child's box (slabs relative to the
                # origin): on to the nearer child, the other one onto the stack
                c = node_int[n, 6]
                x0, y0, z0 = node[c, 0] - ox, node[c, 1] - oy, node[c, 2] - oz
                x1, y1, z1 = node[c, 3] - ox, node[c, 4] - oy, node[c, 5] - oz
                x2, y2, z2 = node[c + 1, 0] - ox, node[c + 1, 1] - oy, node[c + 1, 2] - oz
                x3, y3, z3 = node[c + 1, 3] - ox, node[c + 1, 4] - oy, node[c + 1, 5] - oz
                i, j, k, m = hi + 1, lo - 1, hi + 1, lo - 1
                for base in range(lo, hi + 1, LANES):
                    hit_a, hit_b = 0, 0
                    for lane in range(LANES):
                        r = base + lane
                        e = np.uint64(r)
                        ax, bx = x0 * ix[e], x1 * ix[e]
                        ay, by = y0 * iy[e], y1 * iy[e]
                        az, bz = z0 * iz[e], z1 * iz[e]
                        t0 = max(max(min(ax, bx), min(ay, by)), max(min(az, bz), near))
                        t1 = min(min(max(ax, bx), max(ay, by)), min(max(az, bz), t_best[e]))
                        hit_a |= np.int64((t0 <= t1) & (r <= hi)) << lane
                        ax, bx = x2 * ix[e], x3 * ix[e]
                        ay, by = y2 * iy[e], y3 * iy[e]
                        az, bz = z2 * iz[e], z3 * iz[e]
                        t0 = max(max(min(ax, bx), min(ay, by)), max(min(az, bz), near))
                        t1 = min(min(max(ax, bx), max(ay, by)), min(max(az, bz), t_best[e]))
                        hit_b |= np.int64((t0 <= t1) & (r <= hi)) << lane
                    if hit_a:
                        i = min(i, base + _FIRST[hit_a])
                        j = base + _LAST[hit_a]
                    if hit_b:
                        k = min(k, base + _FIRST[hit_b])
                        m = base + _LAST[hit_b]
                if i > j:
                    if k > m:
                        break
                    n, lo, hi = c + 1, k, m
                elif k > m:
                    n, lo, hi = c, i, j
                else:
                    # both: the nearer first, as the middle ray of each run sees them
                    e = np.uint64((i + j) // 2)
                    ax, bx, ay, by = x0 * ix[e], x1 * ix[e], y0 * iy[e], y1 * iy[e]
                    az, bz = z0 * iz[e], z1 * iz[e]
                    ta = max(max(min(ax, bx), min(ay, by)), min(az, bz))
                    e = np.uint64((k + m) // 2)
                    ax, bx, ay, by = x2 * ix[e], x3 * ix[e], y2 * iy[e], y3 * iy[e]
                    az, bz = z2 * iz[e], z3 * iz[e]
                    tb = max(max(min(ax, bx), min(ay, by)), min(az, bz))
                    if ta <= tb:
                        stack[sp, 0], stack[sp, 1], stack[sp, 2] = c + 1, k, m
                        n, lo, hi = c, i, j
                    else:
                        stack[sp, 0], stack[sp, 1], stack[sp, 2] = c, i, j
                        n, lo, hi = c + 1, k, m
                    sp += 1
            if node_int[n, 7] == 0:
                continue
            i, j = lo, hi
            for k in range(node_int[n, 6], node_int[n, 6] + node_int[n, 7]):
                # Moller-Trumbore in float64 (the float32 vertices' edges are exact) with the origin's part
                # per triangle: det = e1 . (d x e2) = -d . n, u det = d . (e2 x s), v det = d . (s x e1)
                wx, wy, wz = np.float64(tri[k, 0]), np.float64(tri[k, 1]), np.float64(tri[k, 2])
                e1x, e1y, e1z = tri[k, 3] - wx, tri[k, 4] - wy, tri[k, 5] - wz
                e2x, e2y, e2z = tri[k, 6] - wx, tri[k, 7] - wy, tri[k, 8] - wz
                sx, sy, sz = ox - wx, oy - wy, oz - wz
                nx, ny, nz = e1y * e2z - e1z * e2y, e1z * e2x - e1x * e2z, e1x * e2y - e1y * e2x
                ux, uy, uz = e2y * sz - e2z * sy, e2z * sx - e2x * sz, e2x * sy - e2y * sx
                qx, qy, qz = sy * e1z - sz * e1y, sz * e1x - sx * e1z, sx * e1y - sy * e1x
                tn = e2x * qx + e2y * qy + e2z * qz
                # the first and the last ray of the run that meet the triangle nearer than their best hit
                f, g = j + 1, i - 1
                for base in range(i, j + 1, LANES):
                    hits = 0
                    for lane in range(LANES):
                        r = base + lane
                        e = np.uint64(r)
                        det = -(dx[e] * nx + dy[e] * ny + dz[e] * nz)
                        uu = dx[e] * ux + dy[e] * uy + dz[e] * uz
                        vv = dx[e] * qx + dy[e] * qy + dz[e] * qz
                        t = tn / det
                        inside = (
                            (uu >= 0.0) & (vv >= 0.0) & (uu + vv <= det)
                            if det > 0.0
                            else ((uu <= 0.0) & (vv <= 0.0) & (uu + vv >= det) & (det < 0.0))
                        )
                        hits |= np.int64(inside & (t >= near) & (t < t_best[e]) & (r <= j)) << lane
                    if hits:
                        f = min(f, base + _FIRST[hits])
                        g = base + _LAST[hits]
                if f > g:
                    continue
                layer = tri_int[k, 10]
                quad_u0 = -1
                quad = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
                for r in range(f, g + 1):
                    det = -(dx[r] * nx + dy[r] * ny + dz[r] * nz)
                    uu = dx[r] * ux + dy[r] * uy + dz[r] * uz
                    vv = dx[r] * qx + dy[r] * qy + dz[r] * qz
                    t = tn / det
                    if det > 0.0:
                        if uu < 0.0 or vv < 0.0 or uu + vv > det:
                            continue
                    elif det < 0.0:
                        if uu > 0.0 or vv > 0.0 or uu + vv < det:
                            continue
                    else:
                        continue
                    if t < near or t >= t_best[r]:
                        continue
                    if layer >= 0:
                        if r - (r & 1) != quad_u0:
                            quad_u0 = r - (r & 1)
                            quad = _quad(k, b, quad_u0, v - (v & 1), xs, ys, R, C, geo, size)
                        if not _kept(k, b, r, v, quad, xs, ys, R, C, geo, layer, pyr, offsets, size):
                            continue  # a discarded texel: the ray goes on through it
                    t_best[r], best[r] = t, k
                    for e in range(share[r, 0], share[r, 1]):
                        t_best[e] = min(t_best[e], t)
        o = row * width
        for r in range(width):
            k = best[r]
            if k < 0:
                depth[o + r], hit[o + r] = np.nan, -1
                continue
            # the depth on the triangle's plane (the renderer's interpolated eye-space z)
            nd = geo[k, 0] * dx[r] + geo[k, 1] * dy[r] + geo[k, 2] * dz[r]
            nc = geo[k, 0] * ox + geo[k, 1] * oy + geo[k, 2] * oz
            t = (geo[k, 3] - nc) / nd if nd != 0.0 else np.nan
            if math.isfinite(t) and t < far:
                depth[o + r], hit[o + r] = t, tri_int[k, 9]
            else:
                depth[o + r], hit[o + r] = np.nan, -1


@numba.njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def _trace_parts(
    parts: int,
    row_pose: np.ndarray,
    row_v: np.ndarray,
    width: int,
    R: np.ndarray,
    C: np.ndarray,
    K: np.ndarray,
    near: float,
    far: float,
    node: np.ndarray,
    node_int: np.ndarray,
    levels: int,
    tri: np.ndarray,
    tri_int: np.ndarray,
    geo: np.ndarray,
    pyr: np.ndarray,
    offsets: np.ndarray,
    size: int,
    share: np.ndarray,
    depth: np.ndarray,
    hit: np.ndarray,
) -> None:
    """:func:`_trace` of every part, on numba's thread pool (releasing the GIL): the pool the batched
    physics and the RL task step use, whose OpenMP threads spin for a while after their own parallel
    regions, on the cores threads of another pool would need (at B = 256 the physics step then the cast
    took 12.3 ms with threads of the caster's own, 6.0 ms on the pool)."""
    for part in numba.prange(parts):
        _trace(
            np.int64(part), parts, row_pose, row_v, width, R, C, K, near, far, node, node_int, levels, tri,
            tri_int, geo, pyr, offsets, size, share, depth, hit,
        )  # fmt: skip


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _sphere_rows(
    row_pose: np.ndarray,
    row_v: np.ndarray,
    width: int,
    R: np.ndarray,
    C: np.ndarray,
    K: np.ndarray,
    near: float,
    far: float,
    centres: np.ndarray,
    radii: np.ndarray,
    depth: np.ndarray,
) -> None:
    """Depth of the image rows (pose index ``row_pose``, pixel row ``row_v``, written from ``row * width``
    on) against pose ``b``'s spheres (``centres[b]``, ``radii[b]``): per pixel the nearest ray-sphere
    intersection at ``near <= t < far`` (NaN where none), the rays those of :func:`_trace`.

    Each sphere goes to the optical frame once per row; with the ray ``t (x, y, 1)`` and the centre ``c``,
    ``t`` solves ``a t^2 - 2 h t + q = 0`` (``a = x^2 + y^2 + 1``, ``h = (x, y, 1) . c``,
    ``q = |c|^2 - r^2``), its roots taken in the cancellation-free form ``q / (h + s)``, ``(h + s) / a``.
    A sphere holding the camera (``q <= 0``), a radius not > 0 or a non-finite centre is skipped; a near
    plane cutting the sphere shows its far side (the renderer culls no faces)."""
    fx, fy, cx, cy = K[0], K[1], K[2], K[3]
    n_spheres = radii.shape[1]
    best = np.empty(width)
    for row in range(row_pose.shape[0]):
        b = row_pose[row]
        y = (row_v[row] - cy) / fy
        best[:] = np.inf
        for j in range(n_spheres):
            r = radii[b, j]
            px, py, pz = centres[b, j, 0] - C[b, 0], centres[b, j, 1] - C[b, 1], centres[b, j, 2] - C[b, 2]
            if not (r > 0.0 and math.isfinite(r) and math.isfinite(px + py + pz)):
                continue
            # the centre in the optical frame (R: optical axes in the world)
            ox = R[b, 0, 0] * px + R[b, 1, 0] * py + R[b, 2, 0] * pz
            oy = R[b, 0, 1] * px + R[b, 1, 1] * py + R[b, 2, 1] * pz
            oz = R[b, 0, 2] * px + R[b, 1, 2] * py + R[b, 2, 2] * pz
            q = ox * ox + oy * oy + oz * oz - r * r
            if q <= 0.0 or oz + r < near or oz - r >= far:
                continue
            for u in range(width):
                x = (u - cx) / fx
                h = x * ox + y * oy + oz
                if h <= 0.0:
                    continue  # the sphere lies behind this ray's origin
                a = x * x + y * y + 1.0
                disc = h * h - a * q
                if disc < 0.0:
                    continue
                hs = h + math.sqrt(disc)
                t = q / hs
                if t < near:
                    t = hs / a
                if near <= t < far and t < best[u]:
                    best[u] = t
        o = row * width
        for u in range(width):
            depth[o + u] = best[u] if best[u] < far else np.nan


def sector_edges(width: int, sectors: int) -> np.ndarray:
    """The first pixel of each of ``sectors`` equal runs of a ``width``-pixel row, then ``width``."""
    return np.linspace(0, width, sectors + 1).round().astype(np.int64)


class DepthCaster:
    """Depth images of body-mounted cameras for batches of body poses in one static scene, by ray casting
    (a BVH), equal to :class:`~droneulator.render.Renderer`'s depth (see the module docstring).

    ``cameras``: one camera or several (names unique); ``threads``: the image rows of a large batch are
    dealt to this many parts, run on numba's thread pool (default: every CPU). The BVH is built once,
    here (about 0.1 s for 50 k triangles). Per triangle of the scene (parts in order, as :meth:`trace`
    numbers them): ``triangle_class``, its semantic class (the renderer's segmentation id), and
    ``alpha_tested``.
    """

    def __init__(
        self,
        scene: Scene,
        cameras: CameraConfig | Sequence[CameraConfig],
        threads: int | None = None,
    ) -> None:
        cams = [cameras] if isinstance(cameras, CameraConfig) else list(cameras)
        if not cams:
            raise ValueError("DepthCaster needs at least one camera")
        names = [c.name for c in cams]
        if len(set(names)) != len(names):
            raise ValueError(f"camera names must be unique, got {names}")
        self.scene = scene
        self.cameras: dict[str, CameraConfig] = {c.name: c for c in cams}
        self.threads = max(1, int(threads if threads is not None else (os.cpu_count() or 1)))
        self._mounts: dict[str, np.ndarray] = {}
        self._K: dict[str, np.ndarray] = {}
        for c in cams:
            camera = Camera(c)
            self._mounts[c.name] = camera.T_body_link @ frames.T_link_optical()
            K = camera.K
            self._K[c.name] = np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
        self._build_tables(scene)
        self._build_bvh()

    # ------------------------------------------------------------------------------------ setup
    def _build_tables(self, scene: Scene) -> None:
        """Vertices and triangles (float32 as the renderer uploads them), each triangle's plane, its
        texture-coordinate map and, for alpha-tested ones, its alpha pyramid layer."""
        parts = [p for p in scene.parts if p.triangle_count]
        self.n_triangles = sum(p.triangle_count for p in parts)
        # textures resized to the renderer's common square, as Renderer._upload_textures does
        images = list(scene.textures.values()) or [np.full((1, 1, 4), 255, dtype=np.uint8)]
        size = min(MAX_TEXTURE_SIZE, max(max(img.shape[:2]) for img in images))
        self._size = int(size)
        alpha_names = sorted({p.texture for p in parts if p.alpha_test})
        if alpha_names and size & (size - 1):
            raise ValueError(f"alpha-tested textures need a power-of-two texture size, got {size}")
        pyramids = []
        for name in alpha_names:
            img = np.ascontiguousarray(scene.textures[name], dtype=np.uint8)
            if img.shape[:2] != (size, size):
                smooth = Image.Resampling.NEAREST if img.shape[:2] == (2, 2) else Image.Resampling.BILINEAR
                img = np.asarray(Image.fromarray(img, "RGBA").resize((size, size), smooth))
            pyramids.append(_pyramid(img[..., 3]))
        counts = [lv.size for lv in pyramids[0]] if pyramids else [1]
        self._offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        flat = [np.concatenate([lv.ravel() for lv in pyr]) for pyr in pyramids]
        self._pyr = np.concatenate(flat) if flat else np.zeros(1, dtype=np.uint8)

        if not self.n_triangles:
            self._positions = np.zeros((0, 3), np.float32)
            self._triangles = np.zeros((0, 3), np.int32)
            self._plane = np.zeros((0, 4))
            self._uvmap = np.zeros((0, 2, 4))
            self._layer = np.zeros(0, np.int64)
            self.triangle_class = np.zeros(0, np.uint8)
            self.alpha_tested = np.zeros(0, bool)
            return
        positions, uvs, triangles, layer, start = [], [], [], [], 0
        for p in parts:
            positions.append(np.asarray(p.positions, dtype=np.float32))
            uvs.append(np.asarray(p.uvs, dtype=np.float64))
            triangles.append(np.asarray(p.indices, dtype=np.int64) + start)
            slot = alpha_names.index(p.texture) if p.alpha_test else -1
            layer.append(np.full(p.triangle_count, slot, dtype=np.int64))
            start += len(p.positions)
        self._positions = np.concatenate(positions)
        self._triangles = np.concatenate(triangles).astype(np.int32)
        self._layer = np.concatenate(layer)
        self.triangle_class = np.concatenate([np.asarray(p.class_ids)[p.indices[:, 0]] for p in parts])
        self.alpha_tested = self._layer >= 0
        tri = self._triangles.astype(np.int64)
        P = self._positions.astype(np.float64)[tri]  # (T, 3, 3)
        e1, e2 = P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]
        n = np.cross(e1, e2)
        self._plane = np.concatenate([n, (n * P[:, 0]).sum(1, keepdims=True)], axis=1)
        # uv(X) = uv0 + Duv G^-1 [e1 e2]^T (X - P0) for X on the plane (G: the edges' Gram matrix)
        W = np.concatenate(uvs)[tri]  # (T, 3, 2)
        duv = np.stack([W[:, 1] - W[:, 0], W[:, 2] - W[:, 0]], axis=2)  # (T, 2, 2)
        g00, g01, g11 = (e1 * e1).sum(1), (e1 * e2).sum(1), (e2 * e2).sum(1)
        det = g00 * g11 - g01 * g01
        ok = det > 0
        inv = np.zeros((len(tri), 2, 2))
        inv[ok, 0, 0], inv[ok, 0, 1] = g11[ok] / det[ok], -g01[ok] / det[ok]
        inv[ok, 1, 0], inv[ok, 1, 1] = -g01[ok] / det[ok], g00[ok] / det[ok]
        A = duv @ inv @ np.stack([e1, e2], axis=1)  # (T, 2, 3)
        offset = W[:, 0] - np.einsum("tij,tj->ti", A, P[:, 0])
        self._uvmap = np.concatenate([A, offset[:, :, None]], axis=2)

    def _build_bvh(self) -> None:
        """The BVH and the tables the kernel reads, packed for locality: per node (row 1 the root, row 0
        unused, children pairs 64-byte aligned) its box (float32, one ulp wider each way: conservative for
        the float64 slab test), then as int32 its first child (the second follows it) or first triangle
        and its triangle count (0: interior); per triangle in leaf order its vertices (float32), then as
        int32 its index in the scene and its alpha layer (-1: opaque); and its plane and texture-coordinate
        map (float64)."""
        if not self.n_triangles:
            self._bvh: tuple[Any, ...] | None = None
            return
        P = self._positions[self._triangles]  # (T, 3, 3) float32
        box, first, count, order, levels = _build_bvh(
            P.min(axis=1).astype(np.float64), P.max(axis=1).astype(np.float64)
        )
        node = _aligned((len(box) + 1, 8))
        node_int = node.view(np.int32)
        node[1:, :3] = np.nextafter(box[:, :3].astype(np.float32), np.float32(-np.inf))
        node[1:, 3:6] = np.nextafter(box[:, 3:].astype(np.float32), np.float32(np.inf))
        node_int[1:, 6] = np.where(count > 0, first, first + 1)
        node_int[1:, 7] = count
        tri = np.zeros((len(order), 12), np.float32)
        tri_int = tri.view(np.int32)
        tri[:, :9] = P[order].reshape(-1, 9)
        tri_int[:, 9] = order
        tri_int[:, 10] = self._layer[order]
        geo = np.ascontiguousarray(np.concatenate([self._plane, self._uvmap.reshape(-1, 8)], axis=1)[order])
        self._bvh = (node, node_int, int(levels), tri, tri_int, geo)

    # ------------------------------------------------------------------------------------ queries
    def _poses(self, T_world_body: np.ndarray, camera: str | None) -> tuple[CameraConfig, np.ndarray]:
        """The camera and the (B, 4, 4) optical-frame poses, checked."""
        name = next(iter(self.cameras)) if camera is None else camera
        if name not in self.cameras:
            raise ValueError(f"unknown camera {name!r}; cameras: {', '.join(self.cameras)}")
        T = np.asarray(T_world_body, dtype=np.float64)
        if T.ndim != 3 or T.shape[1:] != (4, 4):
            raise ValueError(f"T_world_body must have shape (B, 4, 4), got {T.shape}")
        if not np.isfinite(T).all():
            bad = np.flatnonzero(~np.isfinite(T).all(axis=(1, 2)))
            raise ValueError(f"T_world_body has non-finite entries (poses {bad[:8].tolist()})")
        return self.cameras[name], T @ self._mounts[name]

    def depth(
        self, T_world_body: np.ndarray, camera: str | None = None, spheres: Spheres | None = None
    ) -> np.ndarray:
        """(B, H, W) float32 depth of ``camera`` (default: the first) for the (B, 4, 4) body poses; with
        ``spheres`` (see :meth:`sphere_depth`) the nearer of the scene and the spheres per pixel."""
        cam, T_wo = self._poses(T_world_body, camera)
        B, H = len(T_wo), cam.height
        pose, rows = np.repeat(np.arange(B, dtype=np.int64), H), np.tile(np.arange(H, dtype=np.int64), B)
        depth = self._cast(cam, T_wo, pose, rows)[0]
        if spheres is not None:
            np.fmin(depth, self._spheres(cam, T_wo, pose, rows, spheres), out=depth)
        return depth.reshape(B, H, cam.width)

    def centre_row(
        self, T_world_body: np.ndarray, camera: str | None = None, spheres: Spheres | None = None
    ) -> np.ndarray:
        """(B, W) float32: row ``H // 2`` of :meth:`depth` (the row the RL depth strip pools), casting only
        that row's rays; with ``spheres`` the nearer of the scene and the spheres per pixel."""
        cam, T_wo = self._poses(T_world_body, camera)
        B = len(T_wo)
        pose, rows = np.arange(B, dtype=np.int64), np.full(B, cam.height // 2, dtype=np.int64)
        depth = self._cast(cam, T_wo, pose, rows)[0]
        if spheres is not None:
            np.fmin(depth, self._spheres(cam, T_wo, pose, rows, spheres), out=depth)
        return depth.reshape(B, cam.width)

    def centre_row_minima(
        self,
        T_world_body: np.ndarray,
        sectors: int,
        camera: str | None = None,
        spheres: Spheres | None = None,
    ) -> np.ndarray:
        """(B, sectors) float32: the nearest depth in each of ``sectors`` equal runs of :meth:`centre_row`
        (:func:`sector_edges`; NaN where the run has no return), what the RL depth strip keeps of the row;
        with ``spheres``, of the merged row (the fmin of the scene's and the spheres' minima).

        Faster than pooling :meth:`centre_row`: a ray's hit bounds the search of the other rays of its
        sector, so a ray through a gap in the leaves stops where its neighbour's surface is instead of
        going on to what lies behind."""
        cam, T_wo = self._poses(T_world_body, camera)
        if not 1 <= int(sectors) <= cam.width:
            raise ValueError(f"sectors must be between 1 and the image width {cam.width}, got {sectors!r}")
        B, k = len(T_wo), int(sectors)
        if not B:
            return np.zeros((0, k), np.float32)
        pose, rows = np.arange(B, dtype=np.int64), np.full(B, cam.height // 2, dtype=np.int64)
        depth = self._cast(cam, T_wo, pose, rows, k)[0]
        if spheres is not None:
            np.fmin(depth, self._spheres(cam, T_wo, pose, rows, spheres), out=depth)
        return np.fmin.reduceat(depth.reshape(B, cam.width), sector_edges(cam.width, k)[:-1], axis=1)

    def sphere_depth(
        self, T_world_body: np.ndarray, centres: np.ndarray, radii: np.ndarray, camera: str | None = None
    ) -> np.ndarray:
        """(B, H, W) float32 depth of spheres alone (no scene): pose ``b`` sees the spheres ``centres[b]``
        (B, K, 3, world) of ``radii[b]`` (B, K), e.g. the other vehicles' collision spheres. Same rays,
        z-depth and near/far as :meth:`depth`; NaN where no sphere is hit. Spheres of radius <= 0 (or
        non-finite) or with a non-finite centre are skipped (padding), and so is a sphere holding the
        camera (the vehicle's own body, which its camera does not see)."""
        cam, T_wo = self._poses(T_world_body, camera)
        B, H = len(T_wo), cam.height
        pose, rows = np.repeat(np.arange(B, dtype=np.int64), H), np.tile(np.arange(H, dtype=np.int64), B)
        return self._spheres(cam, T_wo, pose, rows, (centres, radii)).reshape(B, H, cam.width)

    def sphere_centre_row(
        self, T_world_body: np.ndarray, centres: np.ndarray, radii: np.ndarray, camera: str | None = None
    ) -> np.ndarray:
        """(B, W) float32: row ``H // 2`` of :meth:`sphere_depth`, the rays :meth:`centre_row` casts."""
        cam, T_wo = self._poses(T_world_body, camera)
        B = len(T_wo)
        pose, rows = np.arange(B, dtype=np.int64), np.full(B, cam.height // 2, dtype=np.int64)
        return self._spheres(cam, T_wo, pose, rows, (centres, radii)).reshape(B, cam.width)

    def _spheres(
        self, cam: CameraConfig, T_wo: np.ndarray, pose: np.ndarray, rows: np.ndarray, spheres: Spheres
    ) -> np.ndarray:
        """Flat float32 depth of the spheres along the image rows (pose index, pixel row), checked."""
        centres = np.ascontiguousarray(spheres[0], dtype=np.float64)
        radii = np.ascontiguousarray(spheres[1], dtype=np.float64)
        B = len(T_wo)
        if centres.ndim != 3 or centres.shape[0] != B or centres.shape[2] != 3:
            raise ValueError(f"sphere centres must have shape ({B}, K, 3), got {centres.shape}")
        if radii.shape != centres.shape[:2]:
            raise ValueError(f"sphere radii must have shape {centres.shape[:2]}, got {radii.shape}")
        depth = np.empty(len(pose) * cam.width, dtype=np.float32)
        R = np.ascontiguousarray(T_wo[:, :3, :3])
        C = np.ascontiguousarray(T_wo[:, :3, 3])
        _sphere_rows(pose, rows, cam.width, R, C, self._K[cam.name], cam.near, cam.far, centres, radii, depth)
        return depth

    def trace(self, T_world_body: np.ndarray, camera: str | None = None) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`depth` and, per pixel, the triangle seen (int32 index into the scene's triangles, parts
        in order; -1 where the depth is NaN): its class is ``triangle_class[i]``, the renderer's
        segmentation id."""
        cam, T_wo = self._poses(T_world_body, camera)
        B, H, W = len(T_wo), cam.height, cam.width
        pose = np.repeat(np.arange(B, dtype=np.int64), H)
        rows = np.tile(np.arange(H, dtype=np.int64), B)
        depth, tri = self._cast(cam, T_wo, pose, rows)
        return depth.reshape(B, H, W), tri.reshape(B, H, W)

    def _cast(
        self, cam: CameraConfig, T_wo: np.ndarray, pose: np.ndarray, rows: np.ndarray, sectors: int = 0
    ) -> tuple[np.ndarray, np.ndarray]:
        """Depth and triangle of each pixel of the image rows (pose index, pixel row), row after row; the
        rows are dealt to the threads in turn for large batches. ``sectors`` > 0: only each sector's
        nearest return is wanted (see :meth:`centre_row_minima`)."""
        share = np.empty((cam.width, 2), np.int64)
        if sectors > 0:
            edges = sector_edges(cam.width, sectors)
            which = np.searchsorted(edges, np.arange(cam.width), side="right") - 1
            share[:, 0], share[:, 1] = edges[which], edges[which + 1]
        else:
            share[:, 0] = share[:, 1] = 0
        n = len(pose) * cam.width
        depth = np.full(n, np.nan, dtype=np.float32)
        tri = np.full(n, -1, dtype=np.int32)
        if not n or self._bvh is None:
            return depth, tri
        R = np.ascontiguousarray(T_wo[:, :3, :3])
        C = np.ascontiguousarray(T_wo[:, :3, 3])
        K = self._K[cam.name]
        parts = min(self.threads, len(pose), max(1, n // MIN_RAYS_PER_THREAD))

        _trace_parts(
            parts, pose, rows, cam.width, R, C, K, cam.near, cam.far, *self._bvh, self._pyr, self._offsets,
            self._size, share, depth, tri,
        )  # fmt: skip
        return depth, tri
