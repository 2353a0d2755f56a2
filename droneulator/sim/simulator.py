"""The single-vehicle face of a :class:`~droneulator.world.World`: one vehicle, one scene, in lockstep.

Everything that flew one vehicle before the world held many (the runtime's dynamics server, the PX4
link, the learning environment, the examples and most tests) keeps this interface: ``Simulator`` is a
world whose first vehicle it speaks for. Its commands are that vehicle's, its ``state`` that vehicle's
state, its frames that vehicle's cameras; ``world`` and ``vehicle`` give the rest.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from droneulator.commands.errors import CommandError
from droneulator.config import LightConfig, SimConfig
from droneulator.controllers.flight import Event, Mode
from droneulator.vehicles.vehicle import NS, Vehicle, VehicleState
from droneulator.world import World
from droneulator.world import world as _world

__all__ = ["NS", "CommandError", "FrameSet", "Simulator", "StepResult", "VehicleState"]


@dataclass
class FrameSet:
    """All cameras of the vehicle rendered at one instant, with the state they were rendered from."""

    t_ns: int
    state: VehicleState
    cameras: dict[str, Any]  # name -> droneulator.render.CameraFrame


@dataclass
class StepResult:
    frames: list[FrameSet] = field(default_factory=list)
    events: list[Event] = field(default_factory=list)
    #: states at camera instants, when an external renderer draws them (``external_cameras=True``)
    camera_states: list[VehicleState] = field(default_factory=list)


class Simulator:
    """A world seen through its first vehicle (see the module docstring).

    ``render=False`` skips the renderer entirely (physics-only use, e.g. benchmarks);
    ``external_cameras=True`` (with ``render=False``) still splits the physics at camera instants
    and hands their states out in :attr:`StepResult.camera_states` for a render server to draw.
    """

    def __init__(
        self,
        scene: str | None = None,
        seed: int | None = None,
        config: SimConfig | None = None,
        render: bool = True,
        external_cameras: bool = False,
    ) -> None:
        self.world = World(config, scene, seed, render, external_cameras)
        self.config = self.world.config
        #: the vehicle this face speaks for: the world's first
        self.vehicle: Vehicle = self.world.vehicle()

    # ------------------------------------------------------------------ the world's
    @property
    def scene(self) -> Any:
        return self.world.scene

    @property
    def renderer(self) -> Any:
        return self.world.renderer

    @property
    def t(self) -> float:
        return self.world.t

    @property
    def t_ns(self) -> int:
        return self.world.t_ns

    @property
    def stamp_ns(self) -> int:
        return self.world.stamp_ns

    @property
    def control_period_ns(self) -> int:
        return self.world.control_period_ns

    @property
    def camera_period_ns(self) -> int:
        return self.world.camera_period_ns

    @property
    def camera_schedule(self) -> bool:
        return self.world.camera_schedule

    @property
    def frame_count(self) -> int:
        return self.world.frame_count

    def reset(
        self,
        seed: int | None = None,
        position: np.ndarray | None = None,
        yaw: float | None = None,
        scene: str | None = None,
        airborne: bool | None = None,
        light: LightConfig | None = None,
        vegetation: float | None = None,
    ) -> VehicleState:
        """Restart the flight at t = 0 from ``position`` (default: the scene's spawn on the ground).

        A position above the ground starts hovering there (mode ``hold``) unless ``airborne=False``;
        ``light`` replaces the light section (time of day, clouds, haze: RGB only); ``vegetation`` rebuilds
        the scene with that vegetation density.
        """
        return self.world.reset(seed, position, yaw, scene, airborne, light=light, vegetation=vegetation)

    def step(self, n: int = 1) -> StepResult:
        """Advance ``n`` control periods; returns the frames rendered and events raised meanwhile."""
        return self._one(self.world.step(n))

    def run(self, seconds: float) -> StepResult:
        """Step for ``seconds`` of simulated time, collecting frames and events."""
        return self._one(self.world.run(seconds))

    def run_until(self, predicate: Any, timeout: float, events: list[Event] | None = None) -> bool:
        """Step until ``predicate(sim)`` holds or ``timeout`` sim seconds pass; events are appended."""
        return self.world.run_until(lambda _world: predicate(self), timeout, events)

    def render(self) -> FrameSet:
        """Render every camera from the current state (also usable outside the camera schedule).

        The images are copies the caller owns (the renderer reuses its readback buffers).
        """
        return self._frames(self.world.render())

    def _frames(self, f: _world.FrameSet) -> FrameSet:
        name = self.vehicle.name
        return FrameSet(f.t_ns, f.states[name], f.cameras[name])

    def _one(self, res: _world.StepResult) -> StepResult:
        name = self.vehicle.name
        return StepResult(
            [self._frames(f) for f in res.frames], res.events, [states[name] for states in res.camera_states]
        )

    def close(self) -> None:
        self.world.close()

    def __enter__(self) -> Simulator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ the vehicle's
    @property
    def quad_params(self) -> dict[str, Any]:
        return self.vehicle.quad_params

    @property
    def flight(self) -> Any:
        return self.vehicle.flight

    @property
    def s(self) -> np.ndarray:
        return self.vehicle.s

    @property
    def mode(self) -> Mode:
        return self.vehicle.mode

    @property
    def state(self) -> VehicleState:
        return self.vehicle.state

    @property
    def specific_force(self) -> np.ndarray:
        return self.vehicle.specific_force

    @property
    def wind_velocity(self) -> np.ndarray:
        return self.vehicle.wind_velocity

    @property
    def acceleration(self) -> np.ndarray:
        return self.vehicle.acceleration

    @property
    def collisions(self) -> int:
        return self.vehicle.collisions

    def takeoff(self, altitude: float | None = None) -> float:
        return self.vehicle.takeoff(altitude)

    def goto(self, position: Any, yaw: float | None = None, speed: float | None = None,
             duration: float | None = None) -> float:  # fmt: skip
        return self.vehicle.goto(position, yaw, speed, duration)

    def velocity(self, forward: float, yaw_rate: float) -> None:
        self.vehicle.velocity(forward, yaw_rate)

    def track(self, position: Any, velocity: Any = None, acceleration: Any = None, yaw: float | None = None,
              yaw_rate: float = 0.0) -> None:  # fmt: skip
        self.vehicle.track(position, velocity, acceleration, yaw, yaw_rate)

    def hold(self) -> None:
        self.vehicle.hold()

    def land(self) -> float:
        return self.vehicle.land()

    def landing_spot(self, clearance: float = 0.5, search_radius: float = 10.0) -> np.ndarray:
        return self.vehicle.landing_spot(clearance, search_radius)

    def safe_land(self, clearance: float = 0.5) -> np.ndarray:
        return self.vehicle.safe_land(clearance)

    def motors_off(self) -> None:
        self.vehicle.motors_off()

    def set_rotor_speeds(self, rotor_speeds: Any) -> None:
        self.vehicle.set_rotor_speeds(rotor_speeds)
