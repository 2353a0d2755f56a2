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
        #: vehicle 0 after every step: (sim t, truth height z, vertical acceleration (world, m/s^2),
        #: specific force along body up (the IMU's, m/s^2))
        self.trace: list[tuple[float, float, float, float]] = []
        self.wall0, self.sim0 = time.monotonic(), 0.0
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        n = max(1, round(0.01 * self.world.config.vehicle.control_hz))
        v = self.world.vehicle_list[0]
        while not self.stop.is_set():
            res = self.fleet.serve_once(0.01, self.lock)
            if res is None and not self.fleet.connected:
                with self.lock:
                    res = self.world.step(n)
            if res is not None:
                self.sim_events.extend(res.events)
                with self.lock:
                    self.trace.append(
                        (self.world.t, float(v.state.position[2]), float(v.acceleration[2]),
                         float(v.specific_force[2]))
                    )  # fmt: skip
            self.events.extend(self.fleet.take_events())

    def speed(self) -> dict[str, float]:
        """Sim time over wall time since :meth:`mark` (or the start)."""
        with self.lock:
            sim = self.world.t - self.sim0
        wall = time.monotonic() - self.wall0
        return {"sim_s": round(sim, 2), "wall_s": round(wall, 2), "sim_per_wall": round(sim / wall, 3)}

    def mark(self) -> None:
        with self.lock:
            self.sim0 = self.world.t
        self.wall0 = time.monotonic()

    def truth_ned(self, k: int = 0) -> np.ndarray:
        with self.lock:
            return enu_to_ned(self.world.vehicle_list[k].state.position)

    def mode(self, k: int = 0) -> str:
        with self.lock:
            return self.world.vehicle_list[k].mode.value

    def heading_deg(self, k: int = 0) -> float:
        """The truth heading, clockwise from north (degrees)."""
        with self.lock:
            x, y, z, w = self.world.vehicle_list[k].state.quaternion
        return float((90.0 - np.degrees(np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)))) % 360.0)

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
        frame = [str(Path(args.defaults) / f) for f in ("copter.parm", "copter-X.parm")]
        if args.params == "sprayer40":
            frame[1] = str(Path(__file__).with_name("ardupilot_octaquad_x.parm"))
        defaults = ",".join(frame)
        self.cmd = [
            os.path.abspath(args.arducopter), "--model", "JSON:127.0.0.1", "--speedup", str(args.speedup),
            "-I", str(k),
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
        beat = self.mav.messages.get("HEARTBEAT")
        return {
            "mav_type": None if beat is None else int(beat.type),
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
    ap.add_argument("--instance", type=int, default=0, help="the (first) ArduPilot instance")
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
    ap.add_argument("--params", default="px4_quadx", help="the airframe (sprayer40: OctaQuad X)")
    ap.add_argument("--speedup", type=float, default=1.0, help="arducopter --speedup")
    ap.add_argument("--on-loss", default="land", choices=["land", "hold", "fall"], help="ardupilot.on_loss")
    ap.add_argument("--auto", action="store_true", help="fly an AUTO mission (take-off, --leg north, land)")
    ap.add_argument("--yaw", type=float, default=0.0, help="in-process, GUIDED: turn this many degrees first")
    ap.add_argument("--leg", type=float, default=0.0, help="fly this many metres north before landing")
    ap.add_argument("--log", default=None, help="append ArduPilot k's console to LOG.k")
    ap.add_argument("--run", action="store_true", help="through droneulator run --ardupilot (renderer, API)")
    ap.add_argument("--out", default=None, help="write the JSON report here")
    args = ap.parse_args()

    cfg = load_config(
        overrides=[
            "vehicle.control_hz=1200",
            f"vehicle.params={args.params}",
            f"ardupilot.on_loss={args.on_loss}",
            f"ardupilot.instance={args.instance}",
        ]
    )
    if args.plan is not None:
        cfg = load_config(scene="planning")
        args.run = True
    if args.run:
        sim: Served | ThroughRun = ThroughRun(cfg, args.instance)
        instances = [args.instance]
    else:
        cfg.vehicles = [VehicleSpec(name=f"uav{k}", controlled_by="ardupilot") for k in range(args.vehicles)]
        sim = Served(World(cfg, scene="default", render=False))
        instances = [args.instance + k for k in range(args.vehicles)]
    copters: list[ArduCopter] = []
    report: dict[str, Any] = {}
    try:
        copters = [ArduCopter(args, k, cfg.site.geodetic) for k in instances]
        report["command"] = " ".join(copters[0].cmd)
        boots = [c.wait_armable(args.boot_timeout) for c in copters]
        report["boot"] = boots
        report.update(sim.stats())
        if isinstance(sim, Served):
            report["boot_speed"] = sim.speed()
            sim.mark()
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
                if args.auto:
                    flights[k] = fly_auto(
                        copters[k].mav, lambda: sim.truth_ned(k), cfg.site.geodetic, args.alt, args.leg
                    )
                else:
                    yaw = (
                        (args.yaw, lambda: sim.heading_deg(k))
                        if args.yaw and isinstance(sim, Served)
                        else None
                    )
                    flights[k] = fly(copters[k].mav, lambda: sim.truth_ned(k), args.alt, kill, args.leg, yaw)

            threads = [threading.Thread(target=one, args=(k,)) for k in range(len(copters))]
            for t in threads:
                t.start()
            for t in threads:
                t.join()
            report["flight"] = flights
            if isinstance(sim, Served):
                report["flight_speed"] = sim.speed()
                if not args.kill_in_air:
                    report["landing"] = landing(sim)
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
    """Instance 0 was killed in its hover: the loss rule (``--on-loss``) takes the vehicle (land: the
    simulator lands it; hold: it hovers there; fall: the rotors stop); a new ArduCopter started at once
    connects over it (held while it is in the air; under hold the script lands it with the simulator's
    controller after 8 s), and gets the rotors once the vehicle is down."""
    out: dict[str, Any] = {"on_loss": args.on_loss}
    t0 = time.monotonic()
    killed_alt = float(-sim.truth_ned(0)[2])
    out["killed_at_alt_m"] = round(killed_alt, 3)
    while time.monotonic() - t0 < 10 and not any("ardupilot_lost" in e.type for e in sim.events):
        time.sleep(0.05)
    lost = [e for e in sim.events if e.type == "ardupilot_lost"]
    out["lost_after_wall_s"] = round(time.monotonic() - t0, 2)
    out["lost_event"] = lost[0].data if lost else None
    out["lost_action"] = lost[0].data.get("action") if lost else None
    out["mode_after_loss"] = sim.mode(0)
    time.sleep(3.0)
    out["alt_3s_after_loss_m"] = round(float(-sim.truth_ned(0)[2]), 3)
    out["mode_3s_after_loss"] = sim.mode(0)
    copters[0] = ArduCopter(args, args.instance, cfg.site.geodetic)  # restarted: boots over the vehicle
    link = sim.fleet.links[0]
    out["restarted_connected_holding"] = link.holding
    out["restarted_alt_m"] = round(float(-sim.truth_ned(0)[2]), 3)
    if args.on_loss == "hold":
        time.sleep(8.0)
        out["hold_8s_later_alt_m"] = round(float(-sim.truth_ned(0)[2]), 3)
        out["hold_8s_later_still_holding"] = link.holding
        with sim.lock:
            sim.world.vehicle_list[0].land()
    while time.monotonic() - t0 < 150 and not (sim.mode(0) == "idle" and -sim.truth_ned(0)[2] < 0.05):
        time.sleep(0.1)
    out["on_the_ground_after_wall_s"] = round(time.monotonic() - t0, 1)
    out["ground_alt_truth_m"] = round(float(-sim.truth_ned(0)[2]), 3)
    end = time.monotonic() + 20
    while time.monotonic() < end and not link.in_control:
        time.sleep(0.1)
    out["new_ardupilot_in_control_on_the_ground"] = link.in_control
    out["in_control_after_wall_s"] = round(time.monotonic() - t0, 1)
    out["arm_refused"] = [e.data for e in sim.events if e.type == "ardupilot_arm_refused"]
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
    mav: Any,
    truth_ned: Callable[[], np.ndarray],
    alt: float,
    kill: Callable[[], None] | None,
    leg: float = 0.0,
    yaw: tuple[float, Callable[[], float]] | None = None,
) -> dict[str, Any]:
    """GUIDED takeoff to ``alt``, 5 s hold, ``leg`` m north and 3 s hold, LAND (or ``kill``); EKF
    (LOCAL_POSITION_NED) against the truth."""
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
    while time.monotonic() - t0 < 300:
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
            if yaw is not None:
                turn, heading = yaw
                before = heading()
                mav.mav.command_long_send(
                    mav.target_system, mav.target_component, mavutil.mavlink.MAV_CMD_CONDITION_YAW, 0,
                    abs(turn), 30.0, 1 if turn > 0 else -1, 1, 0, 0, 0,
                )  # fmt: skip
                time.sleep(abs(turn) / 30.0 + 5.0)
                turned = (heading() - before + 180.0) % 360.0 - 180.0
                out["yaw"] = {
                    "asked_deg": turn,
                    "heading_before_deg": round(before, 1),
                    "turned_deg": round(turned, 1),
                }
                ekf = np.array([msg.x, msg.y, msg.z])
            if leg > 0:
                mav.mav.set_position_target_local_ned_send(
                    0, mav.target_system, mav.target_component, mavutil.mavlink.MAV_FRAME_LOCAL_NED,
                    0b110111111000, ekf[0] + leg, ekf[1], ekf[2], 0, 0, 0, 0, 0, 0, 0, 0,
                )  # fmt: skip
                phase, hold_until = "leg", None
                leg_start = truth[0]
            else:
                mav.set_mode("LAND")
                phase = "land"
                out["land_wall_s"] = round(time.monotonic() - t0, 1)
        elif phase == "leg":
            if hold_until is None and truth[0] - leg_start > leg - 0.3:
                hold_until = time.monotonic() + 3.0
                out["leg_wall_s"] = round(time.monotonic() - t0, 1)
            elif hold_until is not None and time.monotonic() > hold_until:
                out["leg_end_truth_ned"] = np.round(truth, 3).tolist()
                out["leg_end_ekf_ned"] = np.round(ekf, 3).tolist()
                mav.set_mode("LAND")
                phase = "land"
                out["land_wall_s"] = round(time.monotonic() - t0, 1)
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


def fly_auto(
    mav: Any, truth_ned: Callable[[], np.ndarray], site: tuple[float, float, float], alt: float, leg: float
) -> dict[str, Any]:
    """An AUTO mission: NAV_TAKEOFF to ``alt``, NAV_WAYPOINT ``leg`` m north of home, NAV_LAND there;
    uploaded, armed in GUIDED and started with MAV_CMD_MISSION_START (which ArduCopter lets take off
    with no throttle); ends at the disarm."""
    m = mavutil.mavlink
    lat, lon, _ = site
    north = int(round((lat + np.degrees(leg / 6378137.0)) * 1e7))
    items = [
        (m.MAV_FRAME_GLOBAL, m.MAV_CMD_NAV_WAYPOINT, int(lat * 1e7), int(lon * 1e7), 0.0),  # home
        (m.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, m.MAV_CMD_NAV_TAKEOFF, 0, 0, alt),
        (m.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, m.MAV_CMD_NAV_WAYPOINT, north, int(lon * 1e7), alt),
        (m.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, m.MAV_CMD_NAV_LAND, north, int(lon * 1e7), 0.0),
    ]
    out: dict[str, Any] = {}
    sysid, comp = mav.target_system, mav.target_component
    mav.mav.mission_count_send(sysid, comp, len(items), 0)
    end = time.monotonic() + 20
    while time.monotonic() < end:
        msg = mav.recv_match(
            type=["MISSION_REQUEST", "MISSION_REQUEST_INT", "MISSION_ACK"], blocking=True, timeout=1
        )
        if msg is None:
            continue
        if msg.get_type() == "MISSION_ACK":
            out["mission_ack"] = int(msg.type)
            break
        frame, cmd, x, y, z = items[msg.seq]
        mav.mav.mission_item_int_send(
            sysid, comp, msg.seq, frame, cmd, 0, 1, 0, 0, 0, 0, x, y, z, 0
        )  # fmt: skip
    if out.get("mission_ack") != 0:
        return out
    mav.set_mode("GUIDED")
    home = truth_ned()
    mav.arducopter_arm()
    mav.motors_armed_wait()
    mav.mav.command_long_send(sysid, comp, m.MAV_CMD_MISSION_START, 0, 0, 0, 0, 0, 0, 0, 0)
    t0 = time.monotonic()
    top, reached = 0.0, 0.0
    while time.monotonic() - t0 < 240:
        msg = mav.recv_match(
            type=["HEARTBEAT", "STATUSTEXT", "MISSION_ITEM_REACHED"], blocking=True, timeout=1
        )
        truth = truth_ned() - home
        top, reached = max(top, -truth[2]), max(reached, truth[0])
        if msg is not None and msg.get_type() == "STATUSTEXT":
            out.setdefault("texts", []).append(msg.text)
        if msg is not None and msg.get_type() == "MISSION_ITEM_REACHED":
            out.setdefault("reached", []).append((int(msg.seq), round(time.monotonic() - t0, 1)))
        if time.monotonic() - t0 > 5 and not mav.motors_armed():
            out["disarmed_after_wall_s"] = round(time.monotonic() - t0, 1)
            out["landed_truth_ned"] = np.round(truth, 3).tolist()
            break
    out["max_alt_truth_m"] = round(float(top), 3)
    out["max_north_truth_m"] = round(float(reached), 3)
    return out


def landing(sim: Served) -> dict[str, Any]:
    """The last landing of vehicle 0 from :attr:`Served.trace`: touchdown is the first step after the
    highest point, within 10 cm of the rest height it took off from, where the ground pushes up (vertical
    acceleration above 2 m/s^2); the descent speed over the 0.1 s before it; the peak vertical
    acceleration and specific force from 1 s before it to 3 s after; the bounce (the highest point from
    0.2 s after touchdown on, above the rest height) and ArduPilot's disarm, in sim time after it."""
    tr = np.array(sim.trace)
    ground = float(np.median(tr[: max(1, len(tr) // 50), 1]))
    top = int(np.argmax(tr[:, 1]))
    down = top + int(np.argmax((tr[top:, 1] < ground + 0.1) & (tr[top:, 2] > 2.0)))
    t_td = float(tr[down, 0])
    before = tr[(tr[:, 0] > t_td - 0.1) & (tr[:, 0] <= t_td)]
    near = tr[(tr[:, 0] > t_td - 1.0) & (tr[:, 0] < t_td + 3.0)]
    after = tr[tr[:, 0] > t_td + 0.2]
    disarms = [e.t for e in sim.events if e.type == "ardupilot_disarmed" and e.t > t_td - 5.0]
    impacts = [e.data for e in sim.sim_events if e.type == "impact"]
    return {
        "ground_z_m": round(ground, 4),
        "touchdown_sim_t_s": round(t_td, 3),
        "touchdown_height_m": round(float(tr[down, 1]) - ground, 4),
        "descent_speed_before_m_s": round(
            float((before[0, 1] - before[-1, 1]) / (before[-1, 0] - before[0, 0])), 3
        ),
        "peak_vertical_accel_m_s2": round(float(np.max(np.abs(near[:, 2]))), 2),
        "peak_specific_force_up_m_s2": round(float(np.max(near[:, 3])), 2),
        "bounce_m": round(float(np.max(after[:, 1]) - ground), 4) if len(after) else None,
        "disarm_after_touchdown_sim_s": round(disarms[0] - t_td, 2) if disarms else None,
        "impact_events": impacts,
    }


if __name__ == "__main__":
    sys.exit(main())
