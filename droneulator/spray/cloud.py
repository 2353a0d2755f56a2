"""The spray cloud: the parcels every nozzle releases, stepped through the air, and the ledger of where
their liquid went.

One :class:`SprayCloud` serves a whole world: any number of vehicles, each with its nozzles, release
into it; every rotor's wake moves every parcel. The caller gives the vehicles' state at each step
(:class:`Emitter` rows) and the cloud does the rest in one compiled call
(:func:`droneulator.spray.kernel.step_parcels`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from droneulator.config.spray import NozzleConfig, SprayConfig, WeatherConfig
from droneulator.config.wind import WindConfig
from droneulator.frames import quat_to_matrix
from droneulator.spray import kernel
from droneulator.spray.droplets import GRAVITY, Air
from droneulator.spray.spectrum import Spectrum
from droneulator.spray.targets import SprayTargets
from droneulator.wind import dryden
from droneulator.world.downwash import RHO

#: accumulator rows of the parallel step (a multiple of any core count we meet; results do not depend on it)
CHUNKS = 16


@dataclass
class Emitter:
    """What the cloud needs of one vehicle at a step: where it is, how it is turned, how fast it goes, its
    rotors (rows of position (3), thrust axis (3, unit), thrust (N), disk area (m^2), in the world: their
    wakes blow whether it sprays or not), and what each of its nozzles releases this step (litres)."""

    position: np.ndarray
    quaternion: np.ndarray  # (x, y, z, w), body FLU to world ENU
    velocity: np.ndarray
    rotors: np.ndarray
    release: list[tuple[NozzleConfig, float]] = field(default_factory=list)


@dataclass
class Domain:
    """The box parcels are followed in (m): the sprayed area with a margin, up to a ceiling; the ground
    deposit grid covers its floor."""

    x0: float
    x1: float
    y0: float
    y1: float
    ceiling: float

    @classmethod
    def around(cls, lo: np.ndarray, hi: np.ndarray, margin: float, ceiling: float) -> Domain:
        return cls(lo[0] - margin, hi[0] + margin, lo[1] - margin, hi[1] + margin, ceiling)


@dataclass
class Ledger:
    """Where the sprayed liquid went (m^3); the parts add up to ``sprayed``."""

    sprayed: float
    parts: dict[str, float] = field(default_factory=dict)

    @property
    def accounted(self) -> float:
        return float(sum(self.parts.values()))

    def shares(self) -> dict[str, float]:
        """Each part as a share of the sprayed volume."""
        return {k: (v / self.sprayed if self.sprayed > 0 else 0.0) for k, v in self.parts.items()}


class SprayCloud:
    """Parcels of droplets in one world's air (see the module docstring)."""

    def __init__(
        self,
        spray: SprayConfig,
        weather: WeatherConfig,
        wind: WindConfig,
        domain: Domain,
        targets: SprayTargets | None = None,
        shelter: np.ndarray | None = None,
        seed: int = 0,
        dt: float | None = None,
    ) -> None:
        self.config = spray
        self.air = Air.of(weather)
        self.wind = wind
        self.domain = domain
        self.targets = targets or SprayTargets.empty()
        self.shelter = np.ascontiguousarray(
            np.ones_like(self.targets.leaf) if shelter is None else np.asarray(shelter, np.float32)
        )
        if self.shelter.shape != self.targets.leaf.shape:
            raise ValueError(f"shelter grid {self.shelter.shape} != targets grid {self.targets.leaf.shape}")
        self._dims = np.array(self.targets.leaf.shape, np.int64)
        self.seed = int(seed)
        self.rng = np.random.default_rng([seed, 0x5B8A7])
        self._spectra: dict[tuple[float, float, float], Spectrum] = {}
        self.dt = spray.dt_s if dt is None else float(dt)
        self.steps = 0
        self.t = 0.0
        cap = 1 << 14
        self.x = np.zeros((cap, 3))
        self.v = np.zeros((cap, 3))
        self.turb = np.zeros((cap, 3))
        self.d = np.zeros(cap)
        self.dres = np.zeros(cap)
        self.n = np.zeros(cap)
        self.ids = np.zeros(cap, np.int64)
        self.count = 0
        self.next_id = 0
        self.sprayed = 0.0
        self.ledger = np.zeros((CHUNKS, len(kernel.LEDGER)))
        self.dose = np.zeros((CHUNKS, max(self.targets.plant_count, 1), 3))
        cell = spray.grid_cell_m
        self.ground_origin = np.array([domain.x0, domain.y0])
        self.ground_cell = cell
        gx = int(math.ceil((domain.x1 - domain.x0) / cell))
        gy = int(math.ceil((domain.y1 - domain.y0) / cell))
        self.ground = np.zeros((CHUNKS, gx, gy))
        self._air = np.array(
            [
                self.air.density,
                self.air.viscosity,
                spray.liquid_density,
                self.air.wet_bulb_depression,
                spray.min_diameter_um * 1e-6,
                spray.leaf_size_m,
                spray.wood_size_m,
                GRAVITY,
            ]
        )
        self._wind = kernel.wind_row(wind)
        self._turbulence = self._turbulence_table(int(math.ceil(domain.ceiling)) + 1)
        self._domain = np.array([domain.x0, domain.x1, domain.y0, domain.y1, domain.ceiling])
        self.parcels_released = 0

    def _turbulence_table(self, heights: int) -> np.ndarray:
        """The turbulence's step at heights 0, 1, .. m: (e_u, kick_u, e_w, kick_w) with ``e = exp(-dt / T)``
        and ``kick = sigma sqrt(1 - e^2)`` from the Dryden intensities ``sigma`` and the Lagrangian time
        scales ``T = L / U`` of the wind section (zeros when it is calm or steady)."""
        w = self.wind
        table = np.zeros((heights, 4))
        if w.speed_m_s <= 0.0 or w.turbulence == "none":
            return table
        h = np.maximum(np.arange(heights, dtype=float), 0.5)
        su, sw = dryden.intensities(h, np.full(heights, w.speed_m_s))
        lu, lw = dryden.scale_lengths(h)
        if w.profile == "log":
            mean = w.speed_m_s * np.log(np.maximum(h, w.roughness_m * 1.01) / w.roughness_m)
            mean /= math.log(6.096 / w.roughness_m)
        else:
            mean = np.full(heights, w.speed_m_s)
        mean = np.maximum(mean, 1.0)
        eu, ew = np.exp(-self.dt * mean / lu), np.exp(-self.dt * mean / lw)
        table[:, 0] = eu
        table[:, 1] = su * w.turbulence_scale * np.sqrt(1.0 - eu**2)
        table[:, 2] = ew
        table[:, 3] = sw * w.turbulence_scale * np.sqrt(1.0 - ew**2)
        return table

    # ----------------------------------------------------------------------------------- release
    def _grow(self, extra: int) -> None:
        need = self.count + extra
        if need <= self.x.shape[0]:
            return
        alive = self.n[: self.count] > 0.0
        if alive.sum() + extra <= self.x.shape[0] // 2:
            self._compact()
            return
        cap = max(need, 2 * self.x.shape[0])
        for name in ("x", "v", "turb", "d", "dres", "n", "ids"):
            old = getattr(self, name)
            new = np.zeros((cap, *old.shape[1:]), old.dtype)
            new[: self.count] = old[: self.count]
            setattr(self, name, new)

    def _compact(self) -> None:
        """Drop the parcels that are gone (deposited, evaporated, left)."""
        alive = np.flatnonzero(self.n[: self.count] > 0.0)
        k = len(alive)
        for name in ("x", "v", "turb", "d", "dres", "n", "ids"):
            arr = getattr(self, name)
            arr[:k] = arr[alive]
            arr[k : self.count] = 0
        self.count = k

    def _spectrum(self, nozzle: NozzleConfig) -> Spectrum:
        """The nozzle's spectrum, its sizes x ``spray.droplet_scale``."""
        key = nozzle.diameters_um
        if key not in self._spectra:
            s = Spectrum.of(nozzle)
            self._spectra[key] = Spectrum(s.median * self.config.droplet_scale, s.sigma)
        return self._spectra[key]

    def release(self, emitter: Emitter, dt: float) -> float:
        """Release what ``emitter``'s nozzles spray this step (``dt`` s: the parcel count); returns the
        volume (m^3)."""
        R = quat_to_matrix(np.asarray(emitter.quaternion, float))
        total = 0.0
        for nozzle, litres in emitter.release:
            if litres <= 0.0:
                continue
            volume = litres / 1000.0
            k = max(1, int(self.rng.poisson(self.config.parcels_per_s * dt)))
            diam = self._spectrum(nozzle).sample(self.rng, k)
            if nozzle.type == "flat_fan":
                half = math.radians(nozzle.fan_angle_deg) / 2.0
                a = self.rng.uniform(-half, half, k)
                body = np.column_stack([np.zeros(k), np.sin(a), -np.cos(a)])
            else:
                a = self.rng.uniform(0.0, 2.0 * math.pi, k)
                body = np.column_stack([np.cos(a), np.sin(a), np.zeros(k)])
            self._grow(k)
            s = slice(self.count, self.count + k)
            self.x[s] = np.asarray(emitter.position) + R @ np.asarray(nozzle.position, float)
            self.v[s] = np.asarray(emitter.velocity) + nozzle.exit_speed_m_s * body @ R.T
            self.turb[s] = 0.0
            self.d[s] = diam
            self.dres[s] = diam * self.config.nonvolatile_fraction ** (1.0 / 3.0)
            self.n[s] = (volume / k) / (math.pi / 6.0 * diam**3)
            self.ids[s] = np.arange(self.next_id, self.next_id + k)
            self.next_id += k
            self.count += k
            self.parcels_released += k
            total += volume
        self.sprayed += total
        return total

    # ----------------------------------------------------------------------------------- step
    def rotor_rows(self, emitters: list[Emitter]) -> np.ndarray:
        """The kernel's rotor rows for every vehicle's rotors: each disk's induced velocity and radius, and
        the skew of its wake: the air's horizontal motion (the mean wind at the rotor's height) relative
        to the rotor."""
        rows = [e.rotors for e in emitters if len(e.rotors)]
        if not rows:
            return np.zeros((0, kernel.ROTOR_SIZE))
        given = np.array(np.concatenate(rows), float)
        out = np.zeros((len(given), kernel.ROTOR_SIZE))
        out[:, 0:6] = given[:, 0:6]
        thrust, area = np.maximum(given[:, 6], 0.0), given[:, 7]
        out[:, 6] = np.sqrt(thrust / (2.0 * RHO * area))
        out[:, 7] = np.sqrt(area / math.pi)
        probe = np.empty(kernel.AIR_SIZE)
        nothing = np.zeros((0, kernel.ROTOR_SIZE))
        novortex = np.zeros((0, kernel.VORTEX_SIZE))
        k = 0
        for e in emitters:
            for _ in range(len(e.rotors)):
                kernel.air_velocity(out[k, 0], out[k, 1], out[k, 2], self._wind, nothing, novortex, probe)
                out[k, 8] = probe[0] - e.velocity[0]
                out[k, 9] = probe[1] - e.velocity[1]
                k += 1
        out[:, 10] = kernel.reach(out)
        # the share of each vehicle's wake still a jet: the rest is its trailing vortex pair
        k = 0
        for e, v in zip(emitters, self._vortices(emitters, out), strict=True):
            n = len(e.rotors)
            out[k : k + n, 11] = 1.0 if v is None else 1.0 - v[13]
            k += n
        kernel.ground_jets(out)
        return out

    def _vortices(self, emitters: list[Emitter], rows: np.ndarray | None = None) -> list[np.ndarray | None]:
        """Each vehicle's trailing vortex pair (None when slow), from its thrust, span and airspeed."""
        out: list[np.ndarray | None] = []
        probe = np.empty(kernel.AIR_SIZE)
        none = np.zeros((0, kernel.ROTOR_SIZE))
        nov = np.zeros((0, kernel.VORTEX_SIZE))
        for e in emitters:
            if not len(e.rotors):
                out.append(None)
                continue
            p = np.asarray(e.position, float)
            kernel.air_velocity(p[0], p[1], p[2], self._wind, none, nov, probe)
            air = np.asarray(e.velocity, float)[:2] - probe[:2]
            speed = float(np.hypot(*air))
            r = np.asarray(e.rotors, float)
            across = np.array([-air[1], air[0]]) / max(speed, 1e-9)
            radius = math.sqrt(float(r[0, 7]) / math.pi)
            lateral = (r[:, 0:2] - p[:2]) @ across
            span = float(lateral.max() - lateral.min()) + 2.0 * radius
            out.append(kernel.vortex_row(p, air, float(r[:, 6].sum()), span, float(r[:, 7].sum()),
                                         float(r[:, 2].mean())))  # fmt: skip
        return out

    def vortex_rows(self, emitters: list[Emitter]) -> np.ndarray:
        rows = [v for v in self._vortices(emitters) if v is not None]
        return np.array(rows) if rows else np.zeros((0, kernel.VORTEX_SIZE))

    def step(self, emitters: list[Emitter]) -> None:
        """One step: release what every vehicle sprays, then move every parcel."""
        for e in emitters:
            self.release(e, self.dt)
        self.advance(self.rotor_rows(emitters), self.vortex_rows(emitters))

    def advance(self, rotors: np.ndarray, vortices: np.ndarray) -> None:
        """Move every parcel one step through the air of these rotor and vortex rows (the kernel's)."""
        tg = self.targets
        kernel.step_parcels(
            self.x, self.v, self.turb, self.d, self.dres, self.n, self.ids, self.count, self.dt, self.steps,
            self.seed, self._air, self._wind, self._turbulence, rotors, vortices,
            self.shelter.ravel(),
            tg.leaf.ravel(), tg.wood.ravel(), tg.plant.ravel(), tg.third.ravel(), tg.wood_class.ravel(),
            self._dims, tg.origin, tg.cell,
            self.ground_origin, self.ground_cell, self._domain, self.ledger, self.dose, self.ground,
        )  # fmt: skip
        self.steps += 1
        self.t = self.steps * self.dt
        if self.steps % 50 == 0:
            self._compact()

    def settle(self, emitters: list[Emitter] | None = None, limit_s: float = 120.0) -> float:
        """Step with nothing released until every parcel has landed, evaporated or left (or ``limit_s``
        passes); ``emitters`` keep their wakes blowing (their releases are ignored). Returns the time
        taken."""
        quiet = [Emitter(e.position, e.quaternion, e.velocity, e.rotors) for e in emitters or []]
        t0 = self.t
        while self.airborne_count and self.t - t0 < limit_s:
            self.step(quiet)
        return self.t - t0

    # ----------------------------------------------------------------------------------- results
    @property
    def airborne_count(self) -> int:
        return int(np.count_nonzero(self.n[: self.count] > 0.0))

    @property
    def airborne_volume(self) -> float:
        c = self.count
        return float(np.sum(self.n[:c] * math.pi / 6.0 * self.d[:c] ** 3))

    def ledger_now(self) -> Ledger:
        parts = dict(zip(kernel.LEDGER, self.ledger.sum(0).tolist(), strict=True))
        parts["airborne"] = self.airborne_volume
        return Ledger(self.sprayed, parts)

    def ground_deposit(self) -> np.ndarray:
        """(gx, gy) volume (m^3) deposited on each ground cell."""
        return self.ground.sum(0)

    def ground_deposit_ul_cm2(self) -> np.ndarray:
        """(gx, gy) deposit per area (uL/cm^2) on each ground cell."""
        return self.ground_deposit() / self.ground_cell**2 * 1e5

    def plant_dose(self) -> np.ndarray:
        """(plants, 3) volume (m^3) on each plant's lower, middle and upper third."""
        return self.dose.sum(0)[: self.targets.plant_count]
