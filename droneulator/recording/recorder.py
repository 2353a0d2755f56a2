"""Record every ROS 2 message the simulator publishes on Zenoh into an MCAP bag (:class:`BagWriter`).

A :class:`Recorder` is a Zenoh session (a client of the run's router by default) with wildcard
subscribers for the global topics (``/clock``, ``/tf``, ``/tf_static``) and everything under the
simulator's namespace (``/<ns>/**``), in either key convention of :mod:`droneulator.ros.zenoh_node`:

* ``ros2dds``: keys are ROS names without the leading ``/`` (behind the bridge-style prefix), so the
  type comes from the publishers' liveliness tokens (``@/<zid>/@ros2_lv/MP/<key>/<type>/<qos>``, the
  way zenoh-bridge-ros2dds discovers them) or, for a publisher that announces nothing, from the
  simulator's own topic table (:mod:`droneulator.ros.topics`). A sample whose type is not known yet
  waits (on the writer thread) for its token.
* ``rmw_zenoh``: the key names the type itself (``<domain>/<topic>/<pkg>::msg::dds_::<Type>_/<hash>``);
  the attachment's sequence number becomes the MCAP message sequence.

The Zenoh callback only copies the sample into a queue; a writer thread turns it into a bag message
(log time = the sample's own stamp: the header stamp, ``/clock``'s value or the first transform's;
messages without one get the latest stamp seen), compresses and writes the chunks. The queue is bounded
(``max_queue_bytes``): when the writer falls behind, the callback blocks, which holds Zenoh's receive
path and, with the simulator's ``BLOCK`` publishers in lockstep, slows the simulation clock instead of
losing a message. :meth:`Recorder.close` drains the queue and finalises the file.
"""

from __future__ import annotations

import collections
import logging
import re
import struct
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh

from droneulator.recording.bag import BagWriter, Compression, read_stamp, stamp_reader
from droneulator.ros import messages
from droneulator.ros.topics import TYPES, spray_deposit_topic, spray_state_topic, topic_names, vehicle_topics
from droneulator.ros.zenoh_node import KeyMode, QosProfile, RosZenohNode, ZenohNodeConfig, default_qos

__all__ = ["Recorder", "RecorderConfig", "RecordingStats", "run_recorder_config", "topic_of_key"]

log = logging.getLogger("droneulator.recording")

_RMW_TYPE = re.compile(r"^([A-Za-z_][A-Za-z0-9_]*)::(msg|srv|action)::dds_::([A-Za-z_][A-Za-z0-9_]*)_$")
_RMW_ATTACHMENT = struct.Struct("<q")
_STOP = object()
_RESOLVED = object()


@dataclass(frozen=True)
class RecorderConfig:
    """What to record and where it comes from.

    ``connect``: the Zenoh endpoints of the simulator's session (``bridge.listen`` of the run, or the
    router both use). ``namespace`` is the simulator's ROS namespace (``bridge.namespace``); ``key_mode``,
    ``domain_id`` and ``ros2dds_namespace`` must match the run's ``bridge`` settings.
    """

    connect: tuple[str, ...] = ("tcp/127.0.0.1:7448",)
    namespace: str = "droneulator"
    key_mode: KeyMode = "ros2dds"
    domain_id: int = 0
    ros2dds_namespace: str = "/"
    #: "client" of the run's router (fails at once if it is not there), or "peer"
    mode: str = "client"
    zenoh_config: str | None = None
    compression: Compression = "zstd"
    #: samples queued for the writer before the Zenoh callback blocks (back-pressure, no loss)
    max_queue_bytes: int = 512 * 1024 * 1024
    #: split a bag directory into files of this many bytes / seconds of sim time (0: one file), as
    #: ``ros2 bag record --max-bag-size / --max-bag-duration``; an hour's recording should split
    max_bag_bytes: int = 0
    max_bag_duration_s: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "connect", tuple(self.connect))
        vehicle_topics(self.namespace)  # validates the namespace
        if self.mode not in ("client", "peer"):
            raise ValueError(f"recorder mode must be 'client' or 'peer', got {self.mode!r}")
        if self.max_queue_bytes < 16 * 1024 * 1024:
            raise ValueError("max_queue_bytes must be at least 16 MiB (one depth image is 1.2 MB)")
        if self.max_bag_bytes < 0 or not self.max_bag_duration_s >= 0:
            raise ValueError("max_bag_bytes and max_bag_duration_s must be >= 0 (0: no split)")


