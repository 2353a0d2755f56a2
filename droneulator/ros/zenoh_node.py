"""A minimal ROS 2 node on a plain Zenoh session: publish CDR samples, subscribe to decoded messages.

Two wire conventions, chosen with ``key_mode``:

``"ros2dds"`` (default): what zenoh-bridge-ros2dds / zenoh-plugin-ros2dds routes.
    Key = ROS name without its leading ``/``, prefixed by the bridge-style ``namespace`` if set
    (``ros2_utils.rs::ros2_name_to_key_expr``): topic ``/a/b`` -> ``a/b`` (``ns/a/b`` with
    ``namespace="/ns"``). A bridge started with ``-n /ns`` routes exactly those keys: it strips its
    namespace from an announced key to name the DDS topic (``key_expr_to_ros2_name``: ``ns/a/b`` ->
    ``/a/b``) and listens on ``<ns>/<topic>``. Payload = the full CDR sample, encapsulation header
    included. No attachment.
    The bridge forwards a key to DDS once it has a route for it: either a local DDS reader of that
    topic, or a remote announcement. With ``announce=True`` this node announces its publishers and
    subscribers exactly like a remote bridge does (``liveliness_mgt.rs``)::

        @/<zid>/@ros2_lv/MP/<key with / -> §>/<ROS type with / -> §>/<qos>     (publisher)
        @/<zid>/@ros2_lv/MS/<key with / -> §>/<ROS type with / -> §>/<qos>     (subscriber)
        <qos> = "<keyless ''>:<reliability>:<durability>:<history>,<depth>:typehash=RIHS01_<hex>;"

    with DDS enum values (reliability BEST_EFFORT 0 / RELIABLE 1, durability VOLATILE 0 /
    TRANSIENT_LOCAL 1, history KEEP_LAST 0 / KEEP_ALL 1), so the bridge creates the DDS writer
    (``routes_mgr.rs::on_ros_announcement_event``) and ``ros2 topic list`` shows the topic at once.
    ``<key>`` is the routed key, namespace prefix included (``ns§a§b``).

``"rmw_zenoh"``: what ``rmw_zenoh_cpp`` itself speaks (Jazzy 0.2.4+, Kilted; docs/ros2.md).
    Key = ``<domain_id>/<topic without leading and trailing />/<pkg>::msg::dds_::<Name>_/RIHS01_<hex>``
    (``liveliness_utils.cpp::TopicInfo``; type name from ``type_support_common.cpp::_create_type_name``;
    hash from ``rosidl_stringify_type_hash``). Every sample carries the attachment of
    ``attachment_helpers.cpp::AttachmentData::serialize_to_zbytes``: zenoh-ext serialisation of
    ``int64 sequence_number`` (from 1, +1 per publish, ``rmw_publisher_data.cpp``), ``int64
    source_timestamp`` (ns) and ``std::array<uint8_t, 16> source_gid``, i.e. 33 bytes::

        <q sequence_number> <q source_timestamp> 0x10 <16 gid bytes>      (little endian, 0x10 = LEB128 16)

    rmw_zenoh subscriptions drop samples without it. The node and every entity declare liveliness
    tokens (``liveliness_utils.cpp::Entity``) so ``ros2 topic list`` / ``ros2 node list`` see them::

        @ros2_lv/<domain>/<zid>/<nid>/<nid>/NN/<enclave>/<namespace>/<node>
        @ros2_lv/<domain>/<zid>/<nid>/<id>/MP|MS/<enclave>/<namespace>/<node>/<topic>/<type>/<hash>/<qos>

    names mangled by ``mangle_name`` (every ``/`` -> ``%``; the default enclave and namespace ``/``
    become ``%``), ids decimal from one per-session counter (node 0, entities 1, 2, ...), and
    ``<qos>`` from ``qos_to_keyexpr`` relative to rmw_zenoh's defaults (``qos.cpp``: RELIABLE,
    VOLATILE, KEEP_LAST 42, infinite durations), e.g. reliable/volatile/keep-last 10 -> ``::,10:,:,:,,``.
    Every entity's gid is the XXH3-128 hash of its token, low 64 bits then high 64 bits, each little
    endian (``liveliness_utils.cpp::Entity::Entity``), so ``ros2 topic info -v`` and
    ``message_info.publisher_gid`` show the same 16 bytes. rmw_zenoh peers discover each other
    through the ``rmw_zenohd`` router, which does not forward between peers: without explicit
    ``connect`` endpoints this node connects to it on ``tcp/127.0.0.1:7447`` like an rmw_zenoh node.

Session defaults: peer mode, listening on ``tcp/127.0.0.1:7448`` and multicast scouting off, so a run
never attaches to whatever else happens to be on the LAN and tests are deterministic; peers find the node
through explicit ``connect``/``listen`` endpoints (gossip through a router still works). Connect endpoints
that are not up yet never block or fail the open in peer and router mode: zenoh retries them in the
background (``connect/timeout_ms`` -1 with ``exit_on_failure`` false, set explicitly); a client has
nothing to do without its router, so it tries once and the open fails with a clear error. Zenoh's shared
memory transport optimisation (samples above 3 KiB to a process on the same host through the
publisher's 16 MiB ``/dev/shm`` pool instead of the socket) is off unless ``shared_memory`` (the
``bridge.shared_memory`` setting): it moves camera images between local processes about six times
faster, but every local subscriber keeps a crashed publisher's pool mapped for good, so each restart
of the bridge after a crash left 20 to 40 MB more resident in every process of a run
(docs/reliability.md).
"""

