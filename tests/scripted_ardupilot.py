"""An ArduPilot SITL stand-in for CI, where ArduPilot cannot be built: the JSON backend's side of the
wire as ``libraries/SITL/SIM_JSON.{h,cpp}`` (ArduPilot 90700977c5) has it, written here independently of
:mod:`droneulator.ardupilot`.

* It sends ``servo_packet_16`` (``<HHI16H``, magic 18458) or ``servo_packet_32`` (``<HHI32H``, magic
  29569) from its own UDP socket, as ``JSON::output_servos`` does.
* It reads replies as ``JSON::recv_fdm`` does: received bytes are appended to a buffer, every ``\\n``
  becomes a NUL, and the text between the last two NULs is parsed, or nothing when there are not two
  (the buffer is kept for the next datagram); the parse is ``JSON::parse_sensors``: each key found with
  ``strstr`` (section first), the value read right after ``key":`` with ``atof`` or
  ``sscanf("[%f, %f, %f]")``; a missing required key, or neither ``attitude`` nor ``quaternion``, and
  the frame is not taken. ``frame_count`` moves on only when a reply was taken, as SIM_JSON's
  ``frame_counter`` does, so an unanswered frame is sent again with the same number.
* ArduPilot's output chain for a multicopter motor, from thrust fraction to PWM
  (``Thrust_Linearization::thrust_to_actuator``, ``AP_MotorsMulticopter::output_to_pwm``), for a
  scripted mixer.
"""

from __future__ import annotations

import math
import re
import socket
import struct
import time
from typing import Any

import numpy as np

from droneulator.px4.transport import pack_next

MAGIC_16, MAGIC_32 = 18458, 29569
#: wall seconds SIM_JSON waits for a reply before it sends its frame again
REPEAT_S = 1.0

#: SIM_JSON.h's keytable: (section, key, type, required), in its order
KEYTABLE: tuple[tuple[str, str, str, bool], ...] = (
    ("", "timestamp", "double", True),
    ("imu", "gyro", "vector3f", True),
    ("imu", "accel_body", "vector3f", True),
    ("", "position", "vector3d", True),
    ("", "attitude", "vector3f", False),
    ("", "quaternion", "quaternion", False),
    ("", "velocity", "vector3f", True),
    ("", "rng_1", "float", False),
    ("", "rng_2", "float", False),
    ("", "rng_3", "float", False),
    ("", "rng_4", "float", False),
    ("", "rng_5", "float", False),
    ("", "rng_6", "float", False),
    ("windvane", "direction", "float", False),
    ("windvane", "speed", "float", False),
    ("", "airspeed", "float", False),
    ("", "no_time_sync", "boolean", False),
)

_NUM = r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?"
#: sscanf's "[%f, %f, %f]": a literal '[', each %f skipping leading white space, ',' right after a number
_VEC = {n: re.compile(r"\[" + r",\s*".join([rf"\s*({_NUM})"] * n)) for n in (3, 4)}
_ATOF = re.compile(rf"\s*({_NUM})")


def _atof(p: str) -> float:
    m = _ATOF.match(p)
    return float(m.group(1)) if m else 0.0


def parse_sensors(text: str) -> dict[str, Any] | None:
    """``JSON::parse_sensors`` on one line of text: the values by key (``imu.gyro`` for sectioned keys),
    or None when a required key is missing or a vector does not scan (SIM_JSON then drops the frame)."""
    out: dict[str, Any] = {}
    for section, key, kind, required in KEYTABLE:
        at = text.find(section)  # strstr(json, "") is json itself
        if at < 0:
            if required:
                return None
            continue
        p = text[at + len(section) + 1 :]
        at = p.find(key)
        if at < 0:
            if required:
                return None
            continue
        p = p[at + len(key) + 2 :]
        name = f"{section}.{key}" if section else key
        if kind in ("vector3f", "vector3d", "quaternion"):
            m = _VEC[4 if kind == "quaternion" else 3].match(p)
            if m is None:
                return None
            out[name] = [float(g) for g in m.groups()]
        elif kind == "boolean":
            out[name] = int(_atof(p)) != 0
        else:
            out[name] = _atof(p)
    if "attitude" not in out and "quaternion" not in out:
        return None
    return out


class RecvBuffer:
    """``JSON::recv_fdm``'s sensor buffer: what it parses from each datagram received."""

    def __init__(self) -> None:
        self.buf = bytearray()

    def feed(self, data: bytes) -> dict[str, Any] | None:
        self.buf += data.replace(b"\n", b"\0")
        p2 = self.buf.rfind(b"\0")
        if p2 <= 0:
            return None
        p1 = self.buf.rfind(b"\0", 0, p2)
        if p1 < 0:
            return None
        parsed = parse_sensors(self.buf[p1 + 1 : p2].decode("ascii", "replace"))
        if parsed is None:
            return None
        del self.buf[:p2]
        return parsed


