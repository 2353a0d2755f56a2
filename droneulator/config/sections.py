"""The simulator's configuration sections and :class:`SimConfig`, which holds them all."""

from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass, field

from droneulator.config.camera_presets import DEPTH_PRESETS, RGB_PRESETS, radial_invertible
from droneulator.config.capture import CaptureConfig
from droneulator.config.faults import FaultSpec
from droneulator.config.light import LightConfig
from droneulator.config.randomize import RandomizeConfig
from droneulator.config.rl import RLConfig
from droneulator.config.scene import check_vegetation
from droneulator.config.sensor_presets import (
    BARO_PRESETS,
    GPS_PRESETS,
    IMU_PRESETS,
    MAG_PRESETS,
    GpsError,
    ImuModel,
    check_preset,
)
from droneulator.config.site import SiteConfig
from droneulator.config.spray import SprayConfig, WeatherConfig
from droneulator.config.wind import WindConfig


@dataclass
class CameraConfig:
    """One camera of the rig: RGB, depth and segmentation share this pose and these intrinsics."""

    name: str = "front"
    width: int = 640
    height: int = 480
    hfov_deg: float = 90.0
    #: mount position in the body FLU frame, metres
    position: tuple[float, float, float] = (0.12, 0.0, 0.0)
    #: mount roll, pitch, yaw in degrees; positive pitch looks down
    rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    near: float = 0.05
    far: float = 200.0
    #: depth error model (camera_presets.DEPTH_PRESETS): "ideal" (exact), "d435" (RealSense D435 active
    #: stereo) or "tof" (Azure Kinect-class time of flight); invalid pixels read NaN (docs/sensors.md)
    depth_model: str = "ideal"
    #: multiply the depth preset's noise (stereo subpixel error, ToF noise std) and its dropout and flying
    #: pixel probabilities: a camera better or worse than the preset's typical one (domain randomisation
    #: draws them)
    depth_noise_scale: float = 1.0
    depth_dropout_scale: float = 1.0
    #: RGB sensor noise (camera_presets.RGB_PRESETS): "ideal", "machine_vision" or "small_pixel"
    rgb_noise: str = "ideal"
    #: lens distortion, OpenCV's plumb_bob (k1, k2, p1, p2, k3): all three images are distorted alike and
    #: camera_info carries it as D
    distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    #: RGB exposure time (s): brightness relative to the rendered image (which stands for
    #: camera_presets.REFERENCE_EXPOSURE_S) and the motion blur window; with auto_exposure, the longest
    exposure_s: float = 0.002
    #: pick exposure (then gain) each frame so that the mean brightness meets camera_presets.AE_TARGET
    auto_exposure: bool = False
    #: blur RGB along the image motion of the vehicle's velocity and rotation during the exposure
    motion_blur: bool = False

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"camera {self.name!r}: width and height must be positive")
        if not 1.0 <= self.hfov_deg <= 170.0:
            raise ValueError(f"camera {self.name!r}: hfov_deg must lie in [1, 170]")
        if not 0 < self.near < self.far:
            raise ValueError(f"camera {self.name!r}: need 0 < near < far")
        who = f"camera {self.name!r}"
        if self.depth_model not in DEPTH_PRESETS:
            choices = ", ".join(DEPTH_PRESETS)
            raise ValueError(f"{who}: depth_model must be one of {choices}, got {self.depth_model!r}")
        if self.rgb_noise not in RGB_PRESETS:
            choices = ", ".join(RGB_PRESETS)
            raise ValueError(f"{who}: rgb_noise must be one of {choices}, got {self.rgb_noise!r}")
        for name in ("depth_noise_scale", "depth_dropout_scale"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and 0.0 <= value <= 10.0):
                raise ValueError(f"{who}: {name} must lie in [0, 10], got {value!r}")
        if not (math.isfinite(self.exposure_s) and 0.0 < self.exposure_s <= 1.0):
            raise ValueError(f"{who}: exposure_s must lie in (0, 1] seconds, got {self.exposure_s!r}")
        d = tuple(self.distortion)
        if len(d) != 5 or not all(isinstance(v, int | float) and math.isfinite(v) for v in d):
            raise ValueError(f"{who}: distortion must be five finite numbers (k1, k2, p1, p2, k3), got {d!r}")
        self.distortion = (float(d[0]), float(d[1]), float(d[2]), float(d[3]), float(d[4]))
        corner = math.hypot(self.width, self.height) / self.width * math.tan(math.radians(self.hfov_deg) / 2)
        if not radial_invertible(self.distortion, corner):
            raise ValueError(f"{who}: distortion {d} folds the image over (radial part not one-to-one)")

    @property
    def rpy(self) -> tuple[float, float, float]:
        r, p, y = (math.radians(a) for a in self.rpy_deg)
        return r, p, y


#: when a vehicle's cameras take a frame set (``render.camera_trigger``)
CAMERA_TRIGGERS = ("rate", "command")


@dataclass
class RenderConfig:
    shadows: bool = True
    shadow_map_size: int = 2048
    camera_hz: float = 30.0
    cameras: list[CameraConfig] = field(default_factory=lambda: [CameraConfig()])
    #: ``rate``: every camera shoots at ``camera_hz``; ``command``: a vehicle's cameras shoot one frame set
    #: each time the API's ``trigger`` op asks (as a survey camera triggered at its waypoints), and nothing
    #: is rendered in between, so a lockstep run flies as fast as its physics between the shots
    camera_trigger: str = "rate"

    def __post_init__(self) -> None:
        if self.camera_trigger not in CAMERA_TRIGGERS:
            raise ValueError(
                f"render.camera_trigger must be one of {', '.join(CAMERA_TRIGGERS)}; "
                f"got {self.camera_trigger!r}"
            )


#: RotorPy wind profiles ``VehicleConfig.wind`` can name (built by :func:`droneulator.wind.make_wind`); the
#: wind field of the ``wind`` section (mean wind, Dryden turbulence, gusts, shelter) replaces them
WIND_MODELS = ("none", "constant", "sinusoid", "dryden")


#: what a touch does to a vehicle (``vehicle.contact_model``, ``VehicleSpec.contact_model``; docs/contact.md)
CONTACT_MODELS = ("stop", "physical", "crash")


