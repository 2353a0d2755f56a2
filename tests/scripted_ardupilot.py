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

MAGIC_16, MAGIC_32 = 18458, 29569

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
        """Send the next frame and wait for its reply, as ArduPilot's lockstep does."""
        self.send_frame(pwm)
        got = self.receive(timeout)
        if got is None:
            raise TimeoutError(f"no reply to frame {self.frame_counter}")
        return got

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
