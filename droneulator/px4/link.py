"""The simulator side of PX4 SITL's ``simulator_mavlink`` protocol, over TCP, in lockstep.

PX4 (``simulator_mavlink start -c 4560+N``) connects as a TCP *client* to port ``4560 + N`` and
exchanges MAVLink 2 with the simulator, as it does with Gazebo-classic's ``mavlink_interface`` and
jMAVSim:

* PX4 -> simulator: a HEARTBEAT when it connects, a COMMAND_LONG ``SET_MESSAGE_INTERVAL`` asking
  for HIL_STATE_QUATERNION, then one HIL_ACTUATOR_CONTROLS per IMU sample it has processed:
  ``controls[0..3]`` are the quad-X motor outputs in [0, 1] (zeros while disarmed), ``mode`` has
  ``MAV_MODE_FLAG_SAFETY_ARMED`` (128) while armed, ``flags`` bit 0 is set by lockstep builds.
* simulator -> PX4, per physics step: HIL_SENSOR (``id`` 0; accel and gyro every step, mag and baro
  at their rates, flagged in ``fields_updated``), HIL_GPS at ``gps_hz``, HIL_STATE_QUATERNION
  (ground truth), and a HEARTBEAT at 1 Hz; ``time_usec`` is simulation time. PX4 sets its lockstep
  clock from HIL_SENSOR ``time_usec`` and holds its boot script until the first one arrives.

Before PX4's first lockstep HIL_ACTUATOR_CONTROLS on a connection the link free-runs (as Gazebo
does until its first actuator message): PX4 can only boot, and so only start sending actuator
outputs, while sensor time advances. After that each HIL_ACTUATOR_CONTROLS advances the simulation
by exactly one control period, and without one simulation time stops.

One PX4 at a time, vetted before it gets the link (:mod:`.transport`, which also frames MAVLink);
what is sent is packed by :mod:`.hil`; who flies the vehicle when a PX4 is lost or connects over a
vehicle in the air is :mod:`.handover`'s rule. This module keeps the protocol state of a connection and
the lockstep stepping that composes them. Connections, disconnections, losses, arming and hand-overs
are logged and queued as events (:meth:`PX4Link.take_events`).
"""

from __future__ import annotations

import logging
import math
import time
from collections import deque
from collections.abc import Callable, Collection
from contextlib import AbstractContextManager
from typing import TYPE_CHECKING, Any

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from droneulator.config import PX4Config
from droneulator.controllers.flight import Event, Mode
from droneulator.px4 import fleet
from droneulator.px4.fleet import AutopilotFleet
from droneulator.px4.handover import Handover, RotorHandover, on_ground, take_over
from droneulator.px4.hil import HilEncoder
from droneulator.px4.mixing import MotorMap
from droneulator.px4.transport import Candidate, ConnectionLostError, Transport
from droneulator.sensors import SensorSuite, Truth
from droneulator.sensors.suite import PX4_SENSORS

if TYPE_CHECKING:
    import socket

    from droneulator.world.world import StepResult, World

log = logging.getLogger(__name__)

NS = 1_000_000_000

LOCKSTEP_FLAG = mavlink.HIL_ACTUATOR_CONTROLS_FLAGS_LOCKSTEP
ARMED_FLAG = mavlink.MAV_MODE_FLAG_SAFETY_ARMED

#: the HIL_ACTUATOR_CONTROLS output a sprayer's pump follows: PX4's fifth simulator output, set to
#: "Peripheral via Actuator Set 1" (``PWM_MAIN_FUNC5 = 301``: SITL's pwm_out_sim, whose outputs
#: simulator_mavlink sends, takes PWM_MAIN_FUNCn; HIL_ACT_FUNCn are HITL's), which a mission's
#: MAV_CMD_DO_SET_ACTUATOR (actuator 1) drives (:mod:`droneulator.workflows.spraying.px4_mission`)
SPRAY_OUTPUT = 4
#: the output switches the spray on above this and off below its negative (a dead band for an output
#: that is unassigned, 0, or not sent, NaN: then the spray stays as the API set it)
SPRAY_SWITCH = 0.5


