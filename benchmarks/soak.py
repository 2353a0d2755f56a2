"""A long soak of the whole runtime under load, with its render server and bridge killed mid-run.

``droneulator run`` in lockstep with 4 vehicles (``px0`` and ``px1`` flown by scripted PX4 peers,
tests/scripted_px4.py, which take off and loiter; ``uav0`` and ``uav1`` flown by the internal controller
over the API), every vehicle with a small front camera (RGB, depth, segmentation at 30 Hz) and the
browser UI (``--ui-port``), plus ``droneulator record`` writing every topic to an MCAP bag, and 50
WebSocket clients for ``--minutes`` of wall time:

* 20 API clients subscribed to every vehicle's state (10 Hz) and events, reading every message;
* 15 API clients sending commands (goto / velocity / hold for the internal vehicles, state, ping,
  scene_info, set_wind), one every 0.5-1.5 s;
* 10 UI tabs (``/ws`` of the UI server, each watching one vehicle) receiving its camera images, and
  reloading ``/api/config`` now and then;
* 5 API clients asking the scene and every vehicle's state in one go, as a dashboard would.

At 40 % of the run the render server, at 65 % the bridge, are killed with SIGKILL; the supervisor
restarts them (runtime/supervisor.py). Measured:

* **restarts**: the supervisor's restart reports and the new process ids, and how long each took;
* **frames**: a Zenoh subscriber takes every depth and colour image of every vehicle; lockstep loses
  no frame when each stream's stamps are contiguous at the camera period (1/30 s) from its first to
  its last image, across both kills; the recorder's bag is checked the same way;
* **RSS**: every process's resident memory sampled every ``--sample`` s; growth is the median of the
  last 10 % of samples over the median of the first 10 % after warm-up (for a restarted process,
  after its restart plus the warm-up); ``max_rss_growth_pct`` is the largest among the simulator's
  processes and the recorder (this script's own, which keeps every frame's stamp, is reported apart);
* **errors**: tracebacks and ERROR lines in the run's and the recorder's logs, other than the two
  reports of the deliberate kills, and exceptions in the clients.

The figures go to benchmarks/results/soak.json (``--json``) and are printed.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import random
import resource
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from collections import Counter, defaultdict
from pathlib import Path
from typing import Any

import zenoh
from _common import children, write
from websockets.sync.client import connect

from droneulator.api.client import ApiError
from droneulator.config import CameraConfig, VehicleSpec, load_config
from droneulator.recording.bag import read_stamp
from droneulator.runtime.launch import LaunchedRun, free_port, launch_run

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from scripted_px4 import ScriptedPX4  # noqa: E402  (the test suite's PX4 stand-in, one copy)

PERIOD_NS = round(1e9 / 30)
CLIENTS = {"state": 20, "command": 15, "ui": 10, "dashboard": 5}


def log_line(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)



def rss_kb(pid: int) -> int | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except OSError:
        return None
    return None


def px4_ports() -> int:
    """A base port whose next one is free too (PX4 instances 0 and 1 connect to base and base + 1)."""
    while True:
        base = free_port()
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", base + 1))
                return base
            except OSError:
                continue


class Stats:
    """Counters shared by the client threads."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.counts: Counter[str] = Counter()
        self.api_errors: Counter[str] = Counter()
        self.exceptions: list[str] = []

    def add(self, key: str, n: int = 1) -> None:
        with self.lock:
            self.counts[key] += n

    def api_error(self, code: str) -> None:
        with self.lock:
            self.api_errors[code] += 1

    def exception(self, who: str, exc: BaseException) -> None:
        with self.lock:
            self.exceptions.append(f"{who}: {type(exc).__name__}: {exc}")


