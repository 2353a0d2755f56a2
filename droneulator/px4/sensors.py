"""Sensor models PX4 SITL reads from the simulator: IMU, magnetometer, barometer and GPS.

Each model turns the simulator's ground truth (ENU world, FLU body) into what the sensor reports in
PX4's conventions (NED world, FRD body), adds a constant bias and white Gaussian noise, and draws
that noise from its own ``numpy.random.Generator`` spawned from one seed, so a seed fixes every
stream and one sensor's schedule never changes another sensor's noise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from droneulator.config import PX4Config
from droneulator.frames import (
    enu_to_geodetic,
    enu_to_ned,
    flu_to_frd,
    quat_enu_flu_to_ned_frd,
    quat_to_matrix,
)

#: gravity of the dynamics model in the ENU world, m/s^2
GRAVITY_ENU = np.array([0.0, 0.0, -9.81])

# International Standard Atmosphere, troposphere (valid to 11 km)
ISA_P0_PA = 101325.0
ISA_T0_K = 288.15
ISA_LAPSE_K_PER_M = 0.0065
ISA_RHO0 = 1.225
#: g0 * M / (R * L) for dry air
ISA_EXPONENT = 9.80665 * 0.0289644 / (8.3144598 * ISA_LAPSE_K_PER_M)
KELVIN = 273.15


def isa_temperature_k(alt_msl_m: float) -> float:
    return ISA_T0_K - ISA_LAPSE_K_PER_M * alt_msl_m


def isa_pressure_pa(alt_msl_m: float) -> float:
    """Static pressure at an altitude above mean sea level (ISA troposphere)."""
    return ISA_P0_PA * (isa_temperature_k(alt_msl_m) / ISA_T0_K) ** ISA_EXPONENT


def isa_altitude_m(pressure_pa: float) -> float:
    """Pressure altitude: the ISA altitude at which the static pressure is ``pressure_pa``."""
    return ISA_T0_K / ISA_LAPSE_K_PER_M * (1.0 - (pressure_pa / ISA_P0_PA) ** (1.0 / ISA_EXPONENT))


def isa_density(alt_msl_m: float) -> float:
    return ISA_RHO0 * (isa_temperature_k(alt_msl_m) / ISA_T0_K) ** (ISA_EXPONENT - 1.0)


@dataclass(frozen=True)
class Truth:
    """Ground truth at one instant, in the simulator's frames (ENU world, FLU body, [x,y,z,w])."""

    t_ns: int
    position: np.ndarray
    velocity: np.ndarray
    quaternion: np.ndarray
    angular_velocity: np.ndarray
    #: world-frame acceleration over the last step (m/s^2); zero at rest on the ground
    acceleration: np.ndarray
    #: wind velocity in the world frame (m/s)
    wind: np.ndarray

    @classmethod
    def from_sim(cls, sim: Any) -> Truth:
        st = sim.state
        return cls(
            st.t_ns,
            st.position,
            st.velocity,
            st.quaternion,
            st.angular_velocity,
            np.array(sim.acceleration, dtype=float),
            np.array(sim.s[13:16], dtype=float),
        )

    @property
    def R_world_body(self) -> np.ndarray:
        return quat_to_matrix(self.quaternion)

    @property
    def quaternion_ned_frd(self) -> np.ndarray:
        """Attitude as FRD body -> NED world, ``[x, y, z, w]``."""
        return quat_enu_flu_to_ned_frd(self.quaternion)

    @property
    def gyro_frd(self) -> np.ndarray:
        return flu_to_frd(self.angular_velocity)

    @property
    def specific_force_frd(self) -> np.ndarray:
        """What an ideal accelerometer reads: R^T (a - g), in the FRD body frame (m/s^2)."""
        return flu_to_frd(self.R_world_body.T @ (self.acceleration - GRAVITY_ENU))

    @property
    def acceleration_frd(self) -> np.ndarray:
        """Kinematic acceleration (no gravity) in the FRD body frame (m/s^2)."""
        return flu_to_frd(self.R_world_body.T @ self.acceleration)


@dataclass(frozen=True)
class BaroSample:
    pressure_hpa: float
    pressure_alt_m: float
    temperature_c: float


