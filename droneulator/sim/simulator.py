"""The in-process simulator: scene + RotorPy vehicle + flight controller + sensor rig, in lockstep.

Simulation time is an integer count of nanoseconds. ``step()`` advances one control period; the
physics is split at camera instants so every frame is rendered from the exact state at
``k / camera_hz`` (no frame skipped, never paced by the wall clock). The servers are thin shells
around this object.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from droneulator.commands.errors import CommandError
from droneulator.config import SimConfig, load_config
from droneulator.controllers.flight import TRACK_MAX_ACCEL, Event, FlightController, Mode
from droneulator.frames import quat_from_yaw, transform_from_pose, yaw_of
from droneulator.frames_numba import world_to_body
from droneulator.scenes import get_scene
from droneulator.scenes.base import Scene
from droneulator.scenes.collision import sdf_lookup_many
from droneulator.vehicles.dynamics import (
    GRAVITY,
    OUTPUT,
    OUTPUT_SIZE,
    STATE,
    STATE_SIZE,
    FastMultirotor,
    GroundContact,
)
from droneulator.vehicles.params import get_params
from droneulator.wind import make_wind

NS = 1_000_000_000

log = logging.getLogger(__name__)


@dataclass
class VehicleState:
    """Ground-truth vehicle state in the Z-up world (body FLU, quaternion [x, y, z, w]).

    ``t_ns`` is sim time since the last reset (the API's episode clock); ``stamp_ns`` is the simulator's
    monotonic clock, which keeps counting across resets and stamps everything published to ROS.
    This one object is the state message between the processes (picklable, no list round trips).
    """

    t_ns: int
    stamp_ns: int
    position: np.ndarray
    velocity: np.ndarray
    quaternion: np.ndarray
    angular_velocity: np.ndarray  # body frame, rad/s
    rotor_speeds: np.ndarray
    mode: str
    reference: np.ndarray | None = None  # packed flat output being tracked

    @property
    def t(self) -> float:
        return self.t_ns / NS

    @property
    def yaw(self) -> float:
        return yaw_of(self.quaternion)

    @property
    def T_world_body(self) -> np.ndarray:
        return transform_from_pose(self.position, self.quaternion)

    def to_dict(self) -> dict[str, Any]:
        """The API's state object (``state`` op, state stream, ``reset`` result): plain JSON values."""
        return {
            "t": self.t,
            "t_ns": int(self.t_ns),
            "stamp_ns": int(self.stamp_ns),
            "position": self.position.tolist(),
            "velocity": self.velocity.tolist(),
            "quaternion": self.quaternion.tolist(),
            "angular_velocity": self.angular_velocity.tolist(),
            "yaw": self.yaw,
            "mode": self.mode,
        }


@dataclass
class FrameSet:
    """All cameras rendered at one instant, with the state they were rendered from."""

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
    """Compose scene, vehicle, controller and camera rig; step them in lockstep.

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
        self.config = config or load_config()
        if scene is not None:
            self.config.scene = scene
        if seed is not None:
            self.config.seed = seed
        vcfg = self.config.vehicle
        self.quad_params = get_params(vcfg.params)
        self.vehicle = FastMultirotor(
            self.quad_params,
            aero=vcfg.aero,
            enable_ground=True,
            substep=1.0 / (vcfg.control_hz * vcfg.substeps),
            contact=GroundContact(
                vcfg.contact_frequency_hz,
                vcfg.contact_damping_ratio,
                vcfg.contact_rebound_damping_ratio,
                vcfg.ground_friction,
                vcfg.friction_slip_speed,
            ),
        )
        self._out = np.zeros(OUTPUT_SIZE)
        self.flight = FlightController(self.quad_params, self.config.flight)
        self.control_period_ns = round(NS / vcfg.control_hz)
        self.camera_period_ns = round(NS / self.config.render.camera_hz)
        self.render_enabled = render
        self.camera_schedule = render or external_cameras
        self.renderer = None
        self.scene: Scene
        self._load_scene(self.config.scene, self.config.seed)
        self.reset()

    # ------------------------------------------------------------------ setup
    def _load_scene(self, name: str, seed: int) -> None:
        self.scene = get_scene(name, seed)
        col = self.scene.collision
        self.vehicle.set_collision(col.sdf, col.origin, col.resolution, self.config.vehicle.collision_radius)
        if self.renderer is not None:
            self.renderer.close()
            self.renderer = None
        if self.render_enabled:
            from droneulator.render import Renderer

            rc = self.config.render
            self.renderer = Renderer(
                self.scene, rc.cameras, shadows=rc.shadows, shadow_map_size=rc.shadow_map_size
            )

    def reset(
        self,
        seed: int | None = None,
        position: np.ndarray | None = None,
        yaw: float | None = None,
        scene: str | None = None,
        airborne: bool | None = None,
    ) -> VehicleState:
        """Restart the flight at t = 0 from ``position`` (default: the scene's spawn on the ground).

        A position above the ground starts hovering there (mode ``hold``) unless ``airborne=False``.
        """
        if scene is not None or (seed is not None and seed != self.config.seed):
            new = (scene or self.config.scene, self.config.seed if seed is None else seed)
            self._load_scene(*new)  # raises for an unknown scene before anything changes
            self.config.scene, self.config.seed = new
        pos = np.array(self.scene.spawn_position if position is None else position, dtype=float)
        if pos.shape != (3,) or not np.all(np.isfinite(pos)):
            raise CommandError("invalid_argument", "reset position must be three finite numbers")
        yaw_ = self.scene.spawn_yaw if yaw is None else float(yaw)
        if not math.isfinite(yaw_):
            raise CommandError("invalid_argument", "reset yaw must be finite")
        self._check_position(pos, allow_ground=True)
        # the ROS clock never runs backwards: a reset continues it one control period after the last stamp
        self._stamp_base_ns = self.stamp_ns + self.control_period_ns if hasattr(self, "t_ns") else 0
        self.wind = make_wind(self.config.vehicle, self.config.seed, 1.0 / self.config.vehicle.control_hz)
        self.t_ns = 0
        self._next_frame_ns = self.camera_period_ns
        self.frame_count = 0
        s = np.zeros(STATE_SIZE)
        s[STATE.x] = pos
        s[STATE.q] = quat_from_yaw(yaw_)
        self.s = s
        self.flight.motors_off()
        self._reference: np.ndarray | None = None
        self.collisions = 0
        #: world-frame acceleration, mean over the last control period (m/s^2)
        self.acceleration = np.zeros(3)
        # until the first step: what a vehicle at rest on its legs or hovering measures
        self._specific_force = self._holding_force()
        fly = pos[2] > 0.05 if airborne is None else airborne
        if fly:
            s[STATE.rotor_speeds] = self.vehicle.hover_speed
            self.flight.hold(s, 0.0)
        return self.state

    # ------------------------------------------------------------------ state
    @property
    def t(self) -> float:
        return self.t_ns / NS

    @property
    def stamp_ns(self) -> int:
        """The monotonic sim clock (ns): ``t_ns`` plus the time of every earlier episode."""
        return self._stamp_base_ns + self.t_ns

    @property
    def mode(self) -> Mode:
        return self.flight.mode

    @property
    def specific_force(self) -> np.ndarray:
        """What the IMU's accelerometer measures (body FLU, m/s^2): the force per unit mass from
        thrust, drag and ground contact, gravity excluded, averaged over the last control period
        like an IMU's output filter. 9.81 up in hover and at rest on the ground, ~0 in free fall."""
        return self._specific_force.copy()

    @property
    def wind_velocity(self) -> np.ndarray:
        """Wind velocity (world frame, m/s) over the current control step: a sensor model input
        (airspeed) that :attr:`state` does not carry."""
        return self.s[STATE.wind].copy()

    @property
    def state(self) -> VehicleState:
        s = self.s
        return VehicleState(
            self.t_ns,
            self.stamp_ns,
            s[STATE.x].copy(),
            s[STATE.v].copy(),
            s[STATE.q].copy(),
            s[STATE.w].copy(),
            s[STATE.rotor_speeds].copy(),
            self.flight.mode.value,
            None if self._reference is None else self._reference.copy(),
        )

    # ------------------------------------------------------------------ commands
    def _finite(self, name: str, *values: float | None) -> None:
        for v in values:
            if v is not None and not (isinstance(v, (int, float)) and math.isfinite(v)):
                raise CommandError("invalid_argument", f"{name} must be finite numbers, got {v!r}")

    def _check_position(self, p: np.ndarray, allow_ground: bool = False) -> None:
        lo, hi = self.scene.bounds_min, self.scene.bounds_max
        if p[2] < 0 or (p[2] == 0 and not allow_ground):
            raise CommandError("below_ground", f"target altitude {p[2]:.3f} m is not above the ground")
        if np.any(p[:2] < lo[:2]) or np.any(p[:2] > hi[:2]) or p[2] > hi[2]:
            raise CommandError(
                "out_of_bounds",
                f"target {np.round(p, 3).tolist()} is outside the scene bounds "
                f"{lo.tolist()} .. {hi.tolist()}",
            )

    def _require_airborne(self, op: str) -> None:
        if self.flight.mode == Mode.IDLE:
            raise CommandError("not_airborne", f"{op} needs the vehicle in the air: take off first")

    def takeoff(self, altitude: float | None = None) -> float:
        """Climb vertically to ``altitude`` (default from config); returns the planned duration."""
        self._finite("altitude", altitude)
        alt = self.config.flight.takeoff_altitude if altitude is None else float(altitude)
        self._check_position(np.array([*self.s[STATE.x][:2], alt]))
        return self.flight.takeoff(self.s, self.t, alt)

    def goto(
        self,
        position: Any,
        yaw: float | None = None,
        speed: float | None = None,
        duration: float | None = None,
    ) -> float:
        """Min-snap move to ``position`` with heading ``yaw`` (radians, kept if None)."""
        try:
            p = np.asarray(position, dtype=float)
        except (TypeError, ValueError):
            raise CommandError("invalid_argument", "position must be three numbers [x, y, z]") from None
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise CommandError("invalid_argument", "position must be three finite numbers [x, y, z]")
        self._finite("yaw/speed/duration", yaw, speed, duration)
        if speed is not None and not 0 < speed <= self.config.flight.max_speed:
            raise CommandError("out_of_range", f"speed must lie in (0, {self.config.flight.max_speed}] m/s")
        if duration is not None and not 0.2 <= duration <= 3600:
            raise CommandError("out_of_range", "duration must lie in [0.2, 3600] s")
        self._check_position(p)
        return self.flight.goto(self.s, self.t, p, yaw, speed, duration)

    def velocity(self, forward: float, yaw_rate: float) -> None:
        """Velocity mode: forward speed (m/s, body x) and yaw rate (rad/s) at constant altitude."""
        self._finite("forward/yaw_rate", forward, yaw_rate)
        lim = self.config.flight.max_speed
        if abs(forward) > lim or abs(yaw_rate) > math.pi:
            raise CommandError("out_of_range", f"need |forward| <= {lim} m/s and |yaw_rate| <= pi rad/s")
        self._require_airborne("velocity")
        self.flight.velocity(self.s, self.t, float(forward), float(yaw_rate))

    def track(
        self,
        position: Any,
        velocity: Any = None,
        acceleration: Any = None,
        yaw: float | None = None,
        yaw_rate: float = 0.0,
    ) -> None:
        """Track mode: one setpoint (position, velocity and acceleration feed-forward, yaw, yaw rate;
        world frame) for the SE(3) controller, e.g. from a planner's PositionCommand stream.

        ``yaw`` None keeps the current heading. A stream must keep coming: after
        :data:`~droneulator.controllers.flight.TRACK_TIMEOUT` s of sim time without one the vehicle holds.
        """
        vecs = []
        for name, v in (("position", position), ("velocity", velocity), ("acceleration", acceleration)):
            try:
                a = np.zeros(3) if v is None and name != "position" else np.asarray(v, dtype=float)
            except (TypeError, ValueError):
                raise CommandError("invalid_argument", f"{name} must be three numbers [x, y, z]") from None
            if a.shape != (3,) or not np.all(np.isfinite(a)):
                raise CommandError("invalid_argument", f"{name} must be three finite numbers [x, y, z]")
            vecs.append(a)
        p, v, acc = vecs
        self._finite("yaw/yaw_rate", yaw, yaw_rate)
        lim = self.config.flight.max_speed
        if float(np.linalg.norm(v)) > lim:
            raise CommandError(
                "out_of_range", f"track velocity {np.linalg.norm(v):.3f} m/s exceeds {lim} m/s"
            )
        if float(np.linalg.norm(acc)) > TRACK_MAX_ACCEL:
            raise CommandError(
                "out_of_range",
                f"track acceleration {np.linalg.norm(acc):.3f} m/s^2 exceeds {TRACK_MAX_ACCEL} m/s^2",
            )
        if abs(yaw_rate) > math.pi:
            raise CommandError("out_of_range", "need |yaw_rate| <= pi rad/s")
        self._check_position(p)
        self._require_airborne("track")
        heading = yaw_of(self.s[STATE.q]) if yaw is None else float(yaw)
        self.flight.track(self.t, p, v, acc, heading, float(yaw_rate))

    def hold(self) -> None:
        self._require_airborne("hold")
        self.flight.hold(self.s, self.t)

    def land(self) -> float:
        self._require_airborne("land")
        return self.flight.land(self.s, self.t)

    def landing_spot(self, clearance: float = 0.5, search_radius: float = 10.0) -> np.ndarray:
        """The nearest (x, y) where the vehicle can descend from its height to the ground keeping
        ``clearance`` metres (plus its collision radius) from the scene, reached by a level flight
        that keeps it too: straight below when that is clear, else on rings of growing radius.

        Falls back to straight below (and says so in the log) when nothing within
        ``search_radius`` is clear.
        """
        col = self.scene.collision
        x = self.s[STATE.x]
        need = clearance + self.config.vehicle.collision_radius
        step = max(col.resolution, 0.05)

        def clear(a: np.ndarray, b: np.ndarray) -> bool:
            n = max(2, int(np.ceil(np.linalg.norm(b - a) / step)) + 1)
            pts = a + np.linspace(0.0, 1.0, n)[:, None] * (b - a)
            return bool(np.all(sdf_lookup_many(col.sdf, col.origin, col.resolution, pts) >= need))

        top = x.copy()
        low = min(need, float(x[2]))  # the ground itself is not an obstacle: stop the column above it
        lo, hi = self.scene.bounds_min[:2], self.scene.bounds_max[:2]
        for radius in np.arange(0.0, search_radius + 1e-9, 0.5):
            count = 1 if radius == 0.0 else max(8, int(2 * math.pi * radius / 0.5))
            for k in range(count):
                a = 2 * math.pi * k / count
                xy = x[:2] + radius * np.array([math.cos(a), math.sin(a)])
                if np.any(xy < lo) or np.any(xy > hi):
                    continue
                above = np.array([xy[0], xy[1], x[2]])
                if clear(top, above) and clear(above, np.array([xy[0], xy[1], low])):
                    return xy
        log.warning("no landing spot clear of the scene within %.0f m of %s: landing straight down",
                    search_radius, np.round(x, 2).tolist())  # fmt: skip
        return x[:2].copy()

    def safe_land(self, clearance: float = 0.5) -> np.ndarray:
        """Land at :meth:`landing_spot` (flying there level first if it is not straight below);
        returns the spot's (x, y)."""
        self._require_airborne("land")
        xy = self.landing_spot(clearance)
        self.flight.land_at(self.s, self.t, xy)
        return xy

    def motors_off(self) -> None:
        self.flight.motors_off()

    def set_rotor_speeds(self, rotor_speeds: Any) -> None:
        """Command the rotors directly (rad/s, RotorPy rotor order), bypassing the flight controller.

        Used by autopilots in the loop (PX4 SITL); any flight command or ``motors_off`` ends it.
        """
        w = np.asarray(rotor_speeds, dtype=float)
        if w.shape != (4,) or not np.all(np.isfinite(w)):
            raise CommandError("invalid_argument", "rotor_speeds must be four finite numbers (rad/s)")
        self.flight.external(
            np.clip(w, self.quad_params["rotor_speed_min"], self.quad_params["rotor_speed_max"])
        )

    # ------------------------------------------------------------------ stepping
    def step(self, n: int = 1) -> StepResult:
        """Advance ``n`` control periods; returns the frames rendered and events raised meanwhile."""
        out = StepResult()
        dt = self.control_period_ns / NS
        for _ in range(n):
            cmd, ref, events = self.flight.update(self.s, self.t, dt)
            self._reference = ref
            out.events.extend(events)
            self.s[STATE.wind] = self.wind.update(self.t, self.s[STATE.x])
            imu = self._out
            imu[:] = 0.0
            t_start = self.t
            t_end = self.t_ns + self.control_period_ns
            while self.t_ns < t_end:
                t_next = min(t_end, self._next_frame_ns) if self.camera_schedule else t_end
                if self.flight.mode != Mode.COLLIDED and self.vehicle.step(
                    self.s, cmd, (t_next - self.t_ns) / NS, imu
                ):
                    out.events.append(self._on_collision())
                self.t_ns = t_next
                if self.camera_schedule and self.t_ns == self._next_frame_ns:
                    if self.renderer is not None:
                        out.frames.append(self.render())
                    else:
                        out.camera_states.append(self.state)
                    self.frame_count += 1
                    self._next_frame_ns += self.camera_period_ns
            self._finish_period(imu, dt, t_start, out.events)
        return out

    def _finish_period(self, imu: np.ndarray, dt: float, t_start: float, events: list[Event]) -> None:
        """IMU means over the period just stepped, and an ``impact`` event for a hard touchdown."""
        sf = imu[OUTPUT.specific_force] / dt
        held = dt - imu[OUTPUT.elapsed]
        if held > 1e-12:  # time not integrated (stopped against the scene) is spent held by the obstacle
            sf += (held / dt) * self._holding_force()
        self._specific_force = sf
        self.acceleration = imu[OUTPUT.delta_v] / dt
        speed = float(imu[OUTPUT.touchdown_speed])
        if speed > self.config.vehicle.impact_speed:
            events.append(
                Event(
                    "impact",
                    t_start + float(imu[OUTPUT.touchdown_time]),
                    {"position": imu[OUTPUT.touchdown_position].tolist(), "speed": speed},
                )
            )

    def _holding_force(self) -> np.ndarray:
        """Specific force of the vehicle held still against gravity, in the body frame."""
        return world_to_body(self.s[STATE.q], np.array([0.0, 0.0, GRAVITY]))

    def run(self, seconds: float) -> StepResult:
        """Step for ``seconds`` of simulated time, collecting frames and events."""
        return self.step(max(1, round(seconds * NS / self.control_period_ns)))

    def run_until(self, predicate: Any, timeout: float, events: list[Event] | None = None) -> bool:
        """Step until ``predicate(sim)`` holds or ``timeout`` sim seconds pass; events are appended."""
        end = self.t_ns + round(timeout * NS)
        while self.t_ns < end:
            res = self.step()
            if events is not None:
                events.extend(res.events)
            if predicate(self):
                return True
        return False

    def _on_collision(self) -> Event:
        s = self.s
        s[STATE.v] = 0.0
        s[STATE.w] = 0.0
        s[STATE.q] = quat_from_yaw(yaw_of(s[STATE.q]))
        self.flight.collided()
        self.collisions += 1
        return Event("collision", self.t, {"position": s[STATE.x].tolist()})

    def render(self) -> FrameSet:
        """Render every camera from the current state (also usable outside the camera schedule).

        The images are copies the caller owns (the renderer reuses its readback buffers).
        """
        if self.renderer is None:
            raise RuntimeError("this Simulator was created with render=False")
        state = self.state
        cams = {
            name: dataclasses.replace(
                f, rgb=None if f.rgb is None else f.rgb.copy(), depth=f.depth.copy(), seg=f.seg.copy()
            )
            for name, f in self.renderer.render(state.T_world_body).items()
        }
        return FrameSet(self.t_ns, state, cams)

    def close(self) -> None:
        if self.renderer is not None:
            self.renderer.close()
            self.renderer = None

    def __enter__(self) -> Simulator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
