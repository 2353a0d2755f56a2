"""RosZenohNode against real Zenoh peers in other processes (zenoh + rosbags only, no droneulator code).

Every expected key, attachment, gid and liveliness token is recomputed here from the published rules
(zenoh-plugin-ros2dds ``ros2_utils.rs`` / ``liveliness_mgt.rs``; rmw_zenoh ``liveliness_utils.cpp``,
``attachment_helpers.cpp``, ``rmw_publisher_data.cpp``), and the attachment is decoded with zenoh's own
zenoh-ext deserialiser, so the tests do not reuse the implementation they check.
"""

from __future__ import annotations

import json
import logging
import queue
import socket
import struct
import subprocess
import sys
import textwrap
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import xxhash
from rosbags.typesys import Stores, get_typestore

from droneulator.config import BridgeConfig
from droneulator.ros import messages as M
from droneulator.ros.zenoh_node import QosProfile, RosZenohNode, ZenohNodeConfig, rmw_gid

REF = get_typestore(Stores.ROS2_JAZZY)
TWIST_HASH = REF.hash_rihs01("geometry_msgs/msg/Twist")
TWIST_DDS = "geometry_msgs::msg::dds_::Twist_"

PEER_SCRIPT = textwrap.dedent(
    '''
    """Test peer: a plain Zenoh session that listens, or publishes, and reports JSON lines on stdout."""
    import dataclasses, hashlib, json, sys, time
    import numpy as np
    import zenoh
    from zenoh.ext import Int64, UInt8, z_deserialize
    from rosbags.typesys import Stores, get_typestore

    args = json.loads(sys.argv[1])
    ts = get_typestore(Stores.ROS2_JAZZY)

    def out(**kw):
        print(json.dumps(kw), flush=True)

    def plain(v):
        if dataclasses.is_dataclass(v):
            fields = [f.name for f in dataclasses.fields(v) if f.name != "__msgtype__"]
            return {name: plain(getattr(v, name)) for name in fields}
        if isinstance(v, np.ndarray):
            return {"sha256": hashlib.sha256(v.tobytes()).hexdigest(), "len": int(v.size)}
        if isinstance(v, list):
            return [plain(x) for x in v]
        return v

    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(args.get("mode", "peer")))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", json.dumps(args.get("listen", [])))
    conf.insert_json5("connect/endpoints", json.dumps(args.get("connect", [])))
    session = zenoh.open(conf)

    def tokens():
        found = []
        for pattern in ("@ros2_lv/**", "@/*/@ros2_lv/**"):
            for reply in session.liveliness().get(pattern, timeout=2.0):
                if reply.ok is not None:
                    found.append(str(reply.ok.key_expr))
        return sorted(found)

    def wait_for_peer():
        """Wait for a remote session; return the zids of the peers and of the routers connected."""
        deadline = time.monotonic() + args.get("connect_timeout", 10)
        while time.monotonic() < deadline:
            if list(session.info.peers_zid()) or list(session.info.routers_zid()):
                break
            time.sleep(0.02)
        return [str(z) for z in session.info.peers_zid()], [str(z) for z in session.info.routers_zid()]

    if args["role"] == "listen":
        got = []
        def on_sample(sample):
            payload = sample.payload.to_bytes()
            item = {"key": str(sample.key_expr), "head": payload[:4].hex(), "len": len(payload),
                    "shm": sample.payload.as_shm() is not None}
            if sample.attachment is not None:
                raw = sample.attachment.to_bytes()
                seq, stamp, gid = z_deserialize(tuple[Int64, Int64, list[UInt8]], zenoh.ZBytes(raw))
                item["attachment"] = {"seq": seq, "stamp": stamp, "gid": bytes(gid).hex(), "len": len(raw)}
            item["msg"] = plain(ts.deserialize_cdr(payload, args["type"]))
            got.append(item)
        sub = session.declare_subscriber(args["key"], on_sample)
        peers, routers = wait_for_peer()
        out(ready=True, peers=peers, routers=routers)
        # "count" samples end the wait early; its limit is generous, as a loaded machine can take seconds
        # between this report and the test's first publication
        deadline = time.monotonic() + args.get("wait", 30)
        while len(got) < args["count"] and time.monotonic() < deadline:
            time.sleep(0.01)
        gone = set()
        def on_token(s):
            if s.kind == zenoh.SampleKind.DELETE:
                gone.add(str(s.key_expr))
        patterns = ("@ros2_lv/**", "@/*/@ros2_lv/**")
        watchers = [session.liveliness().declare_subscriber(p, on_token) for p in patterns]
        out(samples=got)
        seen = tokens()
        out(tokens=seen)
        deadline = time.monotonic() + 10
        while not set(seen) <= gone and time.monotonic() < deadline:
            time.sleep(0.01)
        out(gone=sorted(gone))
    else:
        pubs = {item["key"]: session.declare_publisher(item["key"]) for item in args["payloads"]}
        peers, routers = wait_for_peer()
        out(ready=True, peers=peers, routers=routers)
        deadline = time.monotonic() + 10
        while not all(p.matching_status for p in pubs.values()) and time.monotonic() < deadline:
            time.sleep(0.01)
        out(matched=all(p.matching_status for p in pubs.values()), tokens=tokens())
        # "repeat_s": the payloads again every 0.1 s for that long (a sample put the moment a route
        # matched can be lost on a loaded machine: a test that only checks decoding takes the first)
        until = time.monotonic() + args.get("repeat_s", 0.0)
        while True:
            for item in args["payloads"]:
                attachment = bytes.fromhex(item["attachment"]) if "attachment" in item else None
                pubs[item["key"]].put(bytes.fromhex(item["payload"]), attachment=attachment)
                time.sleep(0.02)
            if time.monotonic() >= until:
                break
            time.sleep(0.1)
        time.sleep(0.2)
        out(done=True)
    session.close()
    '''
)


