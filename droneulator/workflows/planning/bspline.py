"""Uniform cubic B-spline trajectories and their EGO-Planner-style optimisation (Zhou et al. 2021).

Control points ``Q`` (N x 3) with knot interval ``dt`` give N - 3 polynomial segments. The first
three control points encode the start position/velocity/acceleration and the last three the goal
at rest, so only the middle ones are optimised. Cost = smoothness (squared jerk control points) +
collision (EGO's {p, v} pairs: each colliding control point is pushed along v, the direction from
the obstacle surface p towards the A* guide path, until it is ``safety`` beyond p) + feasibility
(velocity and acceleration control points beyond the limits; the convex hull property makes these
bounds hold along the whole curve). L-BFGS with analytic gradients, then time re-allocation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numba
import numpy as np

_M = np.array([[1, 4, 1, 0], [-3, 0, 3, 0], [3, -6, 3, 0], [-1, 3, -3, 1]], dtype=float) / 6.0


@dataclass
class BSpline:
    """A uniform cubic B-spline in the world frame, starting at time 0."""

    ctrl: np.ndarray  # (N, 3)
    dt: float

    def __post_init__(self) -> None:
        self.ctrl = np.asarray(self.ctrl, dtype=float)
        if self.ctrl.ndim != 2 or self.ctrl.shape[1] != 3 or len(self.ctrl) < 4:
            raise ValueError("a cubic B-spline needs at least 4 control points of shape (N, 3)")
        if self.dt <= 0:
            raise ValueError("dt must be positive")

    @property
    def duration(self) -> float:
        return (len(self.ctrl) - 3) * self.dt

    def _eval(self, t: float | np.ndarray, order: int) -> np.ndarray:
        t = np.clip(np.asarray(t, dtype=float), 0.0, self.duration)
        seg = np.minimum((t / self.dt).astype(int), len(self.ctrl) - 4)
        u = t / self.dt - seg
        if order == 0:
            basis = np.stack([np.ones_like(u), u, u**2, u**3], -1)
        elif order == 1:
            basis = np.stack([np.zeros_like(u), np.ones_like(u), 2 * u, 3 * u**2], -1) / self.dt
        else:
            z = np.zeros_like(u)
            basis = np.stack([z, z, 2 + z, 6 * u], -1) / self.dt**2
        w = basis @ _M  # (..., 4)
        pts = self.ctrl[seg[..., None] + np.arange(4)]  # (..., 4, 3)
        return np.einsum("...k,...kd->...d", w, pts)

    def position(self, t: float | np.ndarray) -> np.ndarray:
        return self._eval(t, 0)

    def velocity(self, t: float | np.ndarray) -> np.ndarray:
        return self._eval(t, 1)

    def acceleration(self, t: float | np.ndarray) -> np.ndarray:
        return self._eval(t, 2)

    def yaw(self, t: float, fallback: float = 0.0, ahead: float = 1.0) -> float:
        """Heading towards where the curve will be ``ahead`` seconds on (its end if sooner), as EGO-Planner's
        trajectory server (``time_forward``): on a bend the camera looks into it, at what the vehicle is
        about to pass, rather than along the tangent (``ahead`` 0: along the velocity). ``fallback`` when
        that point is within 0.1 m (or the speed under 0.1 m/s)."""
        if ahead > 0:
            d = self.position(min(t + ahead, self.duration)) - self.position(min(t, self.duration))
        else:
            d = self.velocity(t)
        return float(math.atan2(d[1], d[0])) if math.hypot(d[0], d[1]) > 0.1 else fallback

    def sample(self, step: float = 0.02) -> np.ndarray:
        """Times 0..duration every ``step`` (duration included)."""
        return np.append(np.arange(0.0, self.duration, step), self.duration)

    def max_vel_acc(self) -> tuple[float, float]:
        """Largest control-point speed and acceleration: upper bounds along the whole curve."""
        v = np.diff(self.ctrl, axis=0) / self.dt
        a = np.diff(self.ctrl, 2, axis=0) / self.dt**2
        return float(np.linalg.norm(v, axis=1).max()), float(np.linalg.norm(a, axis=1).max())


def start_points(p: np.ndarray, v: np.ndarray, a: np.ndarray, dt: float) -> np.ndarray:
    """The three control points that give position ``p``, velocity ``v``, acceleration ``a`` at t = 0."""
    q1 = p - a * dt**2 / 6.0
    return np.stack([q1 - v * dt + a * dt**2 / 2.0, q1, q1 + v * dt + a * dt**2 / 2.0])


def straight_line(p0: np.ndarray, v0: np.ndarray, a0: np.ndarray, goal: np.ndarray, spacing: float,
                  max_vel: float) -> BSpline:  # fmt: skip
    """Initial trajectory: control points evenly along start -> goal, ending at rest on the goal."""
    p0, goal = np.asarray(p0, float), np.asarray(goal, float)
    length = float(np.linalg.norm(goal - p0))
    n = max(int(math.ceil(length / spacing)), 1)
    dt = max(length / n, 1e-3) / max_vel
    inner = p0 + np.outer(np.linspace(0.0, 1.0, n + 1)[1:-1], goal - p0)
    ctrl = np.concatenate([start_points(p0, np.asarray(v0, float), np.asarray(a0, float), dt), inner,
                           np.tile(goal, (3, 1))])  # fmt: skip
    return BSpline(ctrl, dt)


@dataclass
class Weights:
    smooth: float = 1.0
    collision: float = 1000.0
    feasibility: float = 0.1


@dataclass
class Pairs:
    """EGO's {p, v} anchors per control point: stay at least ``safety`` beyond p along unit v."""

    p: dict[int, list[np.ndarray]] = field(default_factory=dict)
    v: dict[int, list[np.ndarray]] = field(default_factory=dict)

    def add(self, i: int, p: np.ndarray, v: np.ndarray) -> None:
        self.p.setdefault(i, []).append(np.asarray(p, float))
        self.v.setdefault(i, []).append(np.asarray(v, float) / np.linalg.norm(v))

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The anchors as flat arrays (control-point index, p, unit v) for the compiled cost."""
        idx = [i for i, ps in self.p.items() for _ in ps]
        if not idx:
            return np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros((0, 3))
        p = np.array([p for ps in self.p.values() for p in ps], dtype=float)
        v = np.array([v for vs in self.v.values() for v in vs], dtype=float)
        return np.array(idx, dtype=np.int64), p, v


@numba.njit(cache=True, nogil=True)
def compiled_cost(x: np.ndarray, head: np.ndarray, tail: np.ndarray, dt: float, pidx: np.ndarray,
                  P: np.ndarray, V: np.ndarray, safety: float, max_vel: float, max_acc: float,
                  ws: float, wc: float, wf: float) -> tuple[float, np.ndarray]:  # fmt: skip
    """Compiled cost and gradient (see :func:`cost`): one pass over the control points, no temporaries."""
    nh, m = head.shape[0], x.shape[0] // 3
    n = nh + m + tail.shape[0]
    Q = np.empty((n, 3))
    Q[:nh] = head
    Q[nh : nh + m] = x.reshape(m, 3)
    Q[nh + m :] = tail
    G = np.zeros((n, 3))
    f = 0.0
    for i in range(n - 3):  # smoothness: squared jerk control points
        for d in range(3):
            j = Q[i + 3, d] - 3.0 * Q[i + 2, d] + 3.0 * Q[i + 1, d] - Q[i, d]
            f += ws * j * j
            gj = 2.0 * ws * j
            G[i + 3, d] += gj
            G[i + 2, d] -= 3.0 * gj
            G[i + 1, d] += 3.0 * gj
            G[i, d] -= gj
    vlim = (0.95 * max_vel) ** 2
    for i in range(n - 1):  # feasibility: velocity control points
        v0, v1, v2 = (Q[i + 1, 0] - Q[i, 0]) / dt, (Q[i + 1, 1] - Q[i, 1]) / dt, (Q[i + 1, 2] - Q[i, 2]) / dt
        e = v0 * v0 + v1 * v1 + v2 * v2 - vlim
        if e > 0:
            f += wf * e * e
            c = wf * 4.0 * e / dt
            for d, vd in ((0, v0), (1, v1), (2, v2)):
                G[i + 1, d] += c * vd
                G[i, d] -= c * vd
    alim = (0.95 * max_acc) ** 2
    dt2 = dt * dt
    for i in range(n - 2):  # feasibility: acceleration control points
        a0 = (Q[i + 2, 0] - 2.0 * Q[i + 1, 0] + Q[i, 0]) / dt2
        a1 = (Q[i + 2, 1] - 2.0 * Q[i + 1, 1] + Q[i, 1]) / dt2
        a2 = (Q[i + 2, 2] - 2.0 * Q[i + 1, 2] + Q[i, 2]) / dt2
        e = a0 * a0 + a1 * a1 + a2 * a2 - alim
        if e > 0:
            f += wf * e * e
            c = wf * 4.0 * e / dt2
            for d, ad in ((0, a0), (1, a1), (2, a2)):
                G[i + 2, d] += c * ad
                G[i + 1, d] -= 2.0 * c * ad
                G[i, d] += c * ad
    for k in range(pidx.shape[0]):  # collision: each {p, v} pair
        i = pidx[k]
        err = safety - ((Q[i, 0] - P[k, 0]) * V[k, 0] + (Q[i, 1] - P[k, 1]) * V[k, 1]
                        + (Q[i, 2] - P[k, 2]) * V[k, 2])  # fmt: skip
        if err > 0:
            f += wc * err * err
            for d in range(3):
                G[i, d] -= wc * 2.0 * err * V[k, d]
    return f, G[nh : nh + m].copy().reshape(-1)


@numba.njit(cache=True, nogil=True)
def _lbfgs(x: np.ndarray, head: np.ndarray, tail: np.ndarray, dt: float, pidx: np.ndarray, P: np.ndarray,
           V: np.ndarray, safety: float, max_vel: float, max_acc: float, ws: float, wc: float, wf: float,
           iters: int, ftol: float) -> tuple[np.ndarray, int]:  # fmt: skip
    """Compiled L-BFGS (8 pairs of memory, Armijo backtracking) on :func:`compiled_cost`.

    Stops when an iteration lowers the cost by less than ``ftol`` relative to it (L-BFGS-B's
    rule), when the gradient vanishes, after ``iters`` iterations or when no step lowers the cost.
    Everything stays in compiled code: SciPy's L-BFGS-B spends ~60 us of Python per iteration,
    most of a replanning cycle. Returns the optimum and the iterations used.
    """
    n, m = x.size, 8
    S, Y = np.zeros((m, n)), np.zeros((m, n))
    rho, alpha = np.zeros(m), np.zeros(m)
    f, g = compiled_cost(x, head, tail, dt, pidx, P, V, safety, max_vel, max_acc, ws, wc, wf)
    stored, newest = 0, -1
    it = 0
    while it < iters:
        it += 1
        q = g.copy()
        for j in range(stored):
            k = (newest - j) % m
            alpha[k] = rho[k] * np.dot(S[k], q)
            q -= alpha[k] * Y[k]
        if stored > 0:
            q *= np.dot(S[newest], Y[newest]) / np.dot(Y[newest], Y[newest])
        else:
            q /= max(np.sqrt(np.dot(g, g)), 1e-12)
        for j in range(stored - 1, -1, -1):
            k = (newest - j) % m
            q += S[k] * (alpha[k] - rho[k] * np.dot(Y[k], q))
        d = -q
        gd = np.dot(g, d)
        if gd >= 0.0:  # not a descent direction: restart from steepest descent
            stored = 0
            d = -g / max(np.sqrt(np.dot(g, g)), 1e-12)
            gd = np.dot(g, d)
        step = 1.0
        accepted = False
        for _ in range(40):
            xn = x + step * d
            fn, gn = compiled_cost(xn, head, tail, dt, pidx, P, V, safety, max_vel, max_acc, ws, wc, wf)
            if fn <= f + 1e-4 * step * gd:
                accepted = True
                break
            step *= 0.5
        if not accepted:
            break
        s, y = xn - x, gn - g
        sy = np.dot(s, y)
        if sy > 1e-12:
            newest = (newest + 1) % m
            S[newest], Y[newest], rho[newest] = s, y, 1.0 / sy
            stored = min(stored + 1, m)
        done = f - fn <= ftol * max(abs(f), abs(fn), 1.0)
        x, f, g = xn, fn, gn
        if done or np.dot(g, g) < 1e-16:
            break
    return x, it


def cost(x: np.ndarray, fixed_head: np.ndarray, fixed_tail: np.ndarray, dt: float, pairs: Pairs,
         safety: float, max_vel: float, max_acc: float, w: Weights) -> tuple[float, np.ndarray]:  # fmt: skip
    """Total cost and gradient over the free control points ``x`` (flattened M x 3)."""
    free = x.reshape(-1, 3)
    Q = np.concatenate([fixed_head, free, fixed_tail])
    G = np.zeros_like(Q)
    # smoothness: squared jerk control points (EGO uses the unscaled finite differences)
    J = Q[3:] - 3 * Q[2:-1] + 3 * Q[1:-2] - Q[:-3]
    f = w.smooth * float((J**2).sum())
    gJ = 2 * w.smooth * J
    G[3:] += gJ
    G[2:-1] -= 3 * gJ
    G[1:-2] += 3 * gJ
    G[:-3] -= gJ
    # feasibility: squared excess of |V|^2 and |A|^2 over the limits (control points, so hull-bounded)
    V = (Q[1:] - Q[:-1]) / dt
    ev = (V**2).sum(1) - (0.95 * max_vel) ** 2
    m = ev > 0
    f += w.feasibility * float((ev[m] ** 2).sum())
    gV = np.zeros_like(V)
    gV[m] = w.feasibility * 4 * ev[m, None] * V[m] / dt
    G[1:] += gV
    G[:-1] -= gV
    A = (Q[2:] - 2 * Q[1:-1] + Q[:-2]) / dt**2
    ea = (A**2).sum(1) - (0.95 * max_acc) ** 2
    m = ea > 0
    f += w.feasibility * float((ea[m] ** 2).sum())
    gA = np.zeros_like(A)
    gA[m] = w.feasibility * 4 * ea[m, None] * A[m] / dt**2
    G[2:] += gA
    G[1:-1] -= 2 * gA
    G[:-2] += gA
    # collision: quadratic penalty while a control point is less than `safety` beyond its anchor
    for i, ps in pairs.p.items():
        for p, v in zip(ps, pairs.v[i], strict=True):
            err = safety - float((Q[i] - p) @ v)
            if err > 0:
                f += w.collision * err**2
                G[i] -= w.collision * 2 * err * v
    return f, G[len(fixed_head) : len(Q) - len(fixed_tail)].ravel()


def optimize(traj: BSpline, pairs: Pairs, safety: float, max_vel: float, max_acc: float,
             w: Weights, iters: int = 200, ftol: float | None = None) -> BSpline:  # fmt: skip
    """L-BFGS over the middle control points; start (3 points) and goal (3 points) stay fixed.

    ``ftol`` is the relative cost reduction at which it stops (None: 2.2e-9, L-BFGS-B's default);
    a looser one ends the flat tail of the descent, where the control points move by micrometres.
    """
    Q = traj.ctrl
    if len(Q) <= 6:
        return traj
    head, tail = np.ascontiguousarray(Q[:3]), np.ascontiguousarray(Q[-3:])
    pidx, P, V = pairs.arrays()
    x, _ = _lbfgs(
        np.ascontiguousarray(Q[3:-3].ravel()), head, tail, float(traj.dt), pidx, P, V, float(safety),
        float(max_vel), float(max_acc), float(w.smooth), float(w.collision), float(w.feasibility), int(iters),
        2.2e-9 if ftol is None else float(ftol),
    )  # fmt: skip
    return BSpline(np.concatenate([head, x.reshape(-1, 3), tail]), traj.dt)


def reallocate_time(traj: BSpline, p0: np.ndarray, v0: np.ndarray, a0: np.ndarray, max_vel: float,
                    max_acc: float) -> BSpline:  # fmt: skip
    """Stretch ``dt`` until velocity and acceleration control points are within the limits.

    Stretching keeps the path; the three start control points are recomputed so the start state
    is kept exactly (EGO re-fits the curve instead; here the start points move by O(v dt)). A start
    acceleration pushes the first control points out by ``a0 dt^2 / 2``, which grows faster than the
    stretch helps, so past 8 times the first ``dt`` the start keeps position and velocity only
    (``a0`` = 0; the acceleration reference jumps once) instead of running away. The result may
    still exceed the limits (e.g. a start faster than ``max_vel``): callers check.
    """
    p0, v0 = np.asarray(p0, float), np.asarray(v0, float)
    out = traj
    for a_start in (np.asarray(a0, float), np.zeros(3)):
        out = BSpline(np.concatenate([start_points(p0, v0, a_start, traj.dt), traj.ctrl[3:]]), traj.dt)
        for _ in range(20):
            vmax, amax = out.max_vel_acc()
            ratio = max(vmax / max_vel, math.sqrt(amax / max_acc))
            if ratio <= 1.0:
                return out
            dt = out.dt * min(ratio * 1.02, 2.0)
            if dt > 8.0 * traj.dt:
                break
            out = BSpline(np.concatenate([start_points(p0, v0, a_start, dt), out.ctrl[3:]]), dt)
    return out

