"""The compiled parcel step: every airborne parcel of droplets moved by one step through the air, and what
it leaves on leaves, wood and the ground, what evaporates and what leaves the domain.

Per parcel (``n`` droplets of diameter ``d`` at ``x`` moving at ``v``), per step ``dt``:

1. **The air's velocity** ``u`` at ``x``: the mean wind ``W(h) s(x)`` along its heading (the log profile
   of the ``wind`` section, ``s`` the canopy's shelter), a turbulent part per parcel (an
   Ornstein-Uhlenbeck process with the Dryden intensities and Lagrangian time scales ``L / U`` at the
   parcel's height, the random-walk dispersion AGDISP uses; inside a rotor wake, the wake's own
   turbulence where it is stronger: :data:`WAKE_INTENSITY` of its speed over eddies of its width), and
   the wakes of every rotor
   (:func:`droneulator.world.downwash.wake_speed`, one actuator disk per rotor so that the near field
   under each rotor is resolved; rotors' wakes combine as their momentum fluxes add, by root sum of
   squares; each wake is skewed by the air's horizontal motion relative to the rotor, and turns into a
   radial wall jet where it meets the ground); in forward flight the wake rolls up into a trailing vortex
   pair (:func:`vortex_row`) that takes over from the jets as the airspeed grows past the induced
   velocity, and that sinks and spreads apart beside the ground, carrying droplets out to the sides.
2. **Drag and gravity**, integrated exactly for the step with the relaxation time ``tau`` frozen at its
   start (:mod:`droneulator.spray.droplets`): ``v' = v_eq + (v - v_eq) e^{-dt/tau}``,
   ``x' = x + v_eq dt + (v - v_eq) tau (1 - e^{-dt/tau})`` with ``v_eq = u + g' tau``. Stable at any step
   (a 50 um droplet's tau is a few ms) and exact at terminal velocity.
3. **Evaporation** by the d^2 law at the step's Reynolds number, down to the droplet's non-volatile
   residue (``spray.nonvolatile_fraction`` of its volume), which flies on; without one, below ``d_min``
   the rest evaporates.
4. **Capture** along the step's path ``ds`` through leaves and wood: a share
   ``1 - exp(-eta a ds)`` of the droplets is deposited, ``a`` the cell's interception density
   (:mod:`droneulator.spray.targets`) and ``eta`` the collection efficiency: inertial impaction on a
   collector of size ``L``, ``(Stk / (Stk + 0.5))^2`` with ``Stk = rho_l d^2 |v| / (9 mu L)`` (Langmuir
   & Blodgett's form), or sedimentation (the share of the parcel's motion that is its settling,
   ``g' tau / |v|``), whichever is larger.
5. **The ground** (z = 0) takes what reaches it, at the crossing point, into the deposit grid; what
   crosses the domain's sides or ceiling has left it (drift, airborne).

Parcels are split into chunks, one accumulator row per chunk, so the parallel loop never races and its
result does not depend on the thread count; the turbulence is drawn from a counter-based generator
(parcel id, step) for the same reason.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from droneulator.config.wind import WindConfig
from droneulator.spray.droplets import EVAPORATION_UM2_S_C, VENTILATION, drag_factor
from droneulator.world.downwash import RHO, SPREAD, Z_MAX, disk_wake_speed

#: the ledger's columns (volumes, m^3): leaves; trunks, branches, posts, wires; ground on the grid; ground
#: beyond it; evaporated; left the domain (drift, airborne)
CANOPY, TRUNKS, BRANCHES, POSTS, WIRES, GROUND, GROUND_OFF, EVAPORATED, LEFT = range(9)
LEDGER = ("canopy", "trunks", "branches", "posts", "wires", "ground", "ground_off_grid", "evaporated", "left")
#: a rotor row: position (3), thrust axis (3, unit, world), its induced velocity at the disk (m/s), its
#: radius (m), the horizontal velocity of the air relative to the rotor (2, m/s) that skews its wake, the
#: horizontal distance (m) beyond which neither its wake nor its wall jet reaches (:func:`reach`), and the
#: share of the vehicle's wake still a jet (the rest has rolled up into its trailing vortex pair); then its
#: wall jet, the same for every parcel of a step (:func:`ground_jets`): where the wake's axis meets the
#: ground (x, y), the jet's width and its layer's thickness there (m), its speed at one width out (m/s)
#: and whether the wake turns into a wall jet at all (1 or 0)
ROTOR_SIZE = 18
#: a vehicle's trailing vortex pair: its position (x, y), the unit direction it moves through the air
#: (2), its airspeed (m/s), the pair's starting height (m), circulation (m^2/s), half separation (m),
#: descent speed (m/s), lowest height (m) and the constant C of its path beside the ground, decay rate
#: (1/s), core radius (m), the share of the wake it carries, and how long it is followed (s)
VORTEX_SIZE = 15
#: what :func:`air_velocity` writes: mean wind (3), wakes (3), the wake's speed and width
AIR_SIZE = 8
#: the collection efficiency's constant (Langmuir & Blodgett's cylinder fit, squared form)
STK_HALF = 0.5
#: the turbulence intensity of a rotor wake: a round jet's centreline fluctuations are about a quarter of
#: its centreline speed (Wygnanski & Fiedler 1969; Bauersfeld et al. 2024 describe a quadrotor's wake as
#: such a jet)
WAKE_INTENSITY = 0.25
#: how far from its impingement point a wall jet is followed, in wake widths
WALL_JET_REACH = 10.0
_K1 = np.uint64(0x9E3779B97F4A7C15)
_K2 = np.uint64(0xBF58476D1CE4E5B9)
_K3 = np.uint64(0x94D049BB133111EB)


@numba.njit(cache=True)
def _mix(z: np.uint64) -> np.uint64:
    """splitmix64's finaliser."""
    z = (z ^ (z >> np.uint64(30))) * _K2
    z = (z ^ (z >> np.uint64(27))) * _K3
    return z ^ (z >> np.uint64(31))


