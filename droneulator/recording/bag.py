"""Writing a ROS 2 bag in MCAP the way ``ros2 bag record`` (Jazzy, ``rosbag2_storage_mcap``) does.

The file a :class:`BagWriter` produces has:

* the ``ros2`` profile in its header;
* one ``ros2msg`` schema per message type, named ``pkg/msg/Type``, whose data is the type's full
  ``.msg`` text with every dependency appended after a line of 80 ``=`` and ``MSG: pkg/Type``
  (rosbag2's ``message_definition_cache``; the text comes from the rosbags typestore, so it has no
  comments but the same fields and constants);
* one channel per topic with message encoding ``cdr`` and the metadata ``offered_qos_profiles``
  (rosbag2 metadata version 9 YAML) and ``topic_type_hash`` (``RIHS01_...``);
* messages whose data is the CDR sample exactly as it travelled (encapsulation header included),
  with log and publish time in simulation nanoseconds;
* chunks compressed with zstd (default) or lz4, message indexes, statistics and summary;
* at close, a ``rosbag2`` metadata record holding ``serialized_metadata`` (what ``ros2 bag info``
  reads) and, for a bag directory, the same information as ``metadata.yaml``.

Output: a path ending in ``.mcap`` is written as that single file (``ros2 bag play out.mcap``, Foxglove
and Lichtblick open it); any other path is a bag directory like ``ros2 bag record -o`` makes,
``<dir>/<name>_0.mcap`` plus ``<dir>/metadata.yaml``.

Splitting, as ``ros2 bag record --max-bag-size/--max-bag-duration`` does it (bag directories only): once
the current file holds ``max_bytes`` or spans ``max_duration_s`` of the bag's clock (the log times,
simulation time here), it is finalised and ``<name>_1.mcap`` (then ``_2`` ...) starts with every schema
and channel registered again; ``metadata.yaml`` lists the files in order. A long recording must split:
an MCAP writer keeps every chunk's index in memory until its file is finished (for the summary).
"""

from __future__ import annotations

import io
import os
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from mcap.writer import CompressionType, Writer
from rosbags.interfaces import (
    Nodetype,
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.rosbag2.metadata import dump_qos_v9
from ruamel.yaml import YAML

from droneulator.ros import messages
from droneulator.ros.zenoh_node import QosProfile, default_qos

__all__ = [
    "BagWriter",
    "Compression",
    "check_output",
    "check_split",
    "message_definition",
    "qos_yaml",
    "stamp_reader",
]

Compression = Literal["zstd", "lz4", "none"]
_COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}

#: rosbag2 metadata version Jazzy writes (QoS as names, not enum numbers)
METADATA_VERSION = 9
#: RMW_DURATION_INFINITE as rosbag2 serialises it
_INFINITE = QosTime(sec=9223372036, nsec=854775807)
_STAMP = {True: struct.Struct("<iI"), False: struct.Struct(">iI")}


def message_definition(typename: str) -> str:
    """Full ``ros2msg`` text of ``typename`` (``pkg/msg/Type``) with its dependencies appended."""
    try:
        messages.TYPESTORE.get_msgdef(typename)
    except KeyError:
        raise ValueError(f"unknown ROS 2 message type {typename!r}: not in the Jazzy typestore") from None
    text, _ = messages.TYPESTORE.generate_msgdef(typename, ros_version=2)
    return text


def _yaml(data: object) -> str:
    yaml = YAML(typ="safe")
    yaml.default_flow_style = False
    out = io.StringIO()
    yaml.dump(data, out)
    return out.getvalue()


def _rosbags_qos(qos: QosProfile) -> Qos:
    return Qos(
        history=QosHistory.KEEP_ALL if qos.keep_all else QosHistory.KEEP_LAST,
        depth=qos.depth,
        reliability=QosReliability.RELIABLE if qos.reliable else QosReliability.BEST_EFFORT,
        durability=QosDurability.TRANSIENT_LOCAL if qos.transient_local else QosDurability.VOLATILE,
        deadline=_INFINITE,
        lifespan=_INFINITE,
        liveliness=QosLiveliness.AUTOMATIC,
        liveliness_lease_duration=_INFINITE,
        avoid_ros_namespace_conventions=False,
    )


def qos_yaml(qos: QosProfile) -> str:
    """``offered_qos_profiles`` of one publisher as rosbag2 (metadata version 9) writes it in a channel."""
    return _yaml(dump_qos_v9([_rosbags_qos(qos)])).strip()


def stamp_reader(typename: str) -> int | None:
    """Byte offset of the sim-time stamp in a CDR sample of ``typename`` (encapsulation included), or
    None if the type carries none.

    ``std_msgs/Header`` first (every stamped message) and ``rosgraph_msgs/Clock``: the ``Time`` sits
    right after the 4-byte encapsulation; ``tf2_msgs/TFMessage``: the first transform's header, after
    the sequence length (offset 8, only when the sequence is not empty).
    """
    fields = messages.TYPESTORE.fielddefs[typename][1]
    if not fields:
        return None
    first = fields[0][1]
    if first[0] == Nodetype.NAME and first[1] in ("std_msgs/msg/Header", "builtin_interfaces/msg/Time"):
        return 4
    if typename == "tf2_msgs/msg/TFMessage":
        return 8
    return None


