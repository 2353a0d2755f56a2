"""Fuzz the simulator's two command surfaces: every WebSocket op and every ROS command topic.

``droneulator run`` in lockstep (default scene, one vehicle with a small camera) gets ``--messages``
messages, 80 % over the WebSocket API (``--connections`` connections in parallel), 20 % as Zenoh
samples on the ROS command topics the dynamics server subscribes to (cmd_vel, goal_pose, position_cmd,
setpoint_raw/attitude, command/motor_speed, fault).

WebSocket messages, for an op drawn from droneulator/commands/ops.py (``OPS``): a valid request (values
drawn inside the op's schema), a field of the wrong type, a number out of its bounds (or NaN written as
a bare ``NaN``), a required field missing, an extra field, an unknown op, garbage that is not JSON, JSON
that is not an object, a bad ``id``, a binary frame of random bytes, a message over the API's 64 KiB
limit, and (rarely) one over the transport limit, which the server answers by closing the connection
with 1009 (docs/api.md), after which the client reconnects. Every other message must be answered: a
reply with its ``id`` (``id`` null when the message could not be read), ``ok`` or an error ``code``.
One not answered within ``--reply-timeout`` s counts as unanswered.

ROS samples: random bytes, a valid CDR message of the topic's type with random values (NaN, infinities,
huge numbers, empty and long sequences and strings, random frame ids), that message truncated, its
encapsulation header corrupted. They get no answer by design; the check is that the run stays up.

At the end: every process alive with the pid it started with (no restart), the run's log scanned for
tracebacks, and the simulator still flies: faults cleared, the vehicle reset, taken off to 2 m, and
reaching it. Counts per op, per category and per error code go to benchmarks/results/fuzz.json.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import random
import tempfile
import threading
import time
from collections import Counter, defaultdict
from pathlib import Path
from typing import Any

import zenoh
from _common import write
from rosbags.interfaces import Nodetype
from soak import children, scan_log
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import ClientConnection, connect

from droneulator.commands.ops import OPS, Arg
from droneulator.config import CameraConfig, load_config
from droneulator.config.faults import FAULT_KINDS
from droneulator.ros import messages
from droneulator.ros.topics import TYPES, vehicle_topics
from droneulator.runtime.launch import launch_run

ROS_KEYS = ("cmd_vel", "goal_pose", "position_cmd", "attitude_target", "motor_speed", "fault")
#: share of each WebSocket category (relative weights)
CATEGORIES = {
    "valid": 30,
    "invalid_type": 14,
    "out_of_range": 10,
    "missing_field": 8,
    "extra_field": 10,
    "unknown_op": 3,
    "garbage_json": 8,
    "not_an_object": 3,
    "bad_id": 3,
    "binary": 6,
    "too_large": 2,
}
OVER_TRANSPORT_EVERY = 2000  # one message in this many is past the transport limit (connection closed)
VALID_SKIP = {"reset": {"scene", "seed", "vegetation", "light"}}  # valid but rebuilds the scene: slow
NAMED = {
    "altitude": (1.0, 5.0),
    "speed": (0.3, 3.0),
    "duration": (0.5, 10.0),
    "forward": (-1.0, 1.0),
    "yaw_rate": (-0.5, 0.5),
    "thrust": (0.0, 1.0),
    "efficiency": (0.0, 1.0),
    "rate": (0.0, 1.0),
    "litres": (0.0, 10.0),
}


# ---------------------------------------------------------------------- WebSocket messages
def valid_value(arg: Arg, op: str, rng: random.Random, vehicle: str) -> Any:
    if arg.name == "vehicle":
        return rng.choice([vehicle, vehicle, "*", "nobody"])
    if arg.name == "kind":
        return rng.choice(sorted(FAULT_KINDS))
    t = arg.type
    if t == "number":
        lo, hi = arg.bounds or NAMED.get(arg.name, (-math.pi, math.pi))
        return rng.uniform(lo, min(hi, lo + 10.0))
    if t == "integer":
        lo, hi = arg.bounds or (0, 3)
        return rng.randint(int(lo), int(min(hi, lo + 100)))
    if t == "boolean":
        return rng.random() < 0.5
    if t == "vec3":
        if arg.name == "position":
            return [rng.uniform(-8, 8), rng.uniform(-8, 8), rng.uniform(0.5, 6)]
        return [rng.uniform(-1, 1) for _ in range(3)]
    if t == "vec4":
        return [rng.uniform(0, 1) for _ in range(4)]
    if t == "streams":
        return rng.choice([["state"], ["events"], ["state", "events"]])
    if t == "strings":
        return [rng.choice(["left", "right", "all", "x"])]
    if t == "light":
        return {}
    return rng.choice(["uav0", "front", "", "x" * 40])


def wrong_type(arg: Arg, rng: random.Random) -> Any:
    choices: list[Any] = [True, None, "1.5", {"a": 1}, [], [1, "2", 3], 1e308, -7, "", [[1, 2, 3]]]
    if arg.type in ("number", "integer"):
        choices += [[1.0], "NaN", False]
    if arg.type.startswith("vec"):
        choices += [[1, 2], [1, 2, 3, 4, 5], [None, 1, 2], ["a", "b", "c"], 3.0]
    if arg.type in ("string", "streams", "strings"):
        choices += [3, ["state", 3], ["nope"], [""]]
    return rng.choice(choices)


def out_of_range(arg: Arg, rng: random.Random) -> Any:
    if arg.bounds is not None and arg.type in ("number", "integer"):
        lo, hi = arg.bounds
        return rng.choice([lo - 1, hi + 1, hi * 1000 + 1, -1e300]) if arg.type == "number" else int(hi) + 1
    if arg.type == "number":
        return rng.choice([1e12, -1e12, 1e308, -5e5])
    if arg.type == "integer":
        return rng.choice([-1, 2**63, -(2**70), 10**6])
    if arg.type.startswith("vec"):
        n = 3 if arg.type == "vec3" else 4
        return [rng.choice([1e9, -1e9, 0.0, 1e308]) for _ in range(n)]
    return "z" * rng.choice([1000, 60000])


def ws_message(rng: random.Random, mid: int, vehicle: str) -> tuple[str, str, str | bytes, bool]:
    """(category, op, payload, whether the reply carries ``id``)."""
    category = rng.choices(list(CATEGORIES), weights=list(CATEGORIES.values()))[0]
    op = rng.choice(sorted(OPS))
    spec = OPS[op]
    skip = VALID_SKIP.get(op, set())
    args = {a.name: valid_value(a, op, rng, vehicle) for a in spec.args if a.required}
    for a in spec.args:
        if not a.required and a.name not in skip and rng.random() < 0.4:
            args[a.name] = valid_value(a, op, rng, vehicle)
    if op == "fault" and "kind" in args:  # the kind's own parameters only, else a valid one is refused
        own = FAULT_KINDS[args["kind"]][1]
        args = {k: v for k, v in args.items() if k in own or k in ("kind", "duration", "vehicle")}
        args["duration"] = rng.uniform(0.2, 3.0)
    if op == "subscribe" and "rate_hz" in args:
        args["rate_hz"] = rng.uniform(0.1, 5.0)  # valid, without flooding the connection
    msg: dict[str, Any] = {**args, "id": mid, "op": op}
    if category == "invalid_type" and spec.args:
        a = rng.choice(spec.args)
        msg[a.name] = wrong_type(a, rng)
    elif category == "out_of_range" and spec.args:
        a = rng.choice(spec.args)
        msg[a.name] = out_of_range(a, rng)
        if rng.random() < 0.1 and a.type == "number":
            text = json.dumps({**msg, a.name: 0.5}).replace(": 0.5", ": " + rng.choice(["NaN", "Infinity"]))
            return category, op, text, True
    elif category == "missing_field":
        required = [a.name for a in spec.args if a.required]
        if required:
            del msg[rng.choice(required)]
        else:
            del msg["op"]
            return category, op, json.dumps(msg), True
    elif category == "extra_field":
        extra = rng.choice(["extra", "Vehicle", "position2", "__proto__", "x" * 200])
        msg[extra] = rng.choice([1, None, "a"])
    elif category == "unknown_op":
        msg["op"] = rng.choice(["fly", "", "TAKEOFF", "takeoff ", "reset\x00", "ö" * 10])
        op = "(unknown)"
    elif category == "garbage_json":
        good = json.dumps(msg)
        cut = rng.randint(0, max(0, len(good) - 1))
        noise = "".join(chr(rng.randint(1, 0x2FFF)) for _ in range(50))
        text = rng.choice([good[:cut], good + "}", good.replace('"', "'"), "{" * 500, "[" * 100_000, noise])
        return category, op, text, False
    elif category == "not_an_object":
        return category, op, json.dumps(rng.choice([[msg], 3, "ping", None, True])), False
    elif category == "bad_id":
        msg["id"] = rng.choice([1.5, None, [1], {"a": 1}, True])
        return category, op, json.dumps(msg), False
    elif category == "binary":
        data = bytes(rng.getrandbits(8) for _ in range(rng.randint(0, 300)))
        if rng.random() < 0.3:
            data = json.dumps(msg).encode()  # JSON in a binary frame: read as JSON
            return category, op, data, True
        return category, op, data, False
    elif category == "too_large":
        msg["pad"] = "x" * rng.randint(70_000, 900_000)
        return category, op, json.dumps(msg), False
    return category, op, json.dumps(msg), True


class WsFuzzer:
    """One connection's share of the WebSocket messages: send, then wait for the answer."""

    def __init__(self, url: str, n: int, seed: int, vehicle: str, reply_timeout: float, stats: Stats) -> None:
        self.url, self.n, self.vehicle, self.timeout = url, n, vehicle, reply_timeout
        self.rng = random.Random(seed)
        self.stats = stats
        self.seed = seed

    def _connect(self) -> ClientConnection:
        return connect(self.url, max_size=None, open_timeout=60, close_timeout=5).__enter__()

    def run(self) -> None:
        ws = self._connect()
        try:
            for k in range(self.n):
                mid = self.seed * 10_000_000 + k
                if k % OVER_TRANSPORT_EVERY == OVER_TRANSPORT_EVERY - 1:
                    ws = self._over_transport(ws)
                    continue
                category, op, payload, has_id = ws_message(self.rng, mid, self.vehicle)
                try:
                    ws.send(payload)
                    answer = self._answer(ws, mid if has_id else None)
                except ConnectionClosed as e:
                    answer = f"connection closed ({e.rcvd.code if e.rcvd else 'none'})"
                    ws = self._connect()
                self.stats.count(category, op, answer, payload)
        finally:
            ws.close()

    def _answer(self, ws: ClientConnection, mid: int | None) -> str:
        deadline = time.monotonic() + self.timeout
        while True:
            try:
                raw = ws.recv(timeout=max(0.01, deadline - time.monotonic()))
            except TimeoutError:
                return "UNANSWERED"
            msg = json.loads(raw)
            if msg.get("type") in ("state", "event"):
                continue
            if mid is not None and msg.get("id") not in (mid, None):
                continue  # a late reply to an earlier message of this connection
            if msg.get("ok") is True:
                return "ok"
            code = (msg.get("error") or {}).get("code")
            return f"error:{code}" if code else "REPLY WITHOUT CODE"

    def _over_transport(self, ws: ClientConnection) -> ClientConnection:
        """A message past the transport limit: websockets closes the connection with 1009."""
        try:
            ws.send(json.dumps({"id": 1, "op": "ping", "pad": "x" * 2_000_000}))
            self._answer(ws, 1)
            outcome = "answered"
        except ConnectionClosed as e:
            outcome = f"closed {e.rcvd.code if e.rcvd else 'none'}"
        self.stats.count("over_transport_limit", "ping", f"connection {outcome}", "")
        ws.close()
        return self._connect()


