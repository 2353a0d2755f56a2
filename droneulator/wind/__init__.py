"""Wind: the wind field of the ``wind`` section (:mod:`.field`, :mod:`.dryden`), and RotorPy's wind profiles
chosen by name in ``VehicleConfig.wind`` (:func:`make_wind`).

RotorPy's wind module is imported only for a profile that needs it: it imports torch when torch is
installed, which costs seconds and hundreds of megabytes in every simulator process."""

from __future__ import annotations

from typing import Protocol

import numpy as np

from droneulator.config import WIND_MODELS, VehicleConfig


class WindModel(Protocol):
    def update(self, t: float, position: np.ndarray) -> np.ndarray: ...


class Calm:
    """No wind (``vehicle.wind = "none"``): zero at every time and place."""

    def update(self, t: float, position: np.ndarray) -> np.ndarray:
        return np.zeros(3)


def make_wind(cfg: VehicleConfig, seed: int, dt: float) -> WindModel:
    """Build the configured RotorPy wind profile (world-frame wind velocity in m/s).

    RotorPy's Dryden gust draws from NumPy's global generator, so it is seeded here for
    reproducible runs; its module imports torch, so it needs the ``rl`` extra.
    """
    mean = np.asarray(cfg.wind_velocity, dtype=float)
    if cfg.wind == "none":
        return Calm()
    from rotorpy.wind.default_winds import ConstantWind, SinusoidWind

    if cfg.wind == "constant":
        return ConstantWind(*mean)
    if cfg.wind == "sinusoid":
        return SinusoidWind(
            amplitudes=np.asarray(cfg.wind_sigma, dtype=float) + mean, frequencies=np.array([0.2, 0.13, 0.05])
        )
    if cfg.wind == "dryden":
        try:
            from rotorpy.wind.dryden_winds import DrydenGust
        except ImportError as exc:
            raise ValueError("the dryden wind model needs torch: pip install 'droneulator[rl]'") from exc
        np.random.seed(seed)
        return DrydenGust(dt=dt, avg_wind=mean, sig_wind=np.asarray(cfg.wind_sigma, dtype=float))
    raise ValueError(f"unknown wind model {cfg.wind!r}; known: {', '.join(WIND_MODELS)}")
