"""The one command path: every command source (WebSocket API, ROS topics, and later the planner and
the UI) reaches the simulator through :class:`CommandPath`.

It applies the same rules to all of them: arguments validated against the op table
(:data:`~droneulator.api.protocol.OPS`), flight commands refused with ``flight_locked`` while another
controller (PX4) is in control, and every simulator op run while holding the simulation lock, so a
command never interleaves with a physics step. Sources that have nobody to answer (ROS topics) have
their rejections logged, once per burst, with the error code.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Collection, Mapping
from contextlib import AbstractContextManager
from typing import TYPE_CHECKING, Any

from droneulator.api.protocol import (
    OPS,
    ExtraOp,
    Request,
    RequestError,
    error_reply,
    execute,
    make_request,
)

if TYPE_CHECKING:
    from droneulator.sim.simulator import Simulator

log = logging.getLogger("droneulator.commands")

#: a rejection of the same (source, op, code) within this many seconds of the last one continues a burst
BURST_GAP_S = 2.0


class _RejectionLog:
    """Log a rejected command once per burst: the first rejection in full, then a count when it ends."""

    def __init__(self, gap_s: float = BURST_GAP_S) -> None:
        self.gap_s = gap_s
        self._lock = threading.Lock()
        self._key: tuple[str, str, str] | None = None
        self._last = 0.0
        self._suppressed = 0

    def rejected(self, source: str, op: str, code: str, message: str) -> None:
        now = time.monotonic()
        with self._lock:
            key = (source, op, code)
            if key == self._key and now - self._last < self.gap_s:
                self._suppressed += 1
                self._last = now
                return
            self._flush()
            self._key, self._last = key, now
        log.warning("%s %s command rejected (%s): %s", source, op, code, message)

    def accepted(self) -> None:
        with self._lock:
            self._flush()
            self._key = None

    def _flush(self) -> None:
        if self._suppressed and self._key is not None:
            source, op, code = self._key
            log.warning("%d more %s %s commands rejected (%s)", self._suppressed, source, op, code)
        self._suppressed = 0


class CommandPath:
    """Validation, flight lock and simulation lock for every command source (see the module docstring)."""

    def __init__(self, sim: Simulator, lock: AbstractContextManager[Any] | None = None) -> None:
        self.sim = sim
        self.lock = lock if lock is not None else threading.Lock()
        self._flight_locked: str | None = None
        self._locked_ops: frozenset[str] | None = None  # None: every flight op
        self._rejections = _RejectionLog()

    # ------------------------------------------------------------------ flight lock
    def refuse_flight(self, reason: str, ops: Collection[str] | None = None) -> None:
        """Answer flight commands (all, or only ``ops``) with ``flight_locked`` and ``reason`` until
        :meth:`allow_flight`."""
        if not reason:
            raise ValueError("refuse_flight needs a reason for the clients")
        unknown = set(ops or ()) - {name for name, op in OPS.items() if op.flight}
        if unknown:
            raise ValueError(f"not flight ops: {', '.join(sorted(unknown))}")
        self._flight_locked = reason
        self._locked_ops = None if ops is None else frozenset(ops)

    def allow_flight(self) -> None:
        self._flight_locked = None
        self._locked_ops = None

    @property
    def flight_locked(self) -> str | None:
        """The reason flight commands are refused, or None."""
        return self._flight_locked

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
        if not OPS[request.op].locked:
            return execute(self.sim, request)
        with self.lock:
            if closing is not None and closing.is_set():
                return error_reply(request.id, "internal_error", "the server is shutting down")
            locked = self._locked_ops is None or request.op in self._locked_ops
            return execute(self.sim, request, flight_locked=self._flight_locked if locked else None)

    def submit(self, source: str, op: str, args: Mapping[str, Any]) -> dict[str, Any]:
        """Validate and run ``op`` from a source that has no client to answer (e.g. ``"ROS cmd_vel"``).

        Returns the reply; a rejection is logged once per burst with its error code.
        """
        try:
            reply = self.execute(make_request(op, args))
        except RequestError as e:
            reply = error_reply(None, e.code, e.message)
        if reply["ok"]:
            self._rejections.accepted()
        else:
            self.reject(source, op, reply["error"]["code"], reply["error"]["message"])
        return reply

    def reject(self, source: str, op: str, code: str, message: str) -> None:
        """Record a command a source refused before submitting it (e.g. a goal in an unknown frame)."""
        self._rejections.rejected(source, op, code, message)
