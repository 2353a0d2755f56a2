"""How far an autopilot strays from the planner's setpoints, turned into a wider obstacle margin.

The planner keeps ``inflation`` (vehicle radius + margin) from what it maps, assuming the vehicle flies
its trajectory. The simulator's own controller does, within centimetres; PX4's position controller
follows offboard setpoints more loosely (it lags and overshoots them by tenths of a metre in turns), so
the true clearance can fall that much short. :class:`TrackingMargin` collects the distance between the
reference and the autopilot's own position estimate while a trajectory is flown and widens the
obstacles by a high percentile of it, rounded up to the map's voxels and bounded, so plans keep the
clearance the margin promises for the vehicle as it really flies.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np


class TrackingMargin:
    """A running high percentile of the tracking error, as an extra obstacle margin (metres).

    ``quantile`` (0-100) of the last ``window`` samples, once ``min_samples`` are in, rounded up to a
    multiple of ``step`` (the map's resolution: a finer change does not move the inflated voxels) and at
    most ``limit`` (0: measured, never widened). The margin only grows within a flight: it stays at the
    worst the autopilot has shown, so the map is not rebuilt back and forth as the error wanders.
    """

    def __init__(
        self, limit: float, step: float, quantile: float = 95.0, window: int = 400, min_samples: int = 40
    ) -> None:
        if limit < 0 or step <= 0 or not 0 < quantile <= 100 or window < 1 or not 1 <= min_samples <= window:
            raise ValueError("need limit >= 0, step > 0, 0 < quantile <= 100 and 1 <= min_samples <= window")
        self.limit, self.step, self.quantile, self.min_samples = limit, step, quantile, min_samples
        self._errors: deque[float] = deque(maxlen=window)
        #: every sample taken, for the statistics (the window holds only the latest)
        self._all: list[float] = []
        #: the current extra margin (metres)
        self.margin = 0.0

    def add(self, error: float) -> bool:
        """Take one tracking error sample (metres); True when :attr:`margin` grew."""
        if not math.isfinite(error):
            return False
        self._errors.append(float(error))
        self._all.append(float(error))
        if len(self._errors) < self.min_samples or self.limit == 0:
            return False
        high = float(np.percentile(self._errors, self.quantile))
        want = min(self.limit, self.step * math.ceil(high / self.step - 1e-9))
        if want <= self.margin:
            return False
        self.margin = want
        return True

    @property
    def count(self) -> int:
        """Samples in the window."""
        return len(self._errors)

    @property
    def high(self) -> float:
        """The ``quantile`` of the window's errors (NaN before any)."""
        return float(np.percentile(self._errors, self.quantile)) if self._errors else math.nan

    def stats(self) -> dict[str, float | int]:
        """Every error sample's count, median, ``quantile`` and max (metres), and the margin."""
        e = np.asarray(self._all)
        pct = (lambda q: float(np.percentile(e, q))) if len(e) else (lambda q: math.nan)
        return {
            "samples": len(e),
            "median": pct(50),
            f"p{self.quantile:g}": pct(self.quantile),
            "max": float(e.max()) if len(e) else math.nan,
            "margin": self.margin,
        }
