"""The physics side of ArduPilot SITL's JSON interface, over UDP, in lockstep.

``arducopter --model JSON -I N`` sends one servo packet per simulation frame to UDP ``9002 + 10 N`` and
waits for the state after that frame (:mod:`.protocol`). The link answers each *new* frame by applying
its motor PWMs (:mod:`.mixing`), stepping the world once (one control period) and sending the vehicle's
state back, so ArduPilot and the world advance together: without a packet the world's clock stops. The
reply's timestamp counts the world time since ArduPilot connected (the first reply is one step), so a
restarted ArduPilot boots from zero whatever the world time; ArduPilot's clock follows the timestamps. It
never runs backwards: should the world be reset under a connected ArduPilot (in-process; the API's reset
is refused meanwhile), the next reply is one step later.

Frames, as SIM_JSON.cpp counts them (``frame_count`` moves on only once ArduPilot has parsed a reply):

* the next frame: applied, stepped, answered;
* the frame just answered, again, at least :data:`RESEND_AFTER_S` after the reply left: ArduPilot lost
  (or could not parse) the reply and repeated the frame after waiting its second: the same reply is
  sent again, the world does not step. A repeat that comes sooner crossed a late reply on its way
  (ArduPilot will read that one): answering it again would leave a stale reply in ArduPilot's socket,
  which it would read for its next frame, and it would run one reply behind from then on;
* the frame waiting for its step, again (a fleet waits for a slower instance): nothing to do;
* a lower count from the same address: ArduPilot restarted; the old one is lost (``on_loss``) and the
  new one connects.

One ArduPilot per port: packets from a second address are refused (not answered, logged) while the
connected ArduPilot has sent within :data:`LINK_SILENCE_S` of wall time; one silent that long is lost
(a running ArduPilot repeats its frame every second while it waits), and the next ArduPilot to send
connects. Who flies the vehicle when ArduPilot is lost, or connects over a vehicle in the air, is
:mod:`droneulator.px4.handover`'s rule with ``ardupilot.on_loss``; the runtime's flight lock
(:class:`~droneulator.px4.flight_lock.PX4FlightLock`) follows each link's hold.
"""

from __future__ import annotations

import logging
import math
import socket
import time
from collections import deque
from collections.abc import Callable, Collection
from contextlib import AbstractContextManager
from typing import TYPE_CHECKING, Any

from droneulator.ardupilot.mixing import ArduCopterOctaQuadMotors, arducopter_motors
from droneulator.ardupilot.protocol import FdmState, ProtocolError, ServoPacket, decode_servo
from droneulator.config import ArduPilotConfig
from droneulator.controllers.flight import Event
from droneulator.logs import LogThrottle
from droneulator.px4 import fleet
from droneulator.px4.fleet import AutopilotFleet
from droneulator.px4.handover import Handover, RotorHandover, on_ground, take_over
from droneulator.sensors import SensorSuite, Truth

if TYPE_CHECKING:
    from droneulator.world.world import StepResult, World

log = logging.getLogger(__name__)

NS = 1_000_000_000
#: wall time after which a connected ArduPilot that sent nothing is lost (it repeats a frame every 1 s)
LINK_SILENCE_S = 2.0
#: a repeated frame is answered again only this long (wall s) after its reply left (ArduPilot waits 1 s)
RESEND_AFTER_S = 0.5
#: the largest datagram read (a servo packet is 40 or 72 bytes)
MAX_DATAGRAM = 2048


