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
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from pymavlink import mavutil

from droneulator.ardupilot import ArduPilotFleet
from droneulator.config import SimConfig, VehicleSpec, load_config
from droneulator.frames import enu_to_ned
from droneulator.world import World


class Served:
    """The links of a world's ArduPilot vehicles served on a thread of this process; the world steps on
    ArduPilot's frames and, while none is connected, on its own in real time (as the runtime does)."""

    def __init__(self, world: World) -> None:
        self.world, self.lock = world, threading.Lock()
        self.fleet = ArduPilotFleet.of(world)
        self.fleet.start()
        self.stop = threading.Event()
        self.events: list[Any] = []
        self.sim_events: list[Any] = []
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        n = max(1, round(0.01 * self.world.config.vehicle.control_hz))
        while not self.stop.is_set():
            res = self.fleet.serve_once(0.01, self.lock)
            if res is None and not self.fleet.connected:
                with self.lock:
                    res = self.world.step(n)
            if res is not None:
                self.sim_events.extend(res.events)
            self.events.extend(self.fleet.take_events())

    def truth_ned(self, k: int = 0) -> np.ndarray:
        with self.lock:
            return enu_to_ned(self.world.vehicle_list[k].state.position)

    def mode(self, k: int = 0) -> str:
        with self.lock:
            return self.world.vehicle_list[k].mode.value

    def stats(self) -> dict[str, Any]:
        return {
            "frames": [link.frames for link in self.fleet.links],
            "resent": [link.resent for link in self.fleet.links],
        }

    def close(self) -> list[str]:
        self.stop.set()
        self.thread.join(5)
        self.fleet.close()
        self.world.close()
        return [f"{e.vehicle} {e.type} {e.data}" if e.data else f"{e.vehicle} {e.type}" for e in self.events]


class ThroughRun:
    """``droneulator run --ardupilot``; the truth from the WebSocket API's state."""

    def __init__(self, cfg: SimConfig, instance: int) -> None:
        from droneulator.runtime.launch import launch_run

        self.run = launch_run(cfg, ["--ardupilot-instance", str(instance)], start_timeout=240)
        self.client = self.run.client()

    def truth_ned(self, k: int = 0) -> np.ndarray:
        return enu_to_ned(np.array(self.client.state()["position"], dtype=float))

    def stats(self) -> dict[str, Any]:
        return {"t_s": self.client.state()["t_ns"] / 1e9}

    def close(self) -> list[str]:
        lines = [line for line in self.run.log.lines() if "ArduPilot" in line]
        self.client.close()
        self.run.stop()
        return lines


