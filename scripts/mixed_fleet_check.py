"""Fly two real ArduCopters and one real PX4 at once in one ``droneulator run`` (a mixed fleet) and report
what they did (docs/ardupilot.md, "A mixed fleet").

    python scripts/mixed_fleet_check.py --arducopter $AP_WORK/src/build/sitl/bin/arducopter \\
        --defaults $AP_WORK/src/Tools/autotest/default_params \\
        --px4 $PX4_WORK/src/build/px4_sitl_default [--alt 5] [--leg 5] [--out FILE]

The run's vehicles: ``uav0`` and ``uav1`` on ArduCopter ``-I 0`` / ``-I 1`` (UDP 9002 / 9012, MAVLink
TCP 5760 / 5770), ``uav2`` on PX4 instance 2 (``px4 -i 2``: TCP 4562, MAVLink UDP 14542); the world at
1000 Hz (one ArduPilot frame a step, PX4's 250 Hz lockstep every 4th step), no cameras. Each autopilot
is flown over MAVLink (pymavlink) at the same time: take off to ``--alt`` m, hold, fly ``--leg`` m
north, hold, land, disarm (ArduPilot in GUIDED, PX4 with NAV_TAKEOFF, DO_REPOSITION and NAV_LAND). Its
own position estimate (LOCAL_POSITION_NED) is compared with the truth from the run's WebSocket API (the
vehicle's position from where it armed, NED). Prints (or writes to ``--out``) one JSON report with the
simulation speed against wall time.
"""

from __future__ import annotations

import argparse
import json
import math
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

sys.path.insert(0, str(Path(__file__).resolve().parent))
from ardupilot_check import ArduCopter  # noqa: E402 - the sibling script's SITL runner

from droneulator.config import VehicleSpec, load_config  # noqa: E402
from droneulator.frames import enu_to_ned  # noqa: E402
from droneulator.runtime.launch import launch_run  # noqa: E402

PX4_INSTANCE = 2
M_PER_DEG = 111_195.0


class Truth:
    """The run's truth, read over its WebSocket API (one client shared by the flights)."""

    def __init__(self, run: Any) -> None:
        self.client = run.client()
        self.lock = threading.Lock()

    def ned(self, vehicle: str) -> np.ndarray:
        with self.lock:
            return enu_to_ned(np.array(self.client.state(vehicle)["position"], dtype=float))

    def t(self) -> float:
        with self.lock:
            return float(self.client.state()["t_ns"]) / 1e9


class PX4:
    """``px4 -i N -d`` (airframe 10016, none_iris) in its own working directory; MAVLink on UDP 14540 + N."""

    def __init__(self, build: str, instance: int, log: str | None) -> None:
        build_dir = Path(build).resolve()
        env = {**os.environ, "PX4_SYS_AUTOSTART": "10016", "PX4_SIM_MODEL": "none_iris"}
        self.cmd = [str(build_dir / "bin" / "px4"), "-i", str(instance), "-d", str(build_dir / "etc")]
        out = open(log if log else os.devnull, "a")  # noqa: SIM115 - the process's
        self.proc = subprocess.Popen(
            self.cmd, cwd=tempfile.mkdtemp(prefix=f"px4-{instance}-"), env=env, stdout=out, stderr=out
        )
        self.mav = mavutil.mavlink_connection(f"udpin:127.0.0.1:{14540 + instance}", source_system=255)
        self.mav.wait_heartbeat(timeout=120)

    def setup(self, alt: float) -> None:
        """No RC and no ground station in SITL; take-off altitude ``alt``."""
        for name, value, kind in (
            ("NAV_RCL_ACT", 0, mavutil.mavlink.MAV_PARAM_TYPE_INT32),
            ("NAV_DLL_ACT", 0, mavutil.mavlink.MAV_PARAM_TYPE_INT32),
            ("COM_RC_IN_MODE", 4, mavutil.mavlink.MAV_PARAM_TYPE_INT32),
            ("MIS_TAKEOFF_ALT", alt, mavutil.mavlink.MAV_PARAM_TYPE_REAL32),
        ):
            self.mav.param_set_send(name, value, kind)
            time.sleep(0.2)

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
        self.mav.close()


def command(mav: Any, cmd: int, *params: float) -> None:
    p = [*params, *[0.0] * (7 - len(params))]
    mav.mav.command_long_send(mav.target_system, mav.target_component, cmd, 0, *p)


