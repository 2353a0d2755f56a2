"""A vehicle's spray system: its tank, pump rate and nozzles, switched on and off by commands.

The tank empties at the pump's flow times the rate; the liquid it holds is the vehicle's payload (the
world's :meth:`~droneulator.world.world.World.set_payload`), so the dynamics, the controller, PX4 and
the rotor wake all feel the vehicle grow lighter. Refusals are :class:`CommandError`: an unknown nozzle
or a rate outside [0, 1] (``invalid_argument`` / ``out_of_range``), spraying from an empty tank
(``tank_empty``); the vehicle flies on.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from droneulator.commands.errors import CommandError
from droneulator.config.spray import SprayConfig


@dataclass
class SpraySystem:
    """The tank and pump of one vehicle (volumes in litres)."""

    config: SprayConfig
    level_l: float = field(init=False)
    rate: float = 0.0
    #: the nozzles open (names); all by default
    open: set[str] = field(default_factory=set)
    sprayed_l: float = 0.0

    def __post_init__(self) -> None:
        self.level_l = float(self.config.load_l)
        self.open = {n.name for n in self.config.nozzles}

    @property
    def on(self) -> bool:
        return self.rate > 0.0 and self.level_l > 0.0

    @property
    def liquid_kg(self) -> float:
        return self.level_l * self.config.liquid_density / 1000.0

    @property
    def flow_l_min(self) -> float:
        """The flow now (L/min): the open nozzles' at the rate, nothing once the tank is dry."""
        if not self.on:
            return 0.0
        return self.rate * sum(n.flow_l_min for n in self.config.nozzles if n.name in self.open)

    def set(self, rate: float, nozzles: list[str] | None = None) -> None:
        """Spray at ``rate`` (0 off .. 1 the pump's full flow) through ``nozzles`` (None: all)."""
        if isinstance(rate, bool) or not isinstance(rate, int | float) or not math.isfinite(rate):
            raise CommandError("invalid_argument", f"spray rate must be a number in [0, 1], got {rate!r}")
        if not 0.0 <= rate <= 1.0:
            raise CommandError(
                "out_of_range", f"spray rate must lie in [0, 1] (of the pump's flow), got {rate}"
            )
        names = {n.name for n in self.config.nozzles}
        if nozzles is not None:
            unknown = sorted(set(nozzles) - names)
            if unknown:
                raise CommandError(
                    "invalid_argument",
                    f"no nozzle {', '.join(unknown)}; the nozzles are {', '.join(sorted(names))}",
                )
        if rate > 0.0 and self.level_l <= 0.0:
            raise CommandError("tank_empty", "the spray tank is empty: refill it before spraying")
        self.rate = float(rate)
        self.open = set(names if nozzles is None else nozzles)

    def refill(self, litres: float | None = None) -> None:
        """Fill the tank to ``litres`` (None: its load)."""
        value = self.config.load_l if litres is None else litres
        if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
            raise CommandError("invalid_argument", f"refill needs a number of litres, got {value!r}")
        if not 0.0 <= value <= self.config.tank_l:
            raise CommandError("out_of_range", f"the tank holds 0 to {self.config.tank_l} L, got {value}")
        self.level_l = float(value)

    def draw(self, dt: float) -> dict[str, float]:
        """Run the pump for ``dt`` s: the volume (L) each open nozzle releases; the tank falls by their sum
        (the last drops shared out when it runs dry)."""
        flow = self.flow_l_min
        if flow <= 0.0:
            return {}
        total = min(flow / 60.0 * dt, self.level_l)
        share = total / flow
        out = {n.name: self.rate * n.flow_l_min * share for n in self.config.nozzles if n.name in self.open}
        self.level_l = max(self.level_l - total, 0.0)
        self.sprayed_l += total
        if self.level_l <= 0.0:  # run dry: the pump stops (a refill does not start it again)
            self.rate = 0.0
        return out

    def state(self) -> dict[str, object]:
        return {
            "on": self.on,
            "rate": self.rate,
            "level_l": self.level_l,
            "tank_l": self.config.tank_l,
            "flow_l_min": self.flow_l_min,
            "sprayed_l": self.sprayed_l,
            "nozzles": sorted(self.open),
        }
