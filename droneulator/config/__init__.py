"""All configuration in one typed place.

Every option is a dataclass field of :class:`SimConfig`, one section per concern
(:mod:`~droneulator.config.sections`; the capture and learning workflows' sections in
:mod:`~droneulator.config.capture` and :mod:`~droneulator.config.rl`). A config is built from the
defaults, then a JSON, TOML or YAML file (``--config FILE``), then ``--set section.key=value`` overrides
from the command line, in that order (:mod:`~droneulator.config.loading`).
"""

from droneulator.config.capture import CaptureConfig
from droneulator.config.faults import FAULT_KINDS, FaultError, FaultSpec
from droneulator.config.light import LightConfig
from droneulator.config.loading import (
    ConfigError,
    apply_override,
    from_dict,
    load_config,
    load_file,
    to_dict,
)
from droneulator.config.randomize import RandomizeConfig
from droneulator.config.rl import RLConfig
from droneulator.config.sections import (
    CONTACT_MODELS,
    CONTROLLERS,
    PX4_ON_LOSS,
    WIND_MODELS,
    AccessConfig,
    ArduPilotConfig,
    BatteryConfig,
    BridgeConfig,
    CameraConfig,
    FlightConfig,
    PX4Config,
    RenderConfig,
    RuntimeConfig,
    SimConfig,
    UIConfig,
    VehicleConfig,
    VehicleSpec,
    fleet,
)
from droneulator.config.sensor_presets import (
    BARO_PRESETS,
    GPS_PRESETS,
    IMU_PRESETS,
    MAG_PRESETS,
    GpsError,
    ImuModel,
)
from droneulator.config.site import SiteConfig
from droneulator.config.spray import NozzleConfig, SprayConfig, WeatherConfig
from droneulator.config.wind import WindConfig

__all__ = [
    "AccessConfig",
    "FAULT_KINDS",
    "FaultError",
    "FaultSpec",
    "BARO_PRESETS",
    "CONTACT_MODELS",
    "CONTROLLERS",
    "GPS_PRESETS",
    "IMU_PRESETS",
    "MAG_PRESETS",
    "PX4_ON_LOSS",
    "WIND_MODELS",
    "BatteryConfig",
    "BridgeConfig",
    "CameraConfig",
    "CaptureConfig",
    "ConfigError",
    "FlightConfig",
    "GpsError",
    "ImuModel",
    "LightConfig",
    "NozzleConfig",
    "ArduPilotConfig",
    "PX4Config",
    "RLConfig",
    "RandomizeConfig",
    "RenderConfig",
    "RuntimeConfig",
    "SimConfig",
    "SiteConfig",
    "SprayConfig",
    "UIConfig",
    "VehicleConfig",
    "VehicleSpec",
    "WeatherConfig",
    "WindConfig",
    "apply_override",
    "fleet",
    "from_dict",
    "load_config",
    "load_file",
    "to_dict",
]
