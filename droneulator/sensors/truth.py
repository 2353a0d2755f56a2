"""Ground truth at one instant, the input every noisy sensor model samples."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np

from droneulator.frames import flu_to_frd, quat_enu_flu_to_ned_frd, quat_to_matrix

#: gravity of the dynamics model in the ENU world, m/s^2
GRAVITY_ENU = np.array([0.0, 0.0, -9.81])


@dataclass(frozen=True)
class Truth:
    """Ground truth at one instant, in the simulator's frames (ENU world, FLU body, [x,y,z,w])."""

    t_ns: int
    position: np.ndarray
    velocity: np.ndarray
    quaternion: np.ndarray
    angular_velocity: np.ndarray
    #: world-frame acceleration, mean over the last step (m/s^2); zero at rest on the ground
    acceleration: np.ndarray
    #: wind velocity in the world frame (m/s)
    wind: np.ndarray
    #: body-frame (FLU) specific force from the forces acting (thrust, drag, ground contact), mean
    #: over the last step (m/s^2); None derives it from ``acceleration`` and the attitude instead
    specific_force: np.ndarray | None = None

    @classmethod
    def from_sim(cls, sim: Any) -> Truth:
        """Read a :class:`~droneulator.vehicles.vehicle.Vehicle` (``world.vehicle()``) through its public
        accessors: its ``state``, ``acceleration``, ``wind_velocity`` and ``specific_force``."""
        st = sim.state
        return cls(
            st.t_ns,
            st.position,
            st.velocity,
            st.quaternion,
            st.angular_velocity,
            np.array(sim.acceleration, dtype=float),
            np.array(sim.wind_velocity, dtype=float),
            np.array(sim.specific_force, dtype=float),
        )

    @cached_property
    def R_world_body(self) -> np.ndarray:
        return quat_to_matrix(self.quaternion)

    @cached_property
    def quaternion_ned_frd(self) -> np.ndarray:
        """Attitude as FRD body -> NED world, ``[x, y, z, w]``."""
        return quat_enu_flu_to_ned_frd(self.quaternion)

    @property
    def gyro_frd(self) -> np.ndarray:
        return flu_to_frd(self.angular_velocity)

    @property
    def specific_force_frd(self) -> np.ndarray:
        """What an ideal accelerometer reads, in the FRD body frame (m/s^2): the simulator's
        specific force when given, else R^T (a - g) from the mean acceleration."""
        if self.specific_force is not None:
            return flu_to_frd(np.asarray(self.specific_force, dtype=float))
        return flu_to_frd(self.R_world_body.T @ (self.acceleration - GRAVITY_ENU))

    @property
    def acceleration_frd(self) -> np.ndarray:
        """Kinematic acceleration (no gravity) in the FRD body frame (m/s^2)."""
        return flu_to_frd(self.R_world_body.T @ self.acceleration)
