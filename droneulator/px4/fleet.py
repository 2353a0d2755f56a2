"""What every autopilot's fleet of links shares: one link a vehicle it flies, started, served and closed
together; the runtime's face of an autopilot interface (PX4's :class:`~droneulator.px4.link.PX4Fleet`,
ArduPilot's :class:`~droneulator.ardupilot.link.ArduPilotFleet`)."""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any, ClassVar, Generic, TypeVar

L = TypeVar("L")


class AutopilotFleet(Generic[L]):
    """The links of one autopilot kind (``kind``, reached over ``scheme``), served together by ``serve``
    (its module's ``serve_links(links, timeout, lock)``); a subclass builds them (``of``)."""

    kind: ClassVar[str]
    scheme: ClassVar[str]
    serve: ClassVar[Callable[..., Any]]

    def __init__(self, links: list[L]) -> None:
        if not links:
            raise ValueError(f"{self.kind}: a fleet needs at least one link")
        self.links = links

    def start(self, listen: bool = True) -> None:
        for link in self.links:
            link.start(listen)  # type: ignore[attr-defined]

    @property
    def listening(self) -> bool:
        return all(link.listening for link in self.links)  # type: ignore[attr-defined]

    @property
    def connected(self) -> bool:
        """True while any of its autopilots is connected (it then drives the simulation clock)."""
        return any(link.connected for link in self.links)  # type: ignore[attr-defined]

    def connected_vehicles(self) -> set[str]:
        """The vehicles with an autopilot connected (their links sample their sensors every step)."""
        return {link.vehicle.name for link in self.links if link.connected}  # type: ignore[attr-defined]

    def describe(self) -> str:
        """Where each link waits, for the runtime's log."""
        return ", ".join(
            f"{self.scheme}://{link.cfg.host}:{link.port} ({link.vehicle.name})"  # type: ignore[attr-defined]
            for link in self.links
        )

    def serve_once(self, timeout: float, lock: threading.Lock | None = None) -> Any:
        """Serve every link once (at most ``timeout`` s): the step result when the world stepped."""
        return type(self).serve(self.links, timeout, lock)

    def take_events(self) -> list[Any]:
        return [e for link in self.links for e in link.take_events()]  # type: ignore[attr-defined]

    def close(self) -> None:
        for link in self.links:
            link.close()  # type: ignore[attr-defined]
