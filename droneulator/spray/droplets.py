"""A droplet in air: its drag, terminal velocity and evaporation.

* Drag: the standard drag curve of a rigid sphere as Clift, Grace & Weber (1978, Bubbles, Drops and
  Particles, Table 5.2) fit it, piecewise in ``Re = rho_air |v - u| d / mu`` (``w = log10 Re``):
  ``Cd = 24 / Re (1 + 0.1315 Re^(0.82 - 0.05 w))`` up to Re 20, ``24 / Re (1 + 0.1935 Re^0.6305)`` up to
  260, ``log10 Cd = 1.6435 - 1.1242 w + 0.1558 w^2`` up to 1500, a cubic in ``w`` up to 1.2e4 and
  Newton's 0.44 beyond (with Stokes' ``24 / Re`` below Re 0.01). Written as a relaxation time,
  ``dv/dt = (u - v) / tau + g (1 - rho_air / rho_liquid)`` with ``tau = rho_liquid d^2 / (18 mu f)``
  and ``f = Cd Re / 24``; :func:`terminal_velocity` solves ``v = g' tau(v)``.
* Evaporation: the d^2 law of Williamson & Threadgill (1974) with Goering's ventilation factor,
  ``d(d^2)/dt = -lambda``, ``lambda = 84.76 dT (1 + 0.27 Re^0.5)`` um^2/s, where ``dT`` is the wet-bulb
  depression (C). The wet-bulb temperature comes from Stull (2011)'s fit (RH 5-99 %, -20 to 50 C).
* Air: density from the ideal gas law, viscosity from Sutherland's law.

Checked against Gunn & Kinzer (1949)'s terminal velocities and the d^2 law's lifetimes in the tests
and in ``benchmarks/spray.py`` (docs/spray.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba

from droneulator.config.spray import WeatherConfig

#: gravity (m/s^2), as the vehicles' model
GRAVITY = 9.81
#: the d^2 law's evaporation constant at rest (um^2 per s per C of wet-bulb depression) and its
#: ventilation coefficient (per Re^0.5)
EVAPORATION_UM2_S_C = 84.76
VENTILATION = 0.27


@numba.njit(cache=True)
def drag_factor(re: float) -> float:
    """``f = Cd Re / 24`` of the standard drag curve (the module docstring): 1 in Stokes flow."""
    if re <= 0.01:
        return 1.0 + 3.0 / 16.0 * re
    w = math.log10(re)
    if re <= 20.0:
        return 1.0 + 0.1315 * re ** (0.82 - 0.05 * w)
    if re <= 260.0:
        return 1.0 + 0.1935 * re**0.6305
    if re <= 1500.0:
        cd = 10.0 ** (1.6435 - 1.1242 * w + 0.1558 * w * w)
    elif re <= 1.2e4:
        cd = 10.0 ** (-2.4571 + 2.5558 * w - 0.9295 * w * w + 0.1049 * w * w * w)
    else:
        cd = 0.44
    return cd * re / 24.0


@numba.njit(cache=True)
def relaxation_time(d: float, speed: float, rho_air: float, mu: float, rho_liquid: float) -> float:
    """The droplet's velocity relaxation time (s) at diameter ``d`` (m) and slip speed ``speed`` (m/s)."""
    re = rho_air * speed * d / mu
    return rho_liquid * d * d / (18.0 * mu * drag_factor(re))


@dataclass(frozen=True)
class Air:
    """The air's properties the droplets need, from the ``weather`` section."""

    density: float
    viscosity: float
    wet_bulb_depression: float
    temperature_c: float

    @classmethod
    def of(cls, weather: WeatherConfig) -> Air:
        t_k = weather.temperature_c + 273.15
        density = weather.pressure_hpa * 100.0 / (287.058 * t_k)
        viscosity = 1.716e-5 * (t_k / 273.15) ** 1.5 * (273.15 + 110.4) / (t_k + 110.4)
        depression = weather.temperature_c - wet_bulb_c(weather.temperature_c, weather.relative_humidity)
        return cls(density, viscosity, max(depression, 0.0), weather.temperature_c)

    def evaporation_rate(self, re: float = 0.0) -> float:
        """``lambda`` (m^2/s): how fast the square of a droplet's diameter shrinks at Reynolds number
        ``re``."""
        return EVAPORATION_UM2_S_C * 1e-12 * self.wet_bulb_depression * (1.0 + VENTILATION * math.sqrt(re))


def wet_bulb_c(temperature_c: float, relative_humidity: float) -> float:
    """Wet-bulb temperature (C) from the air's temperature (C) and relative humidity (0-1): Stull
    (2011), J. Appl. Meteor. Climatol. 50, 2267-2269, within 0.3 C for RH 5-99 % at sea level."""
    t, rh = temperature_c, 100.0 * relative_humidity
    return (
        t * math.atan(0.151977 * math.sqrt(rh + 8.313659))
        + math.atan(t + rh)
        - math.atan(rh - 1.676331)
        + 0.00391838 * rh**1.5 * math.atan(0.023101 * rh)
        - 4.686035
    )


def terminal_velocity(d: float, air: Air, rho_liquid: float = 998.2) -> float:
    """Terminal fall speed (m/s) of a droplet of diameter ``d`` (m) in still air: the fixed point of
    ``v = g' tau(v)`` (bisection; the drag grows monotonically with speed)."""
    g = GRAVITY * (1.0 - air.density / rho_liquid)
    lo, hi = 0.0, 20.0
    for _ in range(80):
        v = 0.5 * (lo + hi)
        if g * relaxation_time(d, v, air.density, air.viscosity, rho_liquid) > v:
            lo = v
        else:
            hi = v
    return 0.5 * (lo + hi)


def lifetime_s(d: float, air: Air) -> float:
    """How long (s) a droplet of diameter ``d`` (m) lives at rest relative to the air (the d^2 law
    without ventilation): ``d^2 / lambda``."""
    rate = air.evaporation_rate()
    return math.inf if rate <= 0.0 else d * d / rate
