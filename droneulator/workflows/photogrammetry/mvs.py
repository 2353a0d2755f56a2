"""Multi-view stereo on a CPU: one depth map per reference view by plane sweeping its neighbours.

Why a plane sweep: every step is a whole-image OpenCV call (``warpPerspective``, ``boxFilter``) that
runs at memory speed on one core, the result is deterministic, and with poses known (the sparse
model after bundle adjustment with pose priors) it needs no rectification, so a ring's wide
baselines (20 to 40 degrees between neighbours) work as well as narrow ones.

For a reference view and a depth range (from the sparse points it sees), ``planes`` fronto-parallel
planes are spaced evenly in inverse depth. For each plane every neighbour is warped into the
reference view by the plane's homography and compared with it by normalised cross-correlation over
a small ``window`` x ``window`` patch (gain and offset invariant: the sun lights each side differently).
A pixel's cost at a plane is the mean of its best ``best_k`` neighbours' ``1 - NCC`` (a neighbour
that does not see the point, occluded or out of frame, is left out), aggregated by a guided filter
with the reference image as guide (He et al.'s edge-preserving filter, used for stereo cost volumes by
Hosni et al.): in a crown nearly every 9x9 window straddles leaves at different depths, and a box
window then picks the depth of the dominant leaf for its neighbours too. The winning plane is refined
to a fraction of a plane by a parabola through its two neighbours' costs, and pixels whose NCC is
below ``min_ncc`` or whose minimum sits at the end of the range are dropped. Geometric consistency
across views is checked afterwards, in :mod:`.fusion`.

Neighbours are chosen as COLMAP does, from the sparse model: the views that share the most sparse
points with the reference, each shared point weighted down when its triangulation angle is small.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numba
import numpy as np


@dataclass
class MvsOptions:
    """Plane-sweep stereo settings (``reconstruct --set``-style names in the report)."""

    #: images are resampled by this factor before stereo (0.75: a 1024x768 capture runs at 768x576); at
    #: 54 views 0.75 covers 83.8 % of the seen tree surface against 77.1 % at 0.5, in 540 s against 221 s
    #: (docs/photogrammetry.md)
    scale: float = 0.75
    #: neighbours warped into each reference view
    neighbors: int = 5
    #: depth hypotheses per reference view, evenly spaced in inverse depth
    planes: int = 160
    #: side of the NCC window, pixels (odd): small, since the guided filter does the aggregating
    window: int = 3
    #: a pixel's cost at a plane is the mean over its best best_k neighbours
    best_k: int = 2
    #: pixels whose aggregated NCC is below this are dropped
    min_ncc: float = 0.3
    #: neighbours whose triangulation angle with the reference is below this are weighted down, degrees
    min_angle_deg: float = 5.0
    #: neighbours seen at a wider angle than this are not used, degrees
    max_angle_deg: float = 50.0
    #: the sparse depths of a view (1st and 99th percentile) are widened by this fraction
    depth_margin: float = 0.15
    #: only sparse points within this factor of the view's median sparse depth set its depth range (the
    #: tree mask also covers the distant trees behind the subject, which would spread the planes over
    #: 2 to 48 m instead of 2 to 10); 0: all of them
    subject_depth_factor: float = 2.0
    #: radius of the guided filter (guide: the reference image) that aggregates each plane's cost, pixels;
    #: 0: off (the NCC window alone). Edge-aware: the window follows the leaf a pixel is on instead of
    #: straddling the leaves behind it
    guided_radius: int = 2
    #: regularisation of the guided filter (grey levels in [0, 1], squared): edges weaker than about
    #: its square root are smoothed over
    guided_eps: float = 1e-4
    #: depth hypotheses kept per pixel: the winning plane and the next best local minima of the
    #: aggregated cost (a leaf in front of a leaf leaves two minima; fusion tries the others when the
    #: winner finds no agreeing view); 1: the winner only
    candidates: int = 1
    #: second pass with geometric consistency (COLMAP's geom_consistency): each neighbour's cost at a
    #: plane adds geom_weight * min(forward-backward reprojection error through that neighbour's
    #: first-pass depth map, geom_max_px); 0: one photometric pass
    geom_weight: float = 0.0
    #: the reprojection error is capped at this, pixels
    geom_max_px: float = 3.0
    #: PatchMatch iterations refining the sweep's depths with a slanted plane per pixel
    #: (:mod:`.patchmatch`); 0: off
    patchmatch_iterations: int = 0
    #: PatchMatch window radius, pixels: the 3x3 NCC costs over it are averaged with support weights
    patchmatch_radius: int = 2
    #: PatchMatch support weights: exp(-mean RGB difference (0 to 1) / sigma_color - distance / sigma_space)
    patchmatch_sigma_color: float = 0.05
    patchmatch_sigma_space: float = 5.0

    def __post_init__(self) -> None:
        if not 0.1 <= self.scale <= 1.0:
            raise ValueError(f"mvs scale must lie in [0.1, 1], got {self.scale}")
        if self.window < 3 or self.window % 2 == 0:
            raise ValueError(f"mvs window must be an odd number >= 3, got {self.window}")
        if self.neighbors < 1 or not 1 <= self.best_k <= self.neighbors:
            raise ValueError("mvs needs neighbors >= 1 and 1 <= best_k <= neighbors")
        if self.planes < 8:
            raise ValueError(f"mvs needs at least 8 depth planes, got {self.planes}")
        if self.subject_depth_factor != 0 and not self.subject_depth_factor > 1:
            raise ValueError(f"mvs subject_depth_factor must be 0 or > 1, got {self.subject_depth_factor}")
        if self.guided_radius < 0 or not self.guided_eps > 0:
            raise ValueError("mvs needs guided_radius >= 0 and guided_eps > 0")
        if not -1.0 <= self.min_ncc < 1.0:
            raise ValueError(f"mvs min_ncc must lie in [-1, 1), got {self.min_ncc}")
        if self.geom_weight < 0 or not self.geom_max_px > 0:
            raise ValueError("mvs needs geom_weight >= 0 and geom_max_px > 0")
        if self.candidates < 1:
            raise ValueError(f"mvs candidates must be >= 1, got {self.candidates}")
        if self.patchmatch_iterations < 0 or self.patchmatch_radius < 1:
            raise ValueError("mvs needs patchmatch_iterations >= 0 and patchmatch_radius >= 1")
        if not (self.patchmatch_sigma_color > 0 and self.patchmatch_sigma_space > 0):
            raise ValueError("mvs needs patchmatch_sigma_color > 0 and patchmatch_sigma_space > 0")


@dataclass
class View:
    """One calibrated image: OpenCV K (pixel centres at integers), ``T_world_cam`` (optical frame, x
    right, y down, z forward), grey levels (H, W) float32 in [0, 1], colour (H, W, 3) uint8 RGB and the
    pixels to reconstruct (H, W) bool."""

    name: str
    K: np.ndarray
    T_world_cam: np.ndarray
    gray: np.ndarray
    rgb: np.ndarray
    mask: np.ndarray

    @property
    def center(self) -> np.ndarray:
        return self.T_world_cam[:3, 3]

    @property
    def shape(self) -> tuple[int, int]:
        return self.gray.shape[:2]

    @property
    def inside(self) -> np.ndarray:
        """Ones over the image (float32): warped like the image, it marks where a warp sampled inside."""
        return np.ones(self.shape, np.float32)

    def scaled(self, s: float) -> View:
        """This view resampled by ``s`` (K follows the OpenCV pixel-centre convention)."""
        if s == 1.0:
            return self
        h, w = self.shape
        size = (max(1, round(w * s)), max(1, round(h * s)))
        sx, sy = size[0] / w, size[1] / h
        K = self.K.copy()
        K[0] *= sx
        K[1] *= sy
        K[0, 2] = (self.K[0, 2] + 0.5) * sx - 0.5
        K[1, 2] = (self.K[1, 2] + 0.5) * sy - 0.5
        return View(
            self.name,
            K,
            self.T_world_cam,
            cv2.resize(self.gray, size, interpolation=cv2.INTER_AREA),
            cv2.resize(self.rgb, size, interpolation=cv2.INTER_AREA),
            cv2.resize(self.mask.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0,
        )


def load_view(
    name: str, image_path: str, K: np.ndarray, T_world_cam: np.ndarray, mask: np.ndarray | None
) -> View:
    """A view from an image file (colour, any format OpenCV reads) and an optional mask."""
    bgr = cv2.imread(str(image_path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise FileNotFoundError(f"cannot read image {image_path}")
    rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    gray = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY).astype(np.float32) / 255.0
    if mask is None:
        mask = np.ones(gray.shape, dtype=bool)
    elif mask.shape != gray.shape:
        raise ValueError(f"{name}: mask {mask.shape} and image {gray.shape} differ in size")
    return View(name, np.asarray(K, dtype=float), np.asarray(T_world_cam, dtype=float), gray, rgb, mask)


# --------------------------------------------------------------------------- view selection
def triangulation_angles(points: np.ndarray, c1: np.ndarray, c2: np.ndarray) -> np.ndarray:
    """Angle (rad) at each point (n, 3) between the rays to the camera centres ``c1`` and ``c2``."""
    a, b = c1 - points, c2 - points
    cos = np.einsum("ij,ij->i", a, b) / np.maximum(
        np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1), 1e-12
    )
    return np.arccos(np.clip(cos, -1.0, 1.0))


def select_neighbors(
    centers: np.ndarray,
    observed: list[np.ndarray],
    points: np.ndarray,
    opts: MvsOptions,
    count: int | None = None,
) -> list[list[int]]:
    """For each view, the ``count`` (default ``opts.neighbors``) other views that share the most sparse
    points with it, each shared point weighted by ``min(1, angle / min_angle)²`` and points seen at more
    than ``max_angle`` left out. ``observed[i]``: indices into ``points`` (n, 3) that view ``i`` sees."""
    count = opts.neighbors if count is None else count
    n = len(centers)
    sets = [np.unique(o) for o in observed]
    lo, hi = math.radians(opts.min_angle_deg), math.radians(opts.max_angle_deg)
    score = np.zeros((n, n))
    for i in range(n):
        for j in range(i + 1, n):
            shared = np.intersect1d(sets[i], sets[j], assume_unique=True)
            if not len(shared):
                continue
            ang = triangulation_angles(points[shared], centers[i], centers[j])
            w = np.where(ang > hi, 0.0, np.minimum(1.0, ang / lo) ** 2)
            score[i, j] = score[j, i] = float(w.sum())
    out = []
    for i in range(n):
        order = [int(j) for j in np.argsort(-score[i], kind="stable") if j != i and score[i, j] > 0]
        out.append(order[:count])
    return out


def geometric_neighbors(
    views: list[View], scene_points: list[np.ndarray | None], opts: MvsOptions
) -> list[list[int]]:
    """Neighbours from the camera geometry alone, for views that share too few sparse points: the other
    views whose rays to the view's scene centre (``scene_points[i]``, e.g. the median of the sparse
    points in its frustum) meet at an angle within [min_angle, max_angle], closest to 15 degrees first."""
    lo, hi = math.radians(opts.min_angle_deg), math.radians(opts.max_angle_deg)
    out = []
    for i, p in enumerate(scene_points):
        if p is None:
            out.append([])
            continue
        cand = []
        for j, v in enumerate(views):
            if j == i:
                continue
            a = float(triangulation_angles(p[None, :], views[i].center, v.center)[0])
            if lo <= a <= hi:
                cand.append((abs(a - math.radians(15.0)), j))
        out.append([j for _, j in sorted(cand)])
    return out


def in_frustum(view: View, points: np.ndarray) -> np.ndarray:
    """The points (n, 3) that project inside ``view``'s image, in front of it."""
    uv, z = project(view, points)
    h, w = view.shape
    with np.errstate(invalid="ignore"):
        ok = (z > 1e-3) & (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)
    return points[ok]