def spray_switch(output: float, on: bool) -> bool | None:
    """The spray's new state for PX4's spray output ``output`` (-1 .. 1) when it is ``on`` now: True or
    False on a switch, None when the output leaves it as it is."""
    if not math.isfinite(output):
        return None
    if output > SPRAY_SWITCH and not on:
        return True
    if output < -SPRAY_SWITCH and on:
        return False
    return None


#: motors stop when an autopilot's last actuator message is older than this (Gazebo-classic's rule)
ACTUATOR_TIMEOUT_NS = 200_000_000
#: PX4 SITL's lockstep rate (its airframes' IMU_INTEG_RATE): one HIL_SENSOR and one answer per 4 ms
PX4_LOCKSTEP_HZ = 250.0
#: wall time a new connection has to answer the first HIL_SENSOR before the link free-runs
BOOT_GRACE_S = 0.05
#: wall time PX4 may take between the answers of a catch-up burst before its newest stale one steps
CATCH_UP_WAIT_S = 0.02
#: falling further behind the wall clock than this restarts the pacing instead of catching up
MAX_LAG_S = 0.25


class PX4Link(RotorHandover):
    """Serve PX4 SITL's simulator MAVLink for one vehicle on ``(cfg.host, cfg.base_port + instance)``.

    The caller owns the loop: :meth:`serve_once` accepts PX4, reads its messages and, when one
    HIL_ACTUATOR_CONTROLS arrives, steps the world once and sends the new sensor data back. Several
    links (one PX4 instance per vehicle) step one world together through :class:`PX4Fleet`.
    ``base_port = 0`` listens on a free port (see :attr:`port`).

    ``world`` is the world PX4 flies in; ``vehicle`` the name of the vehicle PX4
    flies (default: the first); ``instance`` its PX4 SITL instance (default ``cfg.instance``). ``cfg``
    holds the link's settings (address, speed factor, rates, ``on_loss``; default: the world's ``px4``
    section). What PX4 reads comes from the vehicle's sensor rig, built from the simulator's config:
    an IMU, magnetometer and barometer it must have; without a GPS no HIL_GPS is sent, without an
    airspeed sensor HIL_STATE_QUATERNION's airspeeds are zero.
    """

    autopilot = "PX4"
    event_prefix = "px4"
    scheme = "tcp"

    #: the autopilot's name in the flight lock's reasons and the logs
    autopilot = "PX4"

    def __init__(
        self,
        world: World,
        cfg: PX4Config | None = None,
        vehicle: str | None = None,
        instance: int | None = None,
    ) -> None:
        self.world = world
        self.vehicle = self.world.vehicle(vehicle)
        self.cfg = cfg = self.world.config.px4 if cfg is None else cfg
        self.instance = cfg.instance if instance is None else instance
        self.motor_map = MotorMap(self.vehicle.quad_params, cfg.thrust_model_factor)
        self.sensors: SensorSuite = self.vehicle.rig.suite
        missing = [kind for kind in PX4_SENSORS if kind not in self.sensors]
        if missing:
            raise ValueError(
                f"vehicle {self.vehicle.name!r} has no {', '.join(missing)}: PX4 needs "
                f"{', '.join(PX4_SENSORS)} (its 'sensors' list: {', '.join(self.sensors.kinds)})"
            )
        self._hil = HilEncoder(self.sensors, cfg, self.world.config.site)
        self._transport = Transport(cfg.host, 0 if cfg.base_port == 0 else cfg.base_port + self.instance)
        self._events: deque[Event] = deque()
        self._handover = Handover()
        #: PX4 was dropped: the loss rule (``cfg.on_loss``) is applied at the next turn, under the lock
        self._loss_pending = False
        #: called under the lock whenever PX4's hold on the vehicle changes with it (PX4 connects, gets
        #: the rotors, or is lost and ``on_loss`` applied), so the runtime's flight lock follows at once
        self.on_change: Callable[[], None] | None = None
        #: the newest lockstep actuator command not stepped yet (at most one): armed, RotorPy rotor speeds
        self._pending: deque[tuple[bool, np.ndarray | None]] = deque()
        self._last_cmd_t_ns: int | None = None
        self._reset_connection()
        hz = self.world.config.vehicle.control_hz
        #: world steps per exchange with PX4: a world stepping at a multiple of PX4's 250 Hz (a mixed
        #: fleet's 1000 Hz, for ArduPilot's IMU) exchanges every ``every``-th step, on PX4's own clock
        self.every = max(1, round(hz / PX4_LOCKSTEP_HZ))
        if not math.isclose(hz, PX4_LOCKSTEP_HZ * self.every):
            self.every = 1
            log.warning(
                "vehicle.control_hz is %g Hz; PX4 SITL airframes expect a 250 Hz IMU (IMU_INTEG_RATE 250): "
                "use 250 Hz or a multiple of it",
                hz,
            )
        self._period_ns = self.every * self.world.control_period_ns
        log.info(
            "PX4 quad-X motor -> %s rotor of %s: %s",
            self.vehicle.spec.params,
            self.vehicle.name,
            ", ".join(f"{n} {name} {spin} -> {r}" for n, name, spin, r in self.motor_map.table()),
        )

    # ------------------------------------------------------------------ lifecycle
    def start(self, listen: bool = True) -> None:
        """Take the port and, unless ``listen`` is False, listen for PX4 (idempotent).

        Bound but not listening, the port refuses connections, and PX4's simulator_mavlink retries
        every 0.5 ms: the runtime binds at once (a taken port fails the start) and listens only once
        its cameras and bridge are warm, so PX4's first sensor data never waits for them.
        """
        self._transport.bind()
        if listen and self._transport.listen():
            log.info(
                "waiting for PX4 SITL instance %d (simulator_mavlink) for %s on tcp://%s:%d",
                self.instance,
                self.vehicle.name,
                self.cfg.host,
                self.port,
            )

    @property
    def listening(self) -> bool:
        """True once PX4 can connect (:meth:`start` with ``listen``)."""
        return self._transport.listening

    def close(self) -> None:
        """Drop PX4 and stop listening (idempotent)."""
        if self._transport.conn is not None:
            self._drop("the link closed")
        self._transport.close()

    def __enter__(self) -> PX4Link:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def port(self) -> int:
        return self._transport.port

    def endpoint(self) -> dict[str, int]:
        """Where PX4 reaches the vehicle (``scene_info``): its instance and simulator port (bound)."""
        return {"px4_instance": self.instance, "px4_port": self.port}

    @property
    def connected(self) -> bool:
        """True while a PX4 is connected (it then owns the rotors and the simulation clock)."""
        return self._transport.conn is not None

    @property
    def lockstep(self) -> bool:
        """True once the connected PX4 steps the simulation with lockstep actuator messages."""
        return self._lockstep

    @property
    def armed(self) -> bool:
        """Armed state in PX4's last HIL_ACTUATOR_CONTROLS on this connection."""
        return self._armed

    @property
    def holding(self) -> bool:
        """True while a connected PX4 does not have the rotors: it connected with the vehicle in the air
        (after the previous PX4 was lost, or while the API flew it), and the vehicle has not been on
        the ground with PX4 disarmed since. The simulator's controller flies; PX4's outputs are not
        applied."""
        return self.connected and self._handover.holding

    @property
    def in_control(self) -> bool:
        """True while a connected PX4's actuator outputs drive the vehicle (connected, not holding)."""
        return self.connected and not self._handover.holding

    def take_events(self) -> list[Event]:
        """The link's events since the last call, oldest first: ``px4_connected`` (``address``,
        ``holding``), ``px4_disconnected`` (``reason``), ``px4_lost`` (``action``: land, hold, fall or
        rest; ``position``; ``spot``, the landing spot, for land), ``px4_armed``, ``px4_disarmed``,
        ``px4_arm_refused`` (``reason``) and ``px4_in_control`` (a PX4 that connected over an airborne
        vehicle gets the rotors, the vehicle on the ground)."""
        out = list(self._events)
        self._events.clear()
        return out

    def _event(self, kind: str, **data: Any) -> None:
        self._events.append(Event(kind, self.world.t, data, self.vehicle.name))

    # ------------------------------------------------------------------ the loop
    def serve_once(
        self, timeout: float, lock: AbstractContextManager[Any] | None = None
    ) -> StepResult | None:
        """Accept PX4 and handle its messages for up to ``timeout`` s; step at most once.

        Returns the world's StepResult of the step taken (on a HIL_ACTUATOR_CONTROLS, or a free-running
        step before lockstep starts), or None when nothing stepped within ``timeout``. ``lock`` is
        held around every access to the world.
        """
        return serve_links([self], timeout, lock)

    # ------------------------------------------------------------------ the lockstep protocol (.fleet)
    def sockets(self) -> list[socket.socket]:
        return self._transport.sockets()

    def apply_pending_loss(self, guard: Any) -> None:
        if self._loss_pending:
            with guard:
                self._apply_loss()

    def take_command(self) -> tuple[tuple[bool, np.ndarray | None] | None, bool]:
        """PX4's lockstep command for the step (None: none came, e.g. while it boots) and whether the step
        is the connection's first (forced at t = 0), after which PX4 has its boot grace."""
        first, self._force_step = self._force_step, False
        if not self._pending:
            return None, first
        self._awaiting = False
        return self._pending.popleft(), first

    def apply_command(self, cmd: tuple[tuple[bool, np.ndarray | None] | None, bool]) -> None:
        self._apply(cmd[0], cmd[0] is not None)

    def after_step(self, truth: Truth, cmd: tuple[tuple[bool, np.ndarray | None] | None, bool]) -> None:
        """Send the step's HIL batch (HIL_SENSOR, HIL_GPS at its rate, HIL_STATE_QUATERNION) when the
        step ends one of PX4's periods (every step at 250 Hz); the steps between apply its last outputs."""
        if cmd[1] or truth.t_ns % self._period_ns == 0:
            self._send_batch(truth)
        if cmd[1]:
            self._start_boot_grace()

    def time_to_step(self) -> float | None:
        """Seconds until the next step is due (<= 0: now), or None while waiting for PX4."""
        if self._force_step:
            return 0.0
        if self._pending and self._catching_up:
            # PX4 still answers older sensor data: wait for its answer to the latest (a batch PX4 read
            # before its outputs ran is never answered: go on once it has been quiet for a moment)
            left = CATCH_UP_WAIT_S - (time.monotonic() - self._stale_since)
            if left > 0:
                return left
        if self._pending or (self._lockstep and not self._awaiting):
            speed = self.cfg.speed_factor  # its answer came, or the steps between two exchanges
        elif not self._lockstep:
            speed = self.cfg.speed_factor or 1.0
        else:
            return None
        if speed == 0.0:
            return 0.0
        now = time.monotonic()
        due = self._pace_wall + (self.world.t_ns - self._pace_sim) / NS / speed
        if now - due > MAX_LAG_S:
            self._pace_wall, self._pace_sim = now, self.world.t_ns
            due = now
        return due - now

    def on_readable(self, readable: Collection[Any], guard: Any) -> None:
        """Handle what ``select`` found readable among the transport's sockets."""
        t = self._transport
        if t.conn is not None and t.conn in readable:
            self._receive()
        t.receive_candidates(readable)
        if t.listener in readable:
            t.accept()
        if t.candidates:
            c = t.review_candidates()
            if c is not None:
                self._promote(c, guard)

    def on_poll_error(self, exc: Exception) -> None:
        if self.connected:
            self._drop(f"socket error: {exc}")

    # ------------------------------------------------------------------ connection
    def _reset_connection(self) -> None:
        self._pending.clear()
        #: PX4's spray output in its last HIL_ACTUATOR_CONTROLS (:data:`SPRAY_OUTPUT`)
        self._spray_output = math.nan
        #: time (us) of the last sensor batch sent, and whether PX4's newest output answers an older one
        self._sent_us: int | None = None
        #: a batch went out and PX4's answer to it has not been stepped yet (lockstep holds the clock)
        self._awaiting = False
        self._catching_up = False
        self._stale_since = 0.0
        self._lockstep = False
        #: simulation time (ns) at which this connection's PX4 began lockstep (None: not yet)
        self.lockstep_started_ns: int | None = None
        self._armed = False
        self._free_cmd: tuple[bool, np.ndarray | None] | None = None
        self._force_step = False
        self._heartbeat_seen = False
        self._timeout_logged = False
        self._handover = Handover()
        self._hil.reset()
        self._pace_wall = time.monotonic()
        self._pace_sim = self.world.t_ns

    def _promote(self, c: Candidate, guard: Any) -> None:
        """Make candidate ``c``, which showed it is a PX4, the link (dropping a silent PX4 for it), and
        handle what it sent while it waited."""
        if self.connected:
            self._drop(f"silent for {self._transport.silence():.1f} s; the PX4 at {c.address} replaces it")
        self._transport.adopt(c.sock, c.address, c.framer)
        self._install(c.address, guard)
        for msg in c.msgs:
            self._handle(msg)

    def _install(self, address: str, guard: Any) -> None:
        """Start the protocol on the newly adopted connection: apply a pending loss, decide whether the new
        PX4 gets the rotors, and send it the boot batch (or step once at t = 0 first)."""
        self._reset_connection()
        with guard:
            self._apply_loss()
            self._handover.connect(on_ground(self.vehicle))
            if self.on_change is not None:
                self.on_change()
            t_ns = self.world.t_ns
            truth = Truth.from_sim(self.vehicle) if t_ns else None
        holding = self._handover.holding
        log.info(
            "PX4 connected from %s at t=%.3f s%s",
            address,
            t_ns / NS,
            ": the vehicle is in the air, the simulator flies it; PX4 gets the rotors once it is on "
            "the ground"
            if holding
            else "",
        )
        self._event("px4_connected", address=address, holding=holding)
        if truth is None:
            # PX4 treats timestamp 0 as "never": its clock starts from the first step instead
            self._force_step = True
            return
        self._send_batch(truth)
        self._start_boot_grace()

    def _apply_loss(self) -> None:
        """(Under the lock) after PX4 was dropped while its outputs drove the rotors: ``cfg.on_loss``."""
        if not self._loss_pending:
            return
        self._loss_pending = False
        lost = take_over(self.vehicle, self.cfg.on_loss)
        if lost is None:
            return  # PX4 did not have the rotors: whatever flies the vehicle goes on
        action, data = lost
        self._event("px4_lost", action=action, **data)
        if self.on_change is not None:
            self.on_change()

    def _start_boot_grace(self) -> None:
        """Give PX4 BOOT_GRACE_S of wall time to answer the first batch before free-running."""
        self._pace_wall, self._pace_sim = time.monotonic() + BOOT_GRACE_S, self.world.t_ns

    def _drop(self, reason: str) -> None:
        peer = self._transport.peer
        if self._transport.disconnect():
            self._loss_pending = self._loss_pending or not self._handover.holding
            log.warning("PX4 at %s disconnected (%s) at t=%.3f s", peer, reason, self.world.t)
            self._event("px4_disconnected", reason=reason)
        self._transport.peer = ""
        self._reset_connection()

    def _receive(self) -> None:
        try:
            msgs = self._transport.receive()
        except ConnectionLostError as exc:
            self._drop(str(exc))
            return
        for msg in msgs:
            self._handle(msg)

    # ------------------------------------------------------------------ protocol
    def _handle(self, msg: Any) -> None:
        kind = msg.get_type()
        if kind == "HIL_ACTUATOR_CONTROLS":
            armed = bool(msg.mode & ARMED_FLAG)
            speeds = self.motor_map.rotor_speeds(msg.controls[:4]) if armed else None
            self._spray_output = float(msg.controls[SPRAY_OUTPUT])
            if armed != self._armed:
                log.info("PX4 %s at t=%.3f s", "armed" if armed else "disarmed", self.world.t)
                self._event("px4_armed" if armed else "px4_disarmed")
                self._armed = armed
            if msg.flags & LOCKSTEP_FLAG:
                if not self._lockstep:
                    log.info(
                        "PX4 lockstep started at t=%.3f s: %s per actuator message",
                        self.world.t,
                        "one step" if self.every == 1 else f"{self.every} steps",
                    )
                    self._lockstep = True
                    self.lockstep_started_ns = self.world.t_ns
                    self._pace_wall, self._pace_sim = time.monotonic(), self.world.t_ns
                # it answers the batch stamped time_usec (PX4's lockstep clock is the HIL_SENSOR time):
                # one that answers an older batch than the latest sent is PX4 catching up on sensor data
                # sent while it booted; only the answer to the latest may step, with the newest outputs
                self._catching_up = self._sent_us is not None and msg.time_usec < self._sent_us
                self._stale_since = time.monotonic()
                self._pending.clear()
                self._pending.append((armed, speeds))
            else:
                if self._lockstep or self._free_cmd is None:
                    log.warning(
                        "PX4 runs without lockstep: free-running at %g x real time",
                        self.cfg.speed_factor or 1,
                    )
                self._lockstep = False
                self._free_cmd = (armed, speeds)
                self._last_cmd_t_ns = self.world.t_ns
        elif kind == "HEARTBEAT":
            if not self._heartbeat_seen:
                self._heartbeat_seen = True
                log.info(
                    "PX4 heartbeat: autopilot %d, %s",
                    msg.autopilot,
                    "armed" if msg.base_mode & 128 else "disarmed",
                )
        elif kind == "COMMAND_LONG":
            log.debug("PX4 command %d (%s); HIL_STATE_QUATERNION is sent every step", msg.command, msg.param1)
        else:
            log.debug("ignoring %s from PX4", kind)

    # ------------------------------------------------------------------ stepping
    def _apply(self, cmd: tuple[bool, np.ndarray | None] | None, lockstep: bool) -> None:
        """(Under the lock, before a step) apply PX4's command ``cmd`` (``lockstep``: from a lockstep
        message) or, without a fresh one, the actuator timeout."""
        t_ns = self.world.t_ns
        spraying = self.world.spraying
        if spraying is not None and self.vehicle.name in spraying.systems:
            system = spraying.systems[self.vehicle.name]
            switch = spray_switch(self._spray_output, system.rate > 0.0)
            if switch is not None:
                system.set(1.0 if switch else 0.0)
        if cmd is None and self._free_cmd is not None and self._fresh(t_ns):
            cmd = self._free_cmd
        if cmd is not None:
            armed, speeds = cmd
            if self._handover.holding:
                self._update_hold(armed)  # until it hands over, PX4's outputs are not applied
            if not self._handover.holding:
                if armed and speeds is not None:
                    self.vehicle.set_rotor_speeds(speeds)
                else:
                    self.vehicle.motors_off()
            if lockstep:
                self._last_cmd_t_ns = t_ns
        elif not self._handover.holding and self.vehicle.mode == Mode.EXTERNAL and not self._fresh(t_ns):
            self.vehicle.motors_off()
            if not self._timeout_logged:
                self._timeout_logged = True
                log.warning("no actuator outputs from PX4 for 0.2 s of sim time: motors off")

    def _fresh(self, t_ns: int) -> bool:
        return self._last_cmd_t_ns is not None and 0 <= t_ns - self._last_cmd_t_ns <= ACTUATOR_TIMEOUT_NS

    # ------------------------------------------------------------------ sending
    def _send_batch(self, truth: Truth) -> None:
        """Send PX4 the step's sensor data for ``truth`` (:meth:`HilEncoder.batch`)."""
        self._sent_us = truth.t_ns // 1000
        self._awaiting = True
        try:
            self._transport.send(self._hil.batch(truth))
        except ConnectionLostError as exc:
            self._drop(str(exc))


# --------------------------------------------------------------------------- links stepping one world
#: every link of a world, PX4's and ArduPilot's, steps it in one lockstep loop (:mod:`.fleet`)
serve_links = fleet.serve_links


class PX4Fleet(AutopilotFleet[PX4Link]):
    """Every PX4 link of a world (one PX4 SITL instance per vehicle it flies), served and stepped
    together (:func:`serve_links`); :meth:`AutopilotFleet.of` builds a world's mixed fleet."""

    kind = "PX4"

    @classmethod
    def of(cls, world: World) -> PX4Fleet:
        """One link for each vehicle the world's config hands to PX4 (:meth:`SimConfig.px4_instances`)."""
        return cls(
            [PX4Link(world, vehicle=name, instance=k) for name, k in world.config.px4_instances().items()]
        )

