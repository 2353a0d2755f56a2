"""Camera images for the browser, taken from the simulator's public ROS 2 topics over Zenoh.

The UI subscribes to the colour, depth and segmentation topic of every camera of the vehicles its
browser tabs watch (the topics as the API's ``scene_info`` lists them, :func:`vehicle_streams`), keeps
only the newest raw sample per stream (a newer one replaces an older one not yet forwarded: drop-oldest)
and, at most ``image_hz`` times a second, turns each new sample into something a browser shows
directly:

* colour: the simulator's JPEG as it is (no re-encoding),
* depth: metres colour-mapped with :func:`droneulator.imaging.depth_to_rgb` (0 .. ``depth_max_m``), JPEG,
* segmentation: the class-id PNG re-coloured with the palette of docs/segmentation.md, PNG.

In lockstep the image publishers block (``CongestionControl.BLOCK``, nothing is lost), so the Zenoh
callback here does no more than put the sample in its stream's slot; encoding and sending happen on
another thread, and nothing here answers the simulator: however slow the browser or the encoding,
the simulation waits at most for that hand-over.
"""

from __future__ import annotations

import io
import json
import logging
import struct
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from PIL import Image

from droneulator.config import BridgeConfig
from droneulator.imaging import depth_to_rgb
from droneulator.ros import messages
from droneulator.ros.topics import TYPES, decode_compressed, decode_depth, header_ns, vehicle_names
from droneulator.scenes.base import palette_lut

log = logging.getLogger("droneulator.ui")

#: stream kinds forwarded to the browser, keyed like :func:`droneulator.ros.topics.topic_names`
KINDS = ("rgb", "depth", "seg")
#: the image topics of a fleet: vehicle -> camera -> stream kind (:data:`KINDS`) -> ROS topic
Streams = dict[str, dict[str, dict[str, str]]]
_HEADER = struct.Struct(">I")
_PALETTE = palette_lut().ravel().tolist()
#: depth and segmentation are shown beside the colour view at half its size: every 2nd pixel is
#: enough, and a quarter of the pixels to colour-map, encode, send and decode keeps the UI's cost down
DEPTH_SEG_STRIDE = 2


def vehicle_streams(info: dict[str, Any], namespace: str) -> Streams:
    """The image topics of every vehicle of a ``scene_info`` reply, in its order (the first is the
    default vehicle): as the reply lists them, or, where it lists none (an API served without the
    bridge), :func:`~droneulator.ros.topics.vehicle_names` under ``namespace``."""
    vehicles = info.get("vehicles") or []
    out: Streams = {}
    for v in vehicles:
        cameras = v.get("topics", {}).get("cameras")
        if cameras is None:
            names = vehicle_names(namespace, v["name"], len(vehicles) > 1)
            cameras = {cam: names.camera_topics(cam) for cam in v.get("cameras", [])}
        out[v["name"]] = {cam: {k: topics[k] for k in KINDS} for cam, topics in cameras.items()}
    return out


@dataclass
class Frame:
    """One encoded image ready for the browser: ``seq`` counts the frames of its stream from 1."""

    vehicle: str
    cam: str
    kind: str
    seq: int
    stamp_ns: int
    header: dict[str, Any]
    data: bytes

    def blob(self, more: int = 0) -> bytes:
        """The WebSocket message (:func:`pack_frame`); ``more``: how many images of the same round follow
        it, so the page paints a round once, when its last image is decoded."""
        return pack_frame({**self.header, "more": more}, self.data)


def pack_frame(header: dict[str, Any], data: bytes) -> bytes:
    """The binary WebSocket message of one image: 4-byte big-endian header length, JSON header, bytes."""
    head = json.dumps(header, separators=(",", ":")).encode()
    return _HEADER.pack(len(head)) + head + data


def unpack_frame(blob: bytes) -> tuple[dict[str, Any], bytes]:
    """Inverse of :func:`pack_frame`; ValueError on a malformed message."""
    if len(blob) < _HEADER.size:
        raise ValueError("image message shorter than its header length")
    (n,) = _HEADER.unpack_from(blob)
    if len(blob) < _HEADER.size + n:
        raise ValueError("image message shorter than its header")
    return json.loads(blob[_HEADER.size : _HEADER.size + n]), blob[_HEADER.size + n :]