class Stats:
    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.per_op: dict[str, Counter[str]] = defaultdict(Counter)
        self.per_category: dict[str, Counter[str]] = defaultdict(Counter)
        self.codes: Counter[str] = Counter()
        self.unanswered: list[str] = []
        self.total = 0

    def count(self, category: str, op: str, answer: str, payload: str | bytes) -> None:
        with self.lock:
            self.total += 1
            self.per_op[op][answer] += 1
            self.per_category[category][answer] += 1
            self.codes[answer] += 1
            if answer in ("UNANSWERED", "REPLY WITHOUT CODE") and len(self.unanswered) < 20:
                self.unanswered.append(f"{category} {op}: {payload[:200]!r}")


# ---------------------------------------------------------------------- ROS samples
def random_value(rng: random.Random, desc: tuple[Any, Any]) -> Any:
    import numpy as np

    node, info = desc
    if node == Nodetype.NAME:
        return random_message(rng, info)
    if node == Nodetype.BASE:
        typ = info[0]
        if typ == "string":
            return rng.choice(
                [
                    "",
                    "map",
                    "world",
                    "odom",
                    "x" * rng.randint(0, 2000),
                    '{"kind": "gps_loss"}',
                    '{"kind": "rotor", "rotor": 9}',
                    "[1,2]",
                    "{",
                    '{"vehicle": "uav1"}',
                ]
            )
        if typ.startswith("float"):
            huge = 1e300 if typ == "float64" else 3e38
            return rng.choice([0.0, 1.0, -1.0, math.nan, math.inf, -math.inf, huge, rng.uniform(-10, 10)])
        if typ == "bool":
            return rng.random() < 0.5
        bits = int("".join(c for c in typ if c.isdigit()) or 8)
        if typ.startswith(("uint", "byte", "char")):
            return rng.randint(0, 2**bits - 1)
        return rng.randint(-(2 ** (bits - 1)), 2 ** (bits - 1) - 1)
    (sub_node, sub_info), length = info
    n = length if node == Nodetype.ARRAY else rng.choice([0, 1, 3, 4, 5, 1000])
    if sub_node == Nodetype.BASE and sub_info[0] != "string":
        values = [random_value(rng, (sub_node, sub_info)) for _ in range(n)]
        return np.array(values, dtype=_np_type(sub_info[0]))
    return [random_value(rng, (sub_node, sub_info)) for _ in range(n)]


