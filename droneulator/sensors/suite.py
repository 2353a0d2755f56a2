"""A vehicle's noisy sensors: the IMU, magnetometer, barometer, GPS and airspeed it is configured with.

Each noisy model draws from its own ``numpy.random.Generator`` spawned from one seed, so a seed
fixes every stream and one sensor's schedule (or absence) never changes another sensor's noise.
Every sample of any sensor also records the truth into the GPS delay line, so with the IMU sampled
every physics step (as PX4 SITL does) the GPS fix delay resolves to one step.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from droneulator.sensors.baro import BaroSample
from droneulator.sensors.gps import GpsSample
from droneulator.sensors.registry import get_sensor
from droneulator.sensors.truth import Truth

#: noisy sensor kinds, in the order their random streams are spawned (fixes each seed's streams)
NOISY_KINDS = ("imu", "mag", "baro", "gps")
#: every kind a suite can hold, and what a vehicle carries unless configured otherwise
SUITE_KINDS = (*NOISY_KINDS, "airspeed")
#: what every HIL_SENSOR message to PX4 carries: a vehicle PX4 flies must have these
PX4_SENSORS = ("imu", "mag", "baro")


def check_kinds(kinds: Sequence[str]) -> tuple[str, ...]:
    """``kinds`` as a tuple, each a registered sensor a suite holds (cameras are configured apart)."""
    for kind in kinds:
        get_sensor(kind)  # an unknown kind names the registered ones
        if kind not in SUITE_KINDS:
            raise ValueError(
                f"sensor kind {kind!r} is not one a vehicle's 'sensors' list takes "
                f"({', '.join(SUITE_KINDS)}); cameras are configured under 'cameras'"
            )
    if len(set(kinds)) != len(kinds):
        raise ValueError(f"sensors {list(kinds)}: each kind at most once")
    return tuple(kinds)


class SensorSuite:
    """The registered models of ``kinds`` (default all of :data:`SUITE_KINDS`), deterministic under
    ``seed``.

    ``cfg`` is a :class:`~droneulator.config.PX4Config` (noise, biases, rates and home position).
    """

    def __init__(
        self, cfg: Any, seed: int | np.random.SeedSequence = 0, kinds: Sequence[str] = SUITE_KINDS
    ) -> None:
        self.cfg = cfg
        self.kinds = check_kinds(kinds)
        seq = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(seed)
        streams = dict(zip(NOISY_KINDS, seq.spawn(len(NOISY_KINDS)), strict=True))
        self.models: dict[str, Any] = {
            kind: get_sensor(kind)(cfg, np.random.default_rng(streams[kind]))
            if kind in streams
            else get_sensor(kind)(cfg)
            for kind in self.kinds
        }
        #: the GPS delay line hears every sample, when there is a GPS
        self._gps = self.models.get("gps")

    def __contains__(self, kind: str) -> bool:
        return kind in self.models

    def _observe(self, truth: Truth) -> None:
        if self._gps is not None:
            self._gps.observe(truth)

    def imu(self, truth: Truth) -> tuple[np.ndarray, np.ndarray]:
        """(accelerometer m/s^2, gyroscope rad/s), both in the FRD body frame."""
        self._observe(truth)
        return self.models["imu"].sample(truth)

    def mag(self, truth: Truth) -> np.ndarray:
        """Magnetic field in the FRD body frame (gauss)."""
        self._observe(truth)
        return self.models["mag"].sample(truth)

    def baro(self, truth: Truth) -> BaroSample:
        self._observe(truth)
        return self.models["baro"].sample(truth)

    def gps(self, truth: Truth) -> GpsSample:
        """The fix sent now: the state ``gps_delay_s`` earlier, with the correlated error."""
        return self.models["gps"].sample(truth)

    def airspeed(self, truth: Truth) -> tuple[float, float]:
        """(indicated, true) airspeed in m/s."""
        self._observe(truth)
        return self.models["airspeed"].sample(truth)
