"""Fly a list of waypoints over the WebSocket API with nothing but the ``websockets`` package.

This is what a client in any language does (docs/api.md): send one JSON request per WebSocket
message, match the reply by its ``id``, and read the pushed ``state`` and ``event`` messages that
arrive on the same socket in between. No droneulator import.

    droneulator run --scene default              # in another terminal
    python examples/waypoints_ws.py              # a 3 m square around the spawn point at 2 m
    python examples/waypoints_ws.py --waypoints "2,0,2 2,2,3 0,2,2" --speed 1.5

Waypoints are x,y,z in metres relative to the scene's spawn point (world frame, ENU, z up). The
script takes off, flies to each waypoint and waits for its ``arrived`` event, shows what an
error reply looks like (a target below the ground), lands, and exits non-zero if the flight failed.
``--summary FILE`` writes what happened as JSON.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import sys
import time
from typing import Any

from websockets.exceptions import WebSocketException
from websockets.sync.client import ClientConnection, connect

DEFAULT_WAYPOINTS = "3,0,2 3,3,2.5 0,3,2 0,0,2"


class ApiError(Exception):
    """An ``"ok": false`` reply: ``code`` is machine readable, ``message`` says what to fix."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(f"{code}: {message}")
        self.code = code


class Api:
    """One WebSocket connection: requests with replies matched by id, pushed messages kept in order."""

    def __init__(self, ws: ClientConnection, timeout: float) -> None:
        self.ws = ws
        self.timeout = timeout
        self.ids = itertools.count(1)
        self.events: list[dict[str, Any]] = []  # pushed events not yet consumed, oldest first
        self.state: dict[str, Any] | None = None  # the latest pushed state
        self.states_received = 0

    def _receive(self, timeout: float) -> dict[str, Any]:
        msg = json.loads(self.ws.recv(timeout=timeout))
        if msg.get("type") == "state":
            self.state = msg["state"]
            self.states_received += 1
        elif msg.get("type") == "event":
            self.events.append(msg["event"])
        return msg

    def call(self, op: str, **fields: Any) -> dict[str, Any]:
        """Send ``op`` and return its ``result``; raise :class:`ApiError` on an error reply."""
        rid = next(self.ids)
        self.ws.send(json.dumps({"id": rid, "op": op, **fields}))
        deadline = time.monotonic() + self.timeout
        while True:
            msg = self._receive(max(0.01, deadline - time.monotonic()))
            if "ok" not in msg:
                continue  # a pushed state or event, kept by _receive
            if msg["id"] != rid:
                raise RuntimeError(f"reply to request {msg['id']} while waiting for {rid}")
            if not msg["ok"]:
                raise ApiError(msg["error"]["code"], msg["error"]["message"])
            return msg["result"]

    def wait_event(self, wanted: str, timeout: float) -> dict[str, Any]:
        """The next pushed event of type ``wanted``; a ``collision`` on the way is an error."""
        deadline = time.monotonic() + timeout
        while True:
            while self.events:
                ev = self.events.pop(0)
                if ev["type"] == wanted:
                    return ev
                if ev["type"] == "collision":
                    raise RuntimeError(f"collision at {ev['position']} (t={ev['t']:.2f} s)")
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"no {wanted!r} event within {timeout:g} s")
            self._receive(left)


def parse_waypoints(text: str) -> list[list[float]]:
    """``"x,y,z x,y,z ..."`` (spaces or semicolons between points) -> a list of [x, y, z]."""
    points = []
    for item in text.replace(";", " ").split():
        parts = item.split(",")
        if len(parts) != 3:
            raise argparse.ArgumentTypeError(f"waypoint {item!r} is not x,y,z")
        try:
            point = [float(p) for p in parts]
        except ValueError:
            raise argparse.ArgumentTypeError(f"waypoint {item!r} is not three numbers") from None
        if not all(math.isfinite(v) for v in point):
            raise argparse.ArgumentTypeError(f"waypoint {item!r} is not finite")
        points.append(point)
    if not points:
        raise argparse.ArgumentTypeError("no waypoints given")
    return points


def fly(url: str, waypoints: list[list[float]], speed: float, timeout: float) -> dict[str, Any]:
    """Take off, visit the waypoints (relative to the spawn point), land; returns a summary."""
    summary: dict[str, Any] = {"url": url, "waypoints": [], "arrived": []}
    with connect(url, open_timeout=timeout) as ws:
        api = Api(ws, timeout)
        info = api.call("scene_info")
        spawn = info["spawn_position"]
        print(
            f"scene {info['name']!r} (seed {info['seed']}), spawn {spawn}, bounds "
            f"{info['bounds_min']} .. {info['bounds_max']}"
        )
        api.call("subscribe", streams=["state", "events"], rate_hz=5)

        took = api.call("takeoff", altitude=waypoints[0][2])
        print(f"takeoff: climbing for {took['duration']:.1f} s")
        api.wait_event("arrived", 60 + took["duration"])

        for rel in waypoints:
            target = [spawn[0] + rel[0], spawn[1] + rel[1], rel[2]]
            planned = api.call("goto", position=target, speed=speed)
            ev = api.wait_event("arrived", 60 + 3 * planned["duration"])
            error = math.dist(ev["position"], target)
            print(
                f"t={ev['t']:6.2f} s arrived at {[round(v, 2) for v in ev['position']]} "
                f"(target {[round(v, 2) for v in target]}, off by {error:.3f} m)"
            )
            summary["waypoints"].append(target)
            summary["arrived"].append(ev["position"])

        try:  # an error reply names the problem and changes nothing
            api.call("goto", position=[spawn[0], spawn[1], -1.0])
        except ApiError as exc:
            print(f"refused as expected: {exc}")
            summary["refused"] = exc.code

        landing = api.call("land")
        ev = api.wait_event("landed", 60 + 3 * landing["duration"])
        print(f"t={ev['t']:6.2f} s landed at {[round(v, 2) for v in ev['position']]}")
        summary["landed"] = ev["position"]
        summary["states_received"] = api.states_received
        summary["final_state"] = api.call("state")
    return summary


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--url", default="ws://127.0.0.1:8765", help="the simulator's WebSocket API")
    ap.add_argument(
        "--waypoints",
        type=parse_waypoints,
        default=parse_waypoints(DEFAULT_WAYPOINTS),
        help=f'"x,y,z x,y,z ..." relative to the spawn point (default "{DEFAULT_WAYPOINTS}")',
    )
    ap.add_argument("--speed", type=float, default=1.5, help="peak speed of each leg, m/s")
    ap.add_argument("--timeout", type=float, default=30.0, help="seconds to wait for each reply")
    ap.add_argument("--summary", default=None, help="write the flight summary to this JSON file")
    args = ap.parse_args()
    try:
        summary = fly(args.url, args.waypoints, args.speed, args.timeout)
    except (OSError, TimeoutError, RuntimeError, ApiError, WebSocketException) as exc:
        print(f"waypoints_ws: {exc}", file=sys.stderr)
        return 1
    if args.summary:
        with open(args.summary, "w") as f:
            json.dump(summary, f, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
