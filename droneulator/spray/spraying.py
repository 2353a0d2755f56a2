"""Spraying in a world: each vehicle's spray system, one cloud for the world's air, stepped with it.

:class:`Spraying` is attached to a :class:`~droneulator.world.world.World` (its first world) and stepped
after each of the world's control periods: each vehicle's pump draws from its tank, the nozzles release
parcels at the vehicle's pose, every vehicle's rotors blow its wake, and the tank's liquid goes back to
the vehicle as payload. The scene's canopy and wood are the targets, its collision geometry shelters the
wind (as :mod:`droneulator.wind.field` does for the vehicles).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from droneulator.commands.errors import CommandError
from droneulator.config.loading import from_dict
from droneulator.config.spray import SprayConfig, WeatherConfig
from droneulator.config.wind import WindConfig
from droneulator.frames import quat_to_matrix
from droneulator.scenes.base import Scene
from droneulator.spray import kernel
from droneulator.spray.cloud import Domain, Emitter, SprayCloud
from droneulator.spray.deposit import DepositImage
from droneulator.spray.system import SpraySystem
from droneulator.spray.targets import SprayTargets
from droneulator.state import STATE
from droneulator.vehicles.sprayers import SPRAYERS, spray_system
from droneulator.wind.field import SHELTER_FETCH, SHELTER_STEP_M, _shelter_exponents

#: where the tank's liquid sits (body FLU, m): under the centre of mass
TANK_OFFSET = (0.0, 0.0, -0.15)
#: a payload change smaller than this (kg) waits for the next one (re-packing the parameters each step
#: would cost more than the mass error)
PAYLOAD_STEP_KG = 0.01
#: the ledger's column of the liquid on the deposit grid
_GROUND = kernel.LEDGER.index("ground")


def shelter_grid(scene: Scene, targets: SprayTargets, wind: WindConfig) -> np.ndarray:
    """The mean wind's shelter factor on the targets' grid: ``exp(-a sum len_i exp(-s_i / recovery))`` along
    each cell's upwind ray through the scene's canopy, as :class:`~droneulator.wind.field.WindField`
    computes it for a vehicle (ones when calm or without shelter)."""
    shape = targets.leaf.shape
    if wind.calm or not wind.shelter or targets.plant_count == 0:
        return np.ones(shape, np.float32)
    idx = np.indices(shape).reshape(3, -1).T
    pts = targets.origin + (idx + 0.5) * targets.cell
    hx, hy = wind.heading
    heading = np.tile([hx, hy], (len(pts), 1))
    col = scene.collision
    recovery = np.full(len(pts), wind.shelter_recovery_m)
    e = _shelter_exponents(col.sdf, col.origin, col.resolution, pts, heading, recovery, SHELTER_STEP_M,
                           SHELTER_FETCH)  # fmt: skip
    return np.exp(-wind.canopy_attenuation_per_m * e).reshape(shape).astype(np.float32)


def system_config(spray: SprayConfig, vehicle: Any) -> SprayConfig:
    """The spray system ``vehicle`` carries: a spray airframe's own tank and nozzles
    (:func:`~droneulator.vehicles.sprayers.spray_system`) with every field the ``spray`` section changes
    from its defaults over them; any other airframe, the section as it is."""
    params = vehicle.spec.params
    if params not in SPRAYERS:
        return spray
    default = dataclasses.asdict(SprayConfig())
    changed = {k: v for k, v in dataclasses.asdict(spray).items() if v != default[k]}
    return from_dict(SprayConfig, {**spray_system(params), **changed}, "spray")


def rotor_rows(vehicle: Any, s: np.ndarray) -> np.ndarray:
    """A vehicle's rotors for the cloud: position, thrust axis, thrust and disk area each (world frame)."""
    q = vehicle.quad_params
    R = quat_to_matrix(s[STATE.q])
    pos = np.array([q["rotor_pos"][k] for k in q["rotor_pos"]], float)
    w = s[STATE.rotor_speeds]
    radius = math.sqrt(vehicle.disk_area / (4.0 * math.pi))
    rows = np.zeros((len(pos), 8))
    rows[:, 0:3] = s[STATE.x] + pos @ R.T
    rows[:, 3:6] = R[:, 2]
    rows[:, 6] = float(q["k_eta"]) * w**2
    rows[:, 7] = math.pi * radius * radius
    return rows


