"""A vehicle of the world: its airframe, its row of the world's state array, its flight controller, its
wind, its cameras and sensors, and the commands it takes.

The world steps every vehicle at once (one compiled physics step over all rows); a :class:`Vehicle` is
the handle the API, ROS, PX4 and the workflows hold for one of them. Its commands check what the
vehicle can do (finite values, the scene's bounds, the speed limits, in the air or not) and raise
:class:`~droneulator.commands.errors.CommandError` with a code otherwise.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from droneulator.commands.errors import CommandError
from droneulator.config import CameraConfig, FlightConfig, SimConfig, VehicleSpec
from droneulator.controllers.flight import TRACK_MAX_ACCEL, TRACK_TIMEOUT, Event, FlightController, Mode
from droneulator.frames import quat_from_euler, quat_from_yaw, quat_to_matrix, transform_from_pose, yaw_of
from droneulator.frames_numba import world_to_body
from droneulator.scenes.base import Scene
from droneulator.scenes.collision import sdf_lookup_many
from droneulator.sensors.rig import build_rig
from droneulator.state import STATE
from droneulator.vehicles.dynamics import GRAVITY, GroundContact, hover_speed, pack_params
from droneulator.vehicles.params import get_params
from droneulator.wind import make_wind

NS = 1_000_000_000

log = logging.getLogger("droneulator.sim")


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
    vehicle: str = "uav0"
    #: the wind at the vehicle (world frame, m/s; rotor wakes of vehicles above included): ground truth
    wind: np.ndarray | None = None
    #: its spray system's state (:meth:`droneulator.spray.system.SpraySystem.state`), when it has one
    spray: dict[str, Any] | None = None
    #: its battery's state (:meth:`droneulator.vehicles.battery.Battery.state`), when it has one
    battery: dict[str, Any] | None = None
    #: the faults active on it (docs/faults.md: ``id``, ``kind``, ``start``, ``duration``, parameters)
    faults: list[dict[str, Any]] | None = None

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
            "vehicle": self.vehicle,
            "position": self.position.tolist(),
            "velocity": self.velocity.tolist(),
            "quaternion": self.quaternion.tolist(),
            "angular_velocity": self.angular_velocity.tolist(),
            "yaw": self.yaw,
            "mode": self.mode,
            "wind": None if self.wind is None else self.wind.tolist(),
            **({} if self.spray is None else {"spray": self.spray}),
            **({} if self.battery is None else {"battery": self.battery}),
            **({} if not self.faults else {"faults": self.faults}),
        }


class Surroundings(Protocol):
    """What a vehicle needs of its world: the clocks and the scene (bounds, collision model)."""

    @property
    def t(self) -> float: ...

    @property
    def t_ns(self) -> int: ...

    @property
    def stamp_ns(self) -> int: ...

    @property
    def scene(self) -> Scene: ...


def _contact(cfg: SimConfig) -> GroundContact:
    v = cfg.vehicle
    return GroundContact(
        v.contact_frequency_hz,
        v.contact_damping_ratio,
        v.contact_rebound_damping_ratio,
        v.ground_friction,
        v.friction_slip_speed,
    )


class Vehicle:
    """One vehicle: ``s`` is its row of the world's state array (a view the world integrates)."""

    def __init__(
        self,
        world: Surroundings,
        config: SimConfig,
        spec: VehicleSpec,
        row: np.ndarray,
        motion: np.ndarray,
        index: int = 0,
    ) -> None:
        """``row``: the vehicle's row of the world's state array; ``motion``: its row of the world's IMU
        means (specific force, then acceleration), both views the world writes; ``index``: its place
        in the world (seeds its sensor noise)."""
        assert spec.params is not None and spec.cameras is not None and spec.flight is not None
        assert spec.sensors is not None
        self.world = world
        self.config = config
        self.spec = spec
        self.name = spec.name
        self.quad_params = get_params(spec.params)
        #: the airframe's own parameters, before any payload (:meth:`World.set_payload`)
        self.base_params = dict(self.quad_params)
        #: the packed airframe the physics kernel reads (:func:`~droneulator.vehicles.dynamics.pack_params`)
        #: the legs' spring-damper ground contact
        self.contact = _contact(config)
        self.packed = pack_params(self.quad_params, config.vehicle.aero, True, self.contact)
        self.hover_speed = hover_speed(self.packed[0])
        self.flight_config: FlightConfig = spec.flight
        self.flight = FlightController(self.quad_params, spec.flight)
        #: its cameras and noisy sensors, from its config table (:mod:`droneulator.sensors.rig`)
        self.rig = build_rig(
            spec.cameras,
            spec.sensors,
            config.px4,
            config.seed,
            index,
            imu_hz=config.vehicle.control_hz,
            site=config.site,
        )
        self.collision_radius = config.vehicle.collision_radius
        #: what a touch does to it (docs/contact.md): "stop", "physical" or "crash"
        self.contact_model = str(spec.contact_model or "stop")
        #: crashed under ``crash``: its rotors are stopped and it takes no command until placed again
        self.crashed = False
        self.s = row
        self.wind = make_wind(config.vehicle, config.seed, 1.0 / config.vehicle.control_hz)
        self.collisions = 0
        self.index = index
        #: where outside systems reach this vehicle, set by the runtime that serves it (ROS namespace and
        #: topics, TF prefix, PX4 port): what ``scene_info`` lists besides the vehicle's own settings
        self.endpoints: dict[str, Any] = {}
        self._reference: np.ndarray | None = None
        self._motion = motion

    def describe(self) -> dict[str, Any]:
        """What the API's ``scene_info`` says of this vehicle."""
        return {
            "name": self.name,
            "params": self.spec.params,
            "controlled_by": self.spec.controlled_by,
            "cameras": [c.name for c in self.cameras],
            "limits": self.control_limits(),
            **self.endpoints,
        }

    def control_limits(self) -> dict[str, Any]:
        """What the ``rotors``, ``rates`` and ``attitude`` commands accept for this vehicle (docs/control.md):
        the airframe's rotor speed range (rad/s) and largest collective thrust (N, every rotor at full speed)
        with its thrust-to-weight ratio, the largest body rates (rad/s), the largest attitude tilt (deg), the
        body-rate loop's gains (1/s) and the seconds a command stream may pause before the vehicle holds."""
        q = self.quad_params
        return {
            "rotor_speed": [float(q["rotor_speed_min"]), float(q["rotor_speed_max"])],
            "max_thrust": self.max_thrust,
            "thrust_to_weight": self.max_thrust / (float(q["mass"]) * GRAVITY),
            "max_body_rate": np.radians(self.flight_config.max_body_rate_deg_s).tolist(),
            "max_attitude_tilt_deg": float(self.flight_config.max_attitude_tilt_deg),
            "rate_gain": self.flight.se3.k_w.tolist(),
            "stream_timeout": TRACK_TIMEOUT,
        }

    # ------------------------------------------------------------------ state
    @property
    def cameras(self) -> list[CameraConfig]:
        return self.rig.camera_configs

    @property
    def t(self) -> float:
        return self.world.t

    @property
    def mode(self) -> Mode:
        return self.flight.mode

    @property
    def specific_force(self) -> np.ndarray:
        """What the IMU's accelerometer measures (body FLU, m/s^2): the force per unit mass from
        thrust, drag and ground contact, gravity excluded, averaged over the last control period
        like an IMU's output filter. 9.81 up in hover and at rest on the ground, ~0 in free fall."""
        return self._motion[0:3].copy()

    @property
    def acceleration(self) -> np.ndarray:
        """World-frame acceleration, mean over the last control period (m/s^2)."""
        return self._motion[3:6].copy()

    @property
    def wind_velocity(self) -> np.ndarray:
        """Wind velocity (world frame, m/s) over the current control step, rotor wakes of the vehicles
        above included: a sensor model input (airspeed) that :attr:`state` does not carry."""
        return self.s[STATE.wind].copy()

    @property
    def state(self) -> VehicleState:
        s = self.s
        return VehicleState(
            self.world.t_ns,
            self.world.stamp_ns,
            s[STATE.x].copy(),
            s[STATE.v].copy(),
            s[STATE.q].copy(),
            s[STATE.w].copy(),
            s[STATE.rotor_speeds].copy(),
            self.flight.mode.value,
            None if self._reference is None else self._reference.copy(),
            self.name,
            s[STATE.wind].copy(),
            self._spray_state(),
            self._battery_state(),
            self._faults(),
        )

    def _faults(self) -> list[dict[str, Any]] | None:
        """The faults active on it (None: none), as its world's fault board describes them."""
        board = getattr(self.world, "faults", None)
        return None if board is None or not board.active else board.of(self.name) or None

    def _spray_state(self) -> dict[str, Any] | None:
        """Its spray system's state, when its world sprays (``spray.enabled``) and it carries one."""
        spraying = getattr(self.world, "spraying", None)
        system = None if spraying is None else spraying.systems.get(self.name)
        return None if system is None else system.state()

    def _battery_state(self) -> dict[str, Any] | None:
        """Its battery's state, when it has one (``battery.enabled``)."""
        battery = getattr(self.world, "batteries", {}).get(self.name)
        return None if battery is None else battery.state()

    @property
    def thrust(self) -> float:
        """Total rotor thrust now (N): the strength of the wake below the vehicle."""
        w = self.s[STATE.rotor_speeds]
        return float(self.quad_params["k_eta"] * np.dot(w, w))

    @property
    def max_thrust(self) -> float:
        """The largest collective thrust (N): every rotor at ``rotor_speed_max``."""
        return float(4.0 * self.quad_params["k_eta"] * float(self.quad_params["rotor_speed_max"]) ** 2)

    @property
    def disk_area(self) -> float:
        """Total rotor disk area (m^2), from the rotor radius (or, without one, 45 % of the arm length)."""
        arm = float(np.linalg.norm(np.asarray(self.quad_params["rotor_pos"]["r1"], dtype=float)[:2]))
        radius = float(self.quad_params.get("rotor_radius", 0.45 * arm))
        return 4.0 * math.pi * radius * radius

    # ------------------------------------------------------------------ placing
    def place(self, position: Any, yaw: float, airborne: bool | None = None) -> None:
        """Put the vehicle at rest at ``position`` (checked against the scene) with heading ``yaw``; a
        position above the ground hovers there unless ``airborne`` is False. Motors off otherwise."""
        pos = np.array(position, dtype=float)
        if pos.shape != (3,) or not np.all(np.isfinite(pos)):
            raise CommandError("invalid_argument", "reset position must be three finite numbers")
        if not math.isfinite(yaw):
            raise CommandError("invalid_argument", "reset yaw must be finite")
        self._check_position(pos, allow_ground=True)
        self.wind = make_wind(self.config.vehicle, self.config.seed, 1.0 / self.config.vehicle.control_hz)
        s = self.s
        s[:] = 0.0
        s[STATE.x] = pos
        s[STATE.q] = quat_from_yaw(yaw)
        self.flight.revive()
        self.flight.motors_off()
        self._reference = None
        self.collisions = 0
        self.crashed = False
        # until the first step: what a vehicle at rest on its legs or hovering measures
        self._motion[0:3] = self.holding_force()
        self._motion[3:6] = 0.0
        if pos[2] > 0.05 if airborne is None else airborne:
            s[STATE.rotor_speeds] = self.hover_speed
            self.flight.hold(s, 0.0)

    # ------------------------------------------------------------------ commands
    def _finite(self, name: str, *values: float | None) -> None:
        for v in values:
            if v is not None and not (isinstance(v, (int, float)) and math.isfinite(v)):
                raise CommandError("invalid_argument", f"{name} must be finite numbers, got {v!r}")

    def _check_position(self, p: np.ndarray, allow_ground: bool = False) -> None:
        scene = self.world.scene
        lo, hi = scene.bounds_min, scene.bounds_max
        if p[2] < 0 or (p[2] == 0 and not allow_ground):
            raise CommandError("below_ground", f"target altitude {p[2]:.3f} m is not above the ground")
        if np.any(p[:2] < lo[:2]) or np.any(p[:2] > hi[:2]) or p[2] > hi[2]:
            raise CommandError(
                "out_of_bounds",
                f"target {np.round(p, 3).tolist()} is outside the scene bounds "
                f"{lo.tolist()} .. {hi.tolist()}",
            )

    def _require_alive(self, op: str) -> None:
        if self.crashed:
            raise CommandError("crashed", f"{op}: the vehicle crashed (contact model crash): reset it first")

    def _require_airborne(self, op: str) -> None:
        self._require_alive(op)
        if self.flight.mode == Mode.IDLE:
            raise CommandError("not_airborne", f"{op} needs the vehicle in the air: take off first")

    def takeoff(self, altitude: float | None = None) -> float:
        """Climb vertically to ``altitude`` (default from config); returns the planned duration."""
        self._require_alive("takeoff")
        self._finite("altitude", altitude)
        alt = self.flight_config.takeoff_altitude if altitude is None else float(altitude)
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
        self._require_alive("goto")
        try:
            p = np.asarray(position, dtype=float)
        except (TypeError, ValueError):
            raise CommandError("invalid_argument", "position must be three numbers [x, y, z]") from None
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise CommandError("invalid_argument", "position must be three finite numbers [x, y, z]")
        self._finite("yaw/speed/duration", yaw, speed, duration)
        if speed is not None and not 0 < speed <= self.flight_config.max_speed:
            raise CommandError("out_of_range", f"speed must lie in (0, {self.flight_config.max_speed}] m/s")
        if duration is not None and not 0.2 <= duration <= 3600:
            raise CommandError("out_of_range", "duration must lie in [0.2, 3600] s")
        self._check_position(p)
        return self.flight.goto(self.s, self.t, p, yaw, speed, duration)

    def velocity(self, forward: float, yaw_rate: float) -> None:
        """Velocity mode: forward speed (m/s, body x) and yaw rate (rad/s) at constant altitude."""
        self._finite("forward/yaw_rate", forward, yaw_rate)
        lim = self.flight_config.max_speed
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
        lim = self.flight_config.max_speed
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
        scene = self.world.scene
        col = scene.collision
        x = self.s[STATE.x]
        need = clearance + self.collision_radius
        step = max(col.resolution, 0.05)

        def clear(a: np.ndarray, b: np.ndarray) -> bool:
            n = max(2, int(np.ceil(np.linalg.norm(b - a) / step)) + 1)
            pts = a + np.linspace(0.0, 1.0, n)[:, None] * (b - a)
            return bool(np.all(sdf_lookup_many(col.sdf, col.origin, col.resolution, pts) >= need))

        top = x.copy()
        low = min(need, float(x[2]))  # the ground itself is not an obstacle: stop the column above it
        lo, hi = scene.bounds_min[:2], scene.bounds_max[:2]
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

    # ------------------------------------------------------------------ commands below the SE(3) controller
    def _vector(self, name: str, value: Any, n: int) -> np.ndarray:
        try:
            a = np.asarray(value, dtype=float)
        except (TypeError, ValueError):
            raise CommandError("invalid_argument", f"{name} must be {n} numbers") from None
        if a.shape != (n,) or not np.all(np.isfinite(a)):
            raise CommandError("invalid_argument", f"{name} must be {n} finite numbers, got {value!r}")
        return a

    def _thrust(self, thrust: float, normalized: bool) -> float:
        """A collective thrust in N, checked: ``thrust`` in [0, max_thrust] N, or in [0, 1] of it."""
        self._finite("thrust", thrust)
        top = 1.0 if normalized else self.max_thrust
        if not 0.0 <= thrust <= top:
            unit = "(a share of the largest thrust)" if normalized else "N"
            raise CommandError("out_of_range", f"thrust {thrust:g} must lie in [0, {top:g}] {unit}")
        return float(thrust) * (self.max_thrust if normalized else 1.0)

    def rotors(self, rotor_speeds: Any, normalized: bool = False) -> None:
        """Command the four rotors (RotorPy's order) for one control stream: speeds in rad/s within the
        airframe's ``[rotor_speed_min, rotor_speed_max]``, or with ``normalized`` thrusts in [0, 1] of a
        rotor's largest (speed ``rotor_speed_max * sqrt(u)``, raised to ``rotor_speed_min``). A value
        outside is refused (``out_of_range``). The motors follow with the airframe's lag; after
        :data:`~droneulator.controllers.flight.TRACK_TIMEOUT` s without a command the vehicle holds."""
        self._require_alive("rotors")
        w = self._vector("rotor_speeds", rotor_speeds, 4)
        lo, hi = float(self.quad_params["rotor_speed_min"]), float(self.quad_params["rotor_speed_max"])
        if normalized:
            if np.any(w < 0.0) or np.any(w > 1.0):
                raise CommandError("out_of_range", f"normalised thrusts must lie in [0, 1], got {w.tolist()}")
            w = np.maximum(hi * np.sqrt(w), lo)
        elif np.any(w < lo) or np.any(w > hi):
            raise CommandError("out_of_range", f"rotor speeds must lie in [{lo:g}, {hi:g}] rad/s: {w}")
        self.flight.rotors(self.t, w)

    def rates(self, thrust: float, body_rates: Any, normalized: bool = False) -> None:
        """Collective thrust (N, or with ``normalized`` a share in [0, 1] of :attr:`max_thrust`) and body
        rates (rad/s, body FLU, each within ``flight.max_body_rate_deg_s``) for the body-rate loop; after
        :data:`~droneulator.controllers.flight.TRACK_TIMEOUT` s without a command the vehicle holds."""
        self._require_alive("rates")
        f = self._thrust(thrust, normalized)
        w = self._vector("body_rates", body_rates, 3)
        most = np.radians(self.flight_config.max_body_rate_deg_s)
        if np.any(np.abs(w) > most):
            got, top = np.round(w, 3).tolist(), np.round(most, 3).tolist()
            raise CommandError("out_of_range", f"body rates {got} exceed {top} rad/s")
        self.flight.rates(self.t, f, w)

    def attitude(
        self,
        thrust: float,
        quaternion: Any = None,
        roll: float | None = None,
        pitch: float | None = None,
        yaw: float | None = None,
        normalized: bool = False,
    ) -> None:
        """Collective thrust (as :meth:`rates`) and attitude for the attitude loop: a unit quaternion
        ``[x, y, z, w]`` (body FLU to world ENU; normalised, refused when its norm is off 1 by more than 1 %)
        or roll, pitch, yaw (rad, Z-Y-X; 0 for roll and pitch, the current heading for yaw when left out),
        tilted at most ``flight.max_attitude_tilt_deg`` from level; after
        :data:`~droneulator.controllers.flight.TRACK_TIMEOUT` s without a command the vehicle holds."""
        self._require_alive("attitude")
        f = self._thrust(thrust, normalized)
        if quaternion is not None:
            if roll is not None or pitch is not None or yaw is not None:
                raise CommandError("invalid_argument", "give either a quaternion or roll/pitch/yaw, not both")
            q = self._vector("quaternion", quaternion, 4)
            norm = float(np.linalg.norm(q))
            if abs(norm - 1.0) > 0.01:
                raise CommandError("invalid_argument", f"quaternion must have norm 1, got {norm:g}")
            q = q / norm
        else:
            self._finite("roll/pitch/yaw", roll, pitch, yaw)
            heading = yaw_of(self.s[STATE.q]) if yaw is None else float(yaw)
            q = quat_from_euler(float(roll or 0.0), float(pitch or 0.0), heading)
        tilt = math.degrees(math.acos(min(1.0, max(-1.0, float(quat_to_matrix(q)[2, 2])))))
        most = self.flight_config.max_attitude_tilt_deg
        if tilt > most + 1e-9:
            raise CommandError("out_of_range", f"attitude tilt {tilt:.1f} deg exceeds {most:g} deg")
        self.flight.attitude(self.t, f, q)

    # ------------------------------------------------------------------ the world's hooks
    def on_collision(
        self,
        with_: str | None = None,
        t: float | None = None,
        contact: str = "wood",
        rotors_lost: list[int] | None = None,
    ) -> Event:
        """The vehicle began a contact at ``t`` (default: now) with the scene (``contact`` "foliage" or
        "wood") or with ``with_``, another vehicle ("vehicle"), and the world's step met it by its contact
        model: under ``stop`` stopped where it was, level (:func:`~droneulator.world.step.stop_level`; mode
        collided); under ``physical`` pushed and flying on, ``rotors_lost`` (RotorPy's order, from 0) without
        thrust; under ``crash`` with every rotor stopped (mode crashed). Returns the ``collision`` event."""
        if self.contact_model == "stop":
            self.flight.collided()
        elif self.contact_model == "crash":
            self.crashed = True
            self.flight.crashed()
        self.collisions += 1
        data: dict[str, Any] = {
            "position": self.s[STATE.x].tolist(),
            "contact": contact,
            "model": self.contact_model,
            "rotors_lost": list(rotors_lost or []),
        }
        if with_ is not None:
            data["vehicles"] = [self.name, with_]
        return Event("collision", self.t if t is None else t, data, self.name)

    def holding_force(self) -> np.ndarray:
        """Specific force of the vehicle held still against gravity, in the body frame."""
        return world_to_body(self.s[STATE.q], np.array([0.0, 0.0, GRAVITY]))
