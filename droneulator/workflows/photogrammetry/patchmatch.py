"""PatchMatch refinement of a depth map with a slanted plane per pixel (Gipuma / COLMAP style).

Why: the fronto-parallel plane sweep (:func:`.mvs.plane_sweep`) compares square windows at one depth, so
on a leaf seen at an angle, and at a leaf's edge where the window straddles the leaf behind, the window
matches only in part. Here every pixel carries its own plane (depth and normal in the reference camera
frame); its cost is the sweep's on that plane: at each pixel of a small window the 3x3 NCC with each
neighbour warped by the plane-induced homography, the mean of the best ``best_k`` neighbours (occlusion),
averaged over the window with bilateral support weights (the reference colour and the distance to the
window's centre: the average keeps to the leaf the pixel is on, as the sweep's guided filter does).
One bilateral-weighted NCC over a larger window (Gipuma's cost) was tried first and found less
discriminative on the crown (docs/photogrammetry.md).

Starting from the sweep's depths (fronto-parallel normals), each iteration visits the pixels in a red-black
checkerboard: a pixel tries the planes of nearby pixels of the other colour (propagation: a good plane
spreads along its surface), then random perturbations of its own depth and normal, shrinking from one
iteration to the next, keeping whichever costs least. Only masked pixels are visited, in parallel rows.
Random numbers come from a hash of pixel, iteration and trial, so the result does not depend on the
thread count.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import cv2
import numba
import numpy as np

from droneulator.workflows.photogrammetry.mvs import MvsOptions, View

#: the cost of a neighbour that does not see the whole window (out of frame or behind the camera)
INVALID = 2.0
#: propagation: the other-colour pixels a pixel takes planes from (row, column offsets): the four
#: adjacent ones and four at distance 5, as Gipuma's fast scheme (four more at a knight's move: no gain)
_PROPAGATE = np.array([[-1, 0], [1, 0], [0, -1], [0, 1], [-5, 0], [5, 0], [0, -5], [0, 5]], np.int64)


@dataclass
class PatchMatchResult:
    """Refined depth (m, NaN: none), unit normals in the reference optical frame (H, W, 3; facing the
    camera) and the aggregated NCC of each pixel's plane."""

    depth: np.ndarray
    normal: np.ndarray
    ncc: np.ndarray


@numba.njit(cache=True, inline="always")
def _uniform(a: int, b: int, c: int) -> float:
    """A uniform number in [0, 1) hashed from three integers (splitmix64 finaliser)."""
    x = (a * 0x9E3779B1 + b * 0x85EBCA77 + c * 0xC2B2AE3D + 0x27D4EB2F) & 0xFFFFFFFFFFFFFFFF
    x ^= x >> 30
    x = (x * 0xBF58476D1CE4E5B9) & 0xFFFFFFFFFFFFFFFF
    x ^= x >> 27
    x = (x * 0x94D049BB133111EB) & 0xFFFFFFFFFFFFFFFF
    x ^= x >> 31
    return (x >> 11) * (1.0 / 9007199254740992.0)


@numba.njit(cache=True, parallel=True)
def _support_weights(
    rgb: np.ndarray,
    gray: np.ndarray,
    mask: np.ndarray,
    offsets: np.ndarray,
    sigma_color: float,
    sigma_space: float,
    weights: np.ndarray,
    stats: np.ndarray,
) -> None:
    """Per masked pixel: the bilateral support weight of each window sample (``offsets`` (n, 2) rows,
    columns), exp(-|colour difference|_1 / (3 sigma_color) - distance / sigma_space), and the reference's
    weighted sums (sum w, sum w I, sum w I^2; untextured windows are dropped by them). Samples outside
    the image weigh 0."""
    h, w = gray.shape
    n = offsets.shape[0]
    for r in numba.prange(h):
        for c in range(w):
            if not mask[r, c]:
                continue
            s0 = s1 = s2 = 0.0
            for k in range(n):
                rr, cc = r + offsets[k, 0], c + offsets[k, 1]
                wk = 0.0
                if 0 <= rr < h and 0 <= cc < w:
                    dc = (
                        abs(rgb[rr, cc, 0] - rgb[r, c, 0])
                        + abs(rgb[rr, cc, 1] - rgb[r, c, 1])
                        + abs(rgb[rr, cc, 2] - rgb[r, c, 2])
                    )
                    ds = math.sqrt(offsets[k, 0] ** 2 + offsets[k, 1] ** 2)
                    wk = math.exp(-dc / (3.0 * sigma_color) - ds / sigma_space)
                    g = gray[rr, cc]
                    s0 += wk
                    s1 += wk * g
                    s2 += wk * g * g
                weights[r, c, k] = wk
            stats[r, c, 0] = s0
            stats[r, c, 1] = s1
            stats[r, c, 2] = s2