def encode_for_browser(
    kind: str, msg: Any, jpeg_quality: int, depth_max_m: float
) -> tuple[str, bytes, int, int]:
    """``(mime, bytes, width, height)`` of a decoded ROS image message of stream ``kind``."""
    if kind == "rgb":
        fmt = str(msg.format).split(";")[0].strip().lower()
        if fmt in ("jpeg", "jpg"):
            with Image.open(io.BytesIO(bytes(msg.data))) as img:
                w, h = img.size
            return "image/jpeg", bytes(msg.data), w, h
        rgb = decode_compressed(msg)
        return "image/jpeg", _jpeg(rgb, jpeg_quality), rgb.shape[1], rgb.shape[0]
    if kind == "depth":
        depth = decode_depth(msg, DEPTH_SEG_STRIDE)
        return (
            "image/jpeg",
            _jpeg(depth_to_rgb(depth, depth_max_m), jpeg_quality),
            depth.shape[1],
            depth.shape[0],
        )
    if kind == "seg":
        ids = decode_compressed(msg)
        if ids.ndim != 2:
            raise ValueError(f"segmentation image has shape {ids.shape}, expected one channel of class ids")
        ids = ids[::DEPTH_SEG_STRIDE, ::DEPTH_SEG_STRIDE]
        img = Image.fromarray(np.ascontiguousarray(ids, dtype=np.uint8), mode="P")
        img.putpalette(_PALETTE)
        buf = io.BytesIO()
        img.save(buf, format="PNG", compress_level=1)
        return "image/png", buf.getvalue(), ids.shape[1], ids.shape[0]
    raise ValueError(f"unknown image stream kind {kind!r}; expected one of {KINDS}")


def _jpeg(rgb: np.ndarray, quality: int) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format="JPEG", quality=quality)
    return buf.getvalue()