@dataclass
class VehicleConfig:
    #: RotorPy parameter set: see ``droneulator.vehicles.params.PARAMETER_SETS``
    params: str = "hummingbird"
    aero: bool = True
    #: wind model: one of WIND_MODELS
    wind: str = "none"
    wind_velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)
    #: turbulence intensity (dryden) or amplitude (sinusoid) per axis, m/s
    wind_sigma: tuple[float, float, float] = (0.5, 0.5, 0.2)
    #: sphere radius used for collision with the scene, metres
    collision_radius: float = 0.25
    control_hz: float = 100.0
    #: fixed RK4 sub-steps per control period
    substeps: int = 10
    #: ground contact (droneulator.vehicles.dynamics.GroundContact): natural frequency of the vehicle
    #: bouncing on its four spring-damper legs (Hz; the legs compress g / (2 pi f)^2 under the weight),
    #: damping ratio while they compress and while they extend, Coulomb friction coefficient, and the
    #: slip speed (m/s) below which friction turns viscous
    contact_frequency_hz: float = 3.0
    contact_damping_ratio: float = 1.0
    contact_rebound_damping_ratio: float = 3.0
    ground_friction: float = 0.5
    friction_slip_speed: float = 0.05
    #: a touchdown faster than this (m/s, downward) raises an "impact" event
    impact_speed: float = 1.5
    #: what a touch of the scene or another vehicle does (docs/contact.md): "stop" (held where it touched,
    #: level, mode collided), "physical" (foliage pushes and slows it, a strike on wood costs the struck
    #: rotors their thrust), "crash" (the rotors stop: it falls, dead until placed again), or "auto":
    #: physical for a vehicle an autopilot flies (PX4, ArduPilot), stop for the others
    contact_model: str = "auto"
    #: the noisy sensors the vehicle carries (kinds of ``droneulator.sensors``; their noise and rates are
    #: in ``px4``): PX4 needs imu, mag and baro; without gps it gets no GPS fix (as under a dense canopy)
    sensors: list[str] = field(default_factory=lambda: ["imu", "mag", "baro", "gps", "airspeed"])

    def __post_init__(self) -> None:
        if self.wind not in WIND_MODELS:
            raise ValueError(f"vehicle.wind must be one of {', '.join(WIND_MODELS)}; got {self.wind!r}")
        if self.contact_model not in ("auto", *CONTACT_MODELS):
            raise ValueError(
                f"vehicle.contact_model must be auto, {', '.join(CONTACT_MODELS)}; got {self.contact_model!r}"
            )
        for name in (
            "contact_frequency_hz",
            "contact_damping_ratio",
            "contact_rebound_damping_ratio",
            "friction_slip_speed",
            "impact_speed",
        ):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"vehicle.{name} must be a positive number, got {value!r}")
        if not (math.isfinite(self.ground_friction) and self.ground_friction >= 0):
            raise ValueError(f"vehicle.ground_friction must be >= 0, got {self.ground_friction!r}")


@dataclass
class FlightConfig:
    takeoff_altitude: float = 2.0
    default_speed: float = 1.0
    max_speed: float = 5.0
    #: velocity mode limits and filters
    max_forward_accel: float = 3.0
    max_yaw_accel: float = 4.0
    filter_tau: float = 0.15
    #: max horizontal distance between the virtual reference and the vehicle (anti wind-up)
    leash: float = 1.0
    arrive_tolerance: float = 0.05
    arrive_speed: float = 0.05
    #: a goto or take-off not settled within arrive_tolerance and arrive_speed this long (sim s) after its
    #: reference ended arrives once within acceptance_radius (m) of its target, as an autopilot's waypoint
    #: acceptance radius (PX4's NAV_ACC_RAD): in wind this controller keeps a steady offset (it has no
    #: integral term) and gusts keep it moving, so the tight criterion may never hold
    arrive_timeout_s: float = 3.0
    acceptance_radius: float = 0.5
    #: the SE(3) controller keeps its thrust vector within this tilt of vertical (degrees, in (0, 90))
    #: and its vertical part at least ``min_lift`` times the weight, as PX4's MPC_TILTMAX_AIR and
    #: MPC_THR_MIN do, and gives up yaw moment before thrust when a rotor saturates (PX4's mixer);
    #: null: RotorPy's unbounded controller, which can flip the vehicle when a reference jumps metres
    #: away and lifts it when the heading is far off
    max_tilt_deg: float | None = 45.0
    min_lift: float = 0.2
    #: the body-rate loop's gain per axis (1/s, roll, pitch, yaw) for ``rates`` commands (docs/control.md);
    #: null: the airframe's, 0.4 / its motor time constant, at most 25
    rate_gain: tuple[float, float, float] | None = None
    #: the largest body rates a ``rates`` command may ask for (deg/s: roll, pitch, yaw; PX4's MC_ACRO_*_MAX)
    max_body_rate_deg_s: tuple[float, float, float] = (720.0, 720.0, 540.0)
    #: the largest tilt from level an ``attitude`` command may ask for (degrees, in (0, 180])
    max_attitude_tilt_deg: float = 60.0

    def __post_init__(self) -> None:
        if self.rate_gain is not None and (
            len(self.rate_gain) != 3 or not all(math.isfinite(k) and k > 0 for k in self.rate_gain)
        ):
            raise ValueError(f"flight.rate_gain must be three positive numbers or null, got {self.rate_gain}")
        if len(self.max_body_rate_deg_s) != 3 or not all(
            math.isfinite(r) and r > 0 for r in self.max_body_rate_deg_s
        ):
            raise ValueError(f"flight.max_body_rate_deg_s must be three positive numbers, got "
                             f"{self.max_body_rate_deg_s}")  # fmt: skip
        if not 0.0 < self.max_attitude_tilt_deg <= 180.0:
            tilt = self.max_attitude_tilt_deg
            raise ValueError(f"flight.max_attitude_tilt_deg must lie in (0, 180], got {tilt}")
        for name in ("arrive_tolerance", "arrive_speed", "arrive_timeout_s", "acceptance_radius"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"flight.{name} must be a positive number, got {value!r}")
        if self.max_tilt_deg is not None and not 0.0 < self.max_tilt_deg < 90.0:
            raise ValueError(f"flight.max_tilt_deg must lie in (0, 90), got {self.max_tilt_deg}")
        if not 0.0 <= self.min_lift < 1.0:
            raise ValueError(f"flight.min_lift must lie in [0, 1), got {self.min_lift}")


