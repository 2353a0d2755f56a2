"""IMU: accelerometer and gyroscope in PX4's FRD body frame, with a constant bias, white noise (a preset's
noise density at the sampling rate, :mod:`droneulator.config.sensor_presets`) and range saturation."""

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
#: the IMU rate PX4 SITL expects (IMU_INTEG_RATE 250): the sampling rate when none is given
IMU_HZ = 250.0


@register("imu")
class Imu:
    """Specific force (m/s^2) and body rates (rad/s) in FRD; ``cfg`` (a
    :class:`~droneulator.config.PX4Config`) gives the noise
    (:meth:`~droneulator.config.PX4Config.imu_error`: ``imu_preset`` and the ``accel_noise`` /
    ``gyro_noise`` overrides), ``accel_bias`` and ``gyro_bias``.

    ``rate_hz`` is how often the IMU is sampled (the physics rate: every step is one sample, as PX4 SITL
    reads it); a preset's noise densities become per-sample sigmas at it, ``density * sqrt(rate_hz)``.

    Each axis saturates at the part's full scale after noise and bias, as a real sensor clips:
    ``accel_range_g`` (g) and ``gyro_range_dps`` (deg/s) from the arguments, else from ``cfg`` when
    it has them, else the preset's (+-16 g and +-2000 deg/s for ``sitl``).
    """

    def __init__(
        self,
        cfg: Any,
        rng: np.random.Generator,
        accel_range_g: float | None = None,
        gyro_range_dps: float | None = None,
        rate_hz: float = IMU_HZ,
    ) -> None:
        self.cfg = cfg
        self.rng = rng
        if not (math.isfinite(rate_hz) and rate_hz > 0):
            raise ValueError(f"IMU rate_hz must be a positive rate, got {rate_hz!r}")
        #: the part, its per-sample sigmas at ``rate_hz`` and its ranges
        self.model = cfg.imu_error(rate_hz)
        accel_g = _range(accel_range_g, cfg, "accel_range_g", self.model.accel_range_g)
        gyro_dps = _range(gyro_range_dps, cfg, "gyro_range_dps", self.model.gyro_range_dps)
        #: full scale of each accelerometer axis (m/s^2) and gyroscope axis (rad/s)
        self.accel_range = accel_g * G0
        self.gyro_range = math.radians(gyro_dps)
        #: per-sample 1-sigma of each accelerometer (m/s^2) and gyroscope (rad/s) axis
        self.accel_sigma = float(self.model.accel_sigma)
        self.gyro_sigma = float(self.model.gyro_sigma)

    def sample(self, truth: Truth) -> tuple[np.ndarray, np.ndarray]:
        """(accelerometer m/s^2, gyroscope rad/s), both in the FRD body frame, clipped to range."""
        c, rng = self.cfg, self.rng
        accel = truth.specific_force_frd + np.asarray(c.accel_bias) + rng.normal(0.0, self.accel_sigma, 3)
        gyro = truth.gyro_frd + np.asarray(c.gyro_bias) + rng.normal(0.0, self.gyro_sigma, 3)
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
