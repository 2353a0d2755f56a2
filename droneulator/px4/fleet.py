"""What every autopilot link shares, and the one lockstep loop that serves them all: PX4's
(:class:`~droneulator.px4.link.PX4Link`) and ArduPilot's (:class:`~droneulator.ardupilot.link.ArduPilotLink`)
links, any mix of them, step one world together.

A link exposes a small lockstep protocol (:class:`LockstepLink`): the sockets to poll, a handler for what
was readable (which also notices a lost peer), the time until its autopilot lets the world step, the
command to take for the step, applying it, and the sensor data to send after the step. :func:`serve_links`
steps the world once when every connected autopilot is ready (PX4: its actuator message for the last step,
or its boot pacing; ArduPilot: its next servo frame), then each gets the step's data (HIL_SENSOR and
HIL_GPS to PX4, the JSON reply to ArduPilot), so every autopilot sees the same simulation time stamps.
One world step is one control period (``vehicle.control_hz``) for every autopilot of the world.
"""

from __future__ import annotations

import contextlib
import logging
import select
import time
from collections.abc import Collection
from contextlib import AbstractContextManager
from typing import TYPE_CHECKING, Any, ClassVar, Generic, Protocol, TypeVar

from droneulator.sensors import Truth

if TYPE_CHECKING:
    import socket

    from droneulator.world.world import StepResult, World

log = logging.getLogger(__name__)


class LockstepLink(Protocol):
    """One autopilot's link as the lockstep loop drives it (every method but :meth:`apply_command` is
    called outside the world's lock; ``guard`` is that lock, for what the link does under it)."""

    world: World
    autopilot: str
    scheme: ClassVar[str]

    @property
    def listening(self) -> bool: ...

    @property
    def connected(self) -> bool: ...

    def sockets(self) -> list[socket.socket]:
        """The sockets to poll for the link (its listener, connection and candidates, or its port)."""
        ...

    def on_readable(self, readable: Collection[Any], guard: Any) -> None:
        """Handle what polling found readable among :meth:`sockets` (called after every poll, with an
        empty ``readable`` too, so a link notices a silent peer)."""
        ...

    def on_poll_error(self, exc: Exception) -> None:
        """Polling failed (a socket closed under it)."""
        ...

    def apply_pending_loss(self, guard: Any) -> None:
        """Apply ``on_loss`` (under ``guard``) when the autopilot was dropped while it had the rotors."""
        ...

    def time_to_step(self) -> float | None:
        """Wall seconds until this autopilot lets the world step (<= 0: now), or None while it holds the
        clock (its command for the next step has not come)."""
        ...

    def take_command(self) -> Any:
        """Take what the step applies for this autopilot (called once per step, before the lock)."""
        ...

    def apply_command(self, cmd: Any) -> None:
        """(Under the lock, before the step) apply ``cmd`` from :meth:`take_command` to the vehicle."""
        ...

    def after_step(self, truth: Truth, cmd: Any) -> None:
        """Send the autopilot the step's data (``truth`` of its vehicle after the step)."""
        ...


def serve_links(
    links: Collection[Any], timeout: float, lock: AbstractContextManager[Any] | None = None
) -> StepResult | None:
    """Serve every link (:class:`LockstepLink`, of any autopilot) for up to ``timeout`` s and step their
    (one) world at most once.

    The world steps when every connected autopilot is ready (the latest of their :meth:`time_to_step`
    has come), as Gazebo's lockstep waits for every instance; links without an autopilot do not hold
    the clock. Returns the step's result, or None when nothing stepped within ``timeout``. ``lock`` is
    held around every access to the world.

    The sockets are read (without waiting) before a step that is already due: a simulator behind the wall
    clock (a loaded machine) has a free-running step due at every call, and stepping at once would never
    read the autopilot's first lockstep answer (the clock ran on through one in a suite run with a core
    busy; ``tests/test_px4.py``).
    """
    for link in links:
        if not link.listening:
            raise RuntimeError(f"{type(link).__name__} is not listening: call start() first")
    guard = lock if lock is not None else contextlib.nullcontext()
    deadline = time.monotonic() + max(0.0, float(timeout))
    polled = False
    while True:
        for link in links:
            link.apply_pending_loss(guard)
        connected = [link for link in links if link.connected]
        waits = [link.time_to_step() for link in connected]
        due = max(waits) if waits and all(w is not None for w in waits) else None  # type: ignore[type-var]
        if due is not None and due <= 0.0 and polled:
            return step_links(connected, guard)
        now = time.monotonic()
        if polled and now >= deadline:
            return None
        wait = max(0.0, deadline - now)
        if due is not None:
            wait = min(wait, max(0.0, due))
        _poll_links(links, wait, guard)
        polled = True


