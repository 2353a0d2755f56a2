"""Barometer on the International Standard Atmosphere (troposphere, valid to 11 km)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from droneulator.config.site import SiteConfig
from droneulator.sensors.registry import register
from droneulator.sensors.truth import Truth

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


def altitude_msl(site: SiteConfig, truth: Truth) -> float:
    """Altitude above mean sea level: the site's altitude ``site.altitude_m`` plus the world z."""
    return site.altitude_m + float(truth.position[2])


@dataclass(frozen=True)
class BaroSample:
    pressure_hpa: float
    pressure_alt_m: float
    temperature_c: float


@register("baro")
class Barometer:
    """Absolute pressure with ``cfg.baro_bias_hpa`` and the noise of
    :meth:`~droneulator.config.PX4Config.baro_error` (``baro_preset``, or ``baro_noise_hpa`` set)."""

    def __init__(self, cfg: Any, rng: np.random.Generator, site: SiteConfig | None = None) -> None:
        self.cfg = cfg
        self.site = site or SiteConfig()
        self.rng = rng
        #: per-sample pressure noise (hPa, 1-sigma)
        self.sigma_hpa = cfg.baro_error()

    def sample(self, truth: Truth) -> BaroSample:
        """Absolute pressure (ISA at the true altitude, plus bias and noise), the pressure altitude
        it implies, and the ISA temperature."""
        alt = altitude_msl(self.site, truth)
        p_hpa = isa_pressure_pa(alt) / 100.0 + self.cfg.baro_bias_hpa
        p_hpa += self.rng.normal(0.0, self.sigma_hpa)
        return BaroSample(p_hpa, isa_altitude_m(p_hpa * 100.0), isa_temperature_k(alt) - KELVIN)