def depth_range(
    view: View, points: np.ndarray, margin: float, subject_factor: float = 0.0
) -> tuple[float, float] | None:
    """Depth range of ``points`` (n, 3) in ``view`` (1st to 99th percentile, widened by ``margin``);
    None when fewer than 10 of them lie in front of it. With ``subject_factor`` > 1 only the points
    within that factor of their median depth count: the subject, not the background behind it."""
    T_cam_world = np.linalg.inv(view.T_world_cam)
    z = points @ T_cam_world[2, :3] + T_cam_world[2, 3]
    z = z[z > 1e-3]
    if len(z) >= 10 and subject_factor > 1.0:
        med = float(np.median(z))
        z = z[(z >= med / subject_factor) & (z <= med * subject_factor)]
    if len(z) < 10:
        return None
    lo, hi = np.percentile(z, [1, 99])
    return float(lo * (1 - margin)), float(hi * (1 + margin))


# --------------------------------------------------------------------------- plane sweep
def plane_homography(ref: View, src: View, depth: float) -> np.ndarray:
    """Homography taking reference pixels to source pixels through the fronto-parallel plane z = depth
    of the reference camera."""
    T = np.linalg.inv(src.T_world_cam) @ ref.T_world_cam  # reference optical frame -> source optical
    R, t = T[:3, :3], T[:3, 3]
    n = np.array([0.0, 0.0, 1.0])
    return src.K @ (R + np.outer(t, n) / depth) @ np.linalg.inv(ref.K)


