"""The inner loops a vehicle can be commanded at below its SE(3) controller, compiled: collective thrust
and body rates (CTBR) and collective thrust and attitude.

They are RotorPy's own low-level controllers (``Multirotor`` with ``cmd_ctbr`` and ``cmd_ctatt``; the tests
compare them), run once per control period in the world's compiled step like the SE(3) controller:

* **rates**: ``M = J (k_w e + k_w^2 / 5 integral(e)) + w x J w`` with ``e = w_cmd - w``: RotorPy's
  ``cmd_ctbr`` (``M = J k_w e``) with an integral term, which holds the rate against the rotors'
  aerodynamic damping, and the gyroscopic term the SE(3) controller has (without it a fast rotation
  about one axis drives the others); its gains per axis from the airframe's motor lag
  (:func:`~droneulator.controllers.se3.rate_gains`) or ``flight.rate_gain``;
* **attitude**: the SE(3) controller's attitude loop, ``M = J (-kp_att e_R - kd_att w) + w x J w``
  (exactly RotorPy's ``cmd_ctatt``), with the airframe's attitude gains (``kp_att``, ``kd_att``, as the
  SE(3) controller flies them).

The thrust and moments go through the airframe's allocation
(:func:`~droneulator.controllers.se3.allocate_into`): yaw moment is given up first when a rotor would
leave its speed range, and the rotor commands are clipped to ``[rotor_speed_min, rotor_speed_max]`` by the
dynamics.

A setpoint is packed as ``[thrust (N), rates (rad/s, body FLU, 3)]`` or ``[thrust (N), quaternion
(x, y, z, w; body FLU to world ENU)]`` (:data:`SP_THRUST`, :data:`SP_RATES`, :data:`SP_Q`), in the row of the
world's reference array the flat outputs use.
"""

from __future__ import annotations

import numba
import numpy as np

from droneulator.controllers.se3 import _G_J, _G_KDATT, _G_KPATT, _G_KW, allocate_into
from droneulator.frames_numba import quat_to_matrix_into
from droneulator.state import STATE

#: where a packed setpoint holds the collective thrust (N), the body rates (3) and the attitude (4); the rate
#: loop keeps its integral after them (:data:`SP_INTEGRAL`, 3), in the same row, from one period to the next
SP_THRUST, SP_RATES, SP_Q, SP_INTEGRAL = 0, 1, 1, 5
SETPOINT_SIZE = 5
#: the largest angular acceleration (rad/s^2) the rate loop's integral may ask for, and the largest rate
#: error (rad/s) it integrates: a step of the command is the proportional part's, the integral only takes
#: up the small steady error the rotors' damping leaves (anti wind-up)
RATE_INTEGRAL_LIMIT = 30.0
RATE_INTEGRAL_ERROR = 0.5
_Q = STATE.q.start
_W = STATE.w.start

@numba.njit(cache=True)
def _rate_accel(i: int, s: np.ndarray, sp: np.ndarray, k: np.ndarray, dt: float) -> float:
    """The rate loop's angular acceleration about body axis ``i``; advances that axis's integral."""
    kw = k[_G_KW + i]
    e = sp[SP_RATES + i] - s[_W + i]
    ki = 0.2 * kw * kw
    a = kw * e + ki * sp[SP_INTEGRAL + i]
    bound = RATE_INTEGRAL_LIMIT / ki if ki > 0.0 else 0.0
    step = min(max(e, -RATE_INTEGRAL_ERROR), RATE_INTEGRAL_ERROR) * dt
    sp[SP_INTEGRAL + i] = min(max(sp[SP_INTEGRAL + i] + step, -bound), bound)
    return a