def thrust_to_pwm(
    thrust: Any,
    expo: float = 0.65,
    spin_min: float = 0.15,
    spin_max: float = 0.95,
    pwm_min: int = 1000,
    pwm_max: int = 2000,
) -> np.ndarray:
    """ArduCopter's motor output for thrust fractions in [0, 1] (no battery scaling, lift_max 1)."""
    t = np.clip(np.asarray(thrust, dtype=float), 0.0, 1.0)
    root = np.sqrt((1.0 - expo) ** 2 + 4.0 * expo * t)
    ratio = t if expo == 0.0 else ((expo - 1.0) + root) / (2.0 * expo)
    actuator = spin_min + (spin_max - spin_min) * np.clip(ratio, 0.0, 1.0)
    return np.round(pwm_min + (pwm_max - pwm_min) * actuator)


class ScriptedArduPilot:
    """SIM_JSON's wire side: sends servo packets to ``port``, reads and parses the replies."""

    def __init__(self, port: int, rate_hz: int = 1200, channels: int = 16) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.target = ("127.0.0.1", port)
        self.rate_hz, self.channels = rate_hz, channels
        self.frame_counter = 0
        self.inbox = RecvBuffer()
        self.last: dict[str, Any] | None = None
        self.pwm = [1000] * 4
        #: frames sent again by the last :meth:`step` while it waited
        self.repeats_sent = 0

    @property
    def address(self) -> tuple[str, int]:
        return self.sock.getsockname()

    def send_frame(self, pwm: Any = None, frame_count: int | None = None) -> None:
        """One servo packet with motors 1..4 at ``pwm`` (the last ones by default)."""
        if pwm is not None:
            self.pwm = [int(v) for v in pwm]
        channels = list(self.pwm) + [0] * (self.channels - len(self.pwm))
        fmt, magic = ("<HHI16H", MAGIC_16) if self.channels == 16 else ("<HHI32H", MAGIC_32)
        count = self.frame_counter if frame_count is None else frame_count
        self.sock.sendto(struct.pack(fmt, magic, self.rate_hz, count, *channels), self.target)

    def receive(self, timeout: float = 5.0) -> dict[str, Any] | None:
        """The next reply SIM_JSON would take (None on a timeout): it moves ``frame_counter`` on."""
        end = time.monotonic() + timeout
        while (left := end - time.monotonic()) > 0:
            self.sock.settimeout(left)
            try:
                data, _ = self.sock.recvfrom(65000)
            except TimeoutError:
                return None
            parsed = self.inbox.feed(data)
            if parsed is not None:
                self.frame_counter += 1
                self.last = parsed
                return parsed
        return None

    def step(self, pwm: Any = None, timeout: float = 5.0) -> dict[str, Any]:
        """Send the next frame and wait for its reply, as ArduPilot's lockstep does: while no reply comes,
        the same frame is sent again every :data:`REPEAT_S` (``JSON::recv_fdm`` sends the servos again
        each time its wait for a sensor packet ends empty), up to ``timeout`` in all."""
        self.send_frame(pwm)
        end = time.monotonic() + timeout
        self.repeats_sent = 0
        while (left := end - time.monotonic()) > 0:
            got = self.receive(min(REPEAT_S, left))
            if got is not None:
                return got
            if end - time.monotonic() > 0:
                self.send_frame()
                self.repeats_sent += 1
        n = self.repeats_sent
        raise TimeoutError(f"no reply to frame {self.frame_counter} in {timeout} s ({n} repeats sent)")

    def quiet(self, timeout: float = 0.3) -> bool:
        """True when nothing arrives within ``timeout``."""
        self.sock.settimeout(timeout)
        try:
            self.sock.recvfrom(65000)
        except TimeoutError:
            return True
        return False

    def close(self) -> None:
        self.sock.close()


def rpy_factors(angle_deg: float, yaw_factor: float) -> tuple[float, float, float]:
    """``AP_MotorsMatrix::add_motor``'s roll, pitch and yaw factors of a motor at ``angle_deg``."""
    return math.cos(math.radians(angle_deg + 90.0)), math.cos(math.radians(angle_deg)), yaw_factor


