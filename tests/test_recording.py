"""ROS 2 bags (MCAP): the writer's format, the Zenoh recorder, replay, and ``droneulator run --record``.

Everything is read back by independent decoders: the ``mcap`` reader with ``mcap_ros2``'s own CDR
decoder (which parses the recorded ``ros2msg`` schemas itself), and rosbags' rosbag2 ``Reader`` /
``AnyReader``. Publishers and subscribers are real Zenoh sessions.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
import yaml
import zenoh
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rosbags.highlevel import AnyReader
from rosbags.interfaces import QosDurability
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from droneulator.config import CameraConfig, load_config
from droneulator.recording.bag import BagWriter, check_output, message_definition
from droneulator.recording.recorder import Recorder, RecorderConfig
from droneulator.recording.replay import ReplayConfig, replay
from droneulator.ros import messages as M
from droneulator.ros.topics import TYPES, topic_names, vehicle_topics
from droneulator.ros.zenoh_node import RosZenohNode, ZenohNodeConfig
from droneulator.runtime.launch import free_port, launch_run

ROOT = Path(__file__).resolve().parents[1]
NS = "droneulator"
STATE_PERIOD = 10_000_000  # runtime.state_hz 100


def endpoint() -> str:
    return f"tcp/127.0.0.1:{free_port()}"


def read_mcap(path: Path) -> tuple[object, dict[str, list[tuple[int, bytes, object]]]]:
    """Summary and, per topic, (log time, raw CDR, message decoded by mcap_ros2 from the file's schema)."""
    out: dict[str, list[tuple[int, bytes, object]]] = defaultdict(list)
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        for _schema, channel, message, decoded in reader.iter_decoded_messages(log_time_order=False):
            out[channel.topic].append((message.log_time, bytes(message.data), decoded))
    return summary, out


def stamp_of(msg: object) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def sample_messages(t_ns: int) -> dict[str, tuple[str, object]]:
    """One message of every type the simulator publishes, stamped ``t_ns``."""
    names = {**vehicle_topics(NS), **topic_names(NS, "front")}
    depth = np.linspace(0.5, 9.0, 48, dtype=np.float32).reshape(6, 8)
    k = [100.0, 0, 4, 0, 100.0, 3, 0, 0, 1]
    msgs = {
        "clock": M.clock(t_ns),
        "tf": M.tf_message([M.transform_stamped(t_ns, "odom", "base_link", [1, 2, 3], [0, 0, 0, 1])]),
        "tf_static": M.tf_message([M.transform_stamped(t_ns, "map", "odom", [0, 0, 0], [0, 0, 0, 1])]),
        "odom": M.odometry(t_ns, "odom", "base_link", [1, 2, 3], [0, 0, 0, 1], [0.5, 0, 0], [0, 0, 0.1]),
        "position_cmd": M.position_command(t_ns, "world", [1, 2, 3], yaw=0.3),
        "goal_pose": M.pose_stamped(t_ns, "map", [4, 5, 6], [0, 0, 0, 1]),
        "pose": M.pose_stamped(t_ns, "odom", [1, 2, 3], [0, 0, 0, 1]),
        "rgb": M.compressed_image(t_ns, "front_optical_frame", "jpeg", b"\xff\xd8not-a-real-jpeg"),
        "seg": M.compressed_image(t_ns, "front_optical_frame", "png", b"\x89PNG-ish"),
        "depth": M.image(t_ns, "front_optical_frame", depth),
        "info_rgb": M.camera_info(t_ns, "front_optical_frame", 8, 6, k),
    }
    return {names[key]: (TYPES[key], msg) for key, msg in msgs.items()}


# --------------------------------------------------------------------------- the file format
@pytest.mark.parametrize("layout", ["file", "directory"])
def test_bag_reads_back_with_mcap_ros2_and_rosbags(tmp_path: Path, layout: str) -> None:
    path = tmp_path / ("flight.mcap" if layout == "file" else "flight")
    bag = BagWriter(path, "zstd")
    written: dict[str, list[tuple[int, bytes]]] = defaultdict(list)
    for i in range(5):
        t = 1_000_000_000 + i * STATE_PERIOD
        for topic, (typename, msg) in sample_messages(t).items():
            raw = bytes(M.serialize(msg))
            bag.write(bag.channel(topic, typename), t, raw, i + 1)
            written[topic].append((t, raw))
    bag.close()
    mcap_file = path if layout == "file" else path / "flight_0.mcap"

    summary, got = read_mcap(mcap_file)
    with open(mcap_file, "rb") as f:
        reader = make_reader(f)
        assert reader.get_header().profile == "ros2"
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    assert "serialized_metadata" in meta["rosbag2"]
    assert all(c.compression == "zstd" for c in summary.chunk_indexes)
    for topic, items in written.items():
        assert [(t, raw) for t, raw, _ in got[topic]] == items, topic  # the same bytes, sim-time log times
    for schema in summary.schemas.values():
        assert schema.encoding == "ros2msg"
        assert schema.data.decode() == message_definition(schema.name)
        # the schema alone rebuilds the type: same RIHS01 hash as Jazzy's own definition
        fresh = get_typestore(Stores.EMPTY)
        fresh.register(get_types_from_msg(schema.data.decode(), schema.name))
        assert fresh.hash_rihs01(schema.name) == M.type_hash(schema.name)
    for ch in summary.channels.values():
        assert ch.message_encoding == "cdr"
        assert ch.metadata["topic_type_hash"] == M.type_hash(summary.schemas[ch.schema_id].name)
    odom = got[f"/{NS}/odom"][0][2]
    assert odom.pose.pose.position.y == 2.0 and odom.header.frame_id == "odom"  # mcap_ros2's own decoder
    depth = got[f"/{NS}/front/depth/image_raw"][0][2]
    assert depth.encoding == "32FC1" and depth.width == 8 and len(depth.data) == 6 * 8 * 4

    with Reader(path) as rb:  # plain .mcap and bag directory (metadata.yaml) alike
        assert rb.message_count == 5 * len(written)
        conns = {c.topic: c for c in rb.connections}
        types = {t: ty for t, (ty, _) in sample_messages(0).items()}
        assert {t: c.msgtype for t, c in conns.items()} == types
        assert conns["/tf_static"].ext.offered_qos_profiles[0].durability == QosDurability.TRANSIENT_LOCAL
        assert conns[f"/{NS}/odom"].ext.offered_qos_profiles[0].durability == QosDurability.VOLATILE
    with AnyReader([path]) as ar:
        stamps = [
            stamp_of(ar.deserialize(raw, c.msgtype))
            for c, _t, raw in ar.messages()
            if c.topic == f"/{NS}/odom"
        ]
    assert stamps == [t for t, _ in written[f"/{NS}/odom"]]


@pytest.mark.parametrize("split", ["size", "duration"])
def test_a_bag_that_splits_reads_back_whole_with_rosbags_and_each_file_alone(
    tmp_path: Path, split: str
) -> None:
    path = tmp_path / "long"
    limits = {"max_bytes": 64 * 1024} if split == "size" else {"max_duration_s": 0.05}
    bag = BagWriter(path, "none", chunk_size=16 * 1024, **limits)
    written: list[tuple[str, int, bytes]] = []
    big = np.arange(64 * 64, dtype=np.float32).reshape(64, 64)  # a 16 kB depth image per step
    for i in range(30):
        t = 1_000_000_000 + i * STATE_PERIOD
        msgs = {
            **sample_messages(t),
            f"/{NS}/down/depth/image_raw": (TYPES["depth"], M.image(t, "down", big)),
        }
        for topic, (typename, msg) in msgs.items():
            if topic == "/tf_static" and i:
                continue
            raw = bytes(M.serialize(msg))
            bag.write(bag.channel(topic, typename), t, raw, i + 1)
            written.append((topic, t, raw))
    bag.close()

    files = sorted(path.glob("*.mcap"), key=lambda f: int(f.stem.rsplit("_", 1)[1]))
    assert (
        [f.name for f in files]
        == [f"long_{k}.mcap" for k in range(len(files))]
        == [f.name for f in bag.files]
    )
    assert len(files) >= 4
    per_file = []
    for f in files:  # each file stands alone: its own schemas, channels, summary and rosbag2 record
        summary, got = read_mcap(f)
        assert {c.topic for c in summary.channels.values()} == {t for t, _, _ in written}
        spans = [t for items in got.values() for t, _, _ in items]
        if split == "size":  # the limit, passed by at most a chunk and a message
            assert sum(len(raw) for items in got.values() for _, raw, _ in items) < (64 + 16 + 17) * 1024
            assert f == files[-1] or f.stat().st_size >= 64 * 1024
        else:
            assert max(spans) - min(spans) <= 50_000_000
        per_file.append(sum(len(v) for v in got.values()))
    assert sum(per_file) == len(written)
    with Reader(path) as rb:  # metadata.yaml lists every file; rosbags reads them as one bag
        assert rb.message_count == len(written)
        got_all = sorted((c.topic, t, bytes(raw)) for c, t, raw in rb.messages())
    assert got_all == sorted(written)
    info = yaml.safe_load((path / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert info["relative_file_paths"] == [f.name for f in files]
    assert [f["message_count"] for f in info["files"]] == per_file


def test_existing_output_is_refused(tmp_path: Path) -> None:
    (tmp_path / "a.mcap").write_bytes(b"keep me")
    with pytest.raises(ValueError, match="already exists"):
        check_output(tmp_path / "a.mcap")
    with pytest.raises(ValueError, match="does not exist"):
        check_output(tmp_path / "missing" / "b.mcap")
    with pytest.raises(ValueError, match="compression"):
        BagWriter(tmp_path / "c.mcap", "gzip")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="must be a bag directory"):
        BagWriter(tmp_path / "c.mcap", max_bytes=1 << 20)
    with pytest.raises(ValueError, match=">= 0"):
        BagWriter(tmp_path / "c", max_duration_s=-1.0)
    assert not (tmp_path / "c.mcap").exists() and not (tmp_path / "c").exists()
    assert (tmp_path / "a.mcap").read_bytes() == b"keep me"
    for argv, said in (
        (["record", "-o", str(tmp_path / "d.mcap"), "--max-bag-size", "1G"], "must be a bag directory"),
        (["record", "-o", str(tmp_path / "d"), "--max-bag-size", "lots"], "not a size"),
        (["run", "--max-bag-duration", "60"], "add --record BAG"),
    ):
        out = subprocess.run(
            [sys.executable, "-m", "droneulator.cli", *argv],
            capture_output=True,
            text=True,
            cwd=ROOT,
            env={**os.environ, "PYTHONPATH": str(ROOT)},
            timeout=60,
        )
        assert out.returncode == 2 and said in out.stderr, (argv, out.stderr)
    assert not (tmp_path / "d").exists() and not (tmp_path / "d.mcap").exists()
    out = subprocess.run(
        [sys.executable, "-m", "droneulator.cli", "record", "-o", str(tmp_path / "a.mcap")],
        capture_output=True,
        text=True,
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        timeout=60,
    )
    assert out.returncode == 2 and "already exists" in out.stderr


# --------------------------------------------------------------------------- recorder on Zenoh
def publish_flight(node: RosZenohNode, n: int, extra_topic: str | None = None) -> dict[str, list[bytes]]:
    """Publish ``n`` steps of every simulator type (and a Twist on ``extra_topic``); returns the bytes."""
    sent: dict[str, list[bytes]] = defaultdict(list)
    block = zenoh.CongestionControl.BLOCK
    twist = M.TYPESTORE.types["geometry_msgs/msg/Twist"]
    vec = M.TYPESTORE.types["geometry_msgs/msg/Vector3"]
    for i in range(n):
        for topic, (typename, msg) in sample_messages(2_000_000_000 + i * STATE_PERIOD).items():
            raw = bytes(M.serialize(msg))
            node.publisher(topic, typename, congestion_control=block).publish(raw, 0)
            sent[topic].append(raw)
        if extra_topic is not None:
            cmd = twist(linear=vec(x=float(i), y=0.0, z=0.0), angular=vec(x=0.0, y=0.0, z=0.0))
            raw = bytes(M.serialize(cmd))
            node.publisher(extra_topic, "geometry_msgs/msg/Twist", congestion_control=block).publish(raw)
            sent[extra_topic].append(raw)
    return sent


@pytest.mark.parametrize("key_mode", ["ros2dds", "rmw_zenoh"])
def test_recorder_writes_every_sample_with_its_stamp(tmp_path: Path, key_mode: str) -> None:
    ep = endpoint()
    pub = RosZenohNode(ZenohNodeConfig(mode="router", listen=(ep,), connect=(), key_mode=key_mode))
    try:
        rec = Recorder(tmp_path / "rec.mcap", RecorderConfig(connect=(ep,), key_mode=key_mode))
        rec.start()
        # /droneulator/ext/cmd is in no topic table: ros2dds learns its type from the liveliness token
        sent = publish_flight(pub, 60, extra_topic=f"/{NS}/ext/cmd")
        time.sleep(0.5)
        stats = rec.close()
    finally:
        pub.close()
    assert stats.untyped == {}
    assert stats.written == {t: len(v) for t, v in sent.items()}
    _summary, got = read_mcap(tmp_path / "rec.mcap")
    assert set(got) == set(sent)
    for topic, raws in sent.items():
        assert [raw for _t, raw, _m in got[topic]] == raws, topic
    for topic in (f"/{NS}/odom", f"/{NS}/front/depth/image_raw", "/tf", "/clock"):
        logs = [t for t, _raw, _m in got[topic]]
        assert logs == [2_000_000_000 + i * STATE_PERIOD for i in range(60)], topic
    # the unstamped Twist is logged at the latest stamp seen before it
    assert [t for t, _r, _m in got[f"/{NS}/ext/cmd"]][-1] == 2_000_000_000 + 59 * STATE_PERIOD


def test_recorder_blocks_instead_of_dropping_when_the_writer_lags(tmp_path: Path) -> None:
    """A writer slowed to 5 ms a message with a 16 MiB queue: the publisher waits, nothing is lost."""
    ep = endpoint()
    pub = RosZenohNode(ZenohNodeConfig(mode="router", listen=(ep,), connect=()))
    rec = Recorder(tmp_path / "slow.mcap", RecorderConfig(connect=(ep,), max_queue_bytes=16 * 1024 * 1024))
    write = rec._write

    def slow_write(*a: object) -> None:
        time.sleep(0.005)
        write(*a)

    rec._write = slow_write  # type: ignore[method-assign]
    try:
        rec.start()
        block = zenoh.CongestionControl.BLOCK
        images = pub.publisher(f"/{NS}/front/depth/image_raw", TYPES["depth"], congestion_control=block)
        big = np.zeros((480, 640), np.float32)
        for i in range(40):  # 49 MB: three times the queue
            images.publish(bytes(M.serialize(M.image(i * 33_333_333, "front_optical_frame", big))))
        deadline = time.monotonic() + 30
        while rec.received < 40 and time.monotonic() < deadline:  # the last ones are still on the way
            time.sleep(0.05)
        stats = rec.close()
    finally:
        pub.close()
    assert stats.written == {f"/{NS}/front/depth/image_raw": 40}
    assert rec.waits > 0  # the queue filled and the callback held Zenoh back instead of dropping


def test_cli_record_stops_on_sigint_with_a_finalised_file(tmp_path: Path) -> None:
    ep = endpoint()
    pub = RosZenohNode(ZenohNodeConfig(mode="router", listen=(ep,), connect=()))
    out = tmp_path / "cli"  # a bag directory, like ros2 bag record -o
    proc = subprocess.Popen(
        [sys.executable, "-m", "droneulator.cli", "record", "-o", str(out), "--zenoh", ep]
        + ["--compression", "lz4"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT), "PYTHONUNBUFFERED": "1"},
    )
    try:
        assert proc.stdout is not None
        assert "recording" in proc.stdout.readline()
        stop = threading.Event()
        count = 0

        def publish() -> None:
            nonlocal count
            clock = pub.publisher("/clock", TYPES["clock"])
            while not stop.is_set():
                count += 1
                clock.publish(bytes(M.serialize(M.clock(count * STATE_PERIOD))))
                time.sleep(0.002)

        th = threading.Thread(target=publish)
        th.start()
        time.sleep(1.5)
        proc.send_signal(signal.SIGINT)  # mid-recording
        output = proc.communicate(timeout=30)[0]
        stop.set()
        th.join()
    finally:
        if proc.poll() is None:
            proc.kill()
        pub.close()
    assert proc.returncode == 0, output
    assert "/clock" in output
    with Reader(out) as rb:  # metadata.yaml written, summary present
        n = rb.message_count
        stamps = [int(t) for _c, t, _raw in rb.messages()]
    assert 100 < n <= count
    assert stamps == [STATE_PERIOD * (stamps[0] // STATE_PERIOD + i) for i in range(n)]  # no gap


# --------------------------------------------------------------------------- replay
@pytest.mark.alone
@pytest.mark.parametrize("layout", ["file", "split"])
def test_replay_reproduces_stamps_in_order_at_the_recorded_rate(tmp_path: Path, layout: str) -> None:
    path = tmp_path / ("r.mcap" if layout == "file" else "r")
    bag = BagWriter(path, max_duration_s=0.0 if layout == "file" else 0.25)
    expected: dict[str, list[int]] = defaultdict(list)
    for i in range(100):  # 1 s of sim time
        t = 5_000_000_000 + i * STATE_PERIOD
        for topic, (typename, msg) in sample_messages(t).items():
            if topic in (f"/{NS}/odom", f"/{NS}/front/depth/image_raw", "/tf_static") and (
                topic != "/tf_static" or i == 0
            ):
                bag.write(bag.channel(topic, typename), t, bytes(M.serialize(msg)))
                expected[topic].append(t)
    bag.close()

    ep = endpoint()
    got: dict[str, list[int]] = defaultdict(list)
    sub_node = RosZenohNode(ZenohNodeConfig(mode="peer", listen=(), connect=(ep,)))
    try:
        for topic in (f"/{NS}/odom", f"/{NS}/front/depth/image_raw"):
            sub_node.subscribe(
                topic,
                "nav_msgs/msg/Odometry" if topic.endswith("odom") else "sensor_msgs/msg/Image",
                lambda m, topic=topic: got[topic].append(stamp_of(m)),
            )
        t0 = time.monotonic()
        counts = replay(path, ReplayConfig(listen=(ep,), rate=2.0, wait_subscriber_s=10.0))
        wall = time.monotonic() - t0
        assert len(bag.files) == (1 if layout == "file" else 4)
        deadline = time.monotonic() + 5
        while len(got[f"/{NS}/odom"]) < 100 and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        sub_node.close()
    assert counts == {k: len(v) for k, v in expected.items()}
    assert got[f"/{NS}/odom"] == expected[f"/{NS}/odom"]
    assert got[f"/{NS}/front/depth/image_raw"] == expected[f"/{NS}/front/depth/image_raw"]
    assert 0.99 * 0.5 <= wall < 5.0  # 0.99 s of sim time at 2x


def test_replay_waits_for_a_subscribers_topics_declared_one_after_the_other(tmp_path: Path) -> None:
    """A consumer that subscribes to its topics one after the other (here the depth 0.3 s after the
    odometry) gets every topic from its first message: the replay starts once the matches settle."""
    path = tmp_path / "r.mcap"
    bag = BagWriter(path)
    for i in range(100):
        t = 5_000_000_000 + i * STATE_PERIOD
        for topic, (typename, msg) in sample_messages(t).items():
            if topic in (f"/{NS}/odom", f"/{NS}/front/depth/image_raw"):
                bag.write(bag.channel(topic, typename), t, bytes(M.serialize(msg)))
    bag.close()
    ep = endpoint()
    got: dict[str, list[int]] = defaultdict(list)
    nodes: list[RosZenohNode] = []

    def subscribe(topic: str, typename: str) -> None:
        nodes[0].subscribe(topic, typename, lambda m: got[topic].append(stamp_of(m)))

    def on_ready(_node: RosZenohNode) -> None:  # the replay's publishers exist: a consumer arrives
        nodes.append(RosZenohNode(ZenohNodeConfig(mode="peer", listen=(), connect=(ep,))))
        subscribe(f"/{NS}/odom", "nav_msgs/msg/Odometry")
        threading.Timer(0.3, subscribe, (f"/{NS}/front/depth/image_raw", "sensor_msgs/msg/Image")).start()

    try:
        replay(path, ReplayConfig(listen=(ep,), rate=2.0, wait_subscriber_s=10.0), on_ready=on_ready)
        deadline = time.monotonic() + 5
        while min(len(got[f"/{NS}/odom"]), len(got[f"/{NS}/front/depth/image_raw"])) < 100:
            if time.monotonic() > deadline:
                break
            time.sleep(0.05)
    finally:
        for node in nodes:
            node.close()
    expected = [5_000_000_000 + i * STATE_PERIOD for i in range(100)]
    assert got[f"/{NS}/odom"] == expected
    assert got[f"/{NS}/front/depth/image_raw"] == expected


# --------------------------------------------------------------------------- droneulator run --record
TOPICS = {
    "clock": TYPES["clock"],
    "tf": TYPES["tf"],
    f"{NS}/odom": TYPES["odom"],
    f"{NS}/front/color/camera_info": TYPES["info_rgb"],
    f"{NS}/front/color/image_raw/compressed": TYPES["rgb"],
    f"{NS}/front/depth/image_raw": TYPES["depth"],
    f"{NS}/front/segmentation/image_raw/compressed": TYPES["seg"],
}


@pytest.mark.slow
def test_run_record_keeps_every_message_of_a_10s_lockstep_run(tmp_path: Path) -> None:
    """``run --record`` into a bag directory split every 3 s of sim time: 10 s of lockstep; per topic
    the bag's files, in order, hold exactly what an independent subscriber received in its window (same
    bytes, nothing lost at a split), stamps have no gap from the run's first /clock on, and SIGINT leaves
    finalised files."""
    cfg = load_config(scene="default")
    cfg.render.cameras = [CameraConfig(name="front", width=320, height=240)]
    cfg.render.shadow_map_size = 1024
    out = tmp_path / "run"
    seen: dict[str, list[bytes]] = defaultdict(list)
    lock = threading.Lock()

    def on(key: str):
        def cb(sample: zenoh.Sample) -> None:
            with lock:
                seen[key].append(sample.payload.to_bytes())

        return cb

    run = launch_run(cfg, ["--record", str(out), "--max-bag-duration", "3"])
    try:
        conf = zenoh.Config()
        conf.insert_json5("mode", '"peer"')
        conf.insert_json5("connect/endpoints", json.dumps([run.zenoh_endpoint]))
        conf.insert_json5("scouting/multicast/enabled", "false")
        session = zenoh.open(conf)
        subs = [session.declare_subscriber(k, on(k)) for k in TOPICS]
        with run.client(timeout=120) as c:  # the first frames compile shaders and kernels: seconds
            t_end = c.state()["t"] + 10.0
            deadline = time.monotonic() + 300
            while c.state()["t"] < t_end:
                assert time.monotonic() < deadline, run.log.tail()
                time.sleep(0.2)
        for s in subs:
            s.undeclare()  # the subscriber's window closes here; the run and the recorder go on
        session.close()
        time.sleep(0.5)
        run.proc.send_signal(signal.SIGINT)
        assert run.proc.wait(30) == 0, run.log.tail()
    finally:
        run.stop()
    log = "\n".join(run.log.lines())
    assert "recorded" in log and str(out) in log
    files = yaml.safe_load((out / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert len(files["relative_file_paths"]) >= 4, log
    got: dict[str, list[tuple[int, bytes, object]]] = defaultdict(list)
    for name in files["relative_file_paths"]:
        for topic, items in read_mcap(out / name)[1].items():
            got[topic] += items
    for key in TOPICS:
        topic = "/" + key
        raws = [raw for _t, raw, _m in got[topic]]
        window = seen[key]
        assert len(window) > 50, key
        start = raws.index(window[0])
        assert raws[start : start + len(window)] == window, f"{topic}: the bag differs from the subscriber"
    state = [t for t, _r, _m in got["/clock"]]
    assert state[0] <= STATE_PERIOD  # subscribed before the clock started: the run's first /clock is in
    assert np.all(np.diff(state) == STATE_PERIOD)
    assert [t for t, _r, _m in got[f"/{NS}/odom"]] == state
    camera = [t for t, _r, _m in got[f"/{NS}/front/depth/image_raw"]]
    assert camera[0] <= round(1e9 / 30) and np.all(np.diff(camera) == round(1e9 / 30))
    for key in ("front/color/image_raw/compressed", "front/segmentation/image_raw/compressed"):
        # every frame's images, but the SIGINT may fall between the last frame's images
        stamps = [t for t, _r, _m in got[f"/{NS}/{key}"]]
        n = min(len(stamps), len(camera))
        assert stamps[:n] == camera[:n] and abs(len(stamps) - len(camera)) <= 1
    assert state[-1] - state[0] >= 10e9
    with Reader(out) as rb:
        assert rb.message_count == sum(len(v) for v in got.values())
        assert "/tf_static" in {c.topic for c in rb.connections}
