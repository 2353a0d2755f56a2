"""The sensor faults active on one vehicle (docs/faults.md), applied to each sample after the model's own
errors, so that every consumer of the suite (PX4's HIL_SENSOR and HIL_GPS, ArduPilot's JSON reply, the
ROS sensor topics) sees the same faulty data.

The world's fault board (:mod:`droneulator.world.faults`) sets :attr:`SensorSuite.faults` whenever a
fault starts or ends; an inactive :class:`SensorFaults` leaves every sample as it was.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable

import numpy as np

from droneulator.config.faults import FaultSpec
from droneulator.config.site import SiteConfig
from droneulator.frames import enu_to_geodetic, geodetic_to_enu
from droneulator.sensors.baro import BaroSample, isa_pressure_pa
from droneulator.sensors.gps import GpsSample

_NS = 1_000_000_000


class SensorFaults:
    """What the active faults of one vehicle do to its sensors: built from ``(spec, start t_ns)`` pairs
    (:meth:`set`); ``rng`` draws the jamming noise (a stream of its own: the models' noise is untouched)."""

    def __init__(self, rng: np.random.Generator) -> None:
        self.rng = rng
        self.set(())

    def set(self, faults: Iterable[tuple[FaultSpec, int]]) -> None:
        """Take the sensor faults among ``faults`` (each with its start, sim ns) as the active ones."""
        self.gps_lost = False
        self.jam_noise_m = 0.0
        self.jam_satellites: int | None = None
        #: spoofing: (start ns, offset ENU m, drift ENU m/s) of each active spoofer
        self.spoofs: list[tuple[int, np.ndarray, np.ndarray]] = []
        self.accel_bias = np.zeros(3)
        self.gyro_bias = np.zeros(3)
        #: baro drift: (start ns, rate m/s) of each
        self.baro_drifts: list[tuple[int, float]] = []
        self.mag_field = np.zeros(3)
        for spec, start in faults:
            k = spec.kind
            if k == "gps_loss":
                self.gps_lost = True
            elif k == "gps_jamming":
                assert spec.noise_m is not None and spec.satellites is not None
                self.jam_noise_m = math.hypot(self.jam_noise_m, spec.noise_m)
                sats = spec.satellites
                self.jam_satellites = sats if self.jam_satellites is None else min(self.jam_satellites, sats)
            elif k == "gps_spoofing":
                self.spoofs.append(
                    (start, np.array(spec.offset, dtype=float), np.array(spec.drift, dtype=float))
                )
            elif k == "imu_bias":
                self.accel_bias += np.asarray(spec.accel, dtype=float)
                self.gyro_bias += np.asarray(spec.gyro, dtype=float)
            elif k == "baro_drift":
                assert spec.rate is not None
                self.baro_drifts.append((start, spec.rate))
            elif k == "mag_interference":
                self.mag_field += np.asarray(spec.field, dtype=float)
        self.imu_active = bool(np.any(self.accel_bias) or np.any(self.gyro_bias))
        self.gps_active = self.gps_lost or self.jam_satellites is not None or bool(self.spoofs)

    def imu(
        self, accel: np.ndarray, gyro: np.ndarray, accel_range: float, gyro_range: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """The IMU sample (FRD) with the bias steps, clipped to the part's ranges again."""
        if not self.imu_active:
            return accel, gyro
        a = np.clip(accel + self.accel_bias, -accel_range, accel_range)
        g = np.clip(gyro + self.gyro_bias, -gyro_range, gyro_range)
        return a, g

    def mag(self, field: np.ndarray) -> np.ndarray:
        """The magnetometer's field (FRD, gauss) with the interference added."""
        return field + self.mag_field if np.any(self.mag_field) else field

    def baro(self, sample: BaroSample, t_ns: int) -> BaroSample:
        """The barometer sample with its pressure altitude drifted (the pressure follows, by the ISA)."""
        if not self.baro_drifts:
            return sample
        shift = sum(rate * max(0, t_ns - start) / _NS for start, rate in self.baro_drifts)
        alt = sample.pressure_alt_m + shift
        return dataclasses.replace(sample, pressure_hpa=isa_pressure_pa(alt) / 100.0, pressure_alt_m=alt)

    def gps(self, sample: GpsSample, t_ns: int, site: SiteConfig) -> GpsSample:
        """The fix jammed (more noise, fewer satellites, eph/epv grown by the noise) and spoofed (moved by
        every spoofer's offset and drift, its velocity carrying the drift); :meth:`lost` says whether a
        fix comes at all."""
        if not self.gps_active or self.gps_lost:
            return sample
        shift = np.zeros(3)
        drift = np.zeros(3)
        for start, offset, rate in self.spoofs:
            shift += offset + rate * (max(0, t_ns - start) / _NS)
            drift += rate
        out = sample
        if self.jam_satellites is not None:
            shift += self.jam_noise_m * self.rng.standard_normal(3)
            out = dataclasses.replace(
                out,
                eph_m=math.hypot(out.eph_m, self.jam_noise_m),
                epv_m=math.hypot(out.epv_m, self.jam_noise_m),
                satellites=self.jam_satellites,
            )
        if not np.any(shift) and not np.any(drift):
            return out
        origin = site.geodetic
        enu = geodetic_to_enu(out.lat_deg, out.lon_deg, out.alt_msl_m, *origin) + shift
        lat, lon, alt = enu_to_geodetic(enu, *origin)
        vel = out.vel_ned + np.array([drift[1], drift[0], -drift[2]])
        course = math.degrees(math.atan2(vel[1], vel[0])) % 360.0
        speed = float(math.hypot(vel[0], vel[1]))
        return dataclasses.replace(
            out, lat_deg=lat, lon_deg=lon, alt_msl_m=alt, vel_ned=vel, ground_speed=speed, course_deg=course
        )
