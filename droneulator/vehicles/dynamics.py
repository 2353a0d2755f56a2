"""RotorPy's multirotor model, integrated fast, with spring-damper ground contact.

``rotorpy.vehicles.multirotor.Multirotor`` integrates each control period with SciPy's adaptive
RK45 and rebuilds dicts and SciPy rotations at every derivative call (~5x real time at 100 Hz
here). :class:`FastMultirotor` evaluates the same equations of motion in the air — rotor thrust and
yaw moments, motor lag, parasitic drag, rotor drag, induced inflow, translational lift, flapping —
compiled with numba and integrated with fixed-step RK4. Its trajectories are checked against
RotorPy's own integration in the tests and benchmarks.

On the ground it differs from RotorPy on purpose. RotorPy clamps the vehicle to z = 0 and zeroes
its vertical velocity in one step, which an accelerometer sees as a spike of tens of g. Here four
feet under the rotors (:class:`GroundContact`) press on the plane z = 0 through stiff springs with
asymmetric dampers and regularised Coulomb friction, so a touchdown decelerates over many RK4
sub-steps. Their forces are exactly zero while every foot and hub is above the ground.

State vector layout (RotorPy's ``_pack_state``): ``x[0:3] v[3:6] q[6:10] (x,y,z,w) w[10:13]
wind[13:16] rotor_speeds[16:20]``, defined in :mod:`droneulator.state`. Code outside the kernels names
these fields through :data:`~droneulator.state.STATE` (``s[STATE.q]``); the compiled kernels below
index the vector directly. Each step also accumulates the IMU quantities and touchdowns into an
output vector laid out as :data:`OUTPUT`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, NamedTuple

import numba
import numpy as np

from droneulator.frames_numba import quat_to_matrix_into
from droneulator.scenes.collision import sdf_gradient, sdf_lookup
from droneulator.state import STATE, STATE_SIZE

#: gravity of the model (m/s^2), as in RotorPy
GRAVITY = 9.81

# Layout of the packed parameter vector.
_MASS, _G, _KETA, _KM, _KD, _KZ, _KH, _KFLAP, _TAU, _WMIN, _WMAX, _AERO, _GROUND = range(13)
# ground contact, per foot: stiffness (N/m), compression and rebound damping (N s/m), friction
# coefficient, slip speed of the friction regularisation (m/s), foot depth below the body origin
# (m), and the largest distance of a foot from the body origin (m)
_CK, _CCOMP, _CREB, _MU, _VSLIP, _FOOT, _REACH = range(13, 20)
_CD = 20  # 3 drag coefficients
_INERTIA = 23  # 9 entries, row-major
_INV_INERTIA = 32  # 9 entries
_N_PARAMS = 41
#: where the packed vector keeps the top rotor speed (rad/s): the battery lowers it as the voltage sags
PARAM_WMAX = _WMAX


# Layout of the step output vector (sums over the integrated time since the caller zeroed it).
_OUT_SF, _OUT_ACC, _OUT_T, _OUT_TD_SPEED, _OUT_TD_T, _OUT_TD_X = 0, 3, 6, 7, 8, 9


class OutputLayout(NamedTuple):
    """Named parts of the vector :meth:`FastMultirotor.step` accumulates into.

    ``specific_force``: integral over time of the body-frame (FLU) specific force, i.e. the
    non-gravitational force per unit mass (m/s); ``delta_v``: integral of the world acceleration
    (m/s); ``elapsed``: time integrated (s; less than the step when a scene collision stopped it);
    ``touchdown_speed``: the largest downward speed (m/s) at which the feet touched the ground
    (0 if they did not); ``touchdown_time``: when, in integrated time; ``touchdown_position``:
    where the body origin was then (world, m).
    """

    specific_force: slice = slice(_OUT_SF, _OUT_SF + 3)
    delta_v: slice = slice(_OUT_ACC, _OUT_ACC + 3)
    elapsed: int = _OUT_T
    touchdown_speed: int = _OUT_TD_SPEED
    touchdown_time: int = _OUT_TD_T
    touchdown_position: slice = slice(_OUT_TD_X, _OUT_TD_X + 3)


#: the step output's layout
OUTPUT = OutputLayout()
OUTPUT_SIZE = _OUT_TD_X + 3


@dataclass(frozen=True)
class GroundContact:
    """Four feet under the rotor hubs on spring-damper legs, with friction against the ground.

    The rotor hubs touch too, so a vehicle that tips over rests on them (flat, not on its side)
    and one upside down rests with its origin g / (2 pi f)^2 below the plane.

    The legs are sized from the vehicle's mass so every parameter set behaves alike:
    ``frequency_hz`` is the natural frequency of the vehicle bouncing on its four legs
    (stiffness ``m (2 pi f)^2`` in total), ``damping_ratio`` the damping while a leg compresses
    and ``rebound_damping_ratio`` while it extends (higher, like a shock absorber, so a touchdown
    at hover thrust does not throw the vehicle back up). The feet sit ``g / (2 pi f)^2`` below the
    rotor plane, so the vehicle rests with its body origin exactly at z = 0 under its own weight.
    Friction is Coulomb with coefficient ``friction``, smoothed below ``slip_speed`` (m/s) into a
    viscous law so that the stiff stick phase stays stable for RK4.
    """

    frequency_hz: float = 3.0
    damping_ratio: float = 1.0
    rebound_damping_ratio: float = 3.0
    friction: float = 0.5
    slip_speed: float = 0.05

    def __post_init__(self) -> None:
        for name in ("frequency_hz", "damping_ratio", "rebound_damping_ratio", "slip_speed"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"ground contact {name} must be a positive number, got {value!r}")
        if not (math.isfinite(self.friction) and self.friction >= 0):
            raise ValueError(f"ground contact friction must be >= 0, got {self.friction!r}")

    @property
    def omega(self) -> float:
        return 2.0 * math.pi * self.frequency_hz

    @property
    def foot_depth(self) -> float:
        """Distance of the feet below the rotor plane (m): the legs' compression under the weight."""
        return GRAVITY / self.omega**2