#: a LiPo cell's open-circuit (resting) voltage against its state of charge, (SoC, V) from empty to full:
#: the resting-voltage chart LiPo makers and RC references tabulate (3.27 V spent, 3.7 V near the middle,
#: 4.20 V full; docs/battery.md)
LIPO_OCV: tuple[tuple[float, float], ...] = (
    (0.00, 3.27), (0.05, 3.61), (0.10, 3.69), (0.15, 3.71), (0.20, 3.73), (0.25, 3.75), (0.30, 3.77),
    (0.35, 3.79), (0.40, 3.80), (0.45, 3.82), (0.50, 3.84), (0.55, 3.85), (0.60, 3.87), (0.65, 3.91),
    (0.70, 3.95), (0.75, 3.98), (0.80, 4.02), (0.85, 4.08), (0.90, 4.11), (0.95, 4.15), (1.00, 4.20),
)


def _check_battery_number(name: str, value: object, low: float, high: float | None = None) -> None:
    ok = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
    if not ok or value <= low or (high is not None and value > high):
        bound = f"in ({low:g}, {high:g}]" if high is not None else f"above {low:g}"
        raise ValueError(f"battery.{name} must be a number {bound}, got {value!r}")


@dataclass
class BatteryConfig:
    """A vehicle's battery (docs/battery.md): a pack of ``cells`` LiPo cells in series of ``capacity_mah``
    with a pack internal resistance, discharged by the rotors' electrical power (momentum-theory power /
    ``figure_of_merit`` / ``efficiency``). Unset (null) numbers take the airframe's pack
    (``droneulator.vehicles.battery.AIRFRAME_BATTERIES``)."""

    #: model the battery (its voltage limits the rotors' top speed; a spent pack stops them)
    enabled: bool = True
    #: cells in series, usable capacity (mAh, from full to the empty end of the curve), pack internal
    #: resistance (ohm, cells and wiring); null: the airframe's
    cells: int | None = None
    capacity_mah: float | None = None
    internal_resistance_ohm: float | None = None
    #: motor and ESC efficiency (electrical to shaft power, (0, 1]); null: the airframe's
    efficiency: float | None = None
    #: rotor figure of merit: ideal (momentum theory) power / shaft power, (0, 1]
    figure_of_merit: float = 0.6
    #: air density for the induced velocity (kg/m^3; ISA sea level)
    air_density: float = 1.225
    #: state of charge at every reset, in (0, 1]
    initial_soc: float = 1.0
    #: a cell's voltage at which the airframe's ``rotor_speed_max`` is reached (the LiPo nominal 3.7 V):
    #: below it the top speed falls in proportion to the terminal voltage
    nominal_cell_v: float = 3.7
    #: the top rotor speed follows the sagged voltage through a first-order lag of this time constant (s; the
    #: motors and ESCs do not follow a voltage step at once): it keeps the loop voltage -> top speed ->
    #: power -> voltage from chattering between control periods when a full-throttle demand overloads a pack
    speed_time_constant_s: float = 0.1
    #: a cell's open-circuit voltage against state of charge, (SoC, V) rising from SoC 0 to 1; null: LiPo
    ocv_curve: list[tuple[float, float]] | None = None

    def __post_init__(self) -> None:
        if self.cells is not None and (
            isinstance(self.cells, bool) or not isinstance(self.cells, int) or not 1 <= self.cells <= 24
        ):
            raise ValueError(f"battery.cells must be an integer in [1, 24], got {self.cells!r}")
        if self.capacity_mah is not None:
            _check_battery_number("capacity_mah", self.capacity_mah, 0.0)
        if self.internal_resistance_ohm is not None:
            r = self.internal_resistance_ohm
            if not (isinstance(r, int | float) and math.isfinite(r) and 0.0 <= r <= 10.0):
                raise ValueError(f"battery.internal_resistance_ohm must lie in [0, 10] ohm, got {r!r}")
        if self.efficiency is not None:
            _check_battery_number("efficiency", self.efficiency, 0.0, 1.0)
        _check_battery_number("figure_of_merit", self.figure_of_merit, 0.0, 1.0)
        _check_battery_number("air_density", self.air_density, 0.0)
        _check_battery_number("initial_soc", self.initial_soc, 0.0, 1.0)
        _check_battery_number("nominal_cell_v", self.nominal_cell_v, 0.0)
        _check_battery_number("speed_time_constant_s", self.speed_time_constant_s, 0.0, 10.0)
        if self.ocv_curve is not None:
            curve = [tuple(point) for point in self.ocv_curve]
            if len(curve) < 2 or any(len(p) != 2 for p in curve):
                raise ValueError("battery.ocv_curve must be two or more (SoC, V) pairs")
            soc = [float(p[0]) for p in curve]
            volts = [float(p[1]) for p in curve]
            if not all(math.isfinite(v) for v in soc + volts):
                raise ValueError("battery.ocv_curve must hold finite numbers")
            if soc[0] != 0.0 or soc[-1] != 1.0 or any(b <= a for a, b in zip(soc[:-1], soc[1:], strict=True)):
                raise ValueError(f"battery.ocv_curve's SoC must rise strictly from 0 to 1, got {soc}")
            if volts[0] <= 0.0 or any(b < a for a, b in zip(volts[:-1], volts[1:], strict=True)):
                raise ValueError(f"battery.ocv_curve's voltages must be positive and never fall, got {volts}")
            self.ocv_curve = [(s, v) for s, v in zip(soc, volts, strict=True)]

    @property
    def curve(self) -> tuple[tuple[float, float], ...]:
        """The cell's (SoC, V) curve: ``ocv_curve`` or :data:`LIPO_OCV`."""
        return LIPO_OCV if self.ocv_curve is None else tuple(self.ocv_curve)


