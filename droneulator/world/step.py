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
2. (:func:`run_period_serial`, once per stretch between camera instants) RK4 with the scene's collisions,
   each row by its contact model (``model``; docs/contact.md): under ``stop`` a row that touches its
   world's scene stops there, level, and is integrated no further; under ``physical`` the leaves push and
   slow it and a strike on wood costs the struck rotors their thrust (``eff``, the world's
   ``rotor_efficiency``); under ``crash`` its rotors stop for good (``dead``);
3. :func:`end_period`: vehicles of one world whose bodies overlap meet by their contact models (``stop``:
   back where they were at the start of the period, level and stopped; ``physical`` and ``crash``: back
   there bouncing apart, losing the rotors facing each other or all of them).

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
from droneulator.frames_numba import quat_to_matrix_into, set_quat_from_yaw, yaw_of
from droneulator.scenes.collision import CollisionModel
from droneulator.state import STATE, STATE_SIZE
from droneulator.vehicles.dynamics import (
    CONTACT_CRASH,
    CONTACT_STOP,
    OUTPUT_SIZE,
    STRUCK_SHARE,
    integrate,
)
from droneulator.world.contact import _contacts
from droneulator.world.downwash import _downwash

NS = 1_000_000_000
#: how a row gets its rotor command each period (see the module docstring)
FLAT, VELOCITY, ROTORS, RATES, ATTITUDE = 0, 1, 2, 3, 4
_Q = STATE.q.start
_WIND = STATE.wind.start


class SdfStack:
    """The scenes' signed distance grids in one flat buffer, so that each world's rows collide with its
    own scene variant inside one compiled call (grids of any shapes); their wood grids (the same cells) in
    a second buffer at the same offsets."""

    def __init__(self, models: list[CollisionModel]) -> None:
        sizes = [m.sdf.size for m in models]
        self.buffer = np.concatenate([np.ascontiguousarray(m.sdf, dtype=np.float32).ravel() for m in models])
        self.wood = np.concatenate([np.ascontiguousarray(m.wood, dtype=np.float32).ravel() for m in models])
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
def _begin_row(k, go, states, mode, flats, cmds, vref, dt, lim, gains, R, dead):  # fmt: skip
    N = states.shape[1]
    w, n = k // N, k % N
    if not go[w]:
        return
    if dead[w, n]:  # a crashed row's rotors stay stopped
        for i in range(4):
            cmds[w, n, i] = 0.0
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
def _segment_row(k, go, t_to, t_ns, states, cmds, active, substep, P, G, D, pidx, sdfs, wood, off, shapes,
                 origins, res, variant, radius, model, eff, dead, out, hit, hit_t, hit_kind, work,
                 R):  # fmt: skip
    N = states.shape[1]
    w, n = k // N, k % N
    if not go[w] or not active[w, n] or t_to[w] <= t_ns[w]:
        return 0
    h = (t_to[w] - t_ns[w]) / NS
    n_sub = max(1, math.ceil(h / substep - 1e-9))
    v = variant[w]
    p = pidx[n]
    s = states[w, n]
    m = model[w, n]
    code = integrate(s, cmds[w, n], h, n_sub, P[p], G[p], D[p], eff[w, n], _sdf(sdfs, off, shapes, v),
                     _sdf(wood, off, shapes, v), origins[v], res[v], radius[n], m, out[w, n], work[w, n],
                     R[w, n])  # fmt: skip
    if code == 0:
        return 0
    was = hit_kind[w, n] if hit[w, n] else 0
    hit_kind[w, n] = max(was & 3, code & 3) | ((was | code) >> 2) << 2
    if not hit[w, n]:
        hit_t[w, n] = t_ns[w]
    hit[w, n] = True
    if m == CONTACT_STOP:
        active[w, n] = False
        stop_level(s)
    elif m == CONTACT_CRASH:
        dead[w, n] = True
        for i in range(4):
            cmds[w, n, i] = 0.0
    return 1


@numba.njit(cache=True)
def _advance_clocks(go, t_to, t_ns):  # fmt: skip
    for w in range(t_ns.shape[0]):
        if go[w]:
            t_ns[w] = max(t_ns[w], t_to[w])