def free_endpoint() -> str:
    """A TCP endpoint on a port the OS just handed out, so parallel runs never collide."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


class Peer:
    """A peer process; its JSON lines are read on a thread so every wait has a timeout."""

    def __init__(self, script: Path, args: dict[str, Any]) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, str(script), json.dumps(args)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        self.lines: queue.Queue[dict[str, Any]] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.put(json.loads(line))

    def expect(self, field: str, timeout: float = 15.0) -> Any:
        return self.expect_line(field, timeout)[field]

    def connected(self) -> list[str]:
        """Zids of the peers and routers the process found connected when it became ready."""
        line = self.expect_line("ready")
        return line["peers"] + line["routers"]

    def expect_line(self, field: str, timeout: float = 15.0) -> dict[str, Any]:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                item = self.lines.get(timeout=0.1)
            except queue.Empty:
                if self.proc.poll() is not None and self.lines.empty():
                    break
                continue
            if field in item:
                return item
        err = self.proc.stderr.read() if self.proc.poll() is not None and self.proc.stderr else ""
        raise AssertionError(f"peer never reported {field!r}; stderr: {err}")

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(timeout=10)


@pytest.fixture(scope="module")
def peer_script(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("peer") / "peer.py"
    path.write_text(PEER_SCRIPT)
    return path


@pytest.fixture
def spawn(peer_script: Path) -> Iterator[Callable[[dict[str, Any]], Peer]]:
    peers: list[Peer] = []

    def start(args: dict[str, Any]) -> Peer:
        peers.append(Peer(peer_script, args))
        return peers[-1]

    yield start
    for peer in peers:
        peer.stop()


def wait_until(pred: Callable[[], bool], timeout: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout
    while not pred() and time.monotonic() < deadline:
        time.sleep(0.01)
    return pred()


def sending(send: Callable[[], None], wait: Callable[[], Any], period: float = 0.1) -> Any:
    """``wait()``'s result while ``send()`` repeats every ``period`` s on a thread: a sample sent the moment a
    route matched was lost on a loaded machine (the subscriber's side not yet ready for it)."""
    stop = threading.Event()

    def loop() -> None:
        while not stop.is_set():
            send()
            stop.wait(period)

    sender = threading.Thread(target=loop)
    sender.start()
    try:
        return wait()
    finally:
        stop.set()
        sender.join()


def watcher(**session: Any) -> dict[str, Any]:
    """Peer-process arguments for a session that only reports who connected and which tokens it sees."""
    return {"role": "listen", "key": "unused", "type": "std_msgs/msg/Header", "count": 0, **session}


def rmw_zenoh_gid(token: str) -> bytes:
    """What rmw_zenoh reports as an entity's gid (rmw_zenoh_cpp/src/detail/liveliness_utils.cpp,
    ``Entity::Entity``): ``simplified_XXH3_128bits`` over the whole liveliness key expression, then
    ``memcpy(gid, &hash.low64, 8); memcpy(gid + 8, &hash.high64, 8)``, i.e. two little-endian u64."""
    h = xxhash.xxh3_128(token.encode()).intdigest()
    return struct.pack("<QQ", h & (2**64 - 1), h >> 64)


def twist_cdr(vx: float, wz: float) -> bytes:
    T = REF.types
    vec = T["geometry_msgs/msg/Vector3"]
    msg = T["geometry_msgs/msg/Twist"](linear=vec(x=vx, y=0.0, z=0.0), angular=vec(x=0.0, y=0.0, z=wz))
    return bytes(REF.serialize_cdr(msg, "geometry_msgs/msg/Twist"))


def pose_cdr(frame: str, xyz: tuple[float, float, float], yaw: float) -> bytes:
    T = REF.types
    msg = T["geometry_msgs/msg/PoseStamped"](
        header=T["std_msgs/msg/Header"](
            stamp=T["builtin_interfaces/msg/Time"](sec=3, nanosec=4), frame_id=frame
        ),
        pose=T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=xyz[0], y=xyz[1], z=xyz[2]),
            orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=np.sin(yaw / 2), w=np.cos(yaw / 2)),
        ),
    )
    return bytes(REF.serialize_cdr(msg, "geometry_msgs/msg/PoseStamped"))


