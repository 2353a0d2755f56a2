"""Spray trials as test stations and field trials run them, and the figures they give.

* :func:`hover_trial`: a sprayer hovers and sprays for a set time over a line of ground collectors from
  5 m upwind to 50 m downwind in a set wind (as in wind tunnels and hover tests).
* :func:`pass_trial`: one pass across the wind over the same line (as in ISO 22866 field drift trials),
  which gives the deposit across the flight line: the swath pattern (:func:`swath_cv`,
  :func:`effective_swath`, ISO 23117-2's rule: the widest lane spacing whose overlapped pattern has a
  CV of at most 25 %) and, overlapping passes into a field, the drift curve (:func:`drift_curve`: the
  ground deposit at 1 to 50 m downwind of the field's edge as a share of the field's mean deposit, the
  measure of the JKI/Rautmann basic drift values).

The vehicle flies the trial's line trimmed for it (its thrust carries its weight and its drag at the
trial's speed, pitched into the motion), so its rotors' wakes are those of its actual thrust; the air
is the ``wind`` and ``weather`` sections'; there are no plants (a bare collector field).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from droneulator.config.spray import SprayConfig, WeatherConfig
from droneulator.config.wind import WindConfig
from droneulator.frames import matrix_to_quat
from droneulator.spray.cloud import Domain, Emitter, SprayCloud
from droneulator.spray.droplets import GRAVITY
from droneulator.spray.kernel import AIR_SIZE, ROTOR_SIZE, VORTEX_SIZE, air_velocity, wind_row
from droneulator.vehicles.params import get_params

#: 1 m^3 of liquid per m^2 of ground, in microlitres per cm^2
UL_CM2 = 1e5
#: ISO 23117-2's uniformity limit for the effective swath
CV_LIMIT = 0.25
#: the collectors: 5 m upwind to 50 m downwind of the flight line
COLLECTORS_M = np.array([-5, -4, -3, -2, -1, 0, 1, 2, 3, 4, 5, 7.5, 10, 15, 20, 25, 30, 40, 50], float)
#: drift-curve distances downwind of the field's edge (m)
DRIFT_M = np.array([1, 3, 5, 10, 15, 20, 30, 40, 50], float)


@dataclass
class Airframe:
    """What a trial needs of a vehicle: its take-off mass, rotor layout, each rotor's disk area, and frame
    drag."""

    mass: float
    rotor_pos: np.ndarray
    disk_area: float
    drag: float

    @classmethod
    def of(cls, params: str, spray: SprayConfig) -> Airframe:
        q = get_params(params)
        pos = np.array([q["rotor_pos"][k] for k in q["rotor_pos"]], float)
        radius = float(q.get("rotor_radius", 0.45 * np.linalg.norm(pos[0, :2])))
        mass = float(q["mass"]) + spray.load_l * spray.liquid_density / 1000.0
        return cls(mass, pos, math.pi * radius * radius, float(q.get("c_Dx", 0.0)))

    def emitter(self, position: np.ndarray, velocity: np.ndarray, wind: np.ndarray, release: list) -> Emitter:
        """The vehicle trimmed at ``velocity`` in ``wind``: thrust balancing weight and frame drag, heading
        along the motion (so a flat fan's sheet lies across the flight line)."""
        air = velocity - wind
        drag = -self.drag * np.linalg.norm(air) * air
        force = drag + np.array([0.0, 0.0, self.mass * GRAVITY])
        thrust = float(np.linalg.norm(force))
        z = force / thrust
        ahead = (
            velocity / np.linalg.norm(velocity) if np.linalg.norm(velocity) > 0.1 else np.array([1.0, 0, 0])
        )
        x = ahead - (ahead @ z) * z  # heading along the motion (+x at rest), tilted with the thrust
        x /= np.linalg.norm(x)
        R = np.column_stack([x, np.cross(z, x), z])
        q = matrix_to_quat(R)
        rows = np.zeros((len(self.rotor_pos), 8))
        rows[:, 0:3] = position + self.rotor_pos @ R.T
        rows[:, 3:6] = R[:, 2]
        rows[:, 6] = thrust / len(self.rotor_pos)
        rows[:, 7] = self.disk_area
        return Emitter(position.copy(), q, velocity.copy(), rows, release)


@dataclass
class TrialResult:
    """A trial's collectors and totals (JSON-ready through :meth:`to_dict`)."""

    kind: str
    setup: dict[str, Any]
    collectors_m: list[float]
    deposit_ul_cm2: list[float]
    share_of_peak: list[float]
    ledger: dict[str, float]
    sprayed_l: float
    profile_x_m: list[float] = field(default_factory=list)
    profile_ul_cm2: list[float] = field(default_factory=list)
    parcels: int = 0
    sim_s: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


def _line_profile(cloud: SprayCloud, along: float, width: float) -> tuple[np.ndarray, np.ndarray]:
    """The ground deposit (uL/cm^2) across the flight line (x), averaged over ``width`` m of the line
    (y within +-width/2 of ``along``)."""
    g = cloud.ground_deposit()
    c = cloud.ground_cell
    xs = cloud.ground_origin[0] + (np.arange(g.shape[0]) + 0.5) * c
    ys = cloud.ground_origin[1] + (np.arange(g.shape[1]) + 0.5) * c
    sel = np.abs(ys - along) <= width / 2.0
    per_area = g[:, sel].sum(1) / (sel.sum() * c * c)
    return xs, per_area * UL_CM2


def _collect(xs: np.ndarray, profile: np.ndarray, at: np.ndarray, size: float = 0.5) -> np.ndarray:
    """Collectors ``size`` m wide across the line at ``at``: the profile's mean over each."""
    return np.array([profile[np.abs(xs - a) <= size / 2.0].mean() for a in at])


def _cloud(
    spray: SprayConfig, weather: WeatherConfig, wind: WindConfig, domain: Domain, seed: int
) -> SprayCloud:
    return SprayCloud(spray, weather, wind, domain, None, None, seed)


def _mean_wind(wind: WindConfig, height: float) -> np.ndarray:
    """The mean wind (m/s, world) at ``height`` m."""
    out = np.empty(AIR_SIZE)
    spec = wind_row(wind)
    air_velocity(0.0, 0.0, height, spec, np.zeros((0, ROTOR_SIZE)), np.zeros((0, VORTEX_SIZE)), out)
    return out[:3]


def hover_trial(
    spray: SprayConfig,
    weather: WeatherConfig,
    wind: WindConfig,
    params: str = "sprayer10",
    height: float = 2.5,
    duration: float = 10.0,
    seed: int = 0,
    progress: Callable[[float], None] | None = None,
) -> TrialResult:
    """Hover at ``height`` m for ``duration`` s spraying at the full rate over the collector line (x along
    the wind, through the point under the vehicle), then wait until the cloud has settled."""
    frame = Airframe.of(params, spray)
    domain = Domain(-10.0, 70.0, -40.0, 40.0, spray.ceiling_m)
    cloud = _cloud(spray, weather, _along_x(wind), domain, seed)
    pos = np.array([0.0, 0.0, height])
    wind_v = _mean_wind(_along_x(wind), height)
    steps = round(duration / cloud.dt)
    for k in range(steps):
        release = [(n, n.flow_l_min / 60.0 * cloud.dt) for n in spray.nozzles]
        cloud.step([frame.emitter(pos, np.zeros(3), wind_v, release)])
        if progress:
            progress(0.5 * (k + 1) / steps)
    e = frame.emitter(pos, np.zeros(3), wind_v, [])
    cloud.settle([e], limit_s=120.0)
    if progress:
        progress(1.0)
    xs, prof = _line_profile(cloud, 0.0, 0.5)
    dep = _collect(xs, prof, COLLECTORS_M)
    return TrialResult(
        "hover", {"params": params, "height_m": height, "duration_s": duration, "wind_m_s": wind.speed_m_s},
        COLLECTORS_M.tolist(), dep.tolist(), (dep / max(dep.max(), 1e-300)).tolist(),
        cloud.ledger_now().shares(), cloud.sprayed * 1000.0, xs.tolist(), prof.tolist(),
        cloud.parcels_released, cloud.t,
    )  # fmt: skip


def _along_x(wind: WindConfig) -> WindConfig:
    """The trial's wind: the section's speed and turbulence, blowing towards +x (across the flight line)."""
    return dataclasses.replace(wind, direction_deg=270.0, shelter=False)


def pass_trial(
    spray: SprayConfig,
    weather: WeatherConfig,
    wind: WindConfig,
    params: str = "sprayer10",
    height: float = 2.5,
    speed: float = 5.0,
    length: float = 60.0,
    seed: int = 0,
    progress: Callable[[float], None] | None = None,
) -> TrialResult:
    """One pass along y (across the wind) at ``height`` m and ``speed`` m/s, spraying over ``length`` m
    centred on the collector line; the profile across the line is averaged over its middle third."""
    frame = Airframe.of(params, spray)
    domain = Domain(-20.0, 70.0, -length / 2 - 15.0, length / 2 + 15.0, spray.ceiling_m)
    trial_wind = _along_x(wind)
    cloud = _cloud(spray, weather, trial_wind, domain, seed)
    wind_v = _mean_wind(trial_wind, height)
    vel = np.array([0.0, speed, 0.0])
    steps = round(length / speed / cloud.dt)
    for k in range(steps):
        pos = np.array([0.0, -length / 2 + speed * cloud.dt * k, height])
        release = [(n, n.flow_l_min / 60.0 * cloud.dt) for n in spray.nozzles]
        cloud.step([frame.emitter(pos, vel, wind_v, release)])
        if progress:
            progress(0.5 * (k + 1) / steps)
    pos = np.array([0.0, length / 2, height])
    cloud.settle([frame.emitter(pos + vel * 1e3, vel, wind_v, [])], limit_s=120.0)
    if progress:
        progress(1.0)
    xs, prof = _line_profile(cloud, 0.0, length / 3.0)
    dep = _collect(xs, prof, COLLECTORS_M)
    return TrialResult(
        "pass", {"params": params, "height_m": height, "speed_m_s": speed, "length_m": length,
                 "wind_m_s": wind.speed_m_s},
        COLLECTORS_M.tolist(), dep.tolist(), (dep / max(dep.max(), 1e-300)).tolist(),
        cloud.ledger_now().shares(), cloud.sprayed * 1000.0, xs.tolist(), prof.tolist(),
        cloud.parcels_released, cloud.t,
    )  # fmt: skip


def swath_cv(xs: np.ndarray, profile: np.ndarray, spacing: float) -> float:
    """CV of the deposit of passes ``spacing`` m apart, all flown the same way (a racetrack pattern), over
    one lane: the profile summed at every shift of ``spacing``, sampled over ``[0, spacing)``."""
    step = xs[1] - xs[0]
    lane = np.arange(0.0, spacing, step)
    total = np.zeros_like(lane)
    lo, hi = xs[0], xs[-1]
    for k in range(-int((hi - lo) / spacing) - 2, int((hi - lo) / spacing) + 3):
        total += np.interp(lane + k * spacing, xs, profile, left=0.0, right=0.0)
    mean = total.mean()
    return float(total.std() / mean) if mean > 0 else math.inf


def effective_swath(
    xs: np.ndarray, profile: np.ndarray, step: float = 0.25, limit: float = CV_LIMIT
) -> float:
    """The widest lane spacing (m, in ``step``) whose overlapped pattern has CV <= ``limit`` (0: none)."""
    best = 0.0
    for s in np.arange(step, 30.0 + 1e-9, step):
        if swath_cv(xs, profile, float(s)) <= limit:
            best = float(s)
    return best


def drift_curve(
    xs: np.ndarray, profile: np.ndarray, spacing: float, lanes: int = 8
) -> dict[str, list[float]]:
    """A field of ``lanes`` passes ``spacing`` m apart, the wind blowing across them towards +x: its ground
    deposit at :data:`DRIFT_M` downwind of the field's edge (half a lane beyond the last pass) as a share
    (%) of the field's mean deposit (the passes' total over the field's area)."""
    lines = -np.arange(lanes)[::-1] * spacing  # the last (downwind) pass at x = 0
    edge = spacing / 2.0
    field_lo = lines[0] - spacing / 2.0

    def field_at(x: np.ndarray) -> np.ndarray:
        return sum(np.interp(x - line, xs, profile, left=0.0, right=0.0) for line in lines)

    inside = np.linspace(field_lo, edge, 400)
    mean_in = float(field_at(inside).mean())
    at = edge + DRIFT_M
    values = field_at(at) / mean_in * 100.0 if mean_in > 0 else np.zeros_like(at)
    return {"distance_m": DRIFT_M.tolist(), "drift_percent": values.tolist(), "field_mean_ul_cm2": mean_in}