@numba.njit(cache=True)
def _uniform(key: np.uint64, k: int) -> float:
    """The ``k``-th uniform in (0, 1) of stream ``key``."""
    z = _mix(key + np.uint64(k + 1) * _K1)
    return ((z >> np.uint64(11)) + 0.5) * (1.0 / 9007199254740992.0)


@numba.njit(cache=True)
def _lookup(dims: np.ndarray, origin: np.ndarray, cell: float, x: float, y: float, z: float) -> int:
    """Flat (C order) index of the cell holding (x, y, z) in a grid of shape ``dims``, -1 outside."""
    i = int(math.floor((x - origin[0]) / cell))
    j = int(math.floor((y - origin[1]) / cell))
    k = int(math.floor((z - origin[2]) / cell))
    nx, ny, nz = dims[0], dims[1], dims[2]
    if i < 0 or j < 0 or k < 0 or i >= nx or j >= ny or k >= nz:
        return -1
    return (i * ny + j) * nz + k


def wind_row(wind: WindConfig) -> np.ndarray:
    """The mean wind as the kernel reads it: heading (x, y), W20 (m/s), roughness length z0 (m), 1 for the
    log profile (0: uniform), and W20 / ln(20 ft / z0)."""
    hx, hy = wind.heading
    log = wind.profile == "log"
    scale = wind.speed_m_s / math.log(6.096 / wind.roughness_m)
    return np.array([hx, hy, wind.speed_m_s, wind.roughness_m, 1.0 if log else 0.0, scale])


#: the trailing vortices' core radius, as a share of their separation, and the turbulence velocity (m/s)
#: that decays them (AGDISP's decay law, dGamma/dt = -0.45 q Gamma / b)
VORTEX_CORE = 0.1
VORTEX_Q = 0.5
#: how long (s) a vortex pair is followed behind its vehicle
VORTEX_AGE = 20.0


