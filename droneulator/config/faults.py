"""Faults (the ``faults`` section, the ``fault`` op, the ``/<ns>/fault`` topic): what each kind is and
what it takes, checked once here for all three (docs/faults.md).

A :class:`FaultSpec` names a kind, a vehicle, when it starts (``at``, s since the reset; the op and the
topic start it at once) and for how long (``duration``; null: until cleared or the episode ends), and
the parameters of its kind (:data:`FAULT_KINDS`); a parameter another kind takes is refused. A bad
spec is a :class:`FaultError`, a ``ValueError`` with the command error code a request gets for it.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

#: every fault kind: what it does, its parameters (name -> doc) and its defaults
FAULT_KINDS: dict[str, tuple[str, dict[str, str], dict[str, Any]]] = {
    "rotor": (
        "a rotor's loss of efficiency: its thrust and moments scale by `efficiency` at the same speed "
        "(a chipped propeller, a weak motor; 0: the motor is dead)",
        {
            "rotor": "the rotor, 0-3 in RotorPy's order (required)",
            "efficiency": "what is left of its thrust, 0-1 (default 0)",
        },
        {"efficiency": 0.0},
    ),
    "gps_loss": ("the GPS delivers no fix (PX4 gets no HIL_GPS, ROS no NavSatFix)", {}, {}),
    "gps_jamming": (
        "the GPS fixes get noisier, with fewer satellites and eph/epv grown to match",
        {
            "noise_m": "extra white noise of the position, 1-sigma per axis, m (default 5)",
            "satellites": "satellites the fixes report, 0-50 (default 4)",
        },
        {"noise_m": 5.0, "satellites": 4},
    ),
    "gps_spoofing": (
        "the GPS position moves off the truth by `offset` plus `drift` times the time since the start; "
        "the fixes' velocity carries the drift too (a consistent spoofer)",
        {
            "drift": "[east, north, up] m/s (default 0)",
            "offset": "[east, north, up] m at the start (default 0)",
        },
        {"drift": (0.0, 0.0, 0.0), "offset": (0.0, 0.0, 0.0)},
    ),
    "imu_bias": (
        "a step in the IMU's biases, added to every sample",
        {
            "accel": "accelerometer bias step [x, y, z] m/s^2, body FRD (default 0)",
            "gyro": "gyroscope bias step [x, y, z] rad/s, body FRD (default 0)",
        },
        {"accel": (0.0, 0.0, 0.0), "gyro": (0.0, 0.0, 0.0)},
    ),
    "baro_drift": (
        "the barometer's pressure altitude drifts at `rate` (its pressure follows)",
        {"rate": "drift of the pressure altitude, m/s (default 0.5)"},
        {"rate": 0.5},
    ),
    "mag_interference": (
        "a field added to the magnetometer's (motor currents, a steel structure nearby)",
        {"field": "[x, y, z] gauss, body FRD (required)"},
        {},
    ),
    "camera_dropout": (
        "the vehicle's cameras deliver no frames (its body is still drawn for others)",
        {},
        {},
    ),
    "link_cut": (
        "the vehicle's command link (API and ROS) delivers no command (`link_cut`): a command stream stops, "
        "so the vehicle holds after its stream timeout",
        {},
        {},
    ),
}

#: the parameters every kind shares (not the kind's own)
_COMMON = ("kind", "vehicle", "at", "duration")


class FaultError(ValueError):
    """A bad fault spec; ``code`` is the command error code a request gets for it."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code
        self.message = message


def _vec3(name: str, value: Any) -> tuple[float, float, float]:
    ok = isinstance(value, list | tuple) and len(value) == 3
    ok = ok and all(
        isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) for v in value
    )
    if not ok:
        raise FaultError("invalid_argument", f"`{name}` must be three finite numbers, got {value!r}")
    return (float(value[0]), float(value[1]), float(value[2]))


def _number(name: str, value: Any, lo: float, hi: float) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise FaultError("invalid_argument", f"`{name}` must be a finite number, got {value!r}")
    if not lo <= value <= hi:
        raise FaultError("out_of_range", f"`{name}` must lie in [{lo:g}, {hi:g}], got {value!r}")
    return float(value)


