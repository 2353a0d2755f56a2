"""The control level a vineyard policy acts at (``rl.action``): its normalised action and the command it is.

Every env of the task (single, vector, multi-agent) maps its actions through one :class:`Actuator`, a
batch of envs (the single env is a batch of one), and hands the commands to its vehicles: the batched
rows of a :class:`~droneulator.world.World` (:meth:`Actuator.send_rows`) or one vehicle's flight
controller (:meth:`Actuator.send_vehicle`), which run the same compiled inner loops
(:mod:`droneulator.controllers.inner`). Actions lie in [-1, 1], scaled by the ``rl`` section within the
airframe's limits (:meth:`~droneulator.vehicles.vehicle.Vehicle.control_limits`):

* ``velocity`` (2): forward speed ``mid + a0 * half`` over ``[rl.forward_min, rl.forward_max]`` and yaw
  rate ``a1 * rl.max_yaw_rate``; the velocity mode holds the altitude;
* ``ctbr`` (4): collective thrust ``a0`` (0: the weight, -1: none, +1: every rotor at full speed, or
  ``rl.max_thrust_to_weight`` times the weight; linear on each side) and body rates ``a1..a3`` times
  the airframe's ``flight.max_body_rate_deg_s`` (or ``rl.max_body_rate_deg_s`` within it);
* ``attitude`` (4): collective thrust as ``ctbr``; a tilt ``(a1, a2) * flight.max_attitude_tilt_deg``
  (a rotation vector in the heading frame: about body x, a roll, and y, a pitch; its length clipped to
  the largest tilt); yaw rate ``a3 * rl.max_yaw_rate``, which advances a yaw setpoint held from the
  episode's start heading;
* ``rotors`` (4): each rotor's thrust (RotorPy's order), 0 at a quarter of the weight (hover), -1 at the
  slowest and +1 at the fastest rotor speed (or at a quarter of ``rl.max_thrust_to_weight`` times the
  weight), linear on each side; flown directly, no loop in between.
"""

from __future__ import annotations

import math
from typing import Any

import gymnasium as gym
import numpy as np

from droneulator.config import SimConfig
from droneulator.config.rl import ACTIONS
from droneulator.vehicles.dynamics import GRAVITY
from droneulator.vehicles.params import get_params

#: the action's size and the command's (forward, yaw rate; thrust N and rates; thrust N and quaternion
#: [x, y, z, w]; four rotor speeds rad/s) for each level
ACTION_SIZE = {"velocity": 2, "ctbr": 4, "attitude": 4, "rotors": 4}
COMMAND_SIZE = {"velocity": 2, "ctbr": 4, "attitude": 5, "rotors": 4}
assert tuple(ACTION_SIZE) == ACTIONS


class Airframe:
    """The scale an action is mapped by: ``config.rl``'s (:func:`action_rates`, ``rl.max_thrust_to_weight``)
    within the limits of ``config``'s first vehicle (every env's vehicle flies it)."""

    def __init__(self, config: SimConfig) -> None:
        spec = config.vehicle_specs()[0]
        assert spec.params is not None and spec.flight is not None
        q = get_params(spec.params)
        self.k_eta = float(q["k_eta"])
        self.weight = float(q["mass"]) * GRAVITY
        self.rotor_speed = np.array([q["rotor_speed_min"], q["rotor_speed_max"]], dtype=float)
        self.max_thrust = 4.0 * self.k_eta * self.rotor_speed[1] ** 2
        if config.rl.max_thrust_to_weight is not None:
            self.max_thrust = min(self.max_thrust, config.rl.max_thrust_to_weight * self.weight)
        self.max_rate = action_rates(config)
        self.max_tilt = math.radians(spec.flight.max_attitude_tilt_deg)


def action_rates(config: SimConfig) -> np.ndarray:
    """The body rates (rad/s: roll, pitch, yaw) a ``ctbr`` action of +-1 commands and the levels'
    observation reads as +-1: ``rl.max_body_rate_deg_s`` within the airframe's
    ``flight.max_body_rate_deg_s``."""
    flight = config.vehicle_specs()[0].flight
    assert flight is not None
    limit = np.asarray(flight.max_body_rate_deg_s, dtype=float)
    wanted = config.rl.max_body_rate_deg_s
    return np.radians(limit if wanted is None else np.minimum(wanted, limit))


def _around(a: np.ndarray, low: float, mid: float, high: float) -> np.ndarray:
    """``a`` in [-1, 1] to [low, high], linear on each side of ``mid`` (at 0)."""
    return np.where(a < 0.0, mid + a * (mid - low), mid + a * (high - mid))