def vortex_row(
    position: np.ndarray, air_velocity_xy: np.ndarray, thrust: float, span: float, disk_area: float,
    height: float,
) -> np.ndarray | None:
    """A vehicle's trailing vortex pair (a :data:`VORTEX_SIZE` row; None below 0.5 m/s of airspeed): a
    lifting system of span ``span`` (m) carrying ``thrust`` (N) at airspeed ``|air_velocity_xy|`` sheds an
    elliptically loaded wing's pair, ``b = pi/4 span`` apart with circulation ``Gamma = T / (rho V b)``,
    sinking at ``Gamma / (2 pi b)``. It carries the share ``mu^2 / (1 + mu^2)`` of the wake, ``mu`` the
    airspeed over the hover induced velocity: a jet in hover, a vortex pair in fast flight."""
    speed = float(np.hypot(*air_velocity_xy))
    if speed < 0.5 or thrust <= 0.0 or height <= 0.0:
        return None
    b = math.pi / 4.0 * span
    gamma = thrust / (RHO * speed * b)
    y0, z0 = b / 2.0, float(height)
    c = 1.0 / y0**2 + 1.0 / z0**2
    vh = math.sqrt(thrust / (2.0 * RHO * disk_area))
    mu2 = (speed / vh) ** 2
    d = np.asarray(air_velocity_xy, float) / speed
    return np.array([
        position[0], position[1], d[0], d[1], speed, z0, gamma, y0, gamma / (2.0 * math.pi * b),
        1.0 / math.sqrt(c), c, 0.45 * VORTEX_Q / b, VORTEX_CORE * b, mu2 / (1.0 + mu2), VORTEX_AGE,
    ])  # fmt: skip


def reach(rows: np.ndarray) -> np.ndarray:
    """Each rotor row's horizontal reach (m): the widest its skewed wake (3 widths at the deepest it is
    followed, moved by the skew) or its wall jet (:data:`WALL_JET_REACH` widths round the impingement
    point) gets from the rotor, with a metre to spare for the axis's tilt."""
    vh, r0 = np.maximum(rows[:, 6], 1e-6), rows[:, 7]
    skew = np.hypot(rows[:, 8], rows[:, 9])
    b = r0 / math.sqrt(2.0) + SPREAD * Z_MAX
    down = np.minimum(np.maximum(rows[:, 2], 0.0), Z_MAX)
    wake = 3.0 * b + skew * Z_MAX / (1.5 * vh) + Z_MAX * np.hypot(rows[:, 3], rows[:, 4])
    wall = WALL_JET_REACH * (r0 / math.sqrt(2.0) + SPREAD * down) + skew * down / (1.5 * vh)
    return np.maximum(wake, wall) + 1.0