@dataclass
class FaultSpec:
    """One fault: its ``kind`` (:data:`FAULT_KINDS`), the vehicle it strikes (null: the first), when it
    starts (``at``, s since the reset, in a config's schedule) and how long it lasts (``duration``, s;
    null: until cleared or the episode ends); the other fields are the kinds' parameters, null unless
    the kind takes them (its defaults fill them)."""

    kind: str = ""
    vehicle: str | None = None
    at: float = 0.0
    duration: float | None = None
    rotor: int | None = None
    efficiency: float | None = None
    noise_m: float | None = None
    satellites: int | None = None
    drift: tuple[float, float, float] | None = None
    offset: tuple[float, float, float] | None = None
    accel: tuple[float, float, float] | None = None
    gyro: tuple[float, float, float] | None = None
    rate: float | None = None
    field: tuple[float, float, float] | None = None

    def __post_init__(self) -> None:
        if not self.kind:
            raise FaultError("invalid_argument", f"a fault needs `kind`: one of {', '.join(FAULT_KINDS)}")
        if self.kind not in FAULT_KINDS:
            raise FaultError("invalid_argument", f"unknown fault kind {self.kind!r}; the kinds are "
                             f"{', '.join(FAULT_KINDS)}")  # fmt: skip
        _, params, defaults = FAULT_KINDS[self.kind]
        given = {f.name for f in dataclasses.fields(self) if f.name not in _COMMON and getattr(self, f.name)
                 is not None}  # fmt: skip
        foreign = sorted(given - set(params))
        if foreign:
            takes = ", ".join(params) or "no parameters"
            raise FaultError(
                "invalid_argument", f"a {self.kind} fault takes {takes}, not {', '.join(foreign)}"
            )
        for name, value in defaults.items():
            if getattr(self, name) is None:
                setattr(self, name, value)
        self.at = _number("at", self.at, 0.0, 1e7)
        if self.duration is not None:
            self.duration = _number("duration", self.duration, 0.0, 1e7)
        if self.kind == "rotor":
            if self.rotor is None:
                raise FaultError("invalid_argument", "a rotor fault needs `rotor`, 0-3")
            if isinstance(self.rotor, bool) or not isinstance(self.rotor, int):
                raise FaultError("invalid_argument", f"`rotor` must be an integer, got {self.rotor!r}")
            if not 0 <= self.rotor <= 3:
                raise FaultError(
                    "out_of_range", f"`rotor` must lie in [0, 3] (a quadrotor), got {self.rotor}"
                )
            self.efficiency = _number("efficiency", self.efficiency, 0.0, 1.0)
        elif self.kind == "gps_jamming":
            self.noise_m = _number("noise_m", self.noise_m, 0.0, 1000.0)
            sats = self.satellites
            if isinstance(sats, bool) or not isinstance(sats, int) or not 0 <= sats <= 50:
                raise FaultError("out_of_range", f"`satellites` must be an integer in [0, 50], got {sats!r}")
        elif self.kind == "gps_spoofing":
            self.drift, self.offset = _vec3("drift", self.drift), _vec3("offset", self.offset)
        elif self.kind == "imu_bias":
            self.accel, self.gyro = _vec3("accel", self.accel), _vec3("gyro", self.gyro)
        elif self.kind == "baro_drift":
            self.rate = _number("rate", self.rate, -100.0, 100.0)
        elif self.kind == "mag_interference":
            if self.field is None:
                raise FaultError(
                    "invalid_argument", "a mag_interference fault needs `field`, [x, y, z] gauss"
                )
            self.field = _vec3("field", self.field)

    def params(self) -> dict[str, Any]:
        """The kind's parameters, as plain JSON values (an event's, the state's)."""
        out = {name: getattr(self, name) for name in FAULT_KINDS[self.kind][1]}
        return {k: list(v) if isinstance(v, tuple) else v for k, v in out.items()}


def fault_markdown() -> str:
    """The kinds and their parameters as a Markdown table (docs/faults.md, the ``fault`` op's doc)."""
    lines = ["| kind | what | parameters |", "|---|---|---|"]
    for kind, (what, params, _) in FAULT_KINDS.items():
        args = "; ".join(f"`{name}`: {doc}" for name, doc in params.items()) or "none"
        lines.append(f"| `{kind}` | {what} | {args} |")
    return "\n".join(lines) + "\n"
