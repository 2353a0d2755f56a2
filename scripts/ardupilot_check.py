"""Fly a real ArduCopter SITL on Droneulator's ArduPilot link and report what it did (docs/ardupilot.md).

    python scripts/ardupilot_check.py --arducopter $AP_WORK/src/build/sitl/bin/arducopter \\
        --defaults $AP_WORK/src/Tools/autotest/default_params [--alt 5] [--no-fly] [--run] [--out FILE]

Without ``--run``: a world in this process (no renderer) with its first vehicle on an ArduPilotLink
(UDP 9002 + 10 I). With ``--run``: ``droneulator run --ardupilot`` (renderer, bridge, API; the truth is
read over the WebSocket API). Then starts ``arducopter --model JSON`` in a fresh working directory with
``--home`` at the site origin and, over MAVLink (TCP 5760 + 10 I, pymavlink), waits until ArduPilot's
pre-arm checks pass and its EKF uses GPS, collecting every ``PreArm:`` text; then (unless
``--no-fly``) GUIDED, arm, take off to ``--alt`` m, hold 5 s, LAND, wait for the disarm, comparing
ArduPilot's EKF position (LOCAL_POSITION_NED, from the EKF origin) with the truth (the vehicle's
position from where it armed). Prints (or writes to ``--out``) one JSON report.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from pymavlink import mavutil

from droneulator.ardupilot import ArduPilotLink
from droneulator.config import SimConfig, load_config
from droneulator.frames import enu_to_ned
from droneulator.world import World


class Served:
    """The link served on a thread of this process; the world steps only on ArduPilot's frames."""

    def __init__(self, world: World, instance: int) -> None:
        self.world, self.lock = world, threading.Lock()
        self.link = ArduPilotLink(world, instance=instance)
        self.link.start()
        self.stop = threading.Event()
        self.events: list[Any] = []
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self.stop.is_set():
            self.link.serve_once(0.01, self.lock)
            self.events.extend(self.link.take_events())

    def truth_ned(self) -> np.ndarray:
        with self.lock:
            return enu_to_ned(self.world.vehicle().state.position)

    def stats(self) -> dict[str, Any]:
        return {"frames": self.link.frames, "resent": self.link.resent}

    def close(self) -> list[str]:
        self.stop.set()
        self.thread.join(5)
        self.link.close()
        self.world.close()
        return [e.type for e in self.events]


class ThroughRun:
    """``droneulator run --ardupilot``; the truth from the WebSocket API's state."""

    def __init__(self, cfg: SimConfig, instance: int) -> None:
        from droneulator.runtime.launch import launch_run

        self.run = launch_run(cfg, ["--ardupilot-instance", str(instance)], start_timeout=180)
        self.client = self.run.client()

    def truth_ned(self) -> np.ndarray:
        return enu_to_ned(np.array(self.client.state()["position"], dtype=float))

    def stats(self) -> dict[str, Any]:
        return {"t_s": self.client.state()["t_ns"] / 1e9}

    def close(self) -> list[str]:
        lines = [line for line in self.run.log.lines() if "ArduPilot" in line]
        self.client.close()
        self.run.stop()
        return lines


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--arducopter", required=True, help="build/sitl/bin/arducopter")
    ap.add_argument("--defaults", required=True, help="the folder of copter.parm and copter-X.parm")
    ap.add_argument("--instance", type=int, default=0)
    ap.add_argument("--alt", type=float, default=5.0)
    ap.add_argument("--boot-timeout", type=float, default=120.0, help="wall s to become armable")
    ap.add_argument("--no-fly", action="store_true")
    ap.add_argument("--log", default=None, help="write ArduPilot's console here")
    ap.add_argument("--run", action="store_true", help="through droneulator run --ardupilot (renderer, API)")
    ap.add_argument("--out", default=None, help="write the JSON report here")
    args = ap.parse_args()

    cfg = load_config(overrides=["vehicle.control_hz=1200", "vehicle.params=px4_quadx"])
    if args.run:
        sim: Served | ThroughRun = ThroughRun(cfg, args.instance)
    else:
        sim = Served(World(cfg, scene="default", render=False), args.instance)
    lat, lon, alt = cfg.site.geodetic
    workdir = tempfile.mkdtemp(prefix="arducopter-")
    defaults = ",".join(str(Path(args.defaults) / f) for f in ("copter.parm", "copter-X.parm"))
    cmd = [
        os.path.abspath(args.arducopter), "--model", "JSON:127.0.0.1", "--speedup", "1",
        "-I", str(args.instance), "-w", "--serial0", "tcp:0", "--home", f"{lat},{lon},{alt},0",
        "--defaults", defaults,
    ]  # fmt: skip
    console = open(args.log or os.devnull, "w")  # noqa: SIM115 - lives as long as the process
    proc = subprocess.Popen(cmd, cwd=workdir, stdout=console, stderr=subprocess.STDOUT)
    report: dict[str, Any] = {"command": " ".join(cmd)}
    try:
        mav = mavutil.mavlink_connection(f"tcp:127.0.0.1:{5760 + 10 * args.instance}", source_system=255)
        mav.wait_heartbeat(timeout=60)
        mav.mav.request_data_stream_send(mav.target_system, mav.target_component, 0, 10, 1)
        t0 = time.monotonic()
        texts: list[str] = []
        armable = None
        while time.monotonic() - t0 < args.boot_timeout:
            msg = mav.recv_match(type=["STATUSTEXT", "SYS_STATUS"], blocking=True, timeout=1)
            if msg is None:
                continue
            if msg.get_type() == "STATUSTEXT":
                texts.append(msg.text)
            elif msg.onboard_control_sensors_health & mavutil.mavlink.MAV_SYS_STATUS_PREARM_CHECK and any(
                "is using GPS" in t for t in texts
            ):  # pre-arm checks pass and the EKF has a position (GUIDED needs one)
                armable = time.monotonic() - t0
                break
        report.update(
            armable_after_wall_s=None if armable is None else round(armable, 1),
            prearm_texts=sorted({t for t in texts if "PreArm" in t}),
            texts=texts[:40],
            **sim.stats(),
        )
        if armable is not None and not args.no_fly:
            report["flight"] = fly(mav, sim, args.alt)
    finally:
        proc.terminate()
        proc.wait(10)
        report["events"] = sim.close()
    text = json.dumps(report, indent=1)
    if args.out:
        Path(args.out).write_text(text + "\n")
    else:
        print(text)
    return 0


