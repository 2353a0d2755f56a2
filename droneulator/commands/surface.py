"""The command surface: exactly what the ops use of the world and of a vehicle, as Protocols.

The command path sits below the world in the package's layers (docs/architecture.md), so it may not
import :class:`~droneulator.world.World` or :class:`~droneulator.vehicles.Vehicle`, not even for type
checking. It names them structurally instead: :class:`CommandedWorld` and :class:`CommandedVehicle`
list every method and attribute an op calls, typed, and ``World`` / ``Vehicle`` satisfy them without
knowing of them (tests/test_command_surface.py checks both at run time; mypy checks the signatures).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

if TYPE_CHECKING:  # annotations only: importing the command path stays cheap
    from droneulator.config import FaultSpec, LightConfig, SimConfig, WindConfig
    from droneulator.scenes.base import Scene

#: a point or vector of the world frame as a request carries it: three finite numbers
Vec3 = Sequence[float]


class ReportedState(Protocol):
    """A vehicle's state as the ops report it (``state``, ``reset``): its API object, plain JSON."""

    def to_dict(self) -> dict[str, Any]: ...


@runtime_checkable
class CommandedVehicle(Protocol):
    """What the flight ops, ``state`` and ``scene_info`` use of a vehicle."""

    @property
    def name(self) -> str: ...

    @property
    def state(self) -> ReportedState: ...

    def takeoff(self, altitude: float | None = None) -> float:
        """Climb to ``altitude`` (None: the configured one); the planned duration, s."""
        ...

    def land(self) -> float:
        """Descend and stop the rotors; the planned duration, s."""
        ...

    def goto(
        self,
        position: Vec3,
        yaw: float | None = None,
        speed: float | None = None,
        duration: float | None = None,
    ) -> float:
        """Fly to ``position`` (heading ``yaw``, None: kept); the planned duration, s."""
        ...

    def velocity(self, forward: float, yaw_rate: float) -> None:
        """Fly ``forward`` m/s along the heading, turning at ``yaw_rate`` rad/s."""
        ...

    def track(
        self,
        position: Vec3,
        velocity: Vec3 | None = None,
        acceleration: Vec3 | None = None,
        yaw: float | None = None,
        yaw_rate: float = 0.0,
    ) -> None:
        """Track one setpoint with feed-forward."""
        ...

    def rotors(self, rotor_speeds: Sequence[float], normalized: bool = False) -> None:
        """Set the four rotor speeds (rad/s, or thrusts in [0, 1] with ``normalized``)."""
        ...

    def rates(self, thrust: float, body_rates: Vec3, normalized: bool = False) -> None:
        """Fly a collective thrust (N, or a share of the largest) and body rates (rad/s)."""
        ...

    def attitude(
        self,
        thrust: float,
        quaternion: Sequence[float] | None = None,
        roll: float | None = None,
        pitch: float | None = None,
        yaw: float | None = None,
        normalized: bool = False,
    ) -> None:
        """Fly a collective thrust and an attitude (a quaternion or roll, pitch, yaw)."""
        ...

    def hold(self) -> None: ...

    def motors_off(self) -> None: ...

    def describe(self) -> dict[str, Any]:
        """What ``scene_info`` lists of the vehicle."""
        ...


class WindSettings(Protocol):
    """What ``set_wind`` reads of the world's wind field: each vehicle's settings, in vehicle order."""

    @property
    def configs(self) -> Sequence[WindConfig]: ...


@runtime_checkable
class CommandedWorld(Protocol):
    """What the ops use of the world: its vehicles, clocks, scene and config, reset, trigger, wind."""

    @property
    def config(self) -> SimConfig: ...

    @property
    def scene(self) -> Scene: ...

    @property
    def vehicles(self) -> Mapping[str, CommandedVehicle]:
        """Every vehicle by name, the first the default."""
        ...

    @property
    def wind(self) -> WindSettings: ...

    @property
    def t(self) -> float:
        """Episode time, s."""
        ...

    @property
    def stamp_ns(self) -> int:
        """The ROS clock, ns (never runs backwards across resets)."""
        ...

    def vehicle(self, name: str | None = None) -> CommandedVehicle:
        """The vehicle ``name`` (None: the first); an unknown name is a CommandError."""
        ...

    def reset(
        self,
        seed: int | None = None,
        position: Vec3 | None = None,
        yaw: float | None = None,
        scene: str | None = None,
        airborne: bool | None = None,
        vehicle: str | None = None,
        light: LightConfig | None = None,
        vegetation: float | None = None,
    ) -> ReportedState:
        """Restart at t = 0; the state of ``vehicle`` (None: the first)."""
        ...

    def trigger(self, name: str | None = None) -> int:
        """Have the cameras of ``name`` (None: the first vehicle's) shoot at the end of the next control
        period; the stamp, ns, that frame set will carry."""
        ...

    def set_wind(self, config: WindConfig, vehicle: str | None = None) -> None:
        """Change the wind of every vehicle, or of ``vehicle`` only."""
        ...

    def inject_fault(self, spec: FaultSpec) -> dict[str, Any]:
        """Start the fault ``spec`` now; the fault as started (plain JSON)."""
        ...

    def clear_faults(
        self, vehicle: str | None = None, kind: str | None = None, fault_id: int | None = None
    ) -> list[int]:
        """End the active faults matching every filter given; their ids."""
        ...

    def command_link_cut(self, vehicle: str | None) -> bool:
        """Whether ``vehicle``'s (None: the first vehicle's) command link is cut."""
        ...
