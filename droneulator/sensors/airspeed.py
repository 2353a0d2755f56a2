"""Airspeed: true airspeed from the velocity relative to the wind, indicated airspeed from ISA density."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from droneulator.config.site import SiteConfig
from droneulator.sensors.baro import ISA_RHO0, altitude_msl, isa_density
from droneulator.sensors.registry import register
from droneulator.sensors.truth import Truth


@register("airspeed")
class Airspeed:
    """Noise-free (indicated, true) airspeed in m/s; the air density is the ISA's at ``site``'s altitude
    plus the world z."""

    def __init__(
        self, cfg: Any, rng: np.random.Generator | None = None, site: SiteConfig | None = None
    ) -> None:
        self.cfg = cfg
        self.site = site or SiteConfig()

    def sample(self, truth: Truth) -> tuple[float, float]:
        """(indicated, true) airspeed in m/s from the velocity relative to the wind."""
        tas = float(np.linalg.norm(truth.velocity - truth.wind))
        return tas * math.sqrt(isa_density(altitude_msl(self.site, truth)) / ISA_RHO0), tas