@numba.njit(cache=True)
def air_velocity(
    x: float,
    y: float,
    z: float,
    wind: np.ndarray,
    rotors: np.ndarray,
    vortices: np.ndarray,
    out: np.ndarray,
) -> None:
    """At a point: the mean wind (``wind``: a :func:`wind_row`) into
    ``out[0:3]``, every rotor's wake into ``out[3:6]``, and the wake's speed and the width of the widest
    wake there into ``out[6:8]`` (for its turbulence); the shelter and the wind's turbulence are the
    caller's."""
    h = max(z, 0.0)
    mean = wind[2]
    if wind[4] > 0.5:  # the log profile, zero below the roughness length
        mean = wind[5] * math.log(h / wind[3]) if h > wind[3] else 0.0
    out[0] = wind[0] * mean
    out[1] = wind[1] * mean
    out[2] = 0.0
    out[3] = 0.0
    out[4] = 0.0
    out[5] = 0.0
    out[6] = 0.0
    out[7] = 0.0
    sq = 0.0
    dx_ = 0.0
    dy_ = 0.0
    dz_ = 0.0
    for r in range(rotors.shape[0]):
        vh, r0 = rotors[r, 6], rotors[r, 7]
        if vh <= 0.0:
            continue
        rx, ry, rz = x - rotors[r, 0], y - rotors[r, 1], z - rotors[r, 2]
        if rx * rx + ry * ry > rotors[r, 10] * rotors[r, 10]:
            continue  # too far to the side for this rotor's wake or wall jet
        ax, ay, az = rotors[r, 3], rotors[r, 4], rotors[r, 5]
        depth = -(rx * ax + ry * ay + rz * az)  # below the rotor plane, along the axis
        if depth <= 0.0:
            continue
        lag = depth / (1.5 * vh)  # time the wake takes to get here: it drifts with the air meanwhile
        px = rx + depth * ax - rotors[r, 8] * lag
        py = ry + depth * ay - rotors[r, 9] * lag
        pz = rz + depth * az
        w = 0.0
        if depth <= Z_MAX:  # within 3 widths of the axis (disk_wake_speed's own cut, without a root)
            b = r0 / math.sqrt(2.0) + SPREAD * depth
            r2 = px * px + py * py + pz * pz
            if r2 <= 9.0 * b * b:
                w = disk_wake_speed(vh, r0, depth, math.sqrt(r2)) * rotors[r, 11]
        if w > 0.0:
            out[7] = max(out[7], r0 / math.sqrt(2.0) + SPREAD * depth)
        # the ground: where the wake's axis (down the thrust axis) meets it, the jet stops and spreads
        # out as a wall jet (:func:`ground_jets`)
        if rotors[r, 17] > 0.0:
            b_g, delta = rotors[r, 14], rotors[r, 15]
            fade = math.exp(-h / delta) if h < 8.0 * delta else 0.0
            w *= 1.0 - fade
            ex, ey = x - rotors[r, 12], y - rotors[r, 13]
            rg = math.sqrt(ex * ex + ey * ey)
            if fade > 0.0 and rg > 1e-6 and rg < WALL_JET_REACH * b_g:
                ug = rotors[r, 16] * fade
                ug *= rg / b_g if rg < b_g else b_g / rg
                out[3] += ug * ex / rg
                out[4] += ug * ey / rg
                out[6] = max(out[6], ug)
                out[7] = max(out[7], delta)
        if w > 0.0:
            sq += w * w
            dx_ -= w * ax
            dy_ -= w * ay
            dz_ -= w * az
    if sq > 0.0:
        norm = math.sqrt(dx_ * dx_ + dy_ * dy_ + dz_ * dz_)
        if norm > 0.0:
            s = math.sqrt(sq) / norm
            out[3] += dx_ * s
            out[4] += dy_ * s
            out[5] += dz_ * s
        out[6] = max(out[6], math.sqrt(sq))
    for k in range(vortices.shape[0]):
        _vortex_pair(x, y, h, vortices[k], out)


@numba.njit(cache=True)
def ground_jets(rotors: np.ndarray) -> None:
    """Fill each rotor row's wall-jet columns (12 to 17, :data:`ROTOR_SIZE`) from its first twelve: a
    wake whose axis points down (its thrust axis more than 0.2 up) and meets the ground within 15 m turns
    there, where it has drifted with the air on its way down, into a wall jet of the wake's width, its
    layer half as thick, at the speed the wake has at the ground (its jet share's)."""
    for r in range(rotors.shape[0]):
        vh, r0, az = rotors[r, 6], rotors[r, 7], rotors[r, 5]
        reach = rotors[r, 2] / max(az, 1e-3)
        rotors[r, 12:18] = 0.0
        if vh <= 0.0 or not (az > 0.2 and reach < 15.0):
            continue
        b_g = r0 / math.sqrt(2.0) + SPREAD * reach
        lag_g = reach / (1.5 * vh)
        rotors[r, 12] = rotors[r, 0] - reach * rotors[r, 3] + rotors[r, 8] * lag_g
        rotors[r, 13] = rotors[r, 1] - reach * rotors[r, 4] + rotors[r, 9] * lag_g
        rotors[r, 14] = b_g
        rotors[r, 15] = 0.5 * b_g
        rotors[r, 16] = disk_wake_speed(vh, r0, reach, 0.0) * rotors[r, 11]
        rotors[r, 17] = 1.0