@dataclass
class RuntimeConfig:
    """The multi-process runtime (``droneulator run``)."""

    #: "lockstep": sim time waits for every consumer (as fast as they allow);
    #: "realtime": wall-clock paced, the renderer draws the latest state when it is free
    mode: str = "lockstep"
    #: realtime mode only: simulated seconds per wall second
    speed: float = 1.0
    #: lockstep mode only: at most this many simulated seconds per wall second on average (None: as fast
    #: as the consumers allow); a wait for them of up to a second (a triggered frame holding the clock) is
    #: made up at full speed, so a run capped at 1 keeps real time. A lockstep run with little to render
    #: otherwise spends a whole core on the physics while its clients think (a triggered capture between
    #: views)
    max_speed: float | None = None
    #: loopback by default; any other address needs ``access.token`` (generated when unset; see
    #: :class:`AccessConfig`)
    api_host: str = "127.0.0.1"
    api_port: int = 8765
    api_max_message_bytes: int = 65536
    #: rate of the state stream to WebSocket subscribers and of odometry/TF/clock on the bridge (sim time)
    state_hz: float = 100.0
    #: frames in flight between dynamics, render server and bridge (shared-memory slots)
    frame_slots: int = 3
    #: restarts allowed per child process before the run stops
    max_restarts: int = 5

    def __post_init__(self) -> None:
        if self.mode not in ("lockstep", "realtime"):
            raise ValueError(f"runtime.mode must be 'lockstep' or 'realtime', got {self.mode!r}")
        if not self.speed > 0:
            raise ValueError("runtime.speed must be positive")
        if self.max_speed is not None and not self.max_speed > 0:
            raise ValueError(f"runtime.max_speed must be positive (or null: no limit), got {self.max_speed}")
        if self.frame_slots < 2:
            raise ValueError("runtime.frame_slots must be at least 2")


_ROS_NAMESPACE = re.compile(r"^(/[A-Za-z_][A-Za-z0-9_]*)+$")


@dataclass
class BridgeConfig:
    """ROS 2 over Zenoh publishing (see docs/ros2.md)."""

    #: ROS namespace of the simulator's topics: /<namespace>/odom, /<namespace>/front/...
    namespace: str = "droneulator"
    #: "ros2dds" (zenoh-bridge-ros2dds keys) or "rmw_zenoh"
    key_mode: str = "ros2dds"
    domain_id: int = 0
    #: Zenoh mode of the simulator's session: "router" routes for the simulator's other process and for
    #: local subscribers; "peer"; or "client" (leaf of the router named in connect)
    mode: str = "router"
    listen: list[str] = field(default_factory=lambda: ["tcp/127.0.0.1:7448"])
    #: empty: nothing in ros2dds key mode, rmw_zenohd on tcp/127.0.0.1:7447 in rmw_zenoh key mode
    connect: list[str] = field(default_factory=list)
    #: optional Zenoh JSON5 configuration file (listen/connect above are applied on top); an ACL
    #: (``access_control``) goes here: droneulator.runtime.zenoh_security writes one (docs/security.md)
    zenoh_config: str = ""
    #: TLS of ``tls/HOST:PORT`` endpoints (docs/security.md), PEM files, applied on top of zenoh_config:
    #: the CA that signed the other side's certificate
    tls_ca: str = ""
    #: this side's certificate (chain) and private key: served when listening on tls/, and presented
    #: when a router asks (mutual TLS); both or neither
    tls_cert: str = ""
    tls_key: str = ""
    #: mutual TLS: listening on tls/, accept only peers whose certificate tls_ca signed; connecting,
    #: present tls_cert (a router with mutual TLS refuses a client without one)
    tls_mtls: bool = False
    #: Zenoh's shared-memory transport between the run's processes and local subscribers: about six
    #: times the image throughput through a router, but each crash of a publishing process (the bridge)
    #: leaves its 16 MiB pool mapped in every local subscriber for good (docs/reliability.md): off
    shared_memory: bool = False
    #: ros2dds key mode: zenoh-bridge-ros2dds' own namespace option ("-n /ns" -> keys "ns/..."), so a
    #: bridge started with it routes the simulator's topics
    ros2dds_namespace: str = "/"
    #: how a fleet's TF frames are told apart (one vehicle: today's names either way): "prefix", every
    #: vehicle on /tf with frames "<vehicle>/base_link" (Aerostack2, robot_state_publisher's frame_prefix),
    #: or "namespace", each on /<namespace>/<vehicle>/tf with unprefixed frames (Nav2's multi-robot launch)
    fleet_tf: str = "prefix"
    jpeg_quality: int = 90
    #: threads encoding a frame set's JPEG and PNG images at once in the bridge (Pillow's encoders let go
    #: of the GIL): 0 is one per CPU up to 8, 1 encodes them one after the other in the publishing thread
    encode_threads: int = 0
    #: append "stream stamp_ns wall_ns" here per message (latency benchmark): odometry at the end of the
    #: physics step that produced it, images at the bridge's publish call
    latency_log: str = ""

    def __post_init__(self) -> None:
        if self.key_mode not in ("ros2dds", "rmw_zenoh"):
            raise ValueError(f"bridge.key_mode must be 'ros2dds' or 'rmw_zenoh', got {self.key_mode!r}")
        if self.mode not in ("router", "peer", "client"):
            raise ValueError(f"bridge.mode must be 'router', 'peer' or 'client', got {self.mode!r}")
        if self.ros2dds_namespace != "/" and not _ROS_NAMESPACE.match(self.ros2dds_namespace):
            raise ValueError(
                f"bridge.ros2dds_namespace must be '/' or an absolute ROS namespace like '/robot1', "
                f"got {self.ros2dds_namespace!r}"
            )
        if self.ros2dds_namespace != "/" and self.key_mode != "ros2dds":
            raise ValueError("bridge.ros2dds_namespace applies to bridge.key_mode=ros2dds only")
        if self.mode == "client" and self.key_mode == "ros2dds" and not (self.connect or self.zenoh_config):
            raise ValueError("bridge.mode=client needs a router to connect to: set bridge.connect")
        if not 1 <= self.jpeg_quality <= 100:
            raise ValueError("bridge.jpeg_quality must lie in [1, 100]")
        if not 0 <= self.encode_threads <= 64:
            raise ValueError(
                f"bridge.encode_threads must lie in [0, 64] (0: one per CPU), got {self.encode_threads}"
            )
        if bool(self.tls_cert) != bool(self.tls_key):
            raise ValueError("bridge.tls_cert and bridge.tls_key go together: give both or neither")
        if self.tls_mtls and not (self.tls_ca and self.tls_cert):
            raise ValueError("bridge.tls_mtls needs bridge.tls_ca (to check peers) and tls_cert/tls_key")
        if self.fleet_tf not in ("prefix", "namespace"):
            raise ValueError(f"bridge.fleet_tf must be 'prefix' or 'namespace', got {self.fleet_tf!r}")


