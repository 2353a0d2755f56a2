"""Which vehicle a planner plans for: its topic and frame names and its PX4 instance, as the run reports
them (``scene_info``) or as its configuration sets them.

One planner process plans for one vehicle. In a world of several, each vehicle gets its own
(``droneulator plan --vehicle NAME``), on that vehicle's namespaced topics and prefixed frames; the
renderer draws the other vehicles into its depth images, so each maps the others like any obstacle.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from droneulator.ros.topics import VehicleNames, vehicle_names

if TYPE_CHECKING:
    from droneulator.config import SimConfig


@dataclass(frozen=True)
class PlannedVehicle:
    """The vehicle a planner plans for."""

    names: VehicleNames
    #: its cameras' names; None where nothing told them (the single-vehicle default)
    cameras: list[str] | None = None
    #: the PX4 SITL instance flying it (``px4 -i N``); None: PX4 does not fly it in this run
    px4_instance: int | None = None
    #: the ArduPilot SITL instance flying it (``arducopter -I N``); None: ArduPilot does not fly it
    ardupilot_instance: int | None = None
    #: where the names came from, for messages
    source: str = "defaults"

    @property
    def name(self) -> str:
        return self.names.vehicle

    def check_camera(self, cam: str) -> None:
        """Raise ValueError unless the vehicle has a camera named ``cam`` (when its cameras are known)."""
        if self.cameras is not None and cam not in self.cameras:
            have = ", ".join(self.cameras) or "none"
            raise ValueError(f"vehicle {self.name!r} has no camera {cam!r} ({self.source}: it has {have})")

    def px4(self) -> int:
        """Its PX4 instance; ValueError if PX4 does not fly it."""
        if self.px4_instance is None:
            raise ValueError(
                f"PX4 does not fly vehicle {self.name!r} ({self.source}); run it with controlled_by='px4' "
                "(`droneulator run --px4` hands PX4 the first vehicle), or give --px4-instance"
            )
        return self.px4_instance

    def ardupilot(self) -> int:
        """Its ArduPilot instance; ValueError if ArduPilot does not fly it."""
        if self.ardupilot_instance is None:
            raise ValueError(
                f"ArduPilot does not fly vehicle {self.name!r} ({self.source}); run it with "
                "controlled_by='ardupilot' (`droneulator run --ardupilot`), or give --ardupilot-instance"
            )
        return self.ardupilot_instance


def single_vehicle(namespace: str = "droneulator", name: str = "uav0") -> PlannedVehicle:
    """The one vehicle of a single-vehicle run: today's names under ``namespace``."""
    return PlannedVehicle(vehicle_names(namespace, name, fleet=False))


def _pick(names: list[str], vehicle: str | None, source: str) -> str:
    if not names:
        raise ValueError(f"{source} lists no vehicles")
    if vehicle is None:
        return names[0]
    if vehicle not in names:
        raise ValueError(f"no vehicle {vehicle!r} in {source}: it has {', '.join(names)}")
    return vehicle


def from_scene_info(info: dict[str, Any], vehicle: str | None = None) -> PlannedVehicle:
    """``vehicle`` (default: the first) as a ``scene_info`` reply lists it: the namespace, TF prefix and
    TF topics the run reports, checked against every topic it names (ValueError where they differ)."""
    entries = {v["name"]: v for v in info.get("vehicles", [])}
    name = _pick(list(entries), vehicle, "the run's scene_info")
    entry = entries[name]
    topics = dict(entry["topics"])
    cameras = topics.pop("cameras", {})
    names = VehicleNames(
        name, str(entry["namespace"]).lstrip("/"), entry["tf_prefix"], topics["tf"], topics["tf_static"]
    )
    ours = {**names.topics(), **{c: names.camera_topics(c) for c in cameras}}
    theirs = {**topics, **cameras}
    if ours != theirs:
        diff = sorted(k for k in set(ours) | set(theirs) if ours.get(k) != theirs.get(k))
        raise ValueError(f"the run names the topics {diff} of vehicle {name!r} otherwise than this planner")
    return PlannedVehicle(
        names,
        cameras=list(entry.get("cameras", cameras)),
        px4_instance=entry.get("px4_instance"),
        ardupilot_instance=entry.get("ardupilot_instance"),
        source="the run's scene_info",
    )


def from_config(cfg: SimConfig, vehicle: str | None = None) -> PlannedVehicle:
    """``vehicle`` (default: the first) of the run's configuration: its names as the bridge publishes
    them (:func:`~droneulator.ros.publishers.fleet_names`) and its PX4 instance (``px4_instances``)."""
    from droneulator.ros.publishers import fleet_names

    every = fleet_names(cfg)
    name = _pick(list(every), vehicle, "the configuration")
    return PlannedVehicle(
        every[name],
        cameras=[c.name for c in cfg.camera_rigs()[name]],
        px4_instance=cfg.px4_instances().get(name),
        ardupilot_instance=cfg.ardupilot_instances().get(name),
        source="the configuration",
    )