@numba.njit(cache=True)
def _forward_backward_error(
    H: np.ndarray, N: np.ndarray, kt: np.ndarray, depth: np.ndarray, cap: float, out: np.ndarray
) -> None:
    """Per reference pixel: through homography ``H`` to its source pixel, out to the point at the source's
    ``depth`` there (nearest pixel), and back into the reference (``N`` @ [u, v, 1] * depth + ``kt``, in
    homogeneous reference pixels); the distance to where it started, at most ``cap`` (also where the
    source has no depth)."""
    h, w = out.shape
    hs, ws = depth.shape
    for r in range(h):
        for c in range(w):
            e = cap
            z = H[2, 0] * c + H[2, 1] * r + H[2, 2]
            if z > 0:
                us = (H[0, 0] * c + H[0, 1] * r + H[0, 2]) / z
                vs = (H[1, 0] * c + H[1, 1] * r + H[1, 2]) / z
                ui, vi = round(us), round(vs)
                if 0 <= ui < ws and 0 <= vi < hs:
                    d = depth[int(vi), int(ui)]
                    if d > 0:
                        qz = d * (N[2, 0] * us + N[2, 1] * vs + N[2, 2]) + kt[2]
                        if qz > 0:
                            dx = (d * (N[0, 0] * us + N[0, 1] * vs + N[0, 2]) + kt[0]) / qz - c
                            dy = (d * (N[1, 0] * us + N[1, 1] * vs + N[1, 2]) + kt[1]) / qz - r
                            e = min(math.sqrt(dx * dx + dy * dy), cap)
            out[r, c] = e