# --------------------------------------------------------------------------- keys and configuration
def test_key_for_rules() -> None:
    with RosZenohNode(ZenohNodeConfig(listen=())) as node:
        assert node.key_for("/a/b", "geometry_msgs/msg/Twist") == "a/b"
        assert node.key_for("a/b", "geometry_msgs/msg/Twist") == "a/b"
        for bad in ("", "/a//b", "/a/b/", "/a/*", "~/x", "/1abc"):
            with pytest.raises(ValueError):
                node.key_for(bad, "geometry_msgs/msg/Twist")
        with pytest.raises(ValueError):
            node.key_for("/a", "Twist")
    with RosZenohNode(ZenohNodeConfig(listen=(), namespace="/robot1")) as node:
        assert node.key_for("/a/b", "geometry_msgs/msg/Twist") == "robot1/a/b"
    with RosZenohNode(ZenohNodeConfig(listen=(), key_mode="rmw_zenoh", domain_id=7)) as node:
        assert node.key_for("/cmd_vel", "geometry_msgs/msg/Twist") == f"7/cmd_vel/{TWIST_DDS}/{TWIST_HASH}"


def test_config_file_is_authoritative_except_endpoints(tmp_path: Path) -> None:
    path = tmp_path / "zenoh.json5"
    path.write_text(
        '{ mode: "client", connect: { endpoints: ["tcp/127.0.0.1:9"] },\n'
        '  listen: { endpoints: ["tcp/127.0.0.1:8"] }, scouting: { multicast: { enabled: true } } }'
    )
    ep = free_endpoint()
    conf = ZenohNodeConfig(config_file=str(path), listen=(ep,)).zenoh_config()
    assert json.loads(conf.get_json("listen/endpoints")) == [ep]
    assert json.loads(conf.get_json("connect/endpoints")) == ["tcp/127.0.0.1:9"]
    assert json.loads(conf.get_json("mode")) == "client"
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is True
    plain = ZenohNodeConfig(listen=(ep,)).zenoh_config()
    assert json.loads(plain.get_json("mode")) == "peer"
    assert json.loads(plain.get_json("scouting/multicast/enabled")) is False
    assert json.loads(plain.get_json("transport/shared_memory/enabled")) is False  # docs/reliability.md
    with RosZenohNode.from_config(BridgeConfig(shared_memory=True), listen=()) as node:
        shm = node.config.zenoh_config()
    assert json.loads(shm.get_json("transport/shared_memory/enabled")) is True


def test_ros2dds_announcement_qos() -> None:
    """/tf_static is offered TRANSIENT_LOCAL depth 1 (tf2_ros StaticBroadcasterQoS), DDS enum values."""
    tf_hash = REF.hash_rihs01("tf2_msgs/msg/TFMessage")
    with RosZenohNode(ZenohNodeConfig(listen=())) as node:
        static = node.publisher("/tf_static", "tf2_msgs/msg/TFMessage")
        assert (
            static.token_key
            == f"@/{node.zid}/@ros2_lv/MP/tf_static/tf2_msgs§msg§TFMessage/:1:1:0,1:typehash={tf_hash};"
        )
        sub = node.subscribe("/x/y", "tf2_msgs/msg/TFMessage", print, qos=QosProfile(reliable=False, depth=5))
        assert (
            sub.token_key
            == f"@/{node.zid}/@ros2_lv/MS/x§y/tf2_msgs§msg§TFMessage/:0:0:0,5:typehash={tf_hash};"
        )
    with RosZenohNode(ZenohNodeConfig(listen=(), announce=False)) as node:
        assert node.publisher("/tf", "tf2_msgs/msg/TFMessage").token_key is None


def test_from_bridge_config_ignores_topic_namespace() -> None:
    with RosZenohNode.from_config(BridgeConfig(namespace="droneulator", listen=[])) as node:
        assert node.key_for("/droneulator/odom", "nav_msgs/msg/Odometry") == "droneulator/odom"


def test_bridge_config_checks_mode_and_ros2dds_namespace() -> None:
    assert BridgeConfig().mode == "router" and BridgeConfig().ros2dds_namespace == "/"
    for bad in (
        {"mode": "broker"},
        {"ros2dds_namespace": "robot1"},
        {"ros2dds_namespace": "/robot1/"},
        {"ros2dds_namespace": "/robot 1"},
        {"ros2dds_namespace": "/robot1", "key_mode": "rmw_zenoh"},
        {"mode": "client"},  # a client with nothing to connect to
    ):
        with pytest.raises(ValueError, match="bridge\\."):
            BridgeConfig(**bad)
    BridgeConfig(mode="client", connect=["tcp/127.0.0.1:7447"])
    BridgeConfig(mode="client", key_mode="rmw_zenoh")  # rmw_zenohd on 7447 by default
    with pytest.raises(ValueError, match="ros2dds"):
        ZenohNodeConfig(key_mode="rmw_zenoh", namespace="/robot1")
    with pytest.raises(ValueError, match="connect"):
        ZenohNodeConfig(mode="client", listen=())


