"""Shared helpers for the benchmark scripts: machine description and JSON output."""

from __future__ import annotations

import json
import os
import platform
import subprocess
import time
from pathlib import Path
from typing import Any

RESULTS = Path(__file__).resolve().parent / "results"


def machine() -> dict[str, Any]:
    return {
        "cpu_count": os.cpu_count(),
        "machine": platform.machine(),
        "python": platform.python_version(),
        "processor": platform.processor() or platform.machine(),
        "time": time.strftime("%Y-%m-%d %H:%M:%S"),
    }


def write(name: str, data: dict[str, Any], path: str | None = None) -> Path:
    out = Path(path) if path else RESULTS / f"{name}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"benchmark": name, "machine": machine(), **data}, indent=2))
    print(f"wrote {out}")
    return out


#: the processes of a ``droneulator run``, by module name
ROLES = ("dynamics_server", "render_server", "bridge")


def children(pid: int) -> dict[str, int]:
    """The pids of the run ``pid``'s children, by role (:data:`ROLES`), from ``ps``."""
    out = subprocess.run(["ps", "-o", "pid=,args=", "--ppid", str(pid)], capture_output=True, text=True)
    found = {}
    for line in out.stdout.splitlines():
        child, args = line.strip().split(None, 1)
        for role in ROLES:
            if f"droneulator.runtime.{role}" in args:
                found[role] = int(child)
    return found