@numba.njit(cache=True, fastmath=True)
def _vortex_pair(x: float, y: float, h: float, v: np.ndarray, out: np.ndarray) -> None:
    """The velocity a vehicle's trailing vortex pair (row ``v``, :data:`VORTEX_SIZE`) induces at (x, y) at
    height ``h``, added to ``out[3:6]``: two line vortices left and right of the track behind it, with
    their images below the ground, sinking at their mutual induction and spreading apart beside the ground
    on Lamb's hyperbola ``1/y^2 + 1/z^2 = C``, decaying in time (Rankine cores)."""
    rx, ry = x - v[0], y - v[1]
    dx, dy, speed = v[2], v[3], v[4]
    along = -(rx * dx + ry * dy)  # behind the vehicle, along its track through the air
    if along <= 0.0 or along > speed * v[14]:
        return
    t = along / speed
    lat = -rx * dy + ry * dx  # to the left of the track
    z0, zinf, c = v[5], v[9], v[10]
    zv = z0
    if z0 > zinf:
        zv = zinf + (z0 - zinf) * math.exp(-v[8] * t / (z0 - zinf))
    yv = 1.0 / math.sqrt(max(c - 1.0 / (zv * zv), 1e-12))
    g = v[6] * math.exp(-v[11] * t) * v[13] / (2.0 * math.pi)
    rc2 = v[12] * v[12]
    vl = 0.0
    vz = 0.0
    # (position across the track, height, circulation sign): the pair, turning down between the cores,
    # and its images in the ground
    for sy, sz, sign in ((1.0, 1.0, 1.0), (-1.0, 1.0, -1.0), (1.0, -1.0, -1.0), (-1.0, -1.0, 1.0)):
        py, pz = lat - sy * yv, h - sz * zv
        q = sign * g / (py * py + pz * pz + rc2)
        vl -= q * pz
        vz += q * py
    out[3] += -vl * dy
    out[4] += vl * dx
    out[5] += vz


