"""Collective thrust and body rates (CTBR) from a flat reference, by differential flatness (Mellinger and
Kumar 2011), for flying a trajectory through the ``rates`` command rather than the SE(3) controller.

A multirotor's position and yaw are flat outputs: the reference's acceleration gives the thrust and the
body z axis, its jerk and yaw rate the body rates. The SE(3) controller (:mod:`~droneulator.controllers.se3`)
takes position, velocity and acceleration but no jerk: it tracks the attitude with a loop that damps the
body rates towards zero, so on a fast reference the attitude lags. :class:`CTBRTracker` instead asks for the
feed-forward body rates, plus an attitude correction, and the same position feedback the SE(3) controller
has; ``benchmarks/control.py`` compares the two on a figure-eight (docs/control.md).

The attitude is built as the SE(3) controller builds it: ``z_B`` along the thrust vector ``a + g e_z``,
``y_B`` along ``z_B x x_C`` with ``x_C = (cos yaw, sin yaw, 0)``, ``x_B = y_B x z_B``. Differentiating
gives, with ``h = (j - (z_B . j) z_B) / |a + g e_z|``, the body rates (FLU)

* ``p = -h . y_B``, ``q = h . x_B`` (the turn of the thrust axis),
* ``r = (p z_B . x_C + yaw_rate y_B . y_C) / (x_B . x_C)`` with ``y_C = (-sin yaw, cos yaw, 0)``: exact for
  this construction (from ``d/dt (y_B . x_C) = 0``); it is singular when the body x axis is perpendicular
  to the heading, at a pitch of 90 degrees.

World frame ENU, body FLU (:mod:`droneulator.frames`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from droneulator.controllers.se3 import KD_POS, KP_POS
from droneulator.frames import quat_to_matrix

#: m/s^2, RotorPy's (and the SE(3) controller's, :mod:`~droneulator.controllers.se3`)
GRAVITY = 9.81
_EZ = np.array([0.0, 0.0, 1.0])


@dataclass
class FlatCTBR:
    """What a flat reference asks of the vehicle: collective thrust (N), body rates (rad/s, FLU) and the
    attitude (rotation matrix, body FLU to world ENU)."""

    thrust: float
    body_rates: np.ndarray
    rotation: np.ndarray


def flat_attitude(acceleration: np.ndarray, yaw: float) -> np.ndarray:
    """The attitude (body FLU to world ENU) whose thrust axis gives ``acceleration`` (m/s^2, world) at
    heading ``yaw`` (rad): the SE(3) controller's construction."""
    z = np.asarray(acceleration, dtype=float) + GRAVITY * _EZ
    z = z / np.linalg.norm(z)
    x_c = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    y = np.cross(z, x_c)
    y /= np.linalg.norm(y)
    return np.column_stack([np.cross(y, z), y, z])


def flat_ctbr(
    mass: float, acceleration: np.ndarray, jerk: np.ndarray, yaw: float, yaw_rate: float
) -> FlatCTBR:
    """Collective thrust, body rates and attitude that fly a reference's ``acceleration`` (m/s^2),
    ``jerk`` (m/s^3), ``yaw`` (rad) and ``yaw_rate`` (rad/s) exactly, for a vehicle of ``mass`` (kg)
    without drag (see the module docstring)."""
    t = np.asarray(acceleration, dtype=float) + GRAVITY * _EZ
    c = float(np.linalg.norm(t))
    R = flat_attitude(acceleration, yaw)
    x_b, y_b, z_b = R[:, 0], R[:, 1], R[:, 2]
    j = np.asarray(jerk, dtype=float)
    h = (j - float(z_b @ j) * z_b) / c
    p, q = -float(h @ y_b), float(h @ x_b)
    x_c = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    y_c = np.array([-np.sin(yaw), np.cos(yaw), 0.0])
    r = (p * float(z_b @ x_c) + yaw_rate * float(y_b @ y_c)) / float(x_b @ x_c)
    return FlatCTBR(mass * c, np.array([p, q, r]), R)


class CTBRTracker:
    """Follows a flat reference with ``rates`` commands: the SE(3) controller's position feedback
    (``kp``, ``kd``: RotorPy's gains by default) on the reference's acceleration gives the thrust vector;
    the thrust is its part along the current body z axis, as in the SE(3) controller; the body rates are
    the flat feed-forward (from the reference's jerk and yaw rate) turned into the current body frame, plus
    ``k_att`` (1/s) times the attitude error (below the body-rate loop's gain: ``benchmarks/control.py``
    flies ``0.8 k_w``). Thrust and rates are clipped to the vehicle's limits
    (``max_thrust``, N; ``max_rates``, rad/s per axis) so that a command is never refused."""

    def __init__(
        self,
        mass: float,
        max_thrust: float,
        max_rates: np.ndarray,
        kp: tuple[float, float, float] = KP_POS,
        kd: tuple[float, float, float] = KD_POS,
        k_att: float = 10.0,
    ) -> None:
        self.mass = float(mass)
        self.max_thrust = float(max_thrust)
        self.max_rates = np.asarray(max_rates, dtype=float)
        self.kp, self.kd = np.asarray(kp, dtype=float), np.asarray(kd, dtype=float)
        self.k_att = float(k_att)

    def command(
        self,
        position: np.ndarray,
        velocity: np.ndarray,
        quaternion: np.ndarray,
        reference: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float, float],
    ) -> tuple[float, np.ndarray]:
        """The thrust (N) and body rates (rad/s, FLU) for the state (world ENU position and velocity, body
        FLU to world quaternion ``[x, y, z, w]``) and the ``reference`` (position, velocity, acceleration,
        jerk, yaw, yaw rate)."""
        p_ref, v_ref, a_ref, j_ref, yaw, yaw_rate = reference
        a_cmd = a_ref + self.kp * (p_ref - position) + self.kd * (v_ref - velocity)
        ff = flat_ctbr(self.mass, a_cmd, j_ref, yaw, yaw_rate)
        R = quat_to_matrix(quaternion)
        thrust = self.mass * float((a_cmd + GRAVITY * _EZ) @ R[:, 2])
        S = 0.5 * (ff.rotation.T @ R - R.T @ ff.rotation)
        e_R = np.array([S[2, 1], S[0, 2], S[1, 0]])
        rates = R.T @ ff.rotation @ ff.body_rates - self.k_att * e_R
        return min(max(thrust, 0.0), self.max_thrust), np.clip(rates, -self.max_rates, self.max_rates)
