"""Camera images for the browser, taken from the simulator's public ROS 2 topics over Zenoh.

The UI subscribes to every camera's colour, depth and segmentation topic (the camera names are found
from the keys, so any rig works), keeps only the newest raw sample per stream (a newer one replaces an
older one not yet forwarded: drop-oldest) and, at most ``image_hz`` times a second, turns each new
sample into something a browser shows directly:

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
from droneulator.ros.topics import TYPES, decode_compressed, decode_depth, header_ns, topic_names
from droneulator.scenes.base import palette_lut

log = logging.getLogger("droneulator.ui")

#: stream kinds forwarded to the browser, keyed like :func:`droneulator.ros.topics.topic_names`
KINDS = ("rgb", "depth", "seg")
_PLACEHOLDER = "UICAMERAPLACEHOLDER"
_HEADER = struct.Struct(">I")
_PALETTE = palette_lut().ravel().tolist()
#: depth and segmentation are shown beside the colour view at half its size: every 2nd pixel is
#: enough, and a quarter of the pixels to colour-map, encode, send and decode keeps the UI's cost down
DEPTH_SEG_STRIDE = 2


@dataclass
class Frame:
    """One encoded image ready for the browser: ``seq`` counts the frames of its stream from 1."""

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
    """Zenoh subscriptions to every camera's image topics, newest sample kept per stream.

    :meth:`set_active` opens the Zenoh session (a client of the run's router at ``endpoint``) only while
    a browser watches; :meth:`keep_alive` reopens it when samples stop (the simulator restarted).
    :meth:`encode_new` encodes the samples that arrived since its last call.
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
        topic_names(namespace, "front")  # a bad namespace fails here, not in a Zenoh callback
        self._lock = threading.Lock()
        self._node: Any = None
        self._subs: list[Any] = []
        self._active = False
        #: (cam, kind) -> (raw CDR sample, raw seq); raw seq counts samples received per stream
        #: newest sample per stream, still Zenoh's bytes: copied only when it is encoded (a third of them)
        self._raw: dict[tuple[str, str], tuple[Any, int]] = {}
        self._encoded_seq: dict[tuple[str, str], int] = {}
        self._frames_out: dict[tuple[str, str], int] = {}
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
        """While active: open the session if it is closed, reopen it if no sample came for ``stale_s``."""
        if not self._active:
            return
        now = time.monotonic()
        if self._node is None or now - max(self.last_sample, self.opened_at) > self.stale_s:
            self._close()
            self._open()

    def _open(self) -> None:
        from droneulator.ros.zenoh_node import RosZenohNode

        self.opened_at = time.monotonic()
        try:
            node = RosZenohNode.from_config(self.bridge, mode="client", listen=(), connect=(self.endpoint,))
        except (ConnectionError, ValueError) as exc:
            self.error = f"no images: {exc}"
            return
        try:
            subs = []
            for kind in KINDS:
                template = node.key_for(topic_names(self.namespace, _PLACEHOLDER)[kind], TYPES[kind])
                parts = template.split("/")
                index = parts.index(_PLACEHOLDER)
                parts[index] = "*"
                subs.append(node.session.declare_subscriber("/".join(parts), self._on_sample(kind, index)))
        except Exception:
            node.close()
            raise
        with self._lock:
            self._node, self._subs, self.error = node, subs, None
        log.info("ui: receiving images from %s", self.endpoint)

    def _close(self) -> None:
        with self._lock:
            node, self._node, self._subs = self._node, None, []
        if node is not None:
            node.close()

    def _on_sample(self, kind: str, index: int) -> Any:
        def callback(sample: Any) -> None:
            parts = str(sample.key_expr).split("/")
            if len(parts) <= index:
                return
            key = (parts[index], kind)
            payload = sample.payload
            with self._lock:
                seq = self._raw.get(key, (None, 0))[1] + 1
                self._raw[key] = (payload, seq)
                self.received += 1
                self.last_sample = time.monotonic()

        return callback

    # ------------------------------------------------------------------ frames
    def cameras(self) -> list[str]:
        with self._lock:
            return sorted({cam for cam, _ in self._raw})

    def encode_new(self) -> list[Frame]:
        """Encode the newest sample of every stream that has one not yet encoded (others were dropped)."""
        with self._lock:
            todo = [(k, p, s) for k, (p, s) in self._raw.items() if s > self._encoded_seq.get(k, 0)]
            for key, _, seq in todo:
                self._encoded_seq[key] = seq
        out = []
        for (cam, kind), payload, _ in todo:
            try:
                msg = messages.decode(TYPES[kind], payload.to_bytes())
                mime, data, w, h = encode_for_browser(kind, msg, self.jpeg_quality, self.depth_max_m)
            except (messages.SerdeError, ValueError) as exc:
                self.errors += 1
                log.warning("ui: dropped a %s image of camera %s: %s", kind, cam, exc)
                continue
            n = self._frames_out.get((cam, kind), 0) + 1
            self._frames_out[(cam, kind)] = n
            stamp = header_ns(msg)
            header = {
                "cam": cam,
                "kind": kind,
                "seq": n,
                "stamp_ns": stamp,
                "mime": mime,
                "width": w,
                "height": h,
                "encoded_ns": time.time_ns(),
            }
            out.append(Frame(cam, kind, n, stamp, header, data))
        self.encoded += len(out)
        return out

    def close(self) -> None:
        self._active = False
        self._close()