def test_rmw_zenoh_connects_to_the_router_unless_told_otherwise(tmp_path: Path) -> None:
    """rmw_zenohd does not broker between peers: an rmw_zenoh node must connect to it (7447)."""

    def connects(cfg: ZenohNodeConfig) -> Any:
        return json.loads(cfg.zenoh_config().get_json("connect/endpoints"))

    assert connects(ZenohNodeConfig(key_mode="rmw_zenoh")) == ["tcp/127.0.0.1:7447"]
    assert connects(ZenohNodeConfig()) == []
    other = "tcp/10.1.2.3:7447"
    assert connects(ZenohNodeConfig(key_mode="rmw_zenoh", connect=(other,))) == [other]
    assert connects(ZenohNodeConfig(key_mode="rmw_zenoh", connect=())) == []
    # a config file's own endpoints stay; a file without any gets the router
    with_ep, without = tmp_path / "with.json5", tmp_path / "without.json5"
    with_ep.write_text(f'{{ connect: {{ endpoints: ["{other}"] }} }}')
    without.write_text('{ mode: "peer" }')
    assert connects(ZenohNodeConfig(key_mode="rmw_zenoh", config_file=str(with_ep))) == [other]
    assert connects(ZenohNodeConfig(key_mode="rmw_zenoh", config_file=str(without))) == [
        "tcp/127.0.0.1:7447"
    ]
    # an empty bridge.connect means "not given"; explicit overrides still replace it
    with RosZenohNode.from_config(BridgeConfig(key_mode="rmw_zenoh", listen=[])) as node:
        assert node.config.endpoints_to_connect() == ("tcp/127.0.0.1:7447",)
    # zenoh's connect semantics are pinned: retry in the background (peer, router), fail fast (client)
    conf = ZenohNodeConfig(key_mode="rmw_zenoh").zenoh_config()
    assert json.loads(conf.get_json("connect/timeout_ms")) == {"router": -1, "peer": -1, "client": 0}
    assert json.loads(conf.get_json("connect/exit_on_failure")) == {
        "router": False,
        "peer": False,
        "client": True,
    }


def test_rmw_gid_is_the_token_hash_in_rmw_zenoh_byte_order() -> None:
    token = (
        "@ros2_lv/0/1f2e3d4c5b6a79880f1e2d3c4b5a6978/0/10/MP/%/%/talker/%chatter/"
        "std_msgs::msg::dds_::String_/RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18/"
        "::,7:,:,:,,"
    )
    assert rmw_gid(token) == rmw_zenoh_gid(token) and len(rmw_gid(token)) == 16
    # XXH3-128 of "" is {low64 0x6001c324468d497f, high64 0x99aa06d3014798d8} (xxHash's sanity vector):
    # the gid starts with the low half, each half little endian
    assert rmw_gid("") == bytes.fromhex("7f498d4624c30160" "d8984701d306aa99")
    assert rmw_gid(token) != rmw_gid(token.replace("talker", "listener"))


def test_a_publisher_matches_only_while_a_subscriber_is_there() -> None:
    """``matching`` is the subscriber's presence: a publish before it would be lost, and ``replay`` waits
    on it. (It once read a status object's truth, always True.)"""
    import zenoh

    ep = free_endpoint()
    with RosZenohNode(ZenohNodeConfig(listen=(ep,))) as node:
        pub = node.publisher("/a/b", "geometry_msgs/msg/Twist")
        time.sleep(0.3)
        assert not pub.matching
        conf = zenoh.Config()
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("connect/endpoints", json.dumps([ep]))
        other = zenoh.open(conf)
        try:
            sub = other.declare_subscriber("a/**", lambda sample: None)
            assert wait_until(lambda: pub.matching)
            sub.undeclare()
            assert wait_until(lambda: not pub.matching)
        finally:
            other.close()


# --------------------------------------------------------------------------- ros2dds keys
def test_ros2dds_publish_reaches_peer_process(spawn: Callable[[dict[str, Any]], Peer]) -> None:
    ep = free_endpoint()
    with RosZenohNode(ZenohNodeConfig(listen=(ep,))) as node:
        peer = spawn(
            {"role": "listen", "connect": [ep], "key": "**", "type": "geometry_msgs/msg/Twist", "count": 2}
        )
        assert node.zid in peer.expect("peers")
        pub = node.publisher("/a/b", "geometry_msgs/msg/Twist")
        assert node.publisher("/a/b", "geometry_msgs/msg/Twist") is pub
        assert pub.gid is None  # no attachment, hence no gid, on bridge keys
        assert wait_until(lambda: pub.matching)
        pub.publish(
            M.serialize(M.TYPESTORE.deserialize_cdr(twist_cdr(1.25, -0.5), "geometry_msgs/msg/Twist"))
        )
        pub.publish(twist_cdr(2.0, 0.25), 123)
        samples = peer.expect("samples")
        assert [s["key"] for s in samples] == ["a/b", "a/b"]
        assert all(s["head"] == "00010000" and "attachment" not in s for s in samples)
        assert [(s["msg"]["linear"]["x"], s["msg"]["angular"]["z"]) for s in samples] == [
            (1.25, -0.5),
            (2.0, 0.25),
        ]
        # a bridge-style announcement (liveliness_mgt.rs::new_ke_liveliness_pub), keyless, RELIABLE,
        # VOLATILE, KEEP_LAST 10, USER_DATA with the type hash
        announce = f"@/{node.zid}/@ros2_lv/MP/a§b/geometry_msgs§msg§Twist/:1:0:0,10:typehash={TWIST_HASH};"
        assert peer.expect("tokens") == [announce]
    assert peer.expect("gone") == [announce]