@dataclass
class RecordingStats:
    """What a recording received and wrote (per topic), and what it could not type."""

    written: dict[str, int] = field(default_factory=dict)
    untyped: dict[str, int] = field(default_factory=dict)
    path: Path | None = None
    bytes: int = 0
    #: the MCAP files written, in order (more than one when the bag split)
    files: list[Path] = field(default_factory=list)


def _rmw_type(dds_name: str) -> str | None:
    m = _RMW_TYPE.match(dds_name)
    return f"{m.group(1)}/{m.group(2)}/{m.group(3)}" if m else None


def topic_of_key(key: str, cfg: RecorderConfig) -> tuple[str, str | None] | None:
    """``(ROS topic, type or None)`` a Zenoh key stands for under ``cfg``'s key convention, None if the
    key is not a ROS topic of that convention (``rmw_zenoh`` keys carry the type, ``ros2dds`` ones not)."""
    parts = key.split("/")
    if cfg.key_mode == "rmw_zenoh":
        if len(parts) < 4 or parts[0] != str(cfg.domain_id):
            return None
        typename = _rmw_type(parts[-2])
        return ("/" + "/".join(parts[1:-2]), typename) if typename else None
    prefix = cfg.ros2dds_namespace.strip("/")
    if prefix:
        if not key.startswith(prefix + "/"):
            return None
        key = key[len(prefix) + 1 :]
    return "/" + key, None


def _known_types(namespace: str) -> tuple[dict[str, str], dict[str, str]]:
    """The simulator's topics: exact names (vehicle and global topics) and per-camera name suffixes."""
    exact = {name: TYPES[k] for k, name in vehicle_topics(namespace).items()}
    exact[spray_state_topic(namespace)] = TYPES["spray"]
    exact[spray_deposit_topic(namespace)] = TYPES["spray_deposit"]
    marker = "CAMERA"
    suffixes = {
        name.split(f"/{marker}/", 1)[1]: TYPES[k] for k, name in topic_names(namespace, marker).items()
    }
    return exact, suffixes


def _parse_ros2dds_token(key: str) -> tuple[str, str, QosProfile] | None:
    """``(zenoh key, ROS type, QoS)`` of a zenoh-bridge-ros2dds style publisher token, None otherwise."""
    parts = key.split("/")
    try:
        i = parts.index("MP")
    except ValueError:
        return None
    if i < 2 or parts[i - 1] != "@ros2_lv" or len(parts) != i + 4:
        return None
    data_key, typename = parts[i + 1].replace("§", "/"), parts[i + 2].replace("§", "/")
    m = re.match(r"^[^:]*:(\d+):(\d+):(\d+),(\d+)", parts[i + 3])
    qos = (
        QosProfile(
            reliable=m.group(1) == "1",
            transient_local=m.group(2) == "1",
            keep_all=m.group(3) == "1",
            depth=int(m.group(4)),
        )
        if m
        else QosProfile()
    )
    return data_key, typename, qos


