"""Magnetometer: the World Magnetic Model's Earth field at home, seen from PX4's FRD body frame.

PX4 checks the measured field against its own World Magnetic Model tables at the GPS position
(declination for the heading, inclination and strength in its arming checks), so the default
field is NOAA's WMM2025 (the ``wmm-calculator`` package, coefficients shipped with it, no network)
at the site (``site.latitude_deg`` / ``longitude_deg`` / ``altitude_m``) on the decimal year
``px4.mag_wmm_year``.
``px4.mag_field_ned_gauss`` replaces it with an explicit field. The field is computed once: over
a flight of a few kilometres the WMM changes by hundredths of a degree.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from droneulator.config.site import SiteConfig
from droneulator.frames import ned_to_enu
from droneulator.frames_numba import flu_to_frd, world_to_body
from droneulator.sensors.registry import register
from droneulator.sensors.truth import Truth

#: gauss per nanotesla, tesla per gauss
GAUSS_PER_NT = 1e-5
TESLA_PER_GAUSS = 1e-4


@dataclass(frozen=True)
class FieldElements:
    """What PX4 compares: declination (deg, east of true north), inclination (deg, down positive)
    and total strength (gauss)."""

    declination_deg: float
    inclination_deg: float
    strength_gauss: float


def wmm_field_ned_gauss(lat_deg: float, lon_deg: float, alt_m: float, year: float) -> np.ndarray:
    """The WMM2025 main field (gauss, north/east/down) at a WGS84 position and decimal year.

    ``alt_m`` is the height above the WGS84 ellipsoid (the ~50 m geoid separation changes the field
    by well under a nanotesla). A year outside the model's validity is a :class:`ValueError`.
    """
    return np.array(_wmm_field(float(lat_deg), float(lon_deg), float(alt_m), float(year)))


@functools.lru_cache(maxsize=64)
def _wmm_field(lat_deg: float, lon_deg: float, alt_m: float, year: float) -> tuple[float, float, float]:
    """:func:`wmm_field_ned_gauss`, computed once per place and year (every vehicle of a fleet asks for
    the field at the same home: 9 ms each)."""
    from wmm import wmm_calc  # imported here: only a run without an explicit field needs it

    model = wmm_calc()
    try:
        model.setup_time(dyear=float(year))
    except ValueError as exc:
        raise ValueError(f"px4.mag_wmm_year={year}: {exc}") from None
    model.setup_env(lat_deg, lon_deg, alt_m, unit="m")
    out = model.get_all()
    x, y, z = (float(out[k][0]) * GAUSS_PER_NT for k in ("x", "y", "z"))
    return x, y, z


def field_elements(field_ned: Any) -> FieldElements:
    """Declination, inclination and strength of a NED field vector given in gauss."""
    n, e, d = (float(v) for v in np.asarray(field_ned, dtype=float))
    horizontal = math.hypot(n, e)
    return FieldElements(
        math.degrees(math.atan2(e, n)), math.degrees(math.atan2(d, horizontal)), math.hypot(horizontal, d)
    )


def earth_field_ned(cfg: Any, site: SiteConfig | None = None) -> np.ndarray:
    """The Earth field the magnetometer measures (gauss, NED): ``cfg.mag_field_ned_gauss`` when
    set, else the WMM at ``site`` (default: the default site) on ``cfg.mag_wmm_year``."""
    if cfg.mag_field_ned_gauss is not None:
        return np.array(cfg.mag_field_ned_gauss, dtype=float)
    return wmm_field_ned_gauss(*(site or SiteConfig()).geodetic, cfg.mag_wmm_year)


@register("mag")
class Magnetometer:
    """Field in gauss at ``site`` (the world origin's place); ``cfg`` gives ``mag_wmm_year`` or
    ``mag_field_ned_gauss``, ``mag_bias`` and the noise
    (:meth:`~droneulator.config.PX4Config.mag_error`: ``mag_preset``, or ``mag_noise`` set)."""

    def __init__(self, cfg: Any, rng: np.random.Generator, site: SiteConfig | None = None) -> None:
        self.cfg = cfg
        self.rng = rng
        #: per-sample noise of each axis (gauss, 1-sigma)
        self.sigma_gauss = cfg.mag_error()
        #: the Earth field (gauss, NED), and in the simulator's ENU world
        self.field_ned = earth_field_ned(cfg, site)
        self._field_enu = np.ascontiguousarray(ned_to_enu(self.field_ned))

    @property
    def elements(self) -> FieldElements:
        """Declination, inclination and strength of :attr:`field_ned`."""
        return field_elements(self.field_ned)

    def sample(self, truth: Truth) -> np.ndarray:
        """Magnetic field in the FRD body frame (gauss): the NED field rotated into the body (as the ENU
        field into the FLU body, then FLU -> FRD: the same rotation, without SciPy's 0.2 ms per call)."""
        q = np.ascontiguousarray(truth.quaternion, dtype=np.float64)
        field = flu_to_frd(world_to_body(q, self._field_enu))
        return field + np.asarray(self.cfg.mag_bias) + self.rng.normal(0.0, self.sigma_gauss, 3)