def test_ros2dds_depth_image_payload(spawn: Callable[[dict[str, Any]], Peer]) -> None:
    import hashlib

    ep = free_endpoint()
    depth = np.random.default_rng(1).random((480, 640), dtype=np.float32)
    with RosZenohNode(ZenohNodeConfig(listen=(ep,), namespace="/sim")) as node:
        peer = spawn(
            {"role": "listen", "connect": [ep], "key": "sim/**", "type": "sensor_msgs/msg/Image", "count": 3}
        )
        peer.expect("peers")
        pub = node.publisher("/droneulator/front/depth/image_raw", "sensor_msgs/msg/Image")
        assert wait_until(lambda: pub.matching)
        # images are best effort (CongestionControl.DROP), so a loaded machine may drop some: keep
        # publishing frames until the peer has three, then check that what arrived is intact
        done = threading.Event()

        def stream() -> None:
            for i in range(1, 200):
                if done.is_set():
                    return
                pub.publish(M.serialize(M.image(i * 1_000_000, "front_optical_frame", depth)), i)
                time.sleep(0.05)

        publisher = threading.Thread(target=stream, daemon=True)
        publisher.start()
        try:
            samples = peer.expect("samples")
        finally:
            done.set()
            publisher.join(timeout=10)
    assert [s["key"] for s in samples] == ["sim/droneulator/front/depth/image_raw"] * 3
    stamps = [s["msg"]["header"]["stamp"]["nanosec"] for s in samples]
    assert stamps == sorted(set(stamps)) and all(t % 1_000_000 == 0 for t in stamps)
    msg = samples[-1]["msg"]
    assert (msg["width"], msg["height"], msg["encoding"], msg["step"]) == (640, 480, "32FC1", 2560)
    assert msg["data"]["sha256"] == hashlib.sha256(depth.tobytes()).hexdigest()


def test_ros2dds_namespace_is_followed_by_a_bridge_with_that_namespace(
    spawn: Callable[[dict[str, Any]], Peer],
) -> None:
    """``bridge.ros2dds_namespace="/robot1"`` speaks like ``zenoh-bridge-ros2dds -n /robot1``.

    zenoh-plugin-ros2dds (ros2_utils.rs) keys every interface ``<ns>/<name>``, absolute names such as
    ``/clock`` included, and announces that key in its tokens (liveliness_mgt.rs); a bridge with the
    same namespace strips the prefix back off (``key_expr_to_ros2_name``) to name its DDS topic.
    """
    ep = free_endpoint()
    clock_hash = REF.hash_rihs01("rosgraph_msgs/msg/Clock")
    with RosZenohNode.from_config(BridgeConfig(listen=[ep], ros2dds_namespace="/robot1")) as node:
        peer = spawn(
            {"role": "listen", "connect": [ep], "key": "robot1/**", "type": "rosgraph_msgs/msg/Clock"}
            | {"count": 1}
        )
        assert node.zid in peer.expect("routers")
        pub = node.publisher("/clock", "rosgraph_msgs/msg/Clock")
        node.subscribe("/droneulator/cmd_vel", "geometry_msgs/msg/Twist", print)
        assert wait_until(lambda: pub.matching)
        # a put right after the match may be lost on a loaded machine (the routers test saw it): repeat the
        # tick until the peer has one
        done = threading.Event()

        def tick() -> None:
            while not done.is_set():
                pub.publish(M.serialize(M.clock(42)))
                done.wait(0.05)

        ticker = threading.Thread(target=tick, daemon=True)
        ticker.start()
        try:
            sample = peer.expect("samples")[0]
        finally:
            done.set()
            ticker.join(timeout=10)
        assert sample["key"] == "robot1/clock" and sample["msg"]["clock"]["nanosec"] == 42
        tokens = peer.expect("tokens")
    zid = node.zid
    assert tokens == sorted(
        [
            f"@/{zid}/@ros2_lv/MP/robot1§clock/rosgraph_msgs§msg§Clock/:1:0:0,10:typehash={clock_hash};",
            f"@/{zid}/@ros2_lv/MS/robot1§droneulator§cmd_vel/geometry_msgs§msg§Twist/"
            f":1:0:0,10:typehash={TWIST_HASH};",
        ]
    )
    # what a `-n /robot1` bridge names the DDS topics it creates for these announcements
    keys = [t.split("/")[4].replace("§", "/") for t in tokens]
    assert [k.removeprefix("robot1") for k in keys] == ["/clock", "/droneulator/cmd_vel"]


