"""The sensor set PX4 SITL reads: IMU, magnetometer, barometer, GPS and airspeed for one vehicle.

Each noisy model draws from its own ``numpy.random.Generator`` spawned from one seed, so a seed
fixes every stream and one sensor's schedule never changes another sensor's noise. Every sample of
any sensor also records the truth into the GPS delay line, so with the IMU sampled every physics
step (as PX4 SITL does) the GPS fix delay resolves to one step.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from droneulator.sensors.baro import BaroSample
from droneulator.sensors.gps import GpsSample
from droneulator.sensors.registry import get_sensor
from droneulator.sensors.truth import Truth

#: noisy sensor kinds, in the order their random streams are spawned (fixes each seed's streams)
NOISY_KINDS = ("imu", "mag", "baro", "gps")


class SensorSuite:
    """The registered IMU, magnetometer, barometer, GPS and airspeed models, deterministic under ``seed``.

    ``cfg`` is a :class:`~droneulator.config.PX4Config` (noise, biases, rates and home position).
    """

    def __init__(self, cfg: Any, seed: int = 0) -> None:
        self.cfg = cfg
        streams = np.random.SeedSequence(seed).spawn(len(NOISY_KINDS))
        self.models: dict[str, Any] = {
            kind: get_sensor(kind)(cfg, np.random.default_rng(stream))
            for kind, stream in zip(NOISY_KINDS, streams, strict=True)
        }
        self.models["airspeed"] = get_sensor("airspeed")(cfg)

    def imu(self, truth: Truth) -> tuple[np.ndarray, np.ndarray]:
        """(accelerometer m/s^2, gyroscope rad/s), both in the FRD body frame."""
        self.models["gps"].observe(truth)
        return self.models["imu"].sample(truth)

    def mag(self, truth: Truth) -> np.ndarray:
        """Magnetic field in the FRD body frame (gauss)."""
        self.models["gps"].observe(truth)
        return self.models["mag"].sample(truth)

    def baro(self, truth: Truth) -> BaroSample:
        self.models["gps"].observe(truth)
        return self.models["baro"].sample(truth)

    def gps(self, truth: Truth) -> GpsSample:
        """The fix sent now: the state ``gps_delay_s`` earlier, with the correlated error."""
        return self.models["gps"].sample(truth)

    def airspeed(self, truth: Truth) -> tuple[float, float]:
        """(indicated, true) airspeed in m/s."""
        self.models["gps"].observe(truth)
        return self.models["airspeed"].sample(truth)
