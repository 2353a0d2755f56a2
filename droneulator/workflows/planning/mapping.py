"""Rolling local occupancy map from depth images: numba ray casting, log-odds, incremental inflation.

The job of EGO-Planner's grid map: each sampled depth pixel is back-projected with ``K`` and the
camera's optical-frame pose, its end voxel gets a hit (or, for NaN / out of range, the ray runs to
``max_ray_length`` and ends free) and every voxel before it a miss, each voxel at most once per
image (hits win). Log-odds are clamped so the map can change its mind. A per-voxel counter of the
occupied voxels within the inflation radius is kept up to date whenever a voxel changes state, so
the inflated occupancy the planner needs costs nothing extra per query. The grid is a fixed array
centred on the vehicle; when the vehicle moves off-centre, the overlap is copied into a shifted
array and the rest starts unknown (log-odds 0, treated as free).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from droneulator import frames
from droneulator.workflows.planning.config import PlannerConfig, logit


@numba.njit(cache=True, nogil=True)
def _inflate(count: np.ndarray, i: int, j: int, k: int, offsets: np.ndarray, delta: int) -> None:
    nx, ny, nz = count.shape
    for n in range(offsets.shape[0]):
        a, b, c = i + offsets[n, 0], j + offsets[n, 1], k + offsets[n, 2]
        if 0 <= a < nx and 0 <= b < ny and 0 <= c < nz:
            count[a, b, c] += delta


@numba.njit(cache=True, nogil=True)
def _update(
    logodds: np.ndarray,
    count: np.ndarray,
    stamp: np.ndarray,
    frame: int,
    depth: np.ndarray,
    skip: int,
    K: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    origin: np.ndarray,
    res: float,
    min_depth: float,
    max_ray: float,
    l_hit: float,
    l_miss: float,
    l_min: float,
    l_max: float,
    l_occ: float,
    offsets: np.ndarray,
) -> int:
    """Integrate one depth image; returns the number of voxel updates."""
    nx, ny, nz = logodds.shape
    hit_id = 2 * frame
    miss_id = 2 * frame + 1
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    H, W = depth.shape
    ox = (t[0] - origin[0]) / res
    oy = (t[1] - origin[1]) / res
    oz = (t[2] - origin[2]) / res
    updates = 0
    if not (0.0 <= ox < nx and 0.0 <= oy < ny and 0.0 <= oz < nz):
        return -1
    for pass_ in range(2):  # hits first, so a voxel hit by one pixel is never cleared by another's ray
        for v in range(0, H, skip):
            for u in range(0, W, skip):
                d = depth[v, u]
                hit = True
                if d != d or d > max_ray:  # NaN: no return
                    hit = False
                elif d < min_depth:
                    continue
                xo = (u - cx) / fx
                yo = (v - cy) / fy
                # ray direction in the world, scaled to optical z = 1
                dx = R[0, 0] * xo + R[0, 1] * yo + R[0, 2]
                dy = R[1, 0] * xo + R[1, 1] * yo + R[1, 2]
                dz = R[2, 0] * xo + R[2, 1] * yo + R[2, 2]
                norm = math.sqrt(dx * dx + dy * dy + dz * dz)
                if hit:
                    length = d * norm
                    if length > max_ray:
                        hit = False
                        length = max_ray
                else:
                    length = max_ray
                ex = ox + dx / norm * length / res
                ey = oy + dy / norm * length / res
                ez = oz + dz / norm * length / res
                ei, ej, ek = int(math.floor(ex)), int(math.floor(ey)), int(math.floor(ez))
                if pass_ == 0:
                    if hit and 0 <= ei < nx and 0 <= ej < ny and 0 <= ek < nz and stamp[ei, ej, ek] != hit_id:
                        stamp[ei, ej, ek] = hit_id
                        old = logodds[ei, ej, ek]
                        new = min(old + l_hit, l_max)
                        logodds[ei, ej, ek] = new
                        updates += 1
                        if old <= l_occ < new:
                            _inflate(count, ei, ej, ek, offsets, 1)
                    continue
                # pass 1: Amanatides-Woo traversal from the camera voxel to (excluding) the end voxel
                i, j, k = int(math.floor(ox)), int(math.floor(oy)), int(math.floor(oz))
                rx, ry, rz = ex - ox, ey - oy, ez - oz
                sx = 1 if rx > 0 else -1
                sy = 1 if ry > 0 else -1
                sz = 1 if rz > 0 else -1
                big = 1e30
                tdx = abs(1.0 / rx) if rx != 0 else big
                tdy = abs(1.0 / ry) if ry != 0 else big
                tdz = abs(1.0 / rz) if rz != 0 else big
                tmx = ((i + 1 - ox) if rx > 0 else (ox - i)) * tdx if rx != 0 else big
                tmy = ((j + 1 - oy) if ry > 0 else (oy - j)) * tdy if ry != 0 else big
                tmz = ((k + 1 - oz) if rz > 0 else (oz - k)) * tdz if rz != 0 else big
                while True:
                    if i == ei and j == ej and k == ek:
                        break
                    if not (0 <= i < nx and 0 <= j < ny and 0 <= k < nz):
                        break
                    s = stamp[i, j, k]
                    if s != hit_id and s != miss_id:
                        stamp[i, j, k] = miss_id
                        old = logodds[i, j, k]
                        new = max(old + l_miss, l_min)
                        logodds[i, j, k] = new
                        updates += 1
                        if new <= l_occ < old:
                            _inflate(count, i, j, k, offsets, -1)
                    if tmx < tmy and tmx < tmz:
                        if tmx > 1.0:
                            break
                        i += sx
                        tmx += tdx
                    elif tmy < tmz:
                        if tmy > 1.0:
                            break
                        j += sy
                        tmy += tdy
                    else:
                        if tmz > 1.0:
                            break
                        k += sz
                        tmz += tdz
    return updates


@numba.njit(cache=True, nogil=True)
def _rebuild_inflation(logodds: np.ndarray, count: np.ndarray, l_occ: float, offsets: np.ndarray) -> None:
    count[:] = 0
    nx, ny, nz = logodds.shape
    for i in range(nx):
        for j in range(ny):
            for k in range(nz):
                if logodds[i, j, k] > l_occ:
                    _inflate(count, i, j, k, offsets, 1)


_NEIGHBOURS = np.mgrid[-1:2, -1:2, -1:2].reshape(3, -1).T


def sphere_offsets(radius_voxels: float) -> np.ndarray:
    """Integer offsets of the voxels whose centres lie within ``radius_voxels`` of a voxel's centre."""
    r = int(math.ceil(radius_voxels))
    g = np.mgrid[-r : r + 1, -r : r + 1, -r : r + 1].reshape(3, -1).T
    return np.ascontiguousarray(g[(g**2).sum(1) <= radius_voxels**2 + 1e-9], dtype=np.int64)


