"""Flight modes (paper §II-C) on top of RotorPy's SE(3) controller.

* ``goto``/``takeoff``/``land``: a minimum-snap reference from the current state to the target;
* ``velocity``: the unicycle velocity mode of :mod:`droneulator.controllers.velocity`;
* ``hold``: a constant reference at the current position and heading;
* ``track``: an external setpoint stream (position, velocity, acceleration feed-forward, yaw, yaw rate;
  e.g. EGO-Planner's ``PositionCommand``) fed straight to the SE(3) controller as its flat output; when
  no setpoint arrives for :data:`TRACK_TIMEOUT` s of sim time the vehicle holds where it is;
* ``idle``: motors off (rests on the ground);
* ``collided``: the vehicle stopped against the scene until the next command (contact model ``stop``);
* ``crashed``: its rotors stopped for good on a touch (contact model ``crash``) until it is placed again;
* ``external``: rotor speeds set directly by an autopilot (PX4 SITL), no controller in the loop;
* ``rotors``, ``rates``, ``attitude``: a stream of rotor speeds, of collective thrust and body rates, or of
  collective thrust and attitude (the inner loops of :mod:`droneulator.controllers.inner`, run by the
  world's compiled step); like ``track``, after :data:`TRACK_TIMEOUT` s without a command the vehicle
  holds where it is (or stops its motors on the ground).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

import numpy as np

from droneulator.config import FlightConfig
from droneulator.controllers.inner import SP_INTEGRAL, SP_Q, SP_RATES, SP_THRUST, attitude_into, rates_into
from droneulator.controllers.se3 import FastSE3Control
from droneulator.controllers.velocity import VelocityReference
from droneulator.frames import yaw_of
from droneulator.state import FLAT_SIZE, STATE
from droneulator.trajectories.minsnap import PolyTrajectory, goto_trajectory, hold_trajectory

LAND_SPEED = 0.6
TOUCHDOWN_ALTITUDE = 0.03
#: sim seconds without a ``track``, ``rotors``, ``rates`` or ``attitude`` command after which the vehicle
#: holds (raising ``track_timeout``, ``rotors_timeout``, ...)
TRACK_TIMEOUT = 0.5
#: largest ``track`` acceleration feed-forward, m/s^2 (about what the default airframe's thrust margin allows)
TRACK_MAX_ACCEL = 10.0

log = logging.getLogger("droneulator.flight")


class Mode(StrEnum):
    IDLE = "idle"
    TAKEOFF = "takeoff"
    GOTO = "goto"
    HOLD = "hold"
    VELOCITY = "velocity"
    TRACK = "track"
    LAND = "land"
    COLLIDED = "collided"
    #: rotors stopped by a crash (contact model ``crash``): no command until the vehicle is placed again
    CRASHED = "crashed"
    #: rotor speeds commanded from outside (PX4 SITL actuator outputs)
    EXTERNAL = "external"
    #: a stream of rotor speeds (API, ROS, learning)
    ROTORS = "rotors"
    #: a stream of collective thrust and body rates
    RATES = "rates"
    #: a stream of collective thrust and attitude
    ATTITUDE = "attitude"


#: the modes a stream of commands drives, which hold after :data:`TRACK_TIMEOUT` without one
STREAMED = (Mode.TRACK, Mode.ROTORS, Mode.RATES, Mode.ATTITUDE)


@dataclass
class Event:
    """Something that happened at sim time ``t`` (seconds): ``arrived``, ``landed``, ``collision``,
    ``track_timeout`` (setpoints stopped, now holding) or ``impact`` (a hard touchdown, raised by the
    simulator)."""

    type: str
    t: float
    data: dict[str, Any] = field(default_factory=dict)
    #: the vehicle it happened to (set by the world)
    vehicle: str | None = None

    def to_dict(self) -> dict[str, Any]:
        named = {} if self.vehicle is None else {"vehicle": self.vehicle}
        return {"type": self.type, "t": self.t, **named, **self.data}


class FlightController:
    """Turns high-level commands into rotor speed commands, one control tick at a time."""

    def __init__(self, quad_params: dict[str, Any], cfg: FlightConfig) -> None:
        self.cfg = cfg
        self.se3 = FastSE3Control(quad_params, cfg.max_tilt_deg, cfg.min_lift, cfg.rate_gain)
        self.mode = Mode.IDLE
        self.trajectory: PolyTrajectory | None = None
        self.velocity_ref: VelocityReference | None = None
        self.target: np.ndarray | None = None
        self.target_yaw = 0.0
        self._zero = np.zeros(4)
        self._external = np.zeros(4)
        self._setpoint = np.zeros(FLAT_SIZE)  # the latest track setpoint, packed like a flat output
        self._setpoint_t = 0.0
        self._track_flat = np.zeros(FLAT_SIZE)
        #: the latest rotors command, and the latest thrust and rates or attitude setpoint, packed
        #: (:mod:`droneulator.controllers.inner`; the rate loop's integral after it)
        self._rotors = np.zeros(4)
        self._inner = np.zeros(SP_INTEGRAL + 3)
        #: land on arriving at the current goto's target (:meth:`land_at`)
        self._then_land = False
        #: called on every command taken: a world skipping :attr:`steady` vehicles hears when one arrives
        self.on_command: Callable[[], None] | None = None

    @property
    def airborne_modes(self) -> tuple[Mode, ...]:
        return (Mode.TAKEOFF, Mode.GOTO, Mode.HOLD, Mode.VELOCITY, Mode.TRACK, Mode.LAND, Mode.COLLIDED,
                Mode.ROTORS, Mode.RATES, Mode.ATTITUDE)  # fmt: skip

    # ------------------------------------------------------------------ commands
    def _commanded(self) -> None:
        if self.on_command is not None:
            self.on_command()

    def motors_off(self) -> None:
        if self.mode == Mode.CRASHED:  # stopped already, and stays crashed until placed again
            return
        self._commanded()
        self.mode, self.trajectory, self.velocity_ref, self.target = Mode.IDLE, None, None, None
        self._then_land = False

    def goto(
        self,
        s: np.ndarray,
        t: float,
        position: np.ndarray,
        yaw: float | None = None,
        speed: float | None = None,
        duration: float | None = None,
        mode: Mode = Mode.GOTO,
    ) -> float:
        """Start a min-snap move to ``position`` (yaw kept if None); returns the planned duration."""
        self._commanded()
        self._then_land = False
        yaw0 = yaw_of(s[STATE.q])
        yaw1 = yaw0 if yaw is None else float(yaw)
        v0 = np.zeros(3) if self.mode in (Mode.IDLE, Mode.COLLIDED) else s[STATE.v].copy()
        start = s[STATE.x].copy()
        if self.mode in (Mode.GOTO, Mode.TAKEOFF, Mode.LAND, Mode.HOLD) and self.trajectory is not None:
            ref = self.trajectory.flat(t)  # continue from the reference, not the measured state
            start, v0, yaw0 = ref[0:3].copy(), ref[3:6].copy(), float(ref[9])
        elif self.mode == Mode.VELOCITY and self.velocity_ref is not None:
            start, yaw0 = self.velocity_ref.position.copy(), self.velocity_ref.yaw
        self.trajectory = goto_trajectory(
            start,
            v0,
            yaw0,
            np.asarray(position, dtype=float),
            yaw1,
            speed=speed or self.cfg.default_speed,
            duration=duration,
            t0=t,
        )
        self.target = np.asarray(position, dtype=float).copy()
        self.target_yaw = float(self.trajectory.flat(t + self.trajectory.duration)[9])
        self.velocity_ref = None
        self.mode = mode
        return self.trajectory.duration

    def takeoff(self, s: np.ndarray, t: float, altitude: float | None = None) -> float:
        alt = self.cfg.takeoff_altitude if altitude is None else float(altitude)
        target = np.array([*s[STATE.x][:2], alt])
        return self.goto(s, t, target, speed=self.cfg.default_speed, mode=Mode.TAKEOFF)

    def land(self, s: np.ndarray, t: float) -> float:
        return self.goto(s, t, np.array([*s[STATE.x][:2], 0.0]), speed=LAND_SPEED, mode=Mode.LAND)

    def land_at(self, s: np.ndarray, t: float, xy: np.ndarray) -> float:
        """Fly level to ``xy`` at the current height, then land there (a landing spot clear of the
        scene beside the vehicle); returns the duration of the first leg."""
        if np.allclose(xy, s[STATE.x][:2], atol=1e-6):
            return self.land(s, t)
        duration = self.goto(s, t, np.array([xy[0], xy[1], s[STATE.x][2]]))
        self._then_land = True
        return duration

    def hold(self, s: np.ndarray, t: float) -> None:
        self._commanded()
        self._then_land = False
        self.trajectory = hold_trajectory(s[STATE.x].copy(), yaw_of(s[STATE.q]), t)
        self.target, self.target_yaw = s[STATE.x].copy(), yaw_of(s[STATE.q])
        self.velocity_ref = None
        self.mode = Mode.HOLD

    def velocity(self, s: np.ndarray, t: float, forward: float, yaw_rate: float) -> None:
        if self.mode != Mode.VELOCITY or self.velocity_ref is None:
            if self.trajectory is not None and self.mode != Mode.COLLIDED:
                ref = self.trajectory.flat(t)
                pos, yaw = ref[0:3].copy(), float(ref[9])
            else:
                pos, yaw = s[STATE.x].copy(), yaw_of(s[STATE.q])
            c, sn = math.cos(yaw), math.sin(yaw)
            speed0 = float(s[STATE.v][:2] @ (c, sn)) if self.mode != Mode.COLLIDED else 0.0
            self.velocity_ref = VelocityReference(self.cfg, pos, yaw, speed=speed0)
        self.velocity_ref.command(forward, yaw_rate)
        self._commanded()
        self._then_land = False
        self.trajectory, self.target = None, None
        self.mode = Mode.VELOCITY

    def track(
        self,
        t: float,
        position: np.ndarray,
        velocity: np.ndarray,
        acceleration: np.ndarray,
        yaw: float,
        yaw_rate: float,
    ) -> None:
        """Take one setpoint received at sim time ``t`` as the SE(3) reference (world frame, ENU).

        Between setpoints the reference is propagated with constant acceleration and yaw rate from the
        latest one (a 100 Hz planner and a faster control loop stay smooth); after
        :data:`TRACK_TIMEOUT` s without a new one, :meth:`update` switches to ``hold``.
        """
        self._commanded()
        f = self._setpoint
        f[0:3], f[3:6], f[6:9] = position, velocity, acceleration
        f[9], f[10] = yaw, yaw_rate
        self._setpoint_t = float(t)
        self._then_land = False
        self.trajectory, self.velocity_ref = None, None
        self.target, self.target_yaw = np.array(position, dtype=float), float(yaw)
        self.mode = Mode.TRACK

    def _track_reference(self, t: float) -> np.ndarray:
        tau = max(0.0, t - self._setpoint_t)
        sp, f = self._setpoint, self._track_flat
        f[0:3] = sp[0:3] + sp[3:6] * tau + 0.5 * sp[6:9] * tau * tau
        f[3:6] = sp[3:6] + sp[6:9] * tau
        f[6:9] = sp[6:9]
        f[9] = sp[9] + sp[10] * tau
        f[10] = sp[10]
        return f

    def external(self, rotor_speeds: np.ndarray) -> None:
        """Hand the rotors to an external controller: these speeds (rad/s, RotorPy order) until changed; a
        crashed vehicle ignores them (its autopilot flies on, the rotors stay stopped)."""
        if self.mode == Mode.CRASHED:
            return
        self._commanded()
        self._external[:] = rotor_speeds
        self._then_land = False
        self.mode, self.trajectory, self.velocity_ref, self.target = Mode.EXTERNAL, None, None, None

    def _stream(self, t: float, mode: Mode) -> None:
        """Enter (or stay in) streamed mode ``mode`` with a command received at sim time ``t``."""
        self._commanded()
        if self.mode != mode:
            self._inner[SP_INTEGRAL:] = 0.0  # the rate loop starts afresh
        self._setpoint_t = float(t)
        self._then_land = False
        self.mode, self.trajectory, self.velocity_ref, self.target = mode, None, None, None

    def rotors(self, t: float, rotor_speeds: np.ndarray) -> None:
        """Take rotor speeds (rad/s, RotorPy order, within the airframe's range) received at sim time ``t``;
        they stand until the next command or :data:`TRACK_TIMEOUT`."""
        self._rotors[:] = rotor_speeds
        self._stream(t, Mode.ROTORS)

    def rates(self, t: float, thrust: float, body_rates: np.ndarray) -> None:
        """Take a collective thrust (N) and body rates (rad/s, FLU) received at sim time ``t``."""
        self._inner[SP_THRUST] = thrust
        self._inner[SP_RATES : SP_RATES + 3] = body_rates
        self._stream(t, Mode.RATES)

    def attitude(self, t: float, thrust: float, quaternion: np.ndarray) -> None:
        """Take a collective thrust (N) and attitude (unit quaternion ``[x, y, z, w]``, body FLU to world)
        received at sim time ``t``."""
        self._inner[SP_THRUST] = thrust
        self._inner[SP_Q : SP_Q + 4] = quaternion
        self._stream(t, Mode.ATTITUDE)

    def collided(self) -> None:
        self._commanded()
        self._then_land = False
        self.mode, self.trajectory, self.velocity_ref, self.target = Mode.COLLIDED, None, None, None

    def crashed(self) -> None:
        """The rotors stop for good (contact model ``crash``): zero commands until :meth:`revive`."""
        self._commanded()
        self._then_land = False
        self.mode, self.trajectory, self.velocity_ref, self.target = Mode.CRASHED, None, None, None

    def revive(self) -> None:
        """A crashed vehicle placed again: motors off, commands taken again."""
        if self.mode == Mode.CRASHED:
            self.mode = Mode.IDLE

    # ------------------------------------------------------------------ control tick
    @property
    def steady(self) -> bool:
        """True while :meth:`update` would return the same command or reference and raise nothing (motors
        off, or holding): a world of many vehicles skips them until the next command."""
        return self.mode in (Mode.IDLE, Mode.COLLIDED, Mode.CRASHED, Mode.HOLD)

    def update(
        self, s: np.ndarray, t: float, dt: float
    ) -> tuple[np.ndarray | None, np.ndarray | None, list[Event]]:
        """For the coming ``dt``: ``(rotor speeds, None, events)`` where the rotors are set directly (motors
        off, an autopilot, ``rotors``), or ``(None, reference, events)``: a flat reference for the SE(3)
        controller to track or, in ``rates`` and ``attitude``, the packed inner-loop setpoint
        (:mod:`droneulator.controllers.inner`); the world runs the controllers for every vehicle at once,
        :meth:`command` here for one."""
        events: list[Event] = []
        if self.mode in (Mode.IDLE, Mode.COLLIDED, Mode.CRASHED):
            return self._zero, None, events
        if self.mode == Mode.EXTERNAL:
            return self._external, None, events
        if self.mode in STREAMED and t - self._setpoint_t > TRACK_TIMEOUT:
            age, stream = t - self._setpoint_t, self.mode.value
            on_ground = s[STATE.x][2] < TOUCHDOWN_ALTITUDE
            if on_ground and self.mode != Mode.TRACK:
                self.motors_off()
            else:
                self.hold(s, t)
            log.warning("no %s command for %.2f s of sim time: %s at %s", stream, age, self.mode.value,
                        np.round(s[STATE.x], 3).tolist())  # fmt: skip
            events.append(Event(f"{stream}_timeout", t, {"position": s[STATE.x].tolist(), "age": age}))
            if self.mode == Mode.IDLE:
                return self._zero, None, events
        if self.mode == Mode.ROTORS:
            return self._rotors, None, events
        if self.mode in (Mode.RATES, Mode.ATTITUDE):
            return None, self._inner, events
        if self.mode == Mode.VELOCITY:
            assert self.velocity_ref is not None
            flat = self.velocity_ref.update(dt, s[STATE.x])
        elif self.mode == Mode.TRACK:
            flat = self._track_reference(t)
        else:
            assert self.trajectory is not None
            flat = self.trajectory.flat(t)
            done = t >= self.trajectory.t0 + self.trajectory.duration
            if done and self.mode == Mode.LAND and s[STATE.x][2] < TOUCHDOWN_ALTITUDE:
                self.motors_off()
                events.append(Event("landed", t, {"position": s[STATE.x].tolist()}))
                return self._zero, None, events
            arrival = self._arrival(s, t) if done and self.mode in (Mode.GOTO, Mode.TAKEOFF) else None
            if arrival is not None and self._then_land:
                self.land(s, t)  # the landing spot is reached: the second leg starts now
                assert self.trajectory is not None
                return None, self.trajectory.flat(t), events
            if arrival is not None:
                assert self.target is not None
                data = {"target": self.target.tolist(), "position": s[STATE.x].tolist()}
                events.append(Event("arrived", t, {**data, "command": self.mode.value, "settled": arrival}))
                self.mode = Mode.HOLD
        return None, flat, events

    def command(
        self, s: np.ndarray, t: float, dt: float
    ) -> tuple[np.ndarray, np.ndarray | None, list[Event]]:
        """:meth:`update` with the controller run here: rotor speeds, the reference, events."""
        cmd, flat, events = self.update(s, t, dt)
        if cmd is not None or flat is None:
            return cmd, flat, events
        out = np.empty(4)
        if self.mode == Mode.RATES:
            rates_into(s, flat, self.se3.gains(), out, dt)
        elif self.mode == Mode.ATTITUDE:
            attitude_into(s, flat, self.se3.gains(), out, np.empty((3, 3)))
        else:
            out = self.se3.motor_speeds(s, flat)
        return out, flat, events

    def _arrival(self, s: np.ndarray, t: float) -> bool | None:
        """Whether the vehicle, its reference ended, has arrived: True when settled (within
        ``arrive_tolerance`` and slower than ``arrive_speed``), False when only within ``acceptance_radius``
        ``arrive_timeout_s`` after the reference ended (a wind it cannot settle in), None when not yet."""
        assert self.target is not None and self.trajectory is not None
        error = float(np.linalg.norm(s[STATE.x] - self.target))
        if error < self.cfg.arrive_tolerance and float(np.linalg.norm(s[STATE.v])) < self.cfg.arrive_speed:
            return True
        end = self.trajectory.t0 + self.trajectory.duration
        if t - end >= self.cfg.arrive_timeout_s and error <= self.cfg.acceptance_radius:
            return False
        return None
