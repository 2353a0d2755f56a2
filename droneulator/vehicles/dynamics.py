"""RotorPy's multirotor model, integrated fast.

``rotorpy.vehicles.multirotor.Multirotor`` integrates each control period with SciPy's adaptive
RK45 and rebuilds dicts and SciPy rotations at every derivative call (~5x real time at 100 Hz
here). :class:`FastMultirotor` evaluates the same equations of motion — rotor thrust and yaw
moments, motor lag, parasitic drag, rotor drag, induced inflow, translational lift, flapping,
ground reaction and ground contact — compiled with numba and integrated with fixed-step RK4.
Its trajectories are checked against RotorPy's own integration in the tests and benchmarks.

State vector layout (RotorPy's ``_pack_state``): ``x[0:3] v[3:6] q[6:10] (x,y,z,w) w[10:13]
wind[13:16] rotor_speeds[16:20]``. Code outside :mod:`droneulator.vehicles` names these fields
through :data:`STATE` (``s[STATE.q]``) instead of writing the slices; the compiled kernels below
index the vector directly.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numba
import numpy as np

from droneulator.frames_numba import quat_to_matrix, set_quat_from_yaw, yaw_of
from droneulator.scenes.collision import sdf_lookup

# Layout of the packed parameter vector.
_MASS, _G, _KETA, _KM, _KD, _KZ, _KH, _KFLAP, _TAU, _WMIN, _WMAX, _AERO, _GROUND, _BETA = range(14)
_CD = 14  # 3 drag coefficients
_INERTIA = 17  # 9 entries, row-major
_INV_INERTIA = 26  # 9 entries
_N_PARAMS = 35


class StateLayout(NamedTuple):
    """Named slices of the packed state vector, with RotorPy's field names and order.

    ``x`` position (world, m), ``v`` velocity (world, m/s), ``q`` attitude ``[x, y, z, w]`` (body FLU
    to world), ``w`` body rates (rad/s), ``wind`` wind velocity (world, m/s), ``rotor_speeds`` (rad/s).
    """

    x: slice = slice(0, 3)
    v: slice = slice(3, 6)
    q: slice = slice(6, 10)
    w: slice = slice(10, 13)
    wind: slice = slice(13, 16)
    rotor_speeds: slice = slice(16, 20)

    @property
    def names(self) -> tuple[str, ...]:
        return self._fields

    @property
    def size(self) -> int:
        return max(part.stop for part in self)


#: the packed state's layout: ``s[STATE.x]`` is the position, ``s[STATE.rotor_speeds]`` the rotors
STATE = StateLayout()
STATE_SIZE = STATE.size


def pack_params(
    quad_params: dict[str, Any], aero: bool = True, ground: bool = True
) -> tuple[np.ndarray, ...]:
    """Pack a RotorPy parameter dict into (scalars, rotor_geometry (4,3), rotor_directions (4,))."""
    if quad_params["num_rotors"] != 4:
        raise ValueError("only quadrotors are supported")
    p = np.zeros(_N_PARAMS)
    p[_MASS] = quad_params["mass"]
    p[_G] = 9.81
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
    p[_BETA] = min(0.5, max(0.1, float(quad_params.get("ground_friction_beta", 0.3))))
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
    return p, geometry, directions


@numba.njit(cache=True)
def state_derivative(
    s: np.ndarray, cmd: np.ndarray, p: np.ndarray, geom: np.ndarray, dirs: np.ndarray
) -> np.ndarray:
    """d/dt of the packed state for constant commanded rotor speeds (RotorPy ``_s_dot_fn``)."""
    ds = np.zeros(STATE_SIZE)
    R = quat_to_matrix(s[6:10])
    qx, qy, qz, qw = s[6], s[7], s[8], s[9]
    wx, wy, wz = s[10], s[11], s[12]
    mass = p[_MASS]

    # position and quaternion kinematics (Graf's G matrix, unnormalised as in RotorPy)
    ds[0:3] = s[3:6]
    ds[6] = 0.5 * (qw * wx - qz * wy + qy * wz)
    ds[7] = 0.5 * (qz * wx + qw * wy - qx * wz)
    ds[8] = 0.5 * (-qy * wx + qx * wy + qw * wz)
    ds[9] = 0.5 * (-qx * wx - qy * wy - qz * wz)
    # first-order motor lag
    for i in range(4):
        ds[16 + i] = (cmd[i] - s[16 + i]) / p[_TAU]

    # airspeed in the body frame
    rel = s[3:6] - s[13:16]
    va = R.T @ rel
    F = np.zeros(3)
    M = np.zeros(3)
    aero = p[_AERO] > 0.5
    if aero:
        vn = math.sqrt(va[0] * va[0] + va[1] * va[1] + va[2] * va[2])
        F[0] -= vn * p[_CD] * va[0]
        F[1] -= vn * p[_CD + 1] * va[1]
        F[2] -= vn * p[_CD + 2] * va[2]
    for i in range(4):
        om = s[16 + i]
        rx, ry, rz = geom[i, 0], geom[i, 1], geom[i, 2]
        # local airspeed at the hub: va + w x r
        lx = va[0] + wy * rz - wz * ry
        ly = va[1] + wz * rx - wx * rz
        lz = va[2] + wx * ry - wy * rx
        fx = 0.0
        fy = 0.0
        fz = p[_KETA] * om * om
        if aero:
            fx = -om * p[_KD] * lx
            fy = -om * p[_KD] * ly
            fz += -om * p[_KZ] * lz + p[_KH] * (lx * lx + ly * ly)
            # flapping moment: -k_flap * om * (local x e3)
            M[0] += -p[_KFLAP] * om * ly
            M[1] += p[_KFLAP] * om * lx
        F[0] += fx
        F[1] += fy
        F[2] += fz
        # moment of the hub force about the CoM, plus the rotor's reaction torque
        M[0] += ry * fz - rz * fy
        M[1] += rz * fx - rx * fz
        M[2] += rx * fy - ry * fx + dirs[i] * p[_KM] * om * om

    Fw = R @ F
    Fw[2] -= mass * p[_G]
    if p[_GROUND] > 0.5 and s[2] <= 0.001 and Fw[2] < 0.0:
        Fw[2] = 0.0  # ground reaction cancels any net downward force
    ds[3:6] = Fw / mass

    J = p[_INERTIA : _INERTIA + 9].reshape(3, 3)
    Jinv = p[_INV_INERTIA : _INV_INERTIA + 9].reshape(3, 3)
    w = s[10:13]
    Jw = J @ w
    gyro = np.array([wy * Jw[2] - wz * Jw[1], wz * Jw[0] - wx * Jw[2], wx * Jw[1] - wy * Jw[0]])
    ds[10:13] = Jinv @ (M - gyro)
    return ds


@numba.njit(cache=True)
def _ground_contact(s: np.ndarray, p: np.ndarray) -> None:
    """RotorPy's ground handling: clamp to z=0, no sinking, friction, level attitude (yaw kept)."""
    s[2] = 0.0
    if s[5] < 0.0:
        s[5] = 0.0
    s[3] *= 1.0 - p[_BETA]
    s[4] *= 1.0 - p[_BETA]
    s[10] = 0.0
    s[11] = 0.0
    s[12] = 0.0
    set_quat_from_yaw(s[6:10], yaw_of(s[6:10]))