from __future__ import annotations

import functools
import itertools
import json
import logging
import re
import struct
import threading
import time
import weakref
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal, Protocol

import xxhash
import zenoh
import zenoh.ext

from droneulator.logs import LogThrottle
from droneulator.ros import messages

__all__ = [
    "STATIC_TF_QOS",
    "KeyMode",
    "QosProfile",
    "RosPublisher",
    "RosSubscription",
    "RosZenohNode",
    "RMW_ZENOH_ROUTER",
    "ZenohNodeConfig",
    "default_qos",
    "rmw_gid",
]

log = logging.getLogger("droneulator.ros")
#: undecodable samples: the first of a burst logged, the rest counted (a peer can send thousands a second)
_bad_samples = LogThrottle(log, gap=2.0, period=10.0)

KeyMode = Literal["ros2dds", "rmw_zenoh"]
ZenohMode = Literal["peer", "client", "router"]

#: where rmw_zenoh nodes find ``rmw_zenohd`` (``DEFAULT_RMW_ZENOH_SESSION_CONFIG.json5``: tcp/localhost:7447)
RMW_ZENOH_ROUTER = "tcp/127.0.0.1:7447"

#: zenoh's connect semantics per mode, set explicitly (``orchestrator.rs::connect_peers``): peers and
#: routers retry unreachable endpoints in the background forever, a client tries once and fails the open
_CONNECT_TIMEOUT_MS = {"router": -1, "peer": -1, "client": 0}
_CONNECT_EXIT_ON_FAILURE = {"router": False, "peer": False, "client": True}

#: zenoh-ext serialisation of (int64, int64, std::array<uint8_t, 16>); the length 16 is one LEB128 byte
_ATTACHMENT = struct.Struct("<qqB16s")
_GID_SIZE = 16

#: types that carry camera frames: never block the simulation for them, drop instead
_BULK_TYPES = frozenset(
    {"sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage", "sensor_msgs/msg/PointCloud2"}
)

_NAME_TOKEN = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


@dataclass(frozen=True)
class QosProfile:
    """The ROS QoS announced for an entity (liveliness tokens) and mapped onto Zenoh.

    Zenoh itself delivers to any matching subscriber whatever the QoS; this is what ROS tools and the
    DDS side of a bridge see. RELIABLE is the default because a reliable writer matches both reliable
    and best-effort readers in DDS.
    """

    reliable: bool = True
    transient_local: bool = False
    keep_all: bool = False
    depth: int = 10

    def __post_init__(self) -> None:
        if self.depth < 0:
            raise ValueError("QoS depth must be >= 0")


