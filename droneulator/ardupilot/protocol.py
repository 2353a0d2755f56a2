"""ArduPilot SITL's JSON physics protocol (``--model JSON``), as ``libraries/SITL/SIM_JSON.{h,cpp}`` of
ArduPilot 90700977c5 (master of 2025-07-21) defines it.

ArduPilot -> physics, one UDP datagram per simulation frame, little-endian and packed:

* ``servo_packet_16``: ``uint16 magic = 18458, uint16 frame_rate, uint32 frame_count, uint16 pwm[16]``
  (40 bytes), or with ``SERVO_32_ENABLE = 1`` ``servo_packet_32``: magic 29569 and ``pwm[32]`` (72 bytes).
  ``frame_rate`` (Hz) is the step ArduPilot asks for; ``frame_count`` counts frames from 0 at SITL start
  and moves on only once ArduPilot has parsed a reply; when no reply came within a second ArduPilot sends
  the same frame again.

Physics -> ArduPilot, one reply per servo packet, to the address the packet came from: one JSON object
preceded and followed by ``"\\n"``. ArduPilot's parser (``JSON::parse_sensors``) is not a JSON parser: it
finds each key with ``strstr`` and reads the value right after ``"key":`` with ``sscanf("[%f, %f, %f]")``,
so values must follow their colon with no space (compact separators), and no key may contain another's
name before it. Required: ``timestamp`` (s, physics time, absolute), ``imu.gyro`` (rad/s, body FRD),
``imu.accel_body`` (m/s^2, body FRD, specific force: -g on z at rest), ``position`` (m, NED from home),
``velocity`` (m/s, NED), and ``attitude`` (roll, pitch, yaw, rad) or ``quaternion`` (w, x, y, z of body
FRD -> NED; used when both are sent). Optional: ``rng_1`` .. ``rng_6`` (m), ``windvane.direction`` /
``windvane.speed``, ``airspeed`` (m/s), ``no_time_sync`` (0/1). Battery voltage and current are not in
this parser's key table: ArduPilot simulates the battery itself.

A reply whose timestamp is older than the last one is taken as a physics reset (ArduPilot's clock does
not move); ArduPilot's clock advances by the timestamp difference, so the physics' clock drives it.
"""

from __future__ import annotations

import json
import math
import struct
from dataclasses import dataclass
from typing import Any

import numpy as np

from droneulator.frames import enu_to_ned, xyzw_to_wxyz
from droneulator.sensors.truth import Truth

MAGIC_16 = 18458
MAGIC_32 = 29569
#: ``servo_packet_16`` and ``servo_packet_32`` of SIM_JSON.h (packed, little-endian as x86 and ARM hosts)
SERVO_16 = struct.Struct("<HHI16H")
SERVO_32 = struct.Struct("<HHI32H")
_LAYOUTS = {MAGIC_16: SERVO_16, MAGIC_32: SERVO_32}
#: the keys SIM_JSON.cpp's parser requires (``keytable`` entries with ``required = true``)
REQUIRED_KEYS = ("timestamp", "imu.gyro", "imu.accel_body", "position", "velocity")
#: rangefinders SIM_JSON.cpp reads (``rng_1`` .. ``rng_6``)
MAX_RANGEFINDERS = 6


class ProtocolError(ValueError):
    """A datagram that is not one of ArduPilot's servo packets; the message says why."""


@dataclass(frozen=True)
class ServoPacket:
    """One servo packet: the frame rate asked for (Hz), the frame's number, the PWM of every channel."""

    frame_rate: int
    frame_count: int
    pwm: tuple[int, ...]

    def encode(self) -> bytes:
        """The packet's bytes, as ArduPilot's ``JSON::output_servos`` sends them (16 or 32 channels)."""
        if len(self.pwm) not in (16, 32):
            raise ValueError(f"a servo packet carries 16 or 32 channels, not {len(self.pwm)}")
        layout, magic = (SERVO_16, MAGIC_16) if len(self.pwm) == 16 else (SERVO_32, MAGIC_32)
        return layout.pack(magic, self.frame_rate, self.frame_count, *self.pwm)


