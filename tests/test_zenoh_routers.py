"""Topics across hosts: the simulator on one side of two Zenoh routers, a ROS 2 consumer on the other.

The tested configuration of docs/ros2.md, "Across hosts: Zenoh routers". Router A stands for the
simulator host's router, router B for the consumer host's; B connects to A, as a remote host's
``zenohd`` / ``rmw_zenohd`` configured with ``connect.endpoints`` would. Each router is its own
process running zenoh-python's session in ``mode: "router"``, which is the router code ``zenohd``
runs (there is no ``zenohd`` binary here). Everything listens on 127.0.0.1 with multicast scouting
off, and shared memory is off in the routers and the consumer, so samples cross the routers as bytes
on TCP as they would between hosts.

The consumer is a plain Zenoh client of router B only and decodes what it receives with rosbags'
own Jazzy typestore and PIL, not with the simulator's code. Each router's admin space is read to
check that the samples took the two-router path and no shortcut.
"""

from __future__ import annotations

import io
import json
import socket
import subprocess
import sys
import threading
import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh
from PIL import Image as PILImage
from rosbags.typesys import Stores, get_typestore

from droneulator.config import CameraConfig, load_config
from droneulator.runtime.dynamics_server import open_zenoh_hub
from droneulator.runtime.launch import free_port, launch_run
from droneulator.sensors.camera import intrinsics

TS = get_typestore(Stores.ROS2_JAZZY)
T = TS.types
NS = "droneulator"
CAM = CameraConfig(name="front", width=160, height=120)
STATE_PERIOD = 10_000_000  # runtime.state_hz 100
#: the keys the consumer takes (ros2dds key mode: the ROS name without its leading /) and their types
TOPICS = {
    "clock": "rosgraph_msgs/msg/Clock",
    f"{NS}/odom": "nav_msgs/msg/Odometry",
    f"{NS}/front/color/image_raw/compressed": "sensor_msgs/msg/CompressedImage",
    f"{NS}/front/color/camera_info": "sensor_msgs/msg/CameraInfo",
}

#: one Zenoh router, as ``zenohd`` would run it: prints its zid once listening, runs until stdin closes
ROUTER = r"""
import json, sys, zenoh
listen, connect = sys.argv[1], json.loads(sys.argv[2])
conf = zenoh.Config()
conf.insert_json5("mode", '"router"')
conf.insert_json5("listen/endpoints", json.dumps([listen]))
conf.insert_json5("connect/endpoints", json.dumps(connect))
conf.insert_json5("scouting/multicast/enabled", "false")
conf.insert_json5("transport/shared_memory/enabled", "false")
conf.insert_json5("adminspace/enabled", "true")
session = zenoh.open(conf)
print(session.zid(), flush=True)
sys.stdin.read()
session.close()
"""


def endpoint() -> str:
    return f"tcp/127.0.0.1:{free_port()}"


@dataclass
class Router:
    """A router process: where it listens and its zid."""

    proc: subprocess.Popen[str]
    listen: str
    zid: str

    def stop(self) -> None:
        if self.proc.stdin is not None and not self.proc.stdin.closed:
            self.proc.stdin.close()
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