#: tf2_ros ``StaticBroadcasterQoS``: reliable, transient local, depth 1
STATIC_TF_QOS = QosProfile(transient_local=True, depth=1)


def default_qos(topic: str) -> QosProfile:
    """ROS defaults: ``/tf_static`` like tf2_ros' static broadcaster, everything else reliable/volatile/10.

    ``/tf_static`` must be offered TRANSIENT_LOCAL: tf2 listens to it with TRANSIENT_LOCAL, which a
    VOLATILE DDS writer (what a bridge would create from a volatile announcement) cannot match.
    """
    return STATIC_TF_QOS if topic == "/tf_static" else QosProfile()


#: rmw_zenoh's defaults (``qos.cpp``): fields equal to these are left empty in the liveliness QoS string
_RMW_ZENOH_DEFAULT_DEPTH = 42


def rmw_zenoh_qos(qos: QosProfile) -> str:
    """``liveliness_utils.cpp::qos_to_keyexpr``: rmw enum values, empty where equal to rmw_zenoh's default.

    Layout ``<rel>:<dur>:<hist>,<depth>:<deadline s>,<ns>:<lifespan s>,<ns>:<liveliness>,<lease s>,<ns>``
    with rmw enums RELIABLE 1 / BEST_EFFORT 2, TRANSIENT_LOCAL 1 / VOLATILE 2, KEEP_LAST 1 / KEEP_ALL 2;
    deadline, lifespan and liveliness stay at their defaults (infinite, AUTOMATIC) here.
    """
    reliability = "" if qos.reliable else "2"
    durability = "1" if qos.transient_local else ""
    history = "2" if qos.keep_all else ""
    depth = "" if qos.depth == _RMW_ZENOH_DEFAULT_DEPTH else str(qos.depth)
    return f"{reliability}:{durability}:{history},{depth}:,:,:,,"


def ros2dds_qos(qos: QosProfile, type_hash: str) -> str:
    """``liveliness_mgt.rs::qos_to_key_expr`` for a keyless ROS topic, USER_DATA carrying the type hash."""
    reliability = "1" if qos.reliable else "0"
    durability = "1" if qos.transient_local else "0"
    history = "1" if qos.keep_all else "0"
    return f":{reliability}:{durability}:{history},{qos.depth}:typehash={type_hash};"


def rmw_gid(token_key: str) -> bytes:
    """rmw_zenoh's 16-byte gid of an entity: XXH3-128 of its liveliness token, ``low64`` then ``high64``.

    ``liveliness_utils.cpp::Entity::Entity`` memcpy's both 64-bit halves in host order; every ROS 2 tier-1
    platform is little endian, so the bytes are the 128-bit hash as a little-endian integer.
    """
    return xxhash.xxh3_128_intdigest(token_key.encode()).to_bytes(_GID_SIZE, "little")


def mangle(name: str) -> str:
    """``liveliness_utils.cpp::mangle_name``: every ``/`` becomes ``%``."""
    return name.replace("/", "%")


def dds_type_name(typename: str) -> str:
    """``pkg/msg/Name`` -> ``pkg::msg::dds_::Name_`` (``type_support_common.cpp::_create_type_name``)."""
    parts = typename.split("/")
    if len(parts) != 3 or not all(parts):
        raise ValueError(f"ROS type must be 'pkg/msg/Name', got {typename!r}")
    pkg, kind, name = parts
    return f"{pkg}::{kind}::dds_::{name}_"