class ArduCopter:
    """One ``arducopter --model JSON -I k`` in its own working directory; its MAVLink on TCP 5760 + 10 k."""

    def __init__(self, args: argparse.Namespace, k: int, site: tuple[float, float, float]) -> None:
        lat, lon, alt = site
        defaults = ",".join(str(Path(args.defaults) / f) for f in ("copter.parm", "copter-X.parm"))
        self.cmd = [
            os.path.abspath(args.arducopter), "--model", "JSON:127.0.0.1", "--speedup", "1", "-I", str(k),
            "--sysid", str(k + 1), "-w", "--serial0", "tcp:0", "--home", f"{lat},{lon},{alt},0",
            "--defaults", defaults,
        ]  # fmt: skip
        log = open(f"{args.log}.{k}" if args.log else os.devnull, "a")  # noqa: SIM115 - the process's
        self.proc = subprocess.Popen(
            self.cmd, cwd=tempfile.mkdtemp(prefix=f"arducopter{k}-"), stdout=log, stderr=log
        )
        self.mav = mavutil.mavlink_connection(f"tcp:127.0.0.1:{5760 + 10 * k}", source_system=255)
        self.mav.wait_heartbeat(timeout=60)
        self.mav.mav.request_data_stream_send(self.mav.target_system, self.mav.target_component, 0, 10, 1)

    def wait_armable(self, timeout: float) -> dict[str, Any]:
        """Until the pre-arm checks pass and the EKF uses GPS (GUIDED needs a position)."""
        t0 = time.monotonic()
        texts: list[str] = []
        armable = None
        while time.monotonic() - t0 < timeout:
            msg = self.mav.recv_match(type=["STATUSTEXT", "SYS_STATUS"], blocking=True, timeout=1)
            if msg is None:
                continue
            if msg.get_type() == "STATUSTEXT":
                texts.append(msg.text)
            elif msg.onboard_control_sensors_health & mavutil.mavlink.MAV_SYS_STATUS_PREARM_CHECK and any(
                "is using GPS" in t for t in texts
            ):
                armable = time.monotonic() - t0
                break
        return {
            "armable_after_wall_s": None if armable is None else round(armable, 1),
            "prearm_texts": sorted({t for t in texts if "PreArm" in t}),
            "texts": texts[:40],
        }

    def kill(self) -> None:
        self.proc.kill()
        self.proc.wait(10)

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            self.proc.wait(10)
        self.mav.close()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--arducopter", required=True, help="build/sitl/bin/arducopter")
    ap.add_argument("--defaults", required=True, help="the folder of copter.parm and copter-X.parm")
    ap.add_argument("--instance", type=int, default=0, help="with --run: the ArduPilot instance")
    ap.add_argument("--vehicles", type=int, default=1, help="in-process: this many vehicles, instance k each")
    ap.add_argument("--alt", type=float, default=5.0)
    ap.add_argument("--boot-timeout", type=float, default=120.0, help="wall s to become armable")
    ap.add_argument("--no-fly", action="store_true")
    ap.add_argument(
        "--kill-in-air",
        action="store_true",
        help="in-process: kill instance 0 in its hover instead of landing, watch ardupilot.on_loss, then "
        "start a new ArduCopter over the vehicle and watch the hand-over",
    )
    ap.add_argument(
        "--guided",
        action="store_true",
        help="fly with plan --ardupilot's GuidedLink instead: engage (GUIDED, arm, take off to --alt), a "
        "setpoint 3 m east, 2 m north, 1 m up, then hold, then LAND on close",
    )
    ap.add_argument(
        "--plan",
        type=float,
        nargs=3,
        default=None,
        metavar=("X", "Y", "Z"),
        help="through droneulator run --ardupilot on the planning scene: droneulator plan --ardupilot flies "
        "to this goal (the benchmark's ceiling 4 m, floor 1.5 m, margin 0.6 m, take-off to 2.5 m)",
    )
    ap.add_argument("--log", default=None, help="append ArduPilot k's console to LOG.k")
    ap.add_argument("--run", action="store_true", help="through droneulator run --ardupilot (renderer, API)")
    ap.add_argument("--out", default=None, help="write the JSON report here")
    args = ap.parse_args()

    cfg = load_config(overrides=["vehicle.control_hz=1200", "vehicle.params=px4_quadx"])
    if args.plan is not None:
        cfg = load_config(scene="planning")
        args.run = True
    if args.run:
        sim: Served | ThroughRun = ThroughRun(cfg, args.instance)
        instances = [args.instance]
    else:
        cfg.vehicles = [VehicleSpec(name=f"uav{k}", controlled_by="ardupilot") for k in range(args.vehicles)]
        sim = Served(World(cfg, scene="default", render=False))
        instances = list(range(args.vehicles))
    copters: list[ArduCopter] = []
    report: dict[str, Any] = {}
    try:
        copters = [ArduCopter(args, k, cfg.site.geodetic) for k in instances]
        report["command"] = " ".join(copters[0].cmd)
        boots = [c.wait_armable(args.boot_timeout) for c in copters]
        report["boot"] = boots
        report.update(sim.stats())
        if args.plan is not None and isinstance(sim, ThroughRun) and boots[0]["armable_after_wall_s"]:
            copters[0].mav.close()  # SITL's TCP serial port serves one client: the planner's link
            report["plan"] = plan_flight(sim, args.instance, np.array(args.plan))
        elif args.guided and boots[0]["armable_after_wall_s"] is not None:
            copters[0].mav.close()
            report["guided"] = guided(sim, cfg, copters[0], args.alt)
        elif all(b["armable_after_wall_s"] is not None for b in boots) and not args.no_fly:
            flights: list[dict[str, Any]] = [{} for _ in copters]

            def one(k: int) -> None:
                kill = copters[k].kill if args.kill_in_air and k == 0 else None
                flights[k] = fly(copters[k].mav, lambda: sim.truth_ned(k), args.alt, kill)

            threads = [threading.Thread(target=one, args=(k,)) for k in range(len(copters))]
            for t in threads:
                t.start()
            for t in threads:
                t.join()
            report["flight"] = flights
            if args.kill_in_air and isinstance(sim, Served):
                report["loss"] = after_kill(args, sim, copters, cfg)
    finally:
        for c in copters:
            c.close()
        report["events"] = sim.close()
    text = json.dumps(report, indent=1)
    if args.out:
        Path(args.out).write_text(text + "\n")
    else:
        print(text)
    return 0