@numba.njit(cache=True)
def rates_into(s: np.ndarray, sp: np.ndarray, k: np.ndarray, out: np.ndarray, dt: float) -> None:
    """Write the rotor speeds (rad/s, unclipped) for packed state ``s`` flying the thrust and body rates
    setpoint ``sp`` into ``out``, with the packed gains ``k`` (:meth:`FastSE3Control.gains`), and advance the
    loop's integral (in ``sp``) by ``dt``.

    Per axis the angular acceleration asked for is ``k_w e + k_w^2 / 5 * integral(e)`` (a step of the
    command overshoots by under 10 % and settles to 1 % in about 0.5 s on the Hummingbird), the integral's
    part at most :data:`RATE_INTEGRAL_LIMIT` and its integrand at most :data:`RATE_INTEGRAL_ERROR`;
    it holds the commanded rate against the rotors' aerodynamic damping, which a proportional loop leaves
    as a steady error of a few per cent."""
    a0, a1, a2 = _rate_accel(0, s, sp, k, dt), _rate_accel(1, s, sp, k, dt), _rate_accel(2, s, sp, k, dt)
    wx, wy, wz = s[_W], s[_W + 1], s[_W + 2]
    J = _G_J
    Jw0 = k[J] * wx + k[J + 1] * wy + k[J + 2] * wz
    Jw1 = k[J + 3] * wx + k[J + 4] * wy + k[J + 5] * wz
    Jw2 = k[J + 6] * wx + k[J + 7] * wy + k[J + 8] * wz
    u20 = k[J] * a0 + k[J + 1] * a1 + k[J + 2] * a2 + (wy * Jw2 - wz * Jw1)
    u21 = k[J + 3] * a0 + k[J + 4] * a1 + k[J + 5] * a2 + (wz * Jw0 - wx * Jw2)
    u22 = k[J + 6] * a0 + k[J + 7] * a1 + k[J + 8] * a2 + (wx * Jw1 - wy * Jw0)
    allocate_into(k, sp[SP_THRUST], u20, u21, u22, out)


@numba.njit(cache=True)
def attitude_into(s: np.ndarray, sp: np.ndarray, k: np.ndarray, out: np.ndarray, R: np.ndarray) -> None:
    """Write the rotor speeds (rad/s, unclipped) for packed state ``s`` flying the thrust and attitude
    setpoint ``sp`` into ``out``, with the packed gains ``k``; ``R`` is 3x3 scratch."""
    quat_to_matrix_into(sp[SP_Q : SP_Q + 4], R)
    d00, d01, d02 = R[0, 0], R[0, 1], R[0, 2]
    d10, d11, d12 = R[1, 0], R[1, 1], R[1, 2]
    d20, d21, d22 = R[2, 0], R[2, 1], R[2, 2]
    quat_to_matrix_into(s[_Q : _Q + 4], R)
    # e_R = vee(S), S = (R_des^T R - R^T R_des) / 2: (R_des^T R)_ij = R_des[:, i] . R[:, j]
    d1R2 = d01 * R[0, 2] + d11 * R[1, 2] + d21 * R[2, 2]
    R1d2 = R[0, 1] * d02 + R[1, 1] * d12 + R[2, 1] * d22
    d0R2 = d00 * R[0, 2] + d10 * R[1, 2] + d20 * R[2, 2]
    R0d2 = R[0, 0] * d02 + R[1, 0] * d12 + R[2, 0] * d22
    d0R1 = d00 * R[0, 1] + d10 * R[1, 1] + d20 * R[2, 1]
    R0d1 = R[0, 0] * d01 + R[1, 0] * d11 + R[2, 0] * d21
    e0, e1, e2 = -0.5 * (d1R2 - R1d2), 0.5 * (d0R2 - R0d2), -0.5 * (d0R1 - R0d1)
    wx, wy, wz = s[_W], s[_W + 1], s[_W + 2]
    J = _G_J
    Jw0 = k[J] * wx + k[J + 1] * wy + k[J + 2] * wz
    Jw1 = k[J + 3] * wx + k[J + 4] * wy + k[J + 5] * wz
    Jw2 = k[J + 6] * wx + k[J + 7] * wy + k[J + 8] * wz
    a0 = -k[_G_KPATT] * e0 - k[_G_KDATT] * wx
    a1 = -k[_G_KPATT] * e1 - k[_G_KDATT] * wy
    a2 = -k[_G_KPATT] * e2 - k[_G_KDATT] * wz
    u20 = k[J] * a0 + k[J + 1] * a1 + k[J + 2] * a2 + (wy * Jw2 - wz * Jw1)
    u21 = k[J + 3] * a0 + k[J + 4] * a1 + k[J + 5] * a2 + (wz * Jw0 - wx * Jw2)
    u22 = k[J + 6] * a0 + k[J + 7] * a1 + k[J + 8] * a2 + (wx * Jw1 - wy * Jw0)
    allocate_into(k, sp[SP_THRUST], u20, u21, u22, out)

