"""Sensor models side by side: cameras, IMU, magnetometer, barometer, GPS and airspeed.

Every model registers its class under a kind name (:mod:`.registry`, as MetaDrive's sensor
registry does), so a new sensor is one module here plus the publisher that sends its readings.
The noisy models sample :class:`~droneulator.sensors.truth.Truth` in PX4's conventions (NED
world, FRD body); :class:`~droneulator.sensors.suite.SensorSuite` holds the set PX4 SITL reads.
The renderer that draws the camera images stays in :mod:`droneulator.render`; what a real camera makes of
them (depth errors, sensor noise, exposure, motion blur, lens distortion) is :mod:`.camera_models`, built on
:mod:`.depth_models`, :mod:`.rgb_models` and :mod:`.lens` (docs/sensors.md).
"""

from droneulator.sensors import airspeed, baro, camera, gps, imu, mag
from droneulator.sensors.registry import SENSORS, get_sensor, register
from droneulator.sensors.suite import SensorSuite
from droneulator.sensors.truth import Truth

__all__ = [
    "SENSORS",
    "SensorSuite",
    "Truth",
    "airspeed",
    "baro",
    "camera",
    "get_sensor",
    "gps",
    "imu",
    "mag",
    "register",
]