def start_router(connect: list[str]) -> Router:
    """A router on a free loopback port connecting to ``connect``; returns once it listens."""
    listen = endpoint()
    proc = subprocess.Popen(
        [sys.executable, "-c", ROUTER, listen, json.dumps(connect)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    assert proc.stdout is not None
    zid = proc.stdout.readline().strip()
    if not zid:
        proc.kill()
        raise RuntimeError(f"router on {listen} exited with {proc.wait()} before listening")
    return Router(proc, listen, zid)


@pytest.fixture(scope="module")
def routers() -> Iterator[tuple[Router, Router]]:
    """Router A (the simulator host's) and router B (the consumer host's), B connected to A."""
    a = start_router([])
    try:
        b = start_router([a.listen])
    except BaseException:
        a.stop()
        raise
    yield a, b
    b.stop()
    a.stop()


def consumer(router: Router) -> zenoh.Session:
    """The ROS 2 side: a Zenoh client of ``router`` only (an rmw_zenoh node in client mode, RViz...)."""
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([router.listen]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("transport/shared_memory/enabled", "false")
    return zenoh.open(conf)


def sessions_of(session: zenoh.Session, router: Router) -> dict[str, str]:
    """``router``'s open Zenoh sessions, zid -> whatami, from its admin space ``@/<zid>/router``."""
    replies = [r.ok for r in session.get(f"@/{router.zid}/router", timeout=5.0) if r.ok is not None]
    assert len(replies) == 1, f"no admin space answer from {router.zid}"
    info = json.loads(replies[0].payload.to_string())
    return {s["peer"]: s["whatami"] for s in info["sessions"]}


def wait(condition: Callable[[], bool], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.05)


def stamp(msg: Any) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def clock_ns(cdr: bytes) -> int:
    """The time a /clock sample carries, in ns."""
    m = TS.deserialize_cdr(cdr, "rosgraph_msgs/msg/Clock")
    return m.clock.sec * 1_000_000_000 + m.clock.nanosec


def twist_cdr(forward: float) -> bytes:
    v = T["geometry_msgs/msg/Vector3"]
    msg = T["geometry_msgs/msg/Twist"](linear=v(x=forward, y=0.0, z=0.0), angular=v(x=0.0, y=0.0, z=0.0))
    return bytes(TS.serialize_cdr(msg, "geometry_msgs/msg/Twist"))


def common(a: list[int], b: list[int]) -> tuple[list[int], list[int]]:
    """Both stamp lists cut to the span they share (two subscriptions open and close a few ms apart)."""
    lo, hi = max(a[0], b[0]), min(a[-1], b[-1])
    return [s for s in a if lo <= s <= hi], [s for s in b if lo <= s <= hi]


@pytest.mark.slow  # a real run: 12 s alone on 2 cores, near 20 s beside other work
def test_simulator_behind_router_a_serves_a_client_of_router_b(routers: tuple[Router, Router]) -> None:
    """``droneulator run --set bridge.mode=client --set bridge.connect=[A]``, the consumer a client of B:
    /clock, odometry, a camera's images and camera_info arrive through both routers, none lost, with
    the frame ids and stamps the simulator means; a cmd_vel put on B flies the vehicle."""
    a, b = routers
    cfg = load_config(scene="default")
    cfg.render.cameras = [CAM]
    cfg.render.shadow_map_size = 1024
    sets = ["--set", "bridge.mode=client", "--set", f'bridge.connect=["{a.listen}"]']  # as typed in a shell
    raw: dict[str, list[bytes]] = defaultdict(list)
    lock = threading.Lock()

    def on(key: str) -> Callable[[zenoh.Sample], None]:
        def cb(sample: zenoh.Sample) -> None:
            with lock:
                raw[key].append(sample.payload.to_bytes())

        return cb

    def count(key: str) -> int:
        with lock:
            return len(raw[key])

    with launch_run(cfg, sets) as run, run.client(timeout=120) as c:
        session = consumer(b)
        try:
            subs = [session.declare_subscriber(key, on(key)) for key in TOPICS]
            # the first frames compile shaders and kernels: seconds on a small machine
            wait(lambda: count(f"{NS}/front/color/image_raw/compressed") >= 6, 90, "camera images via B")
            wait(lambda: count("clock") >= 30, 10, "/clock via B")
            for s in subs:
                s.undeclare()

            # the path: consumer -> B -> A -> the run's two sessions (dynamics and camera bridge), leaves of A
            assert [str(z) for z in session.info.routers_zid()] == [b.zid]
            assert sessions_of(session, b) == {a.zid: "router", str(session.zid()): "client"}
            at_a = sessions_of(session, a)
            assert at_a.pop(b.zid) == "router"
            assert sorted(at_a.values()) == ["client", "client"], at_a

            # cmd_vel from the consumer host, through B and A, to the simulator
            p0 = np.array(c.reset(position=[0.0, 0.0, 2.0], yaw=0.0)["state"]["position"])
            pub = session.declare_publisher(f"{NS}/cmd_vel")
            wait(lambda: pub.matching_status.matching, 10, "the simulator's cmd_vel subscriber via A")
            pub.put(twist_cdr(1.0))
            t_end = c.state()["t"] + 1.5
            wait(lambda: c.state()["t"] >= t_end, 30, "1.5 s of sim time")
            st = c.state()
        finally:
            session.close()
    assert st["mode"] == "velocity", st
    assert st["position"][0] > p0[0] + 0.7, st

    msgs = {key: [TS.deserialize_cdr(r, TOPICS[key]) for r in raw[key]] for key in TOPICS}
    clock = [clock_ns(r) for r in raw["clock"]]
    assert np.all(np.diff(clock) == STATE_PERIOD), "a /clock tick lost or reordered between the routers"

    odom = msgs[f"{NS}/odom"]
    assert {(m.header.frame_id, m.child_frame_id) for m in odom} == {("odom", "base_link")}
    on_clock, on_odom = common(clock, [stamp(m) for m in odom])
    assert len(on_odom) > 20 and on_odom == on_clock  # one odometry per clock tick, same stamps

    images = msgs[f"{NS}/front/color/image_raw/compressed"]
    infos = msgs[f"{NS}/front/color/camera_info"]
    assert (
        {m.header.frame_id for m in images} == {m.header.frame_id for m in infos} == {"front_optical_frame"}
    )
    for m in images[:3]:
        assert "jpeg" in m.format
        assert PILImage.open(io.BytesIO(bytes(m.data))).size == (CAM.width, CAM.height)
    for m in infos:
        assert (m.width, m.height) == (CAM.width, CAM.height)
        np.testing.assert_allclose(np.asarray(m.k).reshape(3, 3), intrinsics(CAM), rtol=1e-9)
    frames, with_info = common([stamp(m) for m in images], [stamp(m) for m in infos])
    assert len(frames) >= 5 and frames == with_info  # one camera_info per image, same stamp
    assert np.all(np.diff(frames) == round(1e9 / cfg.render.camera_hz)), "a frame lost between the routers"
    # on the simulation's clock: inside the span of /clock seen in the same window (render lag < 0.5 s)
    assert clock[0] - 500_000_000 <= frames[0] and frames[-1] <= clock[-1] + 500_000_000


@pytest.mark.parametrize("mode", ["router", "peer", "client"])
def test_simulator_session_in_each_mode(routers: tuple[Router, Router], tmp_path: Path, mode: str) -> None:
    """The simulator's own session (``open_zenoh_hub``, what ``droneulator run`` opens) from the documented
    ``--set`` values, both ways through routers to a client of the consumer host's router.

    ``router``: the simulator host runs no other router; the consumer host's router connects to the
    simulator's listen endpoint. ``peer`` / ``client``: the simulator is a peer / a leaf of router A,
    listening on nothing, and B connects to A.
    """
    a, b = routers
    extra: Router | None = None
    if mode == "router":
        sim_listen = endpoint()
        sets = ["bridge.mode=router", f'bridge.listen=["{sim_listen}"]']
    elif mode == "peer":
        sets = ["bridge.mode=peer", "bridge.listen=[]", f'bridge.connect=["{a.listen}"]']
    else:  # a client ignores bridge.listen: it must not bind it
        unused = free_port()
        sets = [
            "bridge.mode=client",
            f'bridge.listen=["tcp/127.0.0.1:{unused}"]',
            f'bridge.connect=["{a.listen}"]',
        ]
    node = open_zenoh_hub(load_config(overrides=sets), f"unixsock-stream/{tmp_path / 'zenoh.sock'}")
    session: zenoh.Session | None = None
    try:
        if mode == "client":
            with socket.socket() as sock:
                sock.bind(("127.0.0.1", unused))  # free while the client's session is open
        if mode == "router":
            extra = start_router([sim_listen])  # the consumer host's router, connecting out to the simulator
        remote = extra if extra is not None else b
        session = consumer(remote)
        clocks: list[int] = []
        twists: list[Any] = []
        sub = session.declare_subscriber("clock", lambda s: clocks.append(clock_ns(s.payload.to_bytes())))
        node.subscribe(f"/{NS}/cmd_vel", "geometry_msgs/msg/Twist", twists.append)
        clock_pub = node.publisher("/clock", "rosgraph_msgs/msg/Clock")
        wait(lambda: clock_pub.matching, 10, "the consumer's /clock subscriber at the simulator")
        # one tick every 10 ms until 20 have arrived: the first may be sent while the far router is still
        # completing its route (the publisher's matching status comes from its own router)
        sent: list[int] = []
        deadline = time.monotonic() + 20
        while len(clocks) < 20:
            assert time.monotonic() < deadline, f"/clock at the consumer: {len(clocks)} in 20 s"
            t = (len(sent) + 1) * STATE_PERIOD
            clock = T["rosgraph_msgs/msg/Clock"](
                clock=T["builtin_interfaces/msg/Time"](sec=t // 1_000_000_000, nanosec=t % 1_000_000_000)
            )
            clock_pub.publish(bytes(TS.serialize_cdr(clock, "rosgraph_msgs/msg/Clock")))
            sent.append(t)
            time.sleep(0.01)
        sub.undeclare()
        pub = session.declare_publisher(f"{NS}/cmd_vel")
        wait(lambda: pub.matching_status.matching, 10, "the simulator's cmd_vel subscriber")
        pub.put(twist_cdr(0.75))
        wait(lambda: len(twists) >= 1, 10, "cmd_vel at the simulator")

        at_remote = sessions_of(session, remote)
        if mode == "router":
            assert at_remote == {node.zid: "router", str(session.zid()): "client"}
        else:
            assert at_remote == {a.zid: "router", str(session.zid()): "client"}  # no shortcut to B
            assert sessions_of(session, a).get(node.zid) == mode
    finally:
        if session is not None:
            session.close()
        node.close()
        if extra is not None:
            extra.stop()
    first = sent.index(clocks[0])
    assert clocks == sent[first : first + len(clocks)]  # in order, and none lost once they flow
    assert len(twists) == 1 and twists[0].linear.x == 0.75