def pack_params(
    quad_params: dict[str, Any],
    aero: bool = True,
    ground: bool = True,
    contact: GroundContact | None = None,
) -> tuple[np.ndarray, ...]:
    """Pack a RotorPy parameter dict into (scalars, rotor_geometry (4,3), rotor_directions (4,))."""
    if quad_params["num_rotors"] != 4:
        raise ValueError("only quadrotors are supported")
    contact = contact or GroundContact()
    mass = float(quad_params["mass"])
    p = np.zeros(_N_PARAMS)
    p[_MASS] = mass
    p[_G] = GRAVITY
    p[_KETA] = quad_params["k_eta"]
    p[_KM] = quad_params["k_m"]
    p[_KD] = quad_params.get("k_d", 0.0)
    p[_KZ] = quad_params.get("k_z", 0.0)
    p[_KH] = quad_params.get("k_h", 0.0)
    p[_KFLAP] = quad_params.get("k_flap", 0.0)
    p[_TAU] = quad_params["tau_m"]
    p[_WMIN] = quad_params["rotor_speed_min"]
    p[_WMAX] = quad_params["rotor_speed_max"]
    p[_AERO] = 1.0 if aero else 0.0
    p[_GROUND] = 1.0 if ground else 0.0
    p[_CK] = mass * contact.omega**2 / 4.0
    p[_CCOMP] = 2.0 * contact.damping_ratio * mass * contact.omega / 4.0
    p[_CREB] = 2.0 * contact.rebound_damping_ratio * mass * contact.omega / 4.0
    p[_MU] = contact.friction
    p[_VSLIP] = contact.slip_speed
    p[_FOOT] = contact.foot_depth
    p[_CD : _CD + 3] = [
        quad_params.get("c_Dx", 0.0),
        quad_params.get("c_Dy", 0.0),
        quad_params.get("c_Dz", 0.0),
    ]
    inertia = np.array(
        [
            [quad_params["Ixx"], quad_params["Ixy"], quad_params["Ixz"]],
            [quad_params["Ixy"], quad_params["Iyy"], quad_params["Iyz"]],
            [quad_params["Ixz"], quad_params["Iyz"], quad_params["Izz"]],
        ]
    )
    p[_INERTIA : _INERTIA + 9] = inertia.ravel()
    p[_INV_INERTIA : _INV_INERTIA + 9] = np.linalg.inv(inertia).ravel()
    geometry = np.array([quad_params["rotor_pos"][k] for k in quad_params["rotor_pos"]], dtype=float)
    directions = np.asarray(quad_params["rotor_directions"], dtype=float)
    p[_REACH] = float(np.max(np.hypot(np.hypot(geometry[:, 0], geometry[:, 1]), p[_FOOT])))
    return p, geometry, directions


