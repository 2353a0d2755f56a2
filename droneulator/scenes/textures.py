"""Procedural RGBA textures (uint8, power-of-two, tileable) written with vectorised numpy.

The textures carry detail at many scales (several octaves of value noise, splatted grass blades,
stones, bark fissures, leaf veins) so feature detectors such as SIFT find plenty of distinctive
keypoints for photogrammetry and visual odometry. Image row 0 is texture v = 0 (upload as-is).

Texture names and what they are drawn on:

``ground`` grass with small bare spots and pebbles (tile ~8 m) · ``soil`` atlas of bare-earth patch
decals (alpha-tested) · ``bark`` trunks and branches (tile 0.5 m)
· ``leaves`` / ``vine_leaves`` 2 x 2 atlases of alpha-tested leaf-card variants · ``wood`` posts
· ``wire`` trellis wire · ``fruit`` apples · ``rock`` boulders.
"""

from __future__ import annotations

import functools
import math

import numpy as np

#: Textures use fixed seeds so every scene shares one cached set (their look does not depend on the
#: scene seed, which only moves geometry).
TEXTURE_SEED = 20240607

#: Each leaf atlas is ATLAS_GRID x ATLAS_GRID card variants; :func:`atlas_rect` gives their uv rectangles.
ATLAS_GRID = 2


