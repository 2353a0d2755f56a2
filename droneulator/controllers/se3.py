"""RotorPy's SE(3) geometric tracking controller (Lee et al. 2010), compiled.

``rotorpy.controllers.quadrotor_control.SE3Control.update`` costs ~0.3 ms per call here, more
than the whole physics step. :class:`FastSE3Control` computes the identical motor-speed command
(RotorPy's gains, the same allocation matrix; equality with RotorPy is asserted in the tests) in a few
microseconds. It takes them from the airframe's parameters itself rather than from an ``SE3Control``:
RotorPy's controller module imports torch when torch is installed, seconds and hundreds of megabytes
in every simulator process.

Optionally it bounds the desired thrust vector as an autopilot's position controller does (PX4's
``MPC_TILTMAX_AIR`` and ``MPC_THR_MIN``): its vertical part at least ``min_lift`` times the weight and
its tilt from vertical at most ``max_tilt_deg``; and it gives up yaw moment before thrust when a rotor
would leave its speed range, as PX4's mixer does. RotorPy's controller has none of these: when a
reference jumps metres away (a planner's emergency stop, a late plan) the desired force can point
sideways or down, and the vehicle rolls past 90 degrees and flies itself into the ground; and a yaw
error of a radian or two asks two rotors for negative thrust, the clipped command lifts the vehicle
and it climbs while it turns. Within the bounds the command is RotorPy's.
"""

from __future__ import annotations

import math
from typing import Any

import numba
import numpy as np

from droneulator.frames_numba import quat_to_matrix_into
from droneulator.state import STATE

# Layout of a packed gain vector (:meth:`FastSE3Control.gains`): what the kernel needs of one airframe.
# The body-rate gains (``_G_KW``, 3) are the rate loop's (:mod:`droneulator.controllers.inner`).
_G_MASS, _G_J, _G_KP, _G_KD, _G_KPATT, _G_KDATT, _G_TM, _G_KETA, _G_TAN, _G_LIFT, _G_FMIN, _G_FMAX, _G_KW = (
    0, 1, 10, 13, 16, 17, 18, 34, 35, 36, 37, 38, 39,
)  # fmt: skip
GAINS_SIZE = 42
#: where the attitude quaternion starts in the packed state (the kernel indexes the state directly)
_Q = STATE.q.start


@numba.njit(cache=True)
def se3_into(s: np.ndarray, flat: np.ndarray, k: np.ndarray, out: np.ndarray, R: np.ndarray) -> None:
    """Write the commanded rotor speeds (rad/s, unclipped) for packed state ``s`` tracking the packed
    flat output ``flat`` into ``out`` (4), with the packed gains ``k``; ``R`` is 3x3 scratch. Allocation
    free, so that many vehicles can be controlled in one compiled loop."""
    g = 9.81
    mass = k[_G_MASS]
    F0 = mass * (-k[_G_KP] * (s[0] - flat[0]) - k[_G_KD] * (s[3] - flat[3]) + flat[6])
    F1 = mass * (-k[_G_KP + 1] * (s[1] - flat[1]) - k[_G_KD + 1] * (s[4] - flat[4]) + flat[7])
    F2 = mass * (-k[_G_KP + 2] * (s[2] - flat[2]) - k[_G_KD + 2] * (s[5] - flat[5]) + flat[8])
    F2 += mass * g
    tan_max_tilt = k[_G_TAN]
    if tan_max_tilt > 0.0:  # the autopilot's thrust bounds: vertical part first, then the tilt
        F2 = max(F2, k[_G_LIFT] * mass * g)
        horizontal = math.sqrt(F0**2 + F1**2)
        most = F2 * tan_max_tilt
        if horizontal > most:
            F0 *= most / horizontal
            F1 *= most / horizontal
    quat_to_matrix_into(s[_Q : _Q + 4], R)
    u1 = F0 * R[0, 2] + F1 * R[1, 2] + F2 * R[2, 2]

    nF = math.sqrt(F0**2 + F1**2 + F2**2)
    b30, b31, b32 = F0 / nF, F1 / nF, F2 / nF
    yaw = flat[9]
    c10, c11, c12 = math.cos(yaw), math.sin(yaw), 0.0
    b20 = b31 * c12 - b32 * c11
    b21 = b32 * c10 - b30 * c12
    b22 = b30 * c11 - b31 * c10
    n2 = math.sqrt(b20**2 + b21**2 + b22**2)
    b20 /= n2
    b21 /= n2
    b22 /= n2
    b10 = b21 * b32 - b22 * b31
    b11 = b22 * b30 - b20 * b32
    b12 = b20 * b31 - b21 * b30
    # R_des = [b1 b2 b3] (columns); S = (R_des^T R - R^T R_des) / 2 with (R_des^T R)_ij = b_i . R[:, j]
    # and (R^T R_des)_ij = R[:, i] . b_j; the attitude error is vee(S) = (-S_12, S_02, -S_01)
    b2R2 = b20 * R[0, 2] + b21 * R[1, 2] + b22 * R[2, 2]
    R1b3 = R[0, 1] * b30 + R[1, 1] * b31 + R[2, 1] * b32
    b1R2 = b10 * R[0, 2] + b11 * R[1, 2] + b12 * R[2, 2]
    R0b3 = R[0, 0] * b30 + R[1, 0] * b31 + R[2, 0] * b32
    b1R1 = b10 * R[0, 1] + b11 * R[1, 1] + b12 * R[2, 1]
    R0b2 = R[0, 0] * b20 + R[1, 0] * b21 + R[2, 0] * b22
    e1 = -0.5 * (b2R2 - R1b3)
    e2 = 0.5 * (b1R2 - R0b3)
    e3 = -0.5 * (b1R1 - R0b2)
    wx, wy, wz = s[10], s[11], s[12]
    J = _G_J
    Jw0 = k[J] * wx + k[J + 1] * wy + k[J + 2] * wz
    Jw1 = k[J + 3] * wx + k[J + 4] * wy + k[J + 5] * wz
    Jw2 = k[J + 6] * wx + k[J + 7] * wy + k[J + 8] * wz
    a0 = -k[_G_KPATT] * e1 - k[_G_KDATT] * wx
    a1 = -k[_G_KPATT] * e2 - k[_G_KDATT] * wy
    a2 = -k[_G_KPATT] * e3 - k[_G_KDATT] * (wz - flat[10])
    u20 = k[J] * a0 + k[J + 1] * a1 + k[J + 2] * a2 + (wy * Jw2 - wz * Jw1)
    u21 = k[J + 3] * a0 + k[J + 4] * a1 + k[J + 5] * a2 + (wz * Jw0 - wx * Jw2)
    u22 = k[J + 6] * a0 + k[J + 7] * a1 + k[J + 8] * a2 + (wx * Jw1 - wy * Jw0)
    allocate_into(k, u1, u20, u21, u22, out)


