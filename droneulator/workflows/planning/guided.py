"""ArduCopter GUIDED control over MAVLink: the planner's setpoints as ``SET_POSITION_TARGET_LOCAL_NED``.

ArduCopter SITL serves MAVLink on TCP ``5760 + 10 N`` (``--serial0 tcp:0``, instance N).
:class:`GuidedLink` is the planner's autopilot there (the :class:`~droneulator.workflows.planning.node.
Autopilot` protocol, as :class:`~droneulator.workflows.planning.offboard.OffboardLink` is for PX4), with
pymavlink's codec on a plain TCP socket:

1. connect, wait for ArduCopter's HEARTBEAT (``MAV_AUTOPILOT_ARDUPILOTMEGA``; its system and component
   become the target), send our own (a companion computer) at 1 Hz and ask for LOCAL_POSITION_NED and
   ATTITUDE at ``stream_hz`` (``MAV_CMD_SET_MESSAGE_INTERVAL``);
2. learn the EKF's local origin: ``GPS_GLOBAL_ORIGIN`` (``MAV_CMD_REQUEST_MESSAGE``) is the geodetic
   point of LOCAL_POSITION_NED's (0, 0, 0); with the simulator's home (the ``site`` section) it is a
   point of the ENU world (``frames.geodetic_to_enu``);
3. when asked for control (:meth:`GuidedLink.engage`, or the first setpoint): GUIDED
   (``MAV_CMD_DO_SET_MODE``, custom mode 4), then, if disarmed, arm and take off to ``takeoff_alt_m``
   (``MAV_CMD_NAV_TAKEOFF``: ArduCopter ignores position targets while landed), each checked against
   its COMMAND_ACK, and wait until it is up; then the link is :attr:`~GuidedLink.engaged` and streams a
   hold where ArduCopter is until the planner's samples come;
4. stream the newest sample at ``rate_hz`` (position, velocity and acceleration feed-forward, yaw);
   no sample for ``stale_s``: hold the last position; on :meth:`close`, ``on_stop``: stay in GUIDED
   holding (``hold``), LOITER or LAND.

The planner plans on :meth:`~GuidedLink.estimate`, ArduCopter's EKF (LOCAL_POSITION_NED through the
origin into the ENU world). Frames go through :mod:`droneulator.frames` only.
"""

from __future__ import annotations

import contextlib
import logging
import math
import socket
import threading
import time
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from droneulator import frames
from droneulator.config import SiteConfig
from droneulator.px4.transport import pack_next
from droneulator.workflows.planning.offboard import Estimate

log = logging.getLogger("droneulator.plan.guided")

#: ArduCopter flight modes (``Copter::Mode::Number``)
COPTER_MODES = {"STABILIZE": 0, "GUIDED": 4, "LOITER": 5, "RTL": 6, "LAND": 9}
#: SET_POSITION_TARGET_LOCAL_NED type_mask bits: ignore yaw rate; ignore velocity and acceleration too
IGNORE_YAW_RATE = 2048
IGNORE_VEL_ACC = 8 | 16 | 32 | 64 | 128 | 256


@dataclass
class GuidedConfig:
    """Where ArduCopter's MAVLink is, and how the link behaves."""

    host: str = "127.0.0.1"
    #: ArduCopter instance N (``-I N``) serves MAVLink on TCP base_port + 10 N
    instance: int = 0
    base_port: int = 5760
    #: setpoints per wall second
    rate_hz: float = 20.0
    #: LOCAL_POSITION_NED and ATTITUDE asked for at this rate
    stream_hz: float = 20.0
    connect_timeout_s: float = 30.0
    #: no HEARTBEAT for this long: the link is reported lost
    link_timeout_s: float = 3.0
    ack_timeout_s: float = 2.0
    retries: int = 3
    #: take off to this height (m above the EKF origin) when engaged on the ground
    takeoff_alt_m: float = 2.0
    #: wall s to reach the take-off height
    takeoff_timeout_s: float = 60.0
    #: no setpoint from the planner for this long (wall): hold the last position
    stale_s: float = 0.5
    on_stop: Literal["hold", "loiter", "land"] = "hold"
    #: ENU world position of the EKF's local origin; None: from GPS_GLOBAL_ORIGIN and the home
    origin_enu: tuple[float, float, float] | None = None
    home_lat_deg: float = SiteConfig.latitude_deg
    home_lon_deg: float = SiteConfig.longitude_deg
    home_alt_m: float = SiteConfig.altitude_m

    def __post_init__(self) -> None:
        if not 0 <= self.instance <= 255 or not 0 < self.port <= 65535:
            raise ValueError("instance and base_port must give a TCP port in [1, 65535]")
        for name in ("rate_hz", "stream_hz", "connect_timeout_s", "link_timeout_s", "ack_timeout_s",
                     "takeoff_alt_m", "takeoff_timeout_s", "stale_s"):  # fmt: skip
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if self.on_stop not in ("hold", "loiter", "land"):
            raise ValueError(f"on_stop must be 'hold', 'loiter' or 'land', got {self.on_stop!r}")

    @property
    def port(self) -> int:
        return self.base_port + 10 * self.instance