def after_kill(
    args: argparse.Namespace, sim: Served, copters: list[ArduCopter], cfg: SimConfig
) -> dict[str, Any]:
    """Instance 0 was killed in its hover: the loss rule lands the vehicle; a new ArduCopter started at
    once connects over it in the air (held), and gets the rotors once the vehicle is down."""
    out: dict[str, Any] = {}
    t0 = time.monotonic()
    killed_alt = float(-sim.truth_ned(0)[2])
    out["killed_at_alt_m"] = round(killed_alt, 3)
    while time.monotonic() - t0 < 10 and not any("ardupilot_lost" in e.type for e in sim.events):
        time.sleep(0.05)
    lost = [e for e in sim.events if e.type == "ardupilot_lost"]
    out["lost_after_wall_s"] = round(time.monotonic() - t0, 2)
    out["lost_event"] = lost[0].data if lost else None
    out["mode_after_loss"] = sim.mode(0)
    copters[0] = ArduCopter(args, 0, cfg.site.geodetic)  # restarted: boots over the vehicle in the air
    link = sim.fleet.links[0]
    out["restarted_connected_holding"] = link.holding
    while time.monotonic() - t0 < 120 and not (sim.mode(0) == "idle" and -sim.truth_ned(0)[2] < 0.05):
        time.sleep(0.1)
    out["landed_by_simulator_after_wall_s"] = round(time.monotonic() - t0, 1)
    out["landed_alt_truth_m"] = round(float(-sim.truth_ned(0)[2]), 3)
    end = time.monotonic() + 10
    while time.monotonic() < end and not link.in_control:
        time.sleep(0.1)
    out["new_ardupilot_in_control_on_the_ground"] = link.in_control
    out["impacts"] = [
        e.data for e in sim.sim_events if e.type in ("impact", "collision") and e.vehicle == "uav0"
    ]
    return out


