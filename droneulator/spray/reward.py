"""A reward for learning to spray: what a step of spraying put on the canopy, against what it wasted.

:class:`SprayReward` reads the cloud's ledger (:class:`~droneulator.spray.cloud.Ledger`) at each call and
scores its change since the last: litres on the canopy count ``canopy``, litres that drifted (left the
domain or landed off the deposit grid, and any ground outside the given target area) cost ``drift``,
litres on the ground inside the target cost ``ground`` (lost to the soil), evaporated litres cost
``evaporated``. Liquid still airborne is scored when it lands, so the sum over an episode (once the cloud
has settled) is the episode's balance sheet.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from droneulator.spray.cloud import SprayCloud


@dataclass
class SprayReward:
    """Weights per litre (see the module docstring); ``target``: the area (x0, x1, y0, y1, m) where the
    ground deposit is not drift (None: all the deposit grid's ground is in the field)."""

    canopy: float = 1.0
    drift: float = 5.0
    ground: float = 0.2
    evaporated: float = 0.0
    target: tuple[float, float, float, float] | None = None
    _last: np.ndarray = field(default_factory=lambda: np.zeros(5), repr=False)

    def totals(self, cloud: SprayCloud) -> np.ndarray:
        """Litres now on the canopy (and wood), drifted, on the target's ground, evaporated, sprayed."""
        parts = cloud.ledger_now().parts
        ground = cloud.ground_deposit()
        off = 0.0
        if self.target is not None:
            c = cloud.ground_cell
            xs = cloud.ground_origin[0] + (np.arange(ground.shape[0]) + 0.5) * c
            ys = cloud.ground_origin[1] + (np.arange(ground.shape[1]) + 0.5) * c
            x0, x1, y0, y1 = self.target
            inside = ((xs >= x0) & (xs <= x1))[:, None] & ((ys >= y0) & (ys <= y1))[None, :]
            off = float(ground[~inside].sum())
        plants = parts["canopy"] + parts["trunks"] + parts["branches"] + parts["posts"] + parts["wires"]
        drifted = parts["left"] + parts["ground_off_grid"] + off
        return 1000.0 * np.array([plants, drifted, parts["ground"] - off, parts["evaporated"], cloud.sprayed])

    def reset(self, cloud: SprayCloud) -> None:
        """Start counting from the cloud as it is (a new episode)."""
        self._last = self.totals(cloud)

    def __call__(self, cloud: SprayCloud) -> float:
        """The reward of what changed since the last call (or :meth:`reset`)."""
        now = self.totals(cloud)
        d = now - self._last
        self._last = now
        return float(self.canopy * d[0] - self.drift * d[1] - self.ground * d[2] - self.evaporated * d[3])
