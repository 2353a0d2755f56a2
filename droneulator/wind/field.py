"""The wind field: the wind each vehicle feels where it is, from one :class:`~droneulator.config.WindConfig`
per vehicle (or per batched world).

A vehicle's wind (world frame, m/s) is

    shelter * ((W(h) + gust(t)) * d  +  R (sigma_u u, sigma_v v, sigma_w w))

* ``W(h)``: the mean wind at the vehicle's height, ``W20 ln(h / z0) / ln(20 ft / z0)`` (MIL-F-8785C's
  wind shear; zero below ``z0``), or ``W20`` everywhere with the uniform profile; ``d`` the horizontal
  direction it blows towards;
* ``gust(t)``: discrete "1 - cosine" gusts along ``d`` (MIL-F-8785C 3.7.4), ``A/2 (1 - cos(2 pi
  tau / D))`` over a gust's length ``D``, arriving as a Poisson process;
* ``u, v, w``: unit Dryden processes (:mod:`droneulator.wind.dryden`) along the wind, across it and up
  (the axes ``R`` turns to the world), each vehicle its own realisation, met at the vehicle's airspeed
  relative to the mean wind (at least 1 m/s: the frozen-field model needs motion through the air);
* ``shelter``: ``exp(-a * sum_i len_i exp(-s_i / recovery))`` over the canopy (the scene's collision
  geometry, the signed distance below zero) that the upwind ray from the vehicle crosses at distances
  ``s_i``: a vehicle inside a crown or just behind a row feels less of the wind, and the full wind
  once it leaves the row or climbs above the trees.

Everything is seeded: a world with the same seed feels the same wind.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numba
import numpy as np

from droneulator.config.wind import WindConfig
from droneulator.scenes.collision import CollisionModel, sdf_lookup
from droneulator.wind import dryden

#: the height the standard's wind speed W20 refers to
H20_M = 20.0 * dryden.FT
#: the slowest airspeed the frozen turbulence is met at (m/s)
V_MIN = 1.0
#: the upwind ray's sample spacing (m) and length in recovery lengths
SHELTER_STEP_M = 0.25
SHELTER_FETCH = 4.0
#: the shelter is recomputed every this many steps (it changes with position, slowly)
SHELTER_EVERY = 5


@numba.njit(cache=True)
def _shelter_exponents(
    sdf: np.ndarray,
    origin: np.ndarray,
    resolution: float,
    points: np.ndarray,
    heading: np.ndarray,
    recovery: np.ndarray,
    step: float,
    fetch: float,
) -> np.ndarray:
    """Per point: the recovery-weighted length (m) of solid geometry along its upwind ray."""
    out = np.zeros(points.shape[0])
    q = np.empty(3)
    for n in range(points.shape[0]):
        length = fetch * recovery[n]
        k = int(length / step)
        acc = 0.0
        for i in range(k):
            s = (i + 0.5) * step
            q[0] = points[n, 0] - heading[n, 0] * s
            q[1] = points[n, 1] - heading[n, 1] * s
            q[2] = points[n, 2]
            if sdf_lookup(sdf, origin, resolution, q) < 0.0:
                acc += step * math.exp(-s / recovery[n])
        out[n] = acc
    return out


class WindField:
    """The wind of ``n`` vehicles (rows), each with its own settings and turbulence."""

    def __init__(
        self,
        configs: Sequence[WindConfig] | WindConfig,
        n: int,
        dt: float,
        seed: int | np.random.SeedSequence = 0,
        collision: CollisionModel | None = None,
    ) -> None:
        self.n = n
        self.dt = float(dt)
        self.collision = collision
        self.configs: list[WindConfig] = []
        self._arrays(n)
        self.configure(configs)
        self.reset(seed)

    def _arrays(self, n: int) -> None:
        self.w20 = np.zeros(n)
        self.heading = np.zeros((n, 2))
        self.log_profile = np.zeros(n, dtype=bool)
        self.z0 = np.ones(n)
        self.turbulence = np.zeros(n)
        self.gust_speed = np.zeros(n)
        self.gust_interval = np.ones(n)
        self.gust_duration = np.ones(n)
        self.shelter_on = np.zeros(n, dtype=bool)
        self.attenuation = np.zeros(n)
        self.recovery = np.ones(n)
        #: the last update's parts, for truth and tests: shelter factor, mean speed, gust speed
        self.shelter = np.ones(n)
        self.mean_speed = np.zeros(n)
        self.gust_now = np.zeros(n)

    def configure(
        self, configs: Sequence[WindConfig] | WindConfig, rows: Sequence[int] | None = None
    ) -> None:
        """Set the settings of ``rows`` (all by default) from one config or one per row; the
        turbulence and gust states carry on (``set_wind`` during a flight changes the wind smoothly)."""
        rows = list(range(self.n)) if rows is None else list(rows)
        if isinstance(configs, WindConfig):
            configs = [configs] * len(rows)
        if len(configs) != len(rows):
            raise ValueError(f"{len(configs)} wind configs for {len(rows)} rows")
        if not self.configs:
            self.configs = [WindConfig()] * self.n
        for r, c in zip(rows, configs, strict=True):
            self.configs[r] = c
            self.w20[r] = c.speed_m_s
            self.heading[r] = c.heading
            self.log_profile[r] = c.profile == "log"
            self.z0[r] = c.roughness_m
            self.turbulence[r] = c.turbulence_scale if c.turbulence == "dryden" else 0.0
            self.gust_speed[r] = c.gust_speed_m_s
            self.gust_interval[r] = c.gust_interval_s
            self.gust_duration[r] = c.gust_duration_s
            self.shelter_on[r] = c.shelter
            self.attenuation[r] = c.canopy_attenuation_per_m
            self.recovery[r] = c.shelter_recovery_m

    @property
    def calm(self) -> bool:
        """Every row's wind is zero everywhere (no mean wind, no gusts)."""
        return all(c.calm for c in self.configs)

    def reset(self, seed: int | np.random.SeedSequence) -> None:
        """Fresh turbulence (drawn from its stationary distribution) and gust schedules for every row."""
        self.rng = np.random.default_rng(seed)
        self.t = 0.0
        self._u, self._v, self._w = dryden.stationary_start(self.rng, self.n)
        self._next_gust = self.rng.exponential(self.gust_interval)
        self._gust_start = np.full(self.n, -np.inf)
        self._steps = 0

    def reset_rows(self, rows: Sequence[int] | np.ndarray) -> None:
        """Fresh turbulence and gust schedules for ``rows`` only (a batched world's copies placed again),
        drawn from the field's running generator."""
        idx = np.asarray(rows, dtype=int)
        u, v, w = dryden.stationary_start(self.rng, len(idx))
        self._u[idx], self._v[idx], self._w[idx] = u, v, w
        self._next_gust[idx] = self.t + self.rng.exponential(self.gust_interval[idx])
        self._gust_start[idx] = -np.inf
        self._steps = 0  # recompute the shelter at the next step

    def update(self, positions: np.ndarray, velocities: np.ndarray) -> np.ndarray:
        """Advance one step of ``dt`` and return every row's wind (n, 3) at ``positions`` for vehicles
        moving at ``velocities`` (world frame)."""
        n, dt = self.n, self.dt
        h = np.maximum(positions[:, 2], 0.0)
        if np.any(self.log_profile):
            ratio = np.log(np.maximum(h, self.z0) / self.z0) / np.log(H20_M / self.z0)
            self.mean_speed = self.w20 * np.where(self.log_profile, ratio, 1.0)
        else:
            self.mean_speed = self.w20.copy()
        # gusts: start the ones due, shape the running ones
        self.t += dt
        due = self.t >= self._next_gust
        if np.any(due):
            self._gust_start[due] = self._next_gust[due]
            self._next_gust[due] += self.gust_duration[due] + self.rng.exponential(self.gust_interval[due])
        tau = np.clip(self.t - self._gust_start, 0.0, self.gust_duration)  # 0 or D: no gust running
        self.gust_now = 0.5 * self.gust_speed * (1.0 - np.cos(2.0 * np.pi * tau / self.gust_duration))
        along = self.mean_speed + self.gust_now
        wind = np.zeros((n, 3))
        wind[:, 0] = along * self.heading[:, 0]
        wind[:, 1] = along * self.heading[:, 1]
        # turbulence, met at the airspeed through the mean wind
        if np.any(self.turbulence > 0.0):
            L_uv, L_w = dryden.scale_lengths(h)
            s_uv, s_w = dryden.intensities(h, self.w20)
            rel = velocities[:, :2] - wind[:, :2]
            V = np.maximum(np.hypot(rel[:, 0], rel[:, 1]), V_MIN)
            noise = self.rng.standard_normal((n, 5))
            dryden.first_order_step(self._u, dt, L_uv / V, noise[:, 0])
            dryden.second_order_step(self._v, dt, L_uv / V, noise[:, 1:3])
            dryden.second_order_step(self._w, dt, L_w / V, noise[:, 3:5])
            u = self.turbulence * s_uv * self._u
            v = self.turbulence * s_uv * dryden.second_order_output(self._v)
            w = self.turbulence * s_w * dryden.second_order_output(self._w)
            dx, dy = self.heading[:, 0], self.heading[:, 1]
            # u along the wind, v to its left (counter-clockwise), w up
            wind[:, 0] += u * dx - v * dy
            wind[:, 1] += u * dy + v * dx
            wind[:, 2] += w
        if self.collision is not None and np.any(self.shelter_on):
            if self._steps % SHELTER_EVERY == 0:
                self.shelter = self.shelter_factor(positions)
            wind *= self.shelter[:, None]
        self._steps += 1
        return wind

    def shelter_factor(self, positions: np.ndarray) -> np.ndarray:
        """The fraction of the open wind that reaches each position (1 outside the canopy's lee)."""
        col = self.collision
        if col is None:
            return np.ones(self.n)
        exps = _shelter_exponents(
            col.sdf,
            col.origin,
            col.resolution,
            np.ascontiguousarray(positions, dtype=float),
            np.ascontiguousarray(self.heading),
            np.ascontiguousarray(self.recovery),
            SHELTER_STEP_M,
            SHELTER_FETCH,
        )
        return np.where(self.shelter_on, np.exp(-self.attenuation * exps), 1.0)