def with_payload(quad_params: dict[str, Any], kg: float, offset: Any = (0.0, 0.0, 0.0)) -> dict[str, Any]:
    """A copy of ``quad_params`` carrying a point mass of ``kg`` at ``offset`` (body FLU, m, from the
    centre of mass): the mass grows by ``kg`` and the inertia by ``kg (|r|^2 I - r r^T)`` (parallel axes;
    the shift of the centre of mass itself is left out, as RotorPy's model has the origin at it)."""
    r = np.asarray(offset, dtype=float).reshape(3)
    extra = kg * (float(r @ r) * np.eye(3) - np.outer(r, r))
    q = dict(quad_params)
    q["mass"] = float(quad_params["mass"]) + kg
    for (a, b), name in zip(((0, 0), (1, 1), (2, 2), (0, 1), (1, 2), (0, 2)),
                            ("Ixx", "Iyy", "Izz", "Ixy", "Iyz", "Ixz"), strict=True):  # fmt: skip
        q[name] = float(quad_params[name]) + float(extra[a, b])
    return q


@numba.njit(cache=True)
def _derivative(
    s: np.ndarray,
    cmd: np.ndarray,
    p: np.ndarray,
    geom: np.ndarray,
    dirs: np.ndarray,
    eff: np.ndarray,
    ds: np.ndarray,
    fb: np.ndarray,
    R: np.ndarray,
) -> None:
    """Write d/dt of the packed state into ``ds`` and the body specific force (m/s^2) into ``fb``.

    ``eff[i]`` is rotor ``i``'s efficiency (1: healthy, 0: no thrust; a damaged propeller or a weak
    motor): every force and moment the rotor makes (thrust, rotor drag, flapping, reaction torque) is
    scaled by it, at the same rotor speed.

    Allocation free (``R`` is a 3x3 scratch for the attitude matrix), so that many vehicles can be
    integrated in parallel without touching the allocator."""
    quat_to_matrix_into(s[6:10], R)
    qx, qy, qz, qw = s[6], s[7], s[8], s[9]
    wx, wy, wz = s[10], s[11], s[12]
    mass = p[_MASS]

    # position and quaternion kinematics (Graf's G matrix, unnormalised as in RotorPy)
    ds[0] = s[3]
    ds[1] = s[4]
    ds[2] = s[5]
    ds[6] = 0.5 * (qw * wx - qz * wy + qy * wz)
    ds[7] = 0.5 * (qz * wx + qw * wy - qx * wz)
    ds[8] = 0.5 * (-qy * wx + qx * wy + qw * wz)
    ds[9] = 0.5 * (-qx * wx - qy * wy - qz * wz)
    ds[13] = 0.0
    ds[14] = 0.0
    ds[15] = 0.0
    # first-order motor lag
    for i in range(4):
        ds[16 + i] = (cmd[i] - s[16 + i]) / p[_TAU]

    # airspeed in the body frame: R^T (v - wind)
    rx0, rx1, rx2 = s[3] - s[13], s[4] - s[14], s[5] - s[15]
    va0 = R[0, 0] * rx0 + R[1, 0] * rx1 + R[2, 0] * rx2
    va1 = R[0, 1] * rx0 + R[1, 1] * rx1 + R[2, 1] * rx2
    va2 = R[0, 2] * rx0 + R[1, 2] * rx1 + R[2, 2] * rx2
    F0 = F1 = F2 = 0.0
    M0 = M1 = M2 = 0.0
    aero = p[_AERO] > 0.5
    if aero:
        vn = math.sqrt(va0 * va0 + va1 * va1 + va2 * va2)
        F0 -= vn * p[_CD] * va0
        F1 -= vn * p[_CD + 1] * va1
        F2 -= vn * p[_CD + 2] * va2
    for i in range(4):
        om = s[16 + i]
        rx, ry, rz = geom[i, 0], geom[i, 1], geom[i, 2]
        # local airspeed at the hub: va + w x r
        lx = va0 + wy * rz - wz * ry
        ly = va1 + wz * rx - wx * rz
        lz = va2 + wx * ry - wy * rx
        fx = 0.0
        fy = 0.0
        fz = p[_KETA] * om * om
        if aero:
            fx = -om * p[_KD] * lx
            fy = -om * p[_KD] * ly
            fz += -om * p[_KZ] * lz + p[_KH] * (lx * lx + ly * ly)
            # flapping moment: -k_flap * om * (local x e3)
            M0 += -eff[i] * p[_KFLAP] * om * ly
            M1 += eff[i] * p[_KFLAP] * om * lx
        e = eff[i]
        fx *= e
        fy *= e
        fz *= e
        F0 += fx
        F1 += fy
        F2 += fz
        # moment of the hub force about the CoM, plus the rotor's reaction torque
        M0 += ry * fz - rz * fy
        M1 += rz * fx - rx * fz
        M2 += rx * fy - ry * fx + e * dirs[i] * p[_KM] * om * om

    if p[_GROUND] > 0.5 and s[2] < p[_REACH]:
        c0, c1, c2, m0, m1, m2 = _contact(s, R, p, geom)
        F0 += c0
        F1 += c1
        F2 += c2
        M0 += m0
        M1 += m1
        M2 += m2

    fb[0] = F0 / mass
    fb[1] = F1 / mass
    fb[2] = F2 / mass
    ds[3] = (R[0, 0] * F0 + R[0, 1] * F1 + R[0, 2] * F2) / mass
    ds[4] = (R[1, 0] * F0 + R[1, 1] * F1 + R[1, 2] * F2) / mass
    ds[5] = (R[2, 0] * F0 + R[2, 1] * F1 + R[2, 2] * F2 - mass * p[_G]) / mass

    J, Ji = _INERTIA, _INV_INERTIA
    Jw0 = p[J] * wx + p[J + 1] * wy + p[J + 2] * wz
    Jw1 = p[J + 3] * wx + p[J + 4] * wy + p[J + 5] * wz
    Jw2 = p[J + 6] * wx + p[J + 7] * wy + p[J + 8] * wz
    t0 = M0 - (wy * Jw2 - wz * Jw1)
    t1 = M1 - (wz * Jw0 - wx * Jw2)
    t2 = M2 - (wx * Jw1 - wy * Jw0)
    ds[10] = p[Ji] * t0 + p[Ji + 1] * t1 + p[Ji + 2] * t2
    ds[11] = p[Ji + 3] * t0 + p[Ji + 4] * t1 + p[Ji + 5] * t2
    ds[12] = p[Ji + 6] * t0 + p[Ji + 7] * t1 + p[Ji + 8] * t2