def fully_qualified(name: str, node_namespace: str = "/") -> str:
    """A ROS topic name made absolute: relative names resolve against ``node_namespace``.

    Rejects what ROS topic names cannot contain (empty tokens, ``~`` substitution, Zenoh wildcards).
    """
    if not name or name.endswith("/"):
        raise ValueError(f"invalid ROS topic name {name!r}")
    if not name.startswith("/"):
        name = node_namespace.rstrip("/") + "/" + name
    tokens = name[1:].split("/")
    if not all(_NAME_TOKEN.match(t) for t in tokens):
        raise ValueError(f"invalid ROS topic name {name!r}: tokens must match [A-Za-z_][A-Za-z0-9_]*")
    return name


class _BridgeConfigLike(Protocol):
    mode: str
    key_mode: str
    domain_id: int
    listen: list[str]
    connect: list[str]
    zenoh_config: str
    ros2dds_namespace: str
    tls_ca: str
    tls_cert: str
    tls_key: str
    tls_mtls: bool
    shared_memory: bool


def tls_entries(ca: str = "", cert: str = "", key: str = "", mtls: bool = False) -> dict[str, Any]:
    """Zenoh's ``transport/link/tls`` settings (paths to PEM files) for ``tls/HOST:PORT`` links.

    ``ca`` verifies the other side (a listener's certificate when connecting; with ``mtls`` a
    connecting peer's too). ``cert``/``key`` serve a ``tls/`` listener and, with ``mtls``, are presented
    when connecting (Zenoh sends a client certificate only with ``enable_mtls``), so one node listens
    and connects with one identity.
    Only the given entries are returned: Zenoh's defaults stay for the rest.
    """
    entries: dict[str, Any] = {}
    if ca:
        entries["root_ca_certificate"] = ca
    if cert:
        entries |= {
            "listen_certificate": cert,
            "listen_private_key": key,
            "connect_certificate": cert,
            "connect_private_key": key,
        }
    if mtls:
        entries["enable_mtls"] = True
    return entries


