"""The dynamics server: owns the simulation clock and the flight, serves the WebSocket API, and
is the hub the render server and the bridge connect to.

Lockstep: a control step is taken only while fewer than ``frame_slots - 1`` frames are in flight
(requested from the render server and not yet published by the bridge), so sim time advances
exactly as fast as the slowest consumer and no frame is skipped. Realtime: steps follow the wall
clock (times ``runtime.speed``); a camera instant is sent to the render server only when it is
free, so it draws the latest state at whatever rate it manages, stamped with that state's time.
"""

from __future__ import annotations

import json
import logging
import os
import queue
import signal
import threading
import time
from multiprocessing.connection import Connection, Listener, wait
from typing import Any

from droneulator.api.server import ApiServer
from droneulator.config import SimConfig, from_dict
from droneulator.runtime.ipc import ENV_ADDRESS, ENV_AUTHKEY, ENV_CONFIG, PROTOCOL_VERSION
from droneulator.sim.simulator import NS, CommandError, Simulator, StepResult, VehicleState

log = logging.getLogger("droneulator.dynamics")
ROLES = ("renderer", "bridge")


def state_payload(st: VehicleState) -> dict[str, Any]:
    """The state fields the render server and the bridge need (plain lists, picklable)."""
    return {
        "t_ns": st.t_ns,
        "position": st.position.tolist(),
        "quaternion": st.quaternion.tolist(),
        "velocity": st.velocity.tolist(),
        "angular_velocity": st.angular_velocity.tolist(),
        "mode": st.mode,
    }