@numba.njit(cache=True)
def _contact(
    s: np.ndarray, R: np.ndarray, p: np.ndarray, geom: np.ndarray
) -> tuple[float, float, float, float, float, float]:
    """Ground force (body frame) and its moment from the contact points: ``(F, M)`` as six floats.

    The points are the four feet under the rotor hubs and the four hubs themselves, which catch a
    vehicle that tips over or lands upside down. Each point below z = 0 gets a normal force from its spring
    and damper (never pulling) and a friction force against its sliding velocity, Coulomb above the
    slip speed, viscous below it. The spring force is written as the leg's share of the weight plus
    the change from the rest compression, and summed in pairs, so that a level vehicle at rest at
    z = 0 feels exactly its weight (no drift from rounding).
    """
    wx, wy, wz = s[10], s[11], s[12]
    share = 0.25 * (p[_MASS] * p[_G])
    ax = ay = az = 0.0  # points 0, 2, 4, 6
    bx_ = by_ = bz_ = 0.0  # points 1, 3, 5, 7
    M0 = M1 = M2 = 0.0
    for k in range(8):
        bx, by = geom[k % 4, 0], geom[k % 4, 1]
        bz = -p[_FOOT] if k < 4 else 0.0
        depth = -(s[2] + R[2, 0] * bx + R[2, 1] * by + R[2, 2] * bz)
        if depth <= 0.0:
            continue
        # the point's velocity in the world: v + R (w x b)
        ux = wy * bz - wz * by
        uy = wz * bx - wx * bz
        uz = wx * by - wy * bx
        vx = s[3] + R[0, 0] * ux + R[0, 1] * uy + R[0, 2] * uz
        vy = s[4] + R[1, 0] * ux + R[1, 1] * uy + R[1, 2] * uz
        vz = s[5] + R[2, 0] * ux + R[2, 1] * uy + R[2, 2] * uz
        damping = p[_CCOMP] if vz < 0.0 else p[_CREB]
        n = share + p[_CK] * (depth - p[_FOOT]) - damping * vz  # = k depth - c vz
        if n <= 0.0:
            continue
        slip = math.sqrt(vx * vx + vy * vy + p[_VSLIP] * p[_VSLIP])
        fx = -p[_MU] * n * vx / slip
        fy = -p[_MU] * n * vy / slip
        # the world force in the body frame: R^T f
        gx = R[0, 0] * fx + R[1, 0] * fy + R[2, 0] * n
        gy = R[0, 1] * fx + R[1, 1] * fy + R[2, 1] * n
        gz = R[0, 2] * fx + R[1, 2] * fy + R[2, 2] * n
        if k % 2 == 0:
            ax += gx
            ay += gy
            az += gz
        else:
            bx_ += gx
            by_ += gy
            bz_ += gz
        M0 += by * gz - bz * gy
        M1 += bz * gx - bx * gz
        M2 += bx * gy - by * gx
    return ax + bx_, ay + by_, az + bz_, M0, M1, M2