class Frames:
    """Every image stamp per Zenoh key (taken from the CDR header, not decoded)."""

    def __init__(self, endpoint: str) -> None:
        conf = zenoh.Config()
        conf.insert_json5("mode", '"peer"')
        conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
        conf.insert_json5("scouting/multicast/enabled", "false")
        self.lock = threading.Lock()
        self.stamps: dict[str, list[int]] = defaultdict(list)
        self.session = zenoh.open(conf)
        self.subs = [
            self.session.declare_subscriber(k, self._on)
            for k in ("**/depth/image_raw", "**/color/image_raw/compressed")
        ]

    def _on(self, sample: zenoh.Sample) -> None:
        stamp = read_stamp(sample.payload.to_bytes()[:16], 4)
        if stamp is not None:
            with self.lock:
                self.stamps[str(sample.key_expr)].append(stamp)

    def total(self) -> int:
        with self.lock:
            return sum(len(v) for v in self.stamps.values())

    def close(self) -> None:
        for s in self.subs:
            s.undeclare()
        self.session.close()


def gaps(stamps: list[int]) -> dict[str, Any]:
    """Frames, and every step between consecutive stamps that is not one camera period."""
    bad = [(a, b) for a, b in zip(stamps, stamps[1:], strict=False) if b - a != PERIOD_NS]
    lost = sum(max(0, round((b - a) / PERIOD_NS) - 1) for a, b in bad)
    return {
        "frames": len(stamps),
        "sim_seconds": (stamps[-1] - stamps[0]) / 1e9 if stamps else 0.0,
        "irregular_steps": len(bad),
        "lost_frames": lost,
        "first_irregular": [[a, b] for a, b in bad[:5]],
    }


def bag_frames(path: Path) -> dict[str, dict[str, Any]]:
    """The same stamp check on the recorder's bag (log time = the sample's stamp), read from the bag's
    message indexes (each chunk's log times per channel) without decompressing a chunk: an hour's bag is
    gigabytes of images, which reading message by message held in memory until the machine ran out."""
    from mcap.records import Channel, MessageIndex
    from mcap.stream_reader import StreamReader

    stamps: dict[str, list[int]] = defaultdict(list)
    files = sorted(path.glob("*.mcap")) if path.is_dir() else [path]
    for file in files:
        times: dict[int, list[int]] = defaultdict(list)
        topics: dict[int, str] = {}
        with open(file, "rb") as f:
            for record in StreamReader(f, emit_chunks=True).records:
                if isinstance(record, MessageIndex):
                    times[record.channel_id].extend(t for t, _ in record.records)
                elif isinstance(record, Channel):  # the summary repeats every channel
                    topics[record.id] = record.topic
        for channel, ts in times.items():
            topic = topics.get(channel, "")
            if topic.endswith(("depth/image_raw", "color/image_raw/compressed")):
                stamps[topic].extend(ts)
    return {t: gaps(sorted(s)) for t, s in sorted(stamps.items())}


# ---------------------------------------------------------------------- the clients
def state_client(run: LaunchedRun, stop: threading.Event, stats: Stats, k: int) -> None:
    with run.client(timeout=60) as c:
        c.subscribe(["state", "events"], rate_hz=10, vehicle="*")
        while not stop.is_set():
            msg = c.next_message(timeout=5.0)
            stats.add("state_messages" if msg and msg.get("type") == "state" else "event_or_idle")


def command_client(
    run: LaunchedRun, stop: threading.Event, stats: Stats, k: int, homes: dict[str, list[float]]
) -> None:
    rng = random.Random(k)
    with run.client(timeout=60) as c:
        while not stop.is_set():
            name = rng.choice(sorted(homes))
            home = homes[name]
            op = rng.choice(["goto", "goto", "velocity", "hold", "state", "ping", "scene_info", "set_wind"])
            try:
                if op == "goto":
                    target = [home[0] + rng.uniform(-3, 3), home[1] + rng.uniform(-3, 3), rng.uniform(2, 4)]
                    c.goto(target, vehicle=name)
                elif op == "velocity":
                    c.velocity(rng.uniform(-0.5, 0.5), rng.uniform(-0.3, 0.3), vehicle=name)
                elif op == "hold":
                    c.request("hold", vehicle=name)
                elif op == "set_wind":
                    c.request("set_wind", speed=rng.uniform(0, 3), direction_deg=rng.uniform(0, 360))
                else:
                    c.request(op)
                stats.add(f"command_{op}")
            except ApiError as e:
                stats.api_error(e.code)
            stop.wait(rng.uniform(0.5, 1.5))


