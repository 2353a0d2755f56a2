"""The one command path: every command source (WebSocket API, ROS topics, the planner, the browser
UI, and PX4's ownership of the vehicle) reaches the simulator through :class:`CommandPath`.

It applies the same rules to all of them: arguments validated against the op table
(:data:`~droneulator.commands.ops.OPS`), flight commands refused with ``flight_locked`` while another
controller (PX4) is in control, and every simulator op run while holding the simulation lock, so a
command never interleaves with a physics step. Sources that have nobody to answer (ROS topics) have
their rejections logged, once per burst, with the error code.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Collection, Mapping
from contextlib import AbstractContextManager
from typing import Any

from droneulator.commands.ops import (
    OPS,
    ExtraOp,
    Request,
    RequestError,
    error_reply,
    execute,
    make_request,
)
from droneulator.commands.surface import CommandedWorld
from droneulator.logs import LogThrottle

log = logging.getLogger("droneulator.commands")

#: a rejection of the same (source, op, code) within this many seconds of the last one continues a burst
BURST_GAP_S = 2.0
#: the stepping loop lets waiting commands go first for at most this long (wall s) before it steps anyway
LOOP_YIELD_S = 1.0


class SimLock:
    """The simulation lock, fair to commands.

    The stepping loop takes it hundreds of times a second and a CPython lock is handed to no one in
    particular when released: a command waiting for it waited while the loop took it again and again (a
    takeoff asked at t = 0 of a lockstep run ran at t = 3.5 s; on a loaded machine the bundle's demo gave
    up after 30 s). Commands take it with ``with lock:``; the stepping loop with ``with lock.loop:``,
    which first lets every command already waiting have it.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._queue = threading.Condition(threading.Lock())
        self._waiting = 0
        #: the stepping loop's side of the lock (a context manager)
        self.loop = _LoopSide(self)

    def __enter__(self) -> SimLock:
        with self._queue:
            self._waiting += 1
        try:
            self._lock.acquire()
        finally:
            with self._queue:
                self._waiting -= 1
                if not self._waiting:
                    self._queue.notify_all()
        return self

    def __exit__(self, *_exc: object) -> None:
        self._lock.release()


class _LoopSide:
    """``with sim_lock.loop:``: the lock, once the commands waiting for it have had it."""

    def __init__(self, owner: SimLock) -> None:
        self._owner = owner

    def __enter__(self) -> None:
        o = self._owner
        if o._waiting:
            with o._queue:
                o._queue.wait_for(lambda: not o._waiting, timeout=LOOP_YIELD_S)
        o._lock.acquire()

    def __exit__(self, *_exc: object) -> None:
        self._owner._lock.release()


class CommandPath:
    """Validation, flight lock and simulation lock for every command source (see the module docstring).

    ``sim`` is the world the ops run on (:class:`~droneulator.commands.surface.CommandedWorld`).
    """

    def __init__(self, sim: CommandedWorld, lock: AbstractContextManager[Any] | None = None) -> None:
        self.sim = sim
        #: the simulation lock (a :class:`SimLock` unless given): commands hold it while they run
        self.lock = lock if lock is not None else SimLock()
        #: vehicle name (None: every vehicle) -> (reason, the ops refused; None: every flight op)
        self._locks: dict[str | None, tuple[str, frozenset[str] | None]] = {}
        #: one line per burst of the same (source, op, code) rejection, then how many followed; a source's new
        #: code ends its burst at once, another source's rejections (interleaved with it) do not
        self._rejections = LogThrottle(log, gap=BURST_GAP_S, one_at_a_time=True, group=lambda key: key[0])

    # ------------------------------------------------------------------ flight lock
    def refuse_flight(
        self, reason: str, ops: Collection[str] | None = None, vehicle: str | None = None
    ) -> None:
        """Answer flight commands (all, or only ``ops``) to ``vehicle`` (None: to every vehicle) with
        ``flight_locked`` and ``reason`` until :meth:`allow_flight`. ``reset`` moves every vehicle, so it
        is refused while any vehicle's lock covers it."""
        if not reason:
            raise ValueError("refuse_flight needs a reason for the clients")
        unknown = set(ops or ()) - {name for name, op in OPS.items() if op.flight}
        if unknown:
            raise ValueError(f"not flight ops: {', '.join(sorted(unknown))}")
        if vehicle is not None:
            self.sim.vehicle(vehicle)  # a CommandError for an unknown name
        self._locks[vehicle] = (reason, None if ops is None else frozenset(ops))

    def allow_flight(self, vehicle: str | None = None) -> None:
        """Lift the lock of ``vehicle`` (None: every lock)."""
        if vehicle is None:
            self._locks.clear()
        else:
            self._locks.pop(vehicle, None)

    @property
    def flight_locked(self) -> str | None:
        """The reason of a lock on every vehicle or, failing that, on the first vehicle; or None."""
        return self.flight_locked_for(None)

    def flight_locked_for(self, vehicle: str | None) -> str | None:
        """The reason ``vehicle``'s flight commands (None: the first vehicle's) are refused, or None."""
        name = self.sim.vehicle(vehicle).name
        lock = self._locks.get(None) or self._locks.get(name)
        return None if lock is None else lock[0]

    def _refusal(self, request: Request) -> str | None:
        """The lock reason that refuses ``request`` (a flight op), or None."""
        if request.op == "reset":
            covering = [reason for reason, ops in self._locks.values() if ops is None or "reset" in ops]
            return covering[0] if covering else None
        name = request.args.get("vehicle")
        if name is not None and name not in self.sim.vehicles:
            return None  # the op answers the unknown name
        name = name or self.sim.vehicle().name
        for key in (None, name):
            lock = self._locks.get(key)
            if lock is not None and (lock[1] is None or request.op in lock[1]):
                return lock[0]
        return None

    # ------------------------------------------------------------------ execution
    def execute(
        self,
        request: Request,
        extra_ops: Mapping[str, ExtraOp] | None = None,
        closing: threading.Event | None = None,
    ) -> dict[str, Any]:
        """Run a validated request and return its reply (never raises).

        Extra (runtime) ops run without the simulation lock; table ops marked ``locked`` hold it.
        A command still waiting for the lock when ``closing`` is set is answered, not run.
        """
        if extra_ops and request.op in extra_ops:
            return execute(None, request, extra_ops)
        op = OPS[request.op]
        if not op.locked:
            return execute(self.sim, request)
        with self.lock:
            if closing is not None and closing.is_set():
                return error_reply(request.id, "internal_error", "the server is shutting down")
            refused = self._refusal(request) if op.flight else None
            return execute(self.sim, request, flight_locked=refused)

    def submit(self, source: str, op: str, args: Mapping[str, Any]) -> dict[str, Any]:
        """Validate and run ``op`` from a source that has no client to answer (e.g. ``"ROS cmd_vel"``).

        Returns the reply; a rejection is logged once per burst with its error code.
        """
        try:
            reply = self.execute(make_request(op, args))
        except RequestError as e:
            reply = error_reply(None, e.code, e.message)
        if reply["ok"]:
            self._rejections.end()
        else:
            self.reject(source, op, reply["error"]["code"], reply["error"]["message"])
        return reply

    def reject(self, source: str, op: str, code: str, message: str) -> None:
        """Record a command a source refused before submitting it (e.g. a goal in an unknown frame)."""
        self._rejections.log(
            (source, op, code),
            logging.WARNING,
            "%s %s command rejected (%s): %s",
            source,
            op,
            code,
            message,
            summary=f"{{n}} more {source} {op} commands rejected ({code})",
        )
