"""Domain randomisation (the ``randomize`` section): ranges the wind, the light and the depth camera's
error model (its preset and how noisy that camera is) and a rotor fault (docs/faults.md) are drawn from at
every reset, so a policy or a benchmark meets the field's variety.

Drawn per episode from the episode's own generator (seeded: the same seeds draw the same conditions),
by :meth:`RandomizeConfig.draw`. The RL environments (single and batched), ``droneulator capture`` and
the planning benchmark apply what is drawn; see docs/realism.md.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from droneulator.config.camera_presets import DEPTH_PRESETS
from droneulator.config.faults import FaultSpec
from droneulator.config.scene import VEGETATION_RANGE
from droneulator.config.wind import WindConfig


def _range(name: str, value: Any, lo: float, hi: float) -> tuple[float, float]:
    ok = isinstance(value, list | tuple) and len(value) == 2
    ok = ok and all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
    ok = ok and all(math.isfinite(v) for v in value)
    if not ok or not lo <= value[0] <= value[1] <= hi:
        want = f"[low, high] with {lo} <= low <= high <= {hi}"
        raise ValueError(f"randomize.{name} must be {want}, got {value!r}")
    return float(value[0]), float(value[1])


@dataclass
class Draw:
    """What one reset draws: the wind, the depth camera's preset, the light's time of day (h), cloud
    cover and visibility (m; None: clear air)."""

    wind: WindConfig
    depth_model: str
    time_of_day_h: float
    cloud_cover: float
    visibility_m: float | None
    #: the depth preset's noise and dropout probabilities, scaled (``CameraConfig.depth_noise_scale``, ...)
    depth_noise_scale: float = 1.0
    depth_dropout_scale: float = 1.0
    #: the scene's layout seed (None: the config's) and vegetation density (``SimConfig.vegetation``)
    scene_seed: int | None = None
    vegetation: float = 1.0
    #: spraying: every nozzle's droplet sizes x this, and the weather (C, relative humidity 0-1)
    droplet_scale: float = 1.0
    temperature_c: float = 20.0
    relative_humidity: float = 0.6
    #: each rotor's efficiency (docs/faults.md): all 1 but in an episode with a rotor fault drawn
    rotor_efficiency: tuple[float, float, float, float] = (1.0, 1.0, 1.0, 1.0)

    def describe(self) -> str:
        """One line for a log."""
        haze = "clear" if self.visibility_m is None else f"visibility {self.visibility_m:.0f} m"
        return (
            f"wind {self.wind.speed_m_s:.1f} m/s from {self.wind.direction_deg:.0f} deg (gusts "
            f"{self.wind.gust_speed_m_s:.1f} m/s), {self.time_of_day_h:.1f} h, cloud cover "
            f"{self.cloud_cover:.2f}, {haze}, depth {self.depth_model} (noise x{self.depth_noise_scale:.2f}, "
            f"dropouts x{self.depth_dropout_scale:.2f})"
            + ("" if self.scene_seed is None else f", scene seed {self.scene_seed}")
            + ("" if self.vegetation == 1.0 else f", vegetation x{self.vegetation:.2f}")
            + ("" if min(self.rotor_efficiency) == 1.0 else f", rotor efficiency {self.rotor_efficiency}")
        )


@dataclass
class RandomizeConfig:
    """Off by default. Each range is ``[low, high]`` (uniform); ``depth_models`` is a list of the depth
    presets to choose from, uniformly."""

    enabled: bool = False
    #: mean wind W20 (m/s) and where it blows from (degrees clockwise from north)
    wind_speed_m_s: tuple[float, float] = (0.0, 6.0)
    wind_direction_deg: tuple[float, float] = (0.0, 360.0)
    #: Dryden intensity factor, and the 1-cosine gusts' peak as a fraction of the mean wind
    turbulence_scale: tuple[float, float] = (0.5, 1.5)
    gust_fraction: tuple[float, float] = (0.0, 0.6)
    #: the depth camera's error model, one of these presets (``render.cameras[].depth_model``)
    depth_models: list[str] = field(default_factory=lambda: ["ideal", "d435"])
    #: factors on the drawn preset's noise (stereo subpixel error, ToF std) and on its dropout and flying
    #: pixel probabilities: one camera is better than another of the same model
    depth_noise_scale: tuple[float, float] = (0.5, 2.0)
    depth_dropout_scale: tuple[float, float] = (0.5, 1.5)
    #: the scene: a layout seed drawn from ``[low, high]`` (null: the config's seed) and the vegetation
    #: density (``SimConfig.vegetation``: x the leaves, a sparse or a dense canopy; [1, 1]: as designed).
    #: Each is a new scene, seconds to build the first time, so a capture or a planning run draws them
    #: once, and an RL environment draws ``scene_variants`` of them when it is built (the same ones for
    #: every environment made from one config) and flies each episode in one of those, drawn at reset
    scene_seed: tuple[int, int] | None = None
    vegetation: tuple[float, float] = (1.0, 1.0)
    scene_variants: int = 4
    #: the light (RGB only): local time (h), cloud cover, and the share of episodes in haze with a
    #: visibility drawn from ``visibility_m``
    time_of_day_h: tuple[float, float] = (7.0, 19.0)
    cloud_cover: tuple[float, float] = (0.0, 1.0)
    haze_prob: float = 0.2
    visibility_m: tuple[float, float] = (150.0, 2000.0)
    #: spraying (docs/spray.md): a factor on every nozzle's droplet sizes (Dv0.1, Dv0.5, Dv0.9), and the
    #: weather's temperature (C) and relative humidity (the droplets' evaporation)
    droplet_scale: tuple[float, float] = (0.7, 1.4)
    temperature_c: tuple[float, float] = (10.0, 35.0)
    relative_humidity: tuple[float, float] = (0.3, 0.9)
    #: a rotor fault (docs/faults.md): the share of episodes in which one rotor, drawn uniformly, keeps
    #: only an efficiency drawn from ``rotor_efficiency`` (its thrust and moments x it) for the whole episode
    rotor_fault_prob: float = 0.0
    rotor_efficiency: tuple[float, float] = (0.5, 0.9)

    def __post_init__(self) -> None:
        self.wind_speed_m_s = _range("wind_speed_m_s", self.wind_speed_m_s, 0.0, 40.0)
        self.wind_direction_deg = _range("wind_direction_deg", self.wind_direction_deg, -360.0, 720.0)
        self.turbulence_scale = _range("turbulence_scale", self.turbulence_scale, 0.0, 5.0)
        self.gust_fraction = _range("gust_fraction", self.gust_fraction, 0.0, 5.0)
        self.time_of_day_h = _range("time_of_day_h", self.time_of_day_h, 0.0, 24.0)
        self.cloud_cover = _range("cloud_cover", self.cloud_cover, 0.0, 1.0)
        self.visibility_m = _range("visibility_m", self.visibility_m, 1.0, 1e6)
        self.depth_noise_scale = _range("depth_noise_scale", self.depth_noise_scale, 0.0, 10.0)
        self.depth_dropout_scale = _range("depth_dropout_scale", self.depth_dropout_scale, 0.0, 10.0)
        self.vegetation = _range("vegetation", self.vegetation, *VEGETATION_RANGE)
        self.droplet_scale = _range("droplet_scale", self.droplet_scale, 0.1, 10.0)
        self.temperature_c = _range("temperature_c", self.temperature_c, -20.0, 50.0)
        self.relative_humidity = _range("relative_humidity", self.relative_humidity, 0.05, 1.0)
        self.rotor_efficiency = _range("rotor_efficiency", self.rotor_efficiency, 0.0, 1.0)
        prob = self.rotor_fault_prob
        if isinstance(prob, bool) or not (isinstance(prob, int | float) and 0.0 <= prob <= 1.0):
            raise ValueError(f"randomize.rotor_fault_prob must lie in [0, 1], got {prob!r}")
        if self.scene_seed is not None:
            lo, hi = _range("scene_seed", self.scene_seed, 0, 2**32 - 1)
            if lo != int(lo) or hi != int(hi):
                raise ValueError(f"randomize.scene_seed must be two integers, got {self.scene_seed!r}")
            self.scene_seed = (int(lo), int(hi))
        variants = self.scene_variants
        if isinstance(variants, bool) or not isinstance(variants, int) or not 1 <= variants <= 64:
            raise ValueError(f"randomize.scene_variants must be an integer in [1, 64], got {variants!r}")
        if not (isinstance(self.haze_prob, int | float) and 0.0 <= self.haze_prob <= 1.0):
            raise ValueError(f"randomize.haze_prob must lie in [0, 1], got {self.haze_prob!r}")
        bad = [m for m in self.depth_models if m not in DEPTH_PRESETS]
        if not self.depth_models or bad:
            raise ValueError(
                f"randomize.depth_models must be a non-empty list of {', '.join(DEPTH_PRESETS)}; "
                f"got {bad or '[]'}"
            )

    @property
    def scene_drawn(self) -> bool:
        """Whether the scene's layout seed or vegetation density is drawn at all."""
        return self.enabled and (self.scene_seed is not None or self.vegetation != (1.0, 1.0))

    def scene_variants_of(self, seed: int, vegetation: float = 1.0) -> list[tuple[int, float]]:
        """The scenes, ``(layout seed, vegetation)``, an RL environment of a config with seed ``seed`` and
        vegetation ``vegetation`` flies its episodes in: that one alone, or with the scene drawn,
        ``scene_variants`` draws (duplicates dropped) from a generator seeded by ``seed``."""
        if not self.scene_drawn:
            return [(int(seed), float(vegetation))]
        rng = np.random.default_rng([seed, 0x5CE4E])
        seeds, scenes = self.scene_seed, []
        for _ in range(self.scene_variants):
            layout = int(seed) if seeds is None else int(rng.integers(seeds[0], seeds[1] + 1))
            scenes.append((layout, float(rng.uniform(*self.vegetation))))
        return list(dict.fromkeys(scenes))

    def draw(self, rng: np.random.Generator, wind: WindConfig | None = None) -> Draw:
        """One episode's conditions; ``wind``: the settings the drawn ones replace fields of."""
        speed = float(rng.uniform(*self.wind_speed_m_s))
        drawn_wind = dataclasses.replace(
            wind or WindConfig(),
            speed_m_s=speed,
            direction_deg=float(rng.uniform(*self.wind_direction_deg)) % 360.0,
            turbulence_scale=float(rng.uniform(*self.turbulence_scale)),
            gust_speed_m_s=speed * float(rng.uniform(*self.gust_fraction)),
        )
        depth = self.depth_models[int(rng.integers(len(self.depth_models)))]
        hazy = bool(rng.random() < self.haze_prob)
        time_of_day = float(rng.uniform(*self.time_of_day_h)) % 24.0
        cloud = float(rng.uniform(*self.cloud_cover))
        visibility = float(rng.uniform(*self.visibility_m)) if hazy else None
        noise = float(rng.uniform(*self.depth_noise_scale))
        dropout = float(rng.uniform(*self.depth_dropout_scale))
        seeds = self.scene_seed
        scene_seed = None if seeds is None else int(rng.integers(seeds[0], seeds[1] + 1))
        vegetation = float(rng.uniform(*self.vegetation))
        # drawn after the others, so that adding them left every earlier draw as it was
        droplets = float(rng.uniform(*self.droplet_scale))
        temperature = float(rng.uniform(*self.temperature_c))
        humidity = float(rng.uniform(*self.relative_humidity))
        faulty = bool(rng.random() < self.rotor_fault_prob)
        rotor = int(rng.integers(4))
        kept = float(rng.uniform(*self.rotor_efficiency))
        efficiency = tuple(kept if faulty and i == rotor else 1.0 for i in range(4))
        return Draw(
            wind=drawn_wind,
            depth_model=depth,
            time_of_day_h=time_of_day,
            cloud_cover=cloud,
            visibility_m=visibility,
            depth_noise_scale=noise,
            depth_dropout_scale=dropout,
            scene_seed=scene_seed,
            vegetation=vegetation,
            droplet_scale=droplets,
            temperature_c=temperature,
            relative_humidity=humidity,
            rotor_efficiency=efficiency,  # type: ignore[arg-type]
        )

    def apply(self, cfg: Any, draw: Draw) -> Any:
        """A copy of ``cfg`` (a :class:`~droneulator.config.SimConfig`) in the conditions of ``draw``: its
        wind, its light's time of day, clouds and haze, every camera's depth model, its scene's seed and
        vegetation (for a workflow that draws once, e.g. a capture), its weather and nozzles' droplet
        sizes, and a rotor fault drawn (one for the whole episode in its ``faults``)."""
        out = copy.deepcopy(cfg)
        out.wind = draw.wind
        if draw.scene_seed is not None:
            out.seed = draw.scene_seed
        out.vegetation = draw.vegetation
        out.light = dataclasses.replace(
            out.light,
            time_of_day_h=draw.time_of_day_h,
            cloud_cover=draw.cloud_cover,
            visibility_m=draw.visibility_m,
        )
        depth = {
            "depth_model": draw.depth_model,
            "depth_noise_scale": draw.depth_noise_scale,
            "depth_dropout_scale": draw.depth_dropout_scale,
        }
        out.weather = dataclasses.replace(
            out.weather, temperature_c=draw.temperature_c, relative_humidity=draw.relative_humidity
        )
        out.spray = dataclasses.replace(out.spray, droplet_scale=draw.droplet_scale)
        rotors = [FaultSpec(kind="rotor", rotor=i, efficiency=e) for i, e in enumerate(draw.rotor_efficiency)]
        out.faults = [*out.faults, *(f for f in rotors if f.efficiency < 1.0)]  # type: ignore[operator]
        out.render.cameras = [dataclasses.replace(c, **depth) for c in out.render.cameras]
        for v in out.vehicles:
            if v.cameras is not None:
                v.cameras = [dataclasses.replace(c, **depth) for c in v.cameras]
        return out