@dataclass(frozen=True)
class ZenohNodeConfig:
    """How to open the Zenoh session and which ROS wire convention to speak.

    Without ``config_file`` every field applies. With one, the file is authoritative and only
    non-empty ``listen`` / ``connect`` lists are applied on top (``insert_json5``).

    ``connect=None`` means the key mode's default: nothing for ros2dds, :data:`RMW_ZENOH_ROUTER` for
    rmw_zenoh (also on top of a config file that names no connect endpoints); a given tuple, even an
    empty one, replaces it.
    """

    mode: ZenohMode = "peer"
    listen: tuple[str, ...] = ("tcp/127.0.0.1:7448",)
    connect: tuple[str, ...] | None = None
    #: optional Zenoh JSON5 configuration file
    config_file: str | None = None
    multicast_scouting: bool = False
    shared_memory: bool = False
    key_mode: KeyMode = "ros2dds"
    domain_id: int = 0
    #: ros2dds: key prefix exactly like zenoh-bridge-ros2dds' ``namespace`` option ("/ns" -> "ns/...")
    namespace: str = "/"
    #: ros2dds: announce entities with bridge-style liveliness tokens so a bridge creates DDS endpoints
    announce: bool = True
    #: the ROS node these entities belong to (rmw_zenoh tokens); relative topics resolve in node_namespace
    node_name: str = "droneulator"
    node_namespace: str = "/"
    enclave: str = "/"
    #: TLS of ``tls/`` endpoints (:func:`tls_entries`), applied on top of ``config_file``
    tls_ca: str = ""
    tls_cert: str = ""
    tls_key: str = ""
    tls_mtls: bool = False

    def __post_init__(self) -> None:
        if self.key_mode not in ("ros2dds", "rmw_zenoh"):
            raise ValueError(f"key_mode must be 'ros2dds' or 'rmw_zenoh', got {self.key_mode!r}")
        if self.mode not in ("peer", "client", "router"):
            raise ValueError(f"mode must be 'peer', 'client' or 'router', got {self.mode!r}")
        if self.namespace != "/" and self.key_mode != "ros2dds":
            raise ValueError("namespace is zenoh-bridge-ros2dds' key prefix: key_mode 'ros2dds' only")
        if not 0 <= self.domain_id <= 232:
            raise ValueError("domain_id must lie in [0, 232]")
        if self.namespace != "/":
            fully_qualified(self.namespace)
        if not _NAME_TOKEN.match(self.node_name):
            raise ValueError(f"invalid ROS node name {self.node_name!r}")
        if self.node_namespace != "/":
            fully_qualified(self.node_namespace)
        object.__setattr__(self, "listen", tuple(self.listen))
        if self.connect is not None:
            object.__setattr__(self, "connect", tuple(self.connect))
        if self.mode == "client" and not self.config_file and not self.endpoints_to_connect():
            raise ValueError("a Zenoh client needs a router to connect to: give connect endpoints")

    def endpoints_to_connect(self) -> tuple[str, ...]:
        """``connect``, or the key mode's default when it is None."""
        if self.connect is not None:
            return self.connect
        return (RMW_ZENOH_ROUTER,) if self.key_mode == "rmw_zenoh" else ()

    def zenoh_config(self) -> zenoh.Config:
        """The ``zenoh.Config`` this describes."""
        connect = self.endpoints_to_connect()
        if self.config_file:
            conf = zenoh.Config.from_file(self.config_file)
            if self.listen:
                conf.insert_json5("listen/endpoints", json.dumps(list(self.listen)))
            file_connects = json.loads(conf.get_json("connect/endpoints"))
            if connect and (self.connect or not file_connects):
                conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
            self._apply_tls(conf)
            return conf
        conf = zenoh.Config()
        conf.insert_json5("mode", json.dumps(self.mode))
        conf.insert_json5("listen/endpoints", json.dumps(list(self.listen)))
        conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
        conf.insert_json5("connect/timeout_ms", json.dumps(_CONNECT_TIMEOUT_MS))
        conf.insert_json5("connect/exit_on_failure", json.dumps(_CONNECT_EXIT_ON_FAILURE))
        conf.insert_json5("scouting/multicast/enabled", json.dumps(self.multicast_scouting))
        conf.insert_json5("transport/shared_memory/enabled", json.dumps(self.shared_memory))
        self._apply_tls(conf)
        return conf

    def _apply_tls(self, conf: zenoh.Config) -> None:
        for name, value in tls_entries(self.tls_ca, self.tls_cert, self.tls_key, self.tls_mtls).items():
            conf.insert_json5(f"transport/link/tls/{name}", json.dumps(value))


