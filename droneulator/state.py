"""The packed vectors every layer shares: a vehicle's state (RotorPy's layout) and a flat output.

Physics, controllers, trajectories, sensors and the world all pass these as plain float64 arrays, so
compiled kernels can index them directly; code outside the kernels names their fields through
:data:`STATE` (``s[STATE.q]``) and :data:`FLAT` instead of writing the slices. They live here, below
every package that uses them, so none of those packages imports another for a layout.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np


class StateLayout(NamedTuple):
    """Named slices of the packed state vector, with RotorPy's field names and order.

    ``x`` position (world, m), ``v`` velocity (world, m/s), ``q`` attitude ``[x, y, z, w]`` (body FLU
    to world), ``w`` body rates (rad/s), ``wind`` wind velocity (world, m/s), ``rotor_speeds`` (rad/s).
    """

    x: slice = slice(0, 3)
    v: slice = slice(3, 6)
    q: slice = slice(6, 10)
    w: slice = slice(10, 13)
    wind: slice = slice(13, 16)
    rotor_speeds: slice = slice(16, 20)

    @property
    def names(self) -> tuple[str, ...]:
        return self._fields

    @property
    def size(self) -> int:
        return max(part.stop for part in self)


#: the packed state's layout: ``s[STATE.x]`` is the position, ``s[STATE.rotor_speeds]`` the rotors
STATE = StateLayout()
STATE_SIZE = STATE.size


class FlatLayout(NamedTuple):
    """Named parts of a packed flat output (a trajectory's reference for the SE(3) controller):
    position, velocity, acceleration (world, m, m/s, m/s^2), yaw and yaw rate (rad, rad/s)."""

    x: slice = slice(0, 3)
    x_dot: slice = slice(3, 6)
    x_ddot: slice = slice(6, 9)
    yaw: int = 9
    yaw_dot: int = 10


#: the packed flat output's layout
FLAT = FlatLayout()
FLAT_SIZE = 11


def pack_flat(flat_output: dict[str, Any]) -> np.ndarray:
    """RotorPy flat-output dict -> packed vector (:data:`FLAT`)."""
    f = np.zeros(FLAT_SIZE)
    f[FLAT.x] = flat_output["x"]
    f[FLAT.x_dot] = flat_output["x_dot"]
    f[FLAT.x_ddot] = flat_output["x_ddot"]
    f[FLAT.yaw] = flat_output["yaw"]
    f[FLAT.yaw_dot] = flat_output["yaw_dot"]
    return f
