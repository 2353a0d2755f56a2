"""PX4 SITL simulator interface: PX4's ``simulator_mavlink`` protocol over TCP, in lockstep.

:class:`~droneulator.px4.link.PX4Link` serves PX4 on TCP ``4560 + instance``; the sensor models are
in :mod:`droneulator.sensors` (this package only packs their readings into MAVLink) and the quad-X
motor mapping in :mod:`droneulator.px4.mixing`.
See ``docs/px4.md``.
"""

from droneulator.px4.link import PX4Link
from droneulator.px4.mixing import PX4_QUAD_X, MotorMap, px4_rotor_order

__all__ = ["PX4_QUAD_X", "MotorMap", "PX4Link", "px4_rotor_order"]
