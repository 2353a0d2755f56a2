"""Velocity mode (paper §II-C): a unicycle command pair (forward speed, yaw rate) is smoothed by a
slew-rate limit and a first-order low-pass filter, then integrated into a virtual reference
setpoint that the SE(3) controller tracks. Altitude is held at the value the mode started with.

The reference is a packed array (:data:`VREF_SIZE`) advanced by one compiled function,
:func:`velocity_flat`: a :class:`VelocityReference` of one vehicle and every row of the batched worlds
(:mod:`droneulator.world.batched`) run the same code."""

from __future__ import annotations

import math

import numba
import numpy as np

from droneulator.config import FlightConfig
from droneulator.state import FLAT_SIZE

#: a packed reference: position (3), held altitude, yaw, command (forward, yaw rate), slewed (2) and
#: filtered (2) command
VP, VALT, VYAW, VCMD, VSLEW, VFILT = 0, 3, 4, 5, 7, 9
VREF_SIZE = 11


@numba.njit(cache=True)
def velocity_flat(v: np.ndarray, dt: float, veh: np.ndarray, lim: np.ndarray, flat: np.ndarray) -> None:
    """Advance the packed reference ``v`` by ``dt`` toward its command, the vehicle at ``veh``, and write
    the packed flat output to ``flat``; ``lim`` = (max forward accel, max yaw accel, filter tau, leash)."""
    alpha = dt / (lim[2] + dt)
    prev_speed = v[VFILT]
    for i in range(2):
        step = lim[i] * dt
        v[VSLEW + i] += min(max(v[VCMD + i] - v[VSLEW + i], -step), step)
        v[VFILT + i] += alpha * (v[VSLEW + i] - v[VFILT + i])
    speed, rate = v[VFILT], v[VFILT + 1]
    v[VYAW] += rate * dt
    c, s = math.cos(v[VYAW]), math.sin(v[VYAW])
    v[VP] += speed * c * dt
    v[VP + 1] += speed * s * dt
    v[VP + 2] = v[VALT]
    # anti wind-up: the reference never runs further than the leash ahead of the vehicle
    ox, oy = v[VP] - veh[0], v[VP + 1] - veh[1]
    dist = math.hypot(ox, oy)
    if dist > lim[3]:
        v[VP] = veh[0] + ox * (lim[3] / dist)
        v[VP + 1] = veh[1] + oy * (lim[3] / dist)
    accel = (speed - prev_speed) / dt
    for j in range(FLAT_SIZE):
        flat[j] = 0.0
    flat[0], flat[1], flat[2] = v[VP], v[VP + 1], v[VP + 2]
    flat[3], flat[4] = speed * c, speed * s
    flat[6], flat[7] = accel * c - speed * rate * s, accel * s + speed * rate * c
    flat[9], flat[10] = v[VYAW], rate


def velocity_limits(cfg: FlightConfig) -> np.ndarray:
    """The ``lim`` argument of :func:`velocity_flat` for the flight settings ``cfg``."""
    return np.array([cfg.max_forward_accel, cfg.max_yaw_accel, cfg.filter_tau, cfg.leash])


def start_reference(v: np.ndarray, position: np.ndarray, yaw: float, speed: float, yaw_rate: float) -> None:
    """Set the packed reference ``v`` to start at ``position`` facing ``yaw``, filters at the given speed and
    yaw rate, its altitude held at the position's."""
    v[VP : VP + 3] = position
    v[VALT], v[VYAW] = position[2], yaw
    v[VSLEW : VSLEW + 2] = (speed, yaw_rate)
    v[VFILT : VFILT + 2] = (speed, yaw_rate)


class VelocityReference:
    """Virtual reference driven by (forward speed, yaw rate); produces packed flat outputs."""

    def __init__(
        self, cfg: FlightConfig, position: np.ndarray, yaw: float, speed: float = 0.0, yaw_rate: float = 0.0
    ) -> None:
        self.cfg = cfg
        self._lim = velocity_limits(cfg)
        #: the packed reference (:data:`VREF_SIZE`)
        self.v = np.zeros(VREF_SIZE)
        start_reference(self.v, np.asarray(position, dtype=float), float(yaw), float(speed), float(yaw_rate))
        self._flat = np.zeros(FLAT_SIZE)

    @property
    def position(self) -> np.ndarray:
        """The reference position (a view into the packed reference)."""
        return self.v[VP : VP + 3]

    @property
    def yaw(self) -> float:
        return float(self.v[VYAW])

    @property
    def target(self) -> tuple[float, float]:
        """The commanded (forward speed, yaw rate)."""
        return float(self.v[VCMD]), float(self.v[VCMD + 1])

    def command(self, forward: float, yaw_rate: float) -> None:
        self.v[VCMD], self.v[VCMD + 1] = float(forward), float(yaw_rate)

    def update(self, dt: float, vehicle_position: np.ndarray) -> np.ndarray:
        """Advance the filters and the reference by ``dt``; returns the packed flat output (reused)."""
        velocity_flat(self.v, dt, np.asarray(vehicle_position, dtype=np.float64), self._lim, self._flat)
        return self._flat
