"""IMU: accelerometer and gyroscope in PX4's FRD body frame, with a constant bias and white noise."""

from __future__ import annotations

from typing import Any

import numpy as np

from droneulator.sensors.registry import register
from droneulator.sensors.truth import Truth


@register("imu")
class Imu:
    """Specific force (m/s^2) and body rates (rad/s) in FRD; ``cfg`` gives ``accel_noise``,
    ``accel_bias``, ``gyro_noise`` and ``gyro_bias`` (:class:`~droneulator.config.PX4Config`)."""

    def __init__(self, cfg: Any, rng: np.random.Generator) -> None:
        self.cfg = cfg
        self.rng = rng

    def sample(self, truth: Truth) -> tuple[np.ndarray, np.ndarray]:
        """(accelerometer m/s^2, gyroscope rad/s), both in the FRD body frame."""
        c, rng = self.cfg, self.rng
        accel = truth.specific_force_frd + np.asarray(c.accel_bias) + rng.normal(0.0, c.accel_noise, 3)
        gyro = truth.gyro_frd + np.asarray(c.gyro_bias) + rng.normal(0.0, c.gyro_noise, 3)
        return accel, gyro