def fly(mav: Any, served: Served | ThroughRun, alt: float) -> dict[str, Any]:
    """GUIDED takeoff to ``alt``, 5 s hold, LAND; EKF (LOCAL_POSITION_NED) against the truth."""
    out: dict[str, Any] = {}
    mav.set_mode("GUIDED")
    home = served.truth_ned()
    mav.arducopter_arm()
    end = time.monotonic() + 20
    while not mav.motors_armed():
        msg = mav.recv_match(type=["HEARTBEAT", "STATUSTEXT"], blocking=True, timeout=1)
        if msg is not None and msg.get_type() == "STATUSTEXT":
            out.setdefault("texts", []).append(msg.text)
        if time.monotonic() > end:
            out["armed"] = False
            return out
    out["armed"] = True
    mav.mav.command_long_send(mav.target_system, mav.target_component, 22, 0, 0, 0, 0, 0, 0, 0, alt)
    samples: list[tuple[float, np.ndarray, np.ndarray]] = []
    t0 = time.monotonic()
    phase, hold_until = "climb", None
    while time.monotonic() - t0 < 120:
        msg = mav.recv_match(type=["LOCAL_POSITION_NED", "STATUSTEXT"], blocking=True, timeout=1)
        if msg is None:
            continue
        if msg.get_type() == "STATUSTEXT":
            out.setdefault("texts", []).append(msg.text)
            continue
        ekf = np.array([msg.x, msg.y, msg.z])
        truth = served.truth_ned() - home
        samples.append((time.monotonic() - t0, ekf, truth))
        if phase == "climb" and -truth[2] > alt - 0.3:
            phase, hold_until = "hold", time.monotonic() + 5.0
            out["climb_wall_s"] = round(time.monotonic() - t0, 1)
        elif phase == "hold" and hold_until is not None and time.monotonic() > hold_until:
            hold = [(e, t) for _, e, t in samples if -t[2] > alt - 0.5]
            errs = np.array([np.linalg.norm(e - t) for e, t in hold])
            out["hold_alt_truth_m"] = round(float(np.mean([-t[2] for _, t in hold])), 3)
            out["hold_alt_ekf_m"] = round(float(np.mean([-e[2] for e, _ in hold])), 3)
            out["ekf_vs_truth_m"] = {"mean": round(float(errs.mean()), 3), "max": round(float(errs.max()), 3)}
            mav.set_mode("LAND")
            phase = "land"
        elif phase == "land" and not mav.motors_armed():
            out["landed_alt_truth_m"] = round(float(-truth[2]), 3)
            out["disarmed_after_wall_s"] = round(time.monotonic() - t0, 1)
            break
    errs_all = np.array([np.linalg.norm(e - t) for _, e, t in samples]) if samples else np.zeros(1)
    out["ekf_vs_truth_whole_flight_m"] = {
        "mean": round(float(errs_all.mean()), 3),
        "max": round(float(errs_all.max()), 3),
    }
    out["max_alt_truth_m"] = round(float(max(-t[2] for _, _, t in samples)), 3) if samples else None
    out["phase_reached"] = phase
    return out


if __name__ == "__main__":
    sys.exit(main())
