"""The world: ``worlds`` copies (one by default) of one scene, each with its clock and every vehicle in it,
stepped together in lockstep by one compiled step (:mod:`droneulator.world.step`).

Simulation time is an integer count of nanoseconds. :meth:`World.step` advances the first world one
control period, its vehicles driven by their flight controllers:

1. every vehicle's flight controller gives its rotor command or its reference (vehicles holding or with
   the motors off keep the last one, without a call);
2. each vehicle's wind is the wind field's where it is (:mod:`droneulator.wind.field`: mean wind, Dryden
   turbulence, gusts, the canopy's shelter; or a RotorPy profile, ``vehicle.wind``);
3. the compiled step (:mod:`droneulator.world.step`) adds the rotor wakes of the vehicles above
   (:mod:`droneulator.world.downwash`), turns every reference into rotor commands (SE(3)) and integrates
   every row of the state array (``states``, laid out ``(worlds, vehicles, STATE_SIZE)``), split at camera
   instants so that every frame is rendered from the exact state at ``k / camera_hz``, with the scene's
   collisions per row, each vehicle by its contact model (``vehicle.contact_model``: ``stop``, ``physical``
   or ``crash``; docs/contact.md), a ``collision`` event saying what it touched;
4. vehicles whose bodies overlap collide (:mod:`droneulator.world.contact`): one ``collision`` event
   names both, and each meets the other by its contact model (``stop``: where it was at the start of the
   period, held);
5. each vehicle's IMU means and hard touchdowns; the spray systems (``spray.enabled``); each vehicle's
   battery (``battery.enabled``, docs/battery.md): drained by its rotors' power, its sagged voltage setting
   the top rotor speed of the next period in the vehicle's parameter row;
6. with triggered cameras (``render.camera_trigger=command``), the frame sets :meth:`World.trigger` asked
   for, at the end of the period, instead of the camera rate's.

Many worlds (learning's batched envs) are driven row by row instead: :meth:`World.place` restarts worlds
by mask (hovering at given poses, in a scene variant), :meth:`World.velocity` gives velocity-mode
commands (the compiled velocity reference every ``Vehicle.velocity`` runs) and :meth:`World.step_frame`
advances each chosen world to its next camera instant in one call, with the same compiled step.

One vehicle is the default (:class:`~droneulator.config.SimConfig` with no ``vehicles``);
``world.vehicle()`` is its handle.
"""

from __future__ import annotations

import functools
import logging
import math
from collections.abc import Collection, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from droneulator.commands.errors import CommandError
from droneulator.config import FaultSpec, LightConfig, SimConfig, load_config
from droneulator.controllers.flight import Event, Mode
from droneulator.controllers.inner import SETPOINT_SIZE
from droneulator.controllers.velocity import VCMD, VREF_SIZE, start_reference, velocity_limits
from droneulator.frames import quat_to_matrix, yaw_of
from droneulator.scenes import get_scene
from droneulator.scenes.base import Scene
from droneulator.state import FLAT_SIZE, STATE, STATE_SIZE
from droneulator.vehicles.battery import Battery
from droneulator.vehicles.dynamics import (
    CONTACT_CRASH,
    CONTACT_PHYSICAL,
    CONTACT_STOP,
    OUTPUT,
    OUTPUT_SIZE,
    PARALLEL_ROWS,
    PARAM_WMAX,
    TOUCH_FOLIAGE,
    TOUCH_WOOD,
    ParamTable,
    hover_speed,
    pack_params,
    with_payload,
    work_arrays,
)
from droneulator.vehicles.vehicle import Vehicle, VehicleState
from droneulator.wind.field import WindField
from droneulator.world import step as kernel
from droneulator.world.downwash import WakeModel, wakes
from droneulator.world.faults import FaultBoard
from droneulator.world.step import ATTITUDE, FLAT, RATES, ROTORS, VELOCITY, SdfStack

if TYPE_CHECKING:
    from droneulator.render.pipeline import CameraPipeline
    from droneulator.spray.spraying import Spraying

NS = 1_000_000_000

log = logging.getLogger("droneulator.sim")

#: the compiled step's mode for the flight modes whose reference is an inner-loop setpoint, not a flat output
_INNER_MODES = {Mode.RATES: RATES, Mode.ATTITUDE: ATTITUDE}
#: the compiled step's code of each contact model (``vehicle.contact_model``), and of what a row touched
_CONTACT_CODES = {"stop": CONTACT_STOP, "physical": CONTACT_PHYSICAL, "crash": CONTACT_CRASH}
_TOUCHES = {TOUCH_FOLIAGE: "foliage", TOUCH_WOOD: "wood"}