def read_stamp(payload: bytes, offset: int | None) -> int | None:
    """The ``builtin_interfaces/Time`` at ``offset`` of a CDR sample in nanoseconds (None: no stamp)."""
    if offset is None or len(payload) < offset + 8 or len(payload) < 4:
        return None
    little = bool(payload[1] & 1)
    if offset == 8 and struct.unpack_from("<I" if little else ">I", payload, 4)[0] == 0:
        return None  # an empty TFMessage
    sec, nanosec = _STAMP[little].unpack_from(payload, offset)
    return sec * 1_000_000_000 + nanosec


def check_output(path: str | Path) -> None:
    """Raise ``ValueError`` unless ``path`` can become a new bag: a ``.mcap`` file that does not exist in
    an existing, writable folder, or a bag directory that does not exist yet (``ros2 bag`` refuses to
    overwrite too)."""
    path = Path(path)
    if path.exists():
        raise ValueError(f"{path} already exists; choose another name or remove it")
    parent = path.parent
    if not parent.is_dir():
        raise ValueError(f"folder {parent} for {path} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise ValueError(f"folder {parent} for {path} is not writable")


def check_split(path: str | Path, max_bytes: int, max_duration_s: float) -> None:
    """Raise ``ValueError`` unless the split limits are valid for ``path`` (``ros2 bag`` splits only bag
    directories)."""
    if max_bytes < 0 or not max_duration_s >= 0:
        raise ValueError(
            f"bag split limits must be >= 0 (0: no split), got {max_bytes} B, {max_duration_s} s"
        )
    if (max_bytes or max_duration_s) and Path(path).suffix == ".mcap":
        raise ValueError(
            f"{path}: a bag that splits must be a bag directory (a name without .mcap), as with ros2 bag"
        )


@dataclass
class _Channel:
    id: int
    topic: str
    typename: str
    type_hash: str
    qos: QosProfile
    count: int = 0


class BagWriter:
    """An MCAP ROS 2 bag being written; not thread-safe (one writer thread owns it).

    ``path`` ending in ``.mcap``: that file; otherwise a new bag directory (see the module docstring).
    ``chunk_size`` is the uncompressed chunk size in bytes. ``max_bytes`` / ``max_duration_s`` (0: never)
    split a bag directory into files of about that size (a file may pass it by one chunk, checked after
    each message) or span of log time.
    """

    def __init__(
        self,
        path: str | Path,
        compression: Compression = "zstd",
        chunk_size: int = 4 * 1024 * 1024,
        max_bytes: int = 0,
        max_duration_s: float = 0.0,
    ) -> None:
        if compression not in _COMPRESSION:
            raise ValueError(f"compression must be one of {sorted(_COMPRESSION)}, got {compression!r}")
        check_split(path, max_bytes, max_duration_s)
        path = Path(path)
        check_output(path)
        self._compression = compression
        self._chunk_size = chunk_size
        self._max_bytes = int(max_bytes)
        self._max_duration_ns = round(max_duration_s * 1e9)
        if path.suffix == ".mcap":
            self.directory: Path | None = None
            self.file = path
        else:
            path.mkdir()
            self.directory = path
            self.file = path / f"{path.name}_0.mcap"
        #: the finished files before the current one: (file, first log time, last log time, messages)
        self._done: list[tuple[Path, int, int, int]] = []
        self._schemas: dict[str, bytes] = {}  # type -> its ros2msg definition
        self._channels: dict[tuple[str, str], _Channel] = {}
        self._by_id: dict[int, _Channel] = {}
        self.start_ns: int | None = None
        self.end_ns = 0
        self.closed = False
        self._open_file()

    def _open_file(self) -> None:
        """Start ``self.file`` with every schema and channel known so far (all of them again after a split:
        each file of a bag directory stands alone, as rosbag2 writes them)."""
        self._stream = open(self.file, "xb")  # noqa: SIM115 (closed in _finish_file())
        self._writer = Writer(
            self._stream, chunk_size=self._chunk_size, compression=_COMPRESSION[self._compression]
        )
        self._writer.start(profile="ros2", library=f"droneulator {_version()}")
        self._file_schema: dict[str, int] = {}
        self._file_channel: dict[int, int] = {}  # our channel id -> this file's
        self._file_start_ns: int | None = None
        self._file_end_ns = 0
        self._file_count = 0
        for ch in self._by_id.values():
            self._register(ch)

    def _register(self, ch: _Channel) -> None:
        schema_id = self._file_schema.get(ch.typename)
        if schema_id is None:
            schema_id = self._writer.register_schema(ch.typename, "ros2msg", self._schemas[ch.typename])
            self._file_schema[ch.typename] = schema_id
        meta = {"offered_qos_profiles": qos_yaml(ch.qos), "topic_type_hash": ch.type_hash}
        self._file_channel[ch.id] = self._writer.register_channel(ch.topic, "cdr", schema_id, meta)

    def _finish_file(self) -> None:
        """Finalise the current file: the ``rosbag2`` metadata record, summary and footer."""
        self._done.append((self.file, self._file_start_ns or 0, self._file_end_ns, self._file_count))
        meta = self._metadata()
        self._writer.add_metadata("rosbag2", {"serialized_metadata": _yaml(meta).strip()})
        self._writer.finish()
        self._stream.close()

    def _split_due(self) -> bool:
        if self._max_bytes and self._stream.tell() >= self._max_bytes:
            return True
        return bool(
            self._max_duration_ns
            and self._file_start_ns is not None
            and self._file_end_ns - self._file_start_ns >= self._max_duration_ns
        )

    @property
    def files(self) -> list[Path]:
        """The bag's MCAP files so far, in order (one, unless it split)."""
        return [f for f, *_ in self._done] + ([] if self.closed else [self.file])

    def channel(self, topic: str, typename: str, qos: QosProfile | None = None) -> int:
        """The channel id of ``topic`` with type ``typename``, registered (with its schema) on first use."""
        key = (topic, typename)
        ch = self._channels.get(key)
        if ch is not None:
            return ch.id
        if typename not in self._schemas:
            self._schemas[typename] = message_definition(typename).encode()
        ch = _Channel(
            len(self._by_id) + 1, topic, typename, messages.type_hash(typename), qos or default_qos(topic)
        )
        self._register(ch)
        self._channels[key] = self._by_id[ch.id] = ch
        return ch.id

    def write(self, channel_id: int, log_ns: int, payload: bytes, sequence: int = 0) -> None:
        """Add one CDR sample; ``log_ns`` is its sim time (log and publish time)."""
        ch = self._by_id.get(channel_id)
        if ch is None:
            raise KeyError(f"no channel {channel_id}: register it with channel() first")
        self._writer.add_message(self._file_channel[channel_id], log_ns, payload, log_ns, sequence)
        ch.count += 1
        self.start_ns = log_ns if self.start_ns is None else min(self.start_ns, log_ns)
        self.end_ns = max(self.end_ns, log_ns)
        self._file_start_ns = log_ns if self._file_start_ns is None else min(self._file_start_ns, log_ns)
        self._file_end_ns = max(self._file_end_ns, log_ns)
        self._file_count += 1
        if self._split_due():
            assert self.directory is not None
            self._finish_file()
            self.file = self.directory / f"{self.directory.name}_{len(self._done)}.mcap"
            self._open_file()

    def counts(self) -> dict[str, int]:
        """Messages written per topic."""
        out: dict[str, int] = {}
        for ch in self._channels.values():
            out[ch.topic] = out.get(ch.topic, 0) + ch.count
        return out

    def _metadata(self) -> dict[str, object]:
        start = self.start_ns or 0
        duration = max(0, self.end_ns - start)
        total = sum(ch.count for ch in self._channels.values())
        return {
            "version": METADATA_VERSION,
            "storage_identifier": "mcap",
            "duration": {"nanoseconds": duration},
            "starting_time": {"nanoseconds_since_epoch": start},
            "message_count": total,
            "topics_with_message_count": [
                {
                    "topic_metadata": {
                        "name": ch.topic,
                        "type": ch.typename,
                        "serialization_format": "cdr",
                        "offered_qos_profiles": dump_qos_v9([_rosbags_qos(ch.qos)]),
                        "type_description_hash": ch.type_hash,
                    },
                    "message_count": ch.count,
                }
                for ch in self._channels.values()
            ],
            "compression_format": "",
            "compression_mode": "",
            "relative_file_paths": [f.name for f, *_ in self._done],
            "files": [
                {
                    "path": f.name,
                    "starting_time": {"nanoseconds_since_epoch": t0},
                    "duration": {"nanoseconds": max(0, t1 - t0)},
                    "message_count": n,
                }
                for f, t0, t1, n in self._done
            ],
            "custom_data": {"recorded_by": f"droneulator {_version()}", "clock": "simulation time"},
            "ros_distro": "jazzy",
        }

    def close(self) -> None:
        """Write the ``rosbag2`` metadata record, the summary and the footer (and ``metadata.yaml``)."""
        if self.closed:
            return
        self.closed = True
        self._finish_file()
        meta = self._metadata()
        if self.directory is not None:
            tmp = self.directory / "metadata.yaml.tmp"
            tmp.write_text(_yaml({"rosbag2_bagfile_information": meta}))
            tmp.replace(self.directory / "metadata.yaml")


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("droneulator")
    except PackageNotFoundError:
        return "0"