class DynamicsServer:
    def __init__(self, cfg: SimConfig, address: str, authkey: bytes) -> None:
        if cfg.render.camera_hz > cfg.vehicle.control_hz:
            raise ValueError("render.camera_hz must not exceed vehicle.control_hz")
        self.cfg = cfg
        self.sim = Simulator(config=cfg, render=False, external_cameras=True)
        self.lock = threading.Lock()
        rt = cfg.runtime
        self.api = ApiServer(
            self.sim,
            self.lock,
            host=rt.api_host,
            port=rt.api_port,
            max_message_bytes=rt.api_max_message_bytes,
            state_rate_hz=rt.state_hz,
        )
        self.listener = Listener(address, family="AF_UNIX", authkey=authkey)
        self.peers: dict[str, Connection] = {}
        self._new_peers: queue.Queue[tuple[str, Connection]] = queue.Queue()
        self.seq = 0
        #: seq -> [stage ("render" | "publish"), state payload]
        self.in_flight: dict[int, list[Any]] = {}
        self.window = rt.frame_slots - 1
        self.state_period_ns = round(NS / rt.state_hz)
        self._next_state_ns = 0
        self._scene_key = (cfg.scene, cfg.seed)
        self.stopping = threading.Event()
        self.dropped_frames = 0
        self.px4 = None
        if cfg.px4.enabled:
            from droneulator.px4.link import PX4Link

            self.px4 = PX4Link(self.sim, cfg.px4, seed=cfg.seed)

    # ------------------------------------------------------------------ peers
    def _accept_loop(self) -> None:
        while not self.stopping.is_set():
            try:
                conn = self.listener.accept()
                hello = conn.recv()
            except (OSError, EOFError):
                if self.stopping.is_set():
                    return
                log.warning("a process failed the hub handshake", exc_info=True)
                continue
            role = hello.get("hello") if isinstance(hello, dict) else None
            if role not in ROLES or hello.get("version") != PROTOCOL_VERSION:
                conn.send({"error": f"unknown role or protocol version: {hello!r}"})
                conn.close()
                continue
            conn.send({"welcome": role, "scene": self.cfg.scene, "seed": self.cfg.seed})
            self._new_peers.put((role, conn))

    def _take_new_peers(self) -> None:
        while True:
            try:
                role, conn = self._new_peers.get_nowait()
            except queue.Empty:
                return
            if role in self.peers:
                self.peers[role].close()
            self.peers[role] = conn
            log.info("%s connected", role)
            scene = (self.sim.config.scene, self.sim.config.seed)
            if scene != (self.cfg.scene, self.cfg.seed):
                self._send(role, ("scene", *scene))
            stage = "render" if role == "renderer" else "publish"
            for seq, (st, payload) in sorted(self.in_flight.items()):
                if st == stage:  # work the previous instance never finished
                    self._send(role, ("render" if role == "renderer" else "frame", seq, payload))

    def _send(self, role: str, msg: tuple) -> None:
        conn = self.peers.get(role)
        if conn is None:
            return
        try:
            conn.send(msg)
        except (OSError, BrokenPipeError):
            self._drop(role)

    def _drop(self, role: str) -> None:
        conn = self.peers.pop(role, None)
        if conn is not None:
            conn.close()
            log.warning("%s disconnected; waiting for it to come back", role)

    def _poll(self, timeout: float) -> None:
        conns = {c: r for r, c in self.peers.items()}
        if not conns:
            if timeout:
                time.sleep(min(timeout, 0.05))
            return
        for conn in wait(list(conns), timeout):
            role = conns[conn]
            try:
                msg = conn.recv()
            except (EOFError, OSError):
                self._drop(role)
                continue
            self._handle(role, msg)

    def _handle(self, role: str, msg: tuple) -> None:
        kind = msg[0]
        if kind == "rendered":
            item = self.in_flight.get(msg[1])
            if item is not None:
                item[0] = "publish"
                self._send("bridge", ("frame", msg[1], item[1]))
        elif kind == "published":
            self.in_flight.pop(msg[1], None)
        elif kind == "command":
            self._command(msg[1], msg[2])
        else:
            log.error("unexpected message from %s: %r", role, kind)

    def _command(self, op: str, args: dict[str, Any]) -> None:
        """A flight command from ROS (cmd_vel, goal_pose) relayed by the bridge."""
        try:
            with self.lock:
                getattr(self.sim, op)(**args)
        except CommandError as exc:
            log.warning("ROS %s command rejected (%s): %s", op, exc.code, exc.message)
        except (TypeError, AttributeError) as exc:
            log.error("bad ROS command %s %r: %s", op, args, exc)

    # ------------------------------------------------------------------ stepping
    def _step(self, realtime: bool) -> None:
        with self.lock:
            res = self.sim.step()
        self._after_step(res, realtime)

    def _after_step(self, res: StepResult, realtime: bool) -> None:
        """Send camera instants to the render server, events and states to their consumers."""
        scene = (self.sim.config.scene, self.sim.config.seed)
        if scene != self._scene_key:  # reset to another scene through the API
            self._scene_key = scene
            self.in_flight.clear()
            for role in ROLES:
                self._send(role, ("scene", *scene))
        for st in res.camera_states:
            ready = "renderer" in self.peers and len(self.in_flight) < self.window
            if realtime and (not ready or any(v[0] == "render" for v in self.in_flight.values())):
                self.dropped_frames += 1
                continue
            self.seq += 1
            payload = state_payload(st)
            self.in_flight[self.seq] = ["render", payload]
            self._send("renderer", ("render", self.seq, payload))
        for e in res.events:
            self.api.publish_event(e.to_dict())
        if self.sim.t_ns < self._next_state_ns - self.state_period_ns:  # the clock was reset
            self._next_state_ns = 0
        if self.sim.t_ns >= self._next_state_ns:
            self._next_state_ns = self.sim.t_ns + self.state_period_ns
            st = self.sim.state
            self._send("bridge", ("state", state_payload(st)))
            self.api.publish_state({**st.to_dict(), "t_ns": st.t_ns})

    def _px4_turn(self) -> bool:
        """While PX4 is connected its actuator messages drive the clock (lockstep with PX4 and with
        every consumer); WebSocket flight commands are refused meanwhile. True if PX4 is in control."""
        assert self.px4 is not None
        connected = self.px4.connected
        ready = all(r in self.peers for r in ROLES) and len(self.in_flight) < self.window
        res = (
            self.px4.serve_once(0.002 if ready and connected else 0.0, self.lock)
            if ready or not connected
            else None
        )
        if self.px4.connected != self._px4_in_control:
            self._px4_in_control = self.px4.connected
            if self._px4_in_control:
                self.api.refuse_flight("PX4 SITL is in control; flight commands come from PX4")
                log.info("PX4 connected: it now drives the simulation clock")
            else:
                with self.lock:  # the internal controller takes over: hover in place, or rest
                    if self.sim.state.position[2] > 0.05:
                        self.sim.hold()
                    else:
                        self.sim.motors_off()
                self.api.allow_flight()
                log.warning("PX4 disconnected: holding position until it reconnects")
        if res is not None:
            self._after_step(res, realtime=False)
        if self._px4_in_control:
            self._poll(0 if ready else 0.05)
        return self._px4_in_control

    def run(self) -> None:
        threading.Thread(target=self._accept_loop, name="hub-accept", daemon=True).start()
        self._px4_in_control = False
        if self.px4 is not None:
            self.px4.start()
            log.info("waiting for PX4 SITL on tcp://%s:%d", self.cfg.px4.host, self.px4.port)
        self.api.start()
        log.info(
            "dynamics server ready: scene %s, %s mode, API ws://%s:%d",
            self.cfg.scene,
            self.cfg.runtime.mode,
            self.cfg.runtime.api_host,
            self.api.port,
        )
        realtime = self.cfg.runtime.mode == "realtime"
        dt = self.sim.control_period_ns / NS
        wall0, sim0 = time.monotonic(), self.sim.t
        report = time.monotonic() + 5.0
        while not self.stopping.is_set():
            self._take_new_peers()
            if self.px4 is not None and self._px4_turn():
                pass
            elif realtime:
                lag = (time.monotonic() - wall0) * self.cfg.runtime.speed - (self.sim.t - sim0)
                if self.sim.t < sim0:  # reset through the API
                    wall0, sim0 = time.monotonic(), self.sim.t
                if lag >= 0:
                    self._step(realtime=True)
                self._poll(0 if lag >= 0 else min(-lag / self.cfg.runtime.speed, dt))
            else:
                ready = all(r in self.peers for r in ROLES) and len(self.in_flight) < self.window
                if ready:
                    self._step(realtime=False)
                self._poll(0 if ready else 0.05)
            if time.monotonic() > report:
                report = time.monotonic() + 5.0
                log.info(
                    "t=%.2f s sim, %d frames in flight, %d dropped",
                    self.sim.t,
                    len(self.in_flight),
                    self.dropped_frames,
                )

    def close(self) -> None:
        self.stopping.set()
        if self.px4 is not None:
            self.px4.close()
        self.api.stop()
        for conn in self.peers.values():
            conn.close()
        self.peers.clear()
        self.listener.close()


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s")
    cfg = from_dict(SimConfig, json.loads(os.environ[ENV_CONFIG]))
    server = DynamicsServer(cfg, os.environ[ENV_ADDRESS], bytes.fromhex(os.environ[ENV_AUTHKEY]))
    signal.signal(signal.SIGTERM, lambda *_: server.stopping.set())
    signal.signal(signal.SIGINT, lambda *_: server.stopping.set())
    try:
        server.run()
    finally:
        server.close()


if __name__ == "__main__":
    main()