@dataclass(frozen=True)
class GpsSample:
    lat_deg: float
    lon_deg: float
    alt_msl_m: float
    #: velocity north, east, down (m/s)
    vel_ned: np.ndarray
    ground_speed: float
    #: course over ground, degrees in [0, 360)
    course_deg: float
    #: horizontal / vertical 1-sigma position accuracy (m)
    eph_m: float
    epv_m: float
    fix_type: int
    satellites: int


class SensorSuite:
    """IMU, magnetometer, barometer and GPS models for one vehicle, deterministic under ``seed``."""

    def __init__(self, cfg: PX4Config, seed: int = 0) -> None:
        self.cfg = cfg
        imu, mag, baro, gps = (np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(4))
        self._rng_imu, self._rng_mag, self._rng_baro, self._rng_gps = imu, mag, baro, gps
        self.mag_field_ned = np.array(cfg.mag_field_ned_gauss, dtype=float)

    def altitude_msl(self, truth: Truth) -> float:
        return self.cfg.home_alt_m + float(truth.position[2])

    def imu(self, truth: Truth) -> tuple[np.ndarray, np.ndarray]:
        """(accelerometer m/s^2, gyroscope rad/s), both in the FRD body frame."""
        c, rng = self.cfg, self._rng_imu
        accel = truth.specific_force_frd + np.asarray(c.accel_bias) + rng.normal(0.0, c.accel_noise, 3)
        gyro = truth.gyro_frd + np.asarray(c.gyro_bias) + rng.normal(0.0, c.gyro_noise, 3)
        return accel, gyro

    def mag(self, truth: Truth) -> np.ndarray:
        """Magnetic field in the FRD body frame (gauss): the NED field rotated into the body."""
        R_ned_frd = quat_to_matrix(truth.quaternion_ned_frd)
        field = R_ned_frd.T @ self.mag_field_ned
        return field + np.asarray(self.cfg.mag_bias) + self._rng_mag.normal(0.0, self.cfg.mag_noise, 3)

    def baro(self, truth: Truth) -> BaroSample:
        """Absolute pressure (ISA at the true altitude, plus bias and noise), the pressure altitude
        it implies, and the ISA temperature."""
        alt = self.altitude_msl(truth)
        p_hpa = isa_pressure_pa(alt) / 100.0 + self.cfg.baro_bias_hpa
        p_hpa += self._rng_baro.normal(0.0, self.cfg.baro_noise_hpa)
        return BaroSample(p_hpa, isa_altitude_m(p_hpa * 100.0), isa_temperature_k(alt) - KELVIN)

    def gps(self, truth: Truth) -> GpsSample:
        """A 3D fix: position from the home position plus the (noisy) ENU offset, NED velocity."""
        c, rng = self.cfg, self._rng_gps
        sigma = np.array([c.gps_noise_m, c.gps_noise_m, c.gps_vertical_noise_m])
        pos_ned = enu_to_ned(truth.position) + np.asarray(c.gps_bias_m) + rng.normal(0.0, 1.0, 3) * sigma
        vel_ned = enu_to_ned(truth.velocity) + rng.normal(0.0, c.gps_vel_noise, 3)
        lat, lon, alt = enu_to_geodetic(enu_to_ned(pos_ned), c.home_lat_deg, c.home_lon_deg, c.home_alt_m)
        course = math.degrees(math.atan2(vel_ned[1], vel_ned[0])) % 360.0
        return GpsSample(
            lat,
            lon,
            alt,
            vel_ned,
            float(math.hypot(vel_ned[0], vel_ned[1])),
            course,
            eph_m=max(c.gps_noise_m, 0.01),
            epv_m=max(c.gps_vertical_noise_m, 0.01),
            fix_type=3,
            satellites=c.gps_satellites,
        )

    def airspeed(self, truth: Truth) -> tuple[float, float]:
        """(indicated, true) airspeed in m/s from the velocity relative to the wind."""
        tas = float(np.linalg.norm(truth.velocity - truth.wind))
        return tas * math.sqrt(isa_density(self.altitude_msl(truth)) / ISA_RHO0), tas