@numba.njit(cache=True)
def _insert_minimum(
    before: np.ndarray,
    cost: np.ndarray,
    after: np.ndarray,
    plane: int,
    m_cost: np.ndarray,
    m_idx: np.ndarray,
    m_left: np.ndarray,
    m_right: np.ndarray,
) -> None:
    """Where ``plane``'s ``cost`` is a local minimum (below ``before``, not above ``after``), insert it
    into the per-pixel lists of the best minima (``m_*``: (slots, H, W), sorted by cost)."""
    slots, h, w = m_cost.shape
    for r in range(h):
        for c in range(w):
            x = cost[r, c]
            if not (x < before[r, c] and x <= after[r, c]) or not x < m_cost[slots - 1, r, c]:
                continue
            s = slots - 1
            while s > 0 and x < m_cost[s - 1, r, c]:
                m_cost[s, r, c] = m_cost[s - 1, r, c]
                m_idx[s, r, c] = m_idx[s - 1, r, c]
                m_left[s, r, c] = m_left[s - 1, r, c]
                m_right[s, r, c] = m_right[s - 1, r, c]
                s -= 1
            m_cost[s, r, c] = x
            m_idx[s, r, c] = plane
            m_left[s, r, c] = before[r, c]
            m_right[s, r, c] = after[r, c]


@dataclass
class DepthMap:
    """Depth along the optical axis (m, NaN: none) and the aggregated NCC of the winning plane; with
    ``MvsOptions.candidates`` > 1 also ``alternatives`` (candidates - 1, H, W): the depths of the next
    best local minima of the cost, best first (NaN: none)."""

    depth: np.ndarray
    ncc: np.ndarray
    alternatives: np.ndarray | None = None