class Spraying:
    """The spray systems of a world's vehicles and the cloud they spray into (see the module docstring)."""

    def __init__(
        self,
        world: Any,
        spray: SprayConfig | None = None,
        weather: WeatherConfig | None = None,
        vehicles: list[str] | None = None,
        domain: Domain | None = None,
        targets: SprayTargets | None = None,
    ) -> None:
        cfg = world.config
        self.world = world
        self.config = spray or cfg.spray
        names = list(world.vehicles) if vehicles is None else vehicles
        for name in names:
            world.vehicle(name)
        self.systems = {name: SpraySystem(system_config(self.config, world.vehicle(name))) for name in names}
        self.weather = weather or cfg.weather
        self._given = (domain, targets)
        self._scene: Scene | None = None
        self._payload: dict[str, float] = {}
        self._shelter_key: tuple[Any, ...] | None = None
        # the cloud steps ``substeps`` times a control period, or once every ``every`` periods when its
        # step is the longer
        period = world.control_period_ns / 1e9
        self.substeps = max(1, math.ceil(period / self.config.dt_s - 1e-9))
        self.every = max(1, round(self.config.dt_s / period))
        self.dt = period / self.substeps if self.substeps > 1 else period * self.every
        self._episode = 0
        #: the deposit picture last encoded and what it showed (episode, volume on the grid)
        self._deposit: DepositImage | None = None
        self._deposit_key: tuple[int, float] | None = None
        self.reset()

    def reset(self) -> None:
        """A new episode: an empty cloud over the world's scene (its targets rebuilt if the scene changed),
        full tanks, every spray off."""
        world, cfg = self.world, self.world.config
        domain, targets = self._given
        scene = world.scene
        if targets is not None:
            self.targets = targets
        elif self._scene is not scene:
            self.targets = SprayTargets.of(scene, self.config.leaf_projection)
        self._scene = scene
        wind = cfg.wind
        self.domain = domain or Domain.around(
            scene.bounds_min, scene.bounds_max, self.config.margin_m, self.config.ceiling_m
        )
        key = (id(scene), id(self.targets), dataclasses.astuple(wind))
        if self._shelter_key != key:  # the shelter grid costs a second: kept while valid
            self._shelter, self._shelter_key = shelter_grid(scene, self.targets, wind), key
        shelter = self._shelter
        self.cloud = SprayCloud(
            self.config, self.weather, wind, self.domain, self.targets, shelter, seed=cfg.seed, dt=self.dt
        )
        self._periods = 0
        self._episode += 1
        for name, system in self.systems.items():
            system.refill()
            system.rate = 0.0
            system.sprayed_l = 0.0
            self._update_payload(name, force=True)

    def system(self, name: str | None) -> SpraySystem:
        """The spray system of vehicle ``name`` (None: the first vehicle's)."""
        v = self.world.vehicle(name)
        if v.name not in self.systems:
            raise CommandError("no_spray_system", f"vehicle {v.name!r} has no spray system")
        return self.systems[v.name]

    def refill(self, name: str | None, litres: float | None = None) -> SpraySystem:
        """Fill vehicle ``name``'s tank (None: to its load); its mass follows at once."""
        system = self.system(name)
        system.refill(litres)
        self._update_payload(self.world.vehicle(name).name, force=True)
        return system

    def deposit_image(self) -> DepositImage:
        """The ground deposit as the ``spray_deposit`` op sends it. Encoded again only when more liquid has
        landed on the grid or after a reset (its ``version`` then one higher), so asking often is cheap."""
        cloud = self.cloud
        key = (self._episode, float(cloud.ledger[:, _GROUND].sum()))
        if self._deposit is None or key != self._deposit_key:
            version = 1 if self._deposit is None else self._deposit.version + 1
            grid, w = cloud.ground_deposit_ul_cm2(), self.world
            at = (version, w.t, w.stamp_ns)
            self._deposit = DepositImage.of(grid, cloud.ground_cell, cloud.ground_origin, *at)
            self._deposit_key = key
        return self._deposit

    def _update_payload(self, name: str, force: bool = False) -> None:
        kg = self.systems[name].liquid_kg
        if (
            force
            or abs(kg - self._payload.get(name, -1.0)) >= PAYLOAD_STEP_KG
            or (kg == 0.0 and self._payload[name])
        ):
            self.world.set_payload(name, kg, TANK_OFFSET)
            self._payload[name] = kg

    def emitters(self, dt: float) -> list[Emitter]:
        """Every vehicle of the first world as the cloud sees it for a step of ``dt`` s (drawing from the
        tanks of those spraying)."""
        out = []
        states = self.world.states[0]
        for name, v in self.world.vehicles.items():
            s = states[v.index]
            release = []
            system = self.systems.get(name)
            if system is not None and system.on:
                drawn = system.draw(dt)
                release = [(n, drawn[n.name]) for n in system.config.nozzles if n.name in drawn]
            out.append(
                Emitter(s[STATE.x].copy(), s[STATE.q].copy(), s[STATE.v].copy(), rotor_rows(v, s), release)
            )
        return out

    def step(self) -> None:
        """Follow the world's last control period: release, move the parcels, update the payloads."""
        self._periods += 1
        if self._periods % self.every:
            return
        for _ in range(self.substeps):
            self.cloud.step(self.emitters(self.cloud.dt))
        for name in self.systems:
            self._update_payload(name)
