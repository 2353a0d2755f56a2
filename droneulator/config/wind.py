"""The wind field's section (``wind``): mean wind with its height profile, Dryden turbulence, discrete
gusts and the shelter of the canopy. Built by :class:`droneulator.wind.field.WindField`; see docs/wind.md."""

from __future__ import annotations

import math
from dataclasses import dataclass

#: the mean wind's height profile: "log" (MIL-F-8785C's logarithmic wind shear over the ground's
#: roughness length) or "uniform" (the same wind at every height)
WIND_PROFILES = ("log", "uniform")
#: the turbulence model: "dryden" (MIL-F-8785C low-altitude Dryden spectra) or "none"
TURBULENCE_MODELS = ("dryden", "none")


@dataclass
class WindConfig:
    """Calm by default: every field is zero until ``speed_m_s`` or ``gust_speed_m_s`` is set.

    The turbulence intensity follows the mean wind as the standard defines it (sigma_w = 0.1 W20), so
    ``speed_m_s = 5`` is a gusty 5 m/s wind; ``turbulence_scale`` scales it, ``turbulence = "none"``
    leaves a steady wind."""

    #: mean wind speed 20 ft (6.1 m) above the ground (the standard's W20), m/s
    speed_m_s: float = 0.0
    #: where the wind blows from, degrees clockwise from north (meteorological): 270 blows from the west
    #: towards +x (east in the ENU world)
    direction_deg: float = 270.0
    profile: str = "log"
    #: the ground's roughness length z0 for the log profile (m; MIL-F-8785C: 0.15 ft for terminal flight)
    roughness_m: float = 0.046
    turbulence: str = "dryden"
    turbulence_scale: float = 1.0
    #: discrete "1 - cosine" gusts along the mean wind (MIL-F-8785C 3.7.4): peak speed (m/s), mean time
    #: between gusts (s; Poisson arrivals) and each gust's length in time (s)
    gust_speed_m_s: float = 0.0
    gust_interval_s: float = 10.0
    gust_duration_s: float = 2.0
    #: the canopy's shelter: the wind is attenuated by exp(-a * s) where s is the length of canopy
    #: (the scene's collision geometry) that the upwind ray from the vehicle crosses, each metre weighted
    #: by exp(-distance / recovery) so that the wind recovers behind a row
    shelter: bool = True
    canopy_attenuation_per_m: float = 0.5
    shelter_recovery_m: float = 6.0

    def __post_init__(self) -> None:
        if self.profile not in WIND_PROFILES:
            raise ValueError(f"wind.profile must be one of {', '.join(WIND_PROFILES)}, got {self.profile!r}")
        if self.turbulence not in TURBULENCE_MODELS:
            choices = ", ".join(TURBULENCE_MODELS)
            raise ValueError(f"wind.turbulence must be one of {choices}, got {self.turbulence!r}")
        for name in ("speed_m_s", "gust_speed_m_s", "turbulence_scale", "canopy_attenuation_per_m"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
                raise ValueError(f"wind.{name} must be a finite number >= 0, got {value!r}")
        for name in ("roughness_m", "gust_interval_s", "gust_duration_s", "shelter_recovery_m"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"wind.{name} must be a positive number, got {value!r}")
        if not (isinstance(self.direction_deg, int | float) and math.isfinite(self.direction_deg)):
            raise ValueError(f"wind.direction_deg must be a finite angle, got {self.direction_deg!r}")

    @property
    def calm(self) -> bool:
        """No mean wind and no gusts: the field is zero everywhere."""
        return self.speed_m_s == 0.0 and self.gust_speed_m_s == 0.0

    @property
    def heading(self) -> tuple[float, float]:
        """Unit vector (x east, y north) the wind blows towards."""
        a = math.radians(self.direction_deg)
        return -math.sin(a), -math.cos(a)
