"""Settings of the scene's light: sun from the time of day, cloud cover, haze (the ``light`` section).

Every field left null takes the scene's value (``Scene.light``), else the built-in default. With every
field null (the default) the renderer lights the scene exactly as it always did: a fixed sun from the
scene (``Scene.sun_direction``), a clear sky and no haze. See docs/light.md for the model.
"""

from __future__ import annotations

import dataclasses
import datetime
import math
from dataclasses import dataclass
from typing import Any

#: the day the sun is computed for when ``date`` is null: midsummer, the long days of the growing season
DEFAULT_DATE = "2026-06-21"


def _number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _iso_day(value: Any) -> bool:
    """Whether ``value`` is a ``YYYY-MM-DD`` string naming a real day."""
    if not isinstance(value, str) or len(value) != 10:
        return False
    try:
        datetime.date.fromisoformat(value)
    except ValueError:
        return False
    return True


@dataclass
class LightConfig:
    """Time of day and weather of the rendered scene (RGB only: depth and segmentation never change)."""

    #: local clock time, hours in [0, 24), e.g. 8.5 for 08:30; null: the scene's fixed sun
    #: (``Scene.sun_direction``), as before this section existed
    time_of_day_h: float | None = None
    #: the day (ISO ``YYYY-MM-DD``); null: DEFAULT_DATE
    date: str | None = None
    #: where the sun is computed for, WGS84 degrees, if not at the world's place; null (the rule): the
    #: site's (``site.latitude_deg``, ``site.longitude_deg``), where the GPS puts the world origin too.
    #: Set, they move the sun alone (e.g. per episode through the API's ``reset``), not the GPS
    latitude_deg: float | None = None
    longitude_deg: float | None = None
    #: the clock's offset from UTC, hours (e.g. 1.0 for CET, 2.0 for CEST); null: the site's clock
    #: (``site.utc_offset_h``, whose own null is local mean solar time, longitude / 15)
    utc_offset_h: float | None = None
    #: fraction of the sky covered by cloud, [0, 1]: direct sun scaled by 1 - cover, diffuse light and
    #: a grey sky in its place (1: overcast, no hard shadows); null: 0
    cloud_cover: float | None = None
    #: meteorological visibility, metres (Koschmieder: contrast falls to 2 % at this distance); null: no
    #: haze
    visibility_m: float | None = None

    def __post_init__(self) -> None:
        for name in ("time_of_day_h", "latitude_deg", "longitude_deg", "utc_offset_h", "cloud_cover"):
            value = getattr(self, name)
            if value is not None and not _number(value):
                raise ValueError(f"light.{name} must be a finite number or null, got {value!r}")
        if self.time_of_day_h is not None and not 0.0 <= self.time_of_day_h < 24.0:
            raise ValueError(f"light.time_of_day_h must lie in [0, 24) hours, got {self.time_of_day_h}")
        if self.date is not None and not _iso_day(self.date):
            raise ValueError(f"light.date must be an ISO day like 2026-06-21, got {self.date!r}")
        if self.latitude_deg is not None and not -90.0 <= self.latitude_deg <= 90.0:
            raise ValueError(f"light.latitude_deg must lie in [-90, 90], got {self.latitude_deg}")
        if self.longitude_deg is not None and not -180.0 <= self.longitude_deg <= 180.0:
            raise ValueError(f"light.longitude_deg must lie in [-180, 180], got {self.longitude_deg}")
        if self.utc_offset_h is not None and not -14.0 <= self.utc_offset_h <= 14.0:
            raise ValueError(f"light.utc_offset_h must lie in [-14, 14] hours, got {self.utc_offset_h}")
        if self.cloud_cover is not None and not 0.0 <= self.cloud_cover <= 1.0:
            raise ValueError(f"light.cloud_cover must lie in [0, 1], got {self.cloud_cover}")
        vis = self.visibility_m
        if vis is not None and not (_number(vis) and vis > 0.0):
            raise ValueError(f"light.visibility_m must be a positive number of metres or null, got {vis!r}")

    def over(self, defaults: dict[str, Any]) -> LightConfig:
        """This light with its null fields taken from ``defaults`` (a scene's ``light``: field -> value)."""
        unknown = sorted(set(defaults) - {f.name for f in dataclasses.fields(self)})
        if unknown:
            raise ValueError(f"unknown light field(s) {', '.join(unknown)}")
        merged = {k: v for k, v in defaults.items() if getattr(self, k) is None}
        return dataclasses.replace(self, **merged) if merged else self
