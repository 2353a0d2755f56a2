"""PX4 SITL simulator interface: PX4's ``simulator_mavlink`` protocol over TCP, in lockstep.

:class:`~droneulator.px4.link.PX4Link` serves PX4 on TCP ``4560 + instance`` (the protocol state and
lockstep stepping), over :mod:`~droneulator.px4.transport` (listening, vetting a connection, MAVLink
framing); :mod:`~droneulator.px4.hil` packs the sensor readings into MAVLink (the sensor models are in
:mod:`droneulator.sensors`), :mod:`~droneulator.px4.handover` decides who flies a vehicle when its PX4
is lost or connects over it in the air, and :mod:`~droneulator.px4.mixing` maps the quad-X motors.
See ``docs/px4.md``.
"""

from droneulator.px4.link import PX4Link
from droneulator.px4.mixing import PX4_QUAD_X, MotorMap, px4_rotor_order

__all__ = ["PX4_QUAD_X", "MotorMap", "PX4Link", "px4_rotor_order"]