# --------------------------------------------------------------------------- session modes and endpoints
def test_bridge_mode_reaches_the_session(spawn: Callable[[dict[str, Any]], Peer]) -> None:
    """The default bridge.mode opens a router: a remote session sees it among its routers."""
    ep = free_endpoint()
    with RosZenohNode.from_config(BridgeConfig(listen=[ep])) as node:
        assert node.config.mode == "router"
        assert node.zid in spawn(watcher(connect=[ep])).expect("routers")
    with RosZenohNode.from_config(BridgeConfig(listen=[ep], mode="peer")) as node:
        assert node.zid in spawn(watcher(connect=[ep])).expect("peers")


def test_second_session_from_the_same_bridge_config_with_overrides() -> None:
    """A second process of the run opens a client of the simulator's router with from_config overrides."""
    ep = free_endpoint()
    bridge = BridgeConfig(listen=[ep])
    got: queue.Queue[Any] = queue.Queue()
    with (
        RosZenohNode.from_config(bridge) as sim,
        RosZenohNode.from_config(bridge, mode="client", listen=(), connect=(ep,)) as second,
    ):
        assert (second.config.mode, second.config.listen, second.config.connect) == ("client", (), (ep,))
        sim.subscribe("/droneulator/cmd_vel", "geometry_msgs/msg/Twist", got.put)
        pub = second.publisher("/droneulator/cmd_vel", "geometry_msgs/msg/Twist")
        assert wait_until(lambda: pub.matching)
        pub.publish(twist_cdr(0.75, -0.25))
        assert M.twist_to_command(got.get(timeout=10)) == (0.75, -0.25)


@pytest.mark.parametrize("mode", ["peer", "router"])
def test_missing_router_neither_fails_nor_blocks_the_open_and_is_retried(
    mode: str, spawn: Callable[[dict[str, Any]], Peer]
) -> None:
    ep = free_endpoint()
    start = time.monotonic()
    with RosZenohNode(ZenohNodeConfig(mode=mode, listen=(), connect=(ep,))) as node:  # type: ignore[arg-type]
        assert time.monotonic() - start < 3.0
        # the router comes up later: zenoh's background retry connects to it
        assert node.zid in spawn(watcher(mode="router", listen=[ep])).connected()


def test_client_without_its_router_fails_fast_with_a_clear_error() -> None:
    ep = free_endpoint()
    start = time.monotonic()
    with pytest.raises(ConnectionError, match=f"client mode.*{ep}"):
        RosZenohNode(ZenohNodeConfig(mode="client", listen=(), connect=(ep,)))
    assert time.monotonic() - start < 3.0


def test_rmw_zenoh_node_reaches_a_router_on_the_default_endpoint(
    spawn: Callable[[dict[str, Any]], Peer],
) -> None:
    """Key mode alone is enough: the node finds a late ``rmw_zenohd`` on 7447, with gids on the wire."""
    with socket.socket() as probe:
        if probe.connect_ex(("127.0.0.1", 7447)) == 0:
            pytest.skip("port 7447 is taken on this machine (a Zenoh router may already run there)")
    with RosZenohNode(ZenohNodeConfig(listen=(), key_mode="rmw_zenoh")) as node:
        pub = node.publisher("/droneulator/cmd_vel", "geometry_msgs/msg/Twist")
        router = spawn(
            {
                "role": "listen",
                "mode": "router",
                "listen": ["tcp/127.0.0.1:7447"],
                "key": "0/**",
                "type": "geometry_msgs/msg/Twist",
                "count": 1,
                "wait": 20,
            }
        )
        assert node.zid in router.expect("peers")
        assert wait_until(lambda: pub.matching)
        (sample,) = sending(lambda: pub.publish(twist_cdr(0.5, 0.0)), lambda: router.expect("samples"))
        token = (
            f"@ros2_lv/0/{node.zid}/0/1/MP/%/%/droneulator/%droneulator%cmd_vel/{TWIST_DDS}/{TWIST_HASH}/::,10:,:,:,,"
        )
        assert sample["attachment"]["gid"] == rmw_zenoh_gid(token).hex()
        assert token in router.expect("tokens")


# --------------------------------------------------------------------------- rmw_zenoh keys
def test_rmw_zenoh_key_attachment_and_liveliness(spawn: Callable[[dict[str, Any]], Peer]) -> None:
    ep = free_endpoint()
    cfg = ZenohNodeConfig(listen=(ep,), connect=(), key_mode="rmw_zenoh", domain_id=3)
    with RosZenohNode(cfg) as node:
        peer = spawn(
            {"role": "listen", "connect": [ep], "key": "3/**", "type": "geometry_msgs/msg/Twist", "count": 3}
        )
        assert node.zid in peer.expect("peers")
        pub = node.publisher("/a/b", "geometry_msgs/msg/Twist")
        assert wait_until(lambda: pub.matching)
        before = time.time_ns()
        pub.publish(twist_cdr(0.1, 0.0), 1_000)
        pub.publish(twist_cdr(0.2, 0.0), 2_000)
        pub.publish(twist_cdr(0.3, 0.0))
        samples = peer.expect("samples")
        assert {s["key"] for s in samples} == {f"3/a/b/{TWIST_DDS}/{TWIST_HASH}"}
        att = [s["attachment"] for s in samples]
        assert [a["seq"] for a in att] == [1, 2, 3]
        assert [a["stamp"] for a in att[:2]] == [1_000, 2_000]
        assert before <= att[2]["stamp"] <= time.time_ns()
        assert {a["len"] for a in att} == {33}
        assert [s["msg"]["linear"]["x"] for s in samples] == [0.1, 0.2, 0.3]
        prefix = f"@ros2_lv/3/{node.zid}/0"
        expected = [
            f"{prefix}/0/NN/%/%/droneulator",
            f"{prefix}/1/MP/%/%/droneulator/%a%b/{TWIST_DDS}/{TWIST_HASH}/::,10:,:,:,,",
        ]
        # the gid on the wire is the one ROS derives from the token (ros2 topic info -v)
        assert {a["gid"] for a in att} == {rmw_zenoh_gid(expected[1]).hex()}
        assert pub.gid == rmw_zenoh_gid(expected[1])
        assert peer.expect("tokens") == sorted(expected)
    assert peer.expect("gone") == sorted(expected)