@numba.njit(cache=True)
def _plane_cost(
    r: int,
    c: int,
    z: float,
    nx: float,
    ny: float,
    nz: float,
    offsets: np.ndarray,
    weights: np.ndarray,
    gray: np.ndarray,
    ref_mu: np.ndarray,
    ref_sd: np.ndarray,
    srcs: np.ndarray,
    A: np.ndarray,
    b: np.ndarray,
    Kinv: np.ndarray,
    best_k: int,
    radius: int,
    patch: np.ndarray,
    cst: np.ndarray,
    scratch: np.ndarray,
) -> float:
    """Like the sweep's cost, on the plane: at every pixel q of the (2 radius + 1)^2 window the 3x3 NCC of
    the reference with each source warped through the plane, the mean of its best ``best_k`` sources,
    averaged over the window with the support weights (``offsets`` within ``radius``; ``patch``,
    ``cst`` and ``scratch`` are the caller's buffers)."""
    h, w = gray.shape
    S, hs, ws = srcs.shape
    rx = Kinv[0, 0] * c + Kinv[0, 1] * r + Kinv[0, 2]
    ry = Kinv[1, 0] * c + Kinv[1, 1] * r + Kinv[1, 2]
    rz = Kinv[2, 0] * c + Kinv[2, 1] * r + Kinv[2, 2]
    rho = z * (nx * rx + ny * ry + nz * rz)
    if rho > -1e-9:
        return INVALID
    m0 = (Kinv[0, 0] * nx + Kinv[1, 0] * ny + Kinv[2, 0] * nz) / rho
    m1 = (Kinv[0, 1] * nx + Kinv[1, 1] * ny + Kinv[2, 1] * nz) / rho
    m2 = (Kinv[0, 2] * nx + Kinv[1, 2] * ny + Kinv[2, 2] * nz) / rho
    P = 2 * radius + 3  # the warped patch: the window and a one-pixel border for the 3x3 NCC
    for s in range(S):
        # warp the patch (NaN: outside the source)
        for i in range(P):
            v = r - radius - 1 + i
            for j in range(P):
                u = c - radius - 1 + j
                d = m0 * u + m1 * v + m2
                X = A[s, 0, 0] * u + A[s, 0, 1] * v + A[s, 0, 2] + b[s, 0] * d
                Y = A[s, 1, 0] * u + A[s, 1, 1] * v + A[s, 1, 2] + b[s, 1] * d
                Z = A[s, 2, 0] * u + A[s, 2, 1] * v + A[s, 2, 2] + b[s, 2] * d
                g = np.nan
                if Z > 1e-9:
                    x = X / Z
                    y = Y / Z
                    if 0.0 <= x < ws - 1 and 0.0 <= y < hs - 1:
                        x0 = int(x)
                        y0 = int(y)
                        fx = x - x0
                        fy = y - y0
                        g = (1.0 - fy) * ((1.0 - fx) * srcs[s, y0, x0] + fx * srcs[s, y0, x0 + 1]) + fy * (
                            (1.0 - fx) * srcs[s, y0 + 1, x0] + fx * srcs[s, y0 + 1, x0 + 1]
                        )
                patch[i, j] = g
        for k in range(offsets.shape[0]):
            if weights[r, c, k] == 0.0:
                continue
            qi = offsets[k, 0] + radius + 1
            qj = offsets[k, 1] + radius + 1
            vr = r + offsets[k, 0]
            ur = c + offsets[k, 1]
            s1 = s2 = rs = 0.0
            for a in range(-1, 2):
                for e in range(-1, 2):
                    g = patch[qi + a, qj + e]
                    s1 += g
                    s2 += g * g
                    rr = min(max(vr + a, 0), h - 1)
                    cc = min(max(ur + e, 0), w - 1)
                    rs += g * gray[rr, cc]
            if math.isnan(s1):  # NaN: part of the 3x3 window outside the source
                cst[k, s] = INVALID
                continue
            mu = s1 / 9.0
            var = s2 / 9.0 - mu * mu
            if var < 1e-5 or ref_sd[vr, ur] <= 0.0:
                cst[k, s] = INVALID
                continue
            cov = rs / 9.0 - ref_mu[vr, ur] * mu
            cst[k, s] = 1.0 - cov / (ref_sd[vr, ur] * math.sqrt(var))
    total = 0.0
    wsum = 0.0
    kk = min(best_k, S)
    for k in range(offsets.shape[0]):
        wk = weights[r, c, k]
        if wk == 0.0:
            continue
        for s in range(S):
            scratch[s] = cst[k, s]
        acc = 0.0
        for j in range(kk):
            best = j
            for i in range(j + 1, S):
                if scratch[i] < scratch[best]:
                    best = i
            tmp = scratch[j]
            scratch[j] = scratch[best]
            scratch[best] = tmp
            acc += scratch[j]
        total += wk * acc / kk
        wsum += wk
    return total / wsum if wsum > 0 else INVALID


