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

One PX4 at a time: while the connected PX4 is alive (it sent data within ``LINK_SILENCE_S``, or owes
no answer because the simulator has sent it nothing since its last message) a new connection to the
port is closed at once, so a second client cannot take the vehicle from it. Any other connection (no
PX4 connected, or the connected one silent: paused in a debugger, stopped, or dead without closing)
is sent nothing and becomes the PX4 link only once it has shown it is a PX4 with a HEARTBEAT from
``MAV_AUTOPILOT_PX4``, which PX4's simulator_mavlink sends the moment it connects; one that shows
none within ``CANDIDATE_TIMEOUT_S`` is closed. So a stray client can neither take the link from a
paused PX4, which resumes into it (PX4's simulator_mavlink never reconnects), nor lock the API's
flight commands as a "PX4" on an empty port.

PX4 lost while its outputs drive the rotors in the air: ``px4.on_loss`` says what the simulator does
(``land``: its controller lands the vehicle at a spot clear of the scene; ``hold``; ``fall``: rotors
stop). A PX4 that connects while the vehicle is in the air (a restarted PX4 boots believing it is
landed, and would output idle when armed) does not get the rotors: the simulator keeps flying, an arm
in the air is refused (its outputs are not applied; logged and an event) until the vehicle is on the
ground and PX4 disarmed or armed there. Connections, disconnections, losses, arming and hand-overs
are logged and queued as events (:meth:`PX4Link.take_events`).
"""

from __future__ import annotations

import contextlib
import logging
import math
import select
import socket
import time
from collections import deque
from collections.abc import Callable, Collection
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from droneulator.commands.ops import world_of
from droneulator.config import PX4Config
from droneulator.controllers.flight import Event, Mode
from droneulator.frames import enu_to_geodetic, enu_to_ned, xyzw_to_wxyz
from droneulator.logs import LogThrottle
from droneulator.px4.mixing import MotorMap
from droneulator.sensors import SensorSuite, Truth
from droneulator.sensors.baro import BaroSample
from droneulator.sensors.suite import PX4_SENSORS, Schedule

if TYPE_CHECKING:
    import threading

    from droneulator.world.world import StepResult

log = logging.getLogger(__name__)

NS = 1_000_000_000
G0 = 9.80665

#: HIL_SENSOR ``fields_updated`` groups PX4 checks (``SensorSource`` in SimulatorMavlink.hpp)
SENSOR_ACCEL = 0b111
SENSOR_GYRO = 0b111000
SENSOR_MAG = 0b111000000
#: abs_pressure, pressure_alt and temperature: PX4 takes the baro sample only with all three
SENSOR_BARO = 0b1101000000000

LOCKSTEP_FLAG = mavlink.HIL_ACTUATOR_CONTROLS_FLAGS_LOCKSTEP
ARMED_FLAG = mavlink.MAV_MODE_FLAG_SAFETY_ARMED
#: MAVLink identity of the simulator (as Gazebo-classic's mavlink_interface: system 1, IMU component)
SIM_SYSTEM_ID = 1
SIM_COMPONENT_ID = mavlink.MAV_COMP_ID_IMU

#: motors stop when an autopilot's last actuator message is older than this (Gazebo-classic's rule)
ACTUATOR_TIMEOUT_NS = 200_000_000
#: wall time a new connection has to answer the first HIL_SENSOR before the link free-runs
BOOT_GRACE_S = 0.05
#: a connection whose PX4 left sensor data unanswered this long (wall time) may be replaced by a new one
LINK_SILENCE_S = 1.0
#: above this height (m, world z) the vehicle is in the air: a new PX4 does not get its rotors
AIRBORNE_Z_M = 0.05
#: a new connection is closed when it shows no PX4 HEARTBEAT within this (wall s)
CANDIDATE_TIMEOUT_S = 3.0
#: at most this many connections wait to show they are a PX4 at once; more are closed
MAX_CANDIDATES = 4
#: PX4 stores accel 0 and gyro 0 as int16 FIFO counts of these sizes (SimulatorMavlink::update_sensors)
ACCEL_FIFO_SCALE = np.float32(G0 / 2048.0)
GYRO_FIFO_SCALE = np.float32(math.radians(2000.0 / 32768.0))
#: wall time PX4 may take between the answers of a catch-up burst before its newest stale one steps
CATCH_UP_WAIT_S = 0.02
#: falling further behind the wall clock than this restarts the pacing instead of catching up
MAX_LAG_S = 0.25
SEND_TIMEOUT_S = 5.0

_STX = bytes([mavlink.PROTOCOL_MARKER_V2, mavlink.PROTOCOL_MARKER_V1])


def _i16(x: float) -> int:
    return int(np.clip(round(x), -32767, 32767))


def _u16(x: float) -> int:
    return int(np.clip(round(x), 0, 65534))


def fifo_clip(values: np.ndarray, scale: np.float32) -> np.ndarray:
    """``values`` clipped to what PX4's int16 FIFO holds at ``scale`` (-32768..32767 counts).

    PX4 divides each float32 HIL_SENSOR value by the FIFO scale and stores it in an ``int16_t``: a
    value at exactly +16 g (or +2000 deg/s) is +32768 counts and wraps to -32768, so the top of the
    range is one count lower than the bottom's mirror image.
    """
    lo, hi = np.float32(-32768.0) * scale, np.float32(32767.0) * scale
    return np.clip(np.asarray(values, dtype=np.float32), lo, hi)


def _next_stx(buf: bytearray, start: int) -> int | None:
    """Index of the next byte at or after ``start`` that can begin a MAVLink 1 or 2 frame."""
    hits = [i for i in (buf.find(stx, start) for stx in _STX) if i >= 0]
    return min(hits) if hits else None


def _parse_frame(data: bytes) -> tuple[Any, int] | bool | None:
    """pymavlink's parser on a frame starting at ``data[0]``: ``(message, frame length)``, None while
    the frame is incomplete, or False when pymavlink rejects it (checksum, unknown message, flags)."""
    parser = mavlink.MAVLink(None)
    parser.robust_parsing = True
    msg = parser.parse_char(data)
    if msg is None:
        return None
    if isinstance(msg, mavlink.MAVLink_bad_data):
        return False
    return msg, len(data) - parser.buf_len()


@dataclass
class _Candidate:
    """A connection that has not shown it is a PX4 yet: it is sent nothing and becomes the link (replacing
    a silent PX4, if one is connected) only once it has (a HEARTBEAT from ``MAV_AUTOPILOT_PX4``)."""

    sock: socket.socket
    address: str
    since: float
    rx: bytearray = field(default_factory=bytearray)
    msgs: list[Any] = field(default_factory=list)
    px4: bool = False


class PX4Link:
    """Serve PX4 SITL's simulator MAVLink for one vehicle on ``(cfg.host, cfg.base_port + instance)``.

    The caller owns the loop: :meth:`serve_once` accepts PX4, reads its messages and, when one
    HIL_ACTUATOR_CONTROLS arrives, steps the world once and sends the new sensor data back. Several
    links (one PX4 instance per vehicle) step one world together through :class:`PX4Fleet`.
    ``base_port = 0`` listens on a free port (see :attr:`port`).

    ``sim`` is the world (or a single-vehicle ``Simulator``); ``vehicle`` the name of the vehicle PX4
    flies (default: the first); ``instance`` its PX4 SITL instance (default ``cfg.instance``). ``cfg``
    holds the link's settings (address, speed factor, rates, ``on_loss``; default: the world's ``px4``
    section). What PX4 reads comes from the vehicle's sensor rig, built from the simulator's config:
    an IMU, magnetometer and barometer it must have; without a GPS no HIL_GPS is sent, without an
    airspeed sensor HIL_STATE_QUATERNION's airspeeds are zero.
    """

    def __init__(
        self, sim: Any, cfg: PX4Config | None = None, vehicle: str | None = None, instance: int | None = None
    ) -> None:
        self.world = world_of(sim)
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
        self._tx = mavlink.MAVLink(None, SIM_SYSTEM_ID, SIM_COMPONENT_ID)
        self._listener: socket.socket | None = None
        self._listening = False
        self._conn: socket.socket | None = None
        self._peer = ""
        self._events: deque[Event] = deque()
        self._errors = LogThrottle(log, period=1.0)
        self._rx = bytearray()
        self._candidates: list[_Candidate] = []
        #: PX4 was dropped: the loss rule (``cfg.on_loss``) is applied at the next turn, under the lock
        self._loss_pending = False
        #: called under the lock whenever PX4's hold on the vehicle changes with it (PX4 connects, gets
        #: the rotors, or is lost and ``on_loss`` applied), so the runtime's flight lock follows at once
        self.on_change: Callable[[], None] | None = None
        #: the newest lockstep actuator command not stepped yet (at most one): armed, RotorPy rotor speeds
        self._pending: deque[tuple[bool, np.ndarray | None]] = deque()
        self._last_cmd_t_ns: int | None = None
        self._last_mag = np.zeros(3)
        self._last_baro = BaroSample(0.0, 0.0, 0.0)
        self._reset_connection()
        hz = self.world.config.vehicle.control_hz
        if not math.isclose(hz, 250.0):
            log.warning(
                "vehicle.control_hz is %g Hz; PX4 SITL airframes expect a 250 Hz IMU (IMU_INTEG_RATE 250)", hz
            )
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
        if self._listener is None:
            port = 0 if self.cfg.base_port == 0 else self.cfg.base_port + self.instance
            sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            try:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                sock.bind((self.cfg.host, port))
                sock.setblocking(False)
            except OSError:
                sock.close()
                raise
            self._listener = sock
        if listen and not self._listening:
            self._listener.listen(1)
            self._listening = True
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
        return self._listening

    def close(self) -> None:
        """Drop PX4 and stop listening (idempotent)."""
        for c in list(self._candidates):
            self._close_candidate(c, "the link closed")
        if self._conn is not None:
            self._drop("the link closed")
        if self._listener is not None:
            self._listener.close()
            self._listener = None
            self._listening = False

    def __enter__(self) -> PX4Link:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def port(self) -> int:
        if self._listener is None:
            raise RuntimeError("PX4Link is not listening: call start() first")
        return int(self._listener.getsockname()[1])

    @property
    def connected(self) -> bool:
        """True while a PX4 is connected (it then owns the rotors and the simulation clock)."""
        return self._conn is not None

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
        return self._conn is not None and self._holding

    @property
    def in_control(self) -> bool:
        """True while a connected PX4's actuator outputs drive the vehicle (connected, not holding)."""
        return self._conn is not None and not self._holding

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
    def serve_once(self, timeout: float, lock: threading.Lock | None = None) -> StepResult | None:
        """Accept PX4 and handle its messages for up to ``timeout`` s; step at most once.

        Returns the world's StepResult of the step taken (on a HIL_ACTUATOR_CONTROLS, or a free-running
        step before lockstep starts), or None when nothing stepped within ``timeout``. ``lock`` is
        held around every access to the world.
        """
        return serve_links([self], timeout, lock)

    def _time_to_step(self) -> float | None:
        """Seconds until the next step is due (<= 0: now), or None while waiting for PX4."""
        if self._force_step:
            return 0.0
        if self._pending and self._catching_up:
            # PX4 still answers older sensor data: wait for its answer to the latest (a batch PX4 read
            # before its outputs ran is never answered: go on once it has been quiet for a moment)
            left = CATCH_UP_WAIT_S - (time.monotonic() - self._stale_since)
            if left > 0:
                return left
        if self._pending:
            speed = self.cfg.speed_factor
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

    def _sockets(self) -> list[Any]:
        """Every socket this link waits on: the listener, PX4's connection, the candidates'."""
        assert self._listener is not None
        socks: list[Any] = [self._listener] if self._conn is None else [self._listener, self._conn]
        return socks + [c.sock for c in self._candidates]

    def _on_readable(self, readable: Collection[Any], guard: Any) -> None:
        """Handle what ``select`` found readable among :meth:`_sockets`."""
        conn = self._conn
        if conn is not None and conn in readable:
            self._receive(conn)
        for c in list(self._candidates):
            if c.sock in readable:
                self._receive_candidate(c)
        if self._listener in readable:
            self._accept(guard)
        if self._candidates:
            self._review_candidates(guard)

    def _select_failed(self, exc: Exception) -> None:
        if self._conn is not None:
            self._drop(f"socket error: {exc}")

    # ------------------------------------------------------------------ connection
    def _reset_connection(self) -> None:
        self._rx.clear()
        self._pending.clear()
        #: time (us) of the last sensor batch sent, and whether PX4's newest output answers an older one
        self._sent_us: int | None = None
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
        self._holding = False
        #: PX4 armed while the simulator flew the vehicle in the air: refused until it disarms
        self._arm_refused = False
        #: wall time of the first batch sent since PX4's last data (None: PX4 owes no answer)
        self._unanswered_since: float | None = None
        self._schedule = Schedule()
        self._last_t_ns: int | None = None
        self._pace_wall = time.monotonic()
        self._pace_sim = self.world.t_ns

    def _accept(self, guard: Any) -> None:
        assert self._listener is not None
        try:
            conn, addr = self._listener.accept()
        except OSError:
            return
        address = f"{addr[0]}:{addr[1]}"
        silent = self._silence() if self._conn is not None else math.inf
        if silent <= LINK_SILENCE_S or len(self._candidates) >= MAX_CANDIDATES:
            with contextlib.suppress(OSError):
                conn.close()
            log.warning(
                "refused a PX4 connection from %s: %s",
                address,
                f"PX4 at {self._peer} is connected and alive (silent {silent:.2f} s)"
                if silent <= LINK_SILENCE_S
                else f"{MAX_CANDIDATES} connections already wait to show they are a PX4",
            )
            return
        # PX4's simulator_mavlink sends a HEARTBEAT the moment it connects ("to initiate the SITL
        # simulator"): until a connection has, it is sent nothing and owns nothing, so a stray client
        # can neither take a paused PX4's link nor lock the API's flight commands as a "PX4"
        conn.setblocking(False)
        self._candidates.append(_Candidate(conn, address, time.monotonic()))
        if self._conn is not None:
            log.warning(
                "PX4 at %s has been silent for %.1f s; the connection from %s replaces it once it shows "
                "it is a PX4 (a HEARTBEAT from MAV_AUTOPILOT_PX4) and is sent nothing until then",
                self._peer,
                silent,
                address,
            )

    def _install(self, conn: socket.socket, address: str, guard: Any) -> None:
        """Make ``conn`` the PX4 link and send it the boot batch (or step once at t = 0 first)."""
        conn.setblocking(True)
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        conn.settimeout(SEND_TIMEOUT_S)
        self._conn, self._peer = conn, address
        self._reset_connection()
        with guard:
            self._apply_loss()
            self._holding = not self._on_ground()
            if self.on_change is not None:
                self.on_change()
            t_ns = self.world.t_ns
            truth = Truth.from_sim(self.vehicle) if t_ns else None
        log.info(
            "PX4 connected from %s at t=%.3f s%s",
            address,
            t_ns / NS,
            ": the vehicle is in the air, the simulator flies it; PX4 gets the rotors once it is on "
            "the ground"
            if self._holding
            else "",
        )
        self._event("px4_connected", address=address, holding=self._holding)
        if truth is None:
            # PX4 treats timestamp 0 as "never": its clock starts from the first step instead
            self._force_step = True
            return
        self._send_batch(truth)
        self._start_boot_grace()

    def _on_ground(self) -> bool:
        """(Under the lock) the vehicle rests on the ground: no PX4 is needed to keep it safe."""
        return self.vehicle.state.position[2] <= AIRBORNE_Z_M and self.vehicle.mode in (
            Mode.IDLE,
            Mode.EXTERNAL,
        )

    def _apply_loss(self) -> None:
        """(Under the lock) after PX4 was dropped while its outputs drove the rotors: ``cfg.on_loss``."""
        if not self._loss_pending:
            return
        self._loss_pending = False
        if self.vehicle.mode != Mode.EXTERNAL:
            return  # PX4 did not have the rotors: whatever flies the vehicle goes on
        position = self.vehicle.state.position
        data: dict[str, Any] = {"position": [round(float(v), 3) for v in position]}
        if position[2] <= AIRBORNE_Z_M or self.cfg.on_loss == "fall":
            action = "rest" if position[2] <= AIRBORNE_Z_M else "fall"
            self.vehicle.motors_off()
            log.warning("PX4 lost %s: rotors stopped", "on the ground" if action == "rest" else "in the air")
        elif self.cfg.on_loss == "hold":
            action = "hold"
            self.vehicle.hold()
            log.warning("PX4 lost in the air: the simulator holds the vehicle at %s", data["position"])
        else:
            action = "land"
            spot = self.vehicle.safe_land()
            data["spot"] = [round(float(v), 3) for v in spot]
            log.warning(
                "PX4 lost in the air: the simulator lands the vehicle at %s (from %s)",
                data["spot"],
                data["position"],
            )
        self._event("px4_lost", action=action, **data)
        if self.on_change is not None:
            self.on_change()

    def _update_hold(self, armed: bool) -> None:
        """(Under the lock, on each actuator command while holding) hand PX4 the rotors once the vehicle
        is on the ground with PX4 disarmed, or armed there; refuse, and say so, an arm in the air."""
        down = self.vehicle.mode == Mode.IDLE and self.vehicle.state.position[2] <= AIRBORNE_Z_M
        if not armed:
            self._arm_refused = False
            if not down:
                return
        elif self._arm_refused or not down:
            if not self._arm_refused:
                self._arm_refused = True
                reason = (
                    f"PX4 armed with the vehicle in the air ({self.vehicle.mode.value} under the simulator's "
                    "controller): its outputs are not applied; it gets the rotors once the vehicle is on "
                    "the ground and PX4 is disarmed or arms there"
                )
                log.warning("%s", reason)
                self._event("px4_arm_refused", reason=reason)
            return
        self._holding = False
        log.info("the vehicle is on the ground at t=%.3f s: PX4 has the rotors", self.world.t)
        self._event("px4_in_control")
        if self.on_change is not None:
            self.on_change()

    def _silence(self) -> float:
        """Wall seconds the connected PX4 has left sensor data unanswered (0 while it owes nothing)."""
        since = self._unanswered_since
        return 0.0 if since is None else time.monotonic() - since

    def _start_boot_grace(self) -> None:
        """Give PX4 BOOT_GRACE_S of wall time to answer the first batch before free-running."""
        self._pace_wall, self._pace_sim = time.monotonic() + BOOT_GRACE_S, self.world.t_ns

    def _drop(self, reason: str) -> None:
        conn, self._conn = self._conn, None
        if conn is not None:
            self._loss_pending = self._loss_pending or not self._holding
            with contextlib.suppress(OSError):
                conn.close()
            log.warning("PX4 at %s disconnected (%s) at t=%.3f s", self._peer, reason, self.world.t)
            self._event("px4_disconnected", reason=reason)
        self._peer = ""
        self._reset_connection()

    def _receive(self, conn: socket.socket) -> None:
        try:
            data = conn.recv(65536)
        except (BlockingIOError, InterruptedError, TimeoutError):
            return
        except OSError as exc:
            self._drop(f"receive failed: {exc}")
            return
        if not data:
            self._drop("PX4 closed the connection")
            return
        self._unanswered_since = None
        self._rx += data
        for msg in self._extract(self._rx):
            self._handle(msg)

    def _receive_candidate(self, c: _Candidate) -> None:
        try:
            data = c.sock.recv(65536)
        except (BlockingIOError, InterruptedError, TimeoutError):
            return
        except OSError as exc:
            self._close_candidate(c, f"receive failed: {exc}")
            return
        if not data:
            self._close_candidate(c, "it closed before showing it is a PX4")
            return
        c.rx += data
        for msg in self._extract(c.rx):
            c.msgs.append(msg)
            if msg.get_type() == "HEARTBEAT" and msg.autopilot == mavlink.MAV_AUTOPILOT_PX4 and not c.px4:
                c.px4 = True
                log.info("the waiting connection from %s sent a PX4 HEARTBEAT", c.address)

    def _close_candidate(self, c: _Candidate, reason: str) -> None:
        self._candidates.remove(c)
        # logged before the close, so that whoever sees the connection end can read why
        log.warning("closed the waiting connection from %s: %s", c.address, reason)
        with contextlib.suppress(OSError):
            c.sock.close()

    def _review_candidates(self, guard: Any) -> None:
        """Replace a silent PX4 by the first waiting PX4; drop waiting connections when PX4 speaks
        again (it was paused, not dead) or when they show no PX4 HEARTBEAT in time."""
        now = time.monotonic()
        if self._conn is not None and self._silence() <= LINK_SILENCE_S:
            for c in list(self._candidates):
                self._close_candidate(c, f"PX4 at {self._peer} is alive and keeps the link")
            return
        for c in list(self._candidates):
            if not c.px4 and now - c.since > CANDIDATE_TIMEOUT_S:
                self._close_candidate(c, f"no PX4 HEARTBEAT within {CANDIDATE_TIMEOUT_S:.0f} s")
        ready = [c for c in self._candidates if c.px4]
        if not ready:
            return
        c = ready[0]
        self._candidates.remove(c)
        if self._conn is not None:
            self._drop(f"silent for {self._silence():.1f} s; the PX4 at {c.address} replaces it")
        self._install(c.sock, c.address, guard)
        self._rx += c.rx
        for msg in c.msgs:
            self._handle(msg)
        for m in self._extract(self._rx):
            self._handle(m)

    # ------------------------------------------------------------------ parsing
    def _extract(self, buf: bytearray) -> list[Any]:
        """Complete MAVLink messages in ``buf`` (removed from it), framed and checked by pymavlink.

        Bytes that cannot start a valid frame are dropped with a logged error. A rejected frame
        costs one byte, not its claimed length, and an incomplete frame is given up once a valid
        frame starts after it, so a valid message inside (or after) a run of garbage is still found:
        in lockstep PX4 sends one message and waits, so nothing else would complete the bogus frame.
        """
        out: list[Any] = []
        while buf:
            found = None
            keep = len(buf)
            p = _next_stx(buf, 0)
            while p is not None:
                parsed = _parse_frame(bytes(buf[p:]))
                if parsed is None:
                    keep = min(keep, p)
                elif parsed is not False:
                    found = (p, *parsed)
                    break
                p = _next_stx(buf, p + 1)
            if found is None:
                if keep:
                    self._garbage(keep)
                    del buf[:keep]
                return out
            p, msg, n = found
            if p:
                self._garbage(p)
            del buf[: p + n]
            out.append(msg)
        return out

    def _garbage(self, n: int) -> None:
        self._errors.error("garbage", "discarded %d bytes from PX4 that are not valid MAVLink", n)

    def _handle(self, msg: Any) -> None:
        kind = msg.get_type()
        if kind == "HIL_ACTUATOR_CONTROLS":
            armed = bool(msg.mode & ARMED_FLAG)
            speeds = self.motor_map.rotor_speeds(msg.controls[:4]) if armed else None
            if armed != self._armed:
                log.info("PX4 %s at t=%.3f s", "armed" if armed else "disarmed", self.world.t)
                self._event("px4_armed" if armed else "px4_disarmed")
                self._armed = armed
            if msg.flags & LOCKSTEP_FLAG:
                if not self._lockstep:
                    log.info("PX4 lockstep started at t=%.3f s: one step per actuator message", self.world.t)
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
        if cmd is None and self._free_cmd is not None and self._fresh(t_ns):
            cmd = self._free_cmd
        if cmd is not None:
            armed, speeds = cmd
            if self._holding:
                self._update_hold(armed)  # until it hands over, PX4's outputs are not applied
            if not self._holding:
                if armed and speeds is not None:
                    self.vehicle.set_rotor_speeds(speeds)
                else:
                    self.vehicle.motors_off()
            if lockstep:
                self._last_cmd_t_ns = t_ns
        elif not self._holding and self.vehicle.mode == Mode.EXTERNAL and not self._fresh(t_ns):
            self.vehicle.motors_off()
            if not self._timeout_logged:
                self._timeout_logged = True
                log.warning("no actuator outputs from PX4 for 0.2 s of sim time: motors off")

    def _fresh(self, t_ns: int) -> bool:
        return self._last_cmd_t_ns is not None and 0 <= t_ns - self._last_cmd_t_ns <= ACTUATOR_TIMEOUT_NS

    def _due(self, name: str, t_ns: int, hz: float) -> bool:
        """True when sensor ``name`` (sampled at ``hz`` in sim time) has a sample due at ``t_ns``."""
        return self._schedule.due(name, t_ns, hz)

    # ------------------------------------------------------------------ sending
    def _send_batch(self, truth: Truth) -> None:
        """HEARTBEAT (1 Hz), HIL_GPS (gps_hz), HIL_STATE_QUATERNION and HIL_SENSOR for ``truth``."""
        t_ns = truth.t_ns
        if self._last_t_ns is not None and t_ns < self._last_t_ns:
            self._schedule.clear()  # the simulation was reset: restart every schedule
        self._last_t_ns = t_ns
        t_us = t_ns // 1000
        self._sent_us = t_us
        msgs = []
        if self._due("heartbeat", t_ns, 1.0):
            msgs.append(
                self._tx.heartbeat_encode(
                    mavlink.MAV_TYPE_GENERIC, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE
                )
            )
        if "gps" in self.sensors and self._due("gps", t_ns, self.cfg.gps_hz):
            msgs.append(self._gps_message(truth, t_us))
        msgs.append(self._state_message(truth, t_us))
        msgs.append(self._sensor_message(truth, t_us))
        self._send(b"".join(m.pack(self._tx) for m in msgs))

    def _sensor_message(self, truth: Truth, t_us: int) -> Any:
        accel, gyro = self.sensors.imu(truth)
        accel, gyro = fifo_clip(accel, ACCEL_FIFO_SCALE), fifo_clip(gyro, GYRO_FIFO_SCALE)
        # what PX4 gets (float32, within its int16 FIFO) is the vehicle's newest IMU sample: ROS publishes it
        self.sensors.record("imu", truth.t_ns, (accel.astype(np.float64), gyro.astype(np.float64)))
        fields = SENSOR_ACCEL | SENSOR_GYRO
        if self._due("mag", truth.t_ns, self.cfg.mag_hz):
            self._last_mag = self.sensors.mag(truth)
            fields |= SENSOR_MAG
        if self._due("baro", truth.t_ns, self.cfg.baro_hz):
            self._last_baro = self.sensors.baro(truth)
            fields |= SENSOR_BARO
        b = self._last_baro
        return self._tx.hil_sensor_encode(
            t_us,
            *(float(v) for v in accel),
            *(float(v) for v in gyro),
            *self._last_mag,
            b.pressure_hpa,
            0.0,
            b.pressure_alt_m,
            b.temperature_c,
            fields,
            0,
        )

    def _gps_message(self, truth: Truth, t_us: int) -> Any:
        g = self.sensors.gps(truth)
        return self._tx.hil_gps_encode(
            t_us,
            g.fix_type,
            round(g.lat_deg * 1e7),
            round(g.lon_deg * 1e7),
            round(g.alt_msl_m * 1000.0),
            _u16(g.eph_m * 100.0),
            _u16(g.epv_m * 100.0),
            _u16(g.ground_speed * 100.0),
            *(_i16(v * 100.0) for v in g.vel_ned),
            round(g.course_deg * 100.0) % 36000,
            g.satellites,
            0,
            0,
        )

    def _state_message(self, truth: Truth, t_us: int) -> Any:
        lat, lon, alt = enu_to_geodetic(truth.position, *self.world.config.site.geodetic)
        ias, tas = self.sensors.airspeed(truth) if "airspeed" in self.sensors else (0.0, 0.0)
        acc_mg = truth.acceleration_frd / G0 * 1000.0
        return self._tx.hil_state_quaternion_encode(
            t_us,
            [float(v) for v in xyzw_to_wxyz(truth.quaternion_ned_frd)],
            *(float(v) for v in truth.gyro_frd),
            round(lat * 1e7),
            round(lon * 1e7),
            round(alt * 1000.0),
            *(_i16(v * 100.0) for v in enu_to_ned(truth.velocity)),
            _u16(ias * 100.0),
            _u16(tas * 100.0),
            *(_i16(v) for v in acc_mg),
        )

    def _send(self, data: bytes) -> None:
        if self._conn is None:
            return
        try:
            self._conn.sendall(data)
        except OSError as exc:
            self._drop(f"send failed: {exc}")
            return
        if self._unanswered_since is None:
            self._unanswered_since = time.monotonic()