def dashboard_client(run: LaunchedRun, stop: threading.Event, stats: Stats, k: int, names: list[str]) -> None:
    rng = random.Random(100 + k)
    with run.client(timeout=60) as c:
        while not stop.is_set():
            c.scene_info()
            for name in names:
                c.state(vehicle=name)
            stats.add("dashboard_rounds")
            stop.wait(rng.uniform(1.0, 3.0))


def ui_client(port: int, stop: threading.Event, stats: Stats, k: int, names: list[str]) -> None:
    base = f"http://127.0.0.1:{port}"
    rng = random.Random(200 + k)
    with urllib.request.urlopen(f"{base}/", timeout=30) as r:
        r.read()
    while not stop.is_set():
        with connect(f"ws://127.0.0.1:{port}/ws", max_size=None, open_timeout=30) as ws:
            ws.send(json.dumps({"type": "ui", "watch": names[k % len(names)]}))
            until = time.monotonic() + rng.uniform(60, 120)  # a tab is reloaded now and then
            while not stop.is_set() and time.monotonic() < until:
                try:
                    msg = ws.recv(timeout=5.0)
                except TimeoutError:
                    stats.add("ui_idle_5s")
                    continue
                stats.add("ui_images" if isinstance(msg, bytes) else "ui_text")
        with urllib.request.urlopen(f"{base}/api/config", timeout=30) as r:
            json.loads(r.read())
        stats.add("ui_reloads")


def guarded(target: Any, stats: Stats, who: str, *args: Any) -> threading.Thread:
    def body() -> None:
        try:
            target(*args)
        except Exception as exc:  # every client failure is a finding: counted and reported
            stats.exception(who, exc)

    t = threading.Thread(target=body, name=who, daemon=True)
    t.start()
    return t


