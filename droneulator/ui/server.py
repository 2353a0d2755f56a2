"""The browser UI's server: static pages, scene pictures, and one WebSocket per browser tab.

It is a client of the simulator's public interfaces only. Each browser tab gets its own connection to
the WebSocket API, and the tab speaks the API's own JSON protocol (docs/api.md) through it: requests go
up unchanged, replies, state and events come back unchanged. Camera images come from the ROS 2 topics
over Zenoh (:class:`~droneulator.ui.images.ImageHub`) and go to the tab as binary messages, at most
``image_hz`` per stream, newest first. Messages the UI adds itself are ``{"type": "ui", ...}``, both
ways: a tab says whose cameras it shows with ``{"type": "ui", "watch": "<vehicle>"}`` (the first
vehicle until it does). The server learns the vehicles and their image topics from the API's
``scene_info`` each time a tab's API connection opens.

When the simulator goes away (a restart), the server tells the tab and reconnects every second; the
tab in turn reconnects to this server if it goes away.

Access (docs/security.md): served beyond loopback (or given ``access.token``), the server asks for the
token: ``/ws`` serves only a tab whose URL carries it (``/ws?token=...``; the page asks for it once and
keeps it in the tab's sessionStorage), any other gets one ``unauthorized`` reply and is closed (1008)
before it gets a state, an image or a relayed reply; the ``/api/`` routes answer 401 without
``?token=``; only the static page, which asks for the token, is served to anyone. There each tab's
messages also pass a token bucket (``access.rate_hz``, ``burst``). The server's own links to the API
carry the same token. With ``access.tls_cert`` and ``tls_key`` it serves https:// and wss://.
HTTP routes::

    GET /                      the single-page app (static/index.html)
    GET /static/<file>         its modules and style sheet
    GET /api/config            API URL, image rate, depth scale, segmentation legend, PX4 flag
    GET /api/scenes            the registered scenes and their one-line descriptions
    GET /api/preview/<scene>   JPEG preview (?seed=N), rendered by the simulator's renderer
    GET /api/map/<scene>       the top-down map's extent and flyable box as JSON (?seed=N)
    GET /api/map/<scene>.png   the top-down map itself (?seed=N)
    GET /api/depth_scale.png   the depth colour bar, near (left) to ``depth_max_m`` (right)
    GET /ws                    the WebSocket
"""

from __future__ import annotations

import asyncio
import contextlib
import http
import io
import json
import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, urlsplit

import numpy as np
from PIL import Image
from websockets.asyncio.client import ClientConnection, connect
from websockets.asyncio.server import Server, ServerConnection, serve
from websockets.datastructures import Headers
from websockets.exceptions import ConnectionClosed, InvalidHandshake, InvalidURI
from websockets.http11 import Request, Response

from droneulator.api.access import (
    UNAUTHORIZED_CLOSE,
    TokenBucket,
    client_ssl_context,
    is_loopback,
    server_ssl_context,
    token_matches,
    url_token,
    with_token,
)
from droneulator.config import AccessConfig, BridgeConfig, UIConfig
from droneulator.imaging import depth_to_rgb
from droneulator.scenes.base import SEGMENTATION_PALETTE
from droneulator.threads import DaemonWorker, lower_priority
from droneulator.ui.images import Frame, ImageHub, Streams, vehicle_streams
from droneulator.ui.scenes import ScenePictures

log = logging.getLogger("droneulator.ui")

STATIC = Path(__file__).resolve().parent / "static"
_TYPES = {".html": "text/html", ".js": "text/javascript", ".css": "text/css", ".svg": "image/svg+xml"}
#: class names of the legend, as docs/segmentation.md names them
_CLASS_LABELS = {"SKY": "sky", "CANOPY": "canopy / leaves"}
RECONNECT_S = 1.0
STATUS_S = 1.0


def _response(status: int, body: bytes, content_type: str, cache: bool = False) -> Response:
    headers = Headers()
    headers["Content-Type"] = content_type
    headers["Content-Length"] = str(len(body))
    headers["Cache-Control"] = "max-age=3600" if cache else "no-store"
    headers["Connection"] = "close"
    return Response(status, http.HTTPStatus(status).phrase, headers, body)