@numba.njit(cache=True, fastmath=True)
def _chunk(
    c: int,
    per: int,
    x: np.ndarray,
    v: np.ndarray,
    turb: np.ndarray,
    d: np.ndarray,
    dres: np.ndarray,
    n: np.ndarray,
    ids: np.ndarray,
    count: int,
    dt: float,
    step: int,
    seed: int,
    air: np.ndarray,
    wind: np.ndarray,
    turbulence: np.ndarray,
    rotors: np.ndarray,
    vortices: np.ndarray,
    shelter: np.ndarray,
    leaf: np.ndarray,
    wood: np.ndarray,
    plant: np.ndarray,
    third: np.ndarray,
    wood_class: np.ndarray,
    dims: np.ndarray,
    grid_origin: np.ndarray,
    cell: float,
    ground_origin: np.ndarray,
    ground_cell: float,
    domain: np.ndarray,
    ledger: np.ndarray,
    dose: np.ndarray,
    ground: np.ndarray,
) -> None:
    """Advance chunk ``c`` (parcels ``c per .. (c + 1) per - 1``) of :func:`step_parcels`."""
    rho_a, mu, rho_l, dT, dmin = air[0], air[1], air[2], air[3], air[4]
    leaf_size, wood_size, g = air[5], air[6], air[7]
    gp = g * (1.0 - rho_a / rho_l)
    lam0 = EVAPORATION_UM2_S_C * 1e-12 * dT
    vol = math.pi / 6.0
    heights = turbulence.shape[0]
    u = np.empty(AIR_SIZE)
    for i in range(c * per, min(count, (c + 1) * per)):
        if n[i] <= 0.0:
            continue
        x0, y0, z0 = x[i, 0], x[i, 1], x[i, 2]
        air_velocity(x0, y0, z0, wind, rotors, vortices, u)
        # the canopy shelters the mean wind and its turbulence
        s = 1.0
        k = _lookup(dims, grid_origin, cell, x0, y0, z0)
        if k >= 0:
            s = shelter[k]
        hk = min(max(int(z0), 0), heights - 1)
        eu, qu, ew, qw = turbulence[hk, 0], turbulence[hk, 1] * s, turbulence[hk, 2], turbulence[hk, 3] * s
        if u[6] > 0.0:
            # a rotor wake is a turbulent jet: fluctuations of WAKE_INTENSITY of its speed, with eddies
            # of its width turning over in width / speed; where they are stronger they take over
            sig = WAKE_INTENSITY * u[6]
            e = math.exp(-dt * u[6] / max(u[7], 1e-3))
            q = sig * math.sqrt(1.0 - e * e)
            if q > qu:
                eu, qu = e, q
            if q > qw:
                ew, qw = e, q
        if qu > 0.0 or qw > 0.0:
            key = _mix(np.uint64(seed) * _K3 + np.uint64(ids[i]) * _K1 + np.uint64(step) * _K2)
            # three standard normals: Box-Muller on two pairs of this parcel's uniforms at this step
            ra = math.sqrt(-2.0 * math.log(_uniform(key, 0)))
            pa = 2.0 * math.pi * _uniform(key, 1)
            rb = math.sqrt(-2.0 * math.log(_uniform(key, 2))) * math.cos(2.0 * math.pi * _uniform(key, 3))
            turb[i, 0] = turb[i, 0] * eu + qu * ra * math.cos(pa)
            turb[i, 1] = turb[i, 1] * eu + qu * ra * math.sin(pa)
            turb[i, 2] = turb[i, 2] * ew + qw * rb
        else:
            turb[i, 0] *= eu
            turb[i, 1] *= eu
            turb[i, 2] *= ew
        mx = u[0] * s + turb[i, 0] + u[3]
        my = u[1] * s + turb[i, 1] + u[4]
        mz = turb[i, 2] + u[5]
        # drag and gravity, exact for the step's relaxation time
        rx, ry, rz = v[i, 0] - mx, v[i, 1] - my, v[i, 2] - mz
        slip = math.sqrt(rx * rx + ry * ry + rz * rz)
        di = d[i]
        re = rho_a * slip * di / mu
        tau = rho_l * di * di / (18.0 * mu * drag_factor(re))
        e = math.exp(-dt / tau)
        ex, ey, ez = mx, my, mz - gp * tau
        f = tau * (1.0 - e)
        x1 = x0 + ex * dt + (v[i, 0] - ex) * f
        y1 = y0 + ey * dt + (v[i, 1] - ey) * f
        z1 = z0 + ez * dt + (v[i, 2] - ez) * f
        v[i, 0] = ex + (v[i, 0] - ex) * e
        v[i, 1] = ey + (v[i, 1] - ey) * e
        v[i, 2] = ez + (v[i, 2] - ez) * e
        # evaporation, down to the droplet's non-volatile residue (if any)
        d2 = di * di - lam0 * (1.0 + VENTILATION * math.sqrt(re)) * dt
        floor = dres[i]
        if floor <= dmin and d2 <= dmin * dmin:
            ledger[c, EVAPORATED] += n[i] * vol * di * di * di
            n[i] = 0.0
            continue
        dn = math.sqrt(max(d2, floor * floor))
        ledger[c, EVAPORATED] += n[i] * vol * (di * di * di - dn * dn * dn)
        d[i] = dn
        drop = vol * dn * dn * dn
        # capture along the path through leaves and wood (at the path's midpoint)
        ds = math.sqrt((x1 - x0) ** 2 + (y1 - y0) ** 2 + (z1 - z0) ** 2)
        k = _lookup(dims, grid_origin, cell, 0.5 * (x0 + x1), 0.5 * (y0 + y1), 0.5 * (z0 + z1))
        if k >= 0 and ds > 0.0:
            speed = math.sqrt(v[i, 0] ** 2 + v[i, 1] ** 2 + v[i, 2] ** 2)
            settle = min(gp * tau / max(speed, 1e-9), 1.0)
            a_leaf = leaf[k]
            if a_leaf > 0.0:
                stk = rho_l * dn * dn * speed / (9.0 * mu * leaf_size)
                eta = max((stk / (stk + STK_HALF)) ** 2, settle)
                caught = n[i] * (1.0 - math.exp(-eta * a_leaf * ds))
                p = plant[k]
                if p >= 0:
                    dose[c, p, third[k]] += caught * drop
                ledger[c, CANOPY] += caught * drop
                n[i] -= caught
            a_wood = wood[k]
            if a_wood > 0.0:
                stk = rho_l * dn * dn * speed / (9.0 * mu * wood_size)
                eta = max((stk / (stk + STK_HALF)) ** 2, settle)
                caught = n[i] * (1.0 - math.exp(-eta * a_wood * ds))
                ledger[c, TRUNKS + max(wood_class[k], 0)] += caught * drop
                n[i] -= caught
        if z1 <= 0.0:  # the ground, where the path crosses it
            t = z0 / (z0 - z1) if z0 > z1 else 1.0
            gx, gy = x0 + t * (x1 - x0), y0 + t * (y1 - y0)
            gi = int(math.floor((gx - ground_origin[0]) / ground_cell))
            gj = int(math.floor((gy - ground_origin[1]) / ground_cell))
            if 0 <= gi < ground.shape[1] and 0 <= gj < ground.shape[2]:
                ground[c, gi, gj] += n[i] * drop
                ledger[c, GROUND] += n[i] * drop
            else:
                ledger[c, GROUND_OFF] += n[i] * drop
            n[i] = 0.0
            continue
        if x1 < domain[0] or x1 > domain[1] or y1 < domain[2] or y1 > domain[3] or z1 > domain[4]:
            ledger[c, LEFT] += n[i] * drop
            n[i] = 0.0
            continue
        x[i, 0], x[i, 1], x[i, 2] = x1, y1, z1


