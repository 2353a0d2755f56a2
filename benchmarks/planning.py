"""Local planning round a tree (paper Table "Trajectory statistics for multi-goal local planning").

``droneulator run --scene planning`` (lockstep, the default 640x480 camera rig) and ``droneulator plan``
run as two processes talking only over Zenoh. For each of five goals on the far side of the central
tree, from far left to far right, the vehicle is reset to the start, takes off to the flight altitude
through the WebSocket API, a fresh planner process is started (an empty map) and the goal is published
on ``/<ns>/planner/goal`` as a ``geometry_msgs/PoseStamped``, like RViz's goal tool. The benchmark
watches the API's state stream (it never talks to the planner) and, per run, reports: flight time
(goal sent -> first within ``--arrive`` metres of the goal, sim time), path length, goal error after
``--settle`` s of sim time, minimum clearance from the vehicle centre to the true scene geometry
(the scene's SDF, which only the benchmark reads), collisions, the planner's plan and map-update
times (median, p99, from its ``--stats`` file) and the real-time factor. Writes
``benchmarks/results/planning.json`` (with each flight's 3-D track, its events and, after a collision
or impact, the last 300 states before it, to trace a failed flight) and a top-down figure of the five
trajectories (``benchmarks/results/planning.png``).

``--px4 PATH`` flies the paper's way, with PX4 in the loop: the run is ``droneulator run --px4`` and for
each goal a fresh PX4 SITL (``PATH`` is a ``px4_sitl_default`` build directory; ``--px4 scripted``: the
PX4-like peer of ``tests/scripted_px4.py``) boots on the ground at the start, takes off to 2.5 m
(``MIS_TAKEOFF_ALT``) on a ground station's ARM and NAV_TAKEOFF (UDP 14550), and ``droneulator plan --px4``
flies it in OFFBOARD. Arrival and the goal error are then measured in PX4's own frame (its
LOCAL_POSITION_NED through its GPS origin, as the planner judges them), clearance and the true goal error
on the simulator's truth. Each flight ends with NAV_LAND and PX4 stopped on the ground.
"""

from __future__ import annotations

import argparse
import collections
import json
import math
import os
import signal
import struct
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
from _common import write
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink

from droneulator import frames
from droneulator.api.client import ApiError
from droneulator.config import load_config
from droneulator.ros import messages as M
from droneulator.ros.topics import ODOM_FRAME
from droneulator.ros.zenoh_node import RosZenohNode
from droneulator.runtime.launch import launch_run
from droneulator.scenes import get_scene
from droneulator.scenes.collision import sdf_lookup_many
from droneulator.workflows.planning.node import GOAL_TYPE

ALTITUDE = 2.5
#: the planner's virtual ceiling (EGO-Planner's ``virtual_ceil_height``): routes go round the crown
CEILING = 4.0
#: and floor: under the crown (clear trunk below about 1.2 m) is not a route either
FLOOR = 1.5
#: inflation beyond the vehicle radius: the SDF's leaf-cluster spheres reach ~0.2 m past the leaves
MARGIN = 0.6
#: far left (+y, seen from the start facing +x) to far right
GOALS_XY = ((7.0, 6.0), (7.5, 3.0), (8.0, 0.0), (7.5, -3.0), (7.0, -6.0))


#: PX4 parameters for SITL without RC or a watching ground station (docs/px4.md), and the take-off height
PX4_PARAMS = {"NAV_RCL_ACT": 0, "NAV_DLL_ACT": 0, "COM_RC_IN_MODE": 4, "MIS_TAKEOFF_ALT": ALTITUDE}


