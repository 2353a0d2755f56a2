"""The latency log (``bridge.latency_log``): when each published message left, for ``benchmarks/latency.py``.

One line per message, ``<stream> <stamp ns> <wall ns>``: the dynamics server writes its odometry
(``odom``, timed from the end of the physics step that produced it), the bridge each image stream. Both
processes append to the same file, a line at a time.
"""

from __future__ import annotations

import time
from pathlib import Path

from droneulator.config import SimConfig


class LatencyLog:
    """An open latency log; :meth:`of` gives None when the run keeps none."""

    def __init__(self, path: str | Path) -> None:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        self._file = open(path, "a", buffering=1)  # noqa: SIM115  (one write a line)

    @classmethod
    def of(cls, cfg: SimConfig) -> LatencyLog | None:
        return cls(cfg.bridge.latency_log) if cfg.bridge.latency_log else None

    def mark(self, stream: str, stamp_ns: int, wall_ns: int | None = None) -> None:
        """``stream``'s message of ``stamp_ns`` left at ``wall_ns`` (default: now)."""
        self._file.write(f"{stream} {stamp_ns} {time.time_ns() if wall_ns is None else wall_ns}\n")

    def close(self) -> None:
        self._file.close()
