"""Threads for blocking work beside an asyncio loop or a simulation: a daemon thread running jobs in
order (the API's commands waiting for the simulation lock, the UI's GL rendering and Zenoh calls),
a lower scheduling priority for threads that must only take the CPU the simulation leaves, and OpenMP
threads that sleep between the compiled kernels' parallel regions.

Unlike asyncio's default executor or a ThreadPoolExecutor, nothing waits for a :class:`DaemonWorker` when
the process ends, so a job in progress never holds up Ctrl-C or SIGTERM.
"""

from __future__ import annotations

import contextlib
import os
import queue
import threading
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any


def sleeping_openmp_threads() -> None:
    """Make numba's OpenMP threads (GNU libgomp: the physics and the ray cast) sleep as soon as a parallel
    region ends instead of spinning 300,000 turns first (``OMP_WAIT_POLICY=PASSIVE``), unless the
    environment sets a policy. Measured no slower on an idle machine, 2.3 to 4.8 times the agent-steps
    beside another job and 3.5 to 4.4 with a core kept busy as well (docs/rl.md, "Measured: many worlds
    of many agents"). libgomp reads it once, when it loads: the package calls this on import."""
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def lower_priority(nice: int) -> None:
    """Raise the calling thread's nice value by ``nice`` (Linux schedules threads one by one; threads it
    starts later, such as a Zenoh session's, inherit it). The UI then takes the CPU the simulation leaves
    idle: on a machine whose cores are all busy, the page's images fall behind (and are counted as
    dropped) instead of the simulation slowing down. Ignored where the OS refuses."""
    if nice > 0 and hasattr(os, "setpriority"):
        with contextlib.suppress(OSError):
            tid = threading.get_native_id()
            os.setpriority(os.PRIO_PROCESS, tid, min(19, os.getpriority(os.PRIO_PROCESS, tid) + nice))


class DaemonWorker:
    """Runs ``submit``-ted callables one at a time on a daemon thread; each returns a Future
    (``asyncio.wrap_future`` makes it awaitable)."""

    def __init__(self, name: str, nice: int = 0) -> None:
        self._todo: queue.Queue[tuple[Future[Any], Callable[..., Any], tuple[Any, ...]] | None]
        self._todo = queue.Queue()
        self._nice = nice
        self._thread = threading.Thread(target=self._work, daemon=True, name=name)
        self._thread.start()

    def _work(self) -> None:
        lower_priority(self._nice)
        while (job := self._todo.get()) is not None:
            future, fn, args = job
            if not future.set_running_or_notify_cancel():
                continue
            try:
                future.set_result(fn(*args))
            except BaseException as exc:
                future.set_exception(exc)

    def submit(self, fn: Callable[..., Any], *args: Any) -> Future[Any]:
        future: Future[Any] = Future()
        self._todo.put((future, fn, args))
        return future

    def close(self) -> None:
        """End the thread after the jobs already queued (it is a daemon: exit does not wait for it)."""
        self._todo.put(None)
