"""PX4 offboard control over MAVLink: the planner's setpoints as ``SET_POSITION_TARGET_LOCAL_NED``.

PX4 SITL opens an onboard/API MAVLink instance for each vehicle (``mavlink start -u 14580+N -o
14540+N -m onboard -f``): it sends to UDP ``14540 + N`` and answers whoever talks to it, which is how
MAVSDK and MAVROS connect. Instances past 9 all send to 14549, the port of instance 9
(``px4-rc.mavlink``: ``[ "$px4_instance" -gt 9 ] && udp_offboard_port_remote=14549``), and are told
apart by their system id, ``MAV_SYS_ID`` = N + 1 (``rcS``), as MAVSDK users must.
:class:`OffboardLink` does the same with pymavlink's codec on a plain UDP socket:

1. bind ``host:`` :func:`offboard_port` (``base_port + min(instance, 9)``), wait for the HEARTBEAT of
   PX4 system ``instance + 1`` (``MAV_AUTOPILOT_PX4``; other PX4 systems on the port are ignored; its
   component id becomes the target) and reply to the address it came from. Where 14549 is already
   another link's (one planner per vehicle of a fleet past 9), bind any port and send HEARTBEATs to
   PX4's own port ``14580 + N`` instead: PX4 takes the first sender as its partner and answers it;
2. send our own HEARTBEAT at ``heartbeat_hz`` (a companion computer: ``MAV_TYPE_ONBOARD_CONTROLLER``,
   PX4's system id, ``MAV_COMP_ID_ONBOARD_COMPUTER``; or MAVSDK's ground-station identity);
3. learn PX4's local origin: ``GPS_GLOBAL_ORIGIN`` (asked for with ``MAV_CMD_REQUEST_MESSAGE``) is
   the geodetic point of EKF2's local NED (0, 0, 0); with the simulator's home (the geodetic point of
   the world origin, the ``site`` section) it is a point of the ENU world (``frames.geodetic_to_enu``);
4. when asked for control (:meth:`OffboardLink.engage`, or the first setpoint): wait for PX4's own
   position estimate (``LOCAL_POSITION_NED``, which PX4 streams at 30 Hz on this link, with
   ``ATTITUDE`` for the heading), stream a hold at that position and heading at ``rate_hz`` (wall
   clock; PX4 needs more than 2 Hz before and during OFFBOARD), after ``prestream_s`` switch to
   OFFBOARD (``MAV_CMD_DO_SET_MODE``, custom main mode 6) and arm if needed
   (``MAV_CMD_COMPONENT_ARM_DISARM``), each checked against its COMMAND_ACK, and wait until PX4's
   HEARTBEAT shows OFFBOARD. Only then is the link :attr:`~OffboardLink.engaged` and
   :meth:`~OffboardLink.estimate` answers, so a planner starts from where PX4 holds, not from where
   the vehicle was a second earlier; the planner's samples replace the hold once they come;
5. no setpoint for ``stale_s``: hold (stream the last position, velocity and acceleration ignored),
   or switch PX4 to AUTO.LOITER / AUTO.LAND (``on_stop``); on :meth:`close`, loiter or land.

A companion computer knows where the vehicle is from PX4, not from the simulator: the planner plans,
checks arrival and judges tracking on :meth:`~OffboardLink.estimate` (PX4's local NED position and
velocity, through the origin into the ENU world), the frame PX4 flies its setpoints in.

Frames go through :mod:`droneulator.frames` only: positions, velocities and accelerations ENU world
-> NED, heading ENU (from +x/east, counter-clockwise) -> NED (from north, clockwise).
"""

from __future__ import annotations

import errno
import logging
import math
import queue
import socket
import threading
import time
from collections.abc import Callable, Collection
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from droneulator import frames
from droneulator.config import SiteConfig
from droneulator.px4.transport import pack_next

log = logging.getLogger("droneulator.plan.offboard")

#: PX4 custom main modes (``px4_custom_mode.h``) and AUTO sub modes
PX4_MAIN_MODE_AUTO = 4
PX4_MAIN_MODE_OFFBOARD = 6
PX4_SUB_MODE_AUTO_LOITER = 3
PX4_SUB_MODE_AUTO_LAND = 6
_MODE_NAMES = {
    (1, 0): "MANUAL",
    (2, 0): "ALTCTL",
    (3, 0): "POSCTL",
    (4, 1): "AUTO.READY",
    (4, 2): "AUTO.TAKEOFF",
    (4, 3): "AUTO.LOITER",
    (4, 4): "AUTO.MISSION",
    (4, 5): "AUTO.RTL",
    (4, 6): "AUTO.LAND",
    (5, 0): "ACRO",
    (6, 0): "OFFBOARD",
    (7, 0): "STABILIZED",
}

#: PX4 SITL sends every instance past this one to the same offboard port (``px4-rc.mavlink``)
LAST_OWN_PORT_INSTANCE = 9