@numba.njit(cache=True, inline="always")
def _facing(nx: float, ny: float, nz: float, rx: float, ry: float, rz: float) -> tuple[float, float, float]:
    """The unit normal, flipped to face the camera along the ray (rx, ry, rz)."""
    L = math.sqrt(nx * nx + ny * ny + nz * nz)
    if L < 1e-12:
        return 0.0, 0.0, -1.0
    nx, ny, nz = nx / L, ny / L, nz / L
    if nx * rx + ny * ry + nz * rz > 0:
        return -nx, -ny, -nz
    return nx, ny, nz


@numba.njit(cache=True, parallel=True)
def _patchmatch_pass(
    color: int,
    it: int,
    seed: int,
    depth: np.ndarray,
    normal: np.ndarray,
    cost: np.ndarray,
    mask: np.ndarray,
    offsets: np.ndarray,
    weights: np.ndarray,
    gray: np.ndarray,
    mu: np.ndarray,
    sd: np.ndarray,
    srcs: np.ndarray,
    A: np.ndarray,
    b: np.ndarray,
    Kinv: np.ndarray,
    best_k: int,
    radius: int,
    inv_near: float,
    inv_far: float,
    depth_step: float,
    normal_step: float,
    propagate: np.ndarray,
) -> None:
    """One half-iteration: every masked pixel of checkerboard ``color`` takes the cheapest of its own
    plane, its other-colour neighbours' planes (re-intersected with its own ray) and random perturbations
    (relative depth ``depth_step``, normal ``normal_step``, plus a fresh random depth and normal)."""
    h, w = depth.shape
    S = srcs.shape[0]
    for i in numba.prange(h):
        r = np.int64(i)  # one compiled _plane_cost (tests/test_structure.py)
        scratch = np.empty(S)
        patch = np.empty((2 * radius + 3, 2 * radius + 3))
        cst = np.empty((offsets.shape[0], S))
        for c in range((r + color) % 2, w, 2):
            if not mask[r, c]:
                continue
            rx = Kinv[0, 0] * c + Kinv[0, 1] * r + Kinv[0, 2]
            ry = Kinv[1, 0] * c + Kinv[1, 1] * r + Kinv[1, 2]
            rz = Kinv[2, 0] * c + Kinv[2, 1] * r + Kinv[2, 2]
            bz = depth[r, c]
            bnx, bny, bnz = normal[r, c, 0], normal[r, c, 1], normal[r, c, 2]
            bc = cost[r, c]
            # propagation: a neighbour's plane n . X = rho meets this pixel's ray at rho / (n . ray)
            for k in range(propagate.shape[0]):
                rr, cc = r + propagate[k, 0], c + propagate[k, 1]
                if not (0 <= rr < h and 0 <= cc < w) or not mask[rr, cc]:
                    continue
                zq = depth[rr, cc]
                if not zq > 0:
                    continue
                qx = Kinv[0, 0] * cc + Kinv[0, 1] * rr + Kinv[0, 2]
                qy = Kinv[1, 0] * cc + Kinv[1, 1] * rr + Kinv[1, 2]
                qz = Kinv[2, 0] * cc + Kinv[2, 1] * rr + Kinv[2, 2]
                nx, ny, nz = normal[rr, cc, 0], normal[rr, cc, 1], normal[rr, cc, 2]
                rho = zq * (nx * qx + ny * qy + nz * qz)
                den = nx * rx + ny * ry + nz * rz
                if den > -1e-6:
                    continue
                z = rho / den
                if not (inv_far * 0.9 <= 1.0 / z <= inv_near * 1.1):
                    continue
                x = _plane_cost(
                    r, c, z, nx, ny, nz, offsets, weights, gray, mu, sd, srcs, A, b, Kinv, best_k, radius,
                    patch, cst, scratch,
                )  # fmt: skip
                if x < bc:
                    bc, bz, bnx, bny, bnz = x, z, nx, ny, nz
            # random search: perturb depth, normal, both; and a fresh random plane
            key = (r * w + c) * 64 + it * 8
            for trial in range(4):
                u1 = _uniform(seed, key + trial, 1)
                u2 = _uniform(seed, key + trial, 2)
                u3 = _uniform(seed, key + trial, 3)
                u4 = _uniform(seed, key + trial, 4)
                if trial == 3:
                    z = 1.0 / (inv_far + u1 * (inv_near - inv_far))
                    nx, ny, nz = u2 - 0.5, u3 - 0.5, -u4
                else:
                    z = bz
                    nx, ny, nz = bnx, bny, bnz
                    if trial != 1:
                        z = bz * (1.0 + depth_step * (2.0 * u1 - 1.0))
                    if trial != 0:
                        nx += normal_step * (2.0 * u2 - 1.0)
                        ny += normal_step * (2.0 * u3 - 1.0)
                        nz += normal_step * (2.0 * u4 - 1.0)
                if not (inv_far * 0.9 <= 1.0 / z <= inv_near * 1.1):
                    continue
                nx, ny, nz = _facing(nx, ny, nz, rx, ry, rz)
                # planes seen nearly edge-on are not tried (their windows smear along the ray)
                if -(nx * rx + ny * ry + nz * rz) < 0.2 * math.sqrt(rx * rx + ry * ry + rz * rz):
                    continue
                x = _plane_cost(
                    r, c, z, nx, ny, nz, offsets, weights, gray, mu, sd, srcs, A, b, Kinv, best_k, radius,
                    patch, cst, scratch,
                )  # fmt: skip
                if x < bc:
                    bc, bz, bnx, bny, bnz = x, z, nx, ny, nz
            depth[r, c] = bz
            normal[r, c, 0] = bnx
            normal[r, c, 1] = bny
            normal[r, c, 2] = bnz
            cost[r, c] = bc