def fly(
    kind: str, mav: Any, name: str, truth: Truth, alt: float, leg: float, timeout: float
) -> dict[str, Any]:
    """Arm, take off to ``alt``, hold 3 s, ``leg`` m north, hold 3 s, land and disarm; the autopilot's
    LOCAL_POSITION_NED against the truth from where it armed."""
    out: dict[str, Any] = {"vehicle": name, "autopilot": kind}
    t_start = time.monotonic()
    texts: list[str] = []
    home = truth.ned(name)
    armed_at = None
    while time.monotonic() - t_start < timeout and armed_at is None:
        if kind == "ArduPilot":
            mav.set_mode("GUIDED")
            mav.arducopter_arm()
        else:
            command(mav, mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        end = time.monotonic() + 3
        while time.monotonic() < end:
            msg = mav.recv_match(type=["HEARTBEAT", "STATUSTEXT"], blocking=True, timeout=0.5)
            if msg is not None and msg.get_type() == "STATUSTEXT":
                texts.append(msg.text)
            if mav.motors_armed():
                armed_at = time.monotonic() - t_start
                break
    out["armed_after_wall_s"] = None if armed_at is None else round(armed_at, 1)
    if armed_at is None:
        out["texts"] = texts[-20:]
        return out
    home = truth.ned(name)
    if kind == "ArduPilot":
        command(mav, mavutil.mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, alt)
    else:
        nan = math.nan
        command(mav, mavutil.mavlink.MAV_CMD_NAV_TAKEOFF, -1, 0, 0, nan, nan, nan, nan)
    samples: list[tuple[str, np.ndarray, np.ndarray]] = []
    phase, until = "climb", 0.0
    global_pos: Any = None
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        msg = mav.recv_match(
            type=["LOCAL_POSITION_NED", "STATUSTEXT", "GLOBAL_POSITION_INT"], blocking=True, timeout=1
        )
        if msg is None:
            continue
        if msg.get_type() == "STATUSTEXT":
            texts.append(msg.text)
            continue
        if msg.get_type() == "GLOBAL_POSITION_INT":
            global_pos = msg
            continue
        est = np.array([msg.x, msg.y, msg.z])
        rel = truth.ned(name) - home
        samples.append((phase, est, rel))
        now = time.monotonic()
        if phase == "climb" and -rel[2] > alt - 0.3:
            phase, until = "hold", now + 3.0
            out["climb_wall_s"] = round(now - t0, 1)
        elif phase == "hold" and now > until:
            phase = "leg"
            target = est + np.array([leg, 0.0, 0.0])
            out["leg_from_estimate_ned"] = np.round(est, 3).tolist()
            if kind == "ArduPilot":
                mav.mav.set_position_target_local_ned_send(
                    0, mav.target_system, mav.target_component, mavutil.mavlink.MAV_FRAME_LOCAL_NED,
                    0b110111111000, target[0], target[1], -alt, 0, 0, 0, 0, 0, 0, 0, 0,
                )  # fmt: skip
            elif global_pos is not None:
                lat = global_pos.lat * 1e-7 + leg / M_PER_DEG
                mav.mav.command_int_send(
                    mav.target_system, mav.target_component, mavutil.mavlink.MAV_FRAME_GLOBAL,
                    mavutil.mavlink.MAV_CMD_DO_REPOSITION, 0, 0, -1, 1, 0, math.nan,
                    int(round(lat * 1e7)), global_pos.lon, global_pos.alt * 1e-3,
                )  # fmt: skip
            leg_t0 = now
        elif phase == "leg" and (abs(rel[0] - leg) < 0.3 or now - leg_t0 > 40):
            phase, until = "leg_hold", now + 3.0
            out["leg_wall_s"] = round(now - leg_t0, 1)
        elif phase == "leg_hold" and now > until:
            hold = [(e, r) for p, e, r in samples if p == "leg_hold"]
            errs = np.array([np.linalg.norm(e - r) for e, r in hold])
            out["leg_end_truth_ned"] = np.round(np.mean([r for _, r in hold], axis=0), 3).tolist()
            out["leg_end_estimate_ned"] = np.round(np.mean([e for e, _ in hold], axis=0), 3).tolist()
            out["leg_hold_estimate_vs_truth_m"] = {
                "mean": round(float(errs.mean()), 3), "max": round(float(errs.max()), 3)
            }  # fmt: skip
            if kind == "ArduPilot":
                mav.set_mode("LAND")
            else:
                command(mav, mavutil.mavlink.MAV_CMD_NAV_LAND, 0, 0, 0, *[math.nan] * 4)
            phase = "land"
        elif phase == "land" and not mav.motors_armed():
            out["landed_alt_truth_m"] = round(float(-rel[2]), 3)
            out["disarmed_after_wall_s"] = round(now - t0, 1)
            phase = "disarmed"
            break
    errs_all = np.array([np.linalg.norm(e - r) for _, e, r in samples]) if samples else np.zeros(1)
    out["estimate_vs_truth_whole_flight_m"] = {
        "mean": round(float(errs_all.mean()), 3), "max": round(float(errs_all.max()), 3)
    }  # fmt: skip
    out["max_alt_truth_m"] = round(float(max(-r[2] for _, _, r in samples)), 3) if samples else None
    out["phase_reached"] = phase
    out["texts"] = [t for t in texts if "PreArm" in t or "fail" in t.lower() or "error" in t.lower()][:20]
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--arducopter", required=True, help="build/sitl/bin/arducopter")
    ap.add_argument("--defaults", required=True, help="the folder of copter.parm and copter-X.parm")
    ap.add_argument(
        "--px4", default=None, help="PX4's build/px4_sitl_default folder (without: uav2's PX4 never connects)"
    )
    ap.add_argument("--alt", type=float, default=5.0)
    ap.add_argument("--leg", type=float, default=5.0)
    ap.add_argument("--timeout", type=float, default=300.0, help="wall s for each stage of a flight")
    ap.add_argument("--log", default=None, help="append the autopilots' consoles to LOG.<vehicle>")
    ap.add_argument("--out", default=None, help="write the JSON report here")
    args = ap.parse_args()

    cfg = load_config(overrides=["vehicle.control_hz=1000", "vehicle.params=px4_quadx"])
    cfg.vehicles = [
        VehicleSpec(name="uav0", controlled_by="ardupilot", cameras=[]),
        VehicleSpec(name="uav1", controlled_by="ardupilot", cameras=[]),
        VehicleSpec(name="uav2", controlled_by="px4", cameras=[]),
    ]
    report: dict[str, Any] = {}
    copters: list[ArduCopter] = []
    px4: PX4 | None = None
    run = launch_run(cfg, start_timeout=240)
    try:
        truth = Truth(run)
        ap_args = argparse.Namespace(arducopter=args.arducopter, defaults=args.defaults,
                                     log=f"{args.log}.ap" if args.log else None)  # fmt: skip
        copters = [ArduCopter(ap_args, k, cfg.site.geodetic) for k in range(2)]
        mavs = [("ArduPilot", copters[0].mav, "uav0"), ("ArduPilot", copters[1].mav, "uav1")]
        if args.px4:
            px4 = PX4(args.px4, PX4_INSTANCE, f"{args.log}.uav2" if args.log else None)
            px4.setup(args.alt)
            mavs.append(("PX4", px4.mav, "uav2"))
        report["commands"] = [" ".join(c.cmd) for c in copters] + ([" ".join(px4.cmd)] if px4 else [])
        report["boot"] = [c.wait_armable(args.timeout) for c in copters]
        wall0, sim0 = time.monotonic(), truth.t()
        flights: list[dict[str, Any]] = [{} for _ in mavs]

        def one(k: int) -> None:
            kind, mav, name = mavs[k]
            try:
                flights[k] = fly(kind, mav, name, truth, args.alt, args.leg, args.timeout)
            except Exception as exc:  # noqa: BLE001 - reported, the other flights go on
                flights[k] = {"vehicle": name, "error": repr(exc)}

        threads = [threading.Thread(target=one, args=(k,)) for k in range(len(mavs))]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        wall, sim = time.monotonic() - wall0, truth.t() - sim0
        report["flights"] = flights
        report["speed"] = {"sim_s": round(sim, 1), "wall_s": round(wall, 1), "factor": round(sim / wall, 3)}
    finally:
        for c in copters:
            c.close()
        if px4 is not None:
            px4.close()
        words = ("PX4", "ArduPilot", "ERROR", "WARNING")
        report["run_log"] = [line for line in run.log.lines() if any(w in line for w in words)][-60:]
        run.stop()
    text = json.dumps(report, indent=1)
    if args.out:
        Path(args.out).write_text(text + "\n")
    else:
        print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