# --------------------------------------------------------------------------- noise primitives
def value_noise(rng: np.random.Generator, size: int, fx: int, fy: int | None = None) -> np.ndarray:
    """Tileable smooth value noise in [0, 1], (size, size) float32, ``fx`` x ``fy`` lattice cells."""
    fy = fx if fy is None else fy
    lat = rng.random((fy, fx), dtype=np.float32)

    def axis(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        x = np.arange(size, dtype=np.float32) * np.float32(n / size)
        fl = np.floor(x)
        i0 = fl.astype(np.int64)
        t = x - fl  # float32 throughout: (x - i0) would promote to float64
        t = t * t * (3.0 - 2.0 * t)
        return i0 % n, (i0 + 1) % n, t

    r0, r1, tr = axis(fy)
    c0, c1, tc = axis(fx)
    cols = lat[:, c0] * (1.0 - tc)[None, :] + lat[:, c1] * tc[None, :]  # (fy, size), small
    out = cols[r0]  # whole-row gathers are cheap
    out *= (1.0 - tr)[:, None]
    out += cols[r1] * tr[:, None]
    return out


def fbm(
    rng: np.random.Generator,
    size: int,
    base: int,
    octaves: int,
    persistence: float = 0.5,
    aniso: tuple[int, int] = (1, 1),
) -> np.ndarray:
    """Fractal sum of value-noise octaves, rescaled to [0, 1]. ``aniso`` multiplies (x, y) frequencies."""
    out = np.zeros((size, size), dtype=np.float32)
    amp, total = 1.0, 0.0
    for o in range(octaves):
        f = base * 2**o
        fx, fy = min(f * aniso[0], size // 2), min(f * aniso[1], size // 2)
        out += amp * value_noise(rng, size, max(fx, 1), max(fy, 1))
        total += amp
        amp *= persistence
    out /= total
    sample = out[::4, ::4]
    lo, hi = (float(x) for x in np.percentile(sample, [0.5, 99.5]))
    out -= lo
    out *= 1.0 / max(hi - lo, 1e-6)
    return np.clip(out, 0.0, 1.0, out=out)


def smoothstep(e0: float, e1: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _rgb(*c: float) -> np.ndarray:
    return np.array(c, dtype=np.float32) / 255.0


def _mix(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Per-pixel blend of colours/images ``a`` -> ``b`` by ``t`` (H, W)."""
    return a + (b - a) * t[..., None]


def _to_rgba(rgb: np.ndarray, alpha: np.ndarray | None = None) -> np.ndarray:
    out = np.empty(rgb.shape[:2] + (4,), dtype=np.uint8)
    out[..., :3] = np.clip(rgb * 255.0 + 0.5, 0, 255).astype(np.uint8)
    out[..., 3] = 255 if alpha is None else np.clip(alpha * 255.0 + 0.5, 0, 255).astype(np.uint8)
    out.setflags(write=False)
    return out


def _splat_lines(
    img: np.ndarray,
    mask: np.ndarray | None,
    p0: np.ndarray,
    p1: np.ndarray,
    colors: np.ndarray,
    width: float = 1.0,
) -> None:
    """Draw many short line segments (x, y pixel endpoints) by splatting samples, wrapping at edges.

    ``colors`` (K, 3). Width > 1 adds parallel offset strokes. Later segments overwrite earlier ones.
    """
    h, w = img.shape[:2]
    length = np.linalg.norm(p1 - p0, axis=1)
    n = max(2, int(np.ceil(length.max() * 1.25)) + 1)
    t = np.linspace(0.0, 1.0, n, dtype=np.float32)
    pts = p0[:, None, :] + (p1 - p0)[:, None, :] * t[None, :, None]  # (K, n, 2)
    offs = [0.0] if width <= 1.0 else np.linspace(-(width - 1) / 2, (width - 1) / 2, int(math.ceil(width)))
    d = (p1 - p0) / np.maximum(length, 1e-6)[:, None]
    perp = np.stack([-d[:, 1], d[:, 0]], 1)
    for o in offs:
        q = pts + perp[:, None, :] * o
        xi = np.floor(q[..., 0]).astype(np.int64) % w
        yi = np.floor(q[..., 1]).astype(np.int64) % h
        img[yi, xi] = np.broadcast_to(colors[:, None, :], q.shape[:2] + (3,))
        if mask is not None:
            mask[yi, xi] = 1.0


# --------------------------------------------------------------------------- textures
def _soil(rng: np.random.Generator, size: int, fine: np.ndarray) -> np.ndarray:
    """Bare earth: brown clods at several scales."""
    soil = _mix(_rgb(92, 70, 48), _rgb(140, 112, 80), fbm(rng, size, 8, 5))
    return soil * (0.8 + 0.4 * fine)[..., None]


def _grass_blades(
    img: np.ndarray,
    rng: np.random.Generator,
    density: np.ndarray,
    dry: np.ndarray,
    alpha: np.ndarray | None = None,
) -> None:
    """Splat short grass blades (random directions, seen from above) where ``density`` allows."""
    size = img.shape[0]
    k = int(size * size / 28)
    roots = rng.random((k, 2)) * size
    ri = roots.astype(np.int64) % size
    keep = rng.random(k) < density[ri[:, 1], ri[:, 0]]
    roots, ri = roots[keep], ri[keep]
    ang = rng.uniform(0, 2 * math.pi, len(roots))
    ln = rng.uniform(4.0, 16.0, len(roots)) * size / 1024
    tips = roots + np.stack([np.cos(ang), np.sin(ang)], 1) * ln[:, None]
    hue = np.clip(rng.random(len(roots)) * 0.6 + dry[ri[:, 1], ri[:, 0]] * 0.8 - 0.25, 0.0, 1.0)
    bright = rng.uniform(0.6, 1.25, len(roots))[:, None]
    cols = (_rgb(70, 110, 38) + hue[:, None] * (_rgb(150, 160, 70) - _rgb(70, 110, 38))) * bright
    _splat_lines(img, alpha, roots.astype(np.float32), tips.astype(np.float32), cols.astype(np.float32))


def _stones(
    img: np.ndarray,
    rng: np.random.Generator,
    count: int,
    where: np.ndarray,
    fine: np.ndarray,
    alpha: np.ndarray | None = None,
) -> None:
    """Shaded elliptical pebbles (1.5-8 cm) with contact shadows, placed with probability ``where``."""
    size = img.shape[0]
    centers = rng.random((count * 3, 2)) * size
    ci = centers.astype(np.int64) % size
    centers = centers[rng.random(count * 3) < where[ci[:, 1], ci[:, 0]]][:count]
    ns = len(centers)
    rmax = int(10 * size / 1024)
    radii = rng.uniform(2.0, rmax, (ns, 2)) * np.array([1.0, rng.uniform(0.6, 1.0)])
    rot = rng.uniform(0, math.pi, ns)
    base_col = _rgb(150, 145, 135) * rng.uniform(0.6, 1.2, (ns, 1)) + rng.normal(0, 0.04, (ns, 3))
    oy, ox = np.mgrid[-rmax : rmax + 1, -rmax : rmax + 1]
    dx = ox[None] - (centers[:, 0] % 1)[:, None, None]
    dy = oy[None] - (centers[:, 1] % 1)[:, None, None]
    c, s = np.cos(rot)[:, None, None], np.sin(rot)[:, None, None]
    ex = (c * dx + s * dy) / radii[:, 0, None, None]
    ey = (-s * dx + c * dy) / radii[:, 1, None, None]
    r2 = ex * ex + ey * ey
    inside = r2 < 1.0
    height = np.sqrt(np.clip(1.0 - r2, 0, 1))
    shade = 0.55 + 0.45 * np.clip(height * 0.8 + (-ex - ey) * 0.35, 0, 1.2)
    xs = (np.floor(centers[:, 0]).astype(np.int64)[:, None, None] + ox[None]) % size
    ys = (np.floor(centers[:, 1]).astype(np.int64)[:, None, None] + oy[None]) % size
    grain = fine[ys, xs][..., None] * 0.25 + 0.85
    stone_rgb = base_col[:, None, None, :] * shade[..., None] * grain
    # a dark rim (contact shadow) first, so that neighbouring stones overwrite it
    rim = (r2 >= 1.0) & (r2 < 1.5)
    img[ys[rim], xs[rim]] *= 0.7
    img[ys[inside], xs[inside]] = stone_rgb[inside]
    if alpha is not None:
        alpha[ys[inside], xs[inside]] = 1.0


def ground_texture(size: int = 1024, seed: int = TEXTURE_SEED) -> np.ndarray:
    """Meadow seen from above (tile ~8 m): grass blades over a dark sward, small bare spots, pebbles.

    Its large-scale statistics are uniform on purpose, so the tiling does not show; big bare-soil
    patches are separate, randomly placed ``soil`` decals.
    """
    rng = np.random.default_rng(seed)
    fine = fbm(rng, size, 64, 3)
    soil = _soil(rng, size, fine)
    clump = fbm(rng, size, 16, 5)
    under = _mix(_rgb(48, 62, 30), _rgb(82, 96, 44), clump) * (0.8 + 0.4 * fine)[..., None]
    spots = smoothstep(0.76, 0.84, fbm(rng, size, 12, 4))  # 1 = bare spot, ~10-30 cm across
    img = _mix(under, soil, spots)
    dry = fbm(rng, size, 6, 3)
    _grass_blades(img, rng, 1.0 - 0.9 * spots, dry)
    _stones(img, rng, int(200 * (size / 1024) ** 2), 0.2 + 0.8 * spots, fine)
    return _to_rgba(np.clip(img, 0, 1))


def soil_texture(size: int = 1024, seed: int = TEXTURE_SEED + 8) -> np.ndarray:
    """2 x 2 atlas of bare-soil patch decals: irregular alpha-tested blobs of earth and stones whose
    ragged edges are overgrown with grass blades."""
    rng = np.random.default_rng(seed)
    fine = fbm(rng, size, 64, 3)
    img = _soil(rng, size, fine)
    cell = size // ATLAS_GRID
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32)
    u = (xx % cell) / cell - 0.5
    v = (yy % cell) / cell - 0.5
    r = np.sqrt(u * u + v * v)
    wobble = fbm(rng, size, 8, 5)
    edge_field = r + 0.22 * (wobble - 0.5)
    alpha = (edge_field < 0.32).astype(np.float32)
    ring = smoothstep(0.18, 0.32, edge_field)  # grass creeps in toward the rim
    _grass_blades(img, rng, ring * 0.8, fbm(rng, size, 6, 3), alpha)
    _stones(img, rng, int(320 * (size / 1024) ** 2), alpha * (1.0 - ring), fine, alpha)
    # blades and stones stay near the blob, and nothing reaches the cell border (no atlas bleeding)
    alpha *= ((edge_field < 0.37) & (np.maximum(np.abs(u), np.abs(v)) < 0.47)).astype(np.float32)
    img[alpha < 0.5] = img[alpha > 0.5].mean(axis=0)
    return _to_rgba(np.clip(img, 0, 1), alpha)


def bark_texture(size: int = 512, seed: int = TEXTURE_SEED + 1) -> np.ndarray:
    """Bark: wavy vertical fissures between rough plates, with lichen patches."""
    rng = np.random.default_rng(seed)
    # contour lines of strongly anisotropic noise meander like the fissures of bark
    plates = fbm(rng, size, 3, 5, aniso=(8, 1))
    fissure = smoothstep(0.0, 0.1, np.abs(plates - 0.5))
    fine = fbm(rng, size, 32, 4)
    grain = fbm(rng, size, 8, 4, aniso=(8, 1))
    base = _mix(_rgb(70, 56, 44), _rgb(128, 112, 96), grain)
    img = base * (0.3 + 0.7 * fissure)[..., None] * (0.75 + 0.5 * fine)[..., None]
    lichen = smoothstep(0.78, 0.84, fbm(rng, size, 6, 5)) * fissure
    img = _mix(img, _rgb(130, 140, 105) * (0.7 + 0.5 * fine)[..., None], lichen * 0.6)
    return _to_rgba(np.clip(img, 0, 1))


def wood_texture(size: int = 512, seed: int = TEXTURE_SEED + 2) -> np.ndarray:
    """Weathered wooden post: vertical grain, cracks and a few knots."""
    rng = np.random.default_rng(seed)
    grain = fbm(rng, size, 4, 5, aniso=(10, 1))
    x = np.arange(size, dtype=np.float32)[None, :]
    rings = 0.5 + 0.5 * np.sin(x * (2 * math.pi * 24 / size) + grain * 12.0)
    img = _mix(_rgb(105, 92, 76), _rgb(160, 146, 124), rings * 0.6 + grain * 0.4)
    cracks = smoothstep(0.0, 0.03, np.abs(fbm(rng, size, 2, 4, aniso=(12, 1)) - 0.5))
    img *= (0.45 + 0.55 * cracks)[..., None]
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32)
    for _ in range(5):
        cx, cy = rng.random(2) * size
        rx, ry = rng.uniform(0.02, 0.04) * size, rng.uniform(0.03, 0.06) * size
        dx = (xx - cx + size / 2) % size - size / 2
        dy = (yy - cy + size / 2) % size - size / 2
        r = np.sqrt((dx / rx) ** 2 + (dy / ry) ** 2)
        knot = np.exp(-r * r) * (0.6 + 0.4 * np.cos(r * 9.0))
        img *= (1.0 - 0.55 * knot)[..., None]
    img *= (0.8 + 0.35 * fbm(rng, size, 32, 3))[..., None]
    return _to_rgba(np.clip(img, 0, 1))


def wire_texture(size: int = 64, seed: int = TEXTURE_SEED + 3) -> np.ndarray:
    """Galvanised wire: grey with faint streaks and rust specks."""
    rng = np.random.default_rng(seed)
    n = fbm(rng, size, 4, 3, aniso=(1, 4))
    img = _mix(_rgb(120, 124, 128), _rgb(200, 204, 208), n)
    rust = smoothstep(0.8, 0.9, fbm(rng, size, 8, 3))
    return _to_rgba(np.clip(_mix(img, _rgb(130, 80, 50), rust), 0, 1))


def fruit_texture(size: int = 256, seed: int = TEXTURE_SEED + 4) -> np.ndarray:
    """Apple skin: red blush with yellow-green streaks and pale lenticel dots."""
    rng = np.random.default_rng(seed)
    blush = fbm(rng, size, 2, 4)
    streak = fbm(rng, size, 2, 4, aniso=(8, 1))
    img = _mix(_rgb(200, 190, 70), _rgb(175, 25, 30), smoothstep(0.25, 0.6, blush * 0.6 + streak * 0.4))
    dots = value_noise(rng, size, size // 4) > 0.93
    img[dots] = img[dots] * 0.4 + _rgb(240, 220, 160) * 0.6
    img *= (0.9 + 0.2 * fbm(rng, size, 16, 3))[..., None]
    return _to_rgba(np.clip(img, 0, 1))


def rock_texture(size: int = 512, seed: int = TEXTURE_SEED + 5) -> np.ndarray:
    """Granite-like rock: mottled grey, dark cracks, lichen."""
    rng = np.random.default_rng(seed)
    mott = fbm(rng, size, 4, 6)
    img = _mix(_rgb(95, 95, 100), _rgb(170, 168, 160), mott)
    cracks = smoothstep(0.0, 0.025, np.abs(fbm(rng, size, 3, 5) - 0.5))
    img *= (0.4 + 0.6 * cracks)[..., None]
    speck = value_noise(rng, size, size // 2)
    img *= (0.8 + 0.4 * speck)[..., None]
    lichen = smoothstep(0.72, 0.8, fbm(rng, size, 6, 4))
    return _to_rgba(np.clip(_mix(img, _rgb(160, 165, 90), lichen * 0.7), 0, 1))


# --------------------------------------------------------------------------- leaf atlases
def atlas_rect(index: int | np.ndarray) -> np.ndarray:
    """uv rectangles (u0, v0, u1, v1) of leaf-atlas variants ``index`` (int or (K,) array)."""
    idx = np.asarray(index)
    col, row = idx % ATLAS_GRID, idx // ATLAS_GRID
    s = 1.0 / ATLAS_GRID
    return np.stack([col * s, row * s, (col + 1) * s, (row + 1) * s], -1).astype(np.float64)


def _draw_leaf(
    rgb: np.ndarray,
    alpha: np.ndarray,
    surf: np.ndarray,
    region: tuple[int, int, int, int],
    base: np.ndarray,
    angle: float,
    length: float,
    width: float,
    color: np.ndarray,
    lobed: bool,
) -> None:
    """Paint one leaf (shape, shading, midrib and veins) into its bounding box, clipped to ``region``."""
    x0r, x1r, y0r, y1r = region
    d = np.array([math.cos(angle), math.sin(angle)])
    tip = base + d * length
    if lobed:
        mid = base + d * 0.45 * length
        lo, hi = np.floor(mid - 0.6 * length).astype(int), np.ceil(mid + 0.6 * length).astype(int)
    else:
        lo = np.floor(np.minimum(base, tip) - width / 2).astype(int)
        hi = np.ceil(np.maximum(base, tip) + width / 2).astype(int)
    x0, x1 = max(lo[0], x0r), min(hi[0], x1r)
    y0, y1 = max(lo[1], y0r), min(hi[1], y1r)
    if x1 <= x0 or y1 <= y0:
        return
    # python-float constants keep the per-pixel maths in float32
    dx, dy, bx, by = math.cos(angle), math.sin(angle), float(base[0]), float(base[1])
    px = np.arange(x0, x1, dtype=np.float32)[None, :] + (0.5 - bx)
    py = np.arange(y0, y1, dtype=np.float32)[:, None] + (0.5 - by)
    if lobed:
        # palmate (grape-like) leaf: five lobes around a centre 45 % along the blade
        cx, cy = px - dx * 0.45 * length, py - dy * 0.45 * length
        rho = np.sqrt(cx * cx + cy * cy) * (1.0 / (0.55 * length))
        phi = np.arctan2(cy * dx - cx * dy, cx * dx + cy * dy)
        outline = 0.72 + 0.28 * np.abs(np.cos(2.5 * phi)) ** 0.6
        outline *= 1.0 - 0.45 * np.exp(-((np.abs(phi) - math.pi) ** 2) / 0.08)
        outline *= 1.0 + 0.04 * np.cos(phi * 23.0)  # serrated margin
        inside = rho < outline
        if not inside.any():
            return
        # shading and veins only for the covered pixels (1-D from here on)
        rho, phi, outline = rho[inside], phi[inside], outline[inside]
        # five main veins fan out from the petiole; side veins run obliquely off the nearest one
        delta = phi[:, None] - np.array([0.0, 0.95, -0.95, 1.9, -1.9], dtype=np.float32)
        nearest = np.take_along_axis(delta, np.abs(delta).argmin(-1)[:, None], -1)[:, 0]
        across, along = rho * np.sin(nearest), rho * np.cos(nearest)
        vein = (np.abs(across) < 0.03) | (
            (np.abs(((along * 6.0 - np.abs(across) * 5.0) % 1.0) - 0.5) < 0.05) & (np.abs(across) < 0.3)
        )
        edge = np.clip(rho / outline, 0, 1)
        side = phi > 0
    else:
        s = (px * dx + py * dy) * (1.0 / length)  # along the blade, 0 at the petiole, 1 at the tip
        w = (py * dx - px * dy) * (2.0 / width)  # across, +-1 at the widest point
        sc = np.clip(s, 0.0, 1.0)
        profile = np.maximum(np.sin(math.pi * sc**0.75), 0.0) ** 0.9 * (1.0 + 0.03 * np.sin(s * 60.0))
        inside = (s > 0.0) & (s < 1.0) & (np.abs(w) < profile)
        if not inside.any():
            return
        s, w, profile = s[inside], w[inside], profile[inside]
        vein = (np.abs(w) < 0.07) | (np.abs(((s * 7.0 - np.abs(w) * 1.6) % 1.0) - 0.5) < 0.06)
        edge = np.clip(np.abs(w) / np.maximum(profile, 1e-3), 0, 1)
        side = w > 0
    shade = (0.8 + 0.35 * surf[y0:y1, x0:x1][inside]) * (1.0 - 0.3 * edge**3) * np.where(side, 0.85, 1.0)
    col = color[None, :] * shade[:, None]
    col[vein] = col[vein] * 0.55 + np.array([0.75, 0.8, 0.45], np.float32) * 0.45
    rgb[y0:y1, x0:x1][inside] = col
    alpha[y0:y1, x0:x1][inside] = 1.0


def _leaf_atlas(size: int, seed: int, vine: bool) -> np.ndarray:
    """ATLAS_GRID^2 card variants, each a few twigs fanning from the centre with leaves painted over them."""
    rng = np.random.default_rng(seed)
    rgb = np.zeros((size, size, 3), dtype=np.float32)
    alpha = np.zeros((size, size), dtype=np.float32)
    surf = fbm(rng, size, 32, 4)
    cell = size // ATLAS_GRID
    margin = max(2, cell // 64)
    twig_col = _rgb(95, 70, 45)
    for v in range(ATLAS_GRID * ATLAS_GRID):
        origin = np.array([(v % ATLAS_GRID) * cell, (v // ATLAS_GRID) * cell], dtype=float)
        region = (
            int(origin[0]) + margin,
            int(origin[0]) + cell - margin,
            int(origin[1]) + margin,
            int(origin[1]) + cell - margin,
        )
        sub = (slice(region[2], region[3]), slice(region[0], region[1]))
        leaves: list[tuple[np.ndarray, float, float]] = []  # (cell-local base, angle, scale)
        n_twigs = int(rng.integers(4, 6))
        first = rng.uniform(0, 2 * math.pi)
        for k in range(n_twigs):
            # twigs fan out from near the card centre (cards overlap around branch tips)
            heading = first + 2 * math.pi * k / n_twigs + rng.normal(0, 0.25)
            twig_len = (rng.uniform(0.18, 0.26) if vine else rng.uniform(0.26, 0.34)) * cell
            n_seg = 6
            pts = [(0.5 + rng.normal(0, 0.08, 2)) * cell]
            for _s in range(n_seg):
                heading += rng.normal(0, 0.15)
                pts.append(pts[-1] + twig_len / n_seg * np.array([math.cos(heading), math.sin(heading)]))
            twig = np.clip(np.array(pts) - margin, 0, cell - 2 * margin - 1).astype(np.float32)
            twig_alpha = np.zeros(alpha[sub].shape, dtype=np.float32)
            _splat_lines(
                rgb[sub],
                twig_alpha,
                twig[:-1],
                twig[1:],
                np.tile(twig_col, (n_seg, 1)),
                width=max(2.0, cell / 160),
            )
            alpha[sub] = np.maximum(alpha[sub], twig_alpha)
            per_twig = rng.integers(3, 5) if vine else rng.integers(10, 14)
            for j in range(per_twig):
                t = (j + 0.5) / per_twig * n_seg
                seg = min(int(t), n_seg - 1)
                step = pts[seg + 1] - pts[seg]
                side = 1 if j % 2 == 0 else -1
                ang = math.atan2(step[1], step[0]) + side * rng.uniform(0.5, 1.1)
                leaves.append((pts[seg] + step * (t - seg), ang, rng.uniform(0.8, 1.2)))
        # extra loose leaves fill the card so it reads as foliage, not a diagram of twigs
        for _ in range(rng.integers(3, 6) if vine else rng.integers(20, 28)):
            loose = rng.uniform(0.25, 0.75, 2) * cell
            leaves.append((loose, rng.uniform(0, 2 * math.pi), rng.uniform(0.8, 1.2)))
        for i in rng.permutation(len(leaves)):
            p, ang, scale = leaves[i]
            if vine:
                length = width = 0.26 * cell * scale
                color = _rgb(70, 120, 40) * rng.uniform(0.75, 1.15) + rng.normal(0, 0.03, 3)
            else:
                length, width = 0.16 * cell * scale, 0.07 * cell * scale
                color = _rgb(60, 115, 35) * rng.uniform(0.7, 1.2) + rng.normal(0, 0.03, 3)
            _draw_leaf(
                rgb,
                alpha,
                surf,
                region,
                p + origin,
                ang,
                length,
                width,
                np.clip(color, 0, 1).astype(np.float32),
                vine,
            )
    # texels outside leaves take the mean leaf colour so filtering never bleeds dark fringes
    mean = rgb[alpha > 0.5].mean(axis=0) if (alpha > 0.5).any() else _rgb(60, 100, 40)
    rgb[alpha < 0.5] = mean
    return _to_rgba(np.clip(rgb, 0, 1), alpha)


def leaves_texture(size: int = 1024, seed: int = TEXTURE_SEED + 6) -> np.ndarray:
    """Atlas of fruit-tree leaf cards: twigs with alternate elliptical leaves, alpha 0 between leaves."""
    return _leaf_atlas(size, seed, vine=False)


def vine_leaves_texture(size: int = 1024, seed: int = TEXTURE_SEED + 7) -> np.ndarray:
    """Atlas of grapevine leaf cards: large palmate five-lobed leaves on shoots."""
    return _leaf_atlas(size, seed, vine=True)


_GENERATORS = {
    "ground": ground_texture,
    "bark": bark_texture,
    "leaves": leaves_texture,
    "vine_leaves": vine_leaves_texture,
    "wood": wood_texture,
    "wire": wire_texture,
    "fruit": fruit_texture,
    "rock": rock_texture,
    "soil": soil_texture,
}

#: Every texture name a scene part may reference.
TEXTURE_NAMES: tuple[str, ...] = tuple(_GENERATORS)


@functools.cache
def get_texture(name: str) -> np.ndarray:
    """Cached, read-only texture ``name`` (generated on first use)."""
    if name not in _GENERATORS:
        raise ValueError(f"unknown texture {name!r}; known: {', '.join(TEXTURE_NAMES)}")
    return _GENERATORS[name]()


def textures_for(names: list[str] | set[str]) -> dict[str, np.ndarray]:
    """The cached textures a scene's parts use, keyed by name."""
    return {n: get_texture(n) for n in sorted(set(names))}