class GuidedLink:
    """Fly ArduCopter in GUIDED from planner setpoints (ENU world): the planner's autopilot."""

    def __init__(self, config: GuidedConfig | None = None) -> None:
        self.cfg = cfg = config or GuidedConfig()
        self._sock = socket.create_connection((cfg.host, cfg.port), timeout=cfg.connect_timeout_s)
        self._sock.settimeout(0.2)
        self._mav = mavlink.MAVLink(None, 255, mavlink.MAV_COMP_ID_ONBOARD_COMPUTER)
        self._rx = mavlink.MAVLink(None)
        self._rx.robust_parsing = True
        self._send_lock = threading.Lock()
        self._lock = threading.Condition()
        self.origin_enu = None if cfg.origin_enu is None else np.asarray(cfg.origin_enu, dtype=float)
        self._target: tuple[int, int] | None = None
        self._beat = 0.0
        self._custom_mode = -1
        self._armed = False
        self._local: tuple[float, np.ndarray, np.ndarray] | None = None
        self._yaw_ned: float | None = None
        self._acks: dict[int, int] = {}
        self._origin_geo: tuple[float, float, float] | None = None
        self._sample: tuple[float, np.ndarray, np.ndarray, np.ndarray, float] | None = None
        self._hold: tuple[np.ndarray, float] | None = None
        self.engaged = threading.Event()
        self.failed: str | None = None
        self._want = threading.Event()
        self._closing = threading.Event()
        self._threads = [
            threading.Thread(target=self._rx_loop, name="guided-rx", daemon=True),
            threading.Thread(target=self._tx_loop, name="guided-tx", daemon=True),
            threading.Thread(target=self._control, name="guided-control", daemon=True),
        ]
        for t in self._threads:
            t.start()

    # ------------------------------------------------------------------ the Autopilot protocol
    def engage(self) -> None:
        """Take control (step 3 of the module docstring); idempotent. The first setpoint does too."""
        self._want.set()

    def estimate(self) -> Estimate | None:
        """ArduCopter's EKF in the ENU world once engaged; None before that or when it is stale."""
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
        """The planner's sample (ENU world position, velocity, acceleration, heading from +x
        counter-clockwise); streamed once engaged. ``t`` and ``yaw_rate`` are not sent."""
        vecs = [np.asarray(x, dtype=float).reshape(-1) for x in (p, v, a)]
        if any(x.shape != (3,) or not np.all(np.isfinite(x)) for x in vecs) or not math.isfinite(yaw):
            raise ValueError(
                f"setpoint needs finite 3-vectors p, v, a and a finite yaw; got {p}, {v}, {a}, {yaw}"
            )
        with self._lock:
            self._sample = (time.monotonic(), *vecs, float(yaw))
        self._want.set()

    @property
    def mode(self) -> str:
        names = {v: k for k, v in COPTER_MODES.items()}
        return names.get(self._custom_mode, str(self._custom_mode))

    @property
    def connected(self) -> bool:
        return time.monotonic() - self._beat < self.cfg.link_timeout_s

    def close(self) -> None:
        """Apply ``on_stop`` and close the connection."""
        if self.engaged.is_set() and self.cfg.on_stop != "hold":
            self._set_mode(self.cfg.on_stop.upper())
        self._closing.set()
        for t in self._threads:
            t.join(2.0)
        with contextlib.suppress(OSError):
            self._sock.close()

    def __enter__(self) -> GuidedLink:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ receiving
    def _rx_loop(self) -> None:
        while not self._closing.is_set():
            try:
                data = self._sock.recv(65536)
            except TimeoutError:
                continue
            except OSError:
                return
            if not data:
                self.failed = self.failed or "ArduCopter closed the MAVLink connection"
                return
            for msg in self._rx.parse_buffer(data) or []:
                self._handle(msg)

    def _handle(self, msg: Any) -> None:
        kind = msg.get_type()
        with self._lock:
            if kind == "HEARTBEAT" and msg.autopilot == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA:
                if self._target is None:
                    self._target = (msg.get_srcSystem(), msg.get_srcComponent())
                    log.info(
                        "ArduCopter system %d on tcp://%s:%d", self._target[0], self.cfg.host, self.cfg.port
                    )
                self._beat = time.monotonic()
                self._custom_mode = msg.custom_mode
                self._armed = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
            elif kind == "LOCAL_POSITION_NED":
                p, v = np.array([msg.x, msg.y, msg.z]), np.array([msg.vx, msg.vy, msg.vz])
                self._local = (time.monotonic(), p, v)
            elif kind == "ATTITUDE":
                self._yaw_ned = float(msg.yaw)
            elif kind == "COMMAND_ACK":
                self._acks[msg.command] = msg.result
            elif kind == "GPS_GLOBAL_ORIGIN":
                self._origin_geo = (msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3)
            elif kind == "STATUSTEXT":
                log.info("ArduCopter: %s", msg.text)
            self._lock.notify_all()

    # ------------------------------------------------------------------ sending
    def _send(self, msg: Any) -> None:
        with self._send_lock:
            try:
                self._sock.sendall(pack_next(self._mav, msg))
            except OSError as exc:
                self.failed = self.failed or f"MAVLink send failed: {exc}"

    def _wait(self, pred: Any, timeout: float) -> bool:
        with self._lock:
            return (
                self._lock.wait_for(lambda: pred() or self._closing.is_set(), timeout)
                and not self._closing.is_set()
            )

    def _command(self, command: int, *params: float) -> bool:
        """COMMAND_LONG ``command`` until ACCEPTED (``retries`` tries)."""
        assert self._target is not None
        p = (list(params) + [0.0] * 7)[:7]
        for _ in range(self.cfg.retries):
            with self._lock:
                self._acks.pop(command, None)
            self._send(self._mav.command_long_encode(*self._target, command, 0, *p))
            if self._wait(lambda: command in self._acks, self.cfg.ack_timeout_s):
                if self._acks[command] == mavlink.MAV_RESULT_ACCEPTED:
                    return True
                log.warning("ArduCopter refused command %d (result %d)", command, self._acks[command])
            time.sleep(0.5)
        return False

    def _set_mode(self, name: str) -> bool:
        number = COPTER_MODES[name]
        ok = self._command(mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, number)
        return ok and self._wait(lambda: self._custom_mode == number, self.cfg.ack_timeout_s)

    def _tx_loop(self) -> None:
        period, next_beat = 1.0 / self.cfg.rate_hz, 0.0
        while not self._closing.wait(period):
            now = time.monotonic()
            if now >= next_beat:
                next_beat = now + 1.0
                self._send(
                    self._mav.heartbeat_encode(
                        mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0
                    )
                )
            if self.engaged.is_set():
                self._stream(now)

    def _stream(self, now: float) -> None:
        with self._lock:
            sample, hold, target, origin = self._sample, self._hold, self._target, self.origin_enu
        if target is None or origin is None:
            return
        if sample is not None and now - sample[0] <= self.cfg.stale_s:
            _, p, v, a, yaw = sample
            mask = IGNORE_YAW_RATE
            with self._lock:
                self._hold = (p, yaw)
        elif hold is not None:
            (p, yaw), v, a, mask = hold, np.zeros(3), np.zeros(3), IGNORE_YAW_RATE | IGNORE_VEL_ACC
        else:
            return
        pn, vn, an = frames.enu_to_ned(p - origin), frames.enu_to_ned(v), frames.enu_to_ned(a)
        self._send(
            self._mav.set_position_target_local_ned_encode(
                0, *target, mavlink.MAV_FRAME_LOCAL_NED, mask, *pn, *vn, *an, frames.yaw_enu_to_ned(yaw), 0.0
            )
        )

    # ------------------------------------------------------------------ taking control
    def _fail(self, why: str) -> None:
        self.failed = why
        log.error("GUIDED control of ArduCopter failed: %s", why)

    def _control(self) -> None:
        c = self.cfg
        if not self._wait(lambda: self._target is not None, c.connect_timeout_s):
            return self._fail(
                f"no ArduCopter HEARTBEAT on tcp://{c.host}:{c.port} within {c.connect_timeout_s:g} s (SITL "
                "serves one client per TCP port: is another connected there? give it SERIAL1, 5762 + 10 N)"
            )
        interval = int(1e6 / c.stream_hz)
        for msg_id in (mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, mavlink.MAVLINK_MSG_ID_ATTITUDE):
            self._command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, interval)
        if self.origin_enu is None:
            self._command(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN)
            if not self._wait(lambda: self._origin_geo is not None, 10.0):
                return self._fail("ArduCopter sent no GPS_GLOBAL_ORIGIN (no EKF origin yet: wait for GPS)")
            assert self._origin_geo is not None
            home = (c.home_lat_deg, c.home_lon_deg, c.home_alt_m)
            with self._lock:
                self.origin_enu = frames.geodetic_to_enu(*self._origin_geo, *home)
        while not self._closing.is_set() and not self._want.wait(0.2):
            pass
        if self._closing.is_set():
            return None
        if not self._wait(lambda: self._local is not None, c.connect_timeout_s):
            return self._fail("no LOCAL_POSITION_NED from ArduCopter (no position estimate)")
        if not self._set_mode("GUIDED"):
            return self._fail("ArduCopter refused GUIDED")
        if not self._armed:
            if not self._command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1):
                return self._fail("ArduCopter refused to arm (see its PreArm messages)")
            if not self._command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, c.takeoff_alt_m):
                return self._fail("ArduCopter refused the take-off")
            up = lambda: self._local is not None and -self._local[1][2] > c.takeoff_alt_m - 0.3  # noqa: E731
            if not self._wait(up, c.takeoff_timeout_s):
                return self._fail(f"ArduCopter did not reach {c.takeoff_alt_m:g} m")
        with self._lock:
            assert self._local is not None and self.origin_enu is not None
            here = self.origin_enu + frames.ned_to_enu(self._local[1])
            self._hold = (here, frames.yaw_ned_to_enu(self._yaw_ned or 0.0))
        self.engaged.set()
        log.info("ArduCopter in GUIDED under the planner, holding at %s", np.round(here, 2).tolist())
        return None