@numba.njit(cache=True)
def integrate(
    s: np.ndarray,
    cmd_in: np.ndarray,
    dt: float,
    n_sub: int,
    p: np.ndarray,
    geom: np.ndarray,
    dirs: np.ndarray,
    sdf: np.ndarray,
    origin: np.ndarray,
    res: float,
    radius: float,
) -> bool:
    """Advance ``s`` in place by ``dt`` with ``n_sub`` RK4 steps under constant rotor commands.

    The collision model is queried after every sub-step; on contact the state is rolled back to
    the last collision-free sub-step and True is returned.
    """
    cmd = np.empty(4)
    for i in range(4):
        cmd[i] = min(max(cmd_in[i], p[_WMIN]), p[_WMAX])
    h = dt / n_sub
    check = sdf.shape[0] > 1
    for _ in range(n_sub):
        prev = s.copy()
        k1 = state_derivative(s, cmd, p, geom, dirs)
        k2 = state_derivative(s + 0.5 * h * k1, cmd, p, geom, dirs)
        k3 = state_derivative(s + 0.5 * h * k2, cmd, p, geom, dirs)
        k4 = state_derivative(s + h * k3, cmd, p, geom, dirs)
        s += (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        if check and sdf_lookup(sdf, origin, res, s[0:3]) < radius:
            s[:] = prev
            return True
    n = math.sqrt(s[6] * s[6] + s[7] * s[7] + s[8] * s[8] + s[9] * s[9])
    s[6:10] /= n
    if p[_GROUND] > 0.5 and s[2] <= 0.001:
        _ground_contact(s, p)
    for i in range(4):
        s[16 + i] = min(max(s[16 + i], p[_WMIN]), p[_WMAX])
    return False


_NO_SDF = np.ones((1, 1, 1), dtype=np.float32)


class FastMultirotor:
    """RotorPy's ``Multirotor`` (``cmd_motor_speeds`` abstraction) with a compiled RK4 integrator."""

    def __init__(
        self,
        quad_params: dict[str, Any],
        aero: bool = True,
        enable_ground: bool = True,
        substep: float = 1e-3,
    ) -> None:
        self.quad_params = quad_params
        self.params, self.geometry, self.directions = pack_params(quad_params, aero, enable_ground)
        self.substep = substep
        self._sdf = _NO_SDF
        self._origin = np.zeros(3)
        self._res = 1.0
        self._radius = 0.0

    def set_collision(self, sdf: np.ndarray, origin: np.ndarray, resolution: float, radius: float) -> None:
        """Query this signed distance grid after every sub-step (sphere of ``radius``)."""
        self._sdf = np.ascontiguousarray(sdf, dtype=np.float32)
        self._origin = np.asarray(origin, dtype=np.float64)
        self._res = float(resolution)
        self._radius = float(radius)

    @property
    def hover_speed(self) -> float:
        """Rotor speed (rad/s) that balances the weight."""
        return math.sqrt(self.params[_MASS] * self.params[_G] / (4 * self.params[_KETA]))

    def step(self, s: np.ndarray, cmd_motor_speeds: np.ndarray, dt: float) -> bool:
        """Integrate state vector ``s`` in place; True if the vehicle touched the scene."""
        n_sub = max(1, math.ceil(dt / self.substep - 1e-9))
        return integrate(
            s,
            np.asarray(cmd_motor_speeds, dtype=np.float64),
            dt,
            n_sub,
            self.params,
            self.geometry,
            self.directions,
            self._sdf,
            self._origin,
            self._res,
            self._radius,
        )


def pack_state(state: dict[str, np.ndarray]) -> np.ndarray:
    """RotorPy state dict -> packed vector."""
    s = np.zeros(STATE_SIZE)
    for name in STATE.names:
        s[getattr(STATE, name)] = state.get(name, 0.0) if name == "wind" else state[name]
    return s


def unpack_state(s: np.ndarray) -> dict[str, np.ndarray]:
    """Packed vector -> RotorPy state dict (copies)."""
    return {name: s[getattr(STATE, name)].copy() for name in STATE.names}