class RosPublisher:
    """One declared Zenoh publisher for one ROS topic; :meth:`publish` puts a CDR sample on it."""

    def __init__(
        self,
        node: RosZenohNode,
        topic: str,
        typename: str,
        key: str,
        qos: QosProfile,
        congestion_control: zenoh.CongestionControl,
        priority: zenoh.Priority,
        token_key: str | None,
        express: bool = False,
    ) -> None:
        self.topic = topic
        self.typename = typename
        self.key = key
        self.qos = qos
        self.token_key = token_key
        self._rmw = node.config.key_mode == "rmw_zenoh"
        #: rmw_zenoh: the source gid in every attachment, derived from the token (:func:`rmw_gid`)
        self.gid = rmw_gid(token_key) if self._rmw and token_key else None
        self._seq = itertools.count(1)
        reliability = zenoh.Reliability.RELIABLE if qos.reliable else zenoh.Reliability.BEST_EFFORT
        if self._rmw and qos.transient_local:
            # rmw_publisher_data.cpp: TRANSIENT_LOCAL -> advanced publisher with a depth-sized cache,
            # publisher detection, and sporadic-heartbeat miss detection when RELIABLE
            self._pub: Any = zenoh.ext.declare_advanced_publisher(
                node.session,
                key,
                congestion_control=congestion_control,
                priority=priority,
                reliability=reliability,
                cache=zenoh.ext.CacheConfig(max(qos.depth, 1)),
                sample_miss_detection=(
                    zenoh.ext.MissDetectionConfig(heartbeat=None, sporadic_heartbeat=0.5)
                    if qos.reliable
                    else None
                ),
                publisher_detection=True,
            )
        else:
            self._pub = node.session.declare_publisher(
                key,
                congestion_control=congestion_control,
                priority=priority,
                reliability=reliability,
                express=express,
            )
        self._token = node.session.liveliness().declare_token(token_key) if token_key else None
        self._closed = False

    @property
    def matching(self) -> bool:
        """Whether a Zenoh subscriber currently matches this publisher's key (an advanced publisher, the
        transient-local kind, does not say: False)."""
        status = getattr(self._pub, "matching_status", None)
        return bool(status is not None and status.matching)

    def publish(self, cdr: messages.CdrBytes, t_ns: int | None = None) -> None:
        """Put one CDR sample (encapsulation header included, e.g. from :func:`messages.serialize`).

        rmw_zenoh mode attaches ``(sequence_number, source_timestamp, gid)``; the source timestamp is
        ``t_ns`` if given (the simulation passes the sample's stamp), else the wall clock like rmw_zenoh.
        """
        if self._closed:
            raise RuntimeError(f"publisher for {self.topic} is closed")
        if self.gid is not None:
            ts = time.time_ns() if t_ns is None else int(t_ns)
            self._pub.put(cdr, attachment=_ATTACHMENT.pack(next(self._seq), ts, _GID_SIZE, self.gid))
        else:
            self._pub.put(cdr)

    def close(self) -> None:
        """Undeclare the liveliness token, then the publisher (as ``PublisherData::shutdown`` does)."""
        if self._closed:
            return
        self._closed = True
        if self._token is not None:
            self._token.undeclare()
        self._pub.undeclare()


class RosSubscription:
    """A Zenoh subscriber that decodes each sample with rosbags and hands the message to a callback.

    A sample that does not decode, or a callback that raises, is logged (``droneulator.ros``) and
    skipped; the subscription keeps running.
    """

    def __init__(
        self,
        node: RosZenohNode,
        topic: str,
        typename: str,
        key: str,
        callback: Callable[[Any], None],
        token_key: str | None,
    ) -> None:
        self.topic = topic
        self.typename = typename
        self.key = key
        self.token_key = token_key
        #: rmw_zenoh: the gid ROS tools report for this subscription (:func:`rmw_gid`)
        self.gid = rmw_gid(token_key) if node.config.key_mode == "rmw_zenoh" and token_key else None
        self._callback = callback
        self.received = 0
        self.errors = 0
        messages.TYPESTORE.get_msgdef(typename)
        self._sub = node.session.declare_subscriber(key, self._on_sample)
        self._token = node.session.liveliness().declare_token(token_key) if token_key else None
        self._closed = False

    def _on_sample(self, sample: zenoh.Sample) -> None:
        payload = sample.payload.to_bytes()
        try:
            msg = messages.decode(self.typename, payload)
        except messages.SerdeError as exc:
            self.errors += 1
            _bad_samples.log(
                (self.topic, self.typename),
                logging.ERROR,
                "dropped a bad %s sample on %s (%d bytes): %s",
                self.typename,
                self.topic,
                len(payload),
                exc,
                summary=f"dropped {{n}} more bad {self.typename} samples on {self.topic}",
            )
            return
        self.received += 1
        try:
            self._callback(msg)
        except Exception:
            self.errors += 1
            log.exception("callback for %s failed", self.topic)

    def close(self) -> None:
        """Undeclare the liveliness token, then the subscriber."""
        if self._closed:
            return
        self._closed = True
        if self._token is not None:
            self._token.undeclare()
        self._sub.undeclare()


def _close_at_exit(ref: weakref.ReferenceType[RosZenohNode]) -> None:
    node = ref()
    if node is not None:
        node.close()


