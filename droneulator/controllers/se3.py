"""RotorPy's SE(3) geometric tracking controller (Lee et al. 2010), compiled.

``rotorpy.controllers.quadrotor_control.SE3Control.update`` costs ~0.3 ms per call here, more
than the whole physics step. :class:`FastSE3Control` computes the identical motor-speed command
(same gains, same allocation matrix; equality with RotorPy is asserted in the tests) in a few
microseconds.

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
from rotorpy.controllers.quadrotor_control import SE3Control

from droneulator.frames_numba import quat_to_matrix
from droneulator.state import STATE


@numba.njit(cache=True)
def se3_motor_speeds(
    x: np.ndarray,
    v: np.ndarray,
    q: np.ndarray,
    w: np.ndarray,
    flat: np.ndarray,
    mass: float,
    inertia: np.ndarray,
    kp_pos: np.ndarray,
    kd_pos: np.ndarray,
    kp_att: float,
    kd_att: float,
    TM_to_f: np.ndarray,
    k_eta: float,
    tan_max_tilt: float,
    min_lift: float,
    f_min: float,
    f_max: float,
) -> np.ndarray:
    g = 9.81
    F_des = np.empty(3)
    for i in range(3):
        F_des[i] = mass * (-kp_pos[i] * (x[i] - flat[i]) - kd_pos[i] * (v[i] - flat[3 + i]) + flat[6 + i])
    F_des[2] += mass * g
    if tan_max_tilt > 0.0:  # the autopilot's thrust bounds: vertical part first, then the tilt
        F_des[2] = max(F_des[2], min_lift * mass * g)
        horizontal = math.sqrt(F_des[0] ** 2 + F_des[1] ** 2)
        most = F_des[2] * tan_max_tilt
        if horizontal > most:
            F_des[0] *= most / horizontal
            F_des[1] *= most / horizontal
    R = quat_to_matrix(q)
    u1 = F_des[0] * R[0, 2] + F_des[1] * R[1, 2] + F_des[2] * R[2, 2]

    b3 = F_des / math.sqrt(F_des[0] ** 2 + F_des[1] ** 2 + F_des[2] ** 2)
    yaw = flat[9]
    c1 = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    b2 = np.array(
        [b3[1] * c1[2] - b3[2] * c1[1], b3[2] * c1[0] - b3[0] * c1[2], b3[0] * c1[1] - b3[1] * c1[0]]
    )
    b2 /= math.sqrt(b2[0] ** 2 + b2[1] ** 2 + b2[2] ** 2)
    b1 = np.array(
        [b2[1] * b3[2] - b2[2] * b3[1], b2[2] * b3[0] - b2[0] * b3[2], b2[0] * b3[1] - b2[1] * b3[0]]
    )
    R_des = np.empty((3, 3))
    R_des[:, 0] = b1
    R_des[:, 1] = b2
    R_des[:, 2] = b3
    S = 0.5 * (R_des.T @ R - R.T @ R_des)
    att_err = np.array([-S[1, 2], S[0, 2], -S[0, 1]])
    w_err = np.array([w[0], w[1], w[2] - flat[10]])
    Jw = inertia @ w
    gyro = np.array([w[1] * Jw[2] - w[2] * Jw[1], w[2] * Jw[0] - w[0] * Jw[2], w[0] * Jw[1] - w[1] * Jw[0]])
    u2 = inertia @ (-kp_att * att_err - kd_att * w_err) + gyro
    TM = np.array([u1, u2[0], u2[1], u2[2]])
    f = TM_to_f @ TM
    if f_max > f_min:  # yaw desaturation: scale the yaw moment down until every rotor is in range
        keep = 1.0
        for i in range(4):
            yaw_part = TM_to_f[i, 3] * TM[3]
            rest = f[i] - yaw_part
            if yaw_part < 0.0 and f[i] < f_min:
                keep = min(keep, max(0.0, (f_min - rest) / yaw_part))
            elif yaw_part > 0.0 and f[i] > f_max:
                keep = min(keep, max(0.0, (f_max - rest) / yaw_part))
        if keep < 1.0:
            for i in range(4):
                f[i] -= (1.0 - keep) * TM_to_f[i, 3] * TM[3]
    out = np.empty(4)
    for i in range(4):
        c = f[i] / k_eta
        out[i] = math.copysign(math.sqrt(abs(c)), c)
    return out


class FastSE3Control:
    """Gains and allocation taken from a RotorPy ``SE3Control`` built with the same parameters.

    ``max_tilt_deg`` (in (0, 90); None: no bounds, RotorPy's exact controller) and ``min_lift`` (share of
    the weight, in [0, 1)) bound the desired thrust vector; with them the yaw moment is also given up
    before thrust when a rotor would leave its speed range (see the module docstring)."""

    def __init__(
        self, quad_params: dict[str, Any], max_tilt_deg: float | None = None, min_lift: float = 0.0
    ) -> None:
        if max_tilt_deg is not None and not 0.0 < max_tilt_deg < 90.0:
            raise ValueError(f"max_tilt_deg must lie in (0, 90) degrees, got {max_tilt_deg}")
        if not 0.0 <= min_lift < 1.0:
            raise ValueError(f"min_lift must lie in [0, 1), got {min_lift}")
        self.tan_max_tilt = 0.0 if max_tilt_deg is None else math.tan(math.radians(max_tilt_deg))
        self.min_lift = float(min_lift)
        ref = SE3Control(quad_params)
        # rotor force range for the yaw desaturation, on with the thrust bounds (both 0: off)
        bounded = max_tilt_deg is not None
        k = float(quad_params["k_eta"])
        self.f_min = k * float(quad_params["rotor_speed_min"]) ** 2 if bounded else 0.0
        self.f_max = k * float(quad_params["rotor_speed_max"]) ** 2 if bounded else 0.0
        self.mass = float(ref.mass)
        self.inertia = np.ascontiguousarray(ref.inertia, dtype=float)
        self.kp_pos = np.asarray(ref.kp_pos, dtype=float)
        self.kd_pos = np.asarray(ref.kd_pos, dtype=float)
        self.kp_att = float(ref.kp_att)
        self.kd_att = float(ref.kd_att)
        self.TM_to_f = np.ascontiguousarray(ref.TM_to_f, dtype=float)
        self.k_eta = float(ref.k_eta)

    def motor_speeds(self, s: np.ndarray, flat: np.ndarray) -> np.ndarray:
        """Commanded rotor speeds (rad/s, unclipped) for packed state ``s`` and packed flat output."""
        return se3_motor_speeds(
            s[STATE.x],
            s[STATE.v],
            s[STATE.q],
            s[STATE.w],
            flat,
            self.mass,
            self.inertia,
            self.kp_pos,
            self.kd_pos,
            self.kp_att,
            self.kd_att,
            self.TM_to_f,
            self.k_eta,
            self.tan_max_tilt,
            self.min_lift,
            self.f_min,
            self.f_max,
        )