def _poll_links(links: Collection[Any], wait: float, guard: Any) -> None:
    owner = {sock: link for link in links for sock in link.sockets()}
    try:
        readable, _, _ = select.select(list(owner), [], [], wait)
    except (OSError, ValueError) as exc:
        for link in links:
            link.on_poll_error(exc)
        return
    for link in links:
        link.on_readable([s for s in readable if owner[s] is link], guard)


def step_links(links: list[Any], guard: Any) -> StepResult:
    """Apply every connected autopilot's command, step the world once, send each its sensor data."""
    world = links[0].world
    cmds = [link.take_command() for link in links]
    with guard:
        for link, cmd in zip(links, cmds, strict=True):
            link.apply_command(cmd)
        result = world.step()
        truths = [Truth.from_sim(link.vehicle) for link in links]
    for link, truth, cmd in zip(links, truths, cmds, strict=True):
        link.after_step(truth, cmd)
    return result


L = TypeVar("L")


class AutopilotFleet(Generic[L]):
    """The autopilot links of one world (one link a vehicle an autopilot flies, PX4's and ArduPilot's
    mixed), started, served (:func:`serve_links`: one lockstep clock) and closed together; the runtime's
    face of the autopilot interfaces."""

    kind: ClassVar[str] = "autopilot"

    def __init__(self, links: list[L]) -> None:
        if not links:
            raise ValueError(f"{self.kind}: a fleet needs at least one link")
        self.links = links

    @classmethod
    def of(cls, world: World) -> AutopilotFleet[Any]:
        """One link for each vehicle the world's config hands to an autopilot: PX4's
        (:meth:`SimConfig.px4_instances`) and ArduPilot's (:meth:`SimConfig.ardupilot_instances`)."""
        from droneulator.ardupilot.link import ArduPilotLink
        from droneulator.px4.link import PX4Link

        px4 = world.config.px4_instances()
        ardupilot = world.config.ardupilot_instances()
        links: list[Any] = []
        for name in world.vehicles:
            if name in px4:
                links.append(PX4Link(world, vehicle=name, instance=px4[name]))
            elif name in ardupilot:
                links.append(ArduPilotLink(world, vehicle=name, instance=ardupilot[name]))
        return AutopilotFleet(links)

    @property
    def autopilots(self) -> str:
        """The autopilots its links speak to, for the logs: "PX4", "ArduPilot" or "PX4 and ArduPilot"."""
        names = list(dict.fromkeys(link.autopilot for link in self.links))  # type: ignore[attr-defined]
        return " and ".join(names)

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
            f"{link.scheme}://{link.cfg.host}:{link.port} ({link.vehicle.name})"  # type: ignore[attr-defined]
            for link in self.links
        )

    def serve_once(
        self, timeout: float, lock: AbstractContextManager[Any] | None = None
    ) -> StepResult | None:
        """Serve every link once (at most ``timeout`` s): the step result when the world stepped."""
        return serve_links(self.links, timeout, lock)

    def take_events(self) -> list[Any]:
        return [e for link in self.links for e in link.take_events()]  # type: ignore[attr-defined]

    def close(self) -> None:
        for link in self.links:
            link.close()  # type: ignore[attr-defined]


#: the type a runtime holds: links of any autopilot
Fleet = AutopilotFleet[Any]