@numba.njit(cache=True, parallel=True)
def _initial_cost(
    depth: np.ndarray,
    normal: np.ndarray,
    cost: np.ndarray,
    mask: np.ndarray,
    offsets: np.ndarray,
    weights: np.ndarray,
    gray: np.ndarray,
    mu: np.ndarray,
    sd: np.ndarray,
    srcs: np.ndarray,
    A: np.ndarray,
    b: np.ndarray,
    Kinv: np.ndarray,
    best_k: int,
    radius: int,
) -> None:
    """The cost of every masked pixel's starting plane."""
    h, w = depth.shape
    for i in numba.prange(h):
        r = np.int64(i)  # one compiled _plane_cost (tests/test_structure.py)
        scratch = np.empty(srcs.shape[0])
        patch = np.empty((2 * radius + 3, 2 * radius + 3))
        cst = np.empty((offsets.shape[0], srcs.shape[0]))
        for c in range(w):
            if mask[r, c]:
                cost[r, c] = _plane_cost(
                    r, c, depth[r, c], normal[r, c, 0], normal[r, c, 1], normal[r, c, 2], offsets, weights,
                    gray, mu, sd, srcs, A, b, Kinv, best_k, radius, patch, cst, scratch,
                )  # fmt: skip


def window_offsets(radius: int, step: int) -> np.ndarray:
    """Row and column offsets (n, 2) of a (2 radius + 1)^2 window sampled every ``step`` pixels (always
    holding its centre)."""
    k = np.arange(-(radius // step) * step, radius + 1, step)
    rr, cc = np.meshgrid(k, k, indexing="ij")
    return np.column_stack([rr.ravel(), cc.ravel()]).astype(np.int64)


def patchmatch_refine(
    ref: View,
    sources: list[View],
    seed_depth: np.ndarray,
    near: float,
    far: float,
    *,
    iterations: int = 2,
    radius: int = 2,
    step: int = 1,
    sigma_color: float = 0.05,
    sigma_space: float = 5.0,
    best_k: int = 2,
    min_ncc: float = 0.3,
    seed: int = 0,
) -> PatchMatchResult:
    """Slanted-plane PatchMatch on the masked pixels of ``ref`` against ``sources`` (same image size),
    starting from ``seed_depth`` (NaN: a random depth in [near, far]) with fronto-parallel normals.
    Pixels whose final aggregated NCC is below ``min_ncc`` get no depth."""
    if not 0 < near < far:
        raise ValueError(f"patchmatch needs 0 < near < far, got {near}, {far}")
    if not sources or any(s.shape != ref.shape for s in sources):
        raise ValueError(f"{ref.name}: patchmatch needs source views of the reference's size")
    h, w = ref.shape
    mask = np.ascontiguousarray(ref.mask)
    offsets = window_offsets(radius, step)
    gray = np.ascontiguousarray(ref.gray, dtype=np.float32)
    rgb = np.ascontiguousarray(ref.rgb, dtype=np.float32) / 255.0
    weights = np.zeros((h, w, len(offsets)), np.float32)
    stats = np.zeros((h, w, 3), np.float64)
    _support_weights(rgb, gray, mask, offsets, sigma_color, sigma_space, weights, stats)
    # the reference's 3x3 mean and standard deviation (0 where untextured: no NCC there)
    mu = cv2.boxFilter(gray, -1, (3, 3), borderType=cv2.BORDER_REPLICATE).astype(np.float64)
    var = cv2.boxFilter(gray * gray, -1, (3, 3), borderType=cv2.BORDER_REPLICATE) - mu * mu
    sd = np.where(var > 1e-5, np.sqrt(np.maximum(var, 0.0)), 0.0)
    srcs = np.ascontiguousarray(np.stack([s.gray for s in sources]), dtype=np.float32)
    Kinv = np.linalg.inv(ref.K)
    A = np.empty((len(sources), 3, 3))
    b = np.empty((len(sources), 3))
    for i, s in enumerate(sources):
        T = np.linalg.inv(s.T_world_cam) @ ref.T_world_cam  # reference optical -> source optical
        A[i] = s.K @ T[:3, :3]
        b[i] = s.K @ T[:3, 3]
    # the homography of the plane n . X = rho is K_s R K^-1 + K_s t (K^-T n / rho)^T: A and b here
    A = A @ Kinv
    inv_near, inv_far = 1.0 / near, 1.0 / far
    depth = np.asarray(seed_depth, dtype=np.float64).copy()
    missing = ~(np.isfinite(depth) & (depth > 0))
    if missing.any():
        u = np.random.default_rng(seed).random(int(missing.sum()))
        depth[missing] = 1.0 / (inv_far + u * (inv_near - inv_far))
    normal = np.zeros((h, w, 3))
    normal[..., 2] = -1.0
    cost = np.full((h, w), INVALID)
    k = min(best_k, len(sources))
    _initial_cost(depth, normal, cost, mask, offsets, weights, gray, mu, sd, srcs, A, b, Kinv, k, radius)
    for it in range(iterations):
        depth_step = 0.05 * 0.5**it
        normal_step = 0.5 * 0.5**it
        for color in (0, 1):
            _patchmatch_pass(
                color, 2 * it + color, seed, depth, normal, cost, mask, offsets, weights, gray, mu, sd,
                srcs, A, b, Kinv, k, radius, inv_near, inv_far, depth_step, normal_step, _PROPAGATE,
            )  # fmt: skip
    ncc = (1.0 - cost).astype(np.float32)
    textured = stats[..., 0] * stats[..., 2] - stats[..., 1] ** 2 > 1e-5 * stats[..., 0] ** 2
    ok = mask & textured & (ncc >= min_ncc)
    out = np.where(ok, depth, np.nan).astype(np.float32)
    return PatchMatchResult(out, normal.astype(np.float32), ncc)


def patchmatch_settings(opts: MvsOptions) -> dict[str, Any]:
    """The keyword arguments of :func:`patchmatch_refine` that ``opts`` sets."""
    return {
        "iterations": opts.patchmatch_iterations,
        "radius": opts.patchmatch_radius,
        "sigma_color": opts.patchmatch_sigma_color,
        "sigma_space": opts.patchmatch_sigma_space,
        "best_k": opts.best_k,
        "min_ncc": opts.min_ncc,
    }