#: what the simulator does when PX4 is lost in the air (``px4.on_loss``)
PX4_ON_LOSS = ("land", "hold", "fall")


@dataclass
class PX4Config:
    """PX4 SITL simulator interface (``droneulator run --px4``). Noise is deterministic under the seed."""

    enabled: bool = False
    #: PX4 instance N connects to TCP port base_port + N
    instance: int = 0
    host: str = "127.0.0.1"
    base_port: int = 4560
    #: decimal year the World Magnetic Model (WMM2025, valid 2025.0-2029.99) is evaluated at (at the
    #: ``site``, whose position the home, the GPS fix and the ground truth are relative to); fixed so
    #: a run is reproducible (the declination at the default home grows by about 0.18 deg a year)
    mag_wmm_year: float = 2025.0
    #: explicit Earth field (gauss, NED) replacing the WMM's, e.g. to test PX4's magnetometer checks
    mag_field_ned_gauss: tuple[float, float, float] | None = None
    gps_hz: float = 10.0
    #: noise presets, each named after a real part (config/sensor_presets.py, docs/sensors.md): IMU
    #: (IMU_PRESETS: sitl, icm42688p, bmi088, adis16448), barometer (BARO_PRESETS: sitl, ms5611, dps310),
    #: magnetometer (MAG_PRESETS: sitl, hmc5883l, rm3100); "sitl" keeps the simulator's own figures
    imu_preset: str = "sitl"
    baro_preset: str = "sitl"
    mag_preset: str = "sitl"
    #: per-sample white noise (1-sigma): accelerometer (m/s^2), gyroscope (rad/s), magnetometer (gauss),
    #: barometer (hPa); null: the preset's (an IMU preset's density at the physics rate; read them resolved
    #: with :meth:`imu_error`, :meth:`mag_error` and :meth:`baro_error`)
    accel_noise: float | None = None
    gyro_noise: float | None = None
    mag_noise: float | None = None
    baro_noise_hpa: float | None = None
    #: constant biases (body FRD)
    accel_bias: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gyro_bias: tuple[float, float, float] = (0.0, 0.0, 0.0)
    #: GPS position error preset (GPS_PRESETS): "sitl" (the few centimetres PX4's own Gazebo simulation
    #: gives, so EKF2's GPS-referenced height and position sit on the truth), "realistic" or its other name
    #: "m8n" (a single-frequency u-blox M8N-class receiver's 0.3 m / 0.5 m wandering over a minute) or
    #: "f9p_rtk" (a u-blox ZED-F9P's RTK fixed solution: about 1 cm, reported as fix type 6)
    gps_preset: str = "sitl"
    #: GPS position error: a first-order Gauss-Markov process per axis with this stationary 1-sigma
    #: (horizontal per axis / vertical, m) and correlation time, plus white per-fix jitter; the fix
    #: reports eph = sqrt(gps_noise_m^2 + gps_jitter_m^2) and epv likewise (what EKF2 takes as 1-sigma).
    #: null: the preset's value (read them resolved with :meth:`gps_error`)
    gps_noise_m: float | None = None
    gps_vertical_noise_m: float | None = None
    gps_correlation_time_s: float | None = None
    gps_jitter_m: float | None = None
    #: GPS velocity noise (white per fix, 1-sigma m/s): horizontal per axis, vertical
    gps_vel_noise: float = 0.05
    gps_vel_vertical_noise: float = 0.1
    #: age of each GPS fix when it is sent (s): PX4 SITL's start script tells EKF2 10 ms
    #: (EKF2_GPS_DELAY / SENS_GPS0_DELAY 10); a real receiver is ~0.11 s (PX4's hardware default)
    gps_delay_s: float = 0.01
    #: magnetometer bias (gauss, body FRD), barometer bias (hPa), GPS position offset (m, NED; not in eph)
    mag_bias: tuple[float, float, float] = (0.0, 0.0, 0.0)
    baro_bias_hpa: float = 0.0
    gps_bias_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    #: satellites reported
    gps_satellites: int = 10
    #: magnetometer and barometer sample rates in HIL_SENSOR (sim time; PX4's Gazebo Iris: 100 / 50 Hz)
    mag_hz: float = 100.0
    baro_hz: float = 50.0
    #: simulated seconds per wall second (PX4_SIM_SPEED_FACTOR); 0 steps as fast as PX4 answers
    speed_factor: float = 1.0
    #: PX4's THR_MDL_FAC: thrust fraction (1 - k) u + k u^2 of motor output u (0: thrust linear in u)
    thrust_model_factor: float = 0.0
    #: PX4 lost while it flies the vehicle in the air: "land" (the simulator's controller lands it
    #: gently, clear of the scene), "hold" (hovers where it is) or "fall" (rotors stop, as a real
    #: vehicle's would). Either way a new PX4 gets the rotors only once the vehicle is on the ground.
    on_loss: str = "land"

    def gps_error(self) -> GpsError:
        """The GPS position error in effect: ``gps_preset``'s, with every explicitly set field instead."""
        base = GPS_PRESETS[self.gps_preset]
        pick = [
            (self.gps_noise_m, base.horizontal_m),
            (self.gps_vertical_noise_m, base.vertical_m),
            (self.gps_correlation_time_s, base.correlation_time_s),
            (self.gps_jitter_m, base.jitter_m),
        ]
        values = (float(base_value if value is None else value) for value, base_value in pick)
        return GpsError(*values, fix_type=base.fix_type)

    def imu_error(self, rate_hz: float) -> ImuModel:
        """The IMU in effect when sampled ``rate_hz`` times a second: ``imu_preset``'s part, its
        per-sample sigmas at that rate (``density * sqrt(rate_hz)``) unless ``accel_noise`` / ``gyro_noise``
        are set, and its full-scale ranges."""
        base = IMU_PRESETS[self.imu_preset]
        accel = base.accel_noise(rate_hz) if self.accel_noise is None else float(self.accel_noise)
        gyro = base.gyro_noise(rate_hz) if self.gyro_noise is None else float(self.gyro_noise)
        return ImuModel(
            base.part, base.accel_density, base.gyro_density, base.accel_range_g, base.gyro_range_dps,
            accel_sigma=accel, gyro_sigma=gyro,
        )  # fmt: skip

    def baro_error(self) -> float:
        """Per-sample barometer noise in effect (hPa, 1-sigma): ``baro_noise_hpa``, else the preset's."""
        if self.baro_noise_hpa is None:
            return float(BARO_PRESETS[self.baro_preset].noise_hpa)
        return float(self.baro_noise_hpa)

    def mag_error(self) -> float:
        """Per-sample magnetometer noise in effect (gauss per axis, 1-sigma): ``mag_noise``, else the
        preset's."""
        return float(MAG_PRESETS[self.mag_preset].noise_gauss if self.mag_noise is None else self.mag_noise)

    def __post_init__(self) -> None:
        for name in ("gps_hz", "mag_hz", "baro_hz"):
            if not math.isfinite(getattr(self, name)) or getattr(self, name) <= 0:
                raise ValueError(f"px4.{name} must be a positive rate in Hz")
        if self.on_loss not in PX4_ON_LOSS:
            raise ValueError(f"px4.on_loss must be one of {', '.join(PX4_ON_LOSS)}, got {self.on_loss!r}")
        if not 0.0 <= self.thrust_model_factor <= 1.0:
            raise ValueError("px4.thrust_model_factor (PX4's THR_MDL_FAC) must lie in [0, 1]")
        if not math.isfinite(self.speed_factor) or self.speed_factor < 0:
            raise ValueError("px4.speed_factor must be >= 0 (0: as fast as PX4 answers)")
        if not 0 <= self.instance <= 255 or not 0 <= self.base_port + self.instance <= 65535:
            raise ValueError("px4.instance and px4.base_port must give a TCP port in [0, 65535]")
        for name, table in (
            ("gps_preset", GPS_PRESETS),
            ("imu_preset", IMU_PRESETS),
            ("baro_preset", BARO_PRESETS),
            ("mag_preset", MAG_PRESETS),
        ):
            check_preset("px4", name, getattr(self, name), table)
        for name in (
            "gps_noise_m",
            "gps_vertical_noise_m",
            "gps_jitter_m",
            "gps_correlation_time_s",
            "accel_noise",
            "gyro_noise",
            "mag_noise",
            "baro_noise_hpa",
        ):
            value = getattr(self, name)
            number = isinstance(value, int | float) and not isinstance(value, bool)
            if value is not None and not (number and math.isfinite(value) and value >= 0):
                raise ValueError(f"px4.{name} must be a number >= 0 or null (the preset's), got {value!r}")
        for name in ("gps_vel_noise", "gps_vel_vertical_noise", "gps_delay_s"):
            if not math.isfinite(getattr(self, name)) or getattr(self, name) < 0:
                raise ValueError(f"px4.{name} must be a finite number >= 0")
        if self.gps_error().correlation_time_s <= 0:
            raise ValueError("px4.gps_correlation_time_s must be a positive time in seconds")
        if not math.isfinite(self.mag_wmm_year):
            raise ValueError("px4.mag_wmm_year must be a decimal year, e.g. 2025.5")
        if self.mag_field_ned_gauss is not None:
            field_ = self.mag_field_ned_gauss
            numbers = isinstance(field_, list | tuple) and all(
                isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) for v in field_
            )
            if not numbers or len(field_) != 3:
                raise ValueError(f"px4.mag_field_ned_gauss must be three finite numbers (G), got {field_!r}")
            self.mag_field_ned_gauss = (float(field_[0]), float(field_[1]), float(field_[2]))