# ---------------------------------------------------------------------- the measures
def rss_growth(samples: list[tuple[float, str, int, int]], warm_s: float) -> dict[str, Any]:
    """Per role: the last process's RSS growth from after warm-up (or its restart + warm-up) to the end."""
    by_role: dict[str, list[tuple[float, int, int]]] = defaultdict(list)
    for t, role, pid, kb in samples:
        by_role[role].append((t, pid, kb))
    out = {}
    for role, rows in by_role.items():
        pid = rows[-1][1]
        mine = [(t, kb) for t, p, kb in rows if p == pid]
        start = mine[0][0] + warm_s if mine[0][0] > rows[0][0] else warm_s
        window = [kb for t, kb in mine if t >= start]
        if len(window) < 10:
            out[role] = {"pid": pid, "samples": len(window), "growth_pct": None}
            continue
        n = max(1, len(window) // 10)
        first, last = statistics.median(window[:n]), statistics.median(window[-n:])
        out[role] = {
            "pid": pid,
            "samples": len(window),
            "rss_mb_after_warmup": round(first / 1024, 1),
            "rss_mb_end": round(last / 1024, 1),
            "rss_mb_max": round(max(window) / 1024, 1),
            "growth_pct": round(100 * (last - first) / first, 2),
        }
    return out


#: what an unhandled error leaves in a run's log (its format carries no level: a traceback, an exception)
#: what marks a line as an error; a child the supervisor saw exit ("exited with code N") is one unless it
#: is one of the deliberate SIGKILLs (-9)
#: this benchmark's own process (50 clients and every frame's stamp, kept for the loss check: it grows by
#: design); sampled and reported, but not one of the simulator's processes judged by the growth
HARNESS = "soak clients"
ERROR_MARKS = ("Traceback", "Error:", "Exception", " failed", "ERROR", "CRITICAL", "Fatal", "panicked",
               "exited with code")  # fmt: skip


def scan_log(lines: list[str], expected: tuple[str, ...] = ("exited with code -9",)) -> dict[str, Any]:
    """Lines that look like an error, less those ``expected`` (by default the supervisor's reports of
    the deliberate SIGKILLs), and WebSocket connections closed on an error (1011)."""
    found = []
    for i, line in enumerate(lines):
        if any(m in line for m in ERROR_MARKS):
            found.append({"line": i + 1, "text": line[:300], "expected": any(e in line for e in expected)})
    unexpected = [f for f in found if not f["expected"]]
    return {
        "expected": len(found) - len(unexpected),
        "unhandled": len(unexpected),
        "tracebacks": sum("Traceback" in line for line in lines),
        "websocket_closes_1011": sum("1011 (internal error)" in line for line in lines),
        "lines": unexpected[:20],
    }


def kill_and_wait(run: LaunchedRun, role: str, timeout: float = 180.0) -> dict[str, Any]:
    old = children(run.pid)[role]
    os.kill(old, signal.SIGKILL)
    t0 = time.monotonic()
    log_line(f"SIGKILL {role} (pid {old})")
    while True:
        new = children(run.pid).get(role)
        if new is not None and new != old:
            break
        if time.monotonic() - t0 > timeout or not run.running():
            return {"killed_pid": old, "restarted": False}
        time.sleep(0.1)
    back = time.monotonic() - t0
    log_line(f"{role} restarted as pid {new} after {back:.1f} s")
    return {"killed_pid": old, "new_pid": new, "restarted": True, "respawn_s": round(back, 2)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--minutes", type=float, default=60.0, help="wall minutes of soak (default 60)")
    ap.add_argument("--quick", action="store_true", help="3 minutes, for checking the script")
    ap.add_argument("--scene", default="default", help="scene (default default: open ground)")
    ap.add_argument("--sample", type=float, default=None, help="RSS sample period, s (default minutes/6)")
    ap.add_argument("--keep", action="store_true", help="keep the run's log and bag (default: deleted)")
    ap.add_argument("--json", default=None, help="output path (default benchmarks/results/soak.json)")
    ap.add_argument(
        "--max-bag-size",
        default="1G",
        help="the recorder's bag splits into files of this size (default 1G; 0: one file, whose chunk "
        "index the writer holds in memory until the end)",
    )
    ap.add_argument(
        "--core-dumps",
        action="store_true",
        help="let a crashing child write a core file (core_pattern decides where) for gdb",
    )
    args = ap.parse_args()
    if args.core_dumps:
        resource.setrlimit(resource.RLIMIT_CORE, (resource.RLIM_INFINITY, resource.RLIM_INFINITY))
    minutes = 3.0 if args.quick else args.minutes
    duration = 60.0 * minutes
    warm = min(300.0, 0.1 * duration)
    sample_s = args.sample or max(1.0, minutes / 6)

    cfg = load_config(scene=args.scene)
    cfg.render.cameras = [CameraConfig(name="front", width=160, height=120)]
    cfg.render.shadow_map_size = 1024
    cfg.vehicle.control_hz = 250.0  # PX4's HIL rate
    cfg.px4.base_port = px4_ports()
    cfg.vehicles = [
        VehicleSpec(name="px0", controlled_by="px4", params="px4_quadx"),
        VehicleSpec(name="px1", controlled_by="px4", params="px4_quadx"),
        VehicleSpec(name="uav0"),
        VehicleSpec(name="uav1"),
    ]
    work = Path(tempfile.mkdtemp(prefix="droneulator-soak-"))
    run_log, rec_log, bag = work / "run.log", work / "record.log", work / "soak"
    ui_port = free_port()
    log_line(f"starting the run (log {run_log}); {minutes:g} min soak")
    run = launch_run(cfg, ["--ui-port", str(ui_port)], log=run_log, start_timeout=300)
    stop = threading.Event()
    stats = Stats()
    rec_out = open(rec_log, "w")  # noqa: SIM115 (closed at the end)
    rec = subprocess.Popen(
        [
            *(sys.executable, "-m", "droneulator.cli", "record", "-o", str(bag)),
            *("--zenoh", run.zenoh_endpoint, "--max-bag-size", args.max_bag_size),
        ],
        stdout=rec_out,
        stderr=subprocess.STDOUT,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    frames = Frames(run.zenoh_endpoint)
    sinks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(2)]
    for s in sinks:
        s.bind(("127.0.0.1", 0))  # where the peers send their offboard MAVLink (nobody reads it)
    px4s = [ScriptedPX4(cfg.px4.base_port + k, s.getsockname()[1], sysid=k + 1) for k, s in enumerate(sinks)]
    samples: list[tuple[float, str, int, int]] = []
    result: dict[str, Any] = {}
    measured_lines: int | None = None  # the run's log lines by the soak's end: later ones are the shutdown
    try:
        with run.client(timeout=300) as c:
            c.subscribe(["state"], vehicle="*", rate_hz=5)
            names = [v["name"] for v in c.scene_info()["vehicles"]]
            deadline = time.monotonic() + 300
            while any(p.origin is None for p in px4s):  # PX4 arms only with a position estimate
                if time.monotonic() > deadline or any(p.error for p in px4s):
                    raise RuntimeError(f"no GPS fix on the PX4 peers: {[p.error for p in px4s]}")
                time.sleep(0.1)
            for px4 in px4s:
                px4.takeoff()
            internal = ["uav0", "uav1"]
            for name in internal:
                c.takeoff(3.0, vehicle=name)
            for name in names:
                c.wait_until(lambda s: s["position"][2] > 2.0, timeout=600, vehicle=name)
            homes = {n: c.state(vehicle=n)["position"] for n in internal}
            t_flying = c.state()["t"]
        log_line(f"all 4 airborne at sim t {t_flying:.1f} s; starting {sum(CLIENTS.values())} clients")
        threads = []
        for k in range(CLIENTS["state"]):
            threads.append(guarded(state_client, stats, f"state{k}", run, stop, stats, k))
        for k in range(CLIENTS["command"]):
            threads.append(guarded(command_client, stats, f"command{k}", run, stop, stats, k, homes))
        for k in range(CLIENTS["ui"]):
            threads.append(guarded(ui_client, stats, f"ui{k}", ui_port, stop, stats, k, names))
        for k in range(CLIENTS["dashboard"]):
            threads.append(guarded(dashboard_client, stats, f"dashboard{k}", run, stop, stats, k, names))

        t0 = time.monotonic()
        kills = {"render_server": 0.40 * duration, "bridge": 0.65 * duration}
        restarts: dict[str, Any] = {}
        next_sample = next_progress = 0.0
        with run.client(timeout=300) as probe:
            sim0 = probe.state()["t"]
            while (now := time.monotonic() - t0) < duration:
                if not run.running():
                    raise RuntimeError("the run exited:\n" + run.log.tail())
                for role, at in kills.items():
                    if role not in restarts and now >= at:
                        restarts[role] = kill_and_wait(run, role)
                if now >= next_sample:
                    procs = {"run (supervisor, API, UI)": run.pid, **children(run.pid)}
                    procs |= {"recorder": rec.pid, HARNESS: os.getpid()}
                    for role, pid in procs.items():
                        kb = rss_kb(pid)
                        if kb is not None:
                            samples.append((now, role, pid, kb))
                    next_sample = now + sample_s
                if now >= next_progress:
                    sim = probe.state()["t"] - sim0
                    with stats.lock:
                        counts = dict(stats.counts)
                        n_exc = len(stats.exceptions)
                    log_line(
                        f"{now / 60:5.1f}/{minutes:g} min, sim {sim:7.1f} s, frames {frames.total()}, "
                        f"state msgs {counts.get('state_messages', 0)}, "
                        f"UI images {counts.get('ui_images', 0)}, "
                        f"client exceptions {n_exc}"
                    )
                    next_progress = now + max(10.0, duration / 30)
                time.sleep(0.2)
            sim_s = probe.state()["t"] - sim0
        wall = time.monotonic() - t0
        measured_lines = len(run.log.lines())
        stop.set()
        for t in threads:
            t.join(timeout=30)
        alive = {n: bool(p) for n, p in {"run": run.running(), "recorder": rec.poll() is None}.items()}
        alive |= {f"px4 {p.sysid}": p.error is None for p in px4s}
        px4_errors = [repr(p.error) for p in px4s if p.error is not None]
        time.sleep(1.0)
        frames.close()
        rec.send_signal(signal.SIGINT)
        rec_code = rec.wait(120)
        stream = {k: gaps(sorted(v)) for k, v in sorted(frames.stamps.items())}
        log_line("reading the bag back")
        recorded = bag_frames(bag) if bag.exists() else {}
        reports = sum("restarting it" in line for line in run.log.lines())
        with stats.lock:
            result = {
                "scene": args.scene,
                "vehicles": "px0, px1 on scripted PX4 peers; uav0, uav1 internal",
                "camera": "front 160x120, 30 Hz, RGB + depth + segmentation, per vehicle",
                "clients": CLIENTS,
                "minutes": minutes,
                "wall_seconds": round(wall, 1),
                "sim_seconds": round(sim_s, 1),
                "real_time_factor": round(sim_s / wall, 3),
                "restarts": {"supervisor_reports": reports, **restarts},
                "alive_at_end": alive,
                "px4_errors": px4_errors,
                "recorder_exit_code": rec_code,
                "frames_subscriber": stream,
                "frames_bag": recorded,
                "bag_files": len(list(bag.glob("*.mcap"))) if bag.is_dir() else int(bag.exists()),
                "lost_frames_subscriber": sum(v["lost_frames"] for v in stream.values()),
                "irregular_steps_subscriber": sum(v["irregular_steps"] for v in stream.values()),
                "lost_frames_bag": sum(v["lost_frames"] for v in recorded.values()),
                "irregular_steps_bag": sum(v["irregular_steps"] for v in recorded.values()),
                "rss_sample_s": sample_s,
                "warmup_s": warm,
                "rss": rss_growth(samples, warm),
                "client_counts": dict(stats.counts),
                "client_api_errors": dict(stats.api_errors),
                "client_exceptions": len(stats.exceptions),
                "client_exception_examples": stats.exceptions[:20],
            }
    finally:
        stop.set()
        for px4 in px4s:
            px4.close()
        with contextlib.suppress(Exception):
            frames.close()
        if rec.poll() is None:
            rec.send_signal(signal.SIGINT)
            with contextlib.suppress(subprocess.TimeoutExpired):
                rec.wait(60)
        rec_out.close()
        run.stop(timeout=30)
    run_lines = run_log.read_text(errors="replace").splitlines()
    end = len(run_lines) if measured_lines is None else measured_lines
    result["errors_run_log"] = scan_log(run_lines[:end])
    result["run_log_after_the_soak"] = run_lines[end:][:20]  # the peers closed, the run stopped: not scanned
    result["errors_recorder_log"] = scan_log(rec_log.read_text(errors="replace").splitlines())
    result["unhandled_errors"] = (
        result["errors_run_log"]["unhandled"]
        + result["errors_recorder_log"]["unhandled"]
        + result.get("client_exceptions", 0)
    )
    growth = [
        v["growth_pct"]
        for role, v in result.get("rss", {}).items()
        if v.get("growth_pct") is not None and role != HARNESS
    ]
    result["max_rss_growth_pct"] = max(growth) if growth else None  # the simulator's processes
    result["rss_series"] = [[round(t, 1), role, pid, kb] for t, role, pid, kb in samples]
    if args.keep:
        result["kept"] = str(work)
    else:
        for f in (run_log, rec_log):
            f.unlink(missing_ok=True)
        if bag.is_dir():
            for f in bag.iterdir():
                f.unlink()
            bag.rmdir()
        bag.unlink(missing_ok=True)
        with contextlib.suppress(OSError):
            work.rmdir()
    summary = {k: v for k, v in result.items() if k not in ("rss_series", "frames_subscriber", "frames_bag")}
    print(json.dumps(summary, indent=2))
    write("soak", result, args.json)


if __name__ == "__main__":
    main()
