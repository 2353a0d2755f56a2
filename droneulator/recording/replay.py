"""Republish a recorded bag on Zenoh at the recorded rate, under the keys the simulator used.

``droneulator replay out.mcap`` opens a Zenoh session in the simulator's place (a router listening on
``tcp/127.0.0.1:7448`` by default, the same key convention options as ``bridge``), declares one
publisher per recorded topic with the QoS the bag records (``/tf_static`` stays transient local), and
puts every message's CDR bytes unchanged in log-time order, paced so that sim time advances ``rate``
times as fast as the wall clock. A planner or perception node connected there sees the flight exactly
as it was published, stamps included, without the simulator. Publishers use ``BLOCK``: a slow
subscriber delays the replay instead of losing messages.

Types the Jazzy typestore does not know (a bag from elsewhere) are registered from the bag's own
``ros2msg`` schemas.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zenoh
from mcap.reader import make_reader
from rosbags.interfaces import QosDurability, QosHistory, QosReliability
from rosbags.rosbag2.metadata import parse_qos
from rosbags.typesys import get_types_from_msg
from ruamel.yaml import YAML

from droneulator.ros import messages
from droneulator.ros.zenoh_node import KeyMode, QosProfile, RosPublisher, RosZenohNode, ZenohNodeConfig

__all__ = ["ReplayConfig", "bag_files", "replay"]

log = logging.getLogger("droneulator.replay")


@dataclass(frozen=True)
class ReplayConfig:
    """Where and how to republish (the Zenoh options mirror ``bridge``'s)."""

    listen: tuple[str, ...] = ("tcp/127.0.0.1:7448",)
    connect: tuple[str, ...] = ()
    mode: str = "router"
    key_mode: KeyMode = "ros2dds"
    domain_id: int = 0
    ros2dds_namespace: str = "/"
    zenoh_config: str | None = None
    #: sim seconds per wall second
    rate: float = 1.0
    #: wait up to this many seconds for a subscriber to match before the first message (0: start at once)
    wait_subscriber_s: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "listen", tuple(self.listen))
        object.__setattr__(self, "connect", tuple(self.connect))
        if not self.rate > 0:
            raise ValueError(f"replay rate must be positive, got {self.rate}")
        if self.wait_subscriber_s < 0:
            raise ValueError("wait_subscriber_s must be >= 0")


def bag_files(path: str | Path) -> list[Path]:
    """The MCAP files of ``path`` in order: the file itself, or a bag directory's files (as its
    ``metadata.yaml`` lists them, else by their ``_N`` index: a bag that split holds several)."""
    path = Path(path)
    if path.is_dir():
        meta = path / "metadata.yaml"
        if meta.exists():
            info = YAML(typ="safe").load(meta.read_text()).get("rosbag2_bagfile_information", {})
            names = info.get("relative_file_paths") or []
            files = [path / n for n in names if n.endswith(".mcap")]
            missing = [f.name for f in files if not f.exists()]
            if missing:
                raise FileNotFoundError(
                    f"bag directory {path} lacks {', '.join(missing)} (metadata.yaml lists them)"
                )
        else:
            files = sorted(path.glob("*.mcap"), key=lambda f: (len(f.stem), f.stem))
        if not files:
            raise ValueError(f"bag directory {path} holds no .mcap file")
        return files
    if not path.exists():
        raise FileNotFoundError(f"no bag at {path}")
    if path.suffix != ".mcap":
        raise ValueError(f"{path} is not an .mcap file or a bag directory")
    return [path]


def _ensure_type(name: str, encoding: str, data: bytes) -> None:
    """Register ``name`` from its ``ros2msg`` schema if the typestore does not know it yet."""
    try:
        messages.TYPESTORE.get_msgdef(name)
        return
    except KeyError:
        pass
    if encoding != "ros2msg":
        raise ValueError(f"type {name} has a {encoding!r} schema; only ros2msg can be registered")
    messages.TYPESTORE.register(get_types_from_msg(data.decode(), name))


def _qos(metadata: dict[str, str]) -> QosProfile | None:
    profiles = parse_qos(metadata.get("offered_qos_profiles", ""))
    if not profiles:
        return None
    q = profiles[0]
    return QosProfile(
        reliable=q.reliability != QosReliability.BEST_EFFORT,
        transient_local=q.durability == QosDurability.TRANSIENT_LOCAL,
        keep_all=q.history == QosHistory.KEEP_ALL,
        depth=max(0, int(q.depth)),
    )