def test_rmw_zenoh_qos_in_token(spawn: Callable[[dict[str, Any]], Peer]) -> None:
    ep = free_endpoint()
    with RosZenohNode(
        ZenohNodeConfig(
            listen=(ep,), connect=(), key_mode="rmw_zenoh", node_name="sim", node_namespace="/uav"
        )
    ) as node:
        tf_hash = REF.hash_rihs01("tf2_msgs/msg/TFMessage")
        peer = spawn(
            {"role": "listen", "connect": [ep], "key": "0/**", "type": "tf2_msgs/msg/TFMessage", "count": 1}
        )
        peer.expect("peers")
        static = node.publisher("/tf_static", "tf2_msgs/msg/TFMessage")  # tf2 static QoS by default
        node.publisher("images", "sensor_msgs/msg/Image", qos=QosProfile(reliable=False, depth=42))
        tf = M.tf_message([M.transform_stamped(5, "base_link", "cam_link", [0.1, 0, 0], [0, 0, 0, 1])])
        # an advanced (transient-local) publisher has no matching status: probe the key with a plain one
        probe = node.session.declare_publisher(static.key)
        assert wait_until(lambda: probe.matching_status)
        probe.undeclare()
        sent = [0]

        def publish() -> None:
            static.publish(M.serialize(tf), 5)
            sent[0] += 1

        (sample,) = sending(publish, lambda: peer.expect("samples"), period=0.2)
        assert sample["key"] == f"0/tf_static/tf2_msgs::msg::dds_::TFMessage_/{tf_hash}"
        assert 1 <= sample["attachment"]["seq"] <= sent[0]  # rmw_zenoh numbers a publisher's samples from 1
        assert sample["msg"]["transforms"][0]["child_frame_id"] == "cam_link"
        prefix = f"@ros2_lv/0/{node.zid}/0"
        image_hash = REF.hash_rihs01("sensor_msgs/msg/Image")
        assert peer.expect("tokens") == sorted(
            [
                f"{prefix}/0/NN/%/%uav/sim",
                f"{prefix}/1/MP/%/%uav/sim/%tf_static/tf2_msgs::msg::dds_::TFMessage_/{tf_hash}/:1:,1:,:,:,,",
                f"{prefix}/2/MP/%/%uav/sim/%uav%images/sensor_msgs::msg::dds_::Image_/{image_hash}/2::,:,:,:,,",
            ]
        )


# --------------------------------------------------------------------------- subscribing
def test_subscribe_decodes_commands_from_peer(spawn: Callable[[dict[str, Any]], Peer]) -> None:
    """The node connects to a listening peer this time (``connect`` instead of ``listen``). The peer
    repeats its commands: once each lost the first twist in a suite run with a core busy."""
    ep = free_endpoint()
    peer = spawn(
        {
            "role": "publish",
            "listen": [ep],
            "payloads": [
                {"key": "droneulator/cmd_vel", "payload": twist_cdr(1.5, 0.2).hex()},
                {"key": "droneulator/goal_pose", "payload": pose_cdr("map", (4.0, -1.0, 2.5), 1.2).hex()},
            ],
            "repeat_s": 2.0,
        }
    )
    twists: queue.Queue[Any] = queue.Queue()
    goals: queue.Queue[Any] = queue.Queue()
    with RosZenohNode(ZenohNodeConfig(listen=(), connect=(ep,))) as node:
        node.subscribe("/droneulator/cmd_vel", "geometry_msgs/msg/Twist", twists.put)
        node.subscribe("/droneulator/goal_pose", "geometry_msgs/msg/PoseStamped", goals.put)
        assert peer.expect("matched") is True
        assert M.twist_to_command(twists.get(timeout=15)) == (1.5, 0.2)
        frame, pos, yaw = M.pose_stamped_to_goal(goals.get(timeout=15))
        peer.expect("done")
    assert frame == "map" and pos.tolist() == [4.0, -1.0, 2.5] and yaw == pytest.approx(1.2)