def decode_servo(data: bytes) -> ServoPacket:
    """The servo packet in ``data``; raises :class:`ProtocolError` for anything else."""
    if len(data) < 2:
        raise ProtocolError(f"{len(data)} bytes is no servo packet")
    (magic,) = struct.unpack_from("<H", data)
    layout = _LAYOUTS.get(magic)
    if layout is None:
        raise ProtocolError(f"magic {magic} is neither {MAGIC_16} (16 channels) nor {MAGIC_32} (32 channels)")
    if len(data) != layout.size:
        raise ProtocolError(f"a packet with magic {magic} has {layout.size} bytes, this one {len(data)}")
    _, rate, count, *pwm = layout.unpack(data)
    if rate == 0:
        raise ProtocolError("frame_rate 0 Hz: no step to take")
    return ServoPacket(rate, count, tuple(pwm))


def _vec(v: Any) -> list[float]:
    out = [float(x) for x in np.asarray(v, dtype=float).reshape(-1)]
    if not all(math.isfinite(x) for x in out):
        raise ValueError(f"non-finite value {out} cannot go to ArduPilot (its parser reads %f)")
    return out


@dataclass(frozen=True)
class FdmState:
    """One reply's content in ArduPilot's frames: NED world, FRD body, SI units."""

    timestamp_s: float
    gyro: np.ndarray
    accel_body: np.ndarray
    position: np.ndarray
    velocity: np.ndarray
    #: body FRD -> NED, scalar first (ArduPilot's ``Quaternion`` q1..q4)
    quaternion_wxyz: np.ndarray
    #: ``airspeed`` (m/s), sent when known
    airspeed: float | None = None
    #: ``rng_1`` .. ``rng_n`` (m)
    ranges: tuple[float, ...] = ()

    @classmethod
    def from_truth(
        cls,
        timestamp_s: float,
        truth: Truth,
        accel_frd: np.ndarray,
        gyro_frd: np.ndarray,
        airspeed: float | None = None,
        ranges: tuple[float, ...] = (),
    ) -> FdmState:
        """``truth`` (ENU world, FLU body) with the IMU sample (``accel_frd``, ``gyro_frd``, already
        FRD), as ArduPilot reads it; position relative to the world origin, ArduPilot's home."""
        return cls(
            float(timestamp_s),
            np.asarray(gyro_frd, dtype=float),
            np.asarray(accel_frd, dtype=float),
            enu_to_ned(truth.position),
            enu_to_ned(truth.velocity),
            xyzw_to_wxyz(truth.quaternion_ned_frd),
            airspeed,
            tuple(ranges),
        )

    def to_dict(self) -> dict[str, Any]:
        """The JSON object, keys in SIM_JSON.cpp's table order."""
        if len(self.ranges) > MAX_RANGEFINDERS:
            raise ValueError(f"ArduPilot reads at most {MAX_RANGEFINDERS} rangefinders (rng_1..rng_6)")
        if not math.isfinite(self.timestamp_s):
            raise ValueError(f"timestamp {self.timestamp_s} is not finite")
        out: dict[str, Any] = {
            "timestamp": self.timestamp_s,
            "imu": {"gyro": _vec(self.gyro), "accel_body": _vec(self.accel_body)},
            "position": _vec(self.position),
            "quaternion": _vec(self.quaternion_wxyz),
            "velocity": _vec(self.velocity),
        }
        for i, r in enumerate(self.ranges, start=1):
            out[f"rng_{i}"] = _vec([r])[0]
        if self.airspeed is not None:
            out["airspeed"] = _vec([self.airspeed])[0]
        return out

    def encode(self) -> bytes:
        """The reply datagram: ``"\\n" + compact JSON + "\\n"`` (SIM_JSON.cpp parses the text between the
        last two newlines it has received)."""
        return ("\n" + json.dumps(self.to_dict(), separators=(",", ":")) + "\n").encode("ascii")