@numba.njit(cache=True)
def allocate_into(k: np.ndarray, u1: float, u20: float, u21: float, u22: float, out: np.ndarray) -> None:
    """Write the rotor speeds (rad/s, unclipped) for collective thrust ``u1`` (N) and body moments ``u2``
    (N m) into ``out`` through the airframe's allocation matrix (packed gains ``k``), giving up yaw moment
    first when a rotor would leave its speed range (with the thrust bounds on, ``f_max > f_min``)."""
    T = _G_TM
    for i in range(4):
        out[i] = k[T + 4 * i] * u1 + k[T + 4 * i + 1] * u20 + k[T + 4 * i + 2] * u21 + k[T + 4 * i + 3] * u22
    f_min, f_max = k[_G_FMIN], k[_G_FMAX]
    if f_max > f_min:  # yaw desaturation: scale the yaw moment down until every rotor is in range
        keep = 1.0
        for i in range(4):
            yaw_part = k[T + 4 * i + 3] * u22
            rest = out[i] - yaw_part
            if yaw_part < 0.0 and out[i] < f_min:
                keep = min(keep, max(0.0, (f_min - rest) / yaw_part))
            elif yaw_part > 0.0 and out[i] > f_max:
                keep = min(keep, max(0.0, (f_max - rest) / yaw_part))
        if keep < 1.0:
            for i in range(4):
                out[i] -= (1.0 - keep) * k[T + 4 * i + 3] * u22
    for i in range(4):
        c = out[i] / k[_G_KETA]
        out[i] = math.copysign(math.sqrt(abs(c)), c)


#: RotorPy ``SE3Control``'s position gains (the same for every airframe), and its attitude gains unless the
#: airframe's parameters name their own (``kp_att``, ``kd_att``)
KP_POS = (6.5, 6.5, 15.0)
KD_POS = (4.0, 4.0, 9.0)
KP_ATT = 310.0
KD_ATT = 57.0

#: the default body-rate gain is this many times the airframe's motor bandwidth (1 / tau_m): slower than
#: the motors it acts through, so the loop settles without ringing
RATE_GAIN_PER_MOTOR_BANDWIDTH = 0.4
#: and at most this (1/s): a loop sampled at the control rate (100 Hz by default) stays well damped
RATE_GAIN_MAX = 25.0


def rate_gains(quad_params: dict[str, Any], override: tuple[float, float, float] | None = None) -> np.ndarray:
    """The body-rate loop's gains (1/s, roll, pitch, yaw) for an airframe: ``override`` (the vehicle's
    ``flight.rate_gain``) or :data:`RATE_GAIN_PER_MOTOR_BANDWIDTH` / ``tau_m``, at most
    :data:`RATE_GAIN_MAX`. (RotorPy's own ``k_w`` values are not flyable at a 100 Hz control rate: 1/s for
    the Hummingbird is a one-second response, 200/s for the Crazyflie oscillates.)"""
    if override is not None:
        return np.asarray(override, dtype=float)
    k = min(RATE_GAIN_PER_MOTOR_BANDWIDTH / float(quad_params["tau_m"]), RATE_GAIN_MAX)
    return np.full(3, k)


