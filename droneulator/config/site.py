"""Where on Earth the world lies (the ``site`` section): the geodetic point of its origin and its clock.

One place for what the GPS fix, the barometer's altitude, the World Magnetic Model, PX4's ground truth
and the sun all read, so that they agree. The defaults are those the ``px4`` section held before this
section existed (``px4.home_lat_deg``, ``home_lon_deg``, ``home_alt_m``), so a config that sets none of
them gives the same fixes and the same sun as before; those old keys still load, with a warning
(:data:`RENAMED`, applied by :mod:`~droneulator.config.loading`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any


def _number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


@dataclass
class SiteConfig:
    """The world origin's WGS84 position and the local clock's offset from UTC."""

    #: latitude of the world origin, degrees north in [-90, 90]
    latitude_deg: float = 53.2281
    #: longitude of the world origin, degrees east in [-180, 180]
    longitude_deg: float = -0.5470
    #: altitude of the world origin (z = 0) above mean sea level, metres: the barometer's and the GPS fix's
    #: altitude is this plus the world z
    altitude_m: float = 10.0
    #: the local clock's offset from UTC, hours in [-14, 14] (e.g. 1.0 for CET, 2.0 for CEST), which
    #: ``light.time_of_day_h`` is read in; null: local mean solar time, longitude / 15, so that 12:00 is
    #: within a quarter of an hour of solar noon
    utc_offset_h: float | None = None

    def __post_init__(self) -> None:
        for name in ("latitude_deg", "longitude_deg", "altitude_m"):
            if not _number(getattr(self, name)):
                raise ValueError(f"site.{name} must be a finite number, got {getattr(self, name)!r}")
        if self.utc_offset_h is not None and not _number(self.utc_offset_h):
            raise ValueError(f"site.utc_offset_h must be a finite number or null, got {self.utc_offset_h!r}")
        if not -90.0 <= self.latitude_deg <= 90.0:
            raise ValueError(f"site.latitude_deg must lie in [-90, 90] degrees, got {self.latitude_deg}")
        if not -180.0 <= self.longitude_deg <= 180.0:
            raise ValueError(f"site.longitude_deg must lie in [-180, 180] degrees, got {self.longitude_deg}")
        if self.utc_offset_h is not None and not -14.0 <= self.utc_offset_h <= 14.0:
            raise ValueError(f"site.utc_offset_h must lie in [-14, 14] hours, got {self.utc_offset_h}")

    @property
    def geodetic(self) -> tuple[float, float, float]:
        """(latitude deg, longitude deg, altitude m AMSL) of the world origin, as ``frames`` takes it."""
        return (float(self.latitude_deg), float(self.longitude_deg), float(self.altitude_m))

    @property
    def clock_offset_h(self) -> float:
        """The clock's offset from UTC in effect: ``utc_offset_h``, else longitude / 15."""
        return self.longitude_deg / 15.0 if self.utc_offset_h is None else float(self.utc_offset_h)


#: old dotted key -> the ``site`` key it now is; an old key still loads, with a DeprecationWarning
RENAMED: dict[str, str] = {
    "px4.home_lat_deg": "site.latitude_deg",
    "px4.home_lon_deg": "site.longitude_deg",
    "px4.home_alt_m": "site.altitude_m",
}
