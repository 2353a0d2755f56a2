"""Minimum-snap references for goto commands.

Solving uses RotorPy's ``MinSnap`` (cvxopt QP, 7th-order segments). Evaluating it at every
control tick with ``MinSnap.update`` costs ~0.1 ms; :class:`PolyTrajectory` evaluates the same
coefficients with a compiled Horner scheme into the packed flat-output vector the SE(3)
controller consumes. Moves shorter than RotorPy's 0.1 m waypoint merge threshold (a yaw-only turn,
a small correction) use the closed-form rest-to-rest 7th-order polynomial, which is the
minimum-snap solution for that boundary-value problem.
"""

from __future__ import annotations

import contextlib
import math
import sys
from collections.abc import Iterator

import numba
import numpy as np

from droneulator.state import FLAT_SIZE


@contextlib.contextmanager
def _without(modules: tuple[str, ...]) -> Iterator[None]:
    """Make ``import`` of ``modules`` fail inside the block (those not imported yet), as if they were not
    installed. RotorPy's trajectory module tries to import torch for its batched class only, which the
    simulator does not use: with the ``rl`` extra installed that import alone took 2-4 s and 300 MB in
    every simulator process. A process that imported torch before keeps it (nothing to save there); the
    module's batched class (``BatchedMinSnap``) is then unusable in this process."""
    blocked = [name for name in modules if name not in sys.modules]
    for name in blocked:
        sys.modules[name] = None  # type: ignore[assignment]
    try:
        yield
    finally:
        for name in blocked:
            if sys.modules.get(name, 0) is None:
                del sys.modules[name]


with _without(("torch", "roma")):
    from rotorpy.trajectories.minsnap import MinSnap

#: time scaling of the rest-to-rest 7th-order polynomial s(tau) = 35t^4 - 84t^5 + 70t^6 - 20t^7
_REST_TO_REST = np.array([-20.0, 70.0, -84.0, 35.0, 0.0, 0.0, 0.0, 0.0])
#: peak of ds/dtau (at tau = 1/2): 35/16
PEAK_SPEED_FACTOR = 35.0 / 16.0


@numba.njit(cache=True)
def _horner(c: np.ndarray, t: float, deriv: int) -> float:
    """Value of the ``deriv``-th derivative at t of a polynomial with highest-first coefficients."""
    n = c.shape[0] - 1
    acc = 0.0
    for i in range(n - deriv + 1):
        power = n - i
        coef = c[i]
        for k in range(deriv):
            coef *= power - k
        acc = acc * t + coef
    return acc


@numba.njit(cache=True)
def _evaluate(
    x_poly: np.ndarray, yaw_poly: np.ndarray, t_keys: np.ndarray, t: float, out: np.ndarray
) -> None:
    m = x_poly.shape[0]
    t = min(max(t, t_keys[0]), t_keys[m])
    i = 0
    while i < m - 1 and t > t_keys[i + 1]:
        i += 1
    tau = t - t_keys[i]
    for j in range(3):
        out[j] = _horner(x_poly[i, j], tau, 0)
        out[3 + j] = _horner(x_poly[i, j], tau, 1)
        out[6 + j] = _horner(x_poly[i, j], tau, 2)
    out[9] = _horner(yaw_poly[i, 0], tau, 0)
    out[10] = _horner(yaw_poly[i, 0], tau, 1)


class PolyTrajectory:
    """Piecewise polynomial reference: ``x_poly`` (m, 3, k+1), ``yaw_poly`` (m, 1, k+1), highest first."""

    def __init__(self, x_poly: np.ndarray, yaw_poly: np.ndarray, t_keyframes: np.ndarray, t0: float = 0.0):
        self.x_poly = np.ascontiguousarray(x_poly, dtype=float)
        self.yaw_poly = np.ascontiguousarray(yaw_poly, dtype=float)
        self.t_keyframes = np.ascontiguousarray(t_keyframes, dtype=float)
        self.t0 = t0
        self._out = np.zeros(FLAT_SIZE)

    @property
    def duration(self) -> float:
        return float(self.t_keyframes[-1])

    @property
    def end_position(self) -> np.ndarray:
        return self.flat(self.t0 + self.duration)[0:3].copy()

    def flat(self, t: float) -> np.ndarray:
        """Packed flat output at absolute time ``t`` (held at the ends). The array is reused."""
        _evaluate(self.x_poly, self.yaw_poly, self.t_keyframes, t - self.t0, self._out)
        return self._out


