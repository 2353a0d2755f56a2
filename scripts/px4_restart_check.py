"""Start, kill and restart a real PX4 SITL against one world and report what its console says.

    python scripts/px4_restart_check.py --px4 $PX4_WORK/src/build/px4_sitl_default \\
        [--mode restart|late|fresh] [--instance 7] [--first-s 12] [--second-s 12]

``fresh``: PX4 connects to a world at t = 0 and runs ``--first-s`` wall seconds. ``restart``: the same,
then PX4 is SIGKILLed and a new PX4 connects to the running world (the issue-43 case). ``late``: the world
first runs 40 s of sim time without PX4, then a first PX4 connects (the clock jump alone, no restart).
Prints one JSON report: each PX4's preflight/health lines from its console, with the simulation time at
which it connected.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import tempfile
import threading
import time
from pathlib import Path

from droneulator.config import load_config
from droneulator.px4 import PX4Link
from droneulator.world import World

KEYS = ("Preflight", "power", "missing", "Ready for takeoff", "Simulator connected")


class PX4Proc:
    """``px4 -i N -d`` (airframe 10016) in a fresh working directory, its console in a file."""

    def __init__(self, build: Path, instance: int) -> None:
        self.dir = tempfile.mkdtemp(prefix=f"px4-restart-{instance}-")
        self.console = Path(self.dir) / "console.txt"
        env = {**os.environ, "PX4_SYS_AUTOSTART": "10016", "PX4_SIM_MODEL": "none_iris"}
        cmd = [str(build / "bin" / "px4"), "-i", str(instance), "-d", str(build / "etc")]
        with open(self.console, "w") as out:
            self.proc = subprocess.Popen(cmd, cwd=self.dir, env=env, stdout=out, stderr=out)

    def kill(self) -> None:
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait()

    def lines(self) -> list[str]:
        return [
            ln.strip()
            for ln in self.console.read_text(errors="replace").splitlines()
            if any(k in ln for k in KEYS)
        ]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--px4", required=True, type=Path, help="the px4_sitl_default build folder")
    ap.add_argument("--mode", choices=("restart", "late", "fresh"), default="restart")
    ap.add_argument("--instance", type=int, default=7)
    ap.add_argument("--first-s", type=float, default=12.0)
    ap.add_argument("--second-s", type=float, default=12.0)
    args = ap.parse_args()

    cfg = load_config(overrides=["vehicle.control_hz=250", "vehicle.params=px4_quadx"])
    world = World(cfg, scene="default", render=False)
    if args.mode == "late":
        while world.t < 40.0:
            world.step()
    lock = threading.Lock()
    stop = threading.Event()
    link = PX4Link(world, cfg.px4, instance=args.instance)
    link.start()

    def serve() -> None:
        while not stop.is_set():
            link.serve_once(0.05, lock)

    server = threading.Thread(target=serve, daemon=True)
    server.start()
    report: dict = {"mode": args.mode, "runs": []}
    runs = [args.first_s] + ([args.second_s] if args.mode == "restart" else [])
    for k, seconds in enumerate(runs):
        t0 = world.t
        px4 = PX4Proc(args.px4, args.instance)
        time.sleep(seconds)
        report["runs"].append({"run": k, "world_t_at_start_s": round(t0, 3), "console": px4.lines()})
        px4.kill()
        time.sleep(2.0)
    stop.set()
    server.join()
    link.close()
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