def _np_type(typ: str) -> Any:
    import numpy as np

    return {
        "float64": np.float64,
        "float32": np.float32,
        "uint8": np.uint8,
        "int8": np.int8,
        "uint16": np.uint16,
        "int16": np.int16,
        "uint32": np.uint32,
        "int32": np.int32,
        "uint64": np.uint64,
        "int64": np.int64,
        "bool": np.bool_,
        "byte": np.uint8,
        "char": np.uint8,
    }[typ]


def random_message(rng: random.Random, typename: str) -> Any:
    fields = messages.TYPESTORE.fielddefs[typename][1]
    return messages.TYPESTORE.types[typename](**{name: random_value(rng, desc) for name, desc in fields})


def ros_payload(rng: random.Random, typename: str) -> tuple[str, bytes]:
    kind = rng.choice(["random_bytes", "valid_random", "valid_random", "truncated", "bad_header"])
    if kind == "random_bytes":
        return kind, bytes(rng.getrandbits(8) for _ in range(rng.randint(0, 400)))
    data = bytes(messages.TYPESTORE.serialize_cdr(random_message(rng, typename), typename))
    if kind == "truncated":
        return kind, data[: rng.randint(0, max(0, len(data) - 1))]
    if kind == "bad_header":
        return kind, bytes([rng.getrandbits(8), rng.getrandbits(8)]) + data[2:]
    return kind, data