class ImageHub:
    """Zenoh subscriptions to the image topics of the watched vehicles, newest sample kept per stream.

    :meth:`watch` says which streams to subscribe to; :meth:`set_active` opens the Zenoh session (a
    client of the run's router at ``endpoint``) only while a browser watches; :meth:`keep_alive` reopens
    it when samples stop (the simulator restarted). :meth:`encode_new` encodes the samples that arrived
    since its last call. A stream is keyed ``(vehicle, camera, kind)``.
    """

    def __init__(
        self,
        bridge: BridgeConfig,
        endpoint: str,
        namespace: str,
        jpeg_quality: int = 80,
        depth_max_m: float = 20.0,
        stale_s: float = 3.0,
    ) -> None:
        self.bridge = bridge
        self.endpoint = endpoint
        self.namespace = namespace
        self.jpeg_quality = jpeg_quality
        self.depth_max_m = depth_max_m
        self.stale_s = stale_s
        vehicle_names(namespace, "vehicle", False)  # a bad namespace fails here, not later
        self._lock = threading.Lock()
        self._node: Any = None
        self._subs: list[Any] = []
        self._streams: Streams = {}
        self._active = False
        #: (vehicle, cam, kind) -> (raw CDR sample, raw seq); raw seq counts samples received per stream
        #: newest sample per stream, still Zenoh's bytes: copied only when it is encoded (a third of them)
        self._raw: dict[tuple[str, str, str], tuple[Any, int]] = {}
        self._encoded_seq: dict[tuple[str, str, str], int] = {}
        self._frames_out: dict[tuple[str, str, str], int] = {}
        self.received = 0
        self.encoded = 0
        self.errors = 0
        self.last_sample = 0.0
        self.opened_at = 0.0
        self.error: str | None = None

    # ------------------------------------------------------------------ session
    @property
    def active(self) -> bool:
        """Whether images are wanted (a browser watches)."""
        return self._active

    @property
    def is_open(self) -> bool:
        """Whether the Zenoh session is open."""
        return self._node is not None

    def set_active(self, active: bool) -> None:
        """Subscribe (True) or close the Zenoh session (False); a failed open leaves ``error`` set."""
        self._active = active
        if not active:
            self._close()
        elif self._node is None:
            self._open()

    def keep_alive(self) -> None:
        """While active: open the session if it is closed, reopen it if no sample came for ``stale_s``
        although some stream is watched."""
        if not self._active:
            return
        now = time.monotonic()
        stale = self._streams and now - max(self.last_sample, self.opened_at) > self.stale_s
        if self._node is None or stale:
            self._close()
            self._open()

    def watch(self, streams: Streams) -> None:
        """Subscribe to exactly these streams from now on (at once on an open session)."""
        if streams == self._streams:
            return
        self._streams = streams
        with self._lock:
            node, old = self._node, self._subs
        if node is None:
            return
        for sub in old:
            sub.undeclare()
        subs = self._declare(node)
        with self._lock:
            self._subs = subs
        self.opened_at = time.monotonic()  # the new streams' first samples are on their way

    def _open(self) -> None:
        from droneulator.ros.zenoh_node import RosZenohNode

        self.opened_at = time.monotonic()
        try:
            node = RosZenohNode.from_config(self.bridge, mode="client", listen=(), connect=(self.endpoint,))
        except (ConnectionError, ValueError) as exc:
            self.error = f"no images: {exc}"
            return
        try:
            subs = self._declare(node)
        except Exception:
            node.close()
            raise
        with self._lock:
            self._node, self._subs, self.error = node, subs, None
        log.info("ui: receiving images from %s", self.endpoint)

    def _declare(self, node: Any) -> list[Any]:
        """A subscriber on ``node`` for every watched stream."""
        return [
            node.session.declare_subscriber(node.key_for(topic, TYPES[kind]), self._on_sample((v, cam, kind)))
            for v, cameras in self._streams.items()
            for cam, topics in cameras.items()
            for kind, topic in topics.items()
        ]

    def _close(self) -> None:
        with self._lock:
            node, self._node, self._subs = self._node, None, []
        if node is not None:
            node.close()

    def _on_sample(self, key: tuple[str, str, str]) -> Any:
        def callback(sample: Any) -> None:
            payload = sample.payload
            with self._lock:
                seq = self._raw.get(key, (None, 0))[1] + 1
                self._raw[key] = (payload, seq)
                self.received += 1
                self.last_sample = time.monotonic()

        return callback

    # ------------------------------------------------------------------ frames
    def cameras(self) -> list[str]:
        """The cameras of the watched vehicles that sent an image."""
        with self._lock:
            return sorted({cam for v, cam, _ in self._raw if v in self._streams})

    def encode_new(self) -> list[Frame]:
        """Encode the newest sample of every stream that has one not yet encoded (others were dropped)."""
        with self._lock:
            todo = [
                (k, p, s)
                for k, (p, s) in self._raw.items()
                if s > self._encoded_seq.get(k, 0) and k[0] in self._streams
            ]
            for key, _, seq in todo:
                self._encoded_seq[key] = seq
        out = []
        for (vehicle, cam, kind), payload, _ in todo:
            try:
                msg = messages.decode(TYPES[kind], payload.to_bytes())
                mime, data, w, h = encode_for_browser(kind, msg, self.jpeg_quality, self.depth_max_m)
            except (messages.SerdeError, ValueError) as exc:
                self.errors += 1
                log.warning("ui: dropped a %s image of camera %s of %s: %s", kind, cam, vehicle, exc)
                continue
            n = self._frames_out.get((vehicle, cam, kind), 0) + 1
            self._frames_out[(vehicle, cam, kind)] = n
            stamp = header_ns(msg)
            header = {
                "vehicle": vehicle,
                "cam": cam,
                "kind": kind,
                "seq": n,
                "stamp_ns": stamp,
                "mime": mime,
                "width": w,
                "height": h,
                "encoded_ns": time.time_ns(),
            }
            out.append(Frame(vehicle, cam, kind, n, stamp, header, data))
        self.encoded += len(out)
        return out

    def close(self) -> None:
        self._active = False
        self._close()
