"""A nozzle's droplet size spectrum, and parcels drawn from it.

A spray's volume is spread over droplet diameters as a log-normal distribution (by volume), fitted to
the spectrum's Dv0.1, Dv0.5 and Dv0.9 (the diameters below which 10, 50 and 90 % of the volume lies):
the median is Dv0.5 and the spread ``sigma = ln(Dv0.9 / Dv0.1) / (2 z_0.9)`` with ``z_0.9 = 1.2816``,
the standard normal's 90th percentile. Parcels carry equal volumes, so their diameters are drawn from
the volume distribution: ``d = Dv0.5 exp(sigma z)``, z standard normal.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from droneulator.config.spray import NozzleConfig

#: the standard normal's 90th percentile
Z90 = 1.2815515655446004


@dataclass(frozen=True)
class Spectrum:
    """A log-normal volume distribution of droplet diameters (m)."""

    median: float
    sigma: float

    @classmethod
    def fit(cls, dv10: float, dv50: float, dv90: float) -> Spectrum:
        """From Dv0.1, Dv0.5, Dv0.9 (m): the median, and the spread from the 10-90 % range (in log space,
        the geometric mean of the two sides, so a skewed spectrum keeps its range)."""
        if not 0.0 < dv10 < dv50 < dv90:
            raise ValueError(f"a spectrum needs 0 < Dv0.1 < Dv0.5 < Dv0.9, got {dv10}, {dv50}, {dv90}")
        return cls(dv50, math.log(dv90 / dv10) / (2.0 * Z90))

    @classmethod
    def of(cls, nozzle: NozzleConfig) -> Spectrum:
        dv10, dv50, dv90 = nozzle.diameters_um
        return cls.fit(dv10 * 1e-6, dv50 * 1e-6, dv90 * 1e-6)

    def dv(self, q: float) -> float:
        """The diameter (m) below which the share ``q`` of the volume lies."""
        from statistics import NormalDist

        return self.median * math.exp(self.sigma * NormalDist().inv_cdf(q))

    def volume_below(self, d: float) -> float:
        """The share of the volume in droplets smaller than ``d`` (m) (e.g. the driftable share below
        100 um, V100)."""
        return 0.5 * (1.0 + math.erf(math.log(d / self.median) / (self.sigma * math.sqrt(2.0))))

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """``n`` diameters (m) of equal-volume parcels."""
        return self.median * np.exp(self.sigma * rng.standard_normal(n))