# --------------------------------------------------------------------------- links stepping one world
def serve_links(
    links: list[PX4Link], timeout: float, lock: threading.Lock | None = None
) -> StepResult | None:
    """Serve every link for up to ``timeout`` s and step their (one) world at most once.

    The world steps when every connected PX4 is ready: each in lockstep has sent its actuator outputs
    for the last step, each booting (before lockstep) is due by its pacing, as Gazebo's lockstep waits
    for every PX4 instance. Links without a PX4 do not hold the clock. Returns the step's result, or
    None when nothing stepped within ``timeout``. ``lock`` is held around every access to the world.
    """
    for link in links:
        if not link._listening:
            raise RuntimeError("PX4Link is not listening: call start() first")
    guard = lock if lock is not None else contextlib.nullcontext()
    deadline = time.monotonic() + max(0.0, float(timeout))
    polled = False
    while True:
        for link in links:
            if link._loss_pending:
                with guard:
                    link._apply_loss()
        waits = [link._time_to_step() for link in links if link._conn is not None]
        due = max(waits) if waits and all(w is not None for w in waits) else None  # type: ignore[type-var]
        if due is not None and due <= 0.0:
            return _step_links([link for link in links if link._conn is not None], guard)
        now = time.monotonic()
        if polled and now >= deadline:
            return None
        wait = max(0.0, deadline - now)
        if due is not None:
            wait = min(wait, due)
        _poll_links(links, wait, guard)
        polled = True


