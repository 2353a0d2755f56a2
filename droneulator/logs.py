"""One log line per burst of a repeating message, for whatever can repeat at a physics step's rate; and
whole lines on the terminal from many threads (:func:`say`).

A PX4 sending garbage 250 times a second, or a ROS topic streaming commands the simulator refuses,
must not flood the log; but the first occurrence is worth a full line, and how many followed is worth
knowing.
"""

from __future__ import annotations

import logging
import math
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TextIO

_SAYING = threading.Lock()


def say(text: str, file: TextIO | None = None) -> None:
    """Print ``text`` as a whole line (one write of the text and its newline, then a flush, under one lock):
    ``print`` writes the two apart, so a line another thread printed meanwhile ran into it (``[dynamics] ...
    connection openUI: http://...`` when a run's relayed output met its ``UI:`` line)."""
    out = sys.stdout if file is None else file
    with _SAYING:
        out.write(text + "\n")
        out.flush()


@dataclass
class _Burst:
    last: float  # monotonic time of the last occurrence
    reported: float  # ... of the last line logged
    summary: str  # "{n}" is replaced by the count
    level: int
    count: int = 0


class LogThrottle:
    """Log a message at once, then only count its repeats while they keep coming.

    A burst of ``key`` lasts while repeats arrive within ``gap`` seconds of each other. Its count is logged
    (the ``summary`` given with the first occurrence, ``{n}`` replaced) when the burst ends: at the next
    occurrence after a gap, on :meth:`end`, or, with ``one_at_a_time``, as soon as another key of its group
    starts a burst (``group(key)``; every key one group by default: e.g. a topic's rejections, whose code
    changed, while another topic's burst, interleaved with it, goes on). With ``period`` a burst that never
    ends also logs its count every ``period`` seconds.
    """

    def __init__(
        self,
        logger: logging.Logger,
        gap: float = 1.0,
        period: float | None = None,
        one_at_a_time: bool = False,
        group: Callable[[Any], Any] = lambda key: None,
    ) -> None:
        self.logger = logger
        self.gap = gap
        self.period = math.inf if period is None else period
        self.one_at_a_time = one_at_a_time
        self.group = group
        self._bursts: dict[Any, _Burst] = {}
        self._lock = threading.Lock()

    def log(self, key: Any, level: int, msg: str, *args: Any, summary: str | None = None) -> None:
        """One occurrence of ``key``: logged, or counted while its burst lasts."""
        now = time.monotonic()
        summary = summary or f"{msg % args if args else msg} ({{n}} more since the last report)"
        lines: list[tuple[int, str]] = []
        with self._lock:
            burst = self._bursts.get(key)
            if burst is not None and now - burst.last < self.gap:
                burst.count += 1
                burst.last = now
                if now - burst.reported >= self.period:
                    lines.append((burst.level, burst.summary.replace("{n}", str(burst.count))))
                    burst.count, burst.reported = 0, now
            else:
                mine = self.group(key)
                ended = [k for k in self._bursts
                         if k == key or (self.one_at_a_time and self.group(k) == mine)]  # fmt: skip
                lines += self._close(ended)
                self._bursts[key] = _Burst(now, now, summary, level)
                lines.append((level, msg % args if args else msg))
        for lvl, line in lines:
            self.logger.log(lvl, "%s", line)

    def error(self, key: Any, msg: str, *args: Any) -> None:
        self.log(key, logging.ERROR, msg, *args)

    def warning(self, key: Any, msg: str, *args: Any) -> None:
        self.log(key, logging.WARNING, msg, *args)

    def end(self) -> None:
        """Every burst is over: log what each left uncounted."""
        with self._lock:
            lines = self._close(list(self._bursts))
        for lvl, line in lines:
            self.logger.log(lvl, "%s", line)

    def _close(self, keys: list[Any]) -> list[tuple[int, str]]:
        out = []
        for k in keys:
            burst = self._bursts.pop(k)
            if burst.count:
                out.append((burst.level, burst.summary.replace("{n}", str(burst.count))))
        return out