class ArduPilotLink(RotorHandover):
    """Serve ArduPilot SITL's JSON physics interface for one vehicle on UDP ``(cfg.host, cfg.base_port +
    10 instance)``; ``base_port = 0`` takes a free port (see :attr:`port`).

    ``world`` is the world ArduPilot flies in; ``vehicle`` the name of its vehicle (default: the first);
    ``instance`` its SITL instance (``-I``; default ``cfg.instance``); ``cfg`` the link's settings
    (default: the world's ``ardupilot`` section). The IMU ArduPilot reads is the vehicle's sensor rig's
    (noise from the ``px4`` section's presets); ArduPilot derives GPS, barometer and compass from the
    state. Several links (one ArduPilot per vehicle) step one world together (:class:`ArduPilotFleet`).
    """

    autopilot = "ArduPilot"
    event_prefix = "ardupilot"
    scheme = "udp"

    #: the autopilot's name in the flight lock's reasons and the logs
    autopilot = "ArduPilot"

    def __init__(
        self,
        world: World,
        cfg: ArduPilotConfig | None = None,
        vehicle: str | None = None,
        instance: int | None = None,
    ) -> None:
        self.world = world
        self.vehicle = world.vehicle(vehicle)
        self.cfg = cfg = world.config.ardupilot if cfg is None else cfg
        self.instance = cfg.instance if instance is None else instance
        self.motors = arducopter_motors(self.vehicle.quad_params, cfg)
        self.sensors: SensorSuite = self.vehicle.rig.suite
        if "imu" not in self.sensors:
            raise ValueError(
                f"vehicle {self.vehicle.name!r} has no imu: ArduPilot's JSON interface needs one (its "
                f"'sensors' list: {', '.join(self.sensors.kinds)})"
            )
        self._sock: socket.socket | None = None
        self._listening = False
        self._events: deque[Event] = deque()
        self._errors = LogThrottle(log, period=1.0)
        #: ArduPilot was dropped while its outputs drove the rotors: ``cfg.on_loss`` at the next turn
        self._loss_pending = False
        #: called under the lock whenever ArduPilot's hold on the vehicle changes (the flight lock)
        self.on_change: Callable[[], None] | None = None
        self._refused: set[str] = set()
        self._reset_connection()
        octa = isinstance(self.motors, ArduCopterOctaQuadMotors)
        log.info(
            "ArduCopter %s motor -> %s rotor of %s: %s",
            "octa-quad X (FRAME_CLASS 4, FRAME_TYPE 1)" if octa else "quad X (FRAME_CLASS 1, FRAME_TYPE 1)",
            self.vehicle.spec.params,
            self.vehicle.name,
            ", ".join(f"{n} {name} {spin} -> {r}" for n, name, spin, r in self.motors.table()),
        )

    def _reset_connection(self) -> None:
        self._peer: tuple[str, int] | None = None
        self._last_rx = 0.0
        #: the newest frame number seen on this connection (answered, or waiting in ``_pending``)
        self._frame: int | None = None
        self._pending: ServoPacket | None = None
        self._reply: bytes | None = None
        self._reply_at = 0.0
        self._armed = False
        self._rate_warned = False
        self._handover = Handover()
        #: the last reply's timestamp (ns of ArduPilot's clock) and the world time (ns) it was taken at
        self.clock_ns = 0
        self._world_ns = 0
        self.frames = 0
        self.resent = 0

    # ------------------------------------------------------------------ lifecycle
    def start(self, listen: bool = True) -> None:
        """Take the port and, unless ``listen`` is False, read ArduPilot's packets (idempotent). Bound but
        not read, the port holds ArduPilot's packets (it repeats its frame every second meanwhile)."""
        if self._sock is None:
            port = 0 if self.cfg.base_port == 0 else self.cfg.base_port + 10 * self.instance
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            try:
                sock.bind((self.cfg.host, port))
                sock.setblocking(False)
            except OSError:
                sock.close()
                raise
            self._sock = sock
        if listen and not self._listening:
            self._listening = True
            log.info(
                "waiting for ArduPilot SITL instance %d (--model JSON) for %s on udp://%s:%d",
                self.instance,
                self.vehicle.name,
                self.cfg.host,
                self.port,
            )

    @property
    def listening(self) -> bool:
        return self._listening

    @property
    def port(self) -> int:
        if self._sock is None:
            raise RuntimeError("ArduPilotLink is not started: call start() first")
        return int(self._sock.getsockname()[1])

    def endpoint(self) -> dict[str, int]:
        """Where ArduPilot reaches the vehicle (``scene_info``): its instance and JSON port (bound)."""
        return {"ardupilot_instance": self.instance, "ardupilot_port": self.port}

    def close(self) -> None:
        """Drop ArduPilot and close the port (idempotent)."""
        if self.connected:
            self._drop("the link closed")
        if self._sock is not None:
            self._sock.close()
            self._sock = None
        self._listening = False

    def __enter__(self) -> ArduPilotLink:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ state
    @property
    def connected(self) -> bool:
        """True while an ArduPilot sends servo packets to this link (it then drives the clock)."""
        return self._peer is not None

    @property
    def peer(self) -> str:
        return "" if self._peer is None else f"{self._peer[0]}:{self._peer[1]}"

    @property
    def armed(self) -> bool:
        """Whether ArduPilot's last motor PWMs read as armed (:meth:`ArduCopterMotors.armed`)."""
        return self._armed

    @property
    def holding(self) -> bool:
        """True while a connected ArduPilot does not have the rotors: it connected with the vehicle in
        the air and the vehicle has not been down with ArduPilot disarmed (or arming there) since."""
        return self.connected and self._handover.holding

    @property
    def in_control(self) -> bool:
        """True while a connected ArduPilot's motor outputs drive the vehicle."""
        return self.connected and not self._handover.holding

    def take_events(self) -> list[Event]:
        """The link's events since the last call, oldest first: ``ardupilot_connected`` (``address``,
        ``holding``), ``ardupilot_disconnected`` (``reason``), ``ardupilot_lost`` (``action``,
        ``position``, ``spot`` for land), ``ardupilot_armed``, ``ardupilot_disarmed``,
        ``ardupilot_arm_refused`` (``reason``), ``ardupilot_in_control`` and ``ardupilot_refused``
        (``address``: a second sender on the port)."""
        out = list(self._events)
        self._events.clear()
        return out

    def _event(self, kind: str, **data: Any) -> None:
        self._events.append(Event(kind, self.world.t, data, self.vehicle.name))

    # ------------------------------------------------------------------ the loop
    def serve_once(
        self, timeout: float, lock: AbstractContextManager[Any] | None = None
    ) -> StepResult | None:
        """Read ArduPilot's packets for up to ``timeout`` s and step at most once (on a new frame);
        None when nothing stepped. ``lock`` is held around every access to the world."""
        return serve_links([self], timeout, lock)

    # ------------------------------------------------------------------ the lockstep protocol (.fleet)
    def sockets(self) -> list[socket.socket]:
        return [] if self._sock is None else [self._sock]

    def on_readable(self, readable: Collection[Any], guard: Any) -> None:
        """Read the waiting servo packets; a peer silent for :data:`LINK_SILENCE_S` is lost."""
        if self._sock is not None and self._sock in readable:
            self._receive(guard)
        self._check_silence()

    def on_poll_error(self, exc: Exception) -> None:
        log.error("ArduPilot link select failed: %s", exc)

    def apply_pending_loss(self, guard: Any) -> None:
        if self._loss_pending:
            with guard:
                self._apply_loss()

    def time_to_step(self) -> float | None:
        """0 once ArduPilot's next frame has come (each frame steps at once), None before."""
        return 0.0 if self._pending is not None else None

    def take_command(self) -> ServoPacket | None:
        return self._pending

    def apply_command(self, cmd: ServoPacket | None) -> None:
        self._apply()

    def after_step(self, truth: Truth, cmd: ServoPacket | None) -> None:
        """Answer the frame with the JSON state after the step."""
        self._answer(truth)

    def _receive(self, guard: Any) -> None:
        """Handle every datagram waiting on the port."""
        assert self._sock is not None
        while True:
            try:
                data, addr = self._sock.recvfrom(MAX_DATAGRAM)
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:  # e.g. ECONNREFUSED from an earlier reply to a closed ArduPilot port
                log.debug("ArduPilot link receive: %s", exc)
                continue
            self._datagram(data, (str(addr[0]), int(addr[1])), guard)

    def _datagram(self, data: bytes, addr: tuple[str, int], guard: Any) -> None:
        try:
            pkt = decode_servo(data)
        except ProtocolError as exc:
            self._errors.error("bad", "ignored a datagram from %s:%d: %s", addr[0], addr[1], exc)
            return
        now = time.monotonic()
        if self._peer is not None and addr != self._peer:
            if now - self._last_rx <= LINK_SILENCE_S:
                self._refuse(addr)
                return
            silent = now - self._last_rx
            self._drop(f"silent for {silent:.1f} s; ArduPilot at {addr[0]}:{addr[1]} replaces it")
        if self._peer is not None and self._frame is not None and pkt.frame_count < self._frame:
            self._drop(
                f"its frame count went back from {self._frame} to {pkt.frame_count}: ArduPilot restarted"
            )
        if self._peer is None:
            self._connect(addr, guard)
        self._last_rx = now
        if pkt.frame_count == self._frame:
            late = now - self._reply_at >= RESEND_AFTER_S
            if self._pending is None and self._reply is not None and late:
                self.resent += 1
                self._reply_at = now
                self._send(self._reply)  # ArduPilot did not get (or parse) the answer: the same again
            return
        if self._frame is not None and pkt.frame_count > self._frame + 1:
            self._errors.warning(
                "gap", "ArduPilot skipped frames %d..%d", self._frame + 1, pkt.frame_count - 1
            )
        self._check_rate(pkt.frame_rate)
        self._frame = pkt.frame_count
        self._pending = pkt

    def _refuse(self, addr: tuple[str, int]) -> None:
        address = f"{addr[0]}:{addr[1]}"
        if address not in self._refused:
            self._refused.add(address)
            log.warning(
                "refused servo packets from %s on port %d: ArduPilot at %s is connected to %s (one ArduPilot "
                "per port; run another instance with -I N)",
                address,
                self.port,
                self.peer,
                self.vehicle.name,
            )
            self._event("ardupilot_refused", address=address)

    def _check_rate(self, rate: int) -> None:
        hz = self.world.config.vehicle.control_hz
        if not self._rate_warned and not math.isclose(rate, hz, rel_tol=0.01):
            self._rate_warned = True
            log.warning(
                "ArduPilot asks for %d Hz frames, the world steps at vehicle.control_hz = %g Hz: each frame "
                "advances %.4f s (ArduPilot's clock follows the reply timestamps); run arducopter with "
                "--rate %g, or set vehicle.control_hz=%d, for its IMU rate",
                rate,
                hz,
                1.0 / hz,
                hz,
                rate,
            )

    def _connect(self, addr: tuple[str, int], guard: Any) -> None:
        """A first packet from ``addr``: apply a pending loss, decide whether the new ArduPilot gets the
        rotors (only with the vehicle on the ground), and start its clock at the world's time."""
        self._reset_connection()
        self._peer = addr
        self._refused.clear()
        with guard:
            self._apply_loss()
            self._handover.connect(on_ground(self.vehicle))
            if self.on_change is not None:
                self.on_change()
            self._world_ns = self.world.t_ns
        holding = self._handover.holding
        log.info(
            "ArduPilot connected from %s:%d to %s at t=%.3f s%s",
            addr[0],
            addr[1],
            self.vehicle.name,
            self._world_ns / NS,
            ": the vehicle is in the air, the simulator flies it; ArduPilot gets the rotors once it is on "
            "the ground"
            if holding
            else "",
        )
        self._event("ardupilot_connected", address=self.peer, holding=holding)

    def _check_silence(self) -> None:
        if self.connected and time.monotonic() - self._last_rx > LINK_SILENCE_S:
            self._drop(f"no servo packet for {time.monotonic() - self._last_rx:.1f} s")

    def _drop(self, reason: str) -> None:
        if self._peer is not None:
            self._loss_pending = self._loss_pending or not self._handover.holding
            log.warning("ArduPilot at %s disconnected (%s) at t=%.3f s", self.peer, reason, self.world.t)
            self._event("ardupilot_disconnected", reason=reason)
        self._reset_connection()

    def _apply_loss(self) -> None:
        """(Under the lock) after ArduPilot was dropped while its outputs drove the rotors: ``on_loss``."""
        if not self._loss_pending:
            return
        self._loss_pending = False
        lost = take_over(self.vehicle, self.cfg.on_loss, self.autopilot)
        if lost is None:
            return
        action, data = lost
        self._event("ardupilot_lost", action=action, **data)
        if self.on_change is not None:
            self.on_change()

    # ------------------------------------------------------------------ stepping
    def _apply(self) -> None:
        """(Under the lock, before the step) apply the pending frame's motor PWMs."""
        pkt = self._pending
        assert pkt is not None
        pwm = pkt.pwm
        armed = self.motors.armed(pwm)
        if armed != self._armed:
            log.info("ArduPilot %s at t=%.3f s", "armed" if armed else "disarmed", self.world.t)
            self._event("ardupilot_armed" if armed else "ardupilot_disarmed")
            self._armed = armed
        if self._handover.holding:
            self._update_hold(armed)
        if not self._handover.holding:
            if armed:
                self.vehicle.set_rotor_speeds(self.motors.rotor_speeds(pwm))
            else:
                self.vehicle.motors_off()

    def _answer(self, truth: Truth) -> None:
        """Send the state after the step (the vehicle's IMU sample, the truth) for the pending frame."""
        accel, gyro = self.sensors.imu(truth)
        airspeed = self.sensors.airspeed(truth)[0] if "airspeed" in self.sensors else None
        step = truth.t_ns - self._world_ns
        self.clock_ns += step if step > 0 else self.world.control_period_ns
        self._world_ns = truth.t_ns
        self._reply = FdmState.from_truth(self.clock_ns / NS, truth, accel, gyro, airspeed).encode()
        self._pending = None
        self.frames += 1
        self._reply_at = time.monotonic()
        self._send(self._reply)

    def _send(self, data: bytes) -> None:
        if self._sock is None or self._peer is None:
            return
        try:
            self._sock.sendto(data, self._peer)
        except OSError as exc:
            self._errors.warning("send", "reply to ArduPilot at %s failed: %s", self.peer, exc)


# --------------------------------------------------------------------------- links stepping one world
#: every link of a world, ArduPilot's and PX4's, steps it in one lockstep loop (:mod:`droneulator.px4.fleet`)
serve_links = fleet.serve_links


class ArduPilotFleet(AutopilotFleet[ArduPilotLink]):
    """Every ArduPilot link of a world (one SITL instance per vehicle it flies), served and stepped
    together (:func:`serve_links`); :meth:`AutopilotFleet.of` builds a world's mixed fleet."""

    kind = "ArduPilot"

    @classmethod
    def of(cls, world: World) -> ArduPilotFleet:
        """One link for each vehicle the world's config hands to ArduPilot
        (:meth:`SimConfig.ardupilot_instances`)."""
        instances = world.config.ardupilot_instances()
        return cls([ArduPilotLink(world, vehicle=name, instance=k) for name, k in instances.items()])