#: use position, velocity, acceleration (not as force: PX4 drops force setpoints), yaw and yaw rate
TYPE_MASK_TRAJECTORY = 0
#: a hold: position and yaw only
TYPE_MASK_HOLD = (
    mavlink.POSITION_TARGET_TYPEMASK_VX_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_VY_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_VZ_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_AX_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_AY_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_AZ_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE
)


def px4_mode_name(custom_mode: int) -> str:
    """Readable PX4 mode of a HEARTBEAT ``custom_mode`` (main mode in bits 16-23, sub mode 24-31)."""
    main, sub = (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF
    return _MODE_NAMES.get((main, sub if main == PX4_MAIN_MODE_AUTO else 0), f"main {main} sub {sub}")


def offboard_port(instance: int, base_port: int = 14540) -> int:
    """The UDP port PX4 SITL instance ``instance`` sends its onboard MAVLink to: ``base_port + instance``,
    and ``base_port + 9`` (14549) for every instance past 9, as ``px4-rc.mavlink`` sets it."""
    return base_port + min(instance, LAST_OWN_PORT_INSTANCE)


def px4_system_id(instance: int) -> int:
    """PX4 SITL's ``MAV_SYS_ID`` of ``instance``: ``rcS`` sets ``MAV_SYS_ID $((px4_instance+1))``."""
    return instance + 1


def _result_name(result: int) -> str:
    entry = mavlink.enums["MAV_RESULT"].get(result)
    return entry.name if entry is not None else f"MAV_RESULT {result}"


class OffboardError(RuntimeError):
    """PX4 could not be put under offboard control (no PX4, a refused command, no origin)."""


@dataclass(frozen=True)
class Estimate:
    """PX4's own estimate of the vehicle, in the simulator's ENU world (through PX4's local origin)."""

    position: np.ndarray
    velocity: np.ndarray
    #: heading (rad from +x, counter-clockwise); None before PX4's first ATTITUDE
    yaw: float | None


@dataclass
class OffboardConfig:
    """Where PX4's offboard MAVLink is, and how the link behaves."""

    host: str = "127.0.0.1"
    #: PX4 instance N (``px4 -i N``) sends to UDP base_port + N, instances past 9 to base_port + 9
    instance: int = 0
    base_port: int = 14540
    #: the PX4 system followed on that port (``MAV_SYS_ID``); None: instance + 1, as PX4 SITL sets it
    system_id: int | None = None
    #: PX4 instance N's own offboard-link port is this + N (``udp_offboard_port_local``, 14580 + N)
    px4_local_base_port: int = 14580
    #: setpoints per wall second (PX4 needs > 2 Hz; MAVROS/MAVSDK examples stream 20-50 Hz)
    rate_hz: float = 50.0
    heartbeat_hz: float = 1.0
    #: "onboard": a companion computer (MAVROS-like); "gcs": MAVSDK's default ground-station identity
    identity: Literal["onboard", "gcs"] = "onboard"
    #: wait this long (wall) for PX4's first HEARTBEAT, then report that none came
    connect_timeout_s: float = 30.0
    #: nothing from PX4 for this long (wall): the link is reported lost. Any message of PX4's counts, not
    #: only its 1 Hz HEARTBEAT: in lockstep PX4 streams on simulated time, so below a third of real time
    #: its heartbeats come more than 3 s apart while its 30 Hz position still flows
    link_timeout_s: float = 3.0
    #: stream setpoints this long before asking for OFFBOARD
    prestream_s: float = 1.0
    ack_timeout_s: float = 1.0
    retries: int = 3
    #: no setpoint from the planner for this long (wall): on_stop applies
    stale_s: float = 0.5
    #: "hold": keep streaming the last position; "loiter"/"land": switch PX4 to AUTO.LOITER/AUTO.LAND
    on_stop: Literal["hold", "loiter", "land"] = "hold"
    #: ENU world position of PX4's local NED origin; None: from PX4's GPS_GLOBAL_ORIGIN and the home
    origin_enu: tuple[float, float, float] | None = None
    #: geodetic point of the simulator's world origin (the run's ``site.latitude_deg``, ``longitude_deg``,
    #: ``altitude_m``)
    home_lat_deg: float = SiteConfig.latitude_deg
    home_lon_deg: float = SiteConfig.longitude_deg
    home_alt_m: float = SiteConfig.altitude_m
    origin_timeout_s: float = 10.0

    def __post_init__(self) -> None:
        if not 0 <= self.instance <= 254 or not 0 <= self.port <= 65535:
            raise ValueError("instance (0 to 254) and base_port must give a UDP port in [0, 65535]")
        if not 1 <= self.px4_sysid <= 255:
            raise ValueError(f"system_id must be in [1, 255], got {self.system_id}")
        if not self.rate_hz > 2.0:
            raise ValueError(f"rate_hz must exceed 2 Hz (PX4's offboard minimum), got {self.rate_hz}")
        positive = (
            "heartbeat_hz",
            "connect_timeout_s",
            "link_timeout_s",
            "ack_timeout_s",
            "stale_s",
            "origin_timeout_s",
        )
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if self.prestream_s < 0 or self.retries < 1:
            raise ValueError("prestream_s must be >= 0 and retries >= 1")
        if self.identity not in ("onboard", "gcs"):
            raise ValueError(f"identity must be 'onboard' or 'gcs', got {self.identity!r}")
        if self.on_stop not in ("hold", "loiter", "land"):
            raise ValueError(f"on_stop must be 'hold', 'loiter' or 'land', got {self.on_stop!r}")
        if self.origin_enu is not None:
            o = np.asarray(self.origin_enu, dtype=float)
            if o.shape != (3,) or not np.all(np.isfinite(o)):
                raise ValueError(f"origin_enu must be three finite numbers, got {self.origin_enu}")

    @property
    def port(self) -> int:
        """The UDP port bound: where PX4 instance ``instance`` sends (:func:`offboard_port`)."""
        return offboard_port(self.instance, self.base_port)

    @property
    def px4_sysid(self) -> int:
        """The system id of the PX4 followed: ``system_id``, or PX4 SITL's for the instance."""
        return px4_system_id(self.instance) if self.system_id is None else self.system_id


@dataclass
class _Sample:
    t: float
    p: np.ndarray
    v: np.ndarray
    a: np.ndarray
    yaw: float
    yaw_rate: float
    wall: float


class OffboardLink:
    """Fly PX4 in OFFBOARD from planner setpoints (ENU world); pass :meth:`setpoint` as the node's sink.

    Three threads: one reads PX4's messages, one sends our HEARTBEAT and the setpoint stream, one
    engages (origin, OFFBOARD, arm) and then applies ``on_stop``. Failures are logged and kept in
    :attr:`error`; :attr:`engaged` is set once PX4 acknowledged OFFBOARD and arming.
    """

    def __init__(self, config: OffboardConfig | None = None) -> None:
        self.cfg = c = config or OffboardConfig()
        #: PX4's own port, told who we are when the shared port is another link's (see :meth:`_bind`)
        self.announce_to: tuple[str, int] | None = None
        self._sock = self._bind()
        self._sock.settimeout(0.05)
        #: the bound (host, port); with base_port 0 the OS chose the port
        self.address: tuple[str, int] = self._sock.getsockname()
        self._mav = mavlink.MAVLink(None)
        self._mav.robust_parsing = True
        if c.identity == "gcs":
            self._mav.srcSystem, self._mav.srcComponent = 245, mavlink.MAV_COMP_ID_MISSIONPLANNER
        else:
            self._mav.srcSystem, self._mav.srcComponent = c.px4_sysid, mavlink.MAV_COMP_ID_ONBOARD_COMPUTER
        self._lock = threading.Condition()
        self._send_lock = threading.Lock()
        self._stop = threading.Event()
        self._peer: tuple[str, int] | None = self.announce_to
        self._last_heard: float | None = None
        self._lost = False
        self.sysid: int | None = None
        self.compid: int | None = None
        #: system ids of other PX4s heard on the port (instances past 9 share 14549)
        self.other_systems: set[int] = set()
        self.custom_mode = 0
        self.armed = False
        self.origin_enu: np.ndarray | None = None if c.origin_enu is None else np.asarray(c.origin_enu, float)
        self._acks: dict[int, int] = {}
        #: the planner's latest sample
        self._sample: _Sample | None = None
        #: what is streamed while holding (PX4's position when asked for control, later the last sample)
        self._hold: _Sample | None = None
        self._holding = True
        self._streaming = False
        self._want = threading.Event()
        #: PX4's LOCAL_POSITION_NED: (monotonic time received, position NED, velocity NED), and its yaw (NED)
        self._local: tuple[float, np.ndarray, np.ndarray] | None = None
        self._yaw_ned: float | None = None
        #: monotonic time the link was engaged; planner samples older than it are not streamed
        self._engaged_at = math.inf
        #: PX4's heartbeat showed OFFBOARD since PX4 last accepted a mode from us
        self._seen_offboard = False
        self.engaged = threading.Event()
        self.error: str | None = None
        self.setpoints_sent = 0
        #: (message kinds, queue) of :meth:`tap`: PX4's messages of those kinds are put on the queue
        self._taps: list[tuple[frozenset[str], queue.Queue[Any]]] = []
        self._threads = [
            threading.Thread(target=self._rx_loop, name="offboard_rx", daemon=True),
            threading.Thread(target=self._tx_loop, name="offboard_tx", daemon=True),
            threading.Thread(target=self._control, name="offboard_control", daemon=True),
        ]
        for th in self._threads:
            th.start()
        log.info("offboard link on udp %s:%d, waiting for PX4 system %d (instance %d)", *self.address,
                 c.px4_sysid, c.instance)  # fmt: skip

    def _bind(self) -> socket.socket:
        """The UDP socket on ``cfg.port``. Where that port is shared (instance 9 and up: 14549) and another
        link holds it, an OS-chosen port instead, announced to PX4's own port (``px4_local_base_port``
        + instance): PX4 SITL's UDP MAVLink on localhost takes the first sender as its partner and sends
        to it from then on (``MavlinkReceiver``), so every instance past 9 can have its own link."""
        c = self.cfg
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.bind((c.host, c.port))
            return sock
        except OSError as exc:
            if exc.errno != errno.EADDRINUSE or c.instance < LAST_OWN_PORT_INSTANCE:
                sock.close()
                why = f"cannot bind UDP {c.host}:{c.port} for PX4's offboard link: {exc}"
                raise OffboardError(why) from exc
        sock.bind((c.host, 0))
        px4_host = "127.0.0.1" if c.host in ("", "0.0.0.0") else c.host
        self.announce_to = (px4_host, c.px4_local_base_port + c.instance)
        log.info(
            "UDP %s:%d, which PX4 instances 9 and up share, is another link's: bound %d and announcing "
            "this one to PX4 instance %d at %s:%d",
            c.host,
            c.port,
            sock.getsockname()[1],
            c.instance,
            *self.announce_to,
        )
        return sock

    # ------------------------------------------------------------------ public
    @property
    def connected(self) -> bool:
        """PX4 was heard (its first HEARTBEAT, then any message) within ``link_timeout_s``."""
        with self._lock:
            return self._last_heard is not None and not self._lost

    @property
    def mode(self) -> str:
        """PX4's flight mode from its last HEARTBEAT."""
        return px4_mode_name(self.custom_mode)

    def engage(self) -> None:
        """Take control of PX4 (step 4 of the module docstring); idempotent. The first setpoint does too."""
        self._want.set()

    def estimate(self) -> Estimate | None:
        """PX4's estimate in the ENU world once the link is engaged (PX4 in OFFBOARD holding where it
        was, or flying our setpoints); None before that, or when PX4's LOCAL_POSITION_NED is older
        than ``link_timeout_s``."""
        with self._lock:
            local, yaw_ned, origin = self._local, self._yaw_ned, self.origin_enu
        if not self.engaged.is_set() or local is None or origin is None:
            return None
        received, p_ned, v_ned = local
        if time.monotonic() - received > self.cfg.link_timeout_s:
            return None
        yaw = None if yaw_ned is None else frames.yaw_ned_to_enu(yaw_ned)
        return Estimate(origin + frames.ned_to_enu(p_ned), frames.ned_to_enu(v_ned), yaw)

    def setpoint(
        self, t: float, p: np.ndarray, v: np.ndarray, a: np.ndarray, yaw: float, yaw_rate: float
    ) -> None:
        """The planner's sample at sim time ``t`` (s): ENU world position, velocity, acceleration,
        heading (rad from +x, counter-clockwise) and its rate. Streamed from the next tick once the link
        is engaged; asks for control (:meth:`engage`) if nothing did."""
        vecs = [np.asarray(x, dtype=float).reshape(-1) for x in (p, v, a)]
        if any(x.shape != (3,) or not np.all(np.isfinite(x)) for x in vecs):
            raise ValueError(f"setpoint needs finite 3-vectors p, v, a; got {p}, {v}, {a}")
        if not (math.isfinite(t) and math.isfinite(yaw) and math.isfinite(yaw_rate)):
            raise ValueError(f"setpoint needs finite t, yaw and yaw_rate; got {t}, {yaw}, {yaw_rate}")
        with self._lock:
            self._sample = _Sample(float(t), *vecs, float(yaw), float(yaw_rate), time.monotonic())
            self._lock.notify_all()
        self._want.set()

    def tap(self, kinds: Collection[str]) -> queue.Queue[Any]:
        """A queue that gets every message of ``kinds`` PX4 (the system followed) sends from now on: for a
        protocol beside offboard control, such as the mission upload (:class:`MavlinkPort`)."""
        q: queue.Queue[Any] = queue.Queue()
        with self._lock:
            self._taps.append((frozenset(kinds), q))
        return q

    def send(self, msg: Any) -> None:
        """Send one MAVLink message to PX4 (packed with this link's identity; dropped before PX4's first
        HEARTBEAT)."""
        self._send(msg)

    def command(self, command: int, name: str, *params: float) -> int | None:
        """COMMAND_LONG ``command`` (``name`` for the logs) until PX4 acknowledges it: its MAV_RESULT, or
        None after ``retries`` tries without an answer."""
        return self._command(command, name, *params)

    @property
    def encoder(self) -> mavlink.MAVLink:
        """This link's MAVLink codec (its source system and component), to build messages for :meth:`send`."""
        return self._mav

    def local_ned(self, p_enu: np.ndarray) -> np.ndarray:
        """An ENU world point in PX4's local NED frame (needs the origin)."""
        if self.origin_enu is None:
            raise OffboardError("PX4's local origin is not known yet")
        return frames.enu_to_ned(np.asarray(p_enu, dtype=float) - self.origin_enu)

    def close(self) -> None:
        """Leave OFFBOARD (AUTO.LAND with ``on_stop`` "land", else AUTO.LOITER) and stop the threads."""
        if self._stop.is_set():
            return
        if self.engaged.is_set() and self.connected:
            if self.cfg.on_stop == "land":
                self._set_mode(PX4_MAIN_MODE_AUTO, PX4_SUB_MODE_AUTO_LAND, "AUTO.LAND", fatal=False)
            else:
                self._set_mode(PX4_MAIN_MODE_AUTO, PX4_SUB_MODE_AUTO_LOITER, "AUTO.LOITER", fatal=False)
        self._stop.set()
        with self._lock:
            self._lock.notify_all()
        for th in self._threads:
            th.join(timeout=5)
        self._sock.close()

    def __enter__(self) -> OffboardLink:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ receive
    def _rx_loop(self) -> None:
        while not self._stop.is_set():
            try:
                data, addr = self._sock.recvfrom(65535)
            except TimeoutError:
                continue
            except OSError:
                return
            try:
                msgs = self._mav.parse_buffer(data) or []
            except mavlink.MAVError as exc:
                log.error("bad MAVLink from %s:%d dropped: %s", *addr, exc)
                continue
            for msg in msgs:
                if isinstance(msg, mavlink.MAVLink_bad_data):
                    log.error("bad MAVLink from %s:%d dropped: %s", *addr, msg.reason)
                else:
                    self._handle(msg, addr)

    def _handle(self, msg: Any, addr: tuple[str, int]) -> None:
        kind = msg.get_type()
        if self._taps and self.sysid is not None and msg.get_srcSystem() == self.sysid:
            for kinds, q in self._taps:
                if kind in kinds:
                    q.put(msg)
        if kind == "HEARTBEAT" and msg.autopilot == mavlink.MAV_AUTOPILOT_PX4:
            src = msg.get_srcSystem()
            if src != self.cfg.px4_sysid:
                self._other_px4(src, addr)
                return
            with self._lock:
                first = self.sysid is None
                if first:
                    self.sysid, self.compid = src, msg.get_srcComponent()
                self._peer = addr
                self._last_heard = time.monotonic()
                back, self._lost = self._lost, False
                old_mode = self.custom_mode
                self.custom_mode = msg.custom_mode
                if (msg.custom_mode >> 16) & 0xFF == PX4_MAIN_MODE_OFFBOARD:
                    self._seen_offboard = True
                self.armed = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
                self._lock.notify_all()
            if first:
                log.info(
                    "PX4 found: system %d component %d at %s:%d, mode %s",
                    self.sysid,
                    self.compid,
                    *addr,
                    self.mode,
                )
            elif back:
                log.info("PX4 is back (mode %s)", self.mode)
            if old_mode != msg.custom_mode and self.engaged.is_set() and not first:
                log.info("PX4 mode %s -> %s", px4_mode_name(old_mode), self.mode)
        elif self.sysid is None or msg.get_srcSystem() != self.sysid:
            return
        else:
            with self._lock:
                self._last_heard = time.monotonic()
                back, self._lost = self._lost, False
            if back:
                log.info("PX4 is back (mode %s)", self.mode)
        if kind == "COMMAND_ACK":
            with self._lock:
                self._acks[msg.command] = msg.result
                self._lock.notify_all()
        elif kind == "LOCAL_POSITION_NED":
            local = (time.monotonic(), np.array([msg.x, msg.y, msg.z]), np.array([msg.vx, msg.vy, msg.vz]))
            with self._lock:
                self._local = local
                self._lock.notify_all()
        elif kind == "ATTITUDE":
            with self._lock:
                self._yaw_ned = float(msg.yaw)
        elif kind == "GPS_GLOBAL_ORIGIN" and self.cfg.origin_enu is None:
            origin = frames.geodetic_to_enu(
                msg.latitude * 1e-7,
                msg.longitude * 1e-7,
                msg.altitude * 1e-3,
                self.cfg.home_lat_deg,
                self.cfg.home_lon_deg,
                self.cfg.home_alt_m,
            )
            with self._lock:
                new = self.origin_enu is None or not np.allclose(origin, self.origin_enu, atol=1e-3)
                self.origin_enu = origin
                self._lock.notify_all()
            if new:
                log.info("PX4's local origin (EKF2) is at ENU world %s", origin.round(3))
        elif kind == "STATUSTEXT" and msg.severity <= mavlink.MAV_SEVERITY_WARNING:
            log.warning("PX4: %s", msg.text)

    def _other_px4(self, sysid: int, addr: tuple[str, int]) -> None:
        """A PX4 that is not ours sends to this port (PX4 SITL sends every instance past 9 to one
        port): noted once and ignored."""
        with self._lock:
            if sysid in self.other_systems:
                return
            self.other_systems.add(sysid)
        log.info(
            "PX4 system %d at %s:%d sends to this port too: ignored (following system %d, instance %d)",
            sysid,
            *addr,
            self.cfg.px4_sysid,
            self.cfg.instance,
        )

    # ------------------------------------------------------------------ send
    def _send(self, msg: Any) -> None:
        with self._send_lock:
            data = pack_next(self._mav, msg)
        self.send_bytes(data)

    def send_bytes(self, data: bytes) -> None:
        """Send an already packed MAVLink message to PX4 (dropped before PX4's first HEARTBEAT)."""
        with self._lock:
            peer = self._peer
        if peer is None:
            return
        try:
            with self._send_lock:
                self._sock.sendto(data, peer)
        except OSError as exc:
            if not self._stop.is_set():
                log.error("send to PX4 at %s:%d failed: %s", *peer, exc)

    def _heartbeat(self) -> Any:
        kind = mavlink.MAV_TYPE_GCS if self.cfg.identity == "gcs" else mavlink.MAV_TYPE_ONBOARD_CONTROLLER
        return self._mav.heartbeat_encode(kind, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE)

    def _setpoint_message(self, s: _Sample, hold: bool) -> Any:
        """SET_POSITION_TARGET_LOCAL_NED of a sample (NED about PX4's origin)."""
        p = self.local_ned(s.p)
        if hold:
            v = a = np.zeros(3)
            mask, yaw_rate = TYPE_MASK_HOLD, 0.0
        else:
            v, a = frames.enu_to_ned(s.v), frames.enu_to_ned(s.a)
            mask, yaw_rate = TYPE_MASK_TRAJECTORY, frames.yaw_rate_enu_to_ned(s.yaw_rate)
        return self._mav.set_position_target_local_ned_encode(
            int(round(s.t * 1000.0)) % 2**32,
            self.sysid,
            self.compid,
            mavlink.MAV_FRAME_LOCAL_NED,
            mask,
            *(float(x) for x in p),
            *(float(x) for x in v),
            *(float(x) for x in a),
            frames.yaw_enu_to_ned(s.yaw),
            yaw_rate,
        )

    def _tx_loop(self) -> None:
        next_hb = next_sp = time.monotonic()
        while not self._stop.is_set():
            now = time.monotonic()
            with self._lock:
                sysid, last_heard = self.sysid, self._last_heard
                streaming, holding = self._streaming, self._holding
                sample = self._hold if holding else self._sample
                if last_heard is not None and not self._lost and now - last_heard > self.cfg.link_timeout_s:
                    self._lost = True
                    lost_now = True
                else:
                    lost_now = False
            if lost_now:
                log.error(
                    "PX4 silent for %.1f s on udp %s:%d: offboard link lost (setpoints go nowhere; "
                    "PX4's own offboard-loss failsafe applies)",
                    self.cfg.link_timeout_s,
                    *self.address,
                )
            if (sysid is not None or self.announce_to is not None) and now >= next_hb:
                self._send(self._heartbeat())
                next_hb = now + 1.0 / self.cfg.heartbeat_hz
            if sysid is not None and streaming and sample is not None and now >= next_sp:
                self._send(self._setpoint_message(sample, holding))
                self.setpoints_sent += 1
                next_sp = max(next_sp + 1.0 / self.cfg.rate_hz, now)
            time.sleep(min(0.005, 1.0 / self.cfg.rate_hz / 4))

    # ------------------------------------------------------------------ commands
    def _command(self, command: int, name: str, *params: float) -> int | None:
        """COMMAND_LONG until PX4 acknowledges it (``retries`` tries); its MAV_RESULT, or None."""
        p = list(params) + [0.0] * (7 - len(params))
        for attempt in range(self.cfg.retries):
            with self._lock:
                self._acks.pop(command, None)
            self._send(self._mav.command_long_encode(self.sysid, self.compid, command, attempt, *p))
            deadline = time.monotonic() + self.cfg.ack_timeout_s
            with self._lock:
                while not self._stop.is_set():
                    result = self._acks.get(command)
                    if result == mavlink.MAV_RESULT_IN_PROGRESS:
                        self._acks.pop(command)
                        deadline = time.monotonic() + self.cfg.ack_timeout_s
                    elif result is not None:
                        return result
                    left = deadline - time.monotonic()
                    if left <= 0:
                        break
                    self._lock.wait(left)
            if self._stop.is_set():
                return None
            log.warning("no COMMAND_ACK for %s (try %d of %d)", name, attempt + 1, self.cfg.retries)
        return None

    def _set_mode(self, main: int, sub: int, name: str, fatal: bool = True) -> bool:
        result = self._command(
            mavlink.MAV_CMD_DO_SET_MODE,
            f"set mode {name}",
            mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
            main,
            sub,
        )
        if result == mavlink.MAV_RESULT_ACCEPTED:
            with self._lock:
                self._seen_offboard = False
            log.info("PX4 accepted mode %s", name)
            return True
        why = "no COMMAND_ACK" if result is None else _result_name(result)
        msg = f"PX4 refused mode {name}: {why}"
        if fatal:
            self._fail(msg)
        else:
            log.error(msg)
        return False

    def _fail(self, msg: str) -> None:
        log.error("offboard: %s", msg)  # logged before it is published: a reader of .error sees the line too
        self.error = msg

    def _wait(self, pred: Callable[[], bool], timeout: float | None) -> bool:
        """Wait (lock held by the caller's ``with``) until ``pred()``, the timeout or close."""
        end = None if timeout is None else time.monotonic() + timeout
        while not pred():
            if self._stop.is_set():
                return False
            left = 0.1 if end is None else min(0.1, end - time.monotonic())
            if left <= 0:
                return False
            self._lock.wait(left)
        return True

    # ------------------------------------------------------------------ engage and supervise
    def _control(self) -> None:
        c = self.cfg
        with self._lock:
            if not self._wait(lambda: self.sysid is not None, c.connect_timeout_s):
                if not self._stop.is_set():
                    others = ""
                    if self.other_systems:
                        heard = ", ".join(map(str, sorted(self.other_systems)))
                        others = f" (heard PX4 system {heard}: another MAV_SYS_ID? see system_id)"
                    self._fail(
                        f"no HEARTBEAT from PX4 on udp {self.address[0]}:{self.address[1]} within "
                        f"{c.connect_timeout_s:.0f} s: is PX4 SITL instance {c.instance} (system "
                        f"{c.px4_sysid}) running?{others}"
                    )
                return
        if self.origin_enu is None and not self._learn_origin():
            return
        while not self._want.wait(0.1):
            if self._stop.is_set():
                return

        def fresh() -> bool:
            return self._local is not None and time.monotonic() - self._local[0] < c.link_timeout_s

        with self._lock:
            if not self._wait(fresh, c.origin_timeout_s):
                if not self._stop.is_set():
                    self._fail(
                        f"PX4 sent no LOCAL_POSITION_NED within {c.origin_timeout_s:.0f} s (no position "
                        "estimate yet, or its onboard MAVLink streams are off): not taking control"
                    )
                return
            _, p_ned, _ = self._local
            yaw_ned = 0.0 if self._yaw_ned is None else self._yaw_ned
            p = self.origin_enu + frames.ned_to_enu(p_ned)
            self._hold = _Sample(0.0, p, np.zeros(3), np.zeros(3), frames.yaw_ned_to_enu(yaw_ned), 0.0,
                                 time.monotonic())  # fmt: skip
            self._holding = self._streaming = True
        log.info("streaming a hold at PX4's position %s (ENU world) at %.0f Hz; OFFBOARD in %.1f s",
                 p.round(2), c.rate_hz, c.prestream_s)  # fmt: skip
        if self._stop.wait(c.prestream_s):
            return
        if not self._set_mode(PX4_MAIN_MODE_OFFBOARD, 0, "OFFBOARD"):
            return
        if self.armed:
            log.info("PX4 is already armed (took off before): not arming again")
            result = mavlink.MAV_RESULT_ACCEPTED
        else:
            result = self._command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, "arm", 1.0)
        if result != mavlink.MAV_RESULT_ACCEPTED:
            if not self._stop.is_set():
                why = "no COMMAND_ACK" if result is None else _result_name(result)
                self._fail(f"PX4 refused to arm: {why} (see PX4's console for the failed preflight check)")
            return
        shown = max(3.0, 2.0 * c.link_timeout_s)  # PX4's heartbeat is 1 Hz
        with self._lock:
            if not self._wait(lambda: self._seen_offboard, shown):
                if not self._stop.is_set():
                    self._fail(f"PX4 accepted OFFBOARD; its HEARTBEAT did not show it within {shown:.0f} s")
                return
            self._engaged_at = time.monotonic()
        log.info("PX4 is in OFFBOARD and armed, holding at %s: flying the planner's setpoints from here",
                 p.round(2))  # fmt: skip
        self.engaged.set()
        self._supervise()

    def _learn_origin(self) -> bool:
        """Ask for GPS_GLOBAL_ORIGIN (once a second) until it arrives or ``origin_timeout_s`` passes."""
        end = time.monotonic() + self.cfg.origin_timeout_s
        while time.monotonic() < end and not self._stop.is_set():
            self._send(
                self._mav.command_long_encode(
                    self.sysid,
                    self.compid,
                    mavlink.MAV_CMD_REQUEST_MESSAGE,
                    0,
                    mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN,
                    0,
                    0,
                    0,
                    0,
                    0,
                    0,
                )
            )
            with self._lock:
                if self._wait(
                    lambda: self.origin_enu is not None, min(1.0, max(0.0, end - time.monotonic()))
                ):
                    return True
        if not self._stop.is_set():
            self._fail(
                f"PX4 sent no GPS_GLOBAL_ORIGIN within {self.cfg.origin_timeout_s:.0f} s (EKF2 without "
                "a GPS fix yet?); give the origin explicitly (--px4-origin) to fly without it"
            )
        return False

    def _supervise(self) -> None:
        """Follow the planner once it sends, apply ``on_stop`` while it is silent, and note when PX4
        leaves OFFBOARD."""
        c = self.cfg
        left_offboard = False
        while not self._stop.wait(0.02):
            with self._lock:
                sample, holding = self._sample, self._holding
                mode, seen_offboard = self.custom_mode, self._seen_offboard
            if sample is not None and sample.wall < self._engaged_at:
                sample = None  # sent before PX4 held where it is: not a plan from here
            stale = sample is None or time.monotonic() - sample.wall > c.stale_s
            main = (mode >> 16) & 0xFF
            if seen_offboard and main != PX4_MAIN_MODE_OFFBOARD and not holding and not left_offboard:
                log.warning("PX4 left OFFBOARD for %s: not taking it back", px4_mode_name(mode))
                left_offboard = True
            if stale and not holding:
                with self._lock:
                    self._holding, self._hold = True, sample
                if c.on_stop == "hold":
                    log.warning(
                        "no setpoint for %.1f s: holding at the last position %s",
                        c.stale_s,
                        sample.p.round(2),
                    )
                else:
                    name = "AUTO.LAND" if c.on_stop == "land" else "AUTO.LOITER"
                    sub = PX4_SUB_MODE_AUTO_LAND if c.on_stop == "land" else PX4_SUB_MODE_AUTO_LOITER
                    log.warning("no setpoint for %.1f s: switching PX4 to %s", c.stale_s, name)
                    with self._lock:
                        self._streaming = False
                    self._set_mode(PX4_MAIN_MODE_AUTO, sub, name, fatal=False)
            elif not stale and holding:
                followed = self._hold is not None and self._hold.wall >= self._engaged_at
                with self._lock:
                    self._holding = False
                    self._streaming = True
                if not followed:
                    log.info("the planner's first setpoint: following it")
                elif c.on_stop == "hold":
                    log.info("setpoints are back: following the planner again")
                elif c.on_stop == "loiter" and not left_offboard:
                    log.info("setpoints are back: asking for OFFBOARD again")
                    if self._stop.wait(c.prestream_s):
                        return
                    self._set_mode(PX4_MAIN_MODE_OFFBOARD, 0, "OFFBOARD", fatal=False)
                else:
                    with self._lock:
                        self._streaming = False
                    log.info("setpoints are back, but PX4 was sent to land: not taking control again")
                    return