def state_derivative(
    s: np.ndarray,
    cmd: np.ndarray,
    p: np.ndarray,
    geom: np.ndarray,
    dirs: np.ndarray,
    efficiency: np.ndarray | None = None,
) -> np.ndarray:
    """d/dt of the packed state for constant commanded rotor speeds (RotorPy ``_s_dot_fn`` in the air),
    each rotor at ``efficiency`` (four factors; None: healthy)."""
    eff = _HEALTHY if efficiency is None else np.ascontiguousarray(efficiency, dtype=np.float64)
    ds = np.empty(STATE_SIZE)
    _derivative(np.asarray(s, dtype=np.float64), np.asarray(cmd, dtype=np.float64), p, geom, dirs, eff, ds,
                np.empty(3), np.empty((3, 3)))  # fmt: skip
    return ds


@numba.njit(cache=True)
def _touching(s: np.ndarray, p: np.ndarray, geom: np.ndarray) -> bool:
    """True if any contact point (feet or hubs) is below the ground plane."""
    if p[_GROUND] < 0.5 or s[2] >= p[_REACH]:
        return False
    qx, qy, qz, qw = s[6], s[7], s[8], s[9]
    n2 = qx * qx + qy * qy + qz * qz + qw * qw
    r20 = 2.0 * (qx * qz - qy * qw) / n2
    r21 = 2.0 * (qy * qz + qx * qw) / n2
    r22 = 1.0 - 2.0 * (qx * qx + qy * qy) / n2
    lowest = s[2]
    for i in range(4):
        lowest = min(lowest, s[2] + r20 * geom[i, 0] + r21 * geom[i, 1] - max(r22, 0.0) * p[_FOOT])
    return lowest < 0.0


#: what a touch of the scene does to a row (``vehicle.contact_model``; docs/contact.md): held where it
#: touched (the caller stops it), pushed, slowed and struck (:func:`_scene_contact`), or that with its
#: rotors stopped for good
CONTACT_STOP, CONTACT_PHYSICAL, CONTACT_CRASH = 0, 1, 2
#: what a row touches: nothing, leaves (the scene grid but not its wood grid), wood
TOUCH_NONE, TOUCH_FOLIAGE, TOUCH_WOOD = 0, 1, 2
#: foliage (per unit mass): the push out along the normal per metre the collision sphere is in (1/s^2), and
#: the drag on the velocity with the sphere wholly in (1/s; less as it is less in)
FOLIAGE_STIFFNESS, FOLIAGE_DRAG = 100.0, 4.0
#: wood (per unit mass): stiffness (1/s^2; stops 3 m/s within 7 cm), damping ratio of the normal motion
#: and Coulomb friction of the sliding motion
WOOD_STIFFNESS, WOOD_DAMPING_RATIO, WOOD_FRICTION = 2000.0, 0.7, 0.5
#: rotors within this share of the arm of the hub nearest the wood are struck with it
STRUCK_SHARE = 0.3

#: rows of an integration work array (:func:`work_arrays`): the four RK4 stages, the stage input,
#: the state before the sub-step, the clamped command, then the four stages' specific forces
_K1, _K2, _K3, _K4, _TMP, _PREV, _CMD, _F1 = 0, 1, 2, 3, 4, 5, 6, 7
_WORK_ROWS = 11


def work_arrays(rows: int) -> tuple[np.ndarray, np.ndarray]:
    """Scratch space for :func:`integrate` (one set per row, reused every step)."""
    return np.zeros((rows, _WORK_ROWS, STATE_SIZE)), np.zeros((rows, 3, 3))


@numba.njit(cache=True)
def _normal(grid: np.ndarray, origin: np.ndarray, res: float, x: np.ndarray) -> np.ndarray:
    """The contact normal at ``x``: the unit gradient of ``grid``, out of the obstacle (straight up where
    the gradient vanishes)."""
    n = sdf_gradient(grid, origin, res, x)
    norm = math.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
    if norm < 1e-9:
        n[0], n[1], n[2] = 0.0, 0.0, 1.0
        return n
    return n / norm


@numba.njit(cache=True)
def _struck(s: np.ndarray, geom: np.ndarray, wood: np.ndarray, origin: np.ndarray, res: float,
            R: np.ndarray) -> int:  # fmt: skip
    """The rotors a strike on wood hits, as a bit mask: the hub nearest the wood and those within
    :data:`STRUCK_SHARE` of an arm of it (both front rotors of a head-on strike)."""
    quat_to_matrix_into(s[6:10], R)
    hub = np.empty(3)
    d = np.empty(4)
    arm = 0.0
    for i in range(4):
        for a in range(3):
            hub[a] = s[a] + R[a, 0] * geom[i, 0] + R[a, 1] * geom[i, 1] + R[a, 2] * geom[i, 2]
        d[i] = sdf_lookup(wood, origin, res, hub)
        arm = max(arm, math.sqrt(geom[i, 0] * geom[i, 0] + geom[i, 1] * geom[i, 1]))
    nearest = d.min()
    mask = 0
    for i in range(4):
        if d[i] <= nearest + STRUCK_SHARE * arm:
            mask |= 1 << i
    return mask


