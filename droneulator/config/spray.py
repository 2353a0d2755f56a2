"""The spray system's sections: ``spray`` (tank, pump, nozzles, droplet spectrum, parcel solver) and
``weather`` (air temperature, humidity, pressure: the droplets' drag and evaporation).

Built by :mod:`droneulator.spray`; the numbers and their sources are in docs/spray.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

#: nozzle types: a hydraulic flat-fan nozzle (a liquid sheet leaving downwards in a fan across the
#: flight line) or a rotary (centrifugal) atomiser (droplets flung horizontally off a spinning disc)
NOZZLE_TYPES = ("flat_fan", "rotary")

#: ASABE S572.3 droplet size classes: (Dv0.1, Dv0.5, Dv0.9) in micrometres of a spray in the middle of
#: the class, with the class's Dv0.5 range as nozzle makers tabulate it (docs/spray.md)
SPECTRUM_CLASSES: dict[str, tuple[float, float, float]] = {
    "XF": (25.0, 50.0, 90.0),
    "VF": (40.0, 85.0, 160.0),
    "F": (75.0, 170.0, 300.0),
    "M": (120.0, 290.0, 500.0),
    "C": (160.0, 370.0, 640.0),
    "VC": (200.0, 450.0, 780.0),
    "XC": (240.0, 580.0, 990.0),
    "UC": (300.0, 720.0, 1200.0),
}


def _positive(section: str, name: str, value: object) -> None:
    if not (isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)) or (
        value <= 0
    ):
        raise ValueError(f"{section}.{name} must be a positive number, got {value!r}")


@dataclass
class NozzleConfig:
    """One nozzle of a vehicle's boom: where it sits (body frame FLU, m, from the vehicle's origin), its
    type, its share of the pump's flow, and its droplet spectrum (an ASABE class, or Dv0.1/Dv0.5/Dv0.9
    given in micrometres, which take precedence)."""

    name: str = "n0"
    position: tuple[float, float, float] = (0.0, 0.0, -0.3)
    type: str = "flat_fan"
    #: flow at the full pump rate, L/min
    flow_l_min: float = 0.75
    spectrum: str = "F"
    dv10_um: float | None = None
    dv50_um: float | None = None
    dv90_um: float | None = None
    #: how fast the liquid leaves: the sheet's speed (flat fan; about sqrt(2 dP / rho) at the nozzle's
    #: pressure) or the disc's rim speed (rotary), m/s
    exit_speed_m_s: float = 15.0
    #: a flat fan's spray angle (degrees, the full fan, across the flight line)
    fan_angle_deg: float = 110.0

    def __post_init__(self) -> None:
        if self.type not in NOZZLE_TYPES:
            raise ValueError(f"nozzle {self.name!r}: type must be one of {', '.join(NOZZLE_TYPES)}")
        given = [self.dv10_um, self.dv50_um, self.dv90_um]
        if any(v is not None for v in given):
            if any(v is None for v in given):
                raise ValueError(f"nozzle {self.name!r}: give all of dv10_um, dv50_um, dv90_um or none")
            for name, v in zip(("dv10_um", "dv50_um", "dv90_um"), given, strict=True):
                _positive(f"nozzle {self.name!r}", name, v)
            if not given[0] < given[1] < given[2]:  # type: ignore[operator]
                raise ValueError(f"nozzle {self.name!r}: need dv10_um < dv50_um < dv90_um, got {given}")
        elif self.spectrum not in SPECTRUM_CLASSES:
            classes = ", ".join(SPECTRUM_CLASSES)
            raise ValueError(f"nozzle {self.name!r}: spectrum must be an ASABE class ({classes})")
        _positive(f"nozzle {self.name!r}", "flow_l_min", self.flow_l_min)
        _positive(f"nozzle {self.name!r}", "exit_speed_m_s", self.exit_speed_m_s)
        if not (0.0 < self.fan_angle_deg < 180.0):
            raise ValueError(f"nozzle {self.name!r}: fan_angle_deg must lie in (0, 180)")
        if len(self.position) != 3 or not all(math.isfinite(v) for v in self.position):
            raise ValueError(f"nozzle {self.name!r}: position must be three finite numbers (body FLU, m)")

    @property
    def diameters_um(self) -> tuple[float, float, float]:
        """(Dv0.1, Dv0.5, Dv0.9) in micrometres."""
        if self.dv50_um is not None:
            return (float(self.dv10_um), float(self.dv50_um), float(self.dv90_um))  # type: ignore[arg-type]
        return SPECTRUM_CLASSES[self.spectrum]


def _two_nozzles() -> list[NozzleConfig]:
    return [
        NozzleConfig(name="left", position=(0.0, 0.35, -0.25)),
        NozzleConfig(name="right", position=(0.0, -0.35, -0.25)),
    ]


@dataclass
class SprayConfig:
    """A vehicle's spray system and the droplet solver (docs/spray.md)."""

    #: give every vehicle of a run this spray system (the ``spray`` op switches it; its state rides on
    #: the vehicle's state); ``droneulator spray`` turns it on itself
    enabled: bool = False
    #: tank volume (L) and how full it starts (L)
    tank_l: float = 10.0
    load_l: float = 10.0
    #: the liquid's density (kg/m^3): the tank's mass and the droplets' inertia
    liquid_density: float = 1000.0
    nozzles: list[NozzleConfig] = field(default_factory=_two_nozzles)
    #: Lagrangian parcels released per second by each nozzle (each carries an equal share of its flow): a
    #: live run's deposit map needs few; ``droneulator spray`` takes 3000 unless this is set
    parcels_per_s: float = 250.0
    #: the droplet solver's step (s): drag is integrated exactly for the step's frozen relaxation time,
    #: so any step is stable; accuracy wants it below the wake's time scales
    dt_s: float = 0.01
    #: a factor on every nozzle's droplet sizes (a finer or coarser spray; ``randomize.droplet_scale``)
    droplet_scale: float = 1.0
    #: the share of the liquid that does not evaporate (active ingredient, adjuvants, a tracer): a droplet
    #: dries to a residue of this share of its volume and flies on (0: water, it evaporates away)
    nonvolatile_fraction: float = 0.0
    #: droplets smaller than this (um) have evaporated (their liquid counts as evaporated)
    min_diameter_um: float = 5.0
    #: the deposit grid's cell (m) and how far parcels are followed: the sprayed area plus this margin
    #: on every side (m; what leaves it has drifted, airborne) and up to this height (m)
    grid_cell_m: float = 0.25
    margin_m: float = 55.0
    ceiling_m: float = 40.0
    #: capture in the canopy: the leaves' mean projection (G; 0.5 for a spherical leaf angle
    #: distribution) and the characteristic size (m) of a leaf and of woody parts for impaction
    leaf_projection: float = 0.5
    leaf_size_m: float = 0.05
    wood_size_m: float = 0.05

    def __post_init__(self) -> None:
        for name in ("tank_l", "liquid_density", "parcels_per_s", "dt_s", "min_diameter_um", "grid_cell_m",
                     "droplet_scale"):  # fmt: skip
            _positive("spray", name, getattr(self, name))
        for name in ("margin_m", "ceiling_m", "leaf_projection", "leaf_size_m", "wood_size_m"):
            _positive("spray", name, getattr(self, name))
        frac = self.nonvolatile_fraction
        if not (isinstance(frac, int | float) and not isinstance(frac, bool) and 0.0 <= frac < 1.0):
            raise ValueError(f"spray.nonvolatile_fraction must lie in [0, 1), got {frac!r}")
        if not (isinstance(self.load_l, int | float) and 0.0 <= self.load_l <= self.tank_l):
            raise ValueError(f"spray.load_l must lie in [0, tank_l={self.tank_l}], got {self.load_l!r}")
        if not self.nozzles:
            raise ValueError("spray.nozzles: a spray system needs at least one nozzle")
        names = [n.name for n in self.nozzles]
        if len(set(names)) != len(names):
            raise ValueError(f"spray.nozzles: names must be unique, got {names}")
        if self.dt_s > 0.05:
            raise ValueError(f"spray.dt_s must be at most 0.05 s (the wake's time scale), got {self.dt_s}")

    @property
    def flow_l_min(self) -> float:
        """The pump's full flow (L/min): every nozzle's together."""
        return float(sum(n.flow_l_min for n in self.nozzles))


@dataclass
class WeatherConfig:
    """The air the droplets fly through: its temperature (C), relative humidity (0-1) and pressure
    (hPa) set the air's density and viscosity (drag) and the wet-bulb depression (evaporation)."""

    temperature_c: float = 20.0
    relative_humidity: float = 0.6
    pressure_hpa: float = 1013.25

    def __post_init__(self) -> None:
        if not (isinstance(self.temperature_c, int | float) and -20.0 <= self.temperature_c <= 50.0):
            raise ValueError(f"weather.temperature_c must lie in [-20, 50] C, got {self.temperature_c!r}")
        if not (isinstance(self.relative_humidity, int | float) and 0.05 <= self.relative_humidity <= 1.0):
            raise ValueError(
                f"weather.relative_humidity is a fraction in [0.05, 1], got {self.relative_humidity!r}"
            )
        if not (isinstance(self.pressure_hpa, int | float) and 500.0 <= self.pressure_hpa <= 1100.0):
            raise ValueError(f"weather.pressure_hpa must lie in [500, 1100], got {self.pressure_hpa!r}")
