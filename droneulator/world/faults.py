"""The world's faults (docs/faults.md): which are active on which vehicle, when each starts and ends, and
what each does to the world.

Faults come from the config's schedule (``faults``, each ``at`` s after every reset), the ``fault`` op
and the ``/<ns>/fault`` topic (at once). Each starts with a ``fault_started`` event and ends with a
``fault_ended`` one (its ``duration`` run out, or cleared by ``fault_clear``), both carrying its
``id``, ``kind``, vehicle and parameters. A reset ends every fault without events and arms the schedule
again: faults belong to an episode.

Whenever the set changes the board writes its effects again, from scratch: each rotor fault's
efficiency into the world's ``rotor_efficiency`` rows of the first world (the compiled physics step
scales that rotor's thrust and moments), each sensor fault into its vehicle's sensor suite
(:mod:`droneulator.sensors.faults`); the camera dropouts and link cuts are asked for by the world's
camera schedule and the command path.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from droneulator.config.faults import FaultSpec
from droneulator.controllers.flight import Event

if TYPE_CHECKING:
    from droneulator.world.world import World

NS = 1_000_000_000
#: the kinds that act on the sensors (the others act on the rotors, the cameras or the command link)
SENSOR_KINDS = frozenset({"gps_loss", "gps_jamming", "gps_spoofing", "imu_bias", "baro_drift",
                          "mag_interference"})  # fmt: skip


@dataclass
class ActiveFault:
    """A fault in effect: its ``id`` (counting from 1 per world), its spec (``vehicle`` named), when it
    started and when it ends (sim ns since the reset; None: until cleared)."""

    id: int
    spec: FaultSpec
    start_ns: int
    end_ns: int | None

    def describe(self) -> dict[str, Any]:
        """Its plain JSON form: events, a vehicle's state, the op's reply."""
        s = self.spec
        return {"id": self.id, "kind": s.kind, "vehicle": s.vehicle, "start": self.start_ns / NS,
                "duration": s.duration, **s.params()}  # fmt: skip


class FaultBoard:
    """The faults of ``world``'s first world (the one its vehicles' handles fly)."""

    def __init__(self, world: World) -> None:
        self.world = world
        self.active: dict[int, ActiveFault] = {}
        self._ids = 0
        #: the config's faults not started yet this episode, earliest first
        self._schedule: list[FaultSpec] = []
        #: events of faults started or ended between steps (the op), emitted by the next step
        self._queued: list[Event] = []
        #: vehicles whose rotor efficiency this board set, with the factors it applied (so it gives back only
        #: those rows, and tells its zeros from a rotor lost on wood)
        self._rotor_rows: dict[int, np.ndarray] = {}
        self.reset()

    def reset(self) -> None:
        """End every fault (no events: the episode they were in is over) and arm the config's schedule."""
        had = bool(self.active)
        self.active.clear()
        self._queued.clear()
        first = next(iter(self.world.vehicles))
        self._schedule = sorted((dataclasses.replace(f, vehicle=f.vehicle or first)
                                 for f in self.world.config.faults), key=lambda f: f.at)  # fmt: skip
        if had or self._rotor_rows:
            self._apply()

    @property
    def idle(self) -> bool:
        """Nothing to do at a step: no fault active, scheduled or with an event waiting."""
        return not (self.active or self._schedule or self._queued)

    def inject(self, spec: FaultSpec) -> ActiveFault:
        """Start ``spec`` now (its ``at`` is ignored); its event comes with the next step. An unknown
        vehicle is a CommandError."""
        name = self.world.vehicle(spec.vehicle).name
        fault = self._start(dataclasses.replace(spec, vehicle=name), self.world.t_ns)
        self._queued.append(self._event("fault_started", fault, self.world.t))
        self._apply()
        return fault

    def clear(
        self, vehicle: str | None = None, kind: str | None = None, fault_id: int | None = None
    ) -> list[int]:
        """End the active faults that match (every one for no filter); returns their ids. Their
        ``fault_ended`` events come with the next step."""
        name = None if vehicle is None else self.world.vehicle(vehicle).name
        gone = [
            f
            for f in self.active.values()
            if (name is None or f.spec.vehicle == name)
            and (kind is None or f.spec.kind == kind)
            and (fault_id is None or f.id == fault_id)
        ]
        for f in gone:
            del self.active[f.id]
            self._queued.append(self._event("fault_ended", f, self.world.t, "cleared"))
        if gone:
            self._apply()
        return [f.id for f in gone]

    def update(self) -> list[Event]:
        """At the start of a control period: end the faults whose time is up, start the scheduled ones due;
        returns their events (and those queued since the last step)."""
        now = self.world.t_ns
        events, self._queued = self._queued, []
        changed = bool(events)
        for f in list(self.active.values()):
            if f.end_ns is not None and f.end_ns <= now:
                del self.active[f.id]
                events.append(self._event("fault_ended", f, f.end_ns / NS, "expired"))
                changed = True
        while self._schedule and round(self._schedule[0].at * NS) <= now:
            spec = self._schedule.pop(0)
            fault = self._start(spec, round(spec.at * NS))
            events.append(self._event("fault_started", fault, fault.start_ns / NS))
            changed = True
        if changed:
            self._apply()
        return events

    def of(self, vehicle: str) -> list[dict[str, Any]]:
        """The faults active on ``vehicle``, described (its state's ``faults``)."""
        return [f.describe() for f in self.active.values() if f.spec.vehicle == vehicle]

    def has(self, vehicle: str, kind: str) -> bool:
        """Whether a ``kind`` fault is active on ``vehicle``."""
        return any(f.spec.vehicle == vehicle and f.spec.kind == kind for f in self.active.values())

    # ------------------------------------------------------------------ internals
    def _start(self, spec: FaultSpec, start_ns: int) -> ActiveFault:
        self._ids += 1
        end = None if spec.duration is None else start_ns + round(spec.duration * NS)
        fault = ActiveFault(self._ids, spec, start_ns, end)
        self.active[fault.id] = fault
        return fault

    @staticmethod
    def _event(kind: str, fault: ActiveFault, t: float, why: str | None = None) -> Event:
        data = fault.describe()
        if why is not None:
            data["reason"] = why
        return Event(kind, t, data, fault.spec.vehicle)

    def _apply(self) -> None:
        """Write every active fault's effect, from scratch."""
        world = self.world
        eff = world.rotor_efficiency[0]
        for i, applied in self._rotor_rows.items():  # give back its rows; a rotor lost on wood stays lost
            eff[i] = np.where((eff[i] == 0.0) & (applied != 0.0), 0.0, 1.0)
        self._rotor_rows.clear()
        index = {name: i for i, name in enumerate(world.vehicles)}
        sensors: dict[str, list[tuple[FaultSpec, int]]] = {name: [] for name in world.vehicles}
        for f in self.active.values():
            s = f.spec
            assert s.vehicle is not None
            if s.kind == "rotor":
                assert s.rotor is not None and s.efficiency is not None
                i = index[s.vehicle]
                eff[i, s.rotor] *= s.efficiency
                self._rotor_rows.setdefault(i, np.ones(4))[s.rotor] *= s.efficiency
            elif s.kind in SENSOR_KINDS:
                sensors[s.vehicle].append((s, f.start_ns))
        for name, v in world.vehicles.items():
            v.rig.suite.faults.set(sensors[name])
