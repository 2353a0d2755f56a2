"""ArduPilot SITL physics interface: ArduPilot's JSON protocol over UDP, in lockstep.

:class:`~droneulator.ardupilot.link.ArduPilotLink` answers ``arducopter --model JSON`` on UDP
``9002 + 10 * instance`` (the lockstep stepping and who holds the vehicle),
:mod:`~droneulator.ardupilot.protocol` packs and unpacks what goes over the wire (servo packets in,
JSON states out), and
:mod:`~droneulator.ardupilot.mixing` maps ArduCopter's quad-X (octa-quad X for the coaxial sprayer)
PWM to rotor speeds. The loss and
hand-over rules and the flight lock are PX4's (:mod:`droneulator.px4.handover`,
:mod:`droneulator.px4.flight_lock`). See ``docs/ardupilot.md``.
"""

from droneulator.ardupilot.link import ArduPilotFleet, ArduPilotLink
from droneulator.ardupilot.mixing import (
    ARDUCOPTER_OCTAQUAD_X,
    ARDUCOPTER_QUAD_X,
    ArduCopterMotors,
    ArduCopterOctaQuadMotors,
    arducopter_motors,
)
from droneulator.ardupilot.protocol import FdmState, ServoPacket, decode_servo

__all__ = [
    "ARDUCOPTER_OCTAQUAD_X",
    "ARDUCOPTER_QUAD_X",
    "ArduCopterMotors",
    "ArduCopterOctaQuadMotors",
    "ArduPilotFleet",
    "ArduPilotLink",
    "FdmState",
    "ServoPacket",
    "arducopter_motors",
    "decode_servo",
]