@numba.njit(cache=True)
def run_period_serial(go, begin, t_to, t_ns, states, cmds, active, substep, P, G, D, pidx, sdfs, wood, off,
                      shapes, origins, res, variant, radius, model, eff, dead, out, hit, hit_t, hit_kind,
                      work, R, wind, period_start, mode, flats, vref, dt, lim, gains):  # fmt: skip
    """Steps 1 (with ``begin``: wind, wakes included, start states, rotor commands) and 2 (integrate the
    active rows of the worlds where ``go`` from their clock to ``t_to``, ns per world, then set those
    clocks) in one call, row after row. A row that begins a contact with the scene is flagged in ``hit``
    (with the segment's start time in ``hit_t`` and what it touched in ``hit_kind``, as
    :func:`~droneulator.vehicles.dynamics.integrate` returns it); under its ``model`` CONTACT_STOP it is
    stopped and made inactive, under CONTACT_CRASH made ``dead`` (rotors stopped until placed again), under
    CONTACT_PHYSICAL it flies on (rotors struck on wood lost in ``eff``). Returns how many rows hit."""
    W, N = states.shape[0], states.shape[1]
    if begin:
        _begin_worlds(go, states, wind, period_start, out)
        for k in range(W * N):
            _begin_row(k, go, states, mode, flats, cmds, vref, dt, lim, gains, R, dead)
    hits = 0
    for k in range(W * N):
        hits += _segment_row(k, go, t_to, t_ns, states, cmds, active, substep, P, G, D, pidx, sdfs, wood,
                             off, shapes, origins, res, variant, radius, model, eff, dead, out, hit, hit_t,
                             hit_kind, work, R)  # fmt: skip
    _advance_clocks(go, t_to, t_ns)
    return hits


@numba.njit(cache=True, parallel=True)
def run_period_parallel(go, begin, t_to, t_ns, states, cmds, active, substep, P, G, D, pidx, sdfs, wood,
                        off, shapes, origins, res, variant, radius, model, eff, dead, out, hit, hit_t,
                        hit_kind, work, R, wind, period_start, mode, flats, vref, dt, lim,
                        gains):  # fmt: skip
    """:func:`run_period_serial` with the rows spread over the cores (compiled apart: a parallel kernel
    takes several times as long to compile, which a world of few vehicles never pays)."""
    W, N = states.shape[0], states.shape[1]
    if begin:
        _begin_worlds(go, states, wind, period_start, out)
        for k in numba.prange(W * N):
            _begin_row(np.int64(k), go, states, mode, flats, cmds, vref, dt, lim, gains, R, dead)
    hits = 0
    for k in numba.prange(W * N):
        # the index cast: a prange index is typed int64, then uint64, and each would compile the row apart
        hits += _segment_row(np.int64(k), go, t_to, t_ns, states, cmds, active, substep, P, G, D, pidx, sdfs,
                             wood, off, shapes, origins, res, variant, radius, model, eff, dead, out, hit,
                             hit_t, hit_kind, work, R)  # fmt: skip
    _advance_clocks(go, t_to, t_ns)
    return hits


#: :func:`run_period_parallel` as :func:`step_to_frame` calls it: the same function, compiled in each process
#: that compiles its caller and never loaded from numba's cache. A cached function compiled against a
#: parallel kernel loaded from the cache is cached broken: the next process that loads it segfaults
#: (numba 0.68; numba/numba#8578 is the same family). Two test workers on a fresh clone did that (one
#: cached the kernel while the other compiled ``step_to_frame``); ``tests/test_world_many.py`` replays it.
_run_period_parallel_here = numba.njit(parallel=True)(run_period_parallel.py_func)


@numba.njit(cache=True)
def _nearest_rotors(s, geom, other, R):  # fmt: skip
    """Bit mask of the rotors of a vehicle in state ``s`` nearest the point ``other`` (those within
    :data:`~droneulator.vehicles.dynamics.STRUCK_SHARE` of an arm of the nearest hub)."""
    quat_to_matrix_into(s[_Q : _Q + 4], R)
    d = np.empty(4)
    arm = 0.0
    for i in range(4):
        d2 = 0.0
        for a in range(3):
            x = s[a] + R[a, 0] * geom[i, 0] + R[a, 1] * geom[i, 1] + R[a, 2] * geom[i, 2] - other[a]
            d2 += x * x
        d[i] = math.sqrt(d2)
        arm = max(arm, math.sqrt(geom[i, 0] * geom[i, 0] + geom[i, 1] * geom[i, 1]))
    mask = 0
    for i in range(4):
        if d[i] <= d.min() + STRUCK_SHARE * arm:
            mask |= 1 << i
    return mask


