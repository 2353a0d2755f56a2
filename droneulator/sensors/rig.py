"""A vehicle's sensor rig, built from its config table: its cameras and its noisy sensors.

As MetaDrive builds an agent's sensors from a config table, a vehicle's rig comes from its
``cameras`` (a list of :class:`~droneulator.config.CameraConfig`) and its ``sensors`` (kinds from
:data:`~droneulator.sensors.suite.SUITE_KINDS`), each model looked up in the registry. A camera's
mount on the body is computed here, once (:class:`~droneulator.sensors.camera.Camera`); the
renderer draws what the cameras see and the PX4 link sends what the noisy sensors read.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from droneulator.config import CameraConfig, SiteConfig
from droneulator.sensors.imu import IMU_HZ
from droneulator.sensors.registry import get_sensor
from droneulator.sensors.suite import SensorSuite


def vehicle_seed(seed: int, index: int) -> np.random.SeedSequence:
    """The noise seed of the world's ``index``-th vehicle: the world's seed itself for the first (so one
    vehicle reads what it read before worlds held several), a distinct sequence for each other."""
    return np.random.SeedSequence(seed if index == 0 else [seed, index])


@dataclass
class Rig:
    """``cameras``: name -> :class:`~droneulator.sensors.camera.Camera` (intrinsics and mount), in
    config order; ``suite``: the noisy sensors."""

    cameras: dict[str, Any]
    suite: SensorSuite

    @property
    def camera_configs(self) -> list[CameraConfig]:
        return [c.cfg for c in self.cameras.values()]


def build_rig(
    cameras: Sequence[CameraConfig],
    sensors: Sequence[str],
    px4: Any,
    seed: int = 0,
    index: int = 0,
    imu_hz: float = IMU_HZ,
    site: SiteConfig | None = None,
) -> Rig:
    """The rig of a vehicle with these ``cameras`` and ``sensors``; ``px4`` is the
    :class:`~droneulator.config.PX4Config` the noise models read; ``index`` the vehicle's place in
    its world (see :func:`vehicle_seed`); ``imu_hz`` the IMU's sampling rate (the physics rate); ``site``
    the world origin's place (:class:`~droneulator.config.SiteConfig`; None: the default). A bad
    sensor kind or a repeated camera name is a ValueError."""
    camera = get_sensor("camera")
    built = {cam.name: camera(cam) for cam in cameras}
    if len(built) != len(cameras):
        raise ValueError(f"camera names must differ: {[c.name for c in cameras]}")
    return Rig(built, SensorSuite(px4, vehicle_seed(seed, index), sensors, imu_hz=imu_hz, site=site))
