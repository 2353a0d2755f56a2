"""One daemon thread running blocking jobs in order (GL rendering, Zenoh session calls).

Unlike asyncio's default executor or a ThreadPoolExecutor, nothing waits for it when the process ends, so a
render or a Zenoh call in progress never holds up Ctrl-C or SIGTERM.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any


class DaemonWorker:
    """Runs ``submit``-ted callables one at a time on a daemon thread; each returns a Future."""

    def __init__(self, name: str) -> None:
        self._todo: queue.Queue[tuple[Future[Any], Callable[..., Any], tuple[Any, ...]] | None]
        self._todo = queue.Queue()
        self._thread = threading.Thread(target=self._work, daemon=True, name=name)
        self._thread.start()

    def _work(self) -> None:
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