def _rotors(mask: int) -> list[int]:
    """The rotors (RotorPy's order, from 0) of a bit mask."""
    return [i for i in range(4) if mask >> i & 1]


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
    """``worlds`` copies (one by default) of a scene, a clock and the vehicles of ``config.vehicles`` (one by
    default), stepped in lockstep.

    The first world's vehicles have handles (:meth:`vehicle`) whose flight controllers drive them through
    :meth:`step` (one world). Any number of worlds is driven row by row with the batched commands
    (:meth:`place`, :meth:`velocity`, :meth:`step_frame`): each world its own clock, scene variant
    (:meth:`add_scene`), wind and reset, all stepped by one compiled call, the vehicles of a world seeing
    each other's wakes and bodies (learning's batched envs).

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
        worlds: int = 1,
    ) -> None:
        self.config = config or load_config()
        if scene is not None:
            self.config.scene = scene
        if seed is not None:
            self.config.seed = seed
        if isinstance(worlds, bool) or not isinstance(worlds, (int, np.integer)) or worlds < 1:
            raise ValueError(f"worlds must be a positive integer, got {worlds!r}")
        cfg = self.config
        self.specs = cfg.vehicle_specs()
        self.num_worlds = W = int(worlds)
        self.num_vehicles = n = len(self.specs)
        # a scene without room for the fleet fails here (ValueError), before any vehicle is built
        get_scene(cfg.scene, cfg.seed, cfg.vegetation).spawn_points(sum(s.spawn is None for s in self.specs))
        #: every vehicle's state, ``(worlds, vehicles, STATE_SIZE)``
        self.states = np.zeros((W, n, STATE_SIZE))
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
        self._radius = np.array([v.collision_radius for v in vs])
        self._hover = np.array([v.hover_speed for v in vs])
        self._lim = np.stack([velocity_limits(v.flight_config) for v in vs])
        self._max_speed = np.array([v.flight_config.max_speed for v in vs])
        #: what the rows' commands below the SE(3) controller may ask for (:meth:`rotors_rows` ...)
        self._rotor_range = np.array([[v.quad_params["rotor_speed_min"], v.quad_params["rotor_speed_max"]]
                                      for v in vs], dtype=float)  # fmt: skip
        self._max_thrust = np.array([v.max_thrust for v in vs])
        self._max_rate = np.radians([v.flight_config.max_body_rate_deg_s for v in vs])
        self._min_cos_tilt = np.cos(np.radians([v.flight_config.max_attitude_tilt_deg for v in vs]))
        self._impact_speed = cfg.vehicle.impact_speed
        self._wake = WakeModel.of(vs)
        # the rows' commands, flags and scratch for the compiled step (:mod:`droneulator.world.step`)
        #: how each row gets its rotor command: FLAT, VELOCITY, ROTORS, RATES or ATTITUDE
        self.mode = np.full((W, n), FLAT, dtype=np.int64)
        self._flats = np.zeros((W, n, FLAT_SIZE))
        self._cmds = np.zeros((W, n, 4))
        self._vref = np.zeros((W, n, VREF_SIZE))
        self._out = np.zeros((W, n, OUTPUT_SIZE))
        #: rows that began a contact with the scene during the last step (under ``stop``: stopped there,
        #: inactive), and what they touched (:func:`~droneulator.vehicles.dynamics.integrate`'s code)
        self.hit = np.zeros((W, n), dtype=bool)
        self._hit_t = np.zeros((W, n), dtype=np.int64)
        self.hit_kind = np.zeros((W, n), dtype=np.int64)
        #: what a touch does to each row (``vehicle.contact_model``: CONTACT_STOP, _PHYSICAL, _CRASH)
        codes = np.array([_CONTACT_CODES[str(spec.contact_model)] for spec in self.specs], dtype=np.int64)
        self.contact_model = np.tile(codes, (W, 1))
        #: each rotor's efficiency per row, ``(worlds, vehicles, 4)``: 1 healthy, lower with a rotor fault
        #: (:mod:`droneulator.world.faults`) or a learning env's draw, 0 for a propeller lost on wood; its
        #: thrust and moments scale by it every sub-step; a reset or a place makes every rotor whole again
        self.rotor_efficiency = np.ones((W, n, 4))
        #: rows crashed under ``crash``: their rotors stay stopped until the row is placed again
        self.dead = np.zeros((W, n), dtype=bool)
        #: rows integrated (a collided or retired row is not)
        self.active = np.ones((W, n), dtype=bool)
        #: for each row, the vehicle of its world it touched in the last :meth:`step_frame` (-1: none)
        self.touched = np.full((W, n), -1, dtype=np.int64)
        work, R = work_arrays(W * n)
        self._work, self._R = work.reshape(W, n, *work.shape[1:]), R.reshape(W, n, 3, 3)
        self._period_start = np.zeros((W, n, STATE_SIZE))
        self._wind_rows = np.zeros((W, n, 3))
        #: each row's state at its world's last camera instant (:meth:`step_frame`)
        self.camera_states = np.zeros((W, n, STATE_SIZE))
        self._all = np.ones(W, dtype=bool)
        #: vehicles whose command must be computed next period: not :attr:`FlightController.steady`, or
        #: commanded since (each flight controller reports its commands); the others keep theirs
        self._busy: set[int] = set(range(n))
        for i, v in enumerate(vs):
            v.flight.on_command = functools.partial(self._busy.add, i)
        self.control_period_ns = round(NS / cfg.vehicle.control_hz)
        self.camera_period_ns = round(NS / cfg.render.camera_hz)
        self._substep = 1.0 / (cfg.vehicle.control_hz * cfg.vehicle.substeps)
        #: each world's clock (ns since its reset) and next camera instant
        self.clocks = np.zeros(W, dtype=np.int64)
        self._next_frame = np.full(W, self.camera_period_ns, dtype=np.int64)
        self.render_enabled = render
        self.camera_schedule = render or external_cameras
        #: cameras shoot only when :meth:`trigger` asks (``render.camera_trigger = "command"``)
        self.triggered = cfg.render.camera_trigger == "command"
        #: vehicles whose cameras shoot at the end of the next control period
        self._shots: set[str] = set()
        #: the camera pipeline (:mod:`droneulator.render.pipeline`) when the world renders its own frames
        self.cameras: CameraPipeline | None = None
        self.scene: Scene
        #: the scene variants worlds fly in (the first is the config's scene) and each world's variant
        self.scenes: list[Scene] = []
        self.variant = np.zeros(W, dtype=np.int64)
        #: the wind field every vehicle flies in (:mod:`droneulator.wind.field`), seeded by the world's seed
        self.wind = WindField(cfg.wind, W * n, self.control_period_ns / NS, cfg.seed)
        #: the vehicles' spray systems and their droplets (``spray.enabled``; the first world's)
        self.spraying: Spraying | None = None
        #: each vehicle's battery (its ``battery.enabled``), drained in :meth:`step`; the batched rows of many
        #: worlds (:meth:`step_frame`) fly without one
        self.batteries: dict[str, Battery] = {}
        #: a rotor's disk area (m^2) of each vehicle with a battery
        self._rotor_area: dict[str, float] = {}
        for i, v in enumerate(vs):
            bat = v.spec.battery
            if bat is not None and bat.enabled and W == 1:
                self.batteries[v.name] = Battery(bat, str(v.spec.params))
                self._rotor_area[v.name] = v.disk_area / 4.0
                self._own_row(i, "own")
        #: the faults of the first world (docs/faults.md): the config's schedule, the ``fault`` op's
        self.faults = FaultBoard(self)
        self._load_scene(cfg.scene, cfg.seed, cfg.vegetation)
        self.reset()
        if cfg.spray.enabled:
            from droneulator.spray.spraying import Spraying

            self.spraying = Spraying(self)

    # ------------------------------------------------------------------ setup
    def _load_scene(self, name: str, seed: int, vegetation: float) -> None:
        scene = get_scene(name, seed, vegetation)
        # a scene without room for the fleet fails here (ValueError), before anything changes
        scene.spawn_points(sum(spec.spawn is None for spec in self.specs))
        self.scene = scene
        self.scenes[:1] = [scene]
        self._sdfs = SdfStack([sc.collision for sc in self.scenes])
        self.wind.collision = scene.collision
        if self.render_enabled:
            from droneulator.render.pipeline import CameraPipeline

            if self.cameras is None:
                self.cameras = CameraPipeline(scene, self.config, seed)
            else:
                self.cameras.load(scene, seed)

    def add_scene(self, scene: Scene) -> int:
        """Make ``scene`` a variant worlds can fly in (:meth:`place` with ``variant``); returns its index."""
        self.scenes.append(scene)
        self._sdfs = SdfStack([sc.collision for sc in self.scenes])
        return len(self.scenes) - 1

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

    def set_payload(self, name: str | None, kg: float, offset: Any = (0.0, 0.0, 0.0)) -> None:
        """Carry ``kg`` of payload (e.g. a spray tank's liquid) at ``offset`` (body FLU, m) on vehicle
        ``name``, in every world: its mass and inertia in the dynamics (and the ground contact's legs),
        and in its SE(3) controller's feed-forward, as :func:`~droneulator.vehicles.dynamics.with_payload`
        gives them. The vehicle gets a parameter row of its own (with the top rotor speed its battery
        leaves)."""
        v = self.vehicle(name)
        if not (isinstance(kg, int | float) and math.isfinite(kg) and kg >= 0.0):
            raise ValueError(f"payload must be a finite mass >= 0 kg, got {kg!r}")
        i = v.index
        q = with_payload(v.base_params, float(kg), offset)
        v.quad_params = q
        v.packed = pack_params(q, self.config.vehicle.aero, True, v.contact)
        v.hover_speed = hover_speed(v.packed[0])
        self._own_row(i, "own")
        row = int(self._pidx[i])
        for arr, value in zip((self.table.params, self.table.geometry, self.table.directions), v.packed,
                              strict=True):  # fmt: skip
            arr[row] = value
        bat = self.batteries.get(v.name)
        if bat is not None:  # the new row keeps the top speed the battery leaves
            self.table.params[row, PARAM_WMAX] = bat.top_speed * float(q["rotor_speed_max"])
        v.flight.se3.set_mass(q)
        self._gains[i] = v.flight.se3.gains()
        self._hover[i] = v.hover_speed

    def _own_row(self, i: int, why: str) -> None:
        """Give vehicle ``i`` a parameter row of its own (a copy of the one it shares with others), so that
        what changes its row (its battery, its payload) changes no other vehicle."""
        t, row = self.table, int(self._pidx[i])
        if np.count_nonzero(self._pidx == row) < 2:
            return
        v = self.vehicle_list[i]
        packed = (t.params[row].copy(), t.geometry[row].copy(), t.directions[row].copy())
        own = t.add((v.spec.params, v.name, why), packed)
        for arr, value in zip((t.params, t.geometry, t.directions), packed, strict=True):
            arr[own] = value
        self._pidx[i] = own

    def _drain(self, vs: list[Vehicle], dt: float, events: list[Event]) -> None:
        """Each battery over the period just stepped (docs/battery.md): the rotors' electrical power at the
        period's end (momentum theory, thrust ``k_eta w^2``, climbing along the thrust axis) drawn for
        ``dt``, and the vehicle's top rotor speed from the sagged voltage; a ``battery_empty`` event when a
        pack is spent."""
        rows, params = self._rows, self.table.params
        for i, v in enumerate(vs):
            bat = self.batteries.get(v.name)
            if bat is None:
                continue
            s = rows[i].tolist()  # floats: cheaper than numpy for these few numbers
            k_eta = v.quad_params["k_eta"]
            thrusts = [k_eta * w * w for w in s[STATE.rotor_speeds]]
            qx, qy, qz, qw = s[STATE.q]
            ax, ay, az = (a - b for a, b in zip(s[STATE.v], s[STATE.wind], strict=True))  # airspeed
            climb = (2.0 * (qx * qz + qw * qy) * ax + 2.0 * (qy * qz - qw * qx) * ay
                     + (1.0 - 2.0 * (qx * qx + qy * qy)) * az)  # fmt: skip
            was_empty = bat.empty
            bat.draw_power(bat.electrical_power(thrusts, self._rotor_area[v.name], climb), dt)
            if bat.empty and not was_empty:
                events.append(Event("battery_empty", self.t, {"position": s[STATE.x]}, v.name))
            params[self._pidx[i], PARAM_WMAX] = bat.follow(dt) * float(v.quad_params["rotor_speed_max"])

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
        self.clocks[:] = 0
        self._next_frame[:] = self.camera_period_ns
        self.frame_count = 0
        self._shots.clear()  # a reset ends the episode a trigger was for
        self.faults.reset()  # and the faults of it
        for v in self.vehicles.values():
            pos, heading = starts[v.name]
            v.place(pos, float(heading), airborne if v is target else None)
        self.mode[:] = FLAT
        self.active[:] = True
        self.rotor_efficiency[:] = 1.0
        self.dead[:] = False
        self.hit[:] = False
        self.touched[:] = -1
        self.variant[:] = 0
        self._busy.update(range(self.num_vehicles))
        if self.spraying is not None:  # a fresh cloud (the scene's targets if it changed), full tanks
            self.spraying.reset()
        for i, v in enumerate(self.vehicle_list):  # charged packs (the airframes' top speeds, when full)
            bat = self.batteries.get(v.name)
            if bat is not None:
                bat.reset()
                top = bat.top_speed * float(v.quad_params["rotor_speed_max"])
                self.table.params[self._pidx[i], PARAM_WMAX] = top
        if self.num_worlds > 1:  # every other world a copy of the first, holding where it is
            self.states[1:] = self._rows
            self._flats[1:] = 0.0
            self._flats[1:, :, 0:3] = self._rows[:, STATE.x]
            self._flats[1:, :, 9] = [yaw_of(q) for q in self._rows[:, STATE.q]]
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
    def t_ns(self) -> int:
        """The first world's clock (ns since its reset)."""
        return int(self.clocks[0])

    @t_ns.setter
    def t_ns(self, value: int) -> None:
        self.clocks[0] = value

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
    def _parallel(self) -> bool:
        return self.states.shape[0] * self.states.shape[1] >= PARALLEL_ROWS

    def _args(self) -> tuple[Any, ...]:
        """The compiled step's arrays, in :func:`~droneulator.world.step.run_period_serial`'s order after
        ``t_to``."""
        sd = self._sdfs
        t = self.table
        return (self.clocks, self.states, self._cmds, self.active, self._substep, t.params, t.geometry,
                t.directions, self._pidx, sd.buffer, sd.wood, sd.offsets, sd.shapes, sd.origins,
                sd.resolutions, self.variant, self._radius, self.contact_model, self.rotor_efficiency,
                self.dead, self._out, self.hit, self._hit_t, self.hit_kind, self._work, self._R)  # fmt: skip

    def _begin_args(self, dt: float) -> tuple[Any, ...]:
        """The arrays :func:`~droneulator.world.step.run_period_serial` takes after :meth:`_args`'s."""
        return (self._wind_rows, self._period_start, self.mode, self._flats, self._vref, dt, self._lim,
                self._gains)  # fmt: skip

    def step(self, n: int = 1) -> StepResult:
        """Advance ``n`` control periods of the first world, its vehicles driven by their flight controllers;
        returns the frames rendered and events raised meanwhile. (Many worlds step with
        :meth:`step_frame`.)"""
        if self.num_worlds > 1:
            raise RuntimeError("a World of many worlds steps with step_frame(), its rows driven by place() "
                               "and velocity()")  # fmt: skip
        out = StepResult()
        dt = self.control_period_ns / NS
        vs = self.vehicle_list
        rows, cmds, flats = self._rows, self._cmds[0], self._flats[0]
        rate = self.camera_schedule and not self.triggered
        go = self._all
        args = self._args()
        extra = self._begin_args(dt)
        run_period = kernel.run_period_parallel if self._parallel() else kernel.run_period_serial
        t_to = np.zeros(1, dtype=np.int64)
        clock = self.clocks
        self.hit[:] = False
        self.wind.dt = dt
        for _ in range(n):
            if args[5] is not self.table.params:  # a vehicle got a parameter row of its own meanwhile
                args = self._args()
            if not self.faults.idle:
                out.events.extend(self.faults.update())
            t = self.t
            for i in sorted(self._busy):
                v = vs[i]
                cmd, ref, events = v.flight.update(rows[i], t, dt)
                for e in events:
                    e.vehicle = v.name
                out.events.extend(events)
                inner = _INNER_MODES.get(v.flight.mode)
                v._reference = None if inner is not None else ref
                if cmd is None and inner is None:
                    flats[i] = ref
                    self.mode[0, i] = FLAT
                elif cmd is None:  # the row keeps the rate loop's integral after the setpoint
                    if self.mode[0, i] != inner:
                        flats[i] = 0.0
                    flats[i, :SETPOINT_SIZE] = ref[:SETPOINT_SIZE]
                    self.mode[0, i] = inner
                else:
                    cmds[i] = cmd
                    self.mode[0, i] = ROTORS
                self.active[0, i] = v.flight.mode != Mode.COLLIDED
                if v.flight.steady:  # holding or motors off: this command stands until the next one
                    self._busy.discard(i)
            wind = self._wind_rows[0]
            if self._still_air:
                wind[:] = 0.0
            elif self.config.vehicle.wind == "none":
                wind[:] = self.wind.update(rows[:, STATE.x], rows[:, STATE.v])
            else:
                for i, v in enumerate(vs):
                    wind[i] = v.wind.update(t, rows[i, STATE.x])
            if self._wake.active:
                wind += wakes(rows, self._wake)
            t_start = t
            now = int(clock[0])
            t_end = now + self.control_period_ns
            begin = True
            while now < t_end:
                t_to[0] = min(t_end, int(self._next_frame[0])) if rate else t_end
                if run_period(go, begin, t_to, *args, *extra):
                    for i in np.flatnonzero(self.hit[0]):
                        code = int(self.hit_kind[0, i])
                        when, touch = self._hit_t[0, i] / NS, _TOUCHES[code & 3]
                        lost = _rotors(code >> 2)
                        out.events.append(vs[i].on_collision(t=when, contact=touch, rotors_lost=lost))
                    self.hit[:] = False
                begin = False
                now = int(clock[0])
                if rate and now == self._next_frame[0]:
                    self._shoot(out, None)
                    self._next_frame[0] += self.camera_period_ns
            if len(vs) > 1:
                t = self.table
                pairs = kernel.end_period(go, self.states, self.active, self._radius, self._period_start,
                                          self.contact_model, self.rotor_efficiency, self.dead, t.geometry,
                                          self._pidx)  # fmt: skip
                self._vehicle_contacts(vs, sorted(tuple(int(x) for x in p[1:]) for p in pairs), out.events)
            self._finish_period(vs, dt, t_start, out.events)
            if self.spraying is not None:
                self.spraying.step()
            if self.batteries:
                self._drain(vs, dt, out.events)
            if self._shots:
                self._shoot(out, tuple(name for name in self.vehicles if name in self._shots))
                self._shots.clear()
        return out

    # ------------------------------------------------------------------ many worlds, row by row
    def _worlds(self, idx: Any) -> np.ndarray:
        """World indices from ``idx``: None (all), a bool mask or indices."""
        if idx is None:
            return np.arange(self.num_worlds)
        a = np.asarray(idx)
        rows = np.flatnonzero(a) if a.dtype == bool else a.astype(np.int64).reshape(-1)
        if len(rows) and (rows.min() < 0 or rows.max() >= self.num_worlds):
            raise ValueError(f"world indices must lie in [0, {self.num_worlds}), got {rows.tolist()[:8]}")
        return rows

    def _per_row(self, name: str, values: Any, k: int) -> np.ndarray:
        """``values`` as (k, vehicles) floats: one per vehicle of each world (or one per world with one
        vehicle), finite."""
        n = self.num_vehicles
        a = np.asarray(values, dtype=float)
        if a.size != k * n:
            raise ValueError(f"{name} needs {k} x {n} values (worlds x vehicles), got shape {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name} must be finite numbers")
        return a.reshape(k, n)

    def place(self, worlds: Any, positions: Any, yaws: Any, variant: Any = None) -> None:
        """Restart worlds ``worlds`` (indices or a mask) at t = 0, their vehicles at rest hovering at
        ``positions`` ``(k, vehicles, 3)`` facing ``yaws`` ``(k, vehicles)``, in scene variant ``variant``
        (one index or one per world; None: as they were). The rows then follow the batched commands
        (:meth:`velocity`, else they hold where they were placed)."""
        rows = self._worlds(worlds)
        k, n = len(rows), self.num_vehicles
        pos = self._per_row("positions", positions, k * 3).reshape(k * n, 3)
        yaw = self._per_row("yaws", yaws, k).reshape(k * n)
        if variant is not None:
            var = np.broadcast_to(np.asarray(variant, dtype=np.int64), (k,))
            if var.min() < 0 or var.max() >= len(self.scenes):
                raise ValueError(f"scene variants are 0 to {len(self.scenes) - 1}, got {var.tolist()[:8]}")
            self.variant[rows] = var
        self.clocks[rows] = 0
        self._next_frame[rows] = self.camera_period_ns
        self.place_rows(np.repeat(rows, n), np.tile(np.arange(n), k), pos, yaw)

    def _pairs(self, worlds: Any, vehicles: Any) -> tuple[np.ndarray, np.ndarray]:
        """Row indices ``(worlds[j], vehicles[j])``, checked."""
        w = np.asarray(worlds, dtype=np.int64).reshape(-1)
        v = np.asarray(vehicles, dtype=np.int64).reshape(-1)
        if len(w) != len(v):
            raise ValueError(f"{len(w)} worlds for {len(v)} vehicles")
        W, n = self.num_worlds, self.num_vehicles
        if len(w) and (w.min() < 0 or w.max() >= W or v.min() < 0 or v.max() >= n):
            raise ValueError(f"rows must lie in {self.num_worlds} worlds x {self.num_vehicles} vehicles")
        return w, v

    def place_rows(self, worlds: Any, vehicles: Any, positions: Any, yaws: Any) -> None:
        """Put vehicle ``vehicles[j]`` of world ``worlds[j]`` at rest hovering at ``positions[j]`` facing
        ``yaws[j]``; its world's clock goes on (a respawn: the other vehicles fly on)."""
        w, v = self._pairs(worlds, vehicles)
        m = len(w)
        pos = np.asarray(positions, dtype=float).reshape(m, 3)
        yaw = np.asarray(yaws, dtype=float).reshape(m)
        if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(yaw))):
            raise ValueError("positions and yaws must be finite")
        s = np.zeros((m, STATE_SIZE))
        s[:, STATE.x] = pos
        s[:, 8], s[:, 9] = np.sin(yaw / 2), np.cos(yaw / 2)
        s[:, STATE.rotor_speeds] = self._hover[v, None]
        self.states[w, v] = s
        flats = np.zeros((m, FLAT_SIZE))
        flats[:, 0:3] = pos
        flats[:, 9] = yaw
        self._flats[w, v] = flats
        self.mode[w, v] = FLAT
        self.active[w, v] = True
        self.rotor_efficiency[w, v] = 1.0
        self.dead[w, v] = False
        self.hit[w, v] = False
        self.touched[w, v] = -1
        self.wind.reset_rows(w * self.num_vehicles + v)

    def velocity(self, worlds: Any, forward: Any, yaw_rate: Any) -> None:
        """Velocity-mode commands (forward speed m/s, yaw rate rad/s; ``(k, vehicles)``) for the vehicles of
        worlds ``worlds`` (:meth:`velocity_rows` for some of them)."""
        rows = self._worlds(worlds)
        k, n = len(rows), self.num_vehicles
        f = self._per_row("forward", forward, k)
        r = self._per_row("yaw_rate", yaw_rate, k)
        self.velocity_rows(np.repeat(rows, n), np.tile(np.arange(n), k), f, r)

    def velocity_rows(self, worlds: Any, vehicles: Any, forward: Any, yaw_rate: Any) -> None:
        """Velocity-mode commands for vehicle ``vehicles[j]`` of world ``worlds[j]``, as ``Vehicle.velocity``:
        a row entering the mode starts its reference where its hold reference is, at its current speed.
        Retired or collided rows take none (ValueError)."""
        w, v = self._pairs(worlds, vehicles)
        f = np.asarray(forward, dtype=float).reshape(len(w))
        r = np.asarray(yaw_rate, dtype=float).reshape(len(w))
        if not (np.all(np.isfinite(f)) and np.all(np.isfinite(r))):
            raise ValueError("forward and yaw_rate must be finite numbers")
        if np.any(np.abs(f) > self._max_speed[v]) or np.any(np.abs(r) > math.pi):
            raise ValueError(f"need |forward| <= {self._max_speed.min():g} m/s and |yaw_rate| <= pi rad/s")
        if not self.active[w, v].all():
            raise ValueError("a collided or retired vehicle takes no command until it is placed again")
        for j in np.flatnonzero(self.mode[w, v] != VELOCITY):
            b, i = w[j], v[j]
            hold = self._flats[b, i]
            heading = float(hold[9])
            speed0 = float(self.states[b, i, 3:5] @ (math.cos(heading), math.sin(heading)))
            start_reference(self._vref[b, i], hold[0:3], heading, speed0, 0.0)
            self.mode[b, i] = VELOCITY
        self._vref[w, v, VCMD] = f
        self._vref[w, v, VCMD + 1] = r

    def _inner_rows(self, w: np.ndarray, v: np.ndarray, mode: int, values: np.ndarray) -> None:
        """Put rows ``(w[j], v[j])`` in compiled-step mode ``mode`` with the setpoints ``values[j]``; a row
        entering RATES starts its rate loop's integral at zero."""
        if not self.active[w, v].all():
            raise ValueError("a collided or retired vehicle takes no command until it is placed again")
        entering = self.mode[w, v] != mode
        self._flats[w[entering], v[entering]] = 0.0
        self.mode[w, v] = mode
        if mode == ROTORS:
            self._cmds[w, v] = values
        else:
            self._flats[w, v, : values.shape[1]] = values

    def _thrusts(self, v: np.ndarray, thrust: Any) -> np.ndarray:
        f = np.asarray(thrust, dtype=float).reshape(len(v))
        if not np.all(np.isfinite(f)):
            raise ValueError("thrust must be finite numbers")
        if np.any(f < 0.0) or np.any(f > self._max_thrust[v]):
            raise ValueError(f"thrust must lie in [0, max_thrust] N ({self._max_thrust.min():g} N or more)")
        return f

    def rotors_rows(self, worlds: Any, vehicles: Any, rotor_speeds: Any) -> None:
        """Rotor speeds (rad/s, ``(k, 4)``, each in its airframe's range) for vehicle ``vehicles[j]`` of
        world ``worlds[j]``, as ``Vehicle.rotors`` (docs/control.md); they stand until the next command
        (the batched rows have no stream timeout: a learning agent commands every frame). ValueError for
        a value out of range."""
        w, v = self._pairs(worlds, vehicles)
        speeds = np.asarray(rotor_speeds, dtype=float).reshape(len(w), 4)
        if not np.all(np.isfinite(speeds)):
            raise ValueError("rotor speeds must be finite numbers")
        lo, hi = self._rotor_range[v, 0:1], self._rotor_range[v, 1:2]
        if np.any(speeds < lo) or np.any(speeds > hi):
            raise ValueError("rotor speeds must lie in each airframe's [rotor_speed_min, rotor_speed_max]")
        self._inner_rows(w, v, ROTORS, speeds)

    def rates_rows(self, worlds: Any, vehicles: Any, thrust: Any, body_rates: Any) -> None:
        """Collective thrust (N, ``(k,)``) and body rates (rad/s, body FLU, ``(k, 3)``) for rows, as
        ``Vehicle.rates``, flown by the compiled rate loop; they stand until the next command."""
        w, v = self._pairs(worlds, vehicles)
        f = self._thrusts(v, thrust)
        rates = np.asarray(body_rates, dtype=float).reshape(len(w), 3)
        if not np.all(np.isfinite(rates)):
            raise ValueError("body rates must be finite numbers")
        if np.any(np.abs(rates) > self._max_rate[v]):
            raise ValueError("body rates must lie within flight.max_body_rate_deg_s")
        self._inner_rows(w, v, RATES, np.column_stack([f, rates]))

    def attitude_rows(self, worlds: Any, vehicles: Any, thrust: Any, quaternions: Any) -> None:
        """Collective thrust (N, ``(k,)``) and attitudes (unit quaternions ``[x, y, z, w]``, ``(k, 4)``,
        normalised; tilted at most ``flight.max_attitude_tilt_deg``) for rows, as ``Vehicle.attitude``,
        flown by the compiled attitude loop; they stand until the next command."""
        w, v = self._pairs(worlds, vehicles)
        f = self._thrusts(v, thrust)
        q = np.asarray(quaternions, dtype=float).reshape(len(w), 4)
        norm = np.linalg.norm(q, axis=1)
        if not np.all(np.isfinite(q)) or np.any(np.abs(norm - 1.0) > 0.01):
            raise ValueError("quaternions must be finite unit quaternions [x, y, z, w] (norm 1 within 1 %)")
        q = q / norm[:, None]
        up = np.array([quat_to_matrix(x)[2, 2] for x in q])
        if np.any(up < self._min_cos_tilt[v] - 1e-12):
            raise ValueError("attitudes must be tilted at most flight.max_attitude_tilt_deg from level")
        self._inner_rows(w, v, ATTITUDE, np.column_stack([f, q]))

    def retire(self, worlds: Any, vehicles: Any) -> None:
        """Take vehicle rows out of their worlds until the world is placed again: the rows ``(worlds[j],
        vehicles[j])`` stop being integrated, touched and seen, and their rotors (and wakes) stop."""
        w, v = self._pairs(worlds, vehicles)
        self.active[w, v] = False
        self.mode[w, v] = FLAT
        self.states[w, v, STATE.rotor_speeds] = 0.0
        self.states[w, v, 3:6] = 0.0

    def set_wind_rows(self, configs: Any, worlds: Any = None) -> None:
        """The wind settings (one :class:`~droneulator.config.WindConfig`, or one per world) of the vehicles
        of worlds ``worlds`` (None: all), from their next step on."""
        rows = self._worlds(worlds)
        n = self.num_vehicles
        per = [configs] * len(rows) if not isinstance(configs, (list, tuple)) else list(configs)
        if len(per) != len(rows):
            raise ValueError(f"{len(per)} wind configs for {len(rows)} worlds")
        self.wind.configure([c for c in per for _ in range(n)], (rows[:, None] * n + np.arange(n)).ravel())
        self._update_still_air()

    def frame_t_ns(self) -> np.ndarray:
        """Each world's latest camera instant (ns since its reset)."""
        return self._next_frame - self.camera_period_ns

    def step_frame(self, run: Any = None) -> tuple[np.ndarray, np.ndarray]:
        """Advance the worlds where ``run`` (a mask; None: all) to the end of the control period holding
        their next camera instant, in one compiled call. Returns (every row's state at its world's camera
        instant, ``(worlds, vehicles, STATE_SIZE)``; rows that touched the scene on the way), arrays this
        world reuses (rows of worlds not run keep old values); :attr:`touched` names the vehicle each row
        touched. The wind is sampled once a frame."""
        if self.config.vehicle.wind != "none":
            raise ValueError("many worlds fly the wind field (the wind section), not RotorPy's profiles: "
                             "set vehicle.wind = 'none'")  # fmt: skip
        mask = self._all if run is None else np.asarray(run, dtype=bool)
        if mask.shape != (self.num_worlds,):
            raise ValueError(f"run must be {self.num_worlds} booleans, got shape {mask.shape}")
        W, n = self.num_worlds, self.num_vehicles
        if self._still_air:
            self._wind_rows[:] = 0.0
        else:
            self.wind.dt = self.camera_period_ns / NS
            flat = self.states.reshape(W * n, STATE_SIZE)
            self._wind_rows[:] = self.wind.update(flat[:, STATE.x], flat[:, STATE.v]).reshape(W, n, 3)
        (clocks, states, cmds, active, substep, P, G, D, pidx, buf, wood, off, shapes, origins, res, variant,
         radius, model, eff, dead, out, hit, hit_t, hit_kind, work, R) = self._args()  # fmt: skip
        kernel.step_to_frame(
            mask, self._parallel(), self.control_period_ns, self.camera_period_ns, clocks, self._next_frame,
            states, self._wind_rows, self._wake.active, self._wake.k_eta, self._wake.disk_area,
            self._period_start, out, self.mode, self._flats, cmds, self._vref, self._lim, self._gains, active,
            substep, P, G, D, pidx, buf, wood, off, shapes, origins, res, variant, radius, model, eff, dead,
            hit, hit_t, hit_kind, work, R, self.camera_states, self.touched,
        )  # fmt: skip
        return self.camera_states, self.hit

    def inject_fault(self, spec: FaultSpec) -> dict[str, Any]:
        """Start the fault ``spec`` (docs/faults.md) on its vehicle now; its ``fault_started`` event comes
        with the next step. Returns it described (``id``, ``kind``, ``vehicle``, ``start``, parameters)."""
        return self.faults.inject(spec).describe()

    def clear_faults(
        self, vehicle: str | None = None, kind: str | None = None, fault_id: int | None = None
    ) -> list[int]:
        """End the active faults matching every filter given (all for none); returns their ids."""
        return self.faults.clear(vehicle, kind, fault_id)

    def camera_dropouts(self) -> set[str]:
        """The vehicles whose cameras deliver no frames now (a ``camera_dropout`` fault)."""
        if not self.faults.active:
            return set()
        return {name for name in self.vehicles if self.faults.has(name, "camera_dropout")}

    def command_link_cut(self, vehicle: str | None) -> bool:
        """Whether ``vehicle``'s command link (None: the first vehicle's) is cut (a ``link_cut`` fault):
        the command path delivers none of its commands."""
        return bool(self.faults.active) and self.faults.has(self.vehicle(vehicle).name, "link_cut")

    def _shoot(self, out: StepResult, rigs: tuple[str, ...] | None) -> None:
        """A camera instant now: the frames (own renderer; none of a vehicle whose cameras drop out) or the
        states for a render server."""
        if self.cameras is not None:
            frames = self.render(rigs)
            for name in self.camera_dropouts():
                frames.cameras.pop(name, None)
            out.frames.append(frames)
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
        touchdowns; a hard touchdown of a vehicle under ``crash`` crashes it (a ``collision`` event with
        ``contact`` "ground": its rotors stop)."""
        imu = self._out[0]
        sf = imu[:, OUTPUT.specific_force] / dt
        held = dt - imu[:, OUTPUT.elapsed]
        for i in np.flatnonzero(held > 1e-12):  # time not integrated (stopped) is spent held by the obstacle
            sf[i] += (held[i] / dt) * vs[i].holding_force()
        self._motion[:, 0:3] = sf
        self._motion[:, 3:6] = imu[:, OUTPUT.delta_v] / dt
        for i in np.flatnonzero(imu[:, OUTPUT.touchdown_speed] > self._impact_speed):
            where = imu[i, OUTPUT.touchdown_position].tolist()
            speed = float(imu[i, OUTPUT.touchdown_speed])
            when = t_start + float(imu[i, OUTPUT.touchdown_time])
            events.append(Event("impact", when, {"position": where, "speed": speed}, vs[i].name))
            if vs[i].contact_model == "crash" and not self.dead[0, i]:
                self.dead[0, i] = True
                events.append(vs[i].on_collision(t=when, contact="ground", rotors_lost=[0, 1, 2, 3]))

    def _vehicle_contacts(self, vs: list[Vehicle], pairs: list[tuple[int, ...]], events: list[Event]) -> None:
        """Vehicles whose bodies overlapped (met by the step, each by its contact model): one ``collision``
        event per pair, naming both (``rotors_lost``: each one's, in the order of ``vehicles``)."""
        rows = self._rows
        for a, b, lost_a, lost_b in pairs:
            lost = [_rotors(lost_a), _rotors(lost_b)]
            vs[a].on_collision(with_=vs[b].name, contact="vehicle", rotors_lost=lost[0])
            vs[b].on_collision(with_=vs[a].name, contact="vehicle", rotors_lost=lost[1])
            mid = 0.5 * (rows[a, STATE.x] + rows[b, STATE.x])
            names = [vs[a].name, vs[b].name]
            data = {"position": mid.tolist(), "vehicles": names, "contact": "vehicle",
                    "models": [vs[a].contact_model, vs[b].contact_model], "rotors_lost": lost}  # fmt: skip
            events.append(Event("collision", self.t, data, names[0]))

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