@dataclass
class ArduPilotConfig:
    """ArduPilot SITL's JSON physics interface (``droneulator run --ardupilot``; docs/ardupilot.md).

    ``arducopter --model JSON -I N`` sends its servo packets to UDP ``base_port + 10 N`` and waits for one
    JSON state per packet; the motor settings mirror ArduCopter's ``MOT_*`` parameters, so keep them equal
    to the ones the autopilot runs with. Sensor noise comes from the vehicle's sensor rig (the ``px4``
    section's presets); ArduPilot derives its GPS, barometer and compass from the state itself."""

    enabled: bool = False
    #: ArduPilot instance N (``-I N``) sends to UDP port base_port + 10 N
    instance: int = 0
    host: str = "127.0.0.1"
    base_port: int = 9002
    #: MOT_PWM_MIN / MOT_PWM_MAX: the PWM range of the motor outputs (us)
    pwm_min: int = 1000
    pwm_max: int = 2000
    #: MOT_SPIN_MIN / MOT_SPIN_MAX: the output fractions of zero and of full thrust
    spin_min: float = 0.15
    spin_max: float = 0.95
    #: MOT_THST_EXPO: thrust fraction (1 - e) r + e r^2 of throttle ratio r (ArduCopter's default 0.65)
    thrust_expo: float = 0.65
    #: ArduPilot lost while it flies the vehicle in the air: "land", "hold" or "fall" (as ``px4.on_loss``)
    on_loss: str = "land"

    def __post_init__(self) -> None:
        if self.on_loss not in PX4_ON_LOSS:
            raise ValueError(
                f"ardupilot.on_loss must be one of {', '.join(PX4_ON_LOSS)}, got {self.on_loss!r}"
            )
        if not 0 <= self.instance <= 255 or not 0 <= self.base_port + 10 * self.instance <= 65535:
            raise ValueError("ardupilot.instance and ardupilot.base_port must give a UDP port in [0, 65535]")
        if not 0 < self.pwm_min < self.pwm_max <= 65535:
            raise ValueError("ardupilot.pwm_min and pwm_max (MOT_PWM_MIN/MAX) need 0 < pwm_min < pwm_max")
        if not 0.0 <= self.spin_min < self.spin_max <= 1.0:
            raise ValueError("ardupilot.spin_min and spin_max (MOT_SPIN_MIN/MAX) need 0 <= min < max <= 1")
        if not -1.0 <= self.thrust_expo <= 1.0:
            raise ValueError("ardupilot.thrust_expo (MOT_THST_EXPO) must lie in [-1, 1]")