@numba.njit(cache=True)
def _scene_contact(s: np.ndarray, kind: int, depth: float, radius: float, grid: np.ndarray,
                   origin: np.ndarray, res: float, h: float, a: np.ndarray) -> None:  # fmt: skip
    """The scene's push on a row whose collision sphere is ``depth`` m into foliage (``kind``
    TOUCH_FOLIAGE) or wood (TOUCH_WOOD; ``grid`` the one touched), as an acceleration ``a`` (world) that
    :func:`integrate` adds to the velocity over the sub-step ``h`` after each RK4 step (explicit: stable for
    these stiffnesses at sub-steps up to a few ms). Foliage pushes out along the normal and drags; wood is
    a stiff damped spring that never pulls, with friction along it."""
    n = _normal(grid, origin, res, s[0:3])
    vn = s[3] * n[0] + s[4] * n[1] + s[5] * n[2]
    if kind == TOUCH_FOLIAGE:
        drag = FOLIAGE_DRAG * min(depth / radius, 1.0)
        for j in range(3):
            a[j] = FOLIAGE_STIFFNESS * depth * n[j] - drag * s[3 + j]
        return
    push = WOOD_STIFFNESS * depth - 2.0 * WOOD_DAMPING_RATIO * math.sqrt(WOOD_STIFFNESS) * vn
    push = max(push, 0.0)
    t0, t1, t2 = s[3] - vn * n[0], s[4] - vn * n[1], s[5] - vn * n[2]
    slip = math.sqrt(t0 * t0 + t1 * t1 + t2 * t2 + 0.05 * 0.05)
    a[0] = push * n[0] - WOOD_FRICTION * push * t0 / slip
    a[1] = push * n[1] - WOOD_FRICTION * push * t1 / slip
    a[2] = push * n[2] - WOOD_FRICTION * push * t2 / slip
    # the friction stops the sliding, it does not reverse it within a sub-step
    if h * WOOD_FRICTION * push > math.sqrt(t0 * t0 + t1 * t1 + t2 * t2):
        a[0], a[1], a[2] = push * n[0] - t0 / h, push * n[1] - t1 / h, push * n[2] - t2 / h


