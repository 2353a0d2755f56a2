"""GPS: a 3D fix in WGS84 from the home position plus the noisy ENU offset, and NED velocity."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from droneulator.frames import enu_to_geodetic, enu_to_ned
from droneulator.sensors.registry import register
from droneulator.sensors.truth import Truth


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


@register("gps")
class Gps:
    """``cfg`` gives the home position, ``gps_noise_m``, ``gps_vertical_noise_m``, ``gps_bias_m``,
    ``gps_vel_noise`` and ``gps_satellites``."""

    def __init__(self, cfg: Any, rng: np.random.Generator) -> None:
        self.cfg = cfg
        self.rng = rng

    def sample(self, truth: Truth) -> GpsSample:
        """A 3D fix: position from the home position plus the (noisy) ENU offset, NED velocity."""
        c, rng = self.cfg, self.rng
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