class Recorder:
    """Subscribes, queues and writes; use :meth:`start` then :meth:`close` (or as a context manager)."""

    def __init__(self, path: str | Path, cfg: RecorderConfig | None = None) -> None:
        self.cfg = cfg or RecorderConfig()
        self.path = Path(path)
        self._bag: BagWriter | None = None
        self._node: RosZenohNode | None = None
        self._subs: list[Any] = []
        self._queue: collections.deque[Any] = collections.deque()
        self._queued_bytes = 0
        self._cond = threading.Condition()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        #: ros2dds: zenoh key -> (type, QoS) announced by liveliness tokens
        self._announced: dict[str, tuple[str, QosProfile]] = {}
        self._exact, self._suffixes = _known_types(self.cfg.namespace)
        self._pending: dict[str, list[tuple[bytes, int]]] = collections.defaultdict(list)
        self._resolved: dict[str, tuple[int, int | None]] = {}  # key -> (channel id, stamp offset)
        self._seq: dict[str, int] = collections.defaultdict(int)
        self._latest_ns = 0
        self.error: BaseException | None = None
        #: samples taken from Zenoh so far (written, queued or waiting for their type)
        self.received = 0
        #: times a Zenoh callback waited for the writer (the queue was full): back-pressure, not loss
        self.waits = 0
        self.stats = RecordingStats(path=self.path)

    # ------------------------------------------------------------------ keys
    def key_expressions(self) -> list[str]:
        """The wildcard key expressions subscribed: the global topics and everything under the namespace."""
        ns = self.cfg.namespace
        if self.cfg.key_mode == "rmw_zenoh":
            d = self.cfg.domain_id
            return [f"{d}/clock/*/*", f"{d}/tf/*/*", f"{d}/tf_static/*/*", f"{d}/{ns}/**"]
        prefix = self.cfg.ros2dds_namespace.strip("/")
        pre = f"{prefix}/" if prefix else ""
        return [f"{pre}clock", f"{pre}tf", f"{pre}tf_static", f"{pre}{ns}/**"]

    def _type_of(self, key: str) -> tuple[str, str, QosProfile] | None:
        """(topic, type, QoS) of a data key, None while the type is not known."""
        found = topic_of_key(key, self.cfg)
        if found is None:
            return None
        topic, typename = found
        if typename is None:
            with self._lock:
                announced = self._announced.get(key)
            if announced is not None:
                return topic, announced[0], announced[1]
            typename = self._exact.get(topic)
            if typename is None:
                rest = topic[len(self.cfg.namespace) + 2 :].split("/", 1)
                if topic.startswith(f"/{self.cfg.namespace}/") and len(rest) == 2:
                    typename = self._suffixes.get(rest[1])
            if typename is None:
                return None
        return topic, typename, default_qos(topic)

    # ------------------------------------------------------------------ lifetime
    @property
    def started(self) -> bool:
        return self._thread is not None

    def start(self) -> None:
        """Open the bag and the Zenoh session and subscribe; returns once the subscriptions are declared
        and a liveliness query has made a round trip through the router (so they are in place there)."""
        if self._thread is not None:
            raise RuntimeError("recorder already started")
        cfg = self.cfg
        self._bag = BagWriter(
            self.path, cfg.compression, max_bytes=cfg.max_bag_bytes, max_duration_s=cfg.max_bag_duration_s
        )
        try:
            self._node = RosZenohNode(
                ZenohNodeConfig(
                    mode=cfg.mode,  # type: ignore[arg-type]
                    listen=(),
                    connect=cfg.connect,
                    config_file=cfg.zenoh_config,
                    key_mode=cfg.key_mode,
                    domain_id=cfg.domain_id,
                    namespace=cfg.ros2dds_namespace,
                    announce=False,
                    node_name="droneulator_recorder",
                )
            )
            session = self._node.session
            self._thread = threading.Thread(target=self._write_loop, name="mcap-writer", daemon=True)
            self._thread.start()
            if cfg.key_mode == "ros2dds":
                self._subs.append(
                    session.liveliness().declare_subscriber("@/*/@ros2_lv/MP/**", self._on_token)
                )
            for expr in self.key_expressions():
                self._subs.append(session.declare_subscriber(expr, self._on_sample))
            barrier = "@/*/@ros2_lv/MP/**" if cfg.key_mode == "ros2dds" else "@ros2_lv/**"
            for reply in session.liveliness().get(barrier, timeout=5.0):
                if reply.ok is not None:
                    self._on_token(reply.ok)
        except BaseException:
            self._abort()
            raise
        log.info("recording %s to %s", ", ".join(self.key_expressions()), self.path)

    def _abort(self) -> None:
        for sub in self._subs:
            sub.undeclare()
        self._subs.clear()
        if self._node is not None:
            self._node.close()
        if self._thread is not None:
            self._put(_STOP, 0)
            self._thread.join()
        if self._bag is not None:
            self._bag.close()

    def close(self) -> RecordingStats:
        """Unsubscribe, write what is queued, finalise the file; returns the statistics. Idempotent."""
        if self._thread is None or self._bag is None:
            raise RuntimeError("recorder was not started")
        if self._bag.closed:
            return self.stats
        for sub in self._subs:
            sub.undeclare()
        self._subs.clear()
        if self._node is not None:
            self._node.close()
        self._put(_STOP, 0)
        self._thread.join()
        for key, items in self._pending.items():
            topic = (topic_of_key(key, self.cfg) or (key, None))[0]
            self.stats.untyped[topic] = self.stats.untyped.get(topic, 0) + len(items)
            log.warning("%d samples on %s not recorded: no publisher announced their type", len(items), key)
        self._bag.close()
        self.stats.written = self._bag.counts()
        self.stats.files = self._bag.files
        self.stats.bytes = sum(f.stat().st_size for f in self.stats.files)
        if self.error is not None:
            raise RuntimeError(f"the recording writer failed: {self.error}") from self.error
        return self.stats

    def __enter__(self) -> Recorder:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ zenoh callbacks (zenoh threads)
    def _put(self, item: Any, size: int) -> None:
        with self._cond:
            if self._queued_bytes > self.cfg.max_queue_bytes and self._queue and self.error is None:
                self.waits += 1
            while self._queued_bytes > self.cfg.max_queue_bytes and self._queue and self.error is None:
                self._cond.wait(0.5)
            self._queue.append(item)
            self._queued_bytes += size
            if item is not _STOP and item[0] is not _RESOLVED:
                self.received += 1
            self._cond.notify_all()

    def _on_sample(self, sample: zenoh.Sample) -> None:
        if sample.kind != zenoh.SampleKind.PUT:
            return
        payload = sample.payload.to_bytes()
        seq = 0
        if sample.attachment is not None and self.cfg.key_mode == "rmw_zenoh":
            raw = sample.attachment.to_bytes()
            if len(raw) >= _RMW_ATTACHMENT.size:
                seq = _RMW_ATTACHMENT.unpack_from(raw)[0]
        self._put((str(sample.key_expr), payload, seq), len(payload))

    def _on_token(self, sample: zenoh.Sample) -> None:
        if sample.kind != zenoh.SampleKind.PUT:
            return
        parsed = _parse_ros2dds_token(str(sample.key_expr))
        if parsed is None:
            return
        key, typename, qos = parsed
        try:
            messages.TYPESTORE.get_msgdef(typename)
        except KeyError:
            log.warning("%s is announced with type %s, which the typestore does not know", key, typename)
            return
        with self._lock:
            new = key not in self._announced
            self._announced[key] = (typename, qos)
        if new:
            self._put((_RESOLVED, key), 0)

    # ------------------------------------------------------------------ writer thread
    def _write_loop(self) -> None:
        while True:
            with self._cond:
                while not self._queue:
                    self._cond.wait()
                item = self._queue.popleft()
                if item is not _STOP and item[0] is not _RESOLVED:
                    self._queued_bytes -= len(item[1])
                self._cond.notify_all()
            if item is _STOP:
                return
            if self.error is not None:
                continue  # keep draining so no callback stays blocked
            try:
                if item[0] is _RESOLVED:
                    for payload, seq in self._pending.pop(item[1], []):
                        self._write(item[1], payload, seq)
                else:
                    self._write(*item)
            except Exception as exc:  # a full disk, say: stop writing, report at close
                self.error = exc
                log.exception("writing %s failed; the recording stops here", self.path)

    def _write(self, key: str, payload: bytes, seq: int) -> None:
        assert self._bag is not None
        resolved = self._resolved.get(key)
        if resolved is None:
            found = self._type_of(key)
            if found is None:
                self._pending[key].append((payload, seq))
                return
            topic, typename, qos = found
            resolved = (self._bag.channel(topic, typename, qos), stamp_reader(typename))
            self._resolved[key] = resolved
            if key in self._pending:  # typed by the name table after all: older samples first
                for old_payload, old_seq in self._pending.pop(key):
                    self._write(key, old_payload, old_seq)
        channel, offset = resolved
        stamp = read_stamp(payload, offset)
        if stamp is None:
            stamp = self._latest_ns
        else:
            self._latest_ns = max(self._latest_ns, stamp)
        if not seq:
            self._seq[key] += 1
            seq = self._seq[key]
        self._bag.write(channel, stamp, payload, seq)


def run_recorder_config(
    bridge: Any,
    hub_endpoint: str | None,
    compression: Compression = "zstd",
    max_bag_bytes: int = 0,
    max_bag_duration_s: float = 0.0,
) -> RecorderConfig:
    """The recorder of a ``droneulator run`` with these ``bridge`` settings (a ``BridgeConfig``): a
    client of the run's private Zenoh endpoint (the one its bridge process uses), or of the user's
    router when ``bridge.mode`` is ``client``."""
    external = bridge.mode == "client" or not hub_endpoint
    return RecorderConfig(
        connect=tuple(bridge.connect) if external else (hub_endpoint,),
        namespace=bridge.namespace,
        key_mode=bridge.key_mode,
        domain_id=bridge.domain_id,
        ros2dds_namespace=bridge.ros2dds_namespace,
        zenoh_config=(bridge.zenoh_config or None) if external else None,
        compression=compression,
        max_bag_bytes=max_bag_bytes,
        max_bag_duration_s=max_bag_duration_s,
    )