def rest_to_rest(
    p0: np.ndarray, p1: np.ndarray, yaw0: float, yaw1: float, duration: float, t0: float = 0.0
) -> PolyTrajectory:
    """Closed-form single-segment minimum-snap move with zero velocity, acceleration and jerk at both ends."""
    T = float(duration)
    scale = np.array([T ** -(7 - i) if i < 7 else 1.0 for i in range(8)])
    base = _REST_TO_REST * scale
    x_poly = np.zeros((1, 3, 8))
    for j in range(3):
        x_poly[0, j] = base * (p1[j] - p0[j])
        x_poly[0, j, 7] += p0[j]
    yaw_poly = np.zeros((1, 1, 8))
    yaw_poly[0, 0] = base * (yaw1 - yaw0)
    yaw_poly[0, 0, 7] += yaw0
    return PolyTrajectory(x_poly, yaw_poly, np.array([0.0, T]), t0)


def goto_trajectory(
    p0: np.ndarray,
    v0: np.ndarray,
    yaw0: float,
    waypoints: np.ndarray,
    yaw1: float,
    speed: float,
    duration: float | None = None,
    max_yaw_rate: float = 1.0,
    t0: float = 0.0,
) -> PolyTrajectory:
    """Minimum-snap path from the current state through ``waypoints`` (k, 3), ending at rest.

    Time allocation: ``duration`` if given, else such that a straight single-segment move peaks at
    ``speed`` (its average speed is 16/35 of the peak), lengthened so the average yaw rate stays
    below ``max_yaw_rate``. The final yaw is taken on the short way round from ``yaw0``.
    """
    p0 = np.asarray(p0, dtype=float)
    targets = np.atleast_2d(np.asarray(waypoints, dtype=float))
    yaw1 = yaw0 + math.remainder(yaw1 - yaw0, 2 * math.pi)
    kept = [p0]
    for w in targets:  # RotorPy merges waypoints closer than 0.1 m; do it here so the end is kept
        if np.linalg.norm(w - kept[-1]) >= 0.1:
            kept.append(w)
    kept[-1] = targets[-1] if len(kept) > 1 else kept[-1]
    pts = np.vstack(kept)
    length = float(np.sum(np.linalg.norm(np.diff(pts, axis=0), axis=1)))
    T = (
        duration
        if duration is not None
        else max(PEAK_SPEED_FACTOR * length / speed, abs(yaw1 - yaw0) / max_yaw_rate, 1.0)
    )
    if len(pts) == 1 or np.any(np.linalg.norm(np.diff(pts, axis=0), axis=1) < 0.1):
        return rest_to_rest(p0, targets[-1], yaw0, yaw1, T, t0)
    yaws = np.linspace(yaw0, yaw1, len(pts))
    v_avg = length / T
    ms = MinSnap(
        pts,
        yaw_angles=yaws,
        v_avg=v_avg,
        v_max=max(10.0, 4 * v_avg),
        yaw_rate_max=max(2 * math.pi, 4 * abs(yaw1 - yaw0) / T),
        v_start=list(np.asarray(v0, dtype=float)),
        v_end=[0.0, 0.0, 0.0],
        verbose=False,
    )
    return PolyTrajectory(ms.x_poly, ms.yaw_poly, ms.t_keyframes, t0)


def hold_trajectory(p: np.ndarray, yaw: float, t0: float = 0.0) -> PolyTrajectory:
    """A constant reference (hover at ``p`` with heading ``yaw``)."""
    x_poly = np.zeros((1, 3, 8))
    x_poly[0, :, 7] = p
    yaw_poly = np.zeros((1, 1, 8))
    yaw_poly[0, 0, 7] = yaw
    return PolyTrajectory(x_poly, yaw_poly, np.array([0.0, 1.0]), t0)