def _refined_inverse_depth(
    inv: np.ndarray, idx: np.ndarray, cost: np.ndarray, left: np.ndarray, right: np.ndarray
) -> np.ndarray:
    """Inverse depth at plane ``idx`` moved to the vertex of the parabola through its cost and its two
    neighbours' (at most half a plane)."""
    denom = left - 2 * cost + right
    offset = np.where(denom > 1e-6, 0.5 * (left - right) / np.where(denom > 1e-6, denom, 1.0), 0.0)
    return inv[np.clip(idx, 0, len(inv) - 1)] + np.clip(offset, -0.5, 0.5) * (inv[1] - inv[0])


def plane_sweep(
    ref: View,
    sources: list[View],
    near: float,
    far: float,
    opts: MvsOptions,
    priors: list[np.ndarray | None] | None = None,
) -> DepthMap:
    """Depth map of ``ref`` (at its own resolution) from ``sources`` between depths ``near`` and ``far``.
    With ``priors`` (the sources' first-pass depth maps) and ``opts.geom_weight`` > 0 each source's cost
    adds the geometric-consistency term."""
    if not 0 < near < far:
        raise ValueError(f"plane sweep needs 0 < near < far, got {near}, {far}")
    if not sources:
        raise ValueError(f"{ref.name}: plane sweep needs at least one source view")
    h, w = ref.shape
    win = (opts.window, opts.window)
    k = min(opts.best_k, len(sources))
    r = ref.gray
    mu_r = cv2.boxFilter(r, -1, win, borderType=cv2.BORDER_REFLECT)
    var_r = np.maximum(cv2.boxFilter(r * r, -1, win, borderType=cv2.BORDER_REFLECT) - mu_r * mu_r, 0.0)
    textured = var_r > 1e-5
    if opts.guided_radius > 0:
        gwin = (2 * opts.guided_radius + 1,) * 2

        def gmean(a: np.ndarray) -> np.ndarray:
            return cv2.boxFilter(a, -1, gwin, borderType=cv2.BORDER_REFLECT)

        mean_I = gmean(r)
        denom_I = gmean(r * r) - mean_I * mean_I + opts.guided_eps
    inv = np.linspace(1.0 / near, 1.0 / far, opts.planes)
    best = np.full((h, w), np.inf, np.float32)
    best_i = np.full((h, w), -1, np.int32)
    left = np.full((h, w), np.nan, np.float32)
    right = np.full((h, w), np.nan, np.float32)
    prev = np.full((h, w), np.nan, np.float32)
    costs = np.empty((len(sources), h, w), np.float32)
    geom = []
    if priors is not None and opts.geom_weight > 0:
        if len(priors) != len(sources):
            raise ValueError("plane sweep needs one prior depth map per source")
        for src, prior in zip(sources, priors, strict=True):
            if prior is None:
                geom.append(None)
                continue
            T = np.linalg.inv(ref.T_world_cam) @ src.T_world_cam  # source optical -> reference optical
            geom.append(
                (ref.K @ T[:3, :3] @ np.linalg.inv(src.K), ref.K @ T[:3, 3], np.nan_to_num(prior, nan=0.0))
            )
    err = np.empty((h, w), np.float32)
    # the best local minima of the cost along the sweep, sorted: cost, plane, and the two neighbours' costs
    slots = opts.candidates if opts.candidates > 1 else 0
    m_cost = np.full((slots, h, w), np.inf, np.float32)
    m_idx = np.full((slots, h, w), -1, np.int32)
    m_left = np.full((slots, h, w), np.nan, np.float32)
    m_right = np.full((slots, h, w), np.nan, np.float32)
    prev2 = np.full((h, w), np.nan, np.float32)
    for i, d_inv in enumerate(inv):
        for s, src in enumerate(sources):
            H = plane_homography(ref, src, 1.0 / d_inv)
            flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
            warped = cv2.warpPerspective(src.gray, H, (w, h), flags=flags, borderMode=cv2.BORDER_CONSTANT)
            # pixels whose whole window comes from inside the source image (box filters of NaN would
            # spread it along the rows, so validity is a separate image)
            inside = cv2.warpPerspective(src.inside, H, (w, h), flags=flags, borderMode=cv2.BORDER_CONSTANT)
            covered = cv2.boxFilter(inside, -1, win, borderType=cv2.BORDER_REFLECT) > 0.999
            mu_s = cv2.boxFilter(warped, -1, win, borderType=cv2.BORDER_REFLECT)
            var_s = cv2.boxFilter(warped * warped, -1, win, borderType=cv2.BORDER_REFLECT) - mu_s * mu_s
            cov = cv2.boxFilter(r * warped, -1, win, borderType=cv2.BORDER_REFLECT) - mu_r * mu_s
            ncc = cov / np.sqrt(np.maximum(var_r * var_s, 1e-10))
            costs[s] = np.where(covered & (var_s > 1e-5), 1.0 - ncc, 2.0)
            if geom and geom[s] is not None:
                N, kt, prior = geom[s]
                _forward_backward_error(H, N, kt, prior, opts.geom_max_px, err)
                costs[s] += opts.geom_weight * err
        # a new array: `prev` must keep this plane's costs when `costs` is refilled for the next one
        c = costs[0].copy() if k == len(sources) == 1 else np.partition(costs, k - 1, axis=0)[:k].mean(axis=0)
        if opts.guided_radius > 0:
            mean_p = gmean(c)
            a = (gmean(r * c) - mean_I * mean_p) / denom_I
            c = gmean(a) * r + gmean(mean_p - a * mean_I)
        just_after = best_i == i - 1
        right[just_after] = c[just_after]
        better = c < best
        best[better] = c[better]
        best_i[better] = i
        left[better] = prev[better]
        right[better] = np.nan
        if slots and i >= 2:
            _insert_minimum(prev2, prev, c, i - 1, m_cost, m_idx, m_left, m_right)
        prev2 = prev
        prev = c
    # sub-plane refinement: vertex of the parabola through the winning plane and its two neighbours
    interior = (best_i > 0) & (best_i < opts.planes - 1) & np.isfinite(left) & np.isfinite(right)
    d_inv = _refined_inverse_depth(inv, best_i, best, left, right)
    ncc = (1.0 - best).astype(np.float32)
    valid = textured & ref.mask
    ok = interior & valid & (ncc >= opts.min_ncc) & (d_inv > 0)
    depth = np.where(ok, 1.0 / np.where(ok, d_inv, 1.0), np.nan).astype(np.float32)
    alternatives = None
    if slots:
        # the minima other than the winner, best first
        other = m_idx != best_i[None]
        order = np.argsort(~other, axis=0, kind="stable")[: slots - 1]
        alt = []
        for rank in range(slots - 1):
            at = order[rank : rank + 1]
            pick = [np.take_along_axis(a, at, axis=0)[0] for a in (m_cost, m_idx, m_left, m_right)]
            a_inv = _refined_inverse_depth(inv, pick[1], pick[0], pick[2], pick[3])
            a_ok = valid & (pick[1] >= 0) & (1.0 - pick[0] >= opts.min_ncc) & (a_inv > 0)
            a_ok &= np.take_along_axis(other, at, axis=0)[0]
            alt.append(np.where(a_ok, 1.0 / np.where(a_ok, a_inv, 1.0), np.nan).astype(np.float32))
        alternatives = np.stack(alt)
    return DepthMap(depth, ncc, alternatives)


def backproject(view: View, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World points (n, 3) of the valid pixels of ``depth`` (same size as ``view``), and their pixel
    indices (n, 2) as (row, column)."""
    rows, cols = np.nonzero(np.isfinite(depth))
    z = depth[rows, cols].astype(np.float64)
    K = view.K
    x = (cols - K[0, 2]) / K[0, 0] * z
    y = (rows - K[1, 2]) / K[1, 1] * z
    p_cam = np.column_stack([x, y, z])
    T = view.T_world_cam
    return p_cam @ T[:3, :3].T + T[:3, 3], np.column_stack([rows, cols])


def project(view: View, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV pixel coordinates (n, 2) of world points (n, 3) in ``view`` and their depth (n,)."""
    T = np.linalg.inv(view.T_world_cam)
    p = points @ T[:3, :3].T + T[:3, 3]
    z = p[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.column_stack(
            [view.K[0, 0] * p[:, 0] / z + view.K[0, 2], view.K[1, 1] * p[:, 1] / z + view.K[1, 2]]
        )
    return uv, z
