"""Magnetometer: a constant NED Earth field seen from PX4's FRD body frame, with bias and noise."""

from __future__ import annotations

from typing import Any

import numpy as np

from droneulator.frames import quat_to_matrix
from droneulator.sensors.registry import register
from droneulator.sensors.truth import Truth


@register("mag")
class Magnetometer:
    """Field in gauss; ``cfg`` gives ``mag_field_ned_gauss``, ``mag_bias`` and ``mag_noise``."""

    def __init__(self, cfg: Any, rng: np.random.Generator) -> None:
        self.cfg = cfg
        self.rng = rng
        self.field_ned = np.array(cfg.mag_field_ned_gauss, dtype=float)

    def sample(self, truth: Truth) -> np.ndarray:
        """Magnetic field in the FRD body frame (gauss): the NED field rotated into the body."""
        R_ned_frd = quat_to_matrix(truth.quaternion_ned_frd)
        field = R_ned_frd.T @ self.field_ned
        return field + np.asarray(self.cfg.mag_bias) + self.rng.normal(0.0, self.cfg.mag_noise, 3)