def _poll_links(links: list[PX4Link], wait: float, guard: Any) -> None:
    owner = {sock: link for link in links for sock in link._sockets()}
    try:
        readable, _, _ = select.select(list(owner), [], [], wait)
    except (OSError, ValueError) as exc:
        for link in links:
            link._select_failed(exc)
        return
    for link in links:
        link._on_readable([s for s in readable if owner[s] is link], guard)


def _step_links(links: list[PX4Link], guard: Any) -> StepResult:
    """Apply every connected PX4's command, step the world once, send each PX4 its sensor data."""
    world = links[0].world
    firsts = []
    cmds = []
    for link in links:
        firsts.append(link._force_step)
        link._force_step = False
        cmds.append(link._pending.popleft() if link._pending else None)
    with guard:
        for link, cmd in zip(links, cmds, strict=True):
            link._apply(cmd, cmd is not None)
        result = world.step()
        truths = [Truth.from_sim(link.vehicle) for link in links]
    for link, truth, first in zip(links, truths, firsts, strict=True):
        link._send_batch(truth)
        if first:
            link._start_boot_grace()
    return result


class PX4Fleet:
    """Every PX4 link of a world (one PX4 SITL instance per vehicle it flies), served and stepped
    together (:func:`serve_links`); the runtime's face of the PX4 interface."""

    def __init__(self, links: list[PX4Link]) -> None:
        if not links:
            raise ValueError("a PX4 fleet needs at least one link")
        self.links = links

    @classmethod
    def of(cls, sim: Any) -> PX4Fleet:
        """One link for each vehicle the world's config hands to PX4 (:meth:`SimConfig.px4_instances`)."""
        world = world_of(sim)
        return cls(
            [PX4Link(world, vehicle=name, instance=k) for name, k in world.config.px4_instances().items()]
        )

    def start(self, listen: bool = True) -> None:
        for link in self.links:
            link.start(listen)

    @property
    def listening(self) -> bool:
        return all(link.listening for link in self.links)

    @property
    def connected(self) -> bool:
        """True while any PX4 is connected (PX4 then drives the simulation clock)."""
        return any(link.connected for link in self.links)

    def serve_once(self, timeout: float, lock: threading.Lock | None = None) -> StepResult | None:
        return serve_links(self.links, timeout, lock)

    def take_events(self) -> list[Event]:
        return [e for link in self.links for e in link.take_events()]

    def close(self) -> None:
        for link in self.links:
            link.close()