def allocation(quad_params: dict[str, Any]) -> np.ndarray:
    """RotorPy's control allocation: the matrix from (thrust, roll, pitch, yaw moments) to the rotor forces,
    the inverse of the map from rotor forces (all along body z) to thrust and moments."""
    ratio = float(quad_params["k_m"]) / float(quad_params["k_eta"])  # rotor torque per unit thrust
    arms = np.array([np.cross(np.asarray(r, dtype=float), (0.0, 0.0, 1.0))[:2]
                     for r in quad_params["rotor_pos"].values()])  # fmt: skip
    f_to_tm = np.vstack([np.ones(len(arms)), arms.T, ratio * np.asarray(quad_params["rotor_directions"])])
    return np.linalg.inv(f_to_tm)


class FastSE3Control:
    """RotorPy ``SE3Control``'s gains and allocation for an airframe's parameters (RotorPy's dict).

    ``max_tilt_deg`` (in (0, 90); None: no bounds, RotorPy's exact controller) and ``min_lift`` (share of
    the weight, in [0, 1)) bound the desired thrust vector; with them the yaw moment is also given up
    before thrust when a rotor would leave its speed range (see the module docstring). ``rate_gain``
    (1/s per body axis; None: the airframe's, :func:`rate_gains`) is the
    body-rate loop's, packed with the rest for the compiled inner loops."""

    def __init__(
        self,
        quad_params: dict[str, Any],
        max_tilt_deg: float | None = None,
        min_lift: float = 0.0,
        rate_gain: tuple[float, float, float] | None = None,
    ) -> None:
        if max_tilt_deg is not None and not 0.0 < max_tilt_deg < 90.0:
            raise ValueError(f"max_tilt_deg must lie in (0, 90) degrees, got {max_tilt_deg}")
        if not 0.0 <= min_lift < 1.0:
            raise ValueError(f"min_lift must lie in [0, 1), got {min_lift}")
        self.tan_max_tilt = 0.0 if max_tilt_deg is None else math.tan(math.radians(max_tilt_deg))
        self.min_lift = float(min_lift)
        # rotor force range for the yaw desaturation, on with the thrust bounds (both 0: off)
        bounded = max_tilt_deg is not None
        k = float(quad_params["k_eta"])
        self.f_min = k * float(quad_params["rotor_speed_min"]) ** 2 if bounded else 0.0
        self.f_max = k * float(quad_params["rotor_speed_max"]) ** 2 if bounded else 0.0
        q = quad_params
        self.mass = float(q["mass"])
        self.inertia = np.array([[q["Ixx"], q["Ixy"], q["Ixz"]],
                                 [q["Ixy"], q["Iyy"], q["Iyz"]],
                                 [q["Ixz"], q["Iyz"], q["Izz"]]], dtype=float)  # fmt: skip
        self.kp_pos = np.array(KP_POS)
        self.kd_pos = np.array(KD_POS)
        self.kp_att = float(q.get("kp_att", KP_ATT))
        self.kd_att = float(q.get("kd_att", KD_ATT))
        self.k_w = rate_gains(q, rate_gain)
        self.TM_to_f = np.ascontiguousarray(allocation(q))
        self.k_eta = float(q["k_eta"])
        self._gains = self.gains()
        self._R = np.empty((3, 3))

    def set_mass(self, quad_params: dict[str, Any]) -> None:
        """Take the mass and inertia of ``quad_params`` (a payload came or went)."""
        q = quad_params
        self.mass = float(q["mass"])
        self.inertia = np.array([[q["Ixx"], q["Ixy"], q["Ixz"]],
                                 [q["Ixy"], q["Iyy"], q["Iyz"]],
                                 [q["Ixz"], q["Iyz"], q["Izz"]]], dtype=float)  # fmt: skip
        self._gains = self.gains()

    def gains(self) -> np.ndarray:
        """The packed gain vector :func:`se3_into` reads (GAINS_SIZE floats)."""
        k = np.zeros(GAINS_SIZE)
        k[_G_MASS] = self.mass
        k[_G_J : _G_J + 9] = self.inertia.ravel()
        k[_G_KP : _G_KP + 3] = self.kp_pos
        k[_G_KD : _G_KD + 3] = self.kd_pos
        k[_G_KPATT], k[_G_KDATT] = self.kp_att, self.kd_att
        k[_G_TM : _G_TM + 16] = self.TM_to_f.ravel()
        k[_G_KETA], k[_G_TAN], k[_G_LIFT] = self.k_eta, self.tan_max_tilt, self.min_lift
        k[_G_FMIN], k[_G_FMAX] = self.f_min, self.f_max
        k[_G_KW : _G_KW + 3] = self.k_w
        return k

    def motor_speeds(self, s: np.ndarray, flat: np.ndarray) -> np.ndarray:
        """Commanded rotor speeds (rad/s, unclipped) for packed state ``s`` and packed flat output."""
        out = np.empty(4)
        se3_into(s, flat, self._gains, out, self._R)
        return out