def _json(status: int, obj: Any) -> Response:
    return _response(status, json.dumps(obj).encode(), "application/json")


def _error(status: int, message: str) -> Response:
    return _json(status, {"error": message})


def legend() -> list[dict[str, Any]]:
    """The segmentation legend: id, class name and RGB colour of every class."""
    return [
        {"id": int(c), "name": _CLASS_LABELS.get(c.name, c.name.lower()), "rgb": list(rgb)}
        for c, rgb in SEGMENTATION_PALETTE.items()
    ]


def depth_scale_png(max_m: float, width: int = 256, height: int = 12) -> bytes:
    """The depth colour bar from 0 m (left) to ``max_m`` (right), exactly as depth images are coloured."""
    row = np.linspace(0.0, max_m, width, dtype=np.float32)
    img = depth_to_rgb(np.repeat(row[None, :], height, axis=0), max_m)
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG")
    return buf.getvalue()


class UIServer:
    """Serves the UI for the simulator whose API is at ``api_url`` and whose Zenoh router is ``zenoh``."""

    def __init__(
        self,
        api_url: str,
        zenoh: str = "tcp/127.0.0.1:7448",
        config: UIConfig | None = None,
        bridge: BridgeConfig | None = None,
        namespace: str | None = None,
        px4: bool = False,
        access: AccessConfig | None = None,
    ) -> None:
        if not api_url.startswith(("ws://", "wss://")):
            raise ValueError(f"the API URL must start with ws:// or wss://, got {api_url!r}")
        self.api_url = api_url
        self.config = config or UIConfig()
        self.access = access or AccessConfig()
        if self.access.token is None and not is_loopback(self.config.host):
            raise ValueError(
                f"the UI served on {self.config.host!r} (beyond loopback) needs a token: set access.token "
                "(droneulator ui and run generate one when it is unset)"
            )
        #: the token a tab must give (None: none asked, on loopback without access.token)
        self.token = self.access.token
        self._ssl = server_ssl_context(self.access.tls_cert, self.access.tls_key)
        #: how this server reaches the API: with the token, over TLS trusting ``tls_ca`` (or the cert)
        self.api_connect_url = with_token(api_url, self.access.token)
        self.api_ssl = client_ssl_context(api_url, self.access.tls_ca or self.access.tls_cert)
        #: tabs refused for a missing or wrong token
        self.refused = 0
        bridge = bridge or BridgeConfig()
        self.px4 = px4
        self.hub = ImageHub(
            bridge,
            zenoh,
            namespace or bridge.namespace,
            jpeg_quality=self.config.jpeg_quality,
            depth_max_m=self.config.depth_max_m,
        )
        self.pictures = ScenePictures(nice=self.config.nice)
        #: Zenoh session calls and image encoding, off the event loop
        self._images = DaemonWorker("ui-images", nice=self.config.nice)
        self.sessions: set[BrowserSession] = set()
        #: every vehicle's image topics, first the default vehicle (from ``scene_info``)
        self.streams: Streams = {}
        self.frames: dict[tuple[str, str, str], Frame] = {}
        self._learning: asyncio.Lock | None = None
        self._closing = False
        self._frames_changed: asyncio.Condition | None = None
        self._server: Server | None = None
        self._pump: asyncio.Task[None] | None = None
        self._depth_scale = depth_scale_png(self.config.depth_max_m)
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None

    @property
    def url(self) -> str:
        """``http://host:port`` of the running server (the bound port when ``port`` was 0)."""
        if self._server is None:
            raise RuntimeError("the UI server is not running")
        port = self._server.sockets[0].getsockname()[1]
        return f"{'https' if self._ssl is not None else 'http'}://{self.config.host}:{port}"

    # ------------------------------------------------------------------ lifetime
    async def start(self) -> None:
        """Bind and start serving; OSError when the port is taken."""
        self._frames_changed = asyncio.Condition()
        self._learning = asyncio.Lock()
        self._server = await serve(
            self._browser,
            self.config.host,
            self.config.port,
            process_request=self._http,
            max_size=1 << 20,
            # a first preview or map is rendered while the request waits: several seconds, one at a time
            open_timeout=300,
            compression=None,  # images are compressed already; deflate would only cost CPU
            ssl=self._ssl,
        )
        self._pump = asyncio.create_task(self._pump_images())

    async def close(self) -> None:
        self._closing = True
        if self._pump is not None:
            self._pump.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._pump
        if self._server is not None:
            self._server.close()
            # a request waiting for a preview render would hold wait_closed() up until the render ends
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._server.wait_closed(), 2.0)
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self._call(self.hub.close), 5.0)
        self._images.close()
        self.pictures.close()

    async def _call(self, fn: Callable[..., Any], *args: Any) -> Any:
        """``fn(*args)`` on the image worker thread."""
        return await asyncio.wrap_future(self._images.submit(fn, *args))

    async def serve_forever(self, ready: Callable[[str], None] | None = None) -> None:
        """Start, call ``ready(url)``, serve until :meth:`stop` (or cancellation), then close."""
        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        await self.start()
        try:
            if ready is not None:
                ready(self.url)
            await self._stop.wait()
        finally:
            await self.close()

    def start_in_thread(self, timeout: float = 10.0) -> str:
        """Serve from a daemon thread with its own event loop; returns the URL once bound.

        Raises OSError (port taken) or RuntimeError (no answer within ``timeout`` s)."""
        bound: dict[str, Any] = {}
        done = threading.Event()

        def ready(url: str) -> None:
            bound["url"] = url
            done.set()

        def main() -> None:
            lower_priority(self.config.nice)
            try:
                asyncio.run(self.serve_forever(ready))
            except BaseException as exc:  # reported to the caller below
                bound["error"] = exc
                done.set()

        self._thread = threading.Thread(target=main, daemon=True, name="droneulator-ui")
        self._thread.start()
        if not done.wait(timeout):
            raise RuntimeError(f"the UI server did not start within {timeout:g} s")
        if "error" in bound:
            raise bound["error"]
        return bound["url"]

    def stop(self, timeout: float = 5.0) -> None:
        """Stop a server started with :meth:`serve_forever` or :meth:`start_in_thread` (any thread)."""
        if self._loop is not None and self._stop is not None and not self._loop.is_closed():
            with contextlib.suppress(RuntimeError):  # the loop already ended
                self._loop.call_soon_threadsafe(self._stop.set)
        if self._thread is not None:
            self._thread.join(timeout)

    # ------------------------------------------------------------------ HTTP
    async def _http(self, connection: ServerConnection, request: Request) -> Response | None:
        url = urlsplit(request.path)
        path = url.path
        if path == "/ws":
            origin = request.headers.get("Origin")
            host = request.headers.get("Host", "")
            if origin is not None and urlsplit(origin).netloc != host:
                return _error(403, f"cross-origin WebSocket from {origin} refused")
            return None
        locked = path.startswith("/api/") and self.token is not None
        if locked and not token_matches(self.token or "", url_token(request.path)):
            return _error(401, "this UI needs its access token: add ?token=TOKEN")
        try:
            seed = int(parse_qs(url.query).get("seed", ["0"])[0])
        except ValueError:
            return _error(400, "seed must be an integer")
        if path in ("/", "/index.html"):
            return self._static("index.html")
        if path.startswith("/static/"):
            return self._static(path.removeprefix("/static/"))
        if path == "/api/config":
            return _json(200, self.client_config())
        if path == "/api/scenes":
            from droneulator.scenes import list_scenes

            scenes = [{"name": n, "description": d} for n, d in list_scenes().items()]
            return _json(200, {"scenes": scenes})
        if path == "/api/depth_scale.png":
            return _response(200, self._depth_scale, "image/png", cache=True)
        if path.startswith("/api/preview/"):
            return await self._picture("preview", path.removeprefix("/api/preview/"), seed)
        if path.startswith("/api/map/"):
            return await self._picture("map", path.removeprefix("/api/map/"), seed)
        return _error(404, f"no such page: {path}")

    def _static(self, name: str) -> Response:
        file = STATIC / name
        if "/" in name or name.startswith(".") or not file.is_file():
            return _error(404, f"no such file: {name}")
        kind = _TYPES.get(file.suffix, "application/octet-stream")
        return _response(
            200, file.read_bytes(), f"{kind}; charset=utf-8" if kind.startswith("text") else kind
        )

    async def _picture(self, kind: str, name: str, seed: int) -> Response:
        png = kind == "map" and name.endswith(".png")
        name = name.removesuffix(".png")
        try:
            job = self.pictures.preview(name, seed) if kind == "preview" else self.pictures.map(name, seed)
            result = await asyncio.wrap_future(job)
        except KeyError as exc:
            return _error(404, str(exc.args[0]))
        except Exception as exc:
            log.exception("ui: rendering the %s of %s failed", kind, name)
            return _error(500, f"rendering the {kind} of {name!r} failed: {type(exc).__name__}: {exc}")
        if kind == "preview":
            return _response(200, result, "image/jpeg", cache=True)
        if png:
            return _response(200, result.png, "image/png", cache=True)
        return _json(200, {**result.meta(), "image": f"/api/map/{name}.png?seed={seed}"})

    def client_config(self) -> dict[str, Any]:
        """What the page needs to know about this server and the simulator it talks to."""
        return {
            "api_url": self.api_url,
            "zenoh": self.hub.endpoint,
            "image_hz": self.config.image_hz,
            "depth_max_m": self.config.depth_max_m,
            "legend": legend(),
            "px4": self.px4,
        }

    # ------------------------------------------------------------------ images
    async def _pump_images(self) -> None:
        """While a browser is connected: encode the newest images at ``image_hz`` and wake the senders."""
        period = 1.0 / self.config.image_hz
        last_check = 0.0
        assert self._frames_changed is not None
        while True:
            started = time.monotonic()
            if self.sessions:
                if started - last_check > 1.0:
                    last_check = started
                    await self._call(self._keep_hub)
                frames = await self._call(self.hub.encode_new)
                if frames:
                    for f in frames:
                        self.frames[(f.vehicle, f.cam, f.kind)] = f
                    async with self._frames_changed:
                        self._frames_changed.notify_all()
            elif self.hub.active:
                await self._call(self.hub.set_active, False)
            await asyncio.sleep(max(0.0, period - (time.monotonic() - started)))

    def _keep_hub(self) -> None:
        if self.hub.active:
            self.hub.keep_alive()
        else:
            self.hub.set_active(True)

    async def wait_frames(self, newer: Callable[[], bool]) -> None:
        assert self._frames_changed is not None
        async with self._frames_changed:
            await self._frames_changed.wait_for(newer)

    # ------------------------------------------------------------------ vehicles
    @property
    def default_vehicle(self) -> str | None:
        """The vehicle a tab that has not chosen one watches: the API's default, the first."""
        return next(iter(self.streams), None)

    async def learn_vehicles(self) -> None:
        """Ask the API for ``scene_info``: the vehicles and their image topics; then watch again."""
        assert self._learning is not None
        async with self._learning:
            try:
                async with connect(
                    self.api_connect_url, open_timeout=5.0, max_size=16 << 20, ssl=self.api_ssl
                ) as api:
                    await api.send(json.dumps({"id": 1, "op": "scene_info"}))
                    async with asyncio.timeout(10.0):
                        reply = json.loads(await api.recv())
            except (OSError, InvalidHandshake, InvalidURI, TimeoutError, ConnectionClosed, ValueError) as exc:
                log.warning("ui: could not read the vehicles from %s: %s", self.api_url, exc)
                return
            if not reply.get("ok"):
                log.warning("ui: scene_info failed: %s", reply.get("error"))
                return
            try:
                self.streams = vehicle_streams(reply["result"], self.hub.namespace)
            except (KeyError, TypeError, AttributeError, ValueError) as exc:
                log.warning("ui: scene_info lists no usable vehicles: %r", exc)
                return
        await self.update_watch()

    async def update_watch(self) -> None:
        """Subscribe to the cameras of the vehicles the open tabs watch, and to no others."""
        if self._closing:  # the image worker may be gone
            return
        watched = {s.watching for s in self.sessions}
        streams = {v: cams for v, cams in self.streams.items() if v in watched}
        self.frames = {k: f for k, f in self.frames.items() if k[0] in streams}
        await self._call(self.hub.watch, streams)

    async def wake_senders(self) -> None:
        """Let every tab look again for frames it has not had (one chose another vehicle)."""
        assert self._frames_changed is not None
        async with self._frames_changed:
            self._frames_changed.notify_all()

    # ------------------------------------------------------------------ browser tabs
    async def _browser(self, ws: ServerConnection) -> None:
        given = url_token(ws.request.path) if ws.request is not None else None
        if self.token is not None and not token_matches(self.token, given):
            self.refused += 1
            log.warning("ui: a tab at %s refused: no or a wrong token", ws.remote_address)
            message = "this UI needs its access token: reload the page and enter it"
            reply = {"id": None, "ok": False, "error": {"code": "unauthorized", "message": message}}
            with contextlib.suppress(ConnectionClosed):
                await ws.send(json.dumps(reply))
                await ws.close(UNAUTHORIZED_CLOSE, "unauthorized")
            return
        session = BrowserSession(self, ws)
        self.sessions.add(session)
        try:
            await session.run()
        finally:
            self.sessions.discard(session)
            await self.update_watch()