@dataclass
class UIConfig:
    """The browser UI (``droneulator ui``, ``droneulator run --ui``; see docs/ui.md)."""

    #: loopback only by default, like the API; any other address needs ``access.token`` (generated when
    #: unset; see :class:`AccessConfig`)
    host: str = "127.0.0.1"
    port: int = 8080
    #: the most images per second forwarded to a browser, per camera stream (the newest wins)
    image_hz: float = 10.0
    #: JPEG quality of the forwarded depth images (RGB is forwarded as the simulator encoded it)
    jpeg_quality: int = 80
    #: depth colour scale: 0 m .. this many metres
    depth_max_m: float = 20.0
    #: how much lower than the simulation the UI server's threads are scheduled (nice, 0..19): the UI
    #: takes what CPU the simulation leaves; 0 schedules them like any other thread
    nice: int = 10

    def __post_init__(self) -> None:
        if not 0 <= self.nice <= 19:
            raise ValueError(f"ui.nice must lie in [0, 19], got {self.nice}")
        if not 0 <= self.port <= 65535:
            raise ValueError(f"ui.port must lie in [0, 65535], got {self.port}")
        if not 0.1 <= self.image_hz <= 60.0:
            raise ValueError(f"ui.image_hz must lie in [0.1, 60], got {self.image_hz}")
        if not 1 <= self.jpeg_quality <= 100:
            raise ValueError("ui.jpeg_quality must lie in [1, 100]")
        if not self.depth_max_m > 0:
            raise ValueError("ui.depth_max_m must be positive")


@dataclass
class AccessConfig:
    """Who may use the WebSocket API and the UI's WebSocket, over what, how fast (docs/security.md)."""

    #: the shared secret clients send as the ``token`` query parameter of the WebSocket URL
    #: (``ws://host:8765/?token=T``). A server bound beyond loopback (``runtime.api_host``, ``ui.host``
    #: not 127.0.0.1/::1/localhost) always asks for it: unset there, ``droneulator run``/``ui`` generate
    #: one and print it once. On loopback it is asked for only when set
    token: str | None = None
    #: PEM certificate (chain) and private key: with both, the API serves wss:// and the UI https://
    tls_cert: str | None = None
    tls_key: str | None = None
    #: a CA file (PEM) clients of this process trust besides the system's (the UI's link to a wss:// API
    #: with a self-signed certificate)
    tls_ca: str | None = None
    #: messages per second one connection may send, sustained; past it (and ``burst`` at once) each is
    #: answered ``rate_limited`` and not run. Applied wherever a token is asked for (loopback without a
    #: token stays unlimited)
    rate_hz: float = 200.0
    burst: int = 400

    def __post_init__(self) -> None:
        token = self.token
        if token is not None and (len(token) < 16 or not token.isprintable() or " " in token):
            raise ValueError("access.token must be at least 16 printable characters without spaces")
        if (self.tls_cert is None) != (self.tls_key is None):
            raise ValueError("access.tls_cert and access.tls_key go together: give both or neither")
        if not self.rate_hz > 0:
            raise ValueError(f"access.rate_hz must be positive, got {self.rate_hz}")
        if self.burst < 1:
            raise ValueError(f"access.burst must be at least 1, got {self.burst}")


#: who flies a vehicle (``VehicleSpec.controlled_by``): the simulator's own flight controller (driven by
#: the API, ROS topics and the workflows), a PX4 SITL instance over its simulator link, or an ArduPilot
#: SITL instance over its JSON interface
CONTROLLERS = ("internal", "px4", "ardupilot")
#: the autopilots a vehicle can be handed to (one kind per world)
AUTOPILOTS = ("px4", "ardupilot")

#: a vehicle name is also a ROS namespace and a TF frame prefix
_VEHICLE_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")


@dataclass
class VehicleSpec:
    """One vehicle of the world (``vehicles``). Unset fields take the single-vehicle sections' values:
    ``params`` from ``vehicle.params``, ``cameras`` from ``render.cameras``, ``sensors`` from
    ``vehicle.sensors``, ``flight`` from ``flight``, ``battery`` from ``battery``;
    ``spawn`` null: the scene's spawn pattern (its spawn point for the first vehicle, free points near it
    for the others), on the ground; ``yaw`` null: the scene's spawn heading."""

    name: str = "uav0"
    params: str | None = None
    spawn: tuple[float, float, float] | None = None
    yaw: float | None = None
    cameras: list[CameraConfig] | None = None
    sensors: list[str] | None = None
    flight: FlightConfig | None = None
    controlled_by: str = "internal"
    #: its battery; null: the ``battery`` section
    battery: BatteryConfig | None = None
    #: what a touch does to it (one of CONTACT_MODELS); null: ``vehicle.contact_model``
    contact_model: str | None = None

    def __post_init__(self) -> None:
        if not _VEHICLE_NAME.match(self.name):
            raise ValueError(
                f"vehicle name {self.name!r} must start with a letter and hold only letters, digits and _ "
                "(it names the vehicle's ROS namespace and TF frames)"
            )
        if self.controlled_by not in CONTROLLERS:
            raise ValueError(f"vehicle {self.name!r}: controlled_by must be one of {', '.join(CONTROLLERS)}")
        if self.contact_model is not None and self.contact_model not in CONTACT_MODELS:
            raise ValueError(
                f"vehicle {self.name!r}: contact_model must be one of {', '.join(CONTACT_MODELS)}; got "
                f"{self.contact_model!r}"
            )
        if self.spawn is not None and not all(math.isfinite(v) for v in self.spawn):
            raise ValueError(f"vehicle {self.name!r}: spawn must be three finite numbers")
        if self.yaw is not None and not math.isfinite(self.yaw):
            raise ValueError(f"vehicle {self.name!r}: yaw must be finite")


def fleet(n: int, prefix: str = "uav") -> list[VehicleSpec]:
    """``n`` vehicles named ``uav0`` .. ``uav<n-1>`` on the scene's spawn pattern (``--vehicles N``)."""
    if n < 1:
        raise ValueError(f"need at least one vehicle, got {n}")
    return [VehicleSpec(name=f"{prefix}{i}") for i in range(n)]


