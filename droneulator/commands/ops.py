"""Every command, once: the op table (:data:`OPS`) with each op's fields, its rules and what it runs.

Every command source builds its requests with :func:`make_request` (the WebSocket server after parsing
JSON, ROS topics from their messages) and runs them with :func:`execute`, normally through the
:class:`~droneulator.commands.path.CommandPath`. The table checks what a field can be (a finite number,
three of them, a known stream); what a value may be for the vehicle (inside the scene, above the
ground, under the speed limit) the core checks itself, for in-process callers too. The reference in
docs/api.md is generated from the same table (:func:`ops_markdown`).

The world is known here only as the interface the ops call (:mod:`~droneulator.commands.surface`):
nothing imports the simulator.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import time
from collections.abc import Callable, Collection, Mapping
from dataclasses import dataclass
from typing import Any

from droneulator.commands.errors import ERROR_CODES, CommandError
from droneulator.commands.surface import CommandedVehicle, CommandedWorld
from droneulator.config.faults import FAULT_KINDS, FaultError, FaultSpec
from droneulator.config.scene import VEGETATION_RANGE

#: the ``vehicle`` value of ``state`` and ``subscribe`` that means every vehicle (not a valid name)
ALL_VEHICLES = "*"


log = logging.getLogger(__name__)

#: stream names accepted by ``subscribe``
STREAMS = ("state", "events")


class RequestError(CommandError):
    """A request rejected before dispatch; ``request_id`` is the id to echo (None if unknown)."""

    def __init__(self, code: str, message: str, request_id: int | str | None = None) -> None:
        super().__init__(code, message)
        self.request_id = request_id


# --------------------------------------------------------------------------- the op table
#: argument types: what JSON each accepts (``null`` for an optional field means "absent")
TYPES: dict[str, str] = {
    "number": "JSON number (not a boolean), finite",
    "integer": "JSON integer (not a boolean)",
    "boolean": "`true` or `false`",
    "string": "JSON string",
    "vec3": "array of 3 finite numbers",
    "strings": "non-empty array of JSON strings",
    "vec4": "array of 4 finite numbers",
    "streams": 'non-empty array of `"state"` and/or `"events"`',
    "light": "JSON object of light settings (the config's `light` section, docs/light.md): "
    "`time_of_day_h`, `latitude_deg`, `longitude_deg`, `utc_offset_h`, `cloud_cover`, `visibility_m` "
    '(numbers) and `date` (`"YYYY-MM-DD"`), each null for its default',
}


@dataclass(frozen=True)
class Arg:
    """One request field: its JSON type, whether it is required, inclusive bounds, a doc line."""

    name: str
    type: str
    doc: str
    required: bool = False
    bounds: tuple[float, float] | None = None


@dataclass(frozen=True)
class Op:
    """One operation.

    ``run(sim, args)`` executes it with validated arguments and returns the result object;
    ``run=None`` means the transport handles it (subscriptions). ``flight`` ops are refused while
    flight is locked; ``locked`` ops must run while holding the simulation lock.
    """

    name: str
    doc: str
    result: str
    args: tuple[Arg, ...] = ()
    run: Callable[[CommandedWorld, dict[str, Any]], dict[str, Any]] | None = None
    flight: bool = False
    locked: bool = True


def _when(sim: CommandedWorld) -> dict[str, Any]:
    """When a command was accepted: episode time ``t`` (s) and the ROS clock ``stamp_ns``."""
    return {"t": sim.t, "stamp_ns": sim.stamp_ns}


def _vehicle(sim: CommandedWorld, a: dict[str, Any]) -> CommandedVehicle:
    """The vehicle a request names (``vehicle``; default: the first); an unknown name is an error."""
    return sim.vehicle(a.get("vehicle"))


def _takeoff(sim: CommandedWorld, a: dict[str, Any]) -> dict[str, Any]:
    return {"duration": float(_vehicle(sim, a).takeoff(a.get("altitude"))), **_when(sim)}


def _land(sim: CommandedWorld, a: dict[str, Any]) -> dict[str, Any]:
    return {"duration": float(_vehicle(sim, a).land()), **_when(sim)}


def _goto(sim: CommandedWorld, a: dict[str, Any]) -> dict[str, Any]:
    duration = _vehicle(sim, a).goto(a["position"], a.get("yaw"), a.get("speed"), a.get("duration"))
    return {"duration": float(duration), **_when(sim)}


def _velocity(sim: CommandedWorld, a: dict[str, Any]) -> dict[str, Any]:
    _vehicle(sim, a).velocity(a["forward"], a["yaw_rate"])
    return _when(sim)


def _track(sim: CommandedWorld, a: dict[str, Any]) -> dict[str, Any]:
    _vehicle(sim, a).track(
        a["position"], a.get("velocity"), a.get("acceleration"), a.get("yaw"), a.get("yaw_rate", 0.0)
    )
    return _when(sim)


def _rotors(sim: CommandedWorld, a: dict[str, Any]) -> dict[str, Any]:
    _vehicle(sim, a).rotors(a["rotor_speeds"], a.get("normalized", False))
    return _when(sim)


def _rates(sim: CommandedWorld, a: dict[str, Any]) -> dict[str, Any]:
    _vehicle(sim, a).rates(a["thrust"], a["body_rates"], a.get("normalized", False))
    return _when(sim)


def _attitude(sim: CommandedWorld, a: dict[str, Any]) -> dict[str, Any]:
    angles = (a.get("roll"), a.get("pitch"), a.get("yaw"))
    _vehicle(sim, a).attitude(a["thrust"], a.get("quaternion"), *angles, a.get("normalized", False))
    return _when(sim)


def _hold(sim: CommandedWorld, a: dict[str, Any]) -> dict[str, Any]:
    _vehicle(sim, a).hold()
    return _when(sim)


def _motors_off(sim: CommandedWorld, a: dict[str, Any]) -> dict[str, Any]:
    _vehicle(sim, a).motors_off()
    return _when(sim)


def _reset(sim: CommandedWorld, a: dict[str, Any]) -> dict[str, Any]:
    from droneulator.scenes import list_scenes

    scene = a.get("scene")
    if scene is not None and scene not in list_scenes():
        raise CommandError(
            "invalid_argument", f"unknown scene {scene!r}; known scenes: {', '.join(list_scenes())}"
        )
    sim.vehicle(a.get("vehicle"))  # an unknown vehicle fails before anything changes
    light = None
    if "light" in a:
        try:
            light = dataclasses.replace(sim.config.light, **a["light"])
        except ValueError as e:
            raise CommandError("invalid_argument", f"`light`: {e}") from None
    state = sim.reset(
        seed=a.get("seed"),
        vegetation=a.get("vegetation"),
        position=a.get("position"),
        yaw=a.get("yaw"),
        scene=scene,
        airborne=a.get("airborne"),
        vehicle=a.get("vehicle"),
        **({} if light is None else {"light": light}),
    )
    result = {
        "scene": sim.scene.name,
        "seed": sim.config.seed,
        "vegetation": sim.config.vegetation,
        "state": state.to_dict(),
    }
    return {**result, "light": dataclasses.asdict(sim.config.light)}


def _state(sim: CommandedWorld, a: dict[str, Any]) -> dict[str, Any]:
    if a.get("vehicle") == ALL_VEHICLES:
        return {"t": sim.t, "stamp_ns": sim.stamp_ns,
                "vehicles": {name: v.state.to_dict() for name, v in sim.vehicles.items()}}  # fmt: skip
    return _vehicle(sim, a).state.to_dict()


def _trigger(sim: CommandedWorld, a: dict[str, Any]) -> dict[str, Any]:
    stamp = sim.trigger(a.get("vehicle"))
    return {"frame_stamp_ns": stamp, **_when(sim)}


def _ping(sim: CommandedWorld, a: dict[str, Any]) -> dict[str, Any]:
    return {"pong": True, "time": time.time()}


def _scene_info(sim: CommandedWorld, a: dict[str, Any]) -> dict[str, Any]:
    from droneulator.scenes import list_scenes

    sc, fl = sim.scene, sim.config.flight
    return {
        "name": sc.name,
        "seed": sc.seed,
        "bounds_min": _plain(sc.bounds_min),
        "bounds_max": _plain(sc.bounds_max),
        "spawn_position": _plain(sc.spawn_position),
        "spawn_yaw": float(sc.spawn_yaw),
        "landmarks": {k: _plain(v) for k, v in sc.landmarks.items()},
        "scenes": list(list_scenes()),
        "vehicles": [v.describe() for v in sim.vehicles.values()],
        "light": dataclasses.asdict(sim.config.light),
        "vegetation": sim.config.vegetation,
        "camera_trigger": sim.config.render.camera_trigger,
        "limits": {
            "max_speed": fl.max_speed,
            "max_yaw_rate": math.pi,
            "default_speed": fl.default_speed,
            "takeoff_altitude": fl.takeoff_altitude,
            "goto_duration": [0.2, 3600.0],
        },
    }


#: ``set_wind``'s fields -> the :class:`~droneulator.config.WindConfig` fields they set
_WIND_FIELDS = {
    "speed": "speed_m_s",
    "direction_deg": "direction_deg",
    "turbulence_scale": "turbulence_scale",
    "gust_speed": "gust_speed_m_s",
    "gust_interval": "gust_interval_s",
    "gust_duration": "gust_duration_s",
    "shelter": "shelter",
}


def _set_wind(sim: CommandedWorld, a: dict[str, Any]) -> dict[str, Any]:
    world = sim
    name = a.get("vehicle")
    row = 0 if name is None else list(world.vehicles).index(world.vehicle(name).name)
    changes = {field: a[arg] for arg, field in _WIND_FIELDS.items() if arg in a}
    if "turbulence" in a:
        changes["turbulence"] = "dryden" if a["turbulence"] else "none"
    try:
        config = dataclasses.replace(world.wind.configs[row], **changes)
    except ValueError as e:
        raise CommandError("invalid_argument", str(e)) from None
    world.set_wind(config, name)
    return {"wind": dataclasses.asdict(config), "vehicle": name, **_when(sim)}


def _spraying(sim: CommandedWorld) -> Any:
    spraying = getattr(sim, "spraying", None)
    if spraying is None:
        raise CommandError(
            "no_spray_system", "this run has no spray systems: start it with --set spray.enabled=true"
        )
    return spraying


def _spray(sim: CommandedWorld, a: dict[str, Any]) -> dict[str, Any]:
    name = _vehicle(sim, a).name
    system = _spraying(sim).system(name)
    system.set(a["rate"], a.get("nozzles"))
    return {"spray": system.state(), "vehicle": name, **_when(sim)}


def _spray_refill(sim: CommandedWorld, a: dict[str, Any]) -> dict[str, Any]:
    name = _vehicle(sim, a).name
    system = _spraying(sim).refill(name, a.get("litres"))
    return {"spray": system.state(), "vehicle": name, **_when(sim)}


def _spray_deposit(sim: CommandedWorld, a: dict[str, Any]) -> dict[str, Any]:
    image = _spraying(sim).deposit_image()
    if a.get("since") == image.version:
        return {"version": image.version, "changed": False}
    return {**image.to_dict(), "changed": True}


#: the ``fault`` op's fields that are a kind's parameters (docs/faults.md)
_FAULT_PARAMS = ("rotor", "efficiency", "noise_m", "satellites", "drift", "offset", "accel", "gyro", "rate",
                 "field")  # fmt: skip


def _fault(sim: CommandedWorld, a: dict[str, Any]) -> dict[str, Any]:
    params = {k: a[k] for k in _FAULT_PARAMS if k in a}
    try:
        spec = FaultSpec(kind=a["kind"], vehicle=a.get("vehicle"), duration=a.get("duration"), **params)
    except FaultError as e:
        raise CommandError(e.code, e.message) from None
    return {"fault": sim.inject_fault(spec), **_when(sim)}


def _fault_clear(sim: CommandedWorld, a: dict[str, Any]) -> dict[str, Any]:
    kind = a.get("kind")
    if kind is not None and kind not in FAULT_KINDS:
        known = ", ".join(FAULT_KINDS)
        raise CommandError("invalid_argument", f"unknown fault kind {kind!r}; the kinds are {known}")
    return {"cleared": sim.clear_faults(a.get("vehicle"), kind, a.get("fault_id")), **_when(sim)}


#: the ``vehicle`` field of every flight op
_VEHICLE = Arg(
    "vehicle", "string", "the vehicle to command, by name (see `scene_info.vehicles`; default: the first)"
)

#: what the three commands below the SE(3) controller share (docs/control.md)
_STREAM = (
    "Send them at 20 Hz or more: after 0.5 s of sim time without one the vehicle holds where it is (on "
    "the ground: stops its motors) and a `{op}_timeout` event follows. Accepted on the ground too; the "
    "limits are the vehicle's, in `scene_info` (`vehicles[].limits`); docs/control.md."
)
_THRUST = Arg(
    "thrust",
    "number",
    "collective thrust, N, in [0, `limits.max_thrust`] (every rotor at full speed); with `normalized` a "
    "share of it in [0, 1]",
    True,
)
_NORMALIZED = Arg("normalized", "boolean", "thrusts as shares in [0, 1] of the largest (default false)")

_T = (
    "sim time (s) when the command was accepted; `stamp_ns`: the same instant on the ROS clock (integer ns), "
    "so a client can wait for the first image stamped after it"
)

OPS: dict[str, Op] = {
    op.name: op
    for op in (
        Op(
            "takeoff",
            "Climb vertically from the current x, y to `altitude` on a min-snap path; an `arrived` "
            "event follows, then the vehicle holds.",
            f"`duration`: planned climb time (s); `t`: {_T}",
            (
                Arg(
                    "altitude", "number", "target altitude above the ground, m (default 2.0, from the config)"
                ),
            ),
            _takeoff,
            flight=True,
        ),
        Op(
            "land",
            "Descend at 0.6 m/s to the ground below; a `landed` event follows and the motors stop "
            "(mode `idle`).",
            f"`duration`: planned descent time (s); `t`: {_T}",
            (),
            _land,
            flight=True,
        ),
        Op(
            "goto",
            "Fly a minimum-snap trajectory to `position`, ending at rest with heading `yaw`; an "
            "`arrived` event follows, then the vehicle holds. A new command replaces the move.",
            f"`duration`: planned flight time (s); `t`: {_T}",
            (
                Arg("position", "vec3", "target [x, y, z] in the world frame (ENU, z up), m", required=True),
                Arg("yaw", "number", "final heading, rad about +z, 0 = +x, CCW positive (default: kept)"),
                Arg("speed", "number", "peak speed, m/s, in (0, max_speed] (default 1.0)"),
                Arg("duration", "number", "flight time, s, in [0.2, 3600]; overrides `speed`"),
            ),
            _goto,
            flight=True,
        ),
        Op(
            "velocity",
            "Velocity mode at constant altitude: move along the body x axis at `forward` while turning "
            "at `yaw_rate`, until another command.",
            f"`t`: {_T}",
            (
                Arg("forward", "number", "speed along the body x axis, m/s, |forward| <= max_speed", True),
                Arg("yaw_rate", "number", "turn rate about +z, rad/s, CCW positive, |yaw_rate| <= pi", True),
            ),
            _velocity,
            flight=True,
        ),
        Op(
            "track",
            "Track one setpoint of a stream (e.g. a planner's, like EGO-Planner's PositionCommand on "
            "`/<ns>/position_cmd`): the SE(3) controller takes it as its reference, propagated with "
            "constant acceleration and yaw rate until the next one. The controller bounds what it asks "
            "of the vehicle as an autopilot does (thrust tilt at most `flight.max_tilt_deg`, 45 deg; "
            "vertical thrust at least `flight.min_lift`, 0.2 g; yaw moment reduced first when a rotor "
            "saturates), so a setpoint far from the vehicle brings it there without turning it over. "
            "Send them at 20 Hz or more: after "
            "0.5 s of sim time without one the vehicle holds where it is and a `track_timeout` event "
            "follows. Needs the vehicle airborne.",
            f"`t`: {_T}",
            (
                Arg("position", "vec3", "reference [x, y, z] in the world frame (ENU, z up), m", True),
                Arg("velocity", "vec3", "velocity feed-forward, m/s, world, norm <= max_speed (default 0)"),
                Arg("acceleration", "vec3", "acceleration feed-forward, m/s^2, world, |a| <= 10 (default 0)"),
                Arg("yaw", "number", "heading, rad about +z, 0 = +x, CCW positive (default: kept)"),
                Arg("yaw_rate", "number", "heading rate feed-forward, rad/s, |yaw_rate| <= pi (default 0)"),
            ),
            _track,
            flight=True,
        ),
        Op(
            "rotors",
            "Set the four rotor speeds directly, no controller in the loop (RotorPy's rotor order; the "
            "motors follow with the airframe's lag). A speed outside the airframe's range "
            "(`limits.rotor_speed`) is refused; normalised thrusts `u` give `rotor_speed_max * sqrt(u)`, "
            "raised to `rotor_speed_min`. " + _STREAM.format(op="rotors"),
            f"`t`: {_T}",
            (
                Arg("rotor_speeds", "vec4", "rad/s, each in `limits.rotor_speed`; with `normalized` each "
                    "rotor's thrust as a share in [0, 1] of its largest", True),  # fmt: skip
                _NORMALIZED,
            ),
            _rotors,
            flight=True,
        ),
        Op(
            "rates",
            "Collective thrust and body rates (CTBR, as an autopilot's acro mode): the body-rate loop "
            "(proportional and integral, its gains `limits.rate_gain` per airframe or `flight.rate_gain`) "
            "turns them into rotor speeds every control period, yaw given up first when a rotor saturates, "
            "rotor speeds clipped to their range. " + _STREAM.format(op="rates"),
            f"`t`: {_T}",
            (
                _THRUST,
                Arg("body_rates", "vec3", "roll, pitch, yaw rates, rad/s, body FLU, each within "
                    "`limits.max_body_rate` (720, 720, 540 deg/s: "
                    "`flight.max_body_rate_deg_s`)", True),  # fmt: skip
                _NORMALIZED,
            ),
            _rates,
            flight=True,
        ),
        Op(
            "attitude",
            "Collective thrust and attitude: the SE(3) controller's attitude loop (RotorPy's `cmd_ctatt`, "
            "the airframe's attitude gains) turns them into rotor speeds every control period. The attitude "
            "is a `quaternion` or `roll`, `pitch`, `yaw`, tilted at most `limits.max_attitude_tilt_deg` (60 "
            "deg: `flight.max_attitude_tilt_deg`) from level. " + _STREAM.format(op="attitude"),
            f"`t`: {_T}",
            (
                _THRUST,
                Arg("quaternion", "vec4", "[x, y, z, w], body FLU to world ENU, norm 1 within 1 % "
                    "(normalised); not with roll, pitch, yaw"),  # fmt: skip
                Arg("roll", "number", "rad, Z-Y-X Euler angles (default 0)"),
                Arg("pitch", "number", "rad (default 0)"),
                Arg("yaw", "number", "heading, rad about +z, 0 = +x, CCW positive (default: the current)"),
                _NORMALIZED,
            ),
            _attitude,
            flight=True,
        ),
        Op(
            "hold",
            "Hover at the current position and heading.",
            f"`t`: {_T}",
            (),
            _hold,
            flight=True,
        ),
        Op(
            "motors_off",
            "Stop the motors at once (the vehicle falls if airborne) and end any command.",
            f"`t`: {_T}",
            (),
            _motors_off,
            flight=True,
        ),
        Op(
            "reset",
            "Restart the flight of every vehicle at t = 0, each at its start, optionally in another scene "
            "or with another seed; `position`, `yaw` and `airborne` place the vehicle `vehicle` names. A "
            "`position` above the ground starts hovering there unless `airborne` is false; `light` changes "
            "the fields it names of the light (time of day, clouds, haze; RGB only). Refused while any "
            "vehicle's flight is locked for it.",
            "`scene`, `seed`, `vegetation`: what is loaded now; `state`: the new state of that vehicle (as "
            "`state`); `light`: the light settings now in effect",
            (
                Arg("scene", "string", "scene name, see `scene_info.scenes` (default: keep)"),
                Arg("seed", "integer", "scene layout and noise seed (default: keep)", bounds=(0, 2**32 - 1)),
                Arg(
                    "vegetation",
                    "number",
                    "vegetation density the scene is built with, 1 as designed (default: keep)",
                    bounds=VEGETATION_RANGE,
                ),
                Arg("position", "vec3", "start [x, y, z], world frame, m (default: the scene's spawn)"),
                Arg("yaw", "number", "start heading, rad (default: the scene's spawn yaw)"),
                Arg("airborne", "boolean", "hover at the start (default: true if z > 0.05 m)"),
                Arg("light", "light", "light fields to change; the others keep their values (default: keep)"),
            ),
            _reset,
            flight=True,
        ),
        Op(
            "state",
            "The current ground-truth vehicle state.",
            "`t` (s) and `t_ns` (integer ns) since the last reset; `stamp_ns` (integer ns): the "
            "simulator's monotonic clock, which keeps counting across resets and stamps every ROS message "
            "(equal to `t_ns` before the first reset); `position` [x, y, z] (m, world); "
            "`velocity` (m/s, world); `quaternion` [x, y, z, w] (body FLU to world); `angular_velocity` "
            "(rad/s, body); `yaw` (rad); `mode` (`idle`, `takeoff`, `goto`, `hold`, `velocity`, `track`, "
            '`land`, `collided`, `crashed`, `external`, `rotors`, `rates`, `attitude`); `vehicle`: its name; '
            "`wind` [x, y, z] (m/s, world): the wind "
            "at the vehicle, rotor wakes of vehicles above included; `battery` (`battery.enabled`, "
            "docs/battery.md): `voltage` (V, under load), `current` (A, discharging positive), `power` (W), "
            "`soc` (0..1), `remaining_mah`, `capacity_mah`, `cells`, `ocv` (V), `empty` and `top_speed` (the "
            "share of the airframe's top rotor speed the voltage leaves). With `vehicle` `\"*\"`: `t`, "
            "`stamp_ns` and `vehicles` (name -> that state) for every vehicle",
            (
                Arg(
                    "vehicle",
                    "string",
                    'the vehicle, by name, or `"*"` for every vehicle (default: the first)',
                ),
            ),
            _state,
        ),
        Op(
            "set_wind",
            "Change the wind field (docs/wind.md) for every vehicle, or for `vehicle` only: fields left out "
            "keep their values. The turbulence carries on, so the wind changes without a jump in its "
            "random part; the wind each vehicle feels is in its `state` (`wind`) and on its ROS `wind` "
            "topic.",
            f"`wind`: the settings now in effect (the `wind` config section's fields); `vehicle`; `t`: {_T}",
            (
                Arg("speed", "number", "mean wind 6.1 m (20 ft) above the ground, m/s", bounds=(0.0, 40.0)),
                Arg("direction_deg", "number", "where it blows from, degrees clockwise from north (270: W)"),
                Arg("turbulence", "boolean", "Dryden turbulence on or off"),
                Arg("turbulence_scale", "number", "turbulence intensity, x the standard's", bounds=(0, 5)),
                Arg("gust_speed", "number", "peak speed of the discrete 1-cosine gusts, m/s", bounds=(0, 40)),
                Arg("gust_interval", "number", "mean time between gusts, s", bounds=(0.1, 3600)),
                Arg("gust_duration", "number", "length of one gust, s", bounds=(0.1, 60)),
                Arg("shelter", "boolean", "the canopy shelters the wind"),
                Arg("vehicle", "string", "the one vehicle whose wind changes (default: every vehicle)"),
            ),
            _set_wind,
        ),
        Op(
            "spray",
            "Switch a vehicle's spray system (`spray.enabled`): spray at `rate` (0: off, 1: the pump's full "
            "flow) through `nozzles` (default: all). The tank empties at the flow and the vehicle grows "
            "lighter; spraying from an empty tank is refused (`tank_empty`), the flight goes on.",
            "`spray`: the system's state (`on`, `rate`, `level_l`, `tank_l`, `flow_l_min`, `sprayed_l`, "
            "`nozzles`); `vehicle`; `t`: " + _T,
            (
                Arg("rate", "number", "share of the pump's full flow", required=True, bounds=(0, 1)),
                Arg("nozzles", "strings", "the nozzles to open, by name (default: all)"),
                _VEHICLE,
            ),
            _spray,
        ),
        Op(
            "spray_refill",
            "Fill a vehicle's spray tank (as on the ground between flights; its mass follows).",
            "`spray`: the system's state; `vehicle`; `t`: " + _T,
            (Arg("litres", "number", "how full (L; default: the configured load)", bounds=(0, 1000)),
             _VEHICLE),  # fmt: skip
            _spray_refill,
        ),
        Op(
            "spray_deposit",
            "The ground deposit of every vehicle's spray (`spray.enabled`) as a small picture: the levels of "
            "the ROS grid `/<namespace>/spray/deposit` (0 where nothing landed, 1-100 over log10 of 1e-4 "
            "to 10 uL/cm^2) as an 8-bit greyscale PNG, one pixel a cell, row r the cells at y index r "
            "from the origin (the ROS grid's order). Give the `version` you have as `since` to get the "
            "picture only when the deposit changed (the browser UI asks once a second of sim time).",
            "`changed`: false (then only `version`) when the deposit is still that of version `since`; "
            "else true with `version` (one higher at each change, across resets too), `t` (s) and "
            "`stamp_ns` when it was taken, `width` (cells along x), `height` (along y), `cell_m`, "
            "`origin` [x, y] (m, world: the corner of cell (0, 0)), `range_ul_cm2` [1e-4, 10] (the "
            "deposits of levels 1 and 100) and `png` (base64)",
            (Arg("since", "integer", "the `version` already held (default: none)", bounds=(0, 2**53)),),
            _spray_deposit,
        ),
        Op(
            "fault",
            "Inject a fault into a vehicle now (docs/faults.md): `rotor` (a rotor's loss of efficiency), "
            "`gps_loss`, `gps_jamming`, `gps_spoofing`, `imu_bias`, `baro_drift`, `mag_interference`, "
            "`camera_dropout` or `link_cut` (its flight commands are answered `link_cut`, so a command "
            "stream stops and the vehicle holds after its stream timeout). A `fault_started` event "
            "follows, and a `fault_ended` one when `duration` runs out or `fault_clear` ends it; a reset "
            "ends every fault. Each kind takes only its own parameters (a foreign one is refused). PX4 and "
            "ArduPilot see the sensor faults in the sensor data they get.",
            "`fault`: the fault as started (`id`, `kind`, `vehicle`, `start` s, `duration`, its "
            "parameters with their defaults); `t`: " + _T,
            (
                Arg("kind", "string", "the fault: " + ", ".join(f"`{k}`" for k in FAULT_KINDS), True),
                Arg("duration", "number", "how long it lasts, s (default: until `fault_clear` or a reset)"),
                Arg("rotor", "integer", "`rotor`: the rotor, 0-3 in RotorPy's order (required)"),
                Arg("efficiency", "number", "`rotor`: the share of its thrust left, 0-1 (default 0: dead)"),
                Arg("noise_m", "number", "`gps_jamming`: extra position noise, 1-sigma per axis, m "
                    "(default 5)"),  # fmt: skip
                Arg("satellites", "integer", "`gps_jamming`: satellites the fixes report, 0-50 (default 4)"),
                Arg("drift", "vec3", "`gps_spoofing`: how fast the position moves off, [e, n, u] m/s "
                    "(default 0)"),  # fmt: skip
                Arg("offset", "vec3", "`gps_spoofing`: the position's offset at the start, [e, n, u] m "
                    "(default 0)"),  # fmt: skip
                Arg("accel", "vec3", "`imu_bias`: accelerometer bias step, m/s^2, body FRD (default 0)"),
                Arg("gyro", "vec3", "`imu_bias`: gyroscope bias step, rad/s, body FRD (default 0)"),
                Arg("rate", "number", "`baro_drift`: drift of the pressure altitude, m/s (default 0.5)"),
                Arg("field", "vec3", "`mag_interference`: field added, gauss, body FRD (required)"),
                _VEHICLE,
            ),
            _fault,
        ),
        Op(
            "fault_clear",
            "End active faults at once (those matching every field given; all of them for none); a "
            "`fault_ended` event follows for each.",
            "`cleared`: the ids of the faults ended; `t`: " + _T,
            (
                Arg("kind", "string", "only faults of this kind"),
                # not `id`: that is the request's own id, which the transport strips before the op sees it
                Arg("fault_id", "integer", "only the fault with this id (the `fault` reply's `fault.id`)"),
                Arg("vehicle", "string", "only the faults of this vehicle"),
            ),
            _fault_clear,
        ),
        Op(
            "trigger",
            "Have the vehicle's cameras take one frame set (every camera of its rig: RGB, depth and "
            "segmentation, with camera_info and pose) at the end of the next control period, as a survey "
            "camera triggered at a waypoint. Only when the simulator runs with "
            "`render.camera_trigger=command`, where nothing else is rendered (`droneulator capture` runs it "
            "so); in lockstep the clock holds until the frame set is published. Refused (`unsupported`) at "
            "the camera rate.",
            "`frame_stamp_ns`: the stamp (ROS clock, integer ns) the frame set will carry; `t`: " + _T,
            (_VEHICLE,),
            _trigger,
        ),
        Op(
            "ping",
            "Liveness check; answered without waiting for the simulation.",
            "`pong`: true; `time`: server wall-clock time (Unix s)",
            (),
            _ping,
            locked=False,
        ),
        Op(
            "scene_info",
            "Describe the loaded scene and the command limits.",
            "`name`, `seed`; `bounds_min`, `bounds_max` (flyable box, m); `spawn_position`, `spawn_yaw`; "
            "`landmarks` (name -> nested lists); `scenes` (loadable names); `limits` (`max_speed`, "
            "`max_yaw_rate`, `default_speed`, `takeoff_altitude`, `goto_duration` range); `vehicles`: "
            "one entry per vehicle, first the default: `name`, `params` (airframe), `controlled_by` "
            "(`internal`, `px4` or `ardupilot`), `cameras` (names), `limits` (what `rotors`, `rates` and "
            "`attitude` accept: `rotor_speed` [min, max] rad/s, `max_thrust` N, `thrust_to_weight`, "
            "`max_body_rate` rad/s, `max_attitude_tilt_deg`, `rate_gain` 1/s, `stream_timeout` s), and where "
            "it is reached when a runtime serves it: `namespace` and `topics` (its ROS 2 topic names), "
            "`tf_prefix`, `px4_port` (PX4 vehicles), `ardupilot_port` (ArduPilot vehicles); "
            "`light`: the light settings (the config's `light` section as it is now; see `reset`); "
            "`vegetation`: the scene's vegetation density; `camera_trigger`: `rate` (cameras shoot at "
            "`render.camera_hz`) or `command` (only at `trigger`)",
            (),
            _scene_info,
        ),
        Op(
            "subscribe",
            "Start pushed streams on this connection, replacing its previous subscription: `state` "
            "messages at up to `rate_hz` (latest value only; each names its `vehicle`) and every `event` "
            "in order (those of a vehicle name it in `vehicle`, whichever vehicle the state stream "
            "follows).",
            "`streams`: the streams now active; `rate_hz`: the state rate (null without `state`); "
            "`vehicles` (when `vehicle` was given): the vehicles whose state is pushed",
            (
                Arg("streams", "streams", 'streams to receive (default ["state", "events"])'),
                Arg(
                    "vehicle",
                    "string",
                    'whose state to push: a vehicle name, or `"*"` for every vehicle, one message each '
                    "(default: the first)",
                ),
                Arg(
                    "rate_hz",
                    "number",
                    "maximum state rate, Hz (default: the server's, 30)",
                    bounds=(0.1, 1000),
                ),
            ),
            None,
            locked=False,
        ),
        Op(
            "unsubscribe",
            "Stop pushed streams on this connection.",
            "`streams`: the streams still active",
            (Arg("streams", "streams", "streams to stop (default: all)"),),
            None,
            locked=False,
        ),
    )
}


#: every flight op commands one vehicle: the one its ``vehicle`` field names, like AirSim's ``vehicle_name``
for _name, _op in OPS.items():
    if _op.flight:
        OPS[_name] = dataclasses.replace(_op, args=(*_op.args, _VEHICLE))


# --------------------------------------------------------------------------- parsing & validation
@dataclass
class Request:
    """A parsed request: ``args`` are validated and normalised for table ops, raw for extra ops."""

    id: int | str | None
    op: str
    args: dict[str, Any]


def _plain(v: Any) -> Any:
    """numpy arrays and scalars as plain lists and numbers."""
    return v.tolist() if hasattr(v, "tolist") else v


def encode(message: Mapping[str, Any]) -> str:
    """Compact strict JSON (no NaN); numpy values become plain numbers and lists."""
    return json.dumps(message, separators=(",", ":"), allow_nan=False, default=_json_default)


def _json_default(o: Any) -> Any:
    if hasattr(o, "tolist"):
        return o.tolist()
    raise TypeError(f"{type(o).__name__} is not JSON serialisable")


def ok_reply(request_id: int | str | None, result: Any) -> dict[str, Any]:
    return {"id": request_id, "ok": True, "result": {} if result is None else result}


def error_reply(request_id: int | str | None, code: str, message: str) -> dict[str, Any]:
    return {"id": request_id, "ok": False, "error": {"code": code, "message": message}}


def _non_finite(value: Any) -> str | None:
    """Path of the first NaN/Infinity inside ``value`` (iterative: no recursion limit), else None."""
    stack: list[tuple[str, Any]] = [("", value)]
    while stack:
        path, v = stack.pop()
        if isinstance(v, float) and not math.isfinite(v):
            return path
        if isinstance(v, dict):
            stack.extend((f"{path}.{k}" if path else str(k), x) for k, x in v.items())
        elif isinstance(v, list):
            stack.extend((f"{path}[{i}]", x) for i, x in enumerate(v))
    return None


def _number(value: Any, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise CommandError("invalid_argument", f"{what} must be a number, got {json.dumps(value)[:40]}")
    try:
        x = float(value)
    except OverflowError:
        x = math.inf
    if not math.isfinite(x):
        raise CommandError("invalid_argument", f"{what} must be a finite number")
    return x


def _validate(arg: Arg, value: Any) -> Any:
    what = f"`{arg.name}`"
    if arg.type == "number":
        out: Any = _number(value, what)
    elif arg.type == "integer":
        if isinstance(value, bool) or not isinstance(value, int):
            raise CommandError("invalid_argument", f"{what} must be an integer, got {json.dumps(value)[:40]}")
        out = value
    elif arg.type == "boolean":
        if not isinstance(value, bool):
            got = json.dumps(value)[:40]
            raise CommandError("invalid_argument", f"{what} must be true or false, got {got}")
        out = value
    elif arg.type == "string":
        if not isinstance(value, str):
            raise CommandError("invalid_argument", f"{what} must be a string, got {json.dumps(value)[:40]}")
        out = value
    elif arg.type == "vec3":
        if not isinstance(value, list) or len(value) != 3:
            raise CommandError("invalid_argument", f"{what} must be an array of 3 numbers [x, y, z]")
        out = [_number(v, f"{what}[{i}]") for i, v in enumerate(value)]
    elif arg.type == "strings":
        if not isinstance(value, list) or not value or not all(isinstance(v, str) for v in value):
            raise CommandError("invalid_argument", f"{what} must be a non-empty array of strings")
        out = list(value)
    elif arg.type == "vec4":
        if not isinstance(value, list) or len(value) != 4:
            raise CommandError("invalid_argument", f"{what} must be an array of 4 numbers")
        out = [_number(v, f"{what}[{i}]") for i, v in enumerate(value)]
    elif arg.type == "streams":
        if not isinstance(value, list) or not value or any(s not in STREAMS for s in value):
            streams = " and/or ".join(f'"{s}"' for s in STREAMS)
            raise CommandError("invalid_argument", f"{what} must be a non-empty array of {streams}")
        out = tuple(s for s in STREAMS if s in value)
    elif arg.type == "light":
        out = _light_fields(value, what)
    else:
        raise AssertionError(f"unknown argument type {arg.type!r}")
    if arg.bounds is not None and not arg.bounds[0] <= out <= arg.bounds[1]:
        raise CommandError("out_of_range", f"{what} must lie in [{arg.bounds[0]:g}, {arg.bounds[1]:g}]")
    return out


def _light_fields(value: Any, what: str) -> dict[str, Any]:
    """A ``light`` object's fields, each of the right JSON type (their ranges are the config's to check)."""
    from droneulator.config.light import LightConfig

    names = [f.name for f in dataclasses.fields(LightConfig)]
    if not isinstance(value, dict):
        accepted = ", ".join(names)
        raise CommandError("invalid_argument", f"{what} must be an object of light fields ({accepted})")
    unknown = sorted(set(value) - set(names))
    if unknown:
        raise CommandError(
            "invalid_argument", f"unknown {what} field(s) {', '.join(unknown)}; accepted: {', '.join(names)}"
        )
    out: dict[str, Any] = {}
    for name, v in value.items():
        field = f"`{what.strip('`')}.{name}`"
        if v is None:
            out[name] = None
        elif name == "date":
            if not isinstance(v, str):
                raise CommandError("invalid_argument", f'{field} must be a string like "2026-06-21"')
            out[name] = v
        else:
            out[name] = _number(v, field)
    return out


def make_request(
    op: str, args: Mapping[str, Any], request_id: int | str | None = None, extra_ops: Collection[str] = ()
) -> Request:
    """Validate ``args`` of ``op`` against :data:`OPS` (raw for extra ops); raises :class:`RequestError`.

    Every command source builds its requests here (the WebSocket server through :func:`parse_request`,
    ROS topics directly), so one set of rules applies to all of them.
    """
    if op not in OPS and op not in extra_ops:
        known = ", ".join([*OPS, *sorted(extra_ops)])
        raise RequestError("unknown_op", f"unknown op {op[:64]!r}; known ops: {known}", request_id)
    bad = _non_finite(dict(args))
    if bad is not None:
        raise RequestError(
            "invalid_argument", f"`{bad}` must be a finite number (NaN/Infinity not allowed)", request_id
        )
    if op not in OPS:
        return Request(request_id, op, dict(args))
    spec = OPS[op]
    names = {a.name for a in spec.args}
    extra = sorted(set(args) - names)
    if extra:
        accepted = ", ".join(sorted(names)) or "none"
        raise RequestError(
            "invalid_argument",
            f"unexpected field(s) {', '.join(extra)} for {op}; accepted: {accepted}",
            request_id,
        )
    out: dict[str, Any] = {}
    try:
        for a in spec.args:
            value = args.get(a.name)
            if value is None:
                if a.required:
                    raise CommandError("invalid_argument", f"missing required field `{a.name}` for {op}")
                continue
            out[a.name] = _validate(a, value)
    except CommandError as e:
        raise RequestError(e.code, e.message, request_id) from None
    return Request(request_id, op, out)


# --------------------------------------------------------------------------- execution
ExtraOp = Callable[[dict[str, Any]], Any]


def execute(
    sim: CommandedWorld | None,
    request: Request,
    extra_ops: Mapping[str, ExtraOp] | None = None,
    flight_locked: str | None = None,
) -> dict[str, Any]:
    """Run a parsed request and build its reply; never raises.

    The caller holds the simulation lock when ``OPS[op].locked``. ``flight_locked`` (a reason) makes
    flight ops answer ``flight_locked``. ``extra_ops`` get the raw arguments and may return any
    JSON-able value (None means ``{}``); ``sim`` is None only for them (a table op then answers
    ``internal_error``).
    """
    try:
        if extra_ops and request.op in extra_ops:
            result = extra_ops[request.op](request.args)
        else:
            spec = OPS[request.op]
            if spec.run is None:
                raise CommandError(
                    "unsupported", f"{request.op} needs a streaming connection (the WebSocket server)"
                )
            if spec.flight and flight_locked is not None:
                raise CommandError("flight_locked", flight_locked)
            if sim is None:
                raise CommandError("internal_error", f"{request.op} needs the simulator, and none was given")
            if spec.flight and request.op != "reset" and sim.command_link_cut(request.args.get("vehicle")):
                who = request.args.get("vehicle") or "the vehicle"
                raise CommandError("link_cut", f"the command link of {who} is cut (a link_cut fault): the "
                                   "command was not delivered")  # fmt: skip
            result = spec.run(sim, request.args)
        reply = ok_reply(request.id, result)
        encode(reply)  # fail here, with a proper error, rather than in the transport
        return reply
    except CommandError as e:
        return error_reply(request.id, e.code, e.message)
    except Exception as e:
        log.exception("op %r failed", request.op)
        return error_reply(request.id, "internal_error", f"{request.op} failed: {type(e).__name__}: {e}")


# --------------------------------------------------------------------------- documentation
def ops_markdown() -> str:
    """The op and error reference of docs/api.md, generated from :data:`OPS` and :data:`ERROR_CODES`."""
    lines: list[str] = []
    for op in OPS.values():
        lines += [f"### `{op.name}`", "", op.doc]
        if op.flight:
            lines[-1] += " Refused with `flight_locked` while another controller is in control."
        lines.append("")
        if op.args:
            lines += ["| field | type | required | meaning |", "|---|---|---|---|"]
            for a in op.args:
                req = "yes" if a.required else "no"
                lines.append(f"| `{a.name}` | {a.type} | {req} | {a.doc} |")
            lines.append("")
        else:
            lines += ["No fields.", ""]
        lines += [f"Result: {op.result}.", ""]
    lines += ["### Argument types", "", "| type | JSON |", "|---|---|"]
    lines += [f"| {name} | {desc} |" for name, desc in TYPES.items()]
    lines += ["", "### Error codes", "", "| code | when |", "|---|---|"]
    lines += [f"| `{code}` | {when} |" for code, when in ERROR_CODES.items()]
    return "\n".join(lines) + "\n"