def ros_fuzz(endpoint: str, n: int, seed: int, counts: dict[str, Counter[str]]) -> None:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    rng = random.Random(seed)
    topics = vehicle_topics("droneulator")
    session = zenoh.open(conf)
    try:
        pubs = {k: session.declare_publisher(topics[k].lstrip("/")) for k in ROS_KEYS}
        time.sleep(1.0)  # let the dynamics server's subscriptions match
        for _ in range(n):
            key = rng.choice(ROS_KEYS)
            kind, payload = ros_payload(rng, TYPES[key])
            pubs[key].put(payload)
            counts[key][kind] += 1
            time.sleep(0.002)
    finally:
        session.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--messages", type=int, default=100_000, help="messages in all (default 100000)")
    ap.add_argument("--connections", type=int, default=4, help="WebSocket connections (default 4)")
    ap.add_argument("--ros-share", type=float, default=0.2, help="share of the messages sent on ROS topics")
    ap.add_argument("--reply-timeout", type=float, default=30.0, help="s to wait for each reply (default 30)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--json", default=None, help="output path (default benchmarks/results/fuzz.json)")
    args = ap.parse_args()

    cfg = load_config(scene="default")
    cfg.render.cameras = [CameraConfig(name="front", width=64, height=48)]
    cfg.render.shadow_map_size = 512
    log_path = Path(tempfile.mkdtemp(prefix="droneulator-fuzz-")) / "run.log"
    run = launch_run(cfg, log=log_path, start_timeout=300)
    n_ros = int(args.messages * args.ros_share)
    n_ws = args.messages - n_ros
    stats = Stats()
    ros_counts: dict[str, Counter[str]] = defaultdict(Counter)
    result: dict[str, Any] = {}
    try:
        with run.client(timeout=120) as c:
            vehicle = c.scene_info()["vehicles"][0]["name"]
            c.takeoff(2.0)
        kids0 = children(run.pid)
        per = [n_ws // args.connections + (k < n_ws % args.connections) for k in range(args.connections)]
        errors: list[str] = []

        def guard(fn: Any, *a: Any) -> threading.Thread:
            def body() -> None:
                try:
                    fn(*a)
                except Exception as exc:  # a fuzzer thread's failure is a finding: reported
                    errors.append(f"{type(exc).__name__}: {exc}")

            t = threading.Thread(target=body, daemon=True)
            t.start()
            return t

        t0 = time.monotonic()
        threads = [
            guard(WsFuzzer(run.url, n, args.seed + k + 1, vehicle, args.reply_timeout, stats).run)
            for k, n in enumerate(per)
        ]
        threads.append(guard(ros_fuzz, run.zenoh_endpoint, n_ros, args.seed, ros_counts))
        step = max(1, args.messages // 20)
        shown = 0
        while any(t.is_alive() for t in threads):
            time.sleep(1.0)
            with stats.lock:
                done = stats.total + sum(sum(v.values()) for v in ros_counts.values())
                codes = dict(stats.codes)
            if done >= shown + step:
                shown = done
                rate = done / (time.monotonic() - t0)
                print(
                    f"[{time.strftime('%H:%M:%S')}] {done}/{args.messages} messages ({rate:.0f}/s), "
                    f"unanswered {codes.get('UNANSWERED', 0)}, run alive {run.running()}",
                    flush=True,
                )
        wall = time.monotonic() - t0
        kids1 = children(run.pid)
        alive = run.running() and all(kids1.get(k) == p for k, p in kids0.items())
        with run.client(timeout=120) as c:  # the simulator still flies
            c.request("fault_clear", vehicle=vehicle)
            c.request("set_wind", speed=0.0)
            c.reset(position=[0.0, 0.0, 0.0])
            c.takeoff(2.0)
            c.wait_until(lambda s: s["position"][2] > 1.8 and s["mode"] == "hold", timeout=300)
            z = c.state()["position"][2]
        flies = z > 1.8
        with stats.lock:
            result = {
                "messages": args.messages,
                "websocket_messages": stats.total,
                "ros_samples": sum(sum(v.values()) for v in ros_counts.values()),
                "connections": args.connections,
                "wall_seconds": round(wall, 1),
                "messages_per_s": round(args.messages / wall, 1),
                "unanswered": stats.codes.get("UNANSWERED", 0),
                "replies_without_code": stats.codes.get("REPLY WITHOUT CODE", 0),
                "unanswered_examples": stats.unanswered,
                "fuzzer_errors": errors,
                "processes_alive_same_pids": alive,
                "pids_before": kids0,
                "pids_after": kids1,
                "flies_after": flies,
                "altitude_after_takeoff_m": round(z, 2),
                "answers": dict(stats.codes.most_common()),
                "per_category": {k: dict(v.most_common()) for k, v in sorted(stats.per_category.items())},
                "per_op": {k: dict(v.most_common()) for k, v in sorted(stats.per_op.items())},
                "ros_per_topic": {k: dict(v.most_common()) for k, v in sorted(ros_counts.items())},
            }
    finally:
        run.stop(timeout=30)
    lines = log_path.read_text(errors="replace").splitlines()
    # the bad samples are the fuzz's own doing: the dynamics server says so for the first of each burst
    result["errors_run_log"] = scan_log(lines, expected=("dropped a bad",))
    result["restarts_in_log"] = sum("restarting it" in line for line in lines)
    # the dynamics server's word on the ROS samples: undecodable ones dropped, decoded ones refused
    result["ros_bad_samples_logged"] = sum("dropped a bad" in line for line in lines)
    result["ros_rejections_logged"] = sum("command rejected (" in line for line in lines)
    result["ros_rejections_summarised"] = sum(
        int(line.split(": ", 1)[1].split()[0])
        for line in lines
        if "commands rejected (" in line and line.split(": ", 1)[-1].split()[0].isdigit()
    )
    summary = {k: v for k, v in result.items() if k not in ("per_op",)}
    print(json.dumps(summary, indent=2))
    write("fuzz", result, args.json)
    os.unlink(log_path)


if __name__ == "__main__":
    main()