class BrowserSession:
    """One browser tab: relays its API requests, pushes images and UI status to it."""

    def __init__(self, server: UIServer, ws: ServerConnection) -> None:
        self.server = server
        self.ws = ws
        self.upstream: ClientConnection | None = None
        self.api_status: dict[str, Any] = {}
        self.sent = 0
        self.skipped = 0
        self._sent_seq: dict[tuple[str, str, str], int] = {}
        #: the tab's rate limit, wherever a token is asked for
        self.bucket = TokenBucket(server.access.rate_hz, server.access.burst) if server.token else None
        #: the vehicle whose cameras the tab shows (None: the default vehicle)
        self.vehicle: str | None = None

    @property
    def watching(self) -> str | None:
        """The vehicle whose images this tab gets."""
        return self.vehicle or self.server.default_vehicle

    async def run(self) -> None:
        tasks = [
            asyncio.create_task(self._upstream_loop()),
            asyncio.create_task(self._send_images()),
            asyncio.create_task(self._send_status()),
        ]
        try:
            async for raw in self.ws:
                if isinstance(raw, bytes):
                    raw = raw.decode("utf-8", "replace")
                if self.bucket is not None and not self.bucket.take():
                    await self._rate_limited(raw)
                    continue
                if '"ui"' in raw and await self._ui_message(raw):
                    continue
                await self._forward(raw)
        except ConnectionClosed:
            pass
        finally:
            if self.upstream is not None:  # first, with 1000: cancelled inside `connect` it closes with 1011
                await self.upstream.close()
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)

    async def _send(self, obj: dict[str, Any]) -> None:
        with contextlib.suppress(ConnectionClosed):
            await self.ws.send(json.dumps(obj))

    async def _forward(self, raw: str) -> None:
        """A request from the tab to the API; answered here with ``not_connected`` while the API is away."""
        upstream = self.upstream
        if upstream is not None:
            try:
                await upstream.send(raw)
                return
            except ConnectionClosed:
                pass
        try:
            rid = json.loads(raw).get("id")
        except (ValueError, AttributeError):
            rid = None
        message = f"the simulator's API at {self.server.api_url} is not reachable; reconnecting"
        await self._send({"id": rid, "ok": False, "error": {"code": "not_connected", "message": message}})

    async def _rate_limited(self, raw: str) -> None:
        """Answer a message past the tab's rate limit with ``rate_limited``, without relaying it."""
        try:
            rid = json.loads(raw).get("id")
        except (ValueError, AttributeError):
            rid = None
        access = self.server.access
        message = f"over the rate limit of {access.rate_hz:g} messages/s (burst {access.burst}); not sent"
        await self._send({"id": rid, "ok": False, "error": {"code": "rate_limited", "message": message}})

    async def _ui_message(self, raw: str) -> bool:
        """Handle a ``{"type": "ui", ...}`` message from the tab; False for anything else."""
        try:
            msg = json.loads(raw)
        except ValueError:
            return False
        if not isinstance(msg, dict) or msg.get("type") != "ui":
            return False
        if isinstance(msg.get("watch"), str):
            self.vehicle = msg["watch"]
            await self.server.update_watch()
            await self.server.wake_senders()
        return True

    async def _set_api_status(self, connected: bool, error: str | None = None) -> None:
        status = {"connected": connected, "url": self.server.api_url, "error": error}
        if status != self.api_status:
            self.api_status = status
            await self._send({"type": "ui", "api": status})

    async def _upstream_loop(self) -> None:
        """Keep a connection to the API, relaying everything it sends; reconnect when it drops."""
        while True:
            try:
                async with connect(
                    self.server.api_connect_url,
                    open_timeout=5.0,
                    max_size=16 << 20,
                    compression=None,
                    ssl=self.server.api_ssl,
                ) as upstream:
                    self.upstream = upstream
                    await self.server.learn_vehicles()
                    await self._set_api_status(True)
                    try:
                        async for msg in upstream:
                            await self.ws.send(msg)
                    finally:
                        self.upstream = None
                    error = "the simulator closed the connection"
            except (OSError, InvalidHandshake, InvalidURI, TimeoutError) as exc:
                error = f"cannot connect: {exc}"
            except ConnectionClosed as exc:
                error = f"connection lost: {exc}"
            await self._set_api_status(False, error)
            await asyncio.sleep(RECONNECT_S)

    async def _send_images(self) -> None:
        """Send every stream's newest frame not sent yet; frames replaced meanwhile count as skipped."""
        server = self.server

        def mine() -> list[tuple[tuple[str, str, str], Frame]]:
            vehicle = self.watching
            return [(k, f) for k, f in server.frames.items() if k[0] == vehicle]

        def newer() -> bool:
            return any(f.seq > self._sent_seq.get(k, 0) for k, f in mine())

        while True:
            await server.wait_frames(newer)
            burst = []
            for key, frame in mine():
                last = self._sent_seq.get(key, 0)
                if frame.seq <= last:
                    continue
                if last:
                    self.skipped += frame.seq - last - 1
                self._sent_seq[key] = frame.seq
                burst.append(frame)
            for i, frame in enumerate(burst):
                await self.ws.send(frame.blob(more=len(burst) - 1 - i))
                self.sent += 1

    async def _send_status(self) -> None:
        """Once a second: cameras seen, image counters and whether images arrive at all."""
        hub = self.server.hub
        while True:
            await self._send(
                {
                    "type": "ui",
                    "images": {
                        "cameras": hub.cameras(),
                        "received": hub.received,
                        "encoded": hub.encoded,
                        "sent": self.sent,
                        "dropped": self.skipped,
                        "error": hub.error,
                    },
                }
            )
            await asyncio.sleep(STATUS_S)


def run_ui(server: UIServer, announce: Callable[[str], None] = print) -> int:
    """Serve until Ctrl-C or SIGTERM (``droneulator ui``); prints ``UI: <url>`` once listening."""
    import signal

    async def main() -> None:
        lower_priority(server.config.nice)
        loop = asyncio.get_running_loop()
        task = asyncio.current_task()
        assert task is not None
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, task.cancel)
        with contextlib.suppress(asyncio.CancelledError):
            await server.serve_forever(lambda url: announce(f"UI: {url}"))

    asyncio.run(main())
    return 0
