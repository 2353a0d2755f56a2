"""The noise presets of the IMU, barometer, magnetometer and GPS, each named after a real part:
``px4.imu_preset``, ``px4.baro_preset``, ``px4.mag_preset`` and ``px4.gps_preset`` name them. One table
per sensor, read by the config's checks and by every sensor model (:mod:`droneulator.sensors`), so PX4's
HIL messages and the ROS sensor topics carry the same numbers. Sources and derivations are in
docs/sensors.md ("IMU, barometer, magnetometer, GPS: presets").

Every preset's ``sitl`` entry reproduces the numbers the simulator used before presets existed, so a
config that names no preset reads what it read before.

Noise densities become per-sample standard deviations at the rate the sensor is sampled,
``sigma = density * sqrt(rate)``: white noise of two-sided density ``density`` seen through an
integrating sampler of period ``1 / rate``. This is Kalibr's discrete-time convention
(``sigma_d = sigma_c / sqrt(dt)``, "IMU Noise Model" in the ethz-asl/kalibr wiki) and what
rotors_simulator's IMU plugin, which PX4's Gazebo-classic simulation uses, computes
(``sigma_g_d = 1 / sqrt(dt) * gyroscope_noise_density``). Barometer and magnetometer datasheets give an
RMS noise per measurement at a stated mode instead, which is used as the per-sample sigma directly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

#: standard gravity (m/s^2): datasheets give accelerometer noise in g
G0 = 9.80665
_UG = 1e-6 * G0  # m/s^2 per micro-g
_DPS = math.pi / 180.0  # rad/s per deg/s


@dataclass(frozen=True)
class ImuModel:
    """An IMU's white noise and full-scale ranges.

    ``accel_density`` (m/s^2/sqrt(Hz)) and ``gyro_density`` (rad/s/sqrt(Hz)) are the datasheet noise
    densities; ``accel_sigma`` / ``gyro_sigma``, when set, are per-sample 1-sigmas that hold at any rate
    instead (the ``sitl`` preset's). ``accel_range_g`` / ``gyro_range_dps``: full scale, where each axis
    clips.
    """

    part: str
    accel_density: float
    gyro_density: float
    accel_range_g: float = 16.0
    gyro_range_dps: float = 2000.0
    accel_sigma: float | None = None
    gyro_sigma: float | None = None

    def accel_noise(self, rate_hz: float) -> float:
        """Per-sample accelerometer 1-sigma (m/s^2) at ``rate_hz`` samples per second."""
        return self.accel_sigma if self.accel_sigma is not None else self.accel_density * math.sqrt(rate_hz)

    def gyro_noise(self, rate_hz: float) -> float:
        """Per-sample gyroscope 1-sigma (rad/s) at ``rate_hz`` samples per second."""
        return self.gyro_sigma if self.gyro_sigma is not None else self.gyro_density * math.sqrt(rate_hz)


#: ``px4.imu_preset`` choices.
#:
#: * sitl: the simulator's own figures (0.02 m/s^2, 0.002 rad/s per sample at any rate; at PX4's 250 Hz
#:   that is 129 ug/sqrt(Hz) and 0.0072 deg/s/sqrt(Hz), between the two parts below), +-16 g, +-2000 deg/s.
#: * icm42688p: TDK InvenSense ICM-42688-P (datasheet DS-000347, low-noise mode): gyro 2.8 mdps/sqrt(Hz),
#:   accel 70 ug/sqrt(Hz); full scale +-16 g, +-2000 deg/s. PX4's usual flight-controller IMU.
#: * bmi088: Bosch BMI088 (datasheet BST-BMI088-DS001; Bosch's summary figures, approx.): gyro
#:   0.014 deg/s/sqrt(Hz), accel 175 ug/sqrt(Hz); full scale +-24 g, +-2000 deg/s.
#: * adis16448: the defaults of PX4's Gazebo-classic IMU plugin (PX4-SITL_gazebo-classic
#:   include/gazebo_imu_plugin.h, "Default values for use with ADIS16448 IMU"): gyro 2 * 35 deg/h/sqrt(Hz)
#:   = 3.39e-4 rad/s/sqrt(Hz), accel 2 * 2.0e-3 = 4.0e-3 m/s^2/sqrt(Hz) (twice the part's own figures);
#:   full scale of the ADIS16448 (Analog Devices datasheet): +-18 g, +-1000 deg/s. The plugin's bias
#:   random walk and turn-on bias are not modelled (``px4.accel_bias`` / ``gyro_bias`` are constant).
IMU_PRESETS: dict[str, ImuModel] = {
    "sitl": ImuModel("simulator default", 0.0, 0.0, 16.0, 2000.0, accel_sigma=0.02, gyro_sigma=0.002),
    "icm42688p": ImuModel("TDK ICM-42688-P", 70.0 * _UG, 0.0028 * _DPS, 16.0, 2000.0),
    "bmi088": ImuModel("Bosch BMI088", 175.0 * _UG, 0.014 * _DPS, 24.0, 2000.0),
    "adis16448": ImuModel(
        "ADIS16448 (PX4 Gazebo-classic)", 2.0 * 2.0e-3, 2.0 * 35.0 / 3600.0 * _DPS, 18.0, 1000.0
    ),
}


@dataclass(frozen=True)
class BaroModel:
    """A barometer's per-sample pressure noise (hPa, 1-sigma) in the datasheet's mode."""

    part: str
    noise_hpa: float


#: ``px4.baro_preset`` choices (1 hPa = 1 mbar = 100 Pa; 0.01 hPa is about 8 cm of height near sea level).
#:
#: * sitl: the simulator's own 0.01 hPa.
#: * ms5611: TE Connectivity (MEAS) MS5611-01BA03, resolution RMS at oversampling 4096: 0.012 mbar (its
#:   datasheet's table: 0.065 / 0.042 / 0.027 / 0.018 / 0.012 mbar at OSR 256 .. 4096; 9.04 ms conversion).
#: * dps310: Infineon DPS310, pressure precision 0.005 hPa in high-precision mode (64x oversampling),
#:   taken as the 1-sigma (approx.: the datasheet's headline figure, not an RMS measured here).
BARO_PRESETS: dict[str, BaroModel] = {
    "sitl": BaroModel("simulator default", 0.01),
    "ms5611": BaroModel("TE MS5611", 0.012),
    "dps310": BaroModel("Infineon DPS310", 0.005),
}


@dataclass(frozen=True)
class MagModel:
    """A magnetometer's per-sample noise (gauss, 1-sigma per axis) in the datasheet's mode."""

    part: str
    noise_gauss: float


#: ``px4.mag_preset`` choices (1 gauss = 1e-4 T = 100,000 nT; the Earth's field is about 0.5 G).
#:
#: * sitl: the simulator's own 0.002 G (the HMC5883L's figure).
#: * hmc5883l: Honeywell HMC5883L, noise floor 2 milli-gauss (datasheet: standard deviation of 100
#:   samples, gain 0, no averaging).
#: * rm3100: PNI RM3100, 15 nT RMS at cycle count 200 (PNI's RM3100 documentation) = 1.5e-4 G.
MAG_PRESETS: dict[str, MagModel] = {
    "sitl": MagModel("simulator default", 0.002),
    "hmc5883l": MagModel("Honeywell HMC5883L", 0.002),
    "rm3100": MagModel("PNI RM3100", 15e-9 / 1e-4),
}


@dataclass(frozen=True)
class GpsError:
    """The GPS position error model: Gauss-Markov 1-sigma (horizontal per axis, vertical; m), its
    correlation time (s), white per-fix jitter (m) and the MAVLink ``GPS_FIX_TYPE`` reported (3: 3D
    fix, 6: RTK fixed)."""

    horizontal_m: float
    vertical_m: float
    correlation_time_s: float
    jitter_m: float
    fix_type: int = 3


#: MAVLink GPS_FIX_TYPE values the presets report
FIX_3D, FIX_RTK_FIXED = 3, 6

#: ``px4.gps_preset`` choices.
#:
#: * sitl: PX4's own Gazebo simulation (GZBridge::addGpsNoise: an AR(1) error of about 2 cm horizontal and
#:   3 cm vertical, correlated over about half a second), what a PX4 user expects from SITL.
#: * realistic (also ``m8n``): a single-frequency receiver, u-blox NEO-M8N class, wandering 0.3 m / 0.5 m
#:   over a minute (approx.; with it a real PX4's GPS-referenced take-off to 5 m ends 4.6-5.7 m up). The
#:   M8N datasheet's 2.5 m CEP also holds the hours-long ionospheric and orbit errors, not modelled.
#: * f9p_rtk: u-blox ZED-F9P with an RTK fixed solution, 0.01 m + 1 ppm CEP horizontally (datasheet; a CEP
#:   is 1.1774 sigma of a circular Gaussian: 0.0085 m per axis) and 0.01 m + 1 ppm R50 vertically
#:   (0.6745 sigma: 0.0148 m), for a base within a few km; correlation time 10 s and 2 mm jitter approx.
GPS_PRESETS: dict[str, GpsError] = {
    "sitl": GpsError(horizontal_m=0.02, vertical_m=0.03, correlation_time_s=0.5, jitter_m=0.0),
    "realistic": GpsError(horizontal_m=0.3, vertical_m=0.5, correlation_time_s=60.0, jitter_m=0.02),
    "m8n": GpsError(horizontal_m=0.3, vertical_m=0.5, correlation_time_s=60.0, jitter_m=0.02),
    "f9p_rtk": GpsError(
        horizontal_m=0.0085,
        vertical_m=0.0148,
        correlation_time_s=10.0,
        jitter_m=0.002,
        fix_type=FIX_RTK_FIXED,
    ),
}


def check_preset(section: str, name: str, value: object, table: dict[str, object]) -> None:
    """A one-line ValueError naming the choices when ``value`` is not a preset of ``table``."""
    if not isinstance(value, str) or value not in table:
        raise ValueError(f"{section}.{name} must be one of {', '.join(table)}, got {value!r}")