class LocalMap:
    """A vehicle-centred voxel grid of clamped log-odds with an inflated occupancy for planning."""

    def __init__(self, config: PlannerConfig, centre: np.ndarray | None = None) -> None:
        self.cfg = config
        self.res = config.resolution
        self.shape = tuple(int(round(s / self.res)) for s in config.map_size)
        self.l_hit, self.l_miss = logit(config.p_hit), logit(config.p_miss)
        self.l_min, self.l_max = logit(config.p_min), logit(config.p_max)
        self.l_occ = logit(config.p_occupied)
        self.offsets = sphere_offsets(config.obstacle_inflation / self.res)
        self.logodds = np.zeros(self.shape, dtype=np.float32)
        self.count = np.zeros(self.shape, dtype=np.int32)
        self.stamp = np.zeros(self.shape, dtype=np.int32)
        self.frame = 0
        self.origin_index = np.zeros(3, dtype=np.int64)
        self.recenter(np.zeros(3) if centre is None else centre, force=True)

    # ----------------------------------------------------------------------------- geometry
    @property
    def origin(self) -> np.ndarray:
        """World position of the grid's minimum corner."""
        return self.origin_index * self.res

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """World (min, max) corners of the grid."""
        return self.origin, self.origin + np.array(self.shape) * self.res

    @property
    def centre(self) -> np.ndarray:
        lo, hi = self.bounds
        return 0.5 * (lo + hi)

    def index(self, p: np.ndarray) -> np.ndarray:
        """Grid index (int, may be out of range) of world point(s) ``p``."""
        return np.floor((np.asarray(p, dtype=float) - self.origin) / self.res).astype(np.int64)

    def point(self, idx: np.ndarray) -> np.ndarray:
        """World centre of grid index(es) ``idx``."""
        return self.origin + (np.asarray(idx, dtype=float) + 0.5) * self.res

    def inside(self, p: np.ndarray) -> np.ndarray:
        idx = self.index(p)
        return np.all((idx >= 0) & (idx < np.array(self.shape)), axis=-1)

    # ----------------------------------------------------------------------------- updates
    def recenter(self, centre: np.ndarray, force: bool = False) -> bool:
        """Scroll the grid so ``centre`` is in its middle, when it drifted past ``recenter_distance``."""
        centre = np.asarray(centre, dtype=float)
        if not force and np.all(np.abs(centre - self.centre) <= self.cfg.recenter_distance):
            return False
        new_origin = np.floor(centre / self.res).astype(np.int64) - np.array(self.shape) // 2
        shift = new_origin - self.origin_index
        shape = np.array(self.shape)
        logodds = np.zeros(self.shape, dtype=np.float32)
        src = tuple(slice(max(s, 0), n + min(s, 0)) for s, n in zip(shift, shape, strict=True))
        dst = tuple(slice(max(-s, 0), n - max(s, 0)) for s, n in zip(shift, shape, strict=True))
        if np.all(np.abs(shift) < shape):
            logodds[dst] = self.logodds[src]
        self.logodds = logodds
        self.origin_index = new_origin
        self._rebuild()
        return True

    def set_tracking_margin(self, margin: float) -> None:
        """Grow the mapped obstacles by ``margin`` beyond ``inflation`` (``cfg.tracking_margin``) and
        recount the inflation; the virtual ceiling and floor keep theirs."""
        if margin < 0:
            raise ValueError(f"tracking margin must be >= 0, got {margin}")
        self.cfg.tracking_margin = float(margin)
        self.offsets = sphere_offsets(self.cfg.obstacle_inflation / self.res)
        self._rebuild()

    def _rebuild(self) -> None:
        """Recount the inflation from the log-odds, then block the layers beyond the ceiling and floor."""
        _rebuild_inflation(self.logodds, self.count, self.l_occ, self.offsets)
        z = self.origin[2] + (np.arange(self.shape[2]) + 0.5) * self.res
        virtual = np.zeros(self.shape[2], dtype=bool)
        if self.cfg.ceiling is not None:
            virtual |= z > self.cfg.ceiling - self.cfg.inflation
        if self.cfg.floor is not None:
            virtual |= z < self.cfg.floor + self.cfg.inflation
        self.count[:, :, virtual] += 1

    def update(self, depth: np.ndarray, T_world_optical: np.ndarray, K: np.ndarray) -> int:
        """Integrate one 32FC1 depth image (metres, NaN = no return) seen from ``T_world_optical``.

        Returns the number of voxel updates. The grid scrolls first when the camera has moved.
        """
        depth = np.asarray(depth)
        if depth.ndim != 2 or depth.dtype != np.float32:
            raise ValueError(f"depth must be a 2-D float32 image in metres, got {depth.dtype} {depth.shape}")
        T = np.asarray(T_world_optical, dtype=float)
        K = np.asarray(K, dtype=float)
        if T.shape != (4, 4) or K.shape != (3, 3):
            raise ValueError("T_world_optical must be 4x4 and K 3x3")
        cam, _ = frames.pose_from_transform(T)
        self.recenter(cam)
        self.frame += 1
        n = _update(
            self.logodds, self.count, self.stamp, self.frame, depth, self.cfg.pixel_skip, K,
            np.ascontiguousarray(T[:3, :3]), np.ascontiguousarray(T[:3, 3]), self.origin.astype(float),
            self.res, self.cfg.min_depth, self.cfg.max_ray_length,
            self.l_hit, self.l_miss, self.l_min, self.l_max, self.l_occ, self.offsets,
        )  # fmt: skip
        if n < 0:
            raise ValueError(f"camera at {cam} is outside the local map {self.bounds}")
        return n

    def insert_points(self, points: np.ndarray) -> None:
        """Mark world points (e.g. a point cloud or a known obstacle) as certainly occupied."""
        idx = self.index(np.atleast_2d(points))
        idx = idx[np.all((idx >= 0) & (idx < np.array(self.shape)), axis=1)]
        self.logodds[idx[:, 0], idx[:, 1], idx[:, 2]] = self.l_max
        self._rebuild()

    # ----------------------------------------------------------------------------- queries
    def occupied_grid(self) -> np.ndarray:
        """Boolean array of occupied voxels (no inflation)."""
        return self.logodds > self.l_occ

    def inflated_grid(self) -> np.ndarray:
        """Boolean array of voxels within the inflation radius of an occupied voxel."""
        return self.count > 0

    def nearest_free(self, idx: np.ndarray, radius: float = 1.0) -> np.ndarray | None:
        """The free (not inflated) voxel nearest to grid index ``idx`` within ``radius`` metres, or None."""
        r = int(math.ceil(radius / self.res))
        lo = np.maximum(np.asarray(idx) - r, 0)
        hi = np.minimum(np.asarray(idx) + r + 1, self.shape)
        free = np.argwhere(self.count[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]] == 0) + lo
        if len(free) == 0:
            return None
        d2 = ((free - idx) ** 2).sum(1)
        best = int(np.argmin(d2))
        return free[best] if d2[best] <= r * r else None

    def seen_free(self, idx: np.ndarray) -> np.ndarray:
        """For grid indices (N, 3): has a depth ray crossed the voxel or one of its 26 neighbours?
        (Rays of every n-th pixel fan out and skip voxels between them at range.)"""
        idx = np.asarray(idx, dtype=np.int64).reshape(-1, 3)
        out = np.zeros(len(idx), dtype=bool)
        for off in _NEIGHBOURS:
            j = idx + off
            ok = np.all((j >= 0) & (j < np.array(self.shape)), axis=1)
            out[ok] |= self.logodds[j[ok, 0], j[ok, 1], j[ok, 2]] < 0.0
        return out

    def is_occupied(self, p: np.ndarray, inflated: bool = True) -> np.ndarray:
        """Occupancy of world point(s) ``p``; outside the grid counts as free (unknown)."""
        idx = np.atleast_2d(self.index(p))
        ok = np.all((idx >= 0) & (idx < np.array(self.shape)), axis=1)
        out = np.zeros(len(idx), dtype=bool)
        i = idx[ok]
        grid = self.count if inflated else self.logodds
        vals = grid[i[:, 0], i[:, 1], i[:, 2]]
        out[ok] = vals > 0 if inflated else vals > self.l_occ
        return out if np.ndim(p) > 1 else out[0]