class Actuator:
    """The actions of ``num_envs`` envs at ``config.rl.action``'s level: the space of one (:attr:`space`),
    the commands they map to (:attr:`commands`, a row per env, 0 at a reset) and each env's yaw setpoint
    (the attitude level's)."""

    def __init__(self, config: SimConfig, num_envs: int) -> None:
        rl = config.rl
        self.level = rl.action
        self.airframe = Airframe(config)
        self._mid = 0.5 * (rl.forward_min + rl.forward_max)
        self._half = 0.5 * (rl.forward_max - rl.forward_min)
        self._max_yaw_rate = rl.max_yaw_rate
        self._frame_dt = 1.0 / config.render.camera_hz
        self.space = gym.spaces.Box(-1.0, 1.0, (ACTION_SIZE[self.level],), dtype=np.float32)
        self.commands = np.zeros((num_envs, COMMAND_SIZE[self.level]))
        self.yaw_ref = np.zeros(num_envs)

    def begin(self, idx: Any, yaws: Any) -> None:
        """Envs ``idx`` start an episode facing ``yaws``: no command yet, the yaw setpoint there."""
        self.commands[idx] = 0.0
        self.yaw_ref[idx] = yaws

    def check(self, actions: Any, k: int) -> np.ndarray:
        """``actions`` as ``(k, size)`` floats clipped to [-1, 1]; ValueError unless finite of that size."""
        size = self.space.shape[0]
        a = np.asarray(actions, dtype=np.float64)
        if a.size != k * size or not np.all(np.isfinite(a)):
            raise ValueError(f"actions must be {k} x {size} finite numbers ({self.level}), got {a.shape}")
        return np.clip(a.reshape(k, size), -1.0, 1.0)

    def map(self, idx: np.ndarray, a: np.ndarray) -> np.ndarray:
        """The commands of envs ``idx`` for their clipped actions ``a`` (into :attr:`commands`, returned);
        at the attitude level their yaw setpoints advance one camera frame."""
        af, out = self.airframe, np.empty((len(idx), COMMAND_SIZE[self.level]))
        if self.level == "velocity":
            out[:, 0] = self._mid + a[:, 0] * self._half
            out[:, 1] = a[:, 1] * self._max_yaw_rate
        elif self.level == "rotors":
            thrust = _around(a, af.k_eta * af.rotor_speed[0] ** 2, 0.25 * af.weight, 0.25 * af.max_thrust)
            out[:] = np.clip(np.sqrt(thrust / af.k_eta), af.rotor_speed[0], af.rotor_speed[1])
        else:
            out[:, 0] = np.clip(_around(a[:, 0], 0.0, af.weight, af.max_thrust), 0.0, af.max_thrust)
            if self.level == "ctbr":
                out[:, 1:4] = a[:, 1:4] * af.max_rate
            else:
                yaw = self.yaw_ref[idx] + a[:, 3] * self._max_yaw_rate * self._frame_dt
                self.yaw_ref[idx] = (yaw + math.pi) % (2 * math.pi) - math.pi
                out[:, 1:5] = tilted(a[:, 1:3] * af.max_tilt, af.max_tilt, self.yaw_ref[idx])
        self.commands[idx] = out
        return out

    def actions(self, commands: np.ndarray) -> np.ndarray:
        """The actions (float32, clipped to [-1, 1]) that :meth:`map` turns into ``commands``: the inverse
        of its scaling, for an expert's or teacher's commands (:mod:`.distil`). ``velocity``: ``(k, 2)``
        forward speed m/s and yaw rate rad/s; ``ctbr``: ``(k, 4)`` thrust N and body rates rad/s."""
        if self.level == "velocity":
            v = np.asarray(commands, dtype=np.float64).reshape(-1, 2)
            a = np.column_stack([(v[:, 0] - self._mid) / self._half, v[:, 1] / self._max_yaw_rate])
            return np.clip(a, -1.0, 1.0).astype(np.float32)
        if self.level != "ctbr":
            raise ValueError(f"actions() inverts the velocity and ctbr levels' scaling, not {self.level!r}")
        af, c = self.airframe, np.asarray(commands, dtype=np.float64).reshape(-1, 4)
        out = np.empty(c.shape)
        thrust = c[:, 0]
        out[:, 0] = np.where(
            thrust < af.weight, thrust / af.weight - 1.0, (thrust - af.weight) / (af.max_thrust - af.weight)
        )
        out[:, 1:4] = c[:, 1:4] / af.max_rate
        return np.clip(out, -1.0, 1.0).astype(np.float32)

    def send_rows(self, world: Any, worlds: np.ndarray, vehicles: np.ndarray, commands: np.ndarray) -> None:
        """Hand ``commands`` to rows ``(worlds[j], vehicles[j])`` of a batched
        :class:`~droneulator.world.World`."""
        if self.level == "velocity":
            world.velocity_rows(worlds, vehicles, commands[:, 0], commands[:, 1])
        elif self.level == "ctbr":
            world.rates_rows(worlds, vehicles, commands[:, 0], commands[:, 1:4])
        elif self.level == "attitude":
            world.attitude_rows(worlds, vehicles, commands[:, 0], commands[:, 1:5])
        else:
            world.rotors_rows(worlds, vehicles, commands)

    def send_vehicle(self, vehicle: Any, command: np.ndarray) -> None:
        """Hand one env's ``command`` to a :class:`~droneulator.vehicles.vehicle.Vehicle`."""
        if self.level == "velocity":
            vehicle.velocity(float(command[0]), float(command[1]))
        elif self.level == "ctbr":
            vehicle.rates(float(command[0]), command[1:4])
        elif self.level == "attitude":
            vehicle.attitude(float(command[0]), quaternion=command[1:5])
        else:
            vehicle.rotors(command)


def tilted(tilt: np.ndarray, most: float, yaw: np.ndarray) -> np.ndarray:
    """Quaternions ``[x, y, z, w]`` (``(k, 4)``) heading ``yaw`` and tilted by the rotation vectors
    ``tilt`` ``(k, 2)`` (about the heading frame's x and y; length clipped to ``most``)."""
    angle = np.hypot(tilt[:, 0], tilt[:, 1])
    scale = np.where(angle > most, most / np.maximum(angle, 1e-300), 1.0)
    tilt, angle = tilt * scale[:, None], np.minimum(angle, most)
    s = np.where(angle > 0.0, np.sin(0.5 * angle) / np.maximum(angle, 1e-300), 0.5)
    bx, by, bw = tilt[:, 0] * s, tilt[:, 1] * s, np.cos(0.5 * angle)
    sz, cz = np.sin(0.5 * yaw), np.cos(0.5 * yaw)
    return np.column_stack([cz * bx - sz * by, cz * by + sz * bx, sz * bw, cz * bw])
