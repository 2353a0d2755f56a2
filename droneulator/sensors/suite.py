"""A vehicle's noisy sensors: the IMU, magnetometer, barometer, GPS and airspeed it is configured with.

Each noisy model draws from its own ``numpy.random.Generator`` spawned from one seed, so a seed
fixes every stream and one sensor's schedule (or absence) never changes another sensor's noise.
Every sample of any sensor also records the truth into the GPS delay line, so with the IMU sampled
every physics step (as PX4 SITL does) the GPS fix delay resolves to one step.

The suite keeps the newest sample of each sensor (:attr:`SensorSuite.latest`), whoever drew it: the
PX4 link, which samples a PX4 vehicle's sensors every step, or the runtime for a vehicle it flies
itself (:meth:`SensorSuite.sample_due`). The ROS sensor topics publish those, so PX4 and ROS get one
sample, not two independent draws.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from droneulator.config.site import SiteConfig
from droneulator.sensors.baro import BaroSample
from droneulator.sensors.faults import SensorFaults
from droneulator.sensors.gps import GpsSample
from droneulator.sensors.imu import IMU_HZ
from droneulator.sensors.registry import get_sensor
from droneulator.sensors.truth import Truth

#: noisy sensor kinds, in the order their random streams are spawned (fixes each seed's streams)
NOISY_KINDS = ("imu", "mag", "baro", "gps")
#: every kind a suite can hold, and what a vehicle carries unless configured otherwise
SUITE_KINDS = (*NOISY_KINDS, "airspeed")
#: what every HIL_SENSOR message to PX4 carries: a vehicle PX4 flies must have these
PX4_SENSORS = ("imu", "mag", "baro")
#: sim nanoseconds per second
_NS = 1_000_000_000


@dataclass(frozen=True)
class Reading:
    """One sample of one sensor: ``seq`` counts the samples of its kind (a new sample, a new number),
    ``t_ns`` is the sim time of the truth it was drawn from, ``value`` what the sensor read: (accel,
    gyro) in FRD for the IMU, the FRD field (gauss) for the magnetometer, a
    :class:`~droneulator.sensors.baro.BaroSample`, a :class:`~droneulator.sensors.gps.GpsSample`."""

    seq: int
    t_ns: int
    value: Any


class Schedule:
    """Which periodic samples are due: one per ``1 / hz`` of sim time per name, the first at once.

    A sample comes due at the first time at or after its slot; the next slot is one period later, or
    one period after now when the schedule fell a whole period behind. Time running backwards (a reset)
    restarts every schedule. The PX4 link and the runtime schedule their sensors with it.
    """

    def __init__(self) -> None:
        self._next: dict[str, int] = {}
        self._last_t_ns: int | None = None

    def clear(self) -> None:
        self._next.clear()

    def due(self, name: str, t_ns: int, hz: float) -> bool:
        """True when ``name`` (sampled at ``hz`` in sim time) has a sample due at ``t_ns``."""
        if self._last_t_ns is not None and t_ns < self._last_t_ns:
            self._next.clear()
        self._last_t_ns = t_ns
        period = max(1, round(_NS / hz))
        nxt = self._next.get(name)
        if nxt is not None and t_ns < nxt:
            return False
        self._next[name] = t_ns + period if nxt is None or nxt + period <= t_ns else nxt + period
        return True


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

    ``cfg`` is a :class:`~droneulator.config.PX4Config` (noise presets and overrides, biases, rates);
    ``site`` the :class:`~droneulator.config.SiteConfig` the GPS, barometer, magnetometer and airspeed
    read the world origin's place from (None: the default site); ``imu_hz`` how often the IMU is
    sampled (the physics rate), at which its preset's noise densities become per-sample sigmas.
    """

    def __init__(
        self,
        cfg: Any,
        seed: int | np.random.SeedSequence = 0,
        kinds: Sequence[str] = SUITE_KINDS,
        imu_hz: float = IMU_HZ,
        site: SiteConfig | None = None,
    ) -> None:
        self.cfg = cfg
        self.site = site or SiteConfig()
        self.kinds = check_kinds(kinds)
        self.imu_hz = float(imu_hz)
        seq = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(seed)
        streams = dict(zip(NOISY_KINDS, seq.spawn(len(NOISY_KINDS)), strict=True))
        self.models: dict[str, Any] = {}
        for kind in self.kinds:
            model = get_sensor(kind)
            if kind == "imu":
                self.models[kind] = model(cfg, np.random.default_rng(streams[kind]), rate_hz=self.imu_hz)
            elif kind in streams:
                self.models[kind] = model(cfg, np.random.default_rng(streams[kind]), site=self.site)
            else:
                self.models[kind] = model(cfg, site=self.site)
        #: the GPS delay line hears every sample, when there is a GPS
        self._gps = self.models.get("gps")
        #: the active sensor faults (docs/faults.md), drawn from a stream of their own spawned after the
        #: models' (so the models' streams are what they were without faults)
        self.faults = SensorFaults(np.random.default_rng(seq.spawn(1)[0]))
        #: the newest sample of each kind (see :class:`Reading`), whoever drew it
        self.latest: dict[str, Reading] = {}
        self._seq = 0

    def record(self, kind: str, t_ns: int, value: Any) -> Reading:
        """Keep ``value`` as the newest ``kind`` sample (the sampling methods call it; the PX4 link
        calls it again with the IMU sample as it sent it, clipped to PX4's FIFO)."""
        self._seq += 1
        reading = Reading(self._seq, int(t_ns), value)
        self.latest[kind] = reading
        return reading

    def sample_due(self, truth: Truth, schedule: Schedule) -> None:
        """Sample the IMU now and each of the magnetometer, barometer and GPS the vehicle carries whose
        rate (``cfg.mag_hz``, ``baro_hz``, ``gps_hz`` in sim time) has a sample due on ``schedule``; the
        samples land in :attr:`latest`."""
        c, t_ns = self.cfg, truth.t_ns
        if "imu" in self.models:
            self.imu(truth)
        if "mag" in self.models and schedule.due("mag", t_ns, c.mag_hz):
            self.mag(truth)
        if "baro" in self.models and schedule.due("baro", t_ns, c.baro_hz):
            self.baro(truth)
        if "gps" in self.models and schedule.due("gps", t_ns, c.gps_hz):
            self.gps(truth)  # None, nothing recorded, while the GPS is lost

    def __contains__(self, kind: str) -> bool:
        return kind in self.models

    def _observe(self, truth: Truth) -> None:
        if self._gps is not None:
            self._gps.observe(truth)

    def imu(self, truth: Truth) -> tuple[np.ndarray, np.ndarray]:
        """(accelerometer m/s^2, gyroscope rad/s), both in the FRD body frame."""
        self._observe(truth)
        model = self.models["imu"]
        accel, gyro = model.sample(truth)
        out = self.faults.imu(accel, gyro, model.accel_range, model.gyro_range)
        self.record("imu", truth.t_ns, out)
        return out

    def mag(self, truth: Truth) -> np.ndarray:
        """Magnetic field in the FRD body frame (gauss)."""
        self._observe(truth)
        out = self.faults.mag(self.models["mag"].sample(truth))
        self.record("mag", truth.t_ns, out)
        return out

    def baro(self, truth: Truth) -> BaroSample:
        self._observe(truth)
        out = self.faults.baro(self.models["baro"].sample(truth), truth.t_ns)
        self.record("baro", truth.t_ns, out)
        return out

    def gps(self, truth: Truth) -> GpsSample | None:
        """The fix sent now: the state ``gps_delay_s`` earlier, with the correlated error (and the active
        jamming or spoofing); None while the GPS is lost (a ``gps_loss`` fault)."""
        if self.faults.gps_lost:
            self._observe(truth)
            return None
        out = self.faults.gps(self.models["gps"].sample(truth), truth.t_ns, self.site)
        self.record("gps", truth.t_ns, out)
        return out

    def airspeed(self, truth: Truth) -> tuple[float, float]:
        """(indicated, true) airspeed in m/s."""
        self._observe(truth)
        return self.models["airspeed"].sample(truth)
