"""Velocity mode (paper §II-C): a unicycle command pair (forward speed, yaw rate) is smoothed by a
slew-rate limit and a first-order low-pass filter, then integrated into a virtual reference
setpoint that the SE(3) controller tracks. Altitude is held at the value the mode started with."""

from __future__ import annotations

import math

import numpy as np

from droneulator.config import FlightConfig
from droneulator.state import FLAT_SIZE


class VelocityReference:
    """Virtual reference driven by (forward speed, yaw rate); produces packed flat outputs."""

    def __init__(
        self, cfg: FlightConfig, position: np.ndarray, yaw: float, speed: float = 0.0, yaw_rate: float = 0.0
    ) -> None:
        self.cfg = cfg
        self.position = np.array(position, dtype=float)
        self.altitude = float(position[2])
        self.yaw = float(yaw)
        self.target = (0.0, 0.0)
        self.slewed = [speed, yaw_rate]
        self.filtered = [speed, yaw_rate]
        self._flat = np.zeros(FLAT_SIZE)

    def command(self, forward: float, yaw_rate: float) -> None:
        self.target = (float(forward), float(yaw_rate))

    def update(self, dt: float, vehicle_position: np.ndarray) -> np.ndarray:
        """Advance the filters and the reference by ``dt``; returns the packed flat output (reused)."""
        cfg = self.cfg
        limits = (cfg.max_forward_accel * dt, cfg.max_yaw_accel * dt)
        alpha = dt / (cfg.filter_tau + dt)
        prev_speed = self.filtered[0]
        for i in range(2):
            self.slewed[i] += min(max(self.target[i] - self.slewed[i], -limits[i]), limits[i])
            self.filtered[i] += alpha * (self.slewed[i] - self.filtered[i])
        speed, rate = self.filtered
        self.yaw += rate * dt
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        self.position[0] += speed * c * dt
        self.position[1] += speed * s * dt
        self.position[2] = self.altitude
        # anti wind-up: the reference never runs further than the leash ahead of the vehicle
        offset = self.position[:2] - vehicle_position[:2]
        dist = float(np.hypot(*offset))
        if dist > cfg.leash:
            self.position[:2] = vehicle_position[:2] + offset * (cfg.leash / dist)
        accel = (speed - prev_speed) / dt
        f = self._flat
        f[0:3] = self.position
        f[3:6] = (speed * c, speed * s, 0.0)
        f[6:9] = (accel * c - speed * rate * s, accel * s + speed * rate * c, 0.0)
        f[9] = self.yaw
        f[10] = rate
        return f
