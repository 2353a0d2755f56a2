"""The dynamics server: owns the world (its clock and every vehicle's flight) and is the hub the render
server and the bridge connect to. Each camera instant goes to the render server as every vehicle's state
at once. It composes what else runs on the clock: the WebSocket API (:mod:`.api_host`), the ROS 2 state
and sensor topics (:mod:`.publishing`), the latency log (:mod:`.latency`), and the autopilot links with
their flight lock: PX4's (:mod:`droneulator.px4`) and ArduPilot's (:mod:`droneulator.ardupilot`), any mix
of them stepping the world on one lockstep clock (:mod:`droneulator.px4.fleet`).

Lockstep: a control step is taken only while fewer than ``frame_slots - 1`` frames are in flight
(requested from the render server and not yet published by the bridge), so sim time advances
exactly as fast as the slowest consumer and no frame is skipped; the bridge publishes images with
Zenoh's ``BLOCK`` policy, so a slow subscriber slows the clock instead of losing images. Realtime:
steps follow the wall clock (times ``runtime.speed``); a camera instant is sent to the render server
only when it is free, so it draws the latest state at whatever rate it manages, and images are
published with ``DROP``. ``runtime.max_speed`` caps lockstep's clock on average (:mod:`.pacing`).
Triggered cameras (``render.camera_trigger=command``) send a camera instant only when the API's
``trigger`` asks for one, in either mode, and it is never dropped; in lockstep a triggered frame holds
the clock until it is published (:func:`lockstep_may_step`).

Odometry, TF, ``/clock`` and the sensor topics leave from here, right after the physics step that
produced the state (no process hop). ROS commands (``cmd_vel``, ``goal_pose``) arrive here too and go
through the same :class:`~droneulator.commands.path.CommandPath` as WebSocket commands.
The Zenoh session of this process is the run's hub on Zenoh as well: by default a router listening on
``bridge.listen``, which the bridge process reaches over a private Unix socket.
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
from typing import TYPE_CHECKING, Any

from droneulator.commands import CommandPath
from droneulator.commands.path import SimLock
from droneulator.config import SimConfig, from_dict
from droneulator.ros.publishers import subscribe_commands
from droneulator.ros.zenoh_node import RosZenohNode
from droneulator.runtime.api_host import ApiHost
from droneulator.runtime.ipc import (
    ENV_ADDRESS,
    ENV_AUTHKEY,
    ENV_CONFIG,
    ENV_ZENOH,
    PROTOCOL_VERSION,
    Hello,
    HubMessage,
    Publish,
    Published,
    Refused,
    Render,
    Rendered,
    Welcome,
)
from droneulator.runtime.latency import LatencyLog
from droneulator.runtime.pacing import Pacer
from droneulator.runtime.publishing import StatePublishing
from droneulator.runtime.scene_sync import SceneSync
from droneulator.runtime.spawn import start_server_process
from droneulator.vehicles.vehicle import NS, VehicleState
from droneulator.world import World
from droneulator.world.world import StepResult

if TYPE_CHECKING:
    from droneulator.px4.fleet import Fleet
    from droneulator.px4.flight_lock import PX4FlightLock

log = logging.getLogger("droneulator.dynamics")
ROLES = ("renderer", "bridge")
#: lockstep under ``runtime.max_speed`` makes up a wait (a frame holding the clock) of up to this long, wall s
MAX_SPEED_CATCH_UP_S = 1.0


def lockstep_may_step(in_flight: dict[int, tuple[str, Any, tuple[str, ...] | None]], window: int) -> bool:
    """Whether lockstep may take a control step with ``in_flight`` frames (seq -> (stage, states, rigs)):
    fewer than ``window`` in flight and none of them triggered. A triggered frame holds the clock until
    the bridge has published it: nothing else is rendered meanwhile, so stepping on would only hover the
    fleet at full speed on the cores the renderer needs (with the hold a capture's frames came in 0.10 s
    instead of 0.28 s on 2 cores: docs/photogrammetry.md), and the frame reaches its consumer before the
    world moves on."""
    return len(in_flight) < window and all(rigs is None for _, _, rigs in in_flight.values())


def open_zenoh_hub(cfg: SimConfig, private_endpoint: str | None) -> RosZenohNode:
    """The run's main Zenoh session: the user's settings, plus the private endpoint the bridge connects to.

    A client (``bridge.mode=client``) is a leaf of the routers in ``bridge.connect`` and listens on
    nothing: a Zenoh client session would otherwise still bind ``bridge.listen``, which no one reaches
    through a leaf and which stops the run from starting when the port is taken."""
    if cfg.bridge.mode == "client":
        return RosZenohNode.from_config(cfg.bridge, listen=())
    if private_endpoint:
        return RosZenohNode.from_config(cfg.bridge, listen=(*cfg.bridge.listen, private_endpoint))
    return RosZenohNode.from_config(cfg.bridge)


class DynamicsServer:
    def __init__(
        self, cfg: SimConfig, address: str, authkey: bytes, zenoh_endpoint: str | None = None
    ) -> None:
        if cfg.render.camera_hz > cfg.vehicle.control_hz:
            raise ValueError("render.camera_hz must not exceed vehicle.control_hz")
        self.cfg = cfg
        self.world = World(cfg, render=False, external_cameras=True)
        self.commands = CommandPath(self.world)
        rt = cfg.runtime
        self.api = ApiHost(self.commands, cfg)
        self.node = open_zenoh_hub(cfg, zenoh_endpoint)
        self._latency = LatencyLog.of(cfg)
        self.publishing = StatePublishing(self.world, self.node, cfg, self._latency)
        subscribe_commands(self.node, cfg, self.commands)
        self._hub_address, self._authkey = address, authkey
        self.listener: Listener | None = None
        self.peers: dict[str, Connection] = {}
        self._new_peers: queue.Queue[tuple[str, Connection]] = queue.Queue()
        self.seq = 0
        #: seq -> (stage "render" | "publish", every vehicle's state, the vehicles whose cameras shoot, None
        #: for all): frames requested and not yet published
        self.in_flight: dict[int, tuple[str, dict[str, VehicleState], tuple[str, ...] | None]] = {}
        self.window = rt.frame_slots - 1
        #: the scene the render server and the bridge must load, as API resets change the world's
        self.scene_sync = SceneSync(self.world.config)
        self.stopping = threading.Event()
        self.dropped_frames = 0
        self.frames_published = 0
        #: the autopilot links (PX4's and ArduPilot's, one lockstep clock for all) and their flight lock
        self.px4: Fleet | None = None
        self.flight_lock: PX4FlightLock | None = None
        if cfg.px4_instances() or cfg.ardupilot_instances():
            from droneulator.px4.fleet import AutopilotFleet
            from droneulator.px4.flight_lock import PX4FlightLock

            self.px4 = AutopilotFleet.of(self.world)
            self.flight_lock = PX4FlightLock(self.commands, self.px4)

    # ------------------------------------------------------------------ peers
    def _accept_loop(self) -> None:
        assert self.listener is not None
        while not self.stopping.is_set():
            try:
                conn = self.listener.accept()
                hello = conn.recv()
            except (OSError, EOFError):
                if self.stopping.is_set():
                    return
                log.warning("a process failed the hub handshake", exc_info=True)
                continue
            if not isinstance(hello, Hello) or hello.role not in ROLES or hello.version != PROTOCOL_VERSION:
                conn.send(Refused(f"unknown role or protocol version: {hello!r}"))
                conn.close()
                continue
            conn.send(Welcome(hello.role, self.cfg.scene, self.cfg.seed))
            self._new_peers.put((hello.role, conn))

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
            load = self.scene_sync.for_newcomer()
            if load is not None:
                self._send(role, load)
            stage = "render" if role == "renderer" else "publish"
            for seq, (st, states, rigs) in sorted(self.in_flight.items()):
                if st == stage:  # work the previous instance never finished
                    self._send(role, self._request(role, seq, states, rigs))

    def _send(self, role: str, msg: HubMessage) -> None:
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

    @staticmethod
    def _request(
        role: str, seq: int, states: dict[str, VehicleState], rigs: tuple[str, ...] | None
    ) -> Render | Publish:
        """What ``role`` is sent of frame ``seq``: every state to draw, the shooting vehicles' to publish."""
        if role == "renderer":
            return Render(seq, states, rigs)
        return Publish(seq, states if rigs is None else {name: states[name] for name in rigs})

    def _handle(self, role: str, msg: HubMessage) -> None:
        match msg:
            case Rendered(seq):
                item = self.in_flight.get(seq)
                if item is not None:
                    self.in_flight[seq] = ("publish", item[1], item[2])
                    request = self._request("bridge", seq, item[1], item[2])
                    dropped = self.world.camera_dropouts()  # a camera_dropout fault: no frames from those
                    if dropped and isinstance(request, Publish):
                        kept = {name: st for name, st in request.states.items() if name not in dropped}
                        request = Publish(seq, kept)
                    self._send("bridge", request)
            case Published(seq):
                self.in_flight.pop(seq, None)
                self.frames_published += 1
            case _:
                log.error("unexpected message from %s: %r", role, msg)

    # ------------------------------------------------------------------ stepping
    @property
    def lock(self) -> SimLock:
        """The simulation lock (the command path's): held for every physics step and every command; the
        stepping loop takes its ``loop`` side, which lets waiting commands go first."""
        return self.commands.lock  # type: ignore[return-value]

    def _step(self, realtime: bool) -> None:
        with self.lock.loop:
            res = self.world.step()
        self._after_step(res, realtime, time.time_ns())

    def _after_step(self, res: StepResult, realtime: bool, stepped_wall_ns: int) -> None:
        """Publish the states when due (:meth:`StatePublishing.due`; ROS odometry first: lowest latency,
        then the API, then the sensor topics), send camera instants to the render server, events to the
        API. ``stepped_wall_ns``: when the step that produced them ended."""
        with self.lock.loop:  # a command may reset the simulation between the step and here
            states = self.world.states_now()
            load = self.scene_sync.changed()
            due = self.publishing.due(states, res)
            fed = self.px4.connected_vehicles() if due and self.px4 is not None else set()
            truths = self.publishing.sensor_truths(fed) if due else {}
        if due:
            self.publishing.publish_states(states, stepped_wall_ns)
            self.api.publish_states(states)
            self.publishing.publish_sensors(states, truths)
        if load is not None:  # reset to another scene, light or vegetation through the API
            self.in_flight.clear()
            for role in ROLES:
                self._send(role, load)
        for cam_state, rigs in zip(res.camera_states, res.camera_rigs, strict=True):
            ready = "renderer" in self.peers and len(self.in_flight) < self.window
            busy = not ready or any(v[0] == "render" for v in self.in_flight.values())
            if realtime and rigs is None and busy:  # a triggered frame set is never dropped
                self.dropped_frames += 1
                continue
            self.seq += 1
            self.in_flight[self.seq] = ("render", cam_state, rigs)
            self._send("renderer", Render(self.seq, cam_state, rigs))
        self.api.publish_events(res.events)

    def _pipeline_warm(self) -> bool:
        """Renderer and bridge connected and a first frame through both (shaders compiled, scene
        uploaded, encoders and publishers made), or no camera: PX4's sensor data will not wait."""
        peers = all(r in self.peers for r in ROLES)
        first = self.frames_published > 0 or not self.world.camera_schedule or self.world.triggered
        return peers and first

    def _px4_turn(self) -> bool:
        """While an autopilot is connected its messages drive the clock (PX4's actuator messages,
        ArduPilot's servo packets: lockstep with every instance and with every consumer); True then. The
        flight lock follows each link (:class:`PX4FlightLock`); the links' events (connection, loss,
        arming, hand-over) are published as API events, naming their vehicle."""
        assert self.px4 is not None and self.flight_lock is not None
        connected = self.px4.connected
        ready = all(r in self.peers for r in ROLES) and lockstep_may_step(self.in_flight, self.window)
        res = (
            self.px4.serve_once(0.002 if ready and connected else 0.0, self.lock.loop)
            if ready or not connected
            else None
        )
        stepped_wall_ns = time.time_ns()
        self.api.publish_events(self.px4.take_events())
        self.flight_lock.update()
        if res is not None:
            self._after_step(res, False, stepped_wall_ns)
        if self.px4.connected:
            self._poll(0 if ready else 0.05)
        return self.px4.connected

    def run(self) -> None:
        if self.px4 is not None:
            self.px4.start(listen=False)  # the port is ours now; PX4 is let in once the pipeline is warm
        self.api.start(self.px4)
        # the hub socket last: it is the supervisor's sign that every port is bound and the run is up
        self.listener = Listener(self._hub_address, family="AF_UNIX", authkey=self._authkey)
        threading.Thread(target=self._accept_loop, name="hub-accept", daemon=True).start()
        log.info(
            "dynamics server ready: scene %s, %s mode, API %s",
            self.cfg.scene,
            self.cfg.runtime.mode,
            self.api.server.url,
        )
        realtime = self.cfg.runtime.mode == "realtime"
        limit = self.cfg.runtime.max_speed
        dt = self.world.control_period_ns / NS
        if realtime:
            pacer: Pacer | None = Pacer(self.cfg.runtime.speed)
        else:  # runtime.max_speed: on average, making up the waits for frames (up to MAX_SPEED_CATCH_UP_S)
            pacer = Pacer(limit, MAX_SPEED_CATCH_UP_S) if limit is not None else None
        report = time.monotonic() + 5.0
        while not self.stopping.is_set():
            self._take_new_peers()
            if self.px4 is not None and not self.px4.listening and self._pipeline_warm():
                self.px4.start()
                log.info(
                    "waiting for %s SITL on %s (renderer and bridge warm: the first frame was published "
                    "at t=%.3f s)",
                    self.px4.autopilots,
                    self.px4.describe(),
                    self.world.t,
                )
            if self.px4 is not None and self.px4.listening and self._px4_turn():
                if pacer is not None:  # pacing restarts here when PX4 leaves
                    pacer.restart(self.world.t, time.monotonic())
            else:
                ready = realtime or (
                    all(r in self.peers for r in ROLES) and lockstep_may_step(self.in_flight, self.window)
                )
                wait = 0.0 if ready else 0.05
                if ready and pacer is not None:
                    ahead = pacer.ahead(self.world.t, time.monotonic())
                    ready, wait = ahead <= 0, min(max(ahead, 0.0), dt)
                if ready:
                    self._step(realtime=realtime)
                self._poll(wait)
            if time.monotonic() > report:
                report = time.monotonic() + 5.0
                drawing = sum(stage == "render" for stage, _, _ in self.in_flight.values())
                log.info(
                    "t=%.2f s sim, %d frames in flight (%d at the renderer, %d at the bridge), %d dropped",
                    self.world.t,
                    len(self.in_flight),
                    drawing,
                    len(self.in_flight) - drawing,
                    self.dropped_frames,
                )

    def close(self) -> None:
        self.stopping.set()
        if self.px4 is not None:
            self.px4.close()
        self.api.stop()
        self.node.close()
        if self._latency is not None:
            self._latency.close()
        for conn in self.peers.values():
            conn.close()
        self.peers.clear()
        if self.listener is not None:
            self.listener.close()


def main() -> None:
    start_server_process()
    cfg = from_dict(SimConfig, json.loads(os.environ[ENV_CONFIG]))
    server = DynamicsServer(
        cfg, os.environ[ENV_ADDRESS], bytes.fromhex(os.environ[ENV_AUTHKEY]), os.environ.get(ENV_ZENOH)
    )
    signal.signal(signal.SIGTERM, lambda *_: server.stopping.set())
    signal.signal(signal.SIGINT, lambda *_: server.stopping.set())
    try:
        server.run()
    finally:
        server.close()


if __name__ == "__main__":
    main()