class _LinkCodec:
    """``mav`` of a :class:`MavlinkPort`: the link's own codec (``*_encode``, ``srcSystem``), whose ``send``
    packs and sends through the link. One codec, one sequence: PX4 counts the gaps between a sender's
    MAVLink sequence numbers as lost messages (MavlinkReceiver::updateRxStats), and a second codec for
    the same system and component would show as loss on every message."""

    def __init__(self, link: OffboardLink) -> None:
        self._link = link

    def send(self, msg: Any) -> None:
        self._link.send(msg)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._link.encoder, name)


class MavlinkPort:
    """What a pymavlink connection offers a protocol that sends and waits for answers (``mav.send``,
    ``recv_match``), over an :class:`OffboardLink`'s socket: so the mission upload
    (:func:`droneulator.workflows.spraying.px4_mission.upload_mission`) runs beside the link without a
    second MAVLink client on PX4's port."""

    def __init__(self, link: OffboardLink, kinds: Collection[str]) -> None:
        self._link = link
        self._queue = link.tap(kinds)
        self.mav = _LinkCodec(link)

    def recv_match(self, type: Collection[str] | str | None = None, blocking: bool = False,
                   timeout: float | None = None) -> Any:  # fmt: skip
        """The next tapped message of ``type`` (None: any), waiting up to ``timeout`` s when ``blocking``;
        None when none came."""
        kinds = {type} if isinstance(type, str) else (None if type is None else set(type))
        end = time.monotonic() + (timeout if timeout is not None else 1e9)
        while True:
            left = end - time.monotonic()
            try:
                msg = self._queue.get(timeout=left) if blocking and left > 0 else self._queue.get_nowait()
            except queue.Empty:
                return None
            if kinds is None or msg.get_type() in kinds:
                return msg