class PX4:
    """One PX4 SITL for one flight, with a ground station on UDP 14550: the real binary of a
    ``px4_sitl_default`` build (``where``), or ``"scripted"`` (tests/scripted_px4.py)."""

    def __init__(self, where: str, sim_port: int, home: tuple[float, float, float], workdir: Path) -> None:
        self.home = home
        gcs_id = {"source_system": 255, "source_component": mavlink.MAV_COMP_ID_MISSIONPLANNER}
        self.gcs = mavutil.mavlink_connection("udpin:127.0.0.1:14550", **gcs_id)
        self.proc: subprocess.Popen | None = None
        self.scripted = None
        self.lock = threading.Lock()
        self.local: tuple[np.ndarray, float] | None = None  # NED position, monotonic time
        self.origin: np.ndarray | None = None
        self.sysid: int | None = None
        self.armed = False
        self.acks: dict[int, int] = {}
        self.texts: list[str] = []
        self._stop = False
        if where == "scripted":
            sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
            from scripted_px4 import ScriptedPX4

            self.scripted = ScriptedPX4(sim_port, 14540, gcs_port=14550)
        else:
            build = Path(where)
            env = {**os.environ, "PX4_SYS_AUTOSTART": "10016", "PX4_SIM_MODEL": "none_iris"}
            rootfs = workdir / "px4"
            rootfs.mkdir(parents=True, exist_ok=True)
            self.log_path = workdir / "px4.log"
            out = open(self.log_path, "a")  # noqa: SIM115 (closed with the process by the OS)
            cmd = [str(build / "bin" / "px4"), "-d", str(build / "etc")]
            self.proc = subprocess.Popen(cmd, cwd=rootfs, env=env, stdout=out, stderr=subprocess.STDOUT)
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        next_hb = 0.0
        while not self._stop:
            if time.monotonic() >= next_hb and self.sysid is not None:
                self.gcs.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
                next_hb = time.monotonic() + 1.0
            m = self.gcs.recv_match(blocking=True, timeout=0.1)
            if m is None:
                continue
            kind = m.get_type()
            with self.lock:
                if kind == "HEARTBEAT" and m.autopilot == mavlink.MAV_AUTOPILOT_PX4:
                    self.sysid = m.get_srcSystem()
                    self.armed = bool(m.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
                elif kind == "LOCAL_POSITION_NED":
                    self.local = (np.array([m.x, m.y, m.z]), time.monotonic())
                elif kind == "GPS_GLOBAL_ORIGIN":
                    lat, lon, alt = m.latitude * 1e-7, m.longitude * 1e-7, m.altitude * 1e-3
                    self.origin = frames.geodetic_to_enu(lat, lon, alt, *self.home)
                elif kind == "COMMAND_ACK":
                    self.acks[m.command] = m.result
                elif kind == "STATUSTEXT":
                    self.texts.append(m.text)

    def _command(self, command: int, *params: float, timeout: float = 2.0) -> int | None:
        with self.lock:
            self.acks.pop(command, None)
        p = list(params) + [0.0] * (7 - len(params))
        self.gcs.mav.command_long_send(self.sysid, 1, command, 0, *p)
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            with self.lock:
                if command in self.acks and self.acks[command] != mavlink.MAV_RESULT_IN_PROGRESS:
                    return self.acks[command]
            time.sleep(0.02)
        return None

    def wait_ready(self, timeout: float = 120.0) -> None:
        """PX4's heartbeat, the SITL parameters set, and its GPS origin known."""
        end = time.monotonic() + timeout
        while self.sysid is None:
            if time.monotonic() > end:
                raise TimeoutError("no PX4 heartbeat on UDP 14550")
            time.sleep(0.1)
        for name, value in PX4_PARAMS.items():
            # PX4 encodes integer parameters bytewise in PARAM_SET's float
            real = isinstance(value, float)
            raw = float(value) if real else struct.unpack("<f", struct.pack("<i", value))[0]
            kind = mavlink.MAV_PARAM_TYPE_REAL32 if real else mavlink.MAV_PARAM_TYPE_INT32
            self.gcs.mav.param_set_send(self.sysid, 1, name.encode(), raw, kind)
        while self.origin is None:
            if time.monotonic() > end:
                raise TimeoutError("PX4 sent no GPS_GLOBAL_ORIGIN")
            origin_id = mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN
            self._command(mavlink.MAV_CMD_REQUEST_MESSAGE, origin_id, timeout=1)

    def takeoff(self, timeout: float = 120.0) -> None:
        """Arm (PX4 refuses until its preflight checks pass: retried) and NAV_TAKEOFF to MIS_TAKEOFF_ALT."""
        end = time.monotonic() + timeout
        while self._command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0) != mavlink.MAV_RESULT_ACCEPTED:
            if time.monotonic() > end:
                raise TimeoutError(f"PX4 would not arm: {self.texts[-5:]}")
            time.sleep(1.0)
        result = self._command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, math.nan, math.nan, math.nan)
        if result != mavlink.MAV_RESULT_ACCEPTED:
            raise RuntimeError(f"PX4 refused NAV_TAKEOFF: {result}; {self.texts[-5:]}")

    def estimate(self) -> np.ndarray | None:
        """PX4's position estimate in the ENU world (LOCAL_POSITION_NED through its origin)."""
        with self.lock:
            if self.local is None or self.origin is None or time.monotonic() - self.local[1] > 1.0:
                return None
            return self.origin + frames.ned_to_enu(self.local[0])

    def land(self) -> None:
        self._command(mavlink.MAV_CMD_NAV_LAND, 0, 0, 0, math.nan, math.nan, math.nan, math.nan)

    def close(self) -> None:
        if self.scripted is not None:
            self.scripted.close()
        if self.proc is not None:
            self.proc.kill()
            self.proc.wait(timeout=20)
        self._stop = True
        self._reader.join(timeout=2)
        self.gcs.close()