def plan_flight(sim: ThroughRun, instance: int, goal: np.ndarray) -> dict[str, Any]:
    """``droneulator plan --ardupilot`` to ``goal``; the truth (ENU) from the run's API."""
    from droneulator.frames import ned_to_enu

    cmd = [
        sys.executable, "-m", "droneulator.cli", "plan", "--url", sim.run.url,
        "--zenoh", sim.run.zenoh_endpoint, "--ardupilot-instance", str(instance),
        "--ardupilot-takeoff", "2.5", "--ceiling", "4.0", "--floor", "1.5", "--margin", "0.6",
        "--goal", *(str(float(g)) for g in goal),
    ]  # fmt: skip
    log = tempfile.NamedTemporaryFile("w+", suffix=".log", delete=False)  # noqa: SIM115 - the planner's
    planner = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT)
    out: dict[str, Any] = {"goal": goal.tolist(), "planner_log": log.name}
    path: list[np.ndarray] = []
    t0 = time.monotonic()
    try:
        while time.monotonic() - t0 < 300:
            path.append(ned_to_enu(sim.truth_ned()))
            if np.linalg.norm(path[-1] - goal) < 0.3:
                break
            time.sleep(0.25)
        out["within_0.3_m_after_wall_s"] = round(time.monotonic() - t0, 1)
        time.sleep(8.0)
        final = ned_to_enu(sim.truth_ned())
        out["truth_8s_later"] = np.round(final, 3).tolist()
        out["true_goal_error_m"] = round(float(np.linalg.norm(final - goal)), 3)
        pts = np.array(path)
        out["path_length_m"] = round(float(np.sum(np.linalg.norm(np.diff(pts, axis=0), axis=1))), 2)
        out["max_z_m"] = round(float(pts[:, 2].max()), 2)
        out["mode"] = sim.client.state()["mode"]
    finally:
        planner.send_signal(signal.SIGTERM)
        try:
            planner.wait(15)
        except subprocess.TimeoutExpired:
            planner.kill()
    log.seek(0)
    out["planner_said"] = [ln.split(" ", 3)[-1].strip() for ln in log if "reached" in ln or "ERROR" in ln]
    return out


def guided(sim: Served | ThroughRun, cfg: SimConfig, copter: ArduCopter, alt: float) -> dict[str, Any]:
    """``plan --ardupilot``'s link on a real ArduCopter: engage, one setpoint, hold, land on close."""
    from droneulator.frames import ned_to_enu
    from droneulator.workflows.planning.guided import GuidedConfig, GuidedLink

    lat, lon, home_alt = cfg.site.geodetic
    g = GuidedLink(GuidedConfig(takeoff_alt_m=alt, on_stop="land", home_lat_deg=lat, home_lon_deg=lon,
                                home_alt_m=home_alt))  # fmt: skip
    out: dict[str, Any] = {}
    t0 = time.monotonic()
    g.engage()
    while not g.engaged.is_set() and g.failed is None and time.monotonic() - t0 < 90:
        time.sleep(0.2)
    out["engaged_after_wall_s"], out["failed"] = round(time.monotonic() - t0, 1), g.failed
    if g.failed is None and g.origin_enu is not None:
        truth = lambda: ned_to_enu(sim.truth_ned())  # noqa: E731
        out["origin_enu"] = np.round(g.origin_enu, 3).tolist()
        out["engaged_truth_enu"] = np.round(truth(), 3).tolist()
        goal = truth() + np.array([3.0, 2.0, 1.0])
        t1 = time.monotonic()
        while time.monotonic() - t1 < 30:
            g.setpoint(0.0, goal, np.zeros(3), np.zeros(3), 0.5, 0.0)
            time.sleep(0.05)
            if time.monotonic() - t1 > 3 and np.linalg.norm(truth() - goal) < 0.15:
                break
        est = g.estimate()
        out["goal_enu"] = np.round(goal, 3).tolist()
        out["reached_after_wall_s"] = round(time.monotonic() - t1, 1)
        out["truth_enu"] = np.round(truth(), 3).tolist()
        out["estimate_enu"] = None if est is None else np.round(est.position, 3).tolist()
        time.sleep(2.0)  # no setpoints: the link holds the last one
        out["truth_after_2s_stale_enu"] = np.round(truth(), 3).tolist()
    g.close()
    time.sleep(5.0)
    out["truth_5s_after_close_land_enu"] = np.round(ned_to_enu(sim.truth_ned()), 3).tolist()
    return out


def fly(
    mav: Any, truth_ned: Callable[[], np.ndarray], alt: float, kill: Callable[[], None] | None
) -> dict[str, Any]:
    """GUIDED takeoff to ``alt``, 5 s hold, LAND (or ``kill``); EKF (LOCAL_POSITION_NED) against the truth."""
    out: dict[str, Any] = {}
    mav.set_mode("GUIDED")
    home = truth_ned()
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
        truth = truth_ned() - home
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
            if kill is not None:
                kill()
                phase = "killed"
                break
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