@numba.njit(cache=True)
def integrate(
    s: np.ndarray,
    cmd_in: np.ndarray,
    dt: float,
    n_sub: int,
    p: np.ndarray,
    geom: np.ndarray,
    dirs: np.ndarray,
    eff: np.ndarray,
    sdf: np.ndarray,
    wood: np.ndarray,
    origin: np.ndarray,
    res: float,
    radius: float,
    model: int,
    out: np.ndarray,
    work: np.ndarray,
    R: np.ndarray,
) -> int:
    """Advance ``s`` in place by ``dt`` with ``n_sub`` RK4 steps under constant rotor commands, each rotor
    at efficiency ``eff[i]`` (1: healthy; a rotor fault lowers it, :mod:`droneulator.world.faults`, and a
    strike on wood sets it to 0).

    The collision model (``sdf``; ``wood`` its wood alone) is queried after every sub-step. A contact
    under ``model`` CONTACT_STOP rolls the state back to the last collision-free sub-step and returns at
    once; under CONTACT_PHYSICAL and CONTACT_CRASH the scene pushes the row (:func:`_scene_contact`) and
    it flies on: a strike on wood sets the struck rotors' ``eff`` to 0 (:func:`_struck`), and under
    CONTACT_CRASH the first touch stops every rotor (a zero command, spun down by the motors' lag).
    Returns the newest contact begun in the call, ``kind | lost << 2`` (kind TOUCH_FOLIAGE or TOUCH_WOOD,
    ``lost`` the bit mask of the rotors it cost), 0 for none. ``out`` (:data:`OUTPUT` layout) accumulates
    the RK4-weighted specific force (the scene's push included) and velocity change of every completed
    sub-step and records the fastest touchdown of the feet on the ground. ``work`` and ``R`` are scratch
    (:func:`work_arrays`): nothing is allocated but a few small vectors while in contact.
    """
    cmd = work[_CMD]
    for i in range(4):
        cmd[i] = min(max(cmd_in[i], p[_WMIN]), p[_WMAX])
    h = dt / n_sub
    check = sdf.shape[0] > 1
    n = STATE_SIZE
    k1, k2, k3, k4 = work[_K1], work[_K2], work[_K3], work[_K4]
    f1, f2, f3, f4 = work[_F1], work[_F1 + 1], work[_F1 + 2], work[_F1 + 3]
    tmp = work[_TMP]
    prev = work[_PREV]
    touching = _touching(s, p, geom)
    # what the row touched before this call (a contact begins when the row touches more than that)
    kind = TOUCH_NONE
    if check and model != CONTACT_STOP and sdf_lookup(sdf, origin, res, s[0:3]) < radius:
        kind = TOUCH_WOOD if sdf_lookup(wood, origin, res, s[0:3]) < radius else TOUCH_FOLIAGE
    begun = 0
    for _ in range(n_sub):
        for j in range(n):
            prev[j] = s[j]
        _derivative(s, cmd, p, geom, dirs, eff, k1, f1, R)
        for j in range(n):
            tmp[j] = s[j] + 0.5 * h * k1[j]
        _derivative(tmp, cmd, p, geom, dirs, eff, k2, f2, R)
        for j in range(n):
            tmp[j] = s[j] + 0.5 * h * k2[j]
        _derivative(tmp, cmd, p, geom, dirs, eff, k3, f3, R)
        for j in range(n):
            tmp[j] = s[j] + h * k3[j]
        _derivative(tmp, cmd, p, geom, dirs, eff, k4, f4, R)
        for j in range(n):
            s[j] += (h / 6.0) * (k1[j] + 2.0 * k2[j] + 2.0 * k3[j] + k4[j])
        now_kind = TOUCH_NONE
        if check:
            d = sdf_lookup(sdf, origin, res, s[0:3])
            if d < radius:
                dw = sdf_lookup(wood, origin, res, s[0:3])
                now_kind = TOUCH_WOOD if dw < radius else TOUCH_FOLIAGE
                if model == CONTACT_STOP:
                    for j in range(n):
                        s[j] = prev[j]
                    return now_kind
                if now_kind > kind:  # a contact begins: a strike on wood costs the struck rotors
                    lost = 0
                    if model == CONTACT_CRASH:
                        lost = 15 if begun == 0 else 0
                        for i in range(4):
                            cmd[i] = 0.0
                    elif now_kind == TOUCH_WOOD:
                        struck = _struck(s, geom, wood, origin, res, R)
                        for i in range(4):
                            if struck & (1 << i) and eff[i] > 0.0:
                                eff[i] = 0.0
                                lost |= 1 << i
                    begun = max(begun & 3, now_kind) | (lost | (begun >> 2)) << 2
                acc = np.empty(3)
                if now_kind == TOUCH_WOOD:
                    _scene_contact(s, now_kind, radius - dw, radius, wood, origin, res, h, acc)
                else:
                    _scene_contact(s, now_kind, radius - d, radius, sdf, origin, res, h, acc)
                quat_to_matrix_into(s[6:10], R)
                for j in range(3):
                    s[3 + j] += h * acc[j]
                    out[_OUT_SF + j] += h * (R[0, j] * acc[0] + R[1, j] * acc[1] + R[2, j] * acc[2])
        kind = now_kind
        for j in range(3):
            out[_OUT_SF + j] += (h / 6.0) * (f1[j] + 2.0 * f2[j] + 2.0 * f3[j] + f4[j])
            out[_OUT_ACC + j] += s[3 + j] - prev[3 + j]
        now = _touching(s, p, geom)
        if now and not touching and -prev[5] > out[_OUT_TD_SPEED]:
            out[_OUT_TD_SPEED] = -prev[5]
            out[_OUT_TD_T] = out[_OUT_T] + h
            for j in range(3):
                out[_OUT_TD_X + j] = s[j]
        touching = now
        out[_OUT_T] += h
    qn = math.sqrt(s[6] * s[6] + s[7] * s[7] + s[8] * s[8] + s[9] * s[9])
    for j in range(6, 10):
        s[j] /= qn
    for i in range(4):
        s[16 + i] = min(max(s[16 + i], p[_WMIN]), p[_WMAX])
    return begun


#: from this many rows (worlds x vehicles) on, the world's step (:mod:`droneulator.world.step`) spreads
#: them over the cores (below, threads cost more than they save: one vehicle's step is a few microseconds)
PARALLEL_ROWS = 32