def test_bad_payloads_are_logged_and_skipped(
    spawn: Callable[[dict[str, Any]], Peer], caplog: pytest.LogCaptureFixture
) -> None:
    ep = free_endpoint()
    good = twist_cdr(0.7, -0.1)
    received: list[Any] = []
    done = threading.Event()

    def on_twist(msg: Any) -> None:
        received.append(msg)
        done.set()

    with (
        caplog.at_level(logging.ERROR, logger="droneulator.ros"),
        RosZenohNode(ZenohNodeConfig(listen=(ep,))) as node,
    ):
        sub = node.subscribe("/cmd_vel", "geometry_msgs/msg/Twist", on_twist)
        peer = spawn(
            {
                "role": "publish",
                "connect": [ep],
                "payloads": [
                    {"key": "cmd_vel", "payload": b"definitely not cdr".hex()},
                    *[{"key": "cmd_vel", "payload": good[:20].hex()}] * 49,  # a flood (found by the fuzz)
                    {"key": "cmd_vel", "payload": good.hex()},
                ],
            }
        )
        assert peer.expect("matched") is True
        assert done.wait(15)
        peer.expect("done")
    assert len(received) == 1 and M.twist_to_command(received[0]) == (0.7, -0.1)
    assert sub.errors == 50 and sub.received == 1
    errors = [r for r in caplog.records if r.name == "droneulator.ros" and r.levelno == logging.ERROR]
    assert len(errors) == 1 and "/cmd_vel" in errors[0].getMessage()  # the burst's first; the rest counted


def test_callback_exception_does_not_stop_subscription(
    spawn: Callable[[dict[str, Any]], Peer], caplog: pytest.LogCaptureFixture
) -> None:
    ep = free_endpoint()
    calls: list[float] = []
    done = threading.Event()

    def flaky(msg: Any) -> None:
        calls.append(msg.linear.x)
        if len(calls) == 1:
            raise RuntimeError("boom")
        done.set()

    with (
        caplog.at_level(logging.ERROR, logger="droneulator.ros"),
        RosZenohNode(ZenohNodeConfig(listen=(ep,))) as node,
    ):
        node.subscribe("/cmd_vel", "geometry_msgs/msg/Twist", flaky)
        peer = spawn(
            {
                "role": "publish",
                "connect": [ep],
                "payloads": [
                    {"key": "cmd_vel", "payload": twist_cdr(1.0, 0).hex()},
                    {"key": "cmd_vel", "payload": twist_cdr(2.0, 0).hex()},
                ],
            }
        )
        assert done.wait(15)
        peer.expect("done")
    assert calls == [1.0, 2.0]
    assert any("callback for /cmd_vel failed" in r.getMessage() for r in caplog.records)


def test_rmw_zenoh_subscription_token_and_attachment_tolerance(
    spawn: Callable[[dict[str, Any]], Peer],
) -> None:
    ep = free_endpoint()
    got: queue.Queue[Any] = queue.Queue()
    with RosZenohNode(ZenohNodeConfig(listen=(ep,), connect=(), key_mode="rmw_zenoh")) as node:
        sub = node.subscribe("/droneulator/cmd_vel", "geometry_msgs/msg/Twist", got.put)
        key = f"0/droneulator/cmd_vel/{TWIST_DDS}/{TWIST_HASH}"
        assert sub.key == key
        # what an rmw_zenoh publisher sends: the CDR sample plus its 33-byte attachment
        attachment = (7).to_bytes(8, "little") + (99).to_bytes(8, "little") + b"\x10" + bytes(range(16))
        peer = spawn(
            {
                "role": "publish",
                "connect": [ep],
                "payloads": [
                    {"key": key, "payload": twist_cdr(0.5, 0.05).hex(), "attachment": attachment.hex()},
                ],
            }
        )
        tokens = peer.expect("tokens")
        token = (
            f"@ros2_lv/0/{node.zid}/0/1/MS/%/%/droneulator/%droneulator%cmd_vel/{TWIST_DDS}/{TWIST_HASH}/::,10:,:,:,,"
        )
        assert token in tokens
        assert sub.gid == rmw_zenoh_gid(token)
        assert M.twist_to_command(got.get(timeout=15)) == (0.5, 0.05)


def test_unclosed_node_does_not_hang_interpreter_exit() -> None:
    """zenoh-python callback threads would block exit; the node closes itself from threading's exit hook."""
    code = (
        "from droneulator.ros.zenoh_node import RosZenohNode, ZenohNodeConfig\n"
        "node = RosZenohNode(ZenohNodeConfig(listen=(), connect=(), key_mode='rmw_zenoh'))\n"
        "node.subscribe('/cmd_vel', 'geometry_msgs/msg/Twist', print)\n"
        "node.publisher('/odom', 'nav_msgs/msg/Odometry')\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=Path(__file__).resolve().parents[1], timeout=30, capture_output=True
    )
    assert done.returncode == 0, done.stderr


def test_closed_node_refuses_work() -> None:
    node = RosZenohNode(ZenohNodeConfig(listen=()))
    pub = node.publisher("/x", "std_msgs/msg/Header")
    node.close()
    node.close()
    with pytest.raises(RuntimeError):
        node.publisher("/y", "std_msgs/msg/Header")
    with pytest.raises(RuntimeError):
        pub.publish(M.serialize(M.header(0, "map")))