class ScriptedArduCopterMavlink:
    """ArduCopter SITL's MAVLink side for a GUIDED client, on TCP ``port`` (as ``--serial0 tcp:0``):
    HEARTBEAT (``MAV_AUTOPILOT_ARDUPILOTMEGA``, custom mode, armed flag), COMMAND_ACKs for
    SET_MESSAGE_INTERVAL, REQUEST_MESSAGE (GPS_GLOBAL_ORIGIN), DO_SET_MODE, COMPONENT_ARM_DISARM and
    NAV_TAKEOFF (refused unless GUIDED and armed, as ArduCopter does), and a point vehicle that flies
    toward the newest position target at 3 m/s, reported as LOCAL_POSITION_NED and ATTITUDE at 20 Hz."""

    GUIDED, LAND = 4, 9

    def __init__(self, origin_geo: tuple[float, float, float]) -> None:
        from pymavlink.dialects.v20 import common as mavlink

        self.m = mavlink
        self.server = socket.create_server(("127.0.0.1", 0))
        self.port = self.server.getsockname()[1]
        self.origin_geo = origin_geo
        self.mode, self.armed = 0, False
        self.pos, self.yaw = np.zeros(3), 0.0
        self.target: np.ndarray | None = None
        self.targets: list[Any] = []
        self.commands: list[int] = []
        #: messages from the client missed by their MAVLink sequence numbers
        self.missed = 0
        self._last_seq: int | None = None
        self._tx = mavlink.MAVLink(None, 1, 1)
        self._rx = mavlink.MAVLink(None)
        self._stop = False
        import threading

        self._lock = threading.Lock()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _send(self, conn: socket.socket, msg: Any) -> None:
        with self._lock:
            conn.sendall(pack_next(self._tx, msg))

    def _run(self) -> None:
        self.server.settimeout(10.0)
        try:
            conn, _ = self.server.accept()
        except OSError:
            return
        conn.settimeout(0.05)
        last = time.monotonic()
        while not self._stop:
            try:
                data = conn.recv(65536)
                if not data:
                    return
                for msg in self._rx.parse_buffer(data) or []:
                    if self._last_seq is not None:  # ArduPilot's link statistics: sequence gaps are losses
                        self.missed += (msg.get_seq() - self._last_seq - 1) % 256
                    self._last_seq = msg.get_seq()
                    self._handle(conn, msg)
            except TimeoutError:
                pass
            except OSError:
                return
            now = time.monotonic()
            dt, last = now - last, now
            self._fly(dt)
            m = self.m
            base = m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (m.MAV_MODE_FLAG_SAFETY_ARMED if self.armed else 0)
            try:
                self._send(
                    conn,
                    self._tx.heartbeat_encode(
                        m.MAV_TYPE_QUADROTOR, m.MAV_AUTOPILOT_ARDUPILOTMEGA, base, self.mode, 4
                    ),
                )
                self._send(conn, self._tx.local_position_ned_encode(0, *self.pos, 0.0, 0.0, 0.0))
                self._send(conn, self._tx.attitude_encode(0, 0.0, 0.0, self.yaw, 0.0, 0.0, 0.0))
            except OSError:
                return

    def _fly(self, dt: float) -> None:
        if self.mode == self.LAND and self.target is not None:
            self.target = np.array([self.pos[0], self.pos[1], 0.0])
        if not self.armed or self.target is None:
            return
        d = self.target - self.pos
        dist = float(np.linalg.norm(d))
        self.pos = self.target.copy() if dist < 3.0 * dt else self.pos + d / dist * 3.0 * dt

    def _handle(self, conn: socket.socket, msg: Any) -> None:
        m = self.m
        kind = msg.get_type()
        if kind == "SET_POSITION_TARGET_LOCAL_NED":
            self.targets.append(msg)
            if self.mode == self.GUIDED and self.armed and not msg.type_mask & 7:
                self.target = np.array([msg.x, msg.y, msg.z])
                self.yaw = msg.yaw
            return
        if kind != "COMMAND_LONG":
            return
        self.commands.append(msg.command)
        result = m.MAV_RESULT_ACCEPTED
        if msg.command == m.MAV_CMD_REQUEST_MESSAGE and int(msg.param1) == m.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN:
            lat, lon, alt = self.origin_geo
            self._send(
                conn, self._tx.gps_global_origin_encode(round(lat * 1e7), round(lon * 1e7), round(alt * 1000))
            )
        elif msg.command == m.MAV_CMD_DO_SET_MODE:
            self.mode = int(msg.param2)
        elif msg.command == m.MAV_CMD_COMPONENT_ARM_DISARM:
            self.armed = msg.param1 == 1
        elif msg.command == m.MAV_CMD_NAV_TAKEOFF:
            if self.mode == self.GUIDED and self.armed:
                self.target = np.array([self.pos[0], self.pos[1], -msg.param7])
            else:
                result = m.MAV_RESULT_FAILED
        self._send(conn, self._tx.command_ack_encode(msg.command, result))

    def close(self) -> None:
        self._stop = True
        self.thread.join(2.0)
        self.server.close()
