"""The compiled step of every world: rows ``(worlds, vehicles, STATE_SIZE)`` through one control period.

:class:`~droneulator.world.World` advances its worlds only through these functions, whichever drives the
rows: its vehicles' Python flight controllers (one world, every flight mode) or the batched commands
(any number of worlds; hold and velocity mode, what learning needs). A period is

1. (:func:`run_period_serial` with ``begin``) each row's wind (given, the rotor wakes of its world's
   vehicles above it included, :mod:`droneulator.world.downwash`), the period's start state, and its
   rotor command: given (``ROTORS``), or the SE(3) controller's tracking a flat output that is given
   (``FLAT``: hold, goto, trajectories) or advanced here by the compiled velocity reference
   (``VELOCITY``), or an inner loop's (:mod:`droneulator.controllers.inner`) flying the collective thrust
   and body rates (``RATES``) or the collective thrust and attitude (``ATTITUDE``) given in the row's
   reference;
2. (:func:`run_period_serial`, once per stretch between camera instants) RK4 with the scene's collisions
   (a row that touches its world's scene stops there, level, and is integrated no further);
3. :func:`end_period`: vehicles of one world whose bodies overlap stop where they were at the start of
   the period, level.

:func:`step_to_frame` runs whole periods of chosen worlds, each to the end of the period holding its
next camera instant, in one call. Each world has its own clock, camera instants and scene (a variant
index into :class:`SdfStack`), so worlds reset at different times step side by side. From
:data:`~droneulator.vehicles.dynamics.PARALLEL_ROWS` rows on, :func:`run_period_parallel` spreads the
rows over the cores.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from droneulator.controllers.inner import attitude_into, rates_into
from droneulator.controllers.se3 import se3_into
from droneulator.controllers.velocity import velocity_flat
from droneulator.frames_numba import set_quat_from_yaw, yaw_of
from droneulator.scenes.collision import CollisionModel
from droneulator.state import STATE, STATE_SIZE
from droneulator.vehicles.dynamics import OUTPUT_SIZE, integrate
from droneulator.world.contact import _contacts
from droneulator.world.downwash import _downwash

NS = 1_000_000_000
#: how a row gets its rotor command each period (see the module docstring)
FLAT, VELOCITY, ROTORS, RATES, ATTITUDE = 0, 1, 2, 3, 4
_Q = STATE.q.start
_WIND = STATE.wind.start


class SdfStack:
    """The scenes' signed distance grids in one flat buffer, so that each world's rows collide with its
    own scene variant inside one compiled call (grids of any shapes)."""

    def __init__(self, models: list[CollisionModel]) -> None:
        sizes = [m.sdf.size for m in models]
        self.buffer = np.concatenate([np.ascontiguousarray(m.sdf, dtype=np.float32).ravel() for m in models])
        self.offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
        self.shapes = np.array([m.sdf.shape for m in models], dtype=np.int64)
        self.origins = np.array([m.origin for m in models], dtype=np.float64)
        self.resolutions = np.array([m.resolution for m in models], dtype=np.float64)


@numba.njit(cache=True)
def _sdf(buf, off, shapes, v):  # fmt: skip
    s = shapes[v]
    return buf[off[v] : off[v] + s[0] * s[1] * s[2]].reshape((s[0], s[1], s[2]))


@numba.njit(cache=True)
def stop_level(s: np.ndarray) -> None:
    """A vehicle that touched something stops where it is, level, keeping its heading."""
    for j in range(3, 6):
        s[j] = 0.0
    for j in range(10, 13):
        s[j] = 0.0
    set_quat_from_yaw(s[_Q : _Q + 4], yaw_of(s[_Q : _Q + 4]))


@numba.njit(cache=True)
def _begin_row(k, go, states, mode, flats, cmds, vref, dt, lim, gains, R):  # fmt: skip
    N = states.shape[1]
    w, n = k // N, k % N
    if not go[w]:
        return
    s = states[w, n]
    m = mode[w, n]
    if m == VELOCITY:
        velocity_flat(vref[w, n], dt, s, lim[n], flats[w, n])
    if m == RATES:
        rates_into(s, flats[w, n], gains[n], cmds[w, n], dt)
    elif m == ATTITUDE:
        attitude_into(s, flats[w, n], gains[n], cmds[w, n], R[w, n])
    elif m != ROTORS:
        se3_into(s, flats[w, n], gains[n], cmds[w, n], R[w, n])


@numba.njit(cache=True)
def _begin_worlds(go, states, wind, period_start, out):  # fmt: skip
    """Step 1's part per world: each row's wind, its start state, its outputs."""
    W, N = states.shape[0], states.shape[1]
    for w in range(W):
        if not go[w]:
            continue
        for n in range(N):
            for j in range(3):
                states[w, n, _WIND + j] = wind[w, n, j]
        for n in range(N):
            for j in range(STATE_SIZE):
                period_start[w, n, j] = states[w, n, j]
            for j in range(OUTPUT_SIZE):
                out[w, n, j] = 0.0


@numba.njit(cache=True)
def _segment_row(k, go, t_to, t_ns, states, cmds, active, substep, P, G, D, pidx, eff, sdfs, off, shapes,
                 origins, res, variant, radius, out, hit, hit_t, work, R):  # fmt: skip
    N = states.shape[1]
    w, n = k // N, k % N
    if not go[w] or not active[w, n] or t_to[w] <= t_ns[w]:
        return 0
    h = (t_to[w] - t_ns[w]) / NS
    n_sub = max(1, math.ceil(h / substep - 1e-9))
    v = variant[w]
    p = pidx[n]
    s = states[w, n]
    if integrate(s, cmds[w, n], h, n_sub, P[p], G[p], D[p], eff[w, n], _sdf(sdfs, off, shapes, v), origins[v],
                 res[v], radius[n], out[w, n], work[w, n], R[w, n]):  # fmt: skip
        hit[w, n] = True
        hit_t[w, n] = t_ns[w]
        active[w, n] = False
        stop_level(s)
        return 1
    return 0


@numba.njit(cache=True)
def _advance_clocks(go, t_to, t_ns):  # fmt: skip
    for w in range(t_ns.shape[0]):
        if go[w]:
            t_ns[w] = max(t_ns[w], t_to[w])


@numba.njit(cache=True)
def run_period_serial(go, begin, t_to, t_ns, states, cmds, active, substep, P, G, D, pidx, eff, sdfs, off,
                      shapes, origins, res, variant, radius, out, hit, hit_t, work, R, wind, period_start,
                      mode, flats, vref, dt, lim, gains):  # fmt: skip
    """Steps 1 (with ``begin``: wind, wakes included, start states, rotor commands) and 2 (integrate the
    active rows of the worlds where ``go`` from their clock to ``t_to``, ns per world, then set those
    clocks) in one call, row after row, each rotor at its efficiency ``eff[w, n, i]`` (1: healthy). A row
    that touches the scene is flagged in ``hit`` (with the segment's start time in ``hit_t``), stopped and
    made inactive. Returns how many rows hit."""
    W, N = states.shape[0], states.shape[1]
    if begin:
        _begin_worlds(go, states, wind, period_start, out)
        for k in range(W * N):
            _begin_row(k, go, states, mode, flats, cmds, vref, dt, lim, gains, R)
    hits = 0
    for k in range(W * N):
        hits += _segment_row(k, go, t_to, t_ns, states, cmds, active, substep, P, G, D, pidx, eff, sdfs, off,
                             shapes, origins, res, variant, radius, out, hit, hit_t, work, R)  # fmt: skip
    _advance_clocks(go, t_to, t_ns)
    return hits


@numba.njit(cache=True, parallel=True)
def run_period_parallel(go, begin, t_to, t_ns, states, cmds, active, substep, P, G, D, pidx, eff, sdfs, off,
                        shapes, origins, res, variant, radius, out, hit, hit_t, work, R, wind, period_start,
                        mode, flats, vref, dt, lim, gains):  # fmt: skip
    """:func:`run_period_serial` with the rows spread over the cores (compiled apart: a parallel kernel
    takes several times as long to compile, which a world of few vehicles never pays)."""
    W, N = states.shape[0], states.shape[1]
    if begin:
        _begin_worlds(go, states, wind, period_start, out)
        for k in numba.prange(W * N):
            _begin_row(k, go, states, mode, flats, cmds, vref, dt, lim, gains, R)
    hits = 0
    for k in numba.prange(W * N):
        hits += _segment_row(k, go, t_to, t_ns, states, cmds, active, substep, P, G, D, pidx, eff, sdfs, off,
                             shapes, origins, res, variant, radius, out, hit, hit_t, work, R)  # fmt: skip
    _advance_clocks(go, t_to, t_ns)
    return hits


@numba.njit(cache=True)
def end_period(go, states, active, radius, period_start):  # fmt: skip
    """Step 3: in each world where ``go``, vehicles whose bodies overlap go back to their start of the
    period, level and stopped, and become inactive. Returns the pairs ``(world, i, j)``."""
    W, N = states.shape[0], states.shape[1]
    found = []
    if N < 2:
        return np.empty((0, 3), dtype=np.int64)
    for w in range(W):
        if not go[w]:
            continue
        pairs = _contacts(states[w, :, 0:3], radius, active[w])
        for k in range(pairs.shape[0]):
            a, b = pairs[k, 0], pairs[k, 1]
            found.append((w, a, b))
        for k in range(pairs.shape[0]):
            for i in (pairs[k, 0], pairs[k, 1]):
                for j in range(STATE_SIZE):
                    states[w, i, j] = period_start[w, i, j]
                stop_level(states[w, i])
                active[w, i] = False
    out = np.empty((len(found), 3), dtype=np.int64)
    for k in range(len(found)):
        out[k, 0], out[k, 1], out[k, 2] = found[k]
    return out


@numba.njit(cache=True)
def step_to_frame(run, parallel, period_ns, camera_ns, t_ns, next_frame, states, wind, wakes, k_eta, area,
                  period_start, out, mode, flats, cmds, vref, lim, gains, active, substep, P, G, D, pidx, eff,
                  sdfs, off, shapes, origins, res, variant, radius, hit, hit_t, work, R, cam,
                  touched):  # fmt: skip
    """Advance every world where ``run`` period by period to the end of the period holding its next camera
    instant, where its rows are copied to ``cam``. ``hit`` flags rows that touched the scene on the way,
    ``touched[w, i]`` the other vehicle a row touched (-1: none)."""
    W, N = states.shape[0], states.shape[1]
    dt = period_ns / NS
    go = run.copy()
    for w in range(W):
        if run[w]:
            for n in range(N):
                hit[w, n] = False
                touched[w, n] = -1
    t_to = np.empty(W, dtype=np.int64)
    now = wind.copy()
    wake = np.zeros((N, 3))
    while go.any():
        if wakes:  # the frame's wind plus the wakes of the period's start
            for w in range(W):
                if go[w]:
                    wake[:] = 0.0
                    _downwash(states[w], k_eta, area, wake)
                    for n in range(N):
                        for j in range(3):
                            now[w, n, j] = wind[w, n, j] + wake[n, j]
        t_end = t_ns + period_ns
        begin = True
        framed = np.zeros(W, dtype=np.bool_)
        while True:
            left = False
            for w in range(W):
                t_to[w] = min(t_end[w], next_frame[w])
                left = left or (go[w] and t_ns[w] < t_end[w])
            if not left:
                break
            if parallel:
                run_period_parallel(go, begin, t_to, t_ns, states, cmds, active, substep, P, G, D, pidx, eff,
                                    sdfs, off, shapes, origins, res, variant, radius, out, hit, hit_t, work,
                                    R, now, period_start, mode, flats, vref, dt, lim, gains)  # fmt: skip
            else:
                run_period_serial(go, begin, t_to, t_ns, states, cmds, active, substep, P, G, D, pidx, eff,
                                  sdfs, off, shapes, origins, res, variant, radius, out, hit, hit_t, work, R,
                                  now, period_start, mode, flats, vref, dt, lim, gains)  # fmt: skip
            begin = False
            for w in range(W):
                if go[w] and t_ns[w] == next_frame[w]:
                    for n in range(N):
                        for j in range(STATE_SIZE):
                            cam[w, n, j] = states[w, n, j]
                    next_frame[w] += camera_ns
                    framed[w] = True
        pairs = end_period(go, states, active, radius, period_start)
        for k in range(pairs.shape[0]):
            w, a, b = pairs[k, 0], pairs[k, 1], pairs[k, 2]
            touched[w, a], touched[w, b] = b, a
        for w in range(W):
            if framed[w]:
                go[w] = False