class ParamTable:
    """Packed parameter sets, one row per airframe (:func:`pack_params`), for the batched kernels."""

    def __init__(self) -> None:
        self.params = np.zeros((0, _N_PARAMS))
        self.geometry = np.zeros((0, 4, 3))
        self.directions = np.zeros((0, 4))
        self._index: dict[tuple[Any, ...], int] = {}

    def add(self, key: tuple[Any, ...], packed: tuple[np.ndarray, np.ndarray, np.ndarray]) -> int:
        """Row of the set packed as ``packed`` under ``key`` (added once; equal keys share a row)."""
        if key not in self._index:
            p, g, d = packed
            self.params = np.vstack([self.params, p[None]])
            self.geometry = np.concatenate([self.geometry, g[None]])
            self.directions = np.vstack([self.directions, d[None]])
            self._index[key] = len(self.params) - 1
        return self._index[key]


_NO_SDF = np.ones((1, 1, 1), dtype=np.float32)
#: every rotor at full efficiency
_HEALTHY = np.ones(4)


class FastMultirotor:
    """RotorPy's ``Multirotor`` (``cmd_motor_speeds`` abstraction) with a compiled RK4 integrator
    and spring-damper ground contact (:class:`GroundContact`; ``enable_ground=False``: no ground)."""

    def __init__(
        self,
        quad_params: dict[str, Any],
        aero: bool = True,
        enable_ground: bool = True,
        substep: float = 1e-3,
        contact: GroundContact | None = None,
    ) -> None:
        self.quad_params = quad_params
        self.contact = contact or GroundContact()
        self.params, self.geometry, self.directions = pack_params(
            quad_params, aero, enable_ground, self.contact
        )
        self.substep = substep
        self._sdf = self._wood = _NO_SDF
        self._origin = np.zeros(3)
        self._res = 1.0
        self._radius = 0.0
        self._scratch = np.zeros(OUTPUT_SIZE)
        #: each rotor's efficiency (1: healthy), as the world's ``rotor_efficiency`` rows
        self.rotor_efficiency = np.ones(4)
        work, R = work_arrays(1)
        self._work, self._R = work[0], R[0]

    def set_collision(self, sdf: np.ndarray, origin: np.ndarray, resolution: float, radius: float) -> None:
        """Query this signed distance grid after every sub-step (sphere of ``radius``)."""
        self._sdf = self._wood = np.ascontiguousarray(sdf, dtype=np.float32)
        self._origin = np.asarray(origin, dtype=np.float64)
        self._res = float(resolution)
        self._radius = float(radius)

    @property
    def hover_speed(self) -> float:
        """Rotor speed (rad/s) that balances the weight."""
        return hover_speed(self.params)

    def step(
        self, s: np.ndarray, cmd_motor_speeds: np.ndarray, dt: float, out: np.ndarray | None = None
    ) -> bool:
        """Integrate state vector ``s`` in place; True if the vehicle touched the scene (and stopped there).

        ``out`` (float64, :data:`OUTPUT` layout), when given, accumulates the step's specific force
        and velocity change integrals and its touchdown; the caller zeroes it when a period starts.
        """
        if out is None:
            out = self._scratch
            out[:] = 0.0
        elif out.shape != (OUTPUT_SIZE,) or out.dtype != np.float64:
            raise ValueError(f"out must be a float64 vector of {OUTPUT_SIZE} (OUTPUT layout)")
        touched = integrate(
            s,
            np.asarray(cmd_motor_speeds, dtype=np.float64),
            dt,
            substeps(dt, self.substep),
            self.params,
            self.geometry,
            self.directions,
            self.rotor_efficiency,
            self._sdf,
            self._wood,
            self._origin,
            self._res,
            self._radius,
            CONTACT_STOP,
            out,
            self._work,
            self._R,
        )
        return touched != 0


def substeps(dt: float, substep: float) -> int:
    """RK4 sub-steps for an interval of ``dt`` s at most ``substep`` s long each."""
    return max(1, math.ceil(dt / substep - 1e-9))


def hover_speed(params: np.ndarray) -> float:
    """Rotor speed (rad/s) that balances the weight of a packed parameter set."""
    return math.sqrt(params[_MASS] * params[_G] / (4 * params[_KETA]))


def pack_state(state: dict[str, np.ndarray]) -> np.ndarray:
    """RotorPy state dict -> packed vector."""
    s = np.zeros(STATE_SIZE)
    for name in STATE.names:
        s[getattr(STATE, name)] = state.get(name, 0.0) if name == "wind" else state[name]
    return s


def unpack_state(s: np.ndarray) -> dict[str, np.ndarray]:
    """Packed vector -> RotorPy state dict (copies)."""
    return {name: s[getattr(STATE, name)].copy() for name in STATE.names}
