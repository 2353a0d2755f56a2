"""The WebSocket API a run serves: its server over the command path, fed every state and every event.

The dynamics server hosts it: each published state and each event (the world's: impacts, landings,
goals; the PX4 links': connections, losses, arming, hand-overs) goes out to the API's clients, and
``scene_info.vehicles`` tells each client where every vehicle is reached (ROS names, PX4 port).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import TYPE_CHECKING

from droneulator.api.access import server_ssl_context
from droneulator.api.server import ApiServer
from droneulator.commands import CommandPath
from droneulator.config import SimConfig
from droneulator.controllers.flight import Event
from droneulator.ros.publishers import fleet_names
from droneulator.vehicles.vehicle import VehicleState

if TYPE_CHECKING:
    from droneulator.px4.fleet import Fleet


class ApiHost:
    """The API server of a run on ``runtime.api_host:api_port``, over ``commands``."""

    def __init__(self, commands: CommandPath, cfg: SimConfig) -> None:
        self.cfg = cfg
        self.world = commands.sim
        rt, access = cfg.runtime, cfg.access
        self.server = ApiServer(
            commands,
            host=rt.api_host,
            port=rt.api_port,
            max_message_bytes=rt.api_max_message_bytes,
            state_rate_hz=rt.state_hz,
            token=access.token,
            ssl_context=server_ssl_context(access.tls_cert, access.tls_key),
            # limited wherever a token is asked for (``droneulator run`` gives one beyond loopback)
            rate_hz=access.rate_hz if access.token is not None else None,
            burst=access.burst,
        )

    @property
    def port(self) -> int:
        return self.server.port

    def start(self, px4: Fleet | None) -> None:
        """Say where each vehicle is reached (its PX4 port bound already), then serve."""
        self._describe_vehicles(px4)
        self.server.start()

    def stop(self) -> None:
        self.server.stop()

    def publish_states(self, states: Mapping[str, VehicleState]) -> None:
        self.server.publish_states(states)

    def publish_events(self, events: Iterable[Event]) -> None:
        for e in events:
            self.server.publish_event(e.to_dict())

    def _describe_vehicles(self, px4: Fleet | None) -> None:
        """Tell each vehicle where it is reached (``scene_info.vehicles``): ROS names, its autopilot's port
        (bound)."""
        ports = {}
        if px4 is not None:
            for link in px4.links:
                ports[link.vehicle.name] = link.endpoint()
        for name, names in fleet_names(self.cfg).items():
            v = self.world.vehicles[name]
            v.endpoints = {**names.describe([c.name for c in v.cameras]), **ports.get(name, {})}