def _wait_matching(publishers: list[RosPublisher], timeout: float, settle: float = 0.5) -> bool:
    """Wait up to ``timeout`` s for a subscriber to match any publisher, then until no further publisher
    has matched for ``settle`` s: a subscriber's topics match one after the other as its declarations
    arrive, and replaying at the first would lose the others' first messages. False if none matched."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if any(p.matching for p in publishers):
            break
        time.sleep(0.02)
    else:
        return False
    matched, quiet_since = sum(p.matching for p in publishers), time.monotonic()
    while time.monotonic() - quiet_since < settle and time.monotonic() < deadline:
        time.sleep(0.02)
        now = sum(p.matching for p in publishers)
        if now != matched:
            matched, quiet_since = now, time.monotonic()
    return True


def replay(
    path: str | Path,
    cfg: ReplayConfig | None = None,
    stop: threading.Event | None = None,
    on_ready: Callable[[RosZenohNode], None] | None = None,
) -> dict[str, int]:
    """Republish the bag at ``path``; returns the messages published per topic.

    ``stop`` ends it early (Ctrl-C); ``on_ready(node)`` runs once every publisher is declared.
    """
    cfg = cfg or ReplayConfig()
    stop = stop or threading.Event()
    counts: dict[str, int] = {}
    with contextlib.ExitStack() as files:
        readers = []
        for file in bag_files(path):
            reader = make_reader(files.enter_context(open(file, "rb")))
            summary = reader.get_summary()
            if summary is None:
                raise ValueError(f"{file} has no summary (not finalised?): run `mcap recover` on it first")
            header = reader.get_header()
            if header.profile != "ros2":
                raise ValueError(f"{file} has MCAP profile {header.profile!r}, not a ROS 2 bag ('ros2')")
            readers.append((reader, summary))
        node = RosZenohNode(
            ZenohNodeConfig(
                mode=cfg.mode,  # type: ignore[arg-type]
                listen=cfg.listen,
                connect=cfg.connect or None,
                config_file=cfg.zenoh_config,
                key_mode=cfg.key_mode,
                domain_id=cfg.domain_id,
                namespace=cfg.ros2dds_namespace,
                node_name="droneulator_replay",
            )
        )
        try:
            by_topic: dict[tuple[str, str], RosPublisher] = {}
            per_file: list[dict[int, RosPublisher]] = []
            for _reader, summary in readers:
                pubs: dict[int, RosPublisher] = {}
                for cid, ch in summary.channels.items():
                    if ch.message_encoding != "cdr":
                        log.warning(
                            "skipping %s: message encoding %r is not cdr", ch.topic, ch.message_encoding
                        )
                        continue
                    schema = summary.schemas[ch.schema_id]
                    key = (ch.topic, schema.name)
                    if key not in by_topic:
                        _ensure_type(schema.name, schema.encoding, schema.data)
                        by_topic[key] = node.publisher(
                            ch.topic,
                            schema.name,
                            qos=_qos(ch.metadata),
                            congestion_control=zenoh.CongestionControl.BLOCK,
                        )
                        counts.setdefault(ch.topic, 0)
                    pubs[cid] = by_topic[key]
                per_file.append(pubs)
            if on_ready is not None:
                on_ready(node)
            if cfg.wait_subscriber_s and not _wait_matching(list(by_topic.values()), cfg.wait_subscriber_s):
                log.warning("no subscriber matched within %.1f s; replaying anyway", cfg.wait_subscriber_s)
            items = (
                m
                for (reader, _), pubs in zip(readers, per_file, strict=True)
                for m in _messages(reader, pubs)
            )
            _publish(items, cfg.rate, stop, counts)
        finally:
            node.close()
    return counts


def _messages(reader: Any, pubs: dict[int, RosPublisher]) -> Iterator[tuple[RosPublisher, int, bytes]]:
    for _schema, channel, message in reader.iter_messages(log_time_order=True):
        pub = pubs.get(channel.id)
        if pub is not None:
            yield pub, message.log_time, message.data


def _publish(
    items: Iterator[tuple[RosPublisher, int, bytes]],
    rate: float,
    stop: threading.Event,
    counts: dict[str, int],
) -> None:
    t0_log: int | None = None
    wall0 = time.monotonic()
    for pub, log_ns, data in items:
        if t0_log is None:
            t0_log, wall0 = log_ns, time.monotonic()
        ahead = (log_ns - t0_log) / 1e9 / rate - (time.monotonic() - wall0)
        if ahead > 0 and stop.wait(ahead):
            return
        if stop.is_set():
            return
        pub.publish(data, log_ns)
        counts[pub.topic] += 1