#: where the parcel count and the ledger stand among :func:`step_parcels`'s arguments
_COUNT, _LEDGER = 7, 28


@numba.njit(cache=True, fastmath=True)
def _serial(*args):  # noqa: ANN002, ANN202 - step_parcels's arguments, passed on
    chunks = args[_LEDGER].shape[0]
    per = (args[_COUNT] + chunks - 1) // chunks
    for c in range(chunks):
        _chunk(c, per, *args)


@numba.njit(cache=True, parallel=True, fastmath=True)
def _parallel(*args):  # noqa: ANN002, ANN202 - step_parcels's arguments, passed on
    chunks = args[_LEDGER].shape[0]
    per = (args[_COUNT] + chunks - 1) // chunks
    for c in numba.prange(chunks):
        _chunk(np.int64(c), per, *args)


#: below this many parcels a step runs on one thread (waking the others costs more than it saves)
PARALLEL_PARCELS = 20_000


def step_parcels(*args: object) -> None:
    """Advance parcels ``0..count-1`` (those with ``n > 0``) by ``dt`` (compiled twice, serial and
    parallel, chosen by the parcel count).

    ``dres``: each parcel's residue diameter (its non-volatile share's, m), where evaporation stops;
    ``air`` = (rho_air, mu, rho_liquid, wet-bulb depression C, d_min m, leaf size m, wood size m, g);
    The targets' grids (``shelter``, ``leaf``, ``wood``, ``plant``, ``third``, ``wood_class``) come
    flattened (C order) from a grid of shape ``dims``.
    ``turbulence``: a table over heights 0, 1, .. m of the turbulence's step (for ``dt``): its decay
    ``e = exp(-dt / T)`` and kick ``sigma sqrt(1 - e^2)``, along the ground (u, v) and up (w); ``shelter``
    the mean wind's factor on the targets' grid; ``domain`` = (x0, x1, y0, y1, ceiling);
    ``ledger`` (chunks, len(LEDGER)), ``dose`` (chunks, plants, 3), ``ground`` (chunks, gx, gy)."""
    (_parallel if args[_COUNT] >= PARALLEL_PARCELS else _serial)(*args)  # type: ignore[operator]
