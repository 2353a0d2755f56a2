"""IMU: accelerometer and gyroscope in PX4's FRD body frame, with a constant bias, white noise and
range saturation."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from droneulator.sensors.registry import register
from droneulator.sensors.truth import Truth

#: standard gravity (m/s^2), the unit of accelerometer ranges
G0 = 9.80665
#: full-scale ranges PX4 configures its usual IMUs for (e.g. the ICM-42688-P)
ACCEL_RANGE_G = 16.0
GYRO_RANGE_DPS = 2000.0


@register("imu")
class Imu:
    """Specific force (m/s^2) and body rates (rad/s) in FRD; ``cfg`` gives ``accel_noise``,
    ``accel_bias``, ``gyro_noise`` and ``gyro_bias`` (:class:`~droneulator.config.PX4Config`).

    Each axis saturates at the part's full scale after noise and bias, as a real sensor clips:
    ``accel_range_g`` (g) and ``gyro_range_dps`` (deg/s) from the arguments, else from ``cfg`` when
    it has them, else +-16 g and +-2000 deg/s.
    """

    def __init__(
        self,
        cfg: Any,
        rng: np.random.Generator,
        accel_range_g: float | None = None,
        gyro_range_dps: float | None = None,
    ) -> None:
        self.cfg = cfg
        self.rng = rng
        accel_g = _range(accel_range_g, cfg, "accel_range_g", ACCEL_RANGE_G)
        gyro_dps = _range(gyro_range_dps, cfg, "gyro_range_dps", GYRO_RANGE_DPS)
        #: full scale of each accelerometer axis (m/s^2) and gyroscope axis (rad/s)
        self.accel_range = accel_g * G0
        self.gyro_range = math.radians(gyro_dps)

    def sample(self, truth: Truth) -> tuple[np.ndarray, np.ndarray]:
        """(accelerometer m/s^2, gyroscope rad/s), both in the FRD body frame, clipped to range."""
        c, rng = self.cfg, self.rng
        accel = truth.specific_force_frd + np.asarray(c.accel_bias) + rng.normal(0.0, c.accel_noise, 3)
        gyro = truth.gyro_frd + np.asarray(c.gyro_bias) + rng.normal(0.0, c.gyro_noise, 3)
        np.clip(accel, -self.accel_range, self.accel_range, out=accel)
        np.clip(gyro, -self.gyro_range, self.gyro_range, out=gyro)
        return accel, gyro


def _range(value: float | None, cfg: Any, name: str, default: float) -> float:
    """A full-scale range: the explicit value, else ``cfg.<name>`` if the config has it, else default."""
    if value is None:
        value = getattr(cfg, name, default)
    value = float(value)
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"IMU {name} must be a positive full-scale range, got {value!r}")
    return value