@numba.njit(cache=True)
def end_period(go, states, active, radius, period_start, model, eff, dead, G, pidx):  # fmt: skip
    """Step 3: in each world where ``go``, vehicles whose bodies overlap meet, each by its ``model``:
    CONTACT_STOP goes back to its start of the period, level and stopped, and becomes inactive;
    CONTACT_PHYSICAL goes back to where it was at the start of the period keeping its motion but for the
    part towards the other, which bounces off (restitution 0.3), and loses the rotors nearest the other
    (``eff``); CONTACT_CRASH does the same with every rotor stopped (``dead``). Returns rows
    ``(world, i, j, rotors i lost, rotors j lost)`` (bit masks; 15 for a crash)."""
    W, N = states.shape[0], states.shape[1]
    found = []
    if N < 2:
        return np.empty((0, 5), dtype=np.int64)
    R = np.empty((3, 3))
    x = np.empty((2, 3))
    for w in range(W):
        if not go[w]:
            continue
        pairs = _contacts(states[w, :, 0:3], radius, active[w])
        for k in range(pairs.shape[0]):
            a, b = pairs[k, 0], pairs[k, 1]
            for j in range(3):
                x[0, j], x[1, j] = states[w, a, j], states[w, b, j]
            lost = [0, 0]
            for side in range(2):
                i = a if side == 0 else b
                m = model[w, i]
                if m == CONTACT_STOP:
                    for j in range(STATE_SIZE):
                        states[w, i, j] = period_start[w, i, j]
                    stop_level(states[w, i])
                    active[w, i] = False
                    continue
                s = states[w, i]
                if m == CONTACT_CRASH:
                    lost[side] = 0 if dead[w, i] else 15
                    dead[w, i] = True
                else:
                    struck = _nearest_rotors(s, G[pidx[i]], x[1 - side], R)
                    for r in range(4):
                        if struck & (1 << r) and eff[w, i, r] > 0.0:
                            eff[w, i, r] = 0.0
                            lost[side] |= 1 << r
                o = 1 - side
                nx, ny, nz = x[side, 0] - x[o, 0], x[side, 1] - x[o, 1], x[side, 2] - x[o, 2]
                norm = max(math.sqrt(nx * nx + ny * ny + nz * nz), 1e-9)
                nx, ny, nz = nx / norm, ny / norm, nz / norm
                vn = s[3] * nx + s[4] * ny + s[5] * nz
                if vn < 0.0:
                    s[3], s[4], s[5] = s[3] - 1.3 * vn * nx, s[4] - 1.3 * vn * ny, s[5] - 1.3 * vn * nz
                for j in range(3):
                    s[j] = period_start[w, i, j]
            found.append((w, a, b, lost[0], lost[1]))
    out = np.empty((len(found), 5), dtype=np.int64)
    for k in range(len(found)):
        out[k, 0], out[k, 1], out[k, 2], out[k, 3], out[k, 4] = found[k]
    return out


@numba.njit(cache=True)
def step_to_frame(run, parallel, period_ns, camera_ns, t_ns, next_frame, states, wind, wakes, k_eta, area,
                  period_start, out, mode, flats, cmds, vref, lim, gains, active, substep, P, G, D, pidx,
                  sdfs, wood, off, shapes, origins, res, variant, radius, model, eff, dead, hit, hit_t,
                  hit_kind, work, R, cam, touched):  # fmt: skip
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
                _run_period_parallel_here(go, begin, t_to, t_ns, states, cmds, active, substep, P, G, D,
                                          pidx, sdfs, wood, off, shapes, origins, res, variant, radius, model,
                                          eff, dead, out, hit, hit_t, hit_kind, work, R, now, period_start,
                                          mode, flats, vref, dt, lim, gains)  # fmt: skip
            else:
                run_period_serial(go, begin, t_to, t_ns, states, cmds, active, substep, P, G, D, pidx, sdfs,
                                  wood, off, shapes, origins, res, variant, radius, model, eff, dead, out,
                                  hit, hit_t, hit_kind, work, R, now, period_start, mode, flats, vref, dt,
                                  lim, gains)  # fmt: skip
            begin = False
            for w in range(W):
                if go[w] and t_ns[w] == next_frame[w]:
                    for n in range(N):
                        for j in range(STATE_SIZE):
                            cam[w, n, j] = states[w, n, j]
                    next_frame[w] += camera_ns
                    framed[w] = True
        pairs = end_period(go, states, active, radius, period_start, model, eff, dead, G, pidx)
        for k in range(pairs.shape[0]):
            w, a, b = pairs[k, 0], pairs[k, 1], pairs[k, 2]
            touched[w, a], touched[w, b] = b, a
        for w in range(W):
            if framed[w]:
                go[w] = False
