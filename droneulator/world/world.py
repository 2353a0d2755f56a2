"""The world: one scene, one clock and every vehicle in it, stepped together in lockstep.

Simulation time is an integer count of nanoseconds. :meth:`World.step` advances one control period:

1. every vehicle's flight controller gives its rotor command or its reference (vehicles holding or with
   the motors off keep the last one, without a call);
2. the SE(3) controller turns every reference into rotor commands in one compiled loop;
3. each vehicle's wind is the wind field's where it is (:mod:`droneulator.wind.field`: mean wind, Dryden
   turbulence, gusts, the canopy's shelter; or a RotorPy profile, ``vehicle.wind``) plus the rotor wakes
   of the vehicles above it (:mod:`droneulator.world.downwash`);
4. one compiled step integrates every vehicle's row of the state array (``states``, laid out
   ``(worlds, vehicles, STATE_SIZE)`` with one world here), split at camera instants so that every
   frame is rendered from the exact state at ``k / camera_hz``, with the scene's collisions per row;
5. vehicles whose bodies overlap collide (:mod:`droneulator.world.contact`): one ``collision`` event
   names both, and both stop where they were at the start of the period;
6. each vehicle's IMU means and hard touchdowns;
7. with triggered cameras (``render.camera_trigger=command``), the frame sets :meth:`World.trigger` asked
   for, at the end of the period, instead of the camera rate's.

One vehicle is the default (:class:`~droneulator.config.SimConfig` with no ``vehicles``);
``world.vehicle()`` is its handle.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Collection, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from droneulator.commands.errors import CommandError
from droneulator.config import LightConfig, SimConfig, load_config
from droneulator.controllers.flight import Event, Mode
from droneulator.controllers.se3 import se3_rows
from droneulator.scenes import get_scene
from droneulator.scenes.base import Scene
from droneulator.state import FLAT_SIZE, STATE, STATE_SIZE
from droneulator.vehicles.dynamics import (
    OUTPUT,
    OUTPUT_SIZE,
    PARALLEL_ROWS,
    ParamTable,
    integrate_rows,
    substeps,
    work_arrays,
)
from droneulator.vehicles.vehicle import Vehicle, VehicleState
from droneulator.wind.field import WindField
from droneulator.world.contact import contacts
from droneulator.world.downwash import WakeModel, downwash

if TYPE_CHECKING:
    from droneulator.render.pipeline import CameraPipeline

NS = 1_000_000_000

log = logging.getLogger("droneulator.sim")


@dataclass
class FrameSet:
    """Every camera of every vehicle rendered at one instant, with the states they were rendered from.

    ``states`` and ``cameras`` are keyed by vehicle name; ``cameras[name]`` by camera name."""

    t_ns: int
    states: dict[str, VehicleState]
    cameras: dict[str, dict[str, Any]]  # vehicle -> camera -> droneulator.render.CameraFrame


@dataclass
class StepResult:
    frames: list[FrameSet] = field(default_factory=list)
    events: list[Event] = field(default_factory=list)
    #: every vehicle's state at each camera instant, when an external renderer draws them
    #: (``external_cameras=True``)
    camera_states: list[dict[str, VehicleState]] = field(default_factory=list)
    #: for each of :attr:`camera_states`, the vehicles whose cameras shoot at it: None for all (the camera
    #: rate), the triggered ones with ``render.camera_trigger = "command"`` (every body is still drawn)
    camera_rigs: list[tuple[str, ...] | None] = field(default_factory=list)


class World:
    """A scene, a clock and the vehicles of ``config.vehicles`` (one by default), stepped in lockstep.

    ``render=False`` skips the renderer entirely (physics-only use, e.g. benchmarks);
    ``external_cameras=True`` (with ``render=False``) still splits the physics at camera instants and
    hands every vehicle's state at them out in :attr:`StepResult.camera_states` for a render server.
    """

    def __init__(
        self,
        config: SimConfig | None = None,
        scene: str | None = None,
        seed: int | None = None,
        render: bool = True,
        external_cameras: bool = False,
    ) -> None:
        self.config = config or load_config()
        if scene is not None:
            self.config.scene = scene
        if seed is not None:
            self.config.seed = seed
        cfg = self.config
        self.specs = cfg.vehicle_specs()
        n = len(self.specs)
        # a scene without room for the fleet fails here (ValueError), before any vehicle is built
        get_scene(cfg.scene, cfg.seed, cfg.vegetation).spawn_points(sum(s.spawn is None for s in self.specs))
        #: every vehicle's state, ``(worlds, vehicles, STATE_SIZE)``: one world here
        self.states = np.zeros((1, n, STATE_SIZE))
        self._rows = self.states[0]
        self.vehicles: dict[str, Vehicle] = {}
        self.table = ParamTable()
        #: each vehicle's IMU means over the last period: specific force (body), acceleration (world)
        self._motion = np.zeros((n, 6))
        for i, spec in enumerate(self.specs):
            self.vehicles[spec.name] = Vehicle(self, cfg, spec, self._rows[i], self._motion[i], i)
        vs = list(self.vehicles.values())
        self._pidx = np.array([self.table.add((v.spec.params,), v.packed) for v in vs], dtype=np.int64)
        self._gains = np.stack([v.flight.se3.gains() for v in vs])
        self._gidx = np.arange(n, dtype=np.int64)
        self._radius = np.array([v.collision_radius for v in vs])
        self._impact_speed = cfg.vehicle.impact_speed
        self._wake = WakeModel.of(vs)
        # per-row scratch and outputs of the compiled steps, reused every step
        self._cmds = np.zeros((n, 4))
        self._flats = np.zeros((n, FLAT_SIZE))
        self._se3 = np.zeros(n, dtype=bool)
        self._imu = np.zeros((n, OUTPUT_SIZE))
        self._hit = np.zeros(n, dtype=bool)
        self._active = np.ones(n, dtype=bool)
        self._work, self._R = work_arrays(n)
        self._Rc = np.zeros((n, 3, 3))
        #: vehicles whose command must be computed next period: not :attr:`FlightController.steady`, or
        #: commanded since (each flight controller reports its commands); the others keep theirs
        self._busy: set[int] = set(range(n))
        for i, v in enumerate(vs):
            v.flight.on_command = functools.partial(self._busy.add, i)
        self._period_start = np.zeros((n, STATE_SIZE))
        self.control_period_ns = round(NS / cfg.vehicle.control_hz)
        self.camera_period_ns = round(NS / cfg.render.camera_hz)
        self._substep = 1.0 / (cfg.vehicle.control_hz * cfg.vehicle.substeps)
        self.render_enabled = render
        self.camera_schedule = render or external_cameras
        #: cameras shoot only when :meth:`trigger` asks (``render.camera_trigger = "command"``)
        self.triggered = cfg.render.camera_trigger == "command"
        #: vehicles whose cameras shoot at the end of the next control period
        self._shots: set[str] = set()
        #: the camera pipeline (:mod:`droneulator.render.pipeline`) when the world renders its own frames
        self.cameras: CameraPipeline | None = None
        self.scene: Scene
        self.t_ns = 0
        #: the wind field every vehicle flies in (:mod:`droneulator.wind.field`), seeded by the world's seed
        self.wind = WindField(cfg.wind, n, self.control_period_ns / NS, cfg.seed)
        self._load_scene(cfg.scene, cfg.seed, cfg.vegetation)
        self.reset()

    # ------------------------------------------------------------------ setup
    def _load_scene(self, name: str, seed: int, vegetation: float) -> None:
        scene = get_scene(name, seed, vegetation)
        # a scene without room for the fleet fails here (ValueError), before anything changes
        scene.spawn_points(sum(spec.spawn is None for spec in self.specs))
        self.scene = scene
        self.wind.collision = scene.collision
        if self.render_enabled:
            from droneulator.render.pipeline import CameraPipeline

            if self.cameras is None:
                self.cameras = CameraPipeline(scene, self.config, seed)
            else:
                self.cameras.load(scene, seed)

    @property
    def vehicle_list(self) -> list[Vehicle]:
        return list(self.vehicles.values())

    def vehicle(self, name: str | None = None) -> Vehicle:
        """The vehicle called ``name`` (the first one for None); an unknown name is a CommandError."""
        if name is None:
            return next(iter(self.vehicles.values()))
        try:
            return self.vehicles[name]
        except KeyError:
            known = ", ".join(self.vehicles)
            raise CommandError("invalid_argument", f"no vehicle {name!r}; the vehicles are {known}") from None

    def spawns(self) -> list[tuple[np.ndarray, float]]:
        """Each vehicle's start (position, yaw): its spec's, or the scene's spawn pattern."""
        unplaced = [spec for spec in self.specs if spec.spawn is None]
        points = iter(self.scene.spawn_points(len(unplaced)) if unplaced else [])
        return [
            (
                np.asarray(spec.spawn if spec.spawn is not None else next(points), dtype=float),
                self.scene.spawn_yaw if spec.yaw is None else float(spec.yaw),
            )
            for spec in self.specs
        ]

    def reset(
        self,
        seed: int | None = None,
        position: Sequence[float] | np.ndarray | None = None,
        yaw: float | None = None,
        scene: str | None = None,
        airborne: bool | None = None,
        vehicle: str | None = None,
        light: LightConfig | None = None,
        vegetation: float | None = None,
    ) -> VehicleState:
        """Restart at t = 0: every vehicle at its start (on the ground), the first one (or ``vehicle``) at
        ``position`` / ``yaw`` if given. A position above the ground starts hovering there (mode ``hold``)
        unless ``airborne=False``. ``light`` replaces the light section (RGB only); ``vegetation`` rebuilds
        the scene with that density. Returns that vehicle's state."""
        target = self.vehicle(vehicle)
        light = self.config.light if light is None else light
        cfg = self.config
        new = (
            scene or cfg.scene,
            cfg.seed if seed is None else seed,
            cfg.vegetation if vegetation is None else float(vegetation),
        )
        if scene is not None or new != (cfg.scene, cfg.seed, cfg.vegetation):
            previous, self.config.light = self.config.light, light
            try:
                self._load_scene(*new)  # raises for an unknown scene before anything changes
            except Exception:
                self.config.light = previous
                raise
            self.config.scene, self.config.seed, self.config.vegetation = new
        elif light != self.config.light:
            self.set_light(light)
        starts = dict(zip(self.vehicles, self.spawns(), strict=True))
        if position is not None or yaw is not None:
            pos, yaw0 = starts[target.name]
            starts[target.name] = (
                pos if position is None else np.asarray(position),
                yaw0 if yaw is None else yaw,
            )
        # the ROS clock never runs backwards: a reset continues it one control period after the last stamp
        self._stamp_base_ns = self.stamp_ns + self.control_period_ns if hasattr(self, "_stamp_base_ns") else 0
        self.t_ns = 0
        self._next_frame_ns = self.camera_period_ns
        self.frame_count = 0
        self._shots.clear()  # a reset ends the episode a trigger was for
        for v in self.vehicles.values():
            pos, heading = starts[v.name]
            v.place(pos, float(heading), airborne if v is target else None)
        # a fresh realisation each episode, the same sequence of them under the same seed
        self._episodes = getattr(self, "_episodes", -1) + 1
        self.wind.reset(np.random.SeedSequence([self.config.seed, 0x57494E44, self._episodes]))
        self._update_still_air()
        return target.state

    def set_light(self, light: LightConfig) -> None:
        """Light the scene with ``light`` from the next frame on (the renderer's shadow map is drawn again,
        nothing else changes). ValueError for a scene whose own light settings are bad."""
        if self.cameras is not None:
            self.cameras.set_light(light)
        self.config.light = light

    def _update_still_air(self) -> None:
        #: no wind model and a calm field: every vehicle's wind is zero (but for the wakes), set at once
        self._still_air = self.config.vehicle.wind == "none" and self.wind.calm

    def set_wind(self, config: Any, vehicle: str | None = None) -> None:
        """Change the wind field's settings (a :class:`~droneulator.config.WindConfig`) for every vehicle,
        or for ``vehicle`` only; the turbulence carries on, so the wind changes without a jump in its
        random part. A RotorPy profile (``vehicle.wind``) and the field are two models: a CommandError."""
        if self.config.vehicle.wind != "none" and not config.calm:
            raise CommandError(
                "invalid_argument",
                f"this world flies RotorPy's {self.config.vehicle.wind!r} wind (vehicle.wind): the wind "
                "field needs vehicle.wind = 'none'",
            )
        rows = None if vehicle is None else [list(self.vehicles).index(self.vehicle(vehicle).name)]
        self.wind.configure(config, rows)
        if vehicle is None:
            self.config.wind = config
        self._update_still_air()

    # ------------------------------------------------------------------ clocks
    @property
    def t(self) -> float:
        return self.t_ns / NS

    @property
    def stamp_ns(self) -> int:
        """The monotonic sim clock (ns): ``t_ns`` plus the time of every earlier episode."""
        return self._stamp_base_ns + self.t_ns

    def states_now(self) -> dict[str, VehicleState]:
        return {name: v.state for name, v in self.vehicles.items()}

    # ------------------------------------------------------------------ stepping
    def step(self, n: int = 1) -> StepResult:
        """Advance ``n`` control periods; returns the frames rendered and events raised meanwhile."""
        out = StepResult()
        dt = self.control_period_ns / NS
        vs = self.vehicle_list
        rows, cmds, flats = self._rows, self._cmds, self._flats
        parallel = len(vs) >= PARALLEL_ROWS
        rate = self.camera_schedule and not self.triggered
        for _ in range(n):
            t = self.t
            for i in sorted(self._busy):
                v = vs[i]
                cmd, ref, events = v.flight.update(rows[i], t, dt)
                for e in events:
                    e.vehicle = v.name
                out.events.extend(events)
                v._reference = ref
                self._se3[i] = cmd is None
                if cmd is None:
                    flats[i] = ref
                else:
                    cmds[i] = cmd
                self._active[i] = v.flight.mode != Mode.COLLIDED
                if v.flight.steady:  # holding or motors off: this command stands until the next one
                    self._busy.discard(i)
            if self._se3.any():
                se3_rows(rows, flats, self._se3, self._gains, self._gidx, cmds, self._Rc, parallel)
            if self._still_air:
                rows[:, STATE.wind] = 0.0
            elif self.config.vehicle.wind == "none":
                rows[:, STATE.wind] = self.wind.update(rows[:, STATE.x], rows[:, STATE.v])
            else:
                for i, v in enumerate(vs):
                    rows[i, STATE.wind] = v.wind.update(t, rows[i, STATE.x])
            if self._wake.active:
                downwash(rows, self._wake)
            self._imu[:] = 0.0
            if len(vs) > 1:
                self._period_start[:] = rows
            t_start = t
            t_end = self.t_ns + self.control_period_ns
            col = self.scene.collision
            while self.t_ns < t_end:
                t_next = min(t_end, self._next_frame_ns) if rate else t_end
                h = (t_next - self.t_ns) / NS
                self._hit[:] = False
                n_sub = substeps(h, self._substep)
                integrate_rows(
                    rows, cmds, self._active, h, n_sub, self.table, self._pidx, col.sdf, col.origin,
                    col.resolution, self._radius, self._imu, self._hit, self._work, self._R,
                )  # fmt: skip
                for i in np.flatnonzero(self._hit):
                    out.events.append(vs[i].on_collision())
                    self._active[i] = False
                self.t_ns = t_next
                if rate and self.t_ns == self._next_frame_ns:
                    self._shoot(out, None)
                    self._next_frame_ns += self.camera_period_ns
            if len(vs) > 1:
                self._vehicle_contacts(vs, out.events)
            self._finish_period(vs, dt, t_start, out.events)
            if self._shots:
                self._shoot(out, tuple(name for name in self.vehicles if name in self._shots))
                self._shots.clear()
        return out

    def _shoot(self, out: StepResult, rigs: tuple[str, ...] | None) -> None:
        """A camera instant now: the frames (own renderer) or the states for a render server."""
        if self.cameras is not None:
            out.frames.append(self.render(rigs))
        else:
            out.camera_states.append(self.states_now())
            out.camera_rigs.append(rigs)
        self.frame_count += 1

    def trigger(self, name: str | None = None) -> int:
        """Have vehicle ``name``'s cameras (the first vehicle's for None) shoot one frame set at the end of
        the next control period (``render.camera_trigger = "command"``); returns the stamp (ns) it will
        carry. Triggers of several vehicles in one period share one camera instant."""
        vehicle = self.vehicle(name)
        if not self.camera_schedule:
            raise CommandError("unsupported", "this world renders no cameras")
        if not self.triggered:
            raise CommandError(
                "unsupported",
                f"the cameras shoot at render.camera_hz ({self.config.render.camera_hz:g} Hz); start the "
                "simulator with render.camera_trigger=command to trigger them",
            )
        self._shots.add(vehicle.name)
        return self.stamp_ns + self.control_period_ns

    def _finish_period(self, vs: list[Vehicle], dt: float, t_start: float, events: list[Event]) -> None:
        """Every vehicle's IMU means over the period just stepped, and ``impact`` events for hard
        touchdowns."""
        imu = self._imu
        sf = imu[:, OUTPUT.specific_force] / dt
        held = dt - imu[:, OUTPUT.elapsed]
        for i in np.flatnonzero(held > 1e-12):  # time not integrated (stopped) is spent held by the obstacle
            sf[i] += (held[i] / dt) * vs[i].holding_force()
        self._motion[:, 0:3] = sf
        self._motion[:, 3:6] = imu[:, OUTPUT.delta_v] / dt
        for i in np.flatnonzero(imu[:, OUTPUT.touchdown_speed] > self._impact_speed):
            where = imu[i, OUTPUT.touchdown_position].tolist()
            speed = float(imu[i, OUTPUT.touchdown_speed])
            events.append(Event("impact", t_start + float(imu[i, OUTPUT.touchdown_time]),
                                {"position": where, "speed": speed}, vs[i].name))  # fmt: skip

    def _vehicle_contacts(self, vs: list[Vehicle], events: list[Event]) -> None:
        """Vehicles whose bodies overlap stop where they were at the start of the period (both)."""
        rows = self._rows
        pairs = contacts(rows[:, 0:3], self._radius, self._active)
        for a, b in pairs:
            for i in (a, b):
                rows[i] = self._period_start[i]
            vs[a].on_collision(with_=vs[b].name)
            vs[b].on_collision(with_=vs[a].name)
            self._active[a] = self._active[b] = False
            mid = 0.5 * (rows[a, STATE.x] + rows[b, STATE.x])
            names = [vs[a].name, vs[b].name]
            events.append(Event("collision", self.t, {"position": mid.tolist(), "vehicles": names}, names[0]))

    def run(self, seconds: float) -> StepResult:
        """Step for ``seconds`` of simulated time, collecting frames and events."""
        return self.step(max(1, round(seconds * NS / self.control_period_ns)))

    def run_until(self, predicate: Any, timeout: float, events: list[Event] | None = None) -> bool:
        """Step until ``predicate(world)`` holds or ``timeout`` sim seconds pass; events are appended."""
        end = self.t_ns + round(timeout * NS)
        while self.t_ns < end:
            res = self.step()
            if events is not None:
                events.extend(res.events)
            if predicate(self):
                return True
        return False

    # ------------------------------------------------------------------ rendering
    def render(self, rigs: Collection[str] | None = None) -> FrameSet:
        """Render every camera of every vehicle (of ``rigs`` only, when given; every body is drawn) from the
        current states in one call (also usable outside the camera schedule). The images are copies the
        caller owns, as each camera delivers them (:mod:`droneulator.sensors.camera_models`: noise,
        distortion, exposure; untouched when ideal)."""
        if self.cameras is None:
            raise RuntimeError("this World was created with render=False")
        states = self.states_now()
        poses = {name: st.T_world_body for name, st in states.items()}
        motion = {name: (st.velocity, st.angular_velocity) for name, st in states.items()}
        return FrameSet(self.t_ns, states, self.cameras.frames(poses, rigs, motion))

    def close(self) -> None:
        if self.cameras is not None:
            self.cameras.close()
            self.cameras = None

    def __enter__(self) -> World:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
