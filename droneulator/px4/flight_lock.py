"""The flight lock that follows PX4's hold on each vehicle, so the API and ROS never fight PX4 (or
ArduPilot: its links, :mod:`droneulator.ardupilot.link`, hold vehicles the same way; ``link.autopilot``
names which in the reasons given).

Per vehicle: while a PX4 is in control of its vehicle, that vehicle's flight commands are refused (the
others still fly on the API); a PX4 that connected over a vehicle in the air is not in control until the
vehicle is on the ground (the simulator flies it meanwhile, by ``px4.on_loss`` after a loss), and while
any PX4 is connected a reset, which would turn its clock back, is refused.
"""

from __future__ import annotations

import functools
import logging
from typing import TYPE_CHECKING

from droneulator.commands import CommandPath

if TYPE_CHECKING:
    from droneulator.ardupilot.link import ArduPilotLink
    from droneulator.px4.fleet import Fleet
    from droneulator.px4.link import PX4Link

log = logging.getLogger(__name__)


class PX4FlightLock:
    """Keeps ``commands``' flight lock on each vehicle of ``fleet`` in step with its link: at once when a
    link's hold changes under the simulation lock (``on_change``), and at each :meth:`update`."""

    def __init__(self, commands: CommandPath, fleet: Fleet) -> None:
        self.commands = commands
        self.fleet = fleet
        #: vehicle -> what PX4 holds of it: "control" (all flight ops), "connected" (reset), or None
        self._holds: dict[str, str | None] = {}
        for link in fleet.links:
            link.on_change = functools.partial(self.follow, link)

    def update(self) -> None:
        """Follow every link."""
        for link in self.fleet.links:
            self.follow(link)

    def follow(self, link: PX4Link | ArduPilotLink) -> None:
        """Lock or free ``link``'s vehicle for what its autopilot holds of it now."""
        name = link.vehicle.name
        who = link.autopilot
        was = self._holds.get(name)
        hold = "control" if link.in_control else "connected" if link.connected else None
        if hold == was:
            return
        self._holds[name] = hold
        if hold == "control":
            self.commands.refuse_flight(
                f"{who} SITL is in control of {name}; flight commands come from {who}", vehicle=name
            )
            log.info(
                "%s is in control of %s: it flies the vehicle and drives the simulation clock", who, name
            )
            return
        if hold == "connected":
            # an autopilot that is connected but not flying (booting over a held vehicle) keeps the clock
            self.commands.refuse_flight(
                f"{who} is connected: reset would turn its clock back", ops=("reset",), vehicle=name
            )
        else:
            self.commands.allow_flight(name)
        if was == "control":  # the link applied on_loss (land, hold or fall) under the lock
            log.warning(
                "%s is not in control of %s: the simulator flies it (%s); a new %s gets the rotors once it "
                "is on the ground",
                who,
                name,
                link.vehicle.mode.value,
                who,
            )