@dataclass
class SimConfig:
    scene: str = "default"
    seed: int = 0
    #: the scene's vegetation density (config.scene.VEGETATION_RANGE): its leaves (cards per cluster, per
    #: metre of hedge) x this, a sparse or a dense canopy; its collision model stays (docs/realism.md)
    vegetation: float = 1.0
    render: RenderConfig = field(default_factory=RenderConfig)
    vehicle: VehicleConfig = field(default_factory=VehicleConfig)
    flight: FlightConfig = field(default_factory=FlightConfig)
    runtime: RuntimeConfig = field(default_factory=RuntimeConfig)
    bridge: BridgeConfig = field(default_factory=BridgeConfig)
    px4: PX4Config = field(default_factory=PX4Config)
    ardupilot: ArduPilotConfig = field(default_factory=ArduPilotConfig)
    capture: CaptureConfig = field(default_factory=CaptureConfig)
    rl: RLConfig = field(default_factory=RLConfig)
    ui: UIConfig = field(default_factory=UIConfig)
    #: the API's and the UI's token, TLS and rate limit (docs/security.md)
    access: AccessConfig = field(default_factory=AccessConfig)
    #: where on Earth the world origin lies and its clock (GPS, barometer, magnetic field, PX4, the sun)
    site: SiteConfig = field(default_factory=SiteConfig)
    #: time of day, clouds and haze of the rendered scene (RGB only; see docs/light.md)
    light: LightConfig = field(default_factory=LightConfig)
    #: the wind field every vehicle flies in (calm by default; see docs/wind.md)
    wind: WindConfig = field(default_factory=WindConfig)
    #: the spray system of spraying vehicles and the droplet solver (docs/spray.md)
    spray: SprayConfig = field(default_factory=SprayConfig)
    #: every vehicle's battery (on; numbers left null take the airframe's pack; docs/battery.md)
    battery: BatteryConfig = field(default_factory=BatteryConfig)
    #: the air's temperature, humidity and pressure (the droplets' drag and evaporation)
    weather: WeatherConfig = field(default_factory=WeatherConfig)
    #: domain randomisation: wind, light and depth-camera ranges drawn at every reset (off by default)
    randomize: RandomizeConfig = field(default_factory=RandomizeConfig)
    #: the vehicles of the world; empty: one vehicle, ``uav0``, from the single-vehicle sections (so
    #: every single-vehicle config file keeps working)
    vehicles: list[VehicleSpec] = field(default_factory=list)
    #: faults scheduled in every episode (docs/faults.md): each starts ``at`` s after the reset
    faults: list[FaultSpec] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.vegetation = check_vegetation(self.vegetation)
        names = [v.name for v in self.vehicles]
        twice = sorted({n for n in names if names.count(n) > 1})
        if twice:
            raise ValueError(f"vehicle names must be unique: {', '.join(twice)} given more than once")
        known = [v.name for v in self.vehicle_specs()]
        strangers = sorted({f.vehicle for f in self.faults if f.vehicle is not None} - set(known))
        if strangers:
            names = ", ".join(known)
            raise ValueError(f"faults name vehicle(s) {', '.join(strangers)}; the vehicles are {names}")
        self.check_autopilots()
        if self.vehicle.wind != "none" and not self.wind.calm:
            raise ValueError(
                f"vehicle.wind={self.vehicle.wind!r} (a RotorPy wind profile) and the wind field "
                "(wind.speed_m_s, wind.gust_speed_m_s) are two wind models: use one"
            )

    def check_autopilots(self) -> None:
        """Refuse ``px4.enabled`` / ``ardupilot.enabled`` handing over a first vehicle that is not theirs to
        take (both at once, or one the list gives the other autopilot); a mixed fleet names each vehicle's
        autopilot (``controlled_by``). Run again by ``droneulator run`` after ``--px4`` / ``--ardupilot``."""
        specs = self.vehicles or [VehicleSpec()]
        claims = [
            kind
            for kind in AUTOPILOTS
            if getattr(self, kind).enabled and all(v.controlled_by != kind for v in specs)
        ]
        if len(claims) > 1 or (claims and specs[0].controlled_by not in ("internal", claims[0])):
            raise ValueError(
                f"{' and '.join(k + '.enabled' for k in claims)} would hand the first vehicle (flown by "
                f"{specs[0].controlled_by}) to {' and '.join(claims)}: for a mixed fleet name each vehicle's "
                "autopilot in the vehicles list (controlled_by: px4 / ardupilot)"
            )

    def vehicle_specs(self) -> list[VehicleSpec]:
        """Every vehicle with its unset fields filled from the single-vehicle sections (copies).

        ``px4.enabled`` (``--px4``) hands the first vehicle to PX4 when no vehicle names PX4 itself;
        ``ardupilot.enabled`` (``--ardupilot``) likewise to ArduPilot. ``contact_model`` comes out set:
        the vehicle's, else ``vehicle.contact_model``, whose ``auto`` is physical under an autopilot and
        stop otherwise."""
        specs = self.vehicles or [VehicleSpec()]
        first = "internal"
        for kind, enabled in (("px4", self.px4.enabled), ("ardupilot", self.ardupilot.enabled)):
            if enabled and all(v.controlled_by != kind for v in specs):
                first = kind
        specs = [
            dataclasses.replace(
                v,
                params=v.params or self.vehicle.params,
                cameras=list(self.render.cameras if v.cameras is None else v.cameras),
                sensors=list(self.vehicle.sensors if v.sensors is None else v.sensors),
                flight=v.flight or self.flight,
                battery=v.battery or self.battery,
                controlled_by=first if first != "internal" and i == 0 else v.controlled_by,
            )
            for i, v in enumerate(specs)
        ]
        for v in specs:
            if v.contact_model is None:
                v.contact_model = self.vehicle.contact_model
            if v.contact_model == "auto":
                v.contact_model = "physical" if v.controlled_by in AUTOPILOTS else "stop"
        return specs

    def camera_rigs(self) -> dict[str, list[CameraConfig]]:
        """Every vehicle's cameras, by vehicle name."""
        return {v.name: list(v.cameras or ()) for v in self.vehicle_specs()}

    def px4_instances(self) -> dict[str, int]:
        """PX4 SITL instance of each vehicle PX4 flies, by name: vehicle k of the list is instance
        ``px4.instance + k`` (``px4 -i k``: simulator port ``px4.base_port`` + instance, MAV_SYS_ID
        instance + 1), as PX4's multi-vehicle SITL numbers them."""
        specs = self.vehicle_specs()
        return {v.name: self.px4.instance + k for k, v in enumerate(specs) if v.controlled_by == "px4"}

    def ardupilot_instances(self) -> dict[str, int]:
        """ArduPilot SITL instance of each vehicle ArduPilot flies, by name: vehicle k of the list is
        instance ``ardupilot.instance + k`` (``arducopter -I k``: servo packets to UDP ``ardupilot.base_port
        + 10 k``, MAVLink on TCP 5760 + 10 k)."""
        specs = self.vehicle_specs()
        return {
            v.name: self.ardupilot.instance + k for k, v in enumerate(specs) if v.controlled_by == "ardupilot"
        }