class RosZenohNode:
    """One Zenoh session acting as one ROS 2 node (see the module docstring for the wire formats)."""

    def __init__(self, config: ZenohNodeConfig | None = None) -> None:
        self.config = config or ZenohNodeConfig()
        try:
            self.session = zenoh.open(self.config.zenoh_config())
        except zenoh.ZError as exc:
            cfg = self.config
            source = f", config file {cfg.config_file}" if cfg.config_file else ""
            raise ConnectionError(
                f"cannot open the Zenoh session ({cfg.mode} mode, listen {list(cfg.listen)}, connect "
                f"{list(cfg.endpoints_to_connect())}{source}): {exc}"
            ) from exc
        self.zid = str(self.session.zid())
        self._lock = threading.Lock()
        self._publishers: dict[tuple[str, str], RosPublisher] = {}
        self._subscriptions: list[RosSubscription] = []
        # rmw_context_impl: one counter per context; the node takes the first id, its entities the next
        self._ids = itertools.count(0)
        self.node_id = next(self._ids)
        self._node_token: Any = None
        self.node_token_key: str | None = None
        self._closed = False
        # zenoh-python runs subscriber callbacks on a non-daemon Python thread that lives until the
        # session closes, so an unclosed node would hang interpreter exit in threading._shutdown. Close
        # it from threading's own exit hook (run before those threads are joined, like
        # concurrent.futures does); a weak reference keeps the hook from pinning the node.
        threading._register_atexit(functools.partial(_close_at_exit, weakref.ref(self)))
        if self.config.key_mode == "rmw_zenoh":
            self.node_token_key = self._rmw_token("NN", self.node_id)
            try:
                self._node_token = self.session.liveliness().declare_token(self.node_token_key)
            except Exception:
                self.close()
                raise
        log.debug("zenoh session %s open (%s keys)", self.zid, self.config.key_mode)

    @classmethod
    def from_config(cls, bridge: _BridgeConfigLike, **overrides: Any) -> RosZenohNode:
        """A node from a ``droneulator.config.BridgeConfig``; ``overrides`` replace any field.

        Uses mode, key_mode, domain_id, listen, connect (empty: the key mode's default, see
        :class:`ZenohNodeConfig`), zenoh_config, ros2dds_namespace (the bridge-style key prefix), the
        ``tls_*`` files and shared_memory.
        ``BridgeConfig.namespace`` is not used: the simulator already puts it into its topic names.
        A second session of the same run passes e.g. ``mode="client", listen=(), connect=(...)``.
        """
        fields: dict[str, Any] = {
            "mode": bridge.mode,
            "key_mode": bridge.key_mode,
            "domain_id": bridge.domain_id,
            "listen": tuple(bridge.listen),
            "connect": tuple(bridge.connect) or None,
            "config_file": bridge.zenoh_config or None,
            "namespace": bridge.ros2dds_namespace,
            "tls_ca": bridge.tls_ca,
            "tls_cert": bridge.tls_cert,
            "tls_key": bridge.tls_key,
            "tls_mtls": bridge.tls_mtls,
            "shared_memory": bridge.shared_memory,
        }
        fields.update(overrides)
        return cls(ZenohNodeConfig(**fields))

    # ------------------------------------------------------------------ keys and tokens
    def key_for(self, topic: str, typename: str) -> str:
        """The Zenoh key expression samples of ``topic`` (of ROS type ``typename``) travel on."""
        cfg = self.config
        if cfg.key_mode == "rmw_zenoh":
            name = fully_qualified(topic, cfg.node_namespace)
            thash = messages.type_hash(typename)
            return f"{cfg.domain_id}/{name.strip('/')}/{dds_type_name(typename)}/{thash}"
        dds_type_name(typename)
        name = fully_qualified(topic, cfg.node_namespace)
        prefix = cfg.namespace.strip("/")
        return f"{prefix}/{name[1:]}" if prefix else name[1:]

    def _rmw_token(self, kind: str, entity_id: int, topic_part: str = "") -> str:
        cfg = self.config
        return (
            f"@ros2_lv/{cfg.domain_id}/{self.zid}/{self.node_id}/{entity_id}/{kind}/"
            f"{mangle(cfg.enclave)}/{mangle(cfg.node_namespace)}/{cfg.node_name}{topic_part}"
        )

    def _token_key(self, kind: str, topic: str, typename: str, key: str, qos: QosProfile) -> str | None:
        cfg = self.config
        thash = messages.type_hash(typename)
        if cfg.key_mode == "rmw_zenoh":
            name = fully_qualified(topic, cfg.node_namespace)
            topic_part = f"/{mangle(name)}/{dds_type_name(typename)}/{thash}/{rmw_zenoh_qos(qos)}"
            return self._rmw_token(kind, next(self._ids), topic_part)
        if not cfg.announce:
            return None
        return (
            f"@/{self.zid}/@ros2_lv/{kind}/{key.replace('/', '§')}/{typename.replace('/', '§')}/"
            f"{ros2dds_qos(qos, thash)}"
        )

    # ------------------------------------------------------------------ entities
    def publisher(
        self,
        topic: str,
        typename: str,
        *,
        qos: QosProfile | None = None,
        congestion_control: zenoh.CongestionControl | None = None,
        priority: zenoh.Priority | None = None,
    ) -> RosPublisher:
        """The publisher for ``topic``; declared once, the same object is returned on later calls.

        QoS defaults to :func:`default_qos`. Camera frames (Image, CompressedImage, PointCloud2) use
        ``CongestionControl.DROP`` at ``Priority.DATA`` so a slow consumer never stalls the simulation;
        everything else (clock, odom, tf, camera_info) uses ``BLOCK`` at ``Priority.DATA_HIGH`` so it is
        neither lost nor queued behind a multi-megabyte frame, and is sent *express* (not held back to
        be batched with other messages), which matters for odometry latency. Relative topic names
        resolve against ``node_namespace``.
        """
        self._check_open()
        with self._lock:
            existing = self._publishers.get((topic, typename))
            if existing is not None:
                return existing
            qos = qos or default_qos(fully_qualified(topic, self.config.node_namespace))
            bulk = typename in _BULK_TYPES
            if congestion_control is None:
                congestion_control = zenoh.CongestionControl.DROP if bulk else zenoh.CongestionControl.BLOCK
            if priority is None:
                priority = zenoh.Priority.DATA if bulk else zenoh.Priority.DATA_HIGH
            messages.TYPESTORE.get_msgdef(typename)
            key = self.key_for(topic, typename)
            token = self._token_key("MP", topic, typename, key, qos)
            pub = RosPublisher(
                self, topic, typename, key, qos, congestion_control, priority, token, express=not bulk
            )
            self._publishers[(topic, typename)] = pub
            return pub

    def subscribe(
        self,
        topic: str,
        typename: str,
        callback: Callable[[Any], None],
        *,
        qos: QosProfile | None = None,
    ) -> RosSubscription:
        """Call ``callback(message)`` (a rosbags object) for every valid sample on ``topic``.

        Callbacks run on a Zenoh thread; keep them short or hand work to another thread.
        """
        self._check_open()
        with self._lock:
            key = self.key_for(topic, typename)
            qos = qos or default_qos(fully_qualified(topic, self.config.node_namespace))
            token = self._token_key("MS", topic, typename, key, qos)
            sub = RosSubscription(self, topic, typename, key, callback, token)
            self._subscriptions.append(sub)
            return sub

    # ------------------------------------------------------------------ lifetime
    def _check_open(self) -> None:
        if self._closed:
            raise RuntimeError("RosZenohNode is closed")

    def close(self) -> None:
        """Undeclare every entity and token (so ROS tools see them leave), then close the session."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            for pub in self._publishers.values():
                pub.close()
            for sub in self._subscriptions:
                sub.close()
            if self._node_token is not None:
                self._node_token.undeclare()
            self.session.close()

    def __enter__(self) -> RosZenohNode:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()
