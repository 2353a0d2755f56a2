"""A vehicle's battery: a LiPo pack's charge, its voltage under load and what it leaves the motors.

The model (docs/battery.md gives the numbers and their sources):

* open-circuit voltage ``OCV(SoC)``: the cell's curve (``BatteryConfig.curve``) times the cells in series;
* terminal voltage under load ``V = OCV(SoC) - I R`` (``R`` the pack's internal resistance);
* the load is the rotors' electrical power ``P``; the current is the constant-power solution of
  ``V I = P``: ``I = (OCV - sqrt(OCV^2 - 4 R P)) / (2 R)``, held at ``OCV / (2 R)`` (the most power the
  pack can give) when ``P`` asks for more;
* the charge falls by ``I dt``: ``SoC -= I dt / capacity``;
* a motor's no-load speed is ``Kv V``, so the top rotor speed is the airframe's ``rotor_speed_max`` times
  ``V / V_nominal`` below the nominal voltage (``cells x nominal_cell_v``), the airframe's own above it,
  followed through a short first-order lag (``speed_time_constant_s``);
* a spent pack (SoC 0) is cut off, as an ESC's low-voltage cutoff does: no voltage, the rotors stop.

The rotors' power is momentum theory's: a rotor of thrust ``T`` and disk area ``A`` climbing axially at
``v_c`` needs ``T (v_c / 2 + sqrt((v_c / 2)^2 + T / (2 rho A)))`` (hover: ``T^1.5 / sqrt(2 rho A)``), divided
by the rotor's figure of merit (profile losses) and the motor and ESC efficiency.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from droneulator.config import BatteryConfig


@dataclass(frozen=True)
class PackSpec:
    """An airframe's battery pack: cells in series, usable capacity (mAh), pack internal resistance (ohm)
    and motor and ESC efficiency, with where the numbers come from."""

    cells: int
    capacity_mah: float
    internal_resistance_ohm: float
    efficiency: float
    source: str


#: each airframe's pack (docs/battery.md): the one the real vehicle flies, or a typical one for its class
AIRFRAME_BATTERIES: dict[str, PackSpec] = {
    "hummingbird": PackSpec(3, 2100.0, 0.035, 0.75, "AscTec Hummingbird: 3S 2100 mAh LiPo"),
    "crazyflie": PackSpec(1, 250.0, 0.15, 0.5, "Bitcraze Crazyflie 2.x: 1S 250 mAh LiPo, brushed motors"),
    "crazyflie_brushless": PackSpec(1, 350.0, 0.12, 0.7, "Bitcraze Crazyflie 2.1 Brushless: 1S 350 mAh"),
    "px4_quadx": PackSpec(3, 3000.0, 0.03, 0.75, "a typical 1 kg quad (PX4 SIH's): 3S 3000 mAh LiPo"),
    "sprayer10": PackSpec(14, 9500.0, 0.05, 0.8, "DJI Agras T10 class: 14S 9500 mAh (51.8 V)"),
    "sprayer40": PackSpec(14, 30000.0, 0.02, 0.8, "DJI Agras T40 class: 14S 30000 mAh (52.22 V)"),
}


def pack_for(params: str, cfg: BatteryConfig) -> tuple[int, float, float, float]:
    """(cells, capacity mAh, internal resistance ohm, efficiency) of airframe ``params``'s battery: ``cfg``'s
    numbers, the unset ones from :data:`AIRFRAME_BATTERIES` (ValueError when neither has them)."""
    pack = AIRFRAME_BATTERIES.get(params)
    values = (cfg.cells, cfg.capacity_mah, cfg.internal_resistance_ohm, cfg.efficiency)
    if pack is None and any(v is None for v in values):
        raise ValueError(
            f"no default battery for airframe {params!r} (known: {', '.join(AIRFRAME_BATTERIES)}): set "
            "battery.cells, battery.capacity_mah, battery.internal_resistance_ohm and battery.efficiency, "
            "or battery.enabled = false"
        )
    defaults = (0, 0.0, 0.0, 0.0) if pack is None else (
        pack.cells, pack.capacity_mah, pack.internal_resistance_ohm, pack.efficiency)  # fmt: skip
    cells, mah, ohm, eff = (d if v is None else v for v, d in zip(values, defaults, strict=True))
    return int(cells), float(mah), float(ohm), float(eff)


def rotor_power(thrusts: Sequence[float], disk_area: float, climb: float, rho: float) -> float:
    """Ideal (momentum theory) power (W) of rotors of ``thrusts`` (N each) and ``disk_area`` (m^2 each)
    climbing axially at ``climb`` m/s (a descent counts as hover: momentum theory fails in the vortex ring
    state). Plain floats: a few rotors cost less this way than as numpy arrays, once a control period."""
    half = 0.5 * max(climb, 0.0)
    k = 1.0 / (2.0 * rho * disk_area)
    total = 0.0
    for t in thrusts:
        if t > 0.0:
            total += t * (half + math.sqrt(half * half + t * k))
    return total


class Battery:
    """One vehicle's battery pack (docs/battery.md), stepped once per control period by its world."""

    def __init__(self, cfg: BatteryConfig, params: str) -> None:
        self.config = cfg
        self.cells, self.capacity_mah, self.resistance, self.efficiency = pack_for(params, cfg)
        self._soc_points = [float(p[0]) for p in cfg.curve]
        self._cell_v = [float(p[1]) for p in cfg.curve]
        #: the pack voltage at which the airframe reaches its ``rotor_speed_max``
        self.nominal_v = self.cells * cfg.nominal_cell_v
        self.capacity_as = self.capacity_mah * 3.6  # ampere-seconds
        self._losses = cfg.figure_of_merit * self.efficiency
        self.reset()

    def reset(self) -> None:
        """A charged pack (``initial_soc``) at rest."""
        self.soc = float(self.config.initial_soc)
        self._ocv = self.ocv(self.soc)  # the OCV at ``soc``, kept with it
        self.current = 0.0
        self.power = 0.0
        self.voltage = self._ocv
        self.empty = False
        #: the share of ``rotor_speed_max`` the motors reach now (:meth:`follow`)
        self.top_speed = self.speed_scale

    def ocv(self, soc: float) -> float:
        """The pack's open-circuit voltage (V) at state of charge ``soc`` (clipped to [0, 1])."""
        s = min(max(soc, 0.0), 1.0)
        xs, vs = self._soc_points, self._cell_v
        j = min(max(bisect.bisect_right(xs, s), 1), len(xs) - 1)
        x0, x1 = xs[j - 1], xs[j]
        return self.cells * (vs[j - 1] + (vs[j] - vs[j - 1]) * (s - x0) / (x1 - x0))

    def draw_current(self, amps: float, dt: float) -> None:
        """Draw ``amps`` for ``dt`` s: the voltage sags to ``OCV(SoC) - I R`` at the SoC the interval starts
        with, and the SoC falls by ``I dt / capacity``; at SoC 0 the pack is spent (cut off)."""
        if not (math.isfinite(amps) and amps >= 0.0 and math.isfinite(dt) and dt >= 0.0):
            raise ValueError(f"need a finite current >= 0 A and time >= 0 s, got {amps!r} A, {dt!r} s")
        if self.empty:
            self.current = self.power = self.voltage = 0.0
            return
        self.current = float(amps)
        self.voltage = max(self._ocv - amps * self.resistance, 0.0)
        self.power = self.voltage * self.current
        self.soc = max(self.soc - amps * dt / self.capacity_as, 0.0)
        self._ocv = self.ocv(self.soc)
        self.empty = self.soc <= 0.0

    def current_for(self, watts: float) -> float:
        """The current (A) that delivers ``watts`` at the terminals now (the constant-power load), at most
        the pack's maximum-power current ``OCV / (2 R)``."""
        ocv = self._ocv
        if watts <= 0.0:
            return 0.0
        if self.resistance == 0.0:
            return watts / ocv
        r = self.resistance
        disc = ocv * ocv - 4.0 * r * watts
        return (ocv - math.sqrt(disc)) / (2.0 * r) if disc > 0.0 else ocv / (2.0 * r)

    def draw_power(self, watts: float, dt: float) -> None:
        """Deliver ``watts`` of electrical power for ``dt`` s (:meth:`current_for`, then
        :meth:`draw_current`)."""
        if not (math.isfinite(watts) and watts >= 0.0):
            raise ValueError(f"need a finite power >= 0 W, got {watts!r}")
        self.draw_current(self.current_for(watts), dt)

    def electrical_power(self, thrusts: Sequence[float], disk_area: float, climb: float) -> float:
        """The electrical power (W) rotors of ``thrusts`` (N each) draw: :func:`rotor_power` divided by the
        figure of merit and the motor and ESC efficiency."""
        return rotor_power(thrusts, disk_area, climb, self.config.air_density) / self._losses

    def hover_endurance_s(self, weight_n: float, disk_area: float) -> float:
        """Seconds a charged pack hovers a vehicle of ``weight_n`` on four rotors of ``disk_area`` (m^2 in
        all): the capacity over the hover current at full charge (the current grows a little as the voltage
        falls, so this is an upper bound of a few percent)."""
        watts = self.electrical_power([weight_n / 4.0] * 4, disk_area / 4.0, 0.0)
        ocv = self.ocv(1.0)
        r = self.resistance
        amps = watts / ocv if r == 0.0 else (ocv - math.sqrt(max(ocv * ocv - 4.0 * r * watts, 0.0))) / (2 * r)
        return self.capacity_as / amps

    def px4_params(self, weight_n: float, disk_area: float) -> dict[str, float | int]:
        """The PX4 parameters that make PX4 SITL's own simulated battery (``battery_simulator``, which
        Droneulator cannot replace: docs/battery.md) resemble this pack: its cells, capacity, full and empty
        cell voltages and internal resistance, ``SIM_BAT_DRAIN`` the hover endurance (s) and
        ``SIM_BAT_MIN_PCT`` 0 so that it drains to empty."""
        return {
            "BAT1_N_CELLS": self.cells,
            "BAT1_CAPACITY": self.capacity_mah,
            "BAT1_V_CHARGED": self._cell_v[-1],
            "BAT1_V_EMPTY": self._cell_v[0],
            "BAT1_R_INTERNAL": self.resistance,
            "SIM_BAT_DRAIN": round(self.hover_endurance_s(weight_n, disk_area)),
            "SIM_BAT_MIN_PCT": 0.0,
        }

    @property
    def speed_scale(self) -> float:
        """The share of the airframe's ``rotor_speed_max`` the motors reach now: ``V / V_nominal`` below
        the nominal voltage, 1 above it, 0 once the pack is spent."""
        if self.empty:
            return 0.0
        return min(1.0, self.voltage / self.nominal_v)

    def follow(self, dt: float) -> float:
        """:attr:`top_speed` after ``dt`` s: :attr:`speed_scale` through the first-order lag of
        ``speed_time_constant_s`` (at once to 0 when the pack is spent)."""
        target = self.speed_scale
        if target == 0.0:
            self.top_speed = 0.0
        else:
            self.top_speed += (target - self.top_speed) * dt / (self.config.speed_time_constant_s + dt)
        return self.top_speed

    def state(self) -> dict[str, Any]:
        """The API's battery object: terminal voltage (V), current (A, discharging positive), electrical
        power (W), state of charge (0..1), remaining and full capacity (mAh), cells, the open-circuit
        voltage (V), whether the pack is spent, and the share of the airframe's top rotor speed the motors
        reach now."""
        return {
            "voltage": self.voltage,
            "current": self.current,
            "power": self.power,
            "soc": self.soc,
            "remaining_mah": self.soc * self.capacity_mah,
            "capacity_mah": self.capacity_mah,
            "cells": self.cells,
            "ocv": self._ocv,
            "empty": self.empty,
            "top_speed": self.top_speed,
        }