def _pct(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float("nan")


def _planner(endpoint: str, ns: str, bounds: list[float], stats: Path, log: Path,
             margin: float, px4: bool, tracking_margin_max: float | None,
             yaw_lookahead: float | None = None) -> subprocess.Popen:  # fmt: skip
    cmd = [sys.executable, "-m", "droneulator.cli", "plan", "--zenoh", endpoint, "--namespace", ns,
           "--bounds", *map(str, bounds), "--ceiling", str(CEILING), "--floor", str(FLOOR),
           "--margin", str(margin), "--stats", str(stats), "-v"] + ["--px4"] * px4  # fmt: skip
    if tracking_margin_max is not None:
        cmd += ["--tracking-margin-max", str(tracking_margin_max)]
    if yaw_lookahead is not None:
        cmd += ["--yaw-lookahead", str(yaw_lookahead)]
    out = open(log, "w")  # noqa: SIM115 (closed with the process by the OS)
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    return subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, env=env)


def _wait_for_line(log: Path, text: str, proc: subprocess.Popen, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if text in log.read_text():
            return
        if proc.poll() is not None:
            raise RuntimeError(f"planner exited ({proc.returncode}):\n{log.read_text()[-2000:]}")
        time.sleep(0.1)
    raise TimeoutError(f"planner log has no {text!r} after {timeout} s:\n{log.read_text()[-2000:]}")


def fly_one(run, client, goal_pub, goal: np.ndarray, start: np.ndarray, bounds: list[float], workdir: Path,
            args: argparse.Namespace, index: int) -> dict:  # fmt: skip
    deadline = time.monotonic() + 30
    while True:
        try:
            client.reset(position=[float(start[0]), float(start[1]), 0.0], yaw=0.0)
            break
        except ApiError as exc:  # the previous flight's PX4 is still being let go
            if exc.code != "flight_locked" or time.monotonic() > deadline:
                raise
            time.sleep(0.2)
    px4 = None
    if args.px4:
        home = run.config.site.geodetic
        px4 = PX4(args.px4, run.config.px4.base_port, home, workdir / f"px4_{index}")
        px4.wait_ready()
        px4.takeoff()
        deadline = time.monotonic() + 120
        while (est := px4.estimate()) is None or min(est[2], client.state()["position"][2]) < ALTITUDE - 0.2:
            if time.monotonic() > deadline:
                raise TimeoutError(f"PX4 did not climb to {ALTITUDE} m: {px4.texts[-5:]}")
            time.sleep(0.1)
        time.sleep(2.0)  # settle in AUTO.LOITER
    else:
        client.takeoff(altitude=ALTITUDE)
        client.wait_for_event("arrived", timeout=120)
    try:
        return _fly(run, client, goal_pub, goal, bounds, workdir, args, index, px4)
    finally:
        if px4 is not None:
            px4.land()
            end = time.monotonic() + 60
            while px4.armed and time.monotonic() < end:
                time.sleep(0.2)
            px4.close()


def _fly(run, client, goal_pub, goal: np.ndarray, bounds: list[float], workdir: Path,
         args: argparse.Namespace, index: int, px4: PX4 | None) -> dict:  # fmt: skip
    stats, log = workdir / f"plan_{index}.json", workdir / f"plan_{index}.log"
    proc = _planner(run.zenoh_endpoint, run.config.bridge.namespace, bounds, stats, log, args.margin,
                    px4 is not None, args.tracking_margin_max, args.yaw_lookahead)  # fmt: skip
    try:
        _wait_for_line(log, "first depth image integrated", proc, 120)
        for _ in client.messages(timeout=0.0):  # what queued up meanwhile: the previous flight's landing
            pass
        s0 = client.state()
        wall0 = time.monotonic()
        goal_pub.publish(M.serialize(M.pose_stamped(0, ODOM_FRAME, goal, (0.0, 0.0, 0.0, 1.0))))
        t0 = s0["t"]
        samples: list[tuple[float, list[float], float]] = []
        #: (sim t, PX4's estimate): with PX4, arrival and the goal error are PX4's, as the planner judges them
        estimates: list[tuple[float, np.ndarray]] = []
        collisions = 0
        events: list[dict] = []  # every event, and the states before the first contact, to trace one
        recent: collections.deque[dict] = collections.deque(maxlen=300)
        before_contact: list[dict] = []
        t_arrive = None
        deadline_wall = wall0 + args.timeout * 4
        while time.monotonic() < deadline_wall:
            msg = client.next_message(timeout=5.0)
            if msg is None:
                continue
            if msg.get("type") == "event":
                events.append(msg["event"])
                if msg["event"].get("type") in ("collision", "impact"):
                    if not collisions:
                        before_contact = list(recent)
                    collisions += 1
                continue
            if msg.get("type") != "state":
                continue
            st = msg["state"]
            if st["stamp_ns"] < s0["stamp_ns"]:  # the monotonic clock: t restarts at every reset
                continue
            recent.append(st)
            p = np.array(st["position"])
            speed = float(np.linalg.norm(st["velocity"]))
            samples.append((st["t"], st["position"], speed))
            if px4 is not None:
                est = px4.estimate()
                if est is None:
                    continue
                estimates.append((st["t"], est))
                p = est
            err = float(np.linalg.norm(p - goal))
            if t_arrive is None and err <= args.arrive:
                t_arrive = st["t"]
            if t_arrive is not None and st["t"] - t_arrive >= args.settle:
                break
            if st["t"] - t0 > args.timeout:
                break
        wall = time.monotonic() - wall0
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
    t = np.array([s[0] for s in samples])
    pos = np.array([s[1] for s in samples])
    end = t_arrive if t_arrive is not None else t[-1]
    flown = pos[t <= end]
    length = float(np.linalg.norm(np.diff(flown, axis=0), axis=1).sum()) if len(flown) > 1 else 0.0
    col = get_scene(run.config.scene, run.config.seed).collision
    clearance = sdf_lookup_many(col.sdf, col.origin, col.resolution, pos)
    planner = json.loads(stats.read_text()) if stats.exists() else {}
    plan_ms = [1e3 * x for x in planner.get("plan_s", [])]
    map_ms = [1e3 * x for x in planner.get("map_update_s", [])]
    true_error = float(np.linalg.norm(pos[-1] - goal))
    return {
        "goal": goal.tolist(),
        "reached": t_arrive is not None,
        "flight_time_s": None if t_arrive is None else float(t_arrive - t0),
        "path_length_m": length,
        "straight_line_m": float(np.linalg.norm(goal - pos[0])),
        # in the frame the vehicle is flown in: PX4's estimate with --px4, else the truth
        "goal_error_m": float(np.linalg.norm(estimates[-1][1] - goal)) if estimates else true_error,
        "true_goal_error_m": true_error,
        "min_clearance_m": float(clearance.min()),
        "collisions": collisions,
        "events": events[:100],
        "states_before_contact": before_contact,
        # the planner's tracking error (setpoints against the autopilot's estimate) and the margin it added
        "tracking": planner.get("tracking"),
        "plans": planner.get("plans"),
        "plan_failures": planner.get("failures"),
        # plans dropped as too late, and holds while the planning thread was stuck (both 0 when it keeps up)
        "stale_plans": planner.get("stale_plans"),
        "stalls": planner.get("stalls"),
        "plan_ms_median": _pct(plan_ms, 50),
        "plan_ms_p99": _pct(plan_ms, 99),
        "map_ms_median": _pct(map_ms, 50),
        "plan_ms": plan_ms,
        "rtf": float((t[-1] - t0) / wall) if len(t) else float("nan"),
        "trajectory": pos.round(3).tolist(),
        # with --px4: (sim t, PX4's estimate in the world) over the flight, the frame it was flown in
        "estimates": [[round(t, 3), *np.round(e, 3).tolist()] for t, e in estimates],
    }


def figure(scene_name: str, seed: int, runs: list[dict], start: np.ndarray, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    col = get_scene(scene_name, seed).collision
    xs, ys = np.arange(-11.0, 11.0, 0.05), np.arange(-9.0, 9.0, 0.05)
    X, Y = np.meshgrid(xs, ys)
    flat = np.stack([X.ravel(), Y.ravel()], 1)
    def at(z: float) -> np.ndarray:
        return sdf_lookup_many(col.sdf, col.origin, col.resolution, np.c_[flat, np.full(len(flat), z)])

    slice_d = at(ALTITUDE)
    anywhere = np.min([at(z) for z in np.arange(0.3, 6.0, 0.3)], axis=0)
    fig, ax = plt.subplots(figsize=(9, 7.5))
    ax.contourf(X, Y, anywhere.reshape(X.shape), levels=[-10, 0], colors=["#cfe3c6"])
    ax.contourf(X, Y, slice_d.reshape(X.shape), levels=[-10, 0, 0.5], colors=["#2f6b2a", "#a9c9a0"])
    colours = plt.cm.plasma(np.linspace(0.05, 0.85, len(runs)))
    for r, c in zip(runs, colours, strict=True):
        tr = np.array(r["trajectory"])
        ok = "reached" if r["reached"] else "NOT reached"
        ax.plot(tr[:, 0], tr[:, 1], color=c, lw=2,
                label=f"goal {r['goal_index']}: {ok}, {r['flight_time_s'] or float('nan'):.1f} s, "
                      f"clearance {r['min_clearance_m']:.2f} m")  # fmt: skip
        ax.plot(*r["goal"][:2], marker="*", ms=16, color=c, mec="k")
    ax.plot(*start[:2], marker="o", ms=10, color="k", label="start")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"`{scene_name}`: five planned flights at {ALTITUDE} m (dark: obstacles at flight altitude, "
                 "mid: their 0.5 m band, light: obstacles at any height)", fontsize=9)  # fmt: skip
    ax.legend(loc="lower left", fontsize=8)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    print(f"wrote {out}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="planning")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--goals", type=int, nargs="+", default=None, help="run only these goals (1-5)")
    ap.add_argument("--arrive", type=float, default=0.1, help="arrival radius for the flight time (m)")
    ap.add_argument("--settle", type=float, default=None,
                    help="sim s after arrival before the goal error (default 2; 5 with --px4: PX4's position "
                         "controller overshoots the end of a trajectory, then settles)")  # fmt: skip
    ap.add_argument("--timeout", type=float, default=60.0, help="sim seconds allowed per flight")
    ap.add_argument("--repeat", type=int, default=1, help="fly each goal this many times")
    ap.add_argument("--margin", type=float, default=MARGIN, help="planner inflation margin (m)")
    ap.add_argument("--tracking-margin-max", type=float, default=None, metavar="M",
                    help="the planner's --tracking-margin-max (default: the planner's; 0: off)")  # fmt: skip
    ap.add_argument("--yaw-lookahead", type=float, default=None, metavar="S",
                    help="the planner's --yaw-lookahead (default: the planner's; 0: along the velocity)")
    ap.add_argument("--logs", default=None, help="keep the simulator's and the planner's logs and stats here")
    ap.add_argument("--output", default=None, help="JSON path (default benchmarks/results/planning.json)")
    ap.add_argument("--px4", default=None, metavar="BUILD|scripted",
                    help="fly with PX4 in the loop: a px4_sitl_default build directory, or 'scripted' for "
                         "the PX4-like peer of tests/scripted_px4.py (see the module docstring)")  # fmt: skip
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="config override for the simulator, e.g. --set wind.speed_m_s=3 --set "
                         "'render.cameras=[{\"name\": \"front\", \"depth_model\": \"d435\"}]'; with "
                         "randomize.enabled=true each flight's wind is drawn (set_wind) and the run's depth "
                         "camera preset once")  # fmt: skip
    args = ap.parse_args()
    if args.settle is None:
        args.settle = 5.0 if args.px4 else 2.0
    if args.px4 and args.px4 != "scripted" and not (Path(args.px4) / "bin" / "px4").exists():
        ap.error(f"--px4 {args.px4}: no bin/px4 there (a px4_sitl_default build directory, or 'scripted')")

    scene = get_scene(args.scene, args.seed)
    start = np.asarray(scene.landmarks.get("start", scene.spawn_position), dtype=float)
    lo, hi = scene.bounds_min, scene.bounds_max
    bounds = [lo[0], lo[1], 0.5, hi[0], hi[1], min(hi[2], 8.0)]
    picks = args.goals or list(range(1, len(GOALS_XY) + 1))
    cfg = load_config(scene=args.scene, seed=args.seed, overrides=args.overrides)
    draws = np.random.default_rng([args.seed, 0x52414E44])
    if cfg.randomize.enabled:  # the depth camera is fixed when the run starts: one draw of it for the run
        cfg = cfg.randomize.apply(cfg, cfg.randomize.draw(draws, cfg.wind))
    if args.px4:  # what `droneulator run --px4` sets; the real PX4 instance 0 connects to 4560
        cfg.px4.enabled, cfg.vehicle.control_hz, cfg.vehicle.params = True, 250.0, "px4_quadx"
    runs = []
    if args.logs:
        Path(args.logs).mkdir(parents=True, exist_ok=True)
    run_log = Path(args.logs) / "run.log" if args.logs else None
    with (
        tempfile.TemporaryDirectory(prefix="droneulator-planning-") as scratch,
        launch_run(cfg, log=run_log) as run,
    ):
        tmp = args.logs or scratch
        client = run.client(timeout=60)
        sender = RosZenohNode.from_config(run.config.bridge, listen=(), connect=(run.zenoh_endpoint,))
        goal_pub = sender.publisher(f"/{run.config.bridge.namespace}/planner/goal", GOAL_TYPE)
        client.subscribe(["state", "events"], rate_hz=50)
        try:
            for k, i in enumerate(i for i in picks for _ in range(args.repeat)):
                gx, gy = GOALS_XY[i - 1]
                goal = np.array([gx, gy, ALTITUDE])
                conditions = None
                if cfg.randomize.enabled:  # each flight in its own wind
                    draw = cfg.randomize.draw(draws, cfg.wind)
                    w = draw.wind
                    client.request("set_wind", speed=w.speed_m_s, direction_deg=w.direction_deg,
                                   turbulence_scale=w.turbulence_scale,
                                   gust_speed=w.gust_speed_m_s)  # fmt: skip
                    conditions = draw.describe()
                    print(f"goal {i}: {conditions}", flush=True)
                r = fly_one(run, client, goal_pub, goal, start, bounds, Path(tmp), args, k + 1)
                r["goal_index"] = i
                r["conditions"] = conditions
                runs.append(r)
                print(f"goal {i} {goal.tolist()}: reached={r['reached']} time={r['flight_time_s']} "
                      f"length={r['path_length_m']:.2f} error={r['goal_error_m']:.3f} "
                      f"clearance={r['min_clearance_m']:.2f} collisions={r['collisions']} "
                      f"plan median/p99={r['plan_ms_median']:.1f}/{r['plan_ms_p99']:.1f} ms "
                      f"plans={r['plans']} failures={r['plan_failures']} stale={r['stale_plans']} "
                      f"stalls={r['stalls']} rtf={r['rtf']:.2f} "
                      f"tracking={r['tracking']}", flush=True)  # fmt: skip
                if not r["reached"]:
                    print((Path(tmp) / f"plan_{k + 1}.log").read_text()[-3000:])
        finally:
            sender.close()
            client.close()
    plan_ms = [x for r in runs for x in r["plan_ms"]]
    flights = [r["flight_time_s"] for r in runs if r["reached"]]
    summary = {
        "reached": f"{sum(r['reached'] for r in runs)}/{len(runs)}",
        "collisions": int(sum(r["collisions"] for r in runs)),
        "mean_goal_error_m": float(np.mean([r["goal_error_m"] for r in runs])),
        "min_clearance_m": float(min(r["min_clearance_m"] for r in runs)),
        "flight_time_s": [min(flights), max(flights)] if flights else None,
        "plan_ms_median": _pct(plan_ms, 50),
        "plan_ms_p99": _pct(plan_ms, 99),
        "rtf_min": float(min(r["rtf"] for r in runs)),
    }
    print("\n| goal | reached | flight time (s) | path (m) | straight (m) | goal error (m) "
          "| min clearance (m) | plan median / p99 (ms) | RTF |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|")
    for r in runs:
        i = r["goal_index"]
        ft = "-" if r["flight_time_s"] is None else f"{r['flight_time_s']:.2f}"
        print(f"| {i} | {'yes' if r['reached'] else 'no'} | {ft} | {r['path_length_m']:.2f} | "
              f"{r['straight_line_m']:.2f} | {r['goal_error_m']:.3f} | {r['min_clearance_m']:.2f} | "
              f"{r['plan_ms_median']:.1f} / {r['plan_ms_p99']:.1f} | {r['rtf']:.2f} |")  # fmt: skip
    print(json.dumps(summary, indent=1))
    mode = "api" if not args.px4 else ("px4 scripted" if args.px4 == "scripted" else f"px4 {args.px4}")
    summary["mean_true_goal_error_m"] = float(np.mean([r["true_goal_error_m"] for r in runs]))
    out = write("planning", {"scene": args.scene, "seed": args.seed, "altitude": ALTITUDE, "mode": mode,
                             "overrides": args.overrides, "summary": summary, "runs": runs},
                args.output)  # fmt: skip
    figure(args.scene, args.seed, runs, start, out.with_suffix(".png"))


if __name__ == "__main__":
    main()
