"""WebSocket front end of the command protocol, on its own asyncio loop in a daemon thread.

Threading: the dynamics server steps the :class:`~droneulator.world.World` in its main
thread while holding the simulation lock. Commands go through the one
:class:`~droneulator.commands.path.CommandPath` (validation, flight lock, simulation lock), one at a
time in a worker thread of this server, so they never interleave with a physics step and never stall
the event loop; ``ping`` and subscriptions are answered on the loop without the lock. The stepping
loop pushes data with the thread-safe :meth:`ApiServer.publish_state` and
:meth:`ApiServer.publish_event`.

Message size has two tiers. A message up to ``max_message_bytes`` is processed. A longer one, up to
:attr:`ApiServer.transport_limit` (16 x ``max_message_bytes``, at least 1 MiB), is read, discarded and
answered with ``message_too_large``; the connection stays usable. Past the transport limit websockets
stops reading and closes that connection with code 1009 (message too big): a protocol-level limit
cannot skip the rest of a frame, and it bounds the memory a client can make the server hold. The
server and the other connections carry on either way.

Access (:mod:`droneulator.api.access`, docs/security.md): bound beyond loopback, or given a token, the
server serves only connections whose URL carries ``?token=...``; any other gets one ``unauthorized``
reply and is closed (1008) before it is registered, so it never sees a state, an event or a reply.
With a rate limit (``droneulator run`` sets one wherever a token is asked for) every connection's
messages pass a token bucket: past it each is answered ``rate_limited``, unrun.
With an SSL context the server speaks ``wss://``.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import json
import logging
import ssl
import threading
from collections import deque
from collections.abc import Callable, Coroutine, Mapping
from typing import TYPE_CHECKING, Any

from websockets.asyncio.server import ServerConnection, serve
from websockets.exceptions import ConnectionClosed
from websockets.frames import CloseCode

from droneulator.api.access import (
    UNAUTHORIZED_CLOSE,
    TokenBucket,
    is_loopback,
    token_matches,
    url_token,
)
from droneulator.api.protocol import (
    ALL_VEHICLES,
    OPS,
    STREAMS,
    ExtraOp,
    Request,
    RequestError,
    encode,
    error_reply,
    ok_reply,
    parse_request,
)
from droneulator.commands import CommandPath
from droneulator.threads import DaemonWorker

if TYPE_CHECKING:
    from droneulator.vehicles.vehicle import VehicleState

log = logging.getLogger(__name__)

#: smallest transport limit (bytes): below it a too-long message is still answered, not disconnected
MIN_TRANSPORT_LIMIT = 1 << 20
_SERVER_OPS = ("subscribe", "unsubscribe")


def _resolve(fut: asyncio.Future[Any]) -> None:
    if not fut.done():
        fut.set_result(None)


class _Session:
    """Per-connection subscription state; one stream task writes its pushed messages."""

    def __init__(self, ws: ServerConnection, bucket: TokenBucket | None) -> None:
        self.ws = ws
        self.bucket = bucket
        addr = ws.remote_address
        self.peer = f"{addr[0]}:{addr[1]}" if addr else "?"
        self.state_period: float | None = None  # None: no state stream
        self.events_on = False
        self.events: deque[str] = deque()
        self.wake = asyncio.Event()
        self.send_lock = asyncio.Lock()  # a reply and a pushed message never interleave or overtake
        self.task: asyncio.Task[None] | None = None
        self.sent_seq = 0
        self.next_state_at = 0.0
        self.awaiting_state = False  # its stream task waits for a state newer than the one it sent
        self.vehicles: tuple[str, ...] | None = None  # whose states it gets (None: the first vehicle's)

    def streams(self) -> list[str]:
        on = {"state": self.state_period is not None, "events": self.events_on}
        return [s for s in STREAMS if on[s]]


class ApiServer:
    """The WebSocket command server: see the module docstring and docs/api.md.

    ``extra_ops`` maps op names to ``callable(args) -> result`` for runtime-specific operations
    (e.g. ``shutdown``); they run in the worker thread *without* the simulation lock, get the raw
    request fields (minus ``id`` and ``op``, NaN/Infinity already rejected) and may raise
    :class:`~droneulator.api.protocol.ApiError` or ``CommandError`` to answer with an error. They
    must not call :meth:`stop` themselves (its reply could not be sent): signal the owner instead.

    ``token`` (required when ``host`` is not a loopback address), ``ssl_context`` (wss://), ``rate_hz``
    and ``burst`` (each connection's message rate limit; None: no limit, as on loopback by default): see
    the module docstring.
    """

    def __init__(
        self,
        commands: CommandPath,
        host: str = "127.0.0.1",
        port: int = 8765,
        max_message_bytes: int = 65536,
        state_rate_hz: float = 30.0,
        extra_ops: Mapping[str, ExtraOp] | None = None,
        max_event_backlog: int = 10_000,
        stop_timeout: float = 5.0,
        token: str | None = None,
        ssl_context: ssl.SSLContext | None = None,
        rate_hz: float | None = None,
        burst: int = 400,
    ) -> None:
        if token is None and not is_loopback(host):
            raise ValueError(
                f"the API bound to {host!r} (beyond loopback) needs a token: set access.token "
                "(droneulator run generates one when it is unset)"
            )
        if rate_hz is not None:
            TokenBucket(rate_hz, burst)  # a bad rate limit fails here, not at the first connection
        if max_message_bytes < 256:
            raise ValueError("max_message_bytes must be at least 256")
        lo, hi = next(a.bounds for a in OPS["subscribe"].args if a.name == "rate_hz") or (0.0, 0.0)
        if not lo <= state_rate_hz <= hi:
            raise ValueError(f"state_rate_hz must lie in [{lo:g}, {hi:g}]")
        self.commands = commands
        self.host = host
        self.port = port
        self.max_message_bytes = max_message_bytes
        self.transport_limit = max(MIN_TRANSPORT_LIMIT, 16 * max_message_bytes)
        self.state_rate_hz = state_rate_hz
        self.max_event_backlog = max_event_backlog
        self.stop_timeout = stop_timeout
        #: the token a client must give (None: none asked, on loopback without one)
        self.token = token
        self.ssl_context = ssl_context
        self.rate_hz = rate_hz
        self.burst = burst
        #: connections refused for a missing or wrong token (for monitoring and tests)
        self.refused = 0
        self._extra_ops: dict[str, ExtraOp] = {}
        for name, fn in (extra_ops or {}).items():
            self.add_op(name, fn)
        self._state_lock = threading.Lock()
        self._state_seq = 0
        #: the latest state of every vehicle published, by name, in the world's order
        self._states: dict[str, VehicleState] = {}
        self._state_cache: tuple[int, dict[str, str | None]] = (0, {})
        self._state_wake_pending = False
        #: sessions whose stream waits for a newer state: only these are woken by a published state (the
        #: others are due later and wake by their own timer), so a 10 Hz subscriber does not wake the
        #: server's loop at the physics rate
        self._n_awaiting_state = 0
        self._sessions: set[_Session] = set()
        self._background: set[asyncio.Task[Any]] = set()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop_fut: asyncio.Future[None] | None = None
        self._thread: threading.Thread | None = None
        #: runs commands that wait for the simulation lock, off the event loop, in arrival order
        self._worker: DaemonWorker | None = None
        self._ready = threading.Event()
        self._closing = threading.Event()
        self._start_error: BaseException | None = None

    # ------------------------------------------------------------------ configuration
    @property
    def url(self) -> str:
        return f"{'wss' if self.ssl_context is not None else 'ws'}://{self.host}:{self.port}"

    @property
    def client_count(self) -> int:
        """Open connections (for monitoring and leak checks)."""
        return len(self._sessions)

    def add_op(self, name: str, fn: ExtraOp) -> None:
        """Register (or replace) a runtime op; thread-safe, also while serving."""
        if name in OPS:
            raise ValueError(f"extra op {name!r} would shadow a built-in op")
        self._extra_ops = {**self._extra_ops, name: fn}  # copy on write: readers never see a mutation

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> ApiServer:
        """Start serving in a daemon thread; returns once listening (``port=0``: see :attr:`port`)."""
        if self._thread is not None:
            raise RuntimeError("ApiServer already started")
        self._ready.clear()
        self._closing.clear()
        self._start_error = None
        self._worker = DaemonWorker("droneulator-api-worker")
        self._thread = threading.Thread(target=self._thread_main, name="droneulator-api", daemon=True)
        self._thread.start()
        self._ready.wait()
        if self._start_error is not None:
            self._thread.join()
            self._thread = None
            self._worker.close()
            raise self._start_error
        return self

    def stop(self) -> None:
        """Close every connection (code 1001) and the listening socket, then end the thread."""
        thread, loop, stop_fut = self._thread, self._loop, self._stop_fut
        if thread is None:
            return
        self._closing.set()
        if loop is not None and stop_fut is not None:
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(_resolve, stop_fut)
        if threading.current_thread() is not thread:
            thread.join(self.stop_timeout + 5.0)
            if thread.is_alive():
                log.warning("API server thread did not stop within %.1f s", self.stop_timeout + 5.0)
        if self._worker is not None:
            self._worker.close()
        self._thread = self._worker = None

    def __enter__(self) -> ApiServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _thread_main(self) -> None:
        try:
            asyncio.run(self._serve())
        except BaseException as e:
            log.exception("API server loop failed")
            self._start_error = self._start_error or e
        finally:
            self._loop = None
            self._ready.set()

    async def _serve(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._stop_fut = self._loop.create_future()
        try:
            server = await serve(
                self._handle,
                self.host,
                self.port,
                max_size=self.transport_limit,
                max_queue=8,
                close_timeout=2.0,
                ssl=self.ssl_context,
            )
        except OSError as e:
            self._start_error = e
            return
        self.port = server.sockets[0].getsockname()[1]
        log.info("API listening on %s", self.url)
        self._ready.set()
        await self._stop_fut
        server.close()
        try:
            await asyncio.wait_for(server.wait_closed(), self.stop_timeout)
        except TimeoutError:
            log.warning("API connections did not close within %.1f s", self.stop_timeout)
        log.info("API server on %s stopped", self.url)

    # ------------------------------------------------------------------ publishing (any thread)
    def publish_state(self, state: VehicleState) -> None:
        """Offer the latest state of one vehicle (see :meth:`publish_states`)."""
        self.publish_states({state.vehicle: state})

    def publish_states(self, states: Mapping[str, VehicleState]) -> None:
        """Offer the latest vehicle states (by name); subscribers get them at their rate (older values are
        skipped).

        Thread-safe and cheap: states are converted and serialised later, on the server thread, and
        only when a subscriber is due (do not mutate them).
        """
        with self._state_lock:
            self._state_seq += 1
            self._states = {**self._states, **states}
        loop = self._loop
        if loop is None or self._state_wake_pending or not self._n_awaiting_state:
            return
        self._state_wake_pending = True
        try:
            loop.call_soon_threadsafe(self._wake_state_subscribers)
        except RuntimeError:  # the loop just closed
            self._state_wake_pending = False

    def publish_event(self, event: dict[str, Any]) -> None:
        """Queue an event for every events subscriber, in publication order. Thread-safe."""
        loop = self._loop
        if loop is None:
            return
        with contextlib.suppress(RuntimeError):
            loop.call_soon_threadsafe(self._push_event, event)

    def _wake_state_subscribers(self) -> None:
        self._state_wake_pending = False
        for s in self._sessions:
            if s.awaiting_state:
                s.wake.set()

    def _push_event(self, event: dict[str, Any]) -> None:
        try:
            text = encode({"type": "event", "event": event})
        except (TypeError, ValueError):
            log.exception("event %r is not JSON serialisable; not sent", event)
            return
        for s in self._sessions:
            if not s.events_on:
                continue
            if len(s.events) >= self.max_event_backlog:
                self._disconnect_slow(s)
                continue
            s.events.append(text)
            s.wake.set()

    def _disconnect_slow(self, s: _Session) -> None:
        """Events are never dropped, so a subscriber that cannot keep up is disconnected instead."""
        log.warning("client %s: %d events unsent, closing its connection", s.peer, len(s.events))
        self._set_streams(s, (), None)
        self._spawn(s.ws.close(CloseCode.POLICY_VIOLATION, "event backlog exceeded: reading too slowly"))

    def _spawn(self, coro: Coroutine[Any, Any, Any]) -> None:
        task = asyncio.get_running_loop().create_task(coro)
        self._background.add(task)
        task.add_done_callback(self._background.discard)

    def _state_texts(self, vehicles: tuple[str, ...] | None) -> tuple[int, list[str]]:
        """The latest states of ``vehicles`` (None: the first vehicle) as pushed messages, each serialised
        once per published state."""
        with self._state_lock:
            seq, states = self._state_seq, self._states
        if self._state_cache[0] != seq:
            self._state_cache = (seq, {})
        cache = self._state_cache[1]
        names = vehicles if vehicles is not None else tuple(states)[:1]
        out = []
        for name in names:
            if name not in cache:
                text = None
                if name in states:
                    try:
                        text = encode({"type": "state", "state": states[name].to_dict()})
                    except (TypeError, ValueError):
                        log.exception("state of %s is not JSON serialisable; not sent", name)
                cache[name] = text
            if cache[name] is not None:
                out.append(cache[name])
        return seq, out

    # ------------------------------------------------------------------ connections
    async def _refuse(self, ws: ServerConnection, given: str | None) -> None:
        """One ``unauthorized`` reply, then close: a client without the token learns nothing else."""
        self.refused += 1
        addr = ws.remote_address
        log.warning(
            "client %s: refused, %s token",
            f"{addr[0]}:{addr[1]}" if addr else "?",
            "no" if given is None else "a wrong",
        )
        message = "this server needs its access token: connect to ws[s]://host:port/?token=TOKEN"
        with contextlib.suppress(ConnectionClosed):
            await ws.send(encode(error_reply(None, "unauthorized", message)))
            await ws.close(UNAUTHORIZED_CLOSE, "unauthorized")

    async def _handle(self, ws: ServerConnection) -> None:
        given = url_token(ws.request.path) if ws.request is not None else None
        if self.token is not None and not token_matches(self.token, given):
            await self._refuse(ws, given)
            return
        bucket = TokenBucket(self.rate_hz, self.burst) if self.rate_hz is not None else None
        session = _Session(ws, bucket)
        self._sessions.add(session)
        log.info("client %s connected (%d open)", session.peer, len(self._sessions))
        try:
            while True:
                raw = await ws.recv(decode=False)
                if session.bucket is not None and not session.bucket.take():
                    await self._rate_limited(session, raw)
                    continue
                reply, activate = await self._respond(session, raw)
                if reply is None:  # stopping
                    return
                async with session.send_lock:  # streams start now, but push only after this reply
                    if activate is not None:
                        activate()
                    await ws.send(self._encode_reply(reply))
        except ConnectionClosed as e:
            log.info("client %s disconnected (%s)", session.peer, e)
        except Exception:
            log.exception("client %s: connection handler failed", session.peer)
        finally:
            self._set_streams(session, (), None)
            self._sessions.discard(session)
            if session.task is not None:
                session.task.cancel()
                await asyncio.gather(session.task, return_exceptions=True)

    async def _rate_limited(self, s: _Session, raw: bytes) -> None:
        """Answer a message past the connection's rate limit with ``rate_limited``, without running it."""
        assert s.bucket is not None and self.rate_hz is not None
        if s.bucket.refused == 1 or s.bucket.refused % 1000 == 0:
            log.warning(
                "client %s: over its rate limit (%g messages/s), %d refused so far",
                s.peer,
                self.rate_hz,
                s.bucket.refused,
            )
        rid = None
        if len(raw) <= self.max_message_bytes:
            with contextlib.suppress(ValueError):
                msg = json.loads(raw)
                if isinstance(msg, dict) and isinstance(msg.get("id"), int | str):
                    rid = msg["id"]
        message = f"over the rate limit of {self.rate_hz:g} messages/s (burst {self.burst}); not run"
        async with s.send_lock:
            await s.ws.send(encode(error_reply(rid, "rate_limited", message)))

    def _encode_reply(self, reply: dict[str, Any]) -> str:
        try:
            return encode(reply)
        except (TypeError, ValueError) as e:
            log.exception("reply not serialisable")
            return encode(error_reply(reply.get("id"), "internal_error", f"reply not serialisable: {e}"))

    async def _respond(
        self, session: _Session, raw: bytes
    ) -> tuple[dict[str, Any] | None, Callable[[], None] | None]:
        """The reply to one message, and a subscription to activate as it is sent."""
        if len(raw) > self.max_message_bytes:
            msg = f"message of {len(raw)} bytes exceeds the limit of {self.max_message_bytes} bytes"
            return error_reply(None, "message_too_large", msg), None
        extra = self._extra_ops
        try:
            req = parse_request(raw, extra)
        except RequestError as e:
            return error_reply(e.request_id, e.code, e.message), None
        log.debug("client %s: %s %s", session.peer, req.op, req.args)
        if req.op in _SERVER_OPS:
            return self._subscription(session, req)
        if req.op in OPS and not OPS[req.op].locked:
            return self.commands.execute(req), None
        assert self._worker is not None and self._stop_fut is not None
        fut = asyncio.wrap_future(self._worker.submit(self._run_command, req, extra))
        await asyncio.wait((fut, self._stop_fut), return_when=asyncio.FIRST_COMPLETED)
        if not fut.done():
            fut.cancel()
            return None, None
        return fut.result(), None

    def _run_command(self, req: Request, extra: Mapping[str, ExtraOp]) -> dict[str, Any]:
        """Worker thread: the command path (extra ops without the lock), never once stopping."""
        return self.commands.execute(req, extra, self._closing)

    # ------------------------------------------------------------------ subscriptions
    def _subscription(self, s: _Session, req: Request) -> tuple[dict[str, Any], Callable[[], None] | None]:
        streams = req.args.get("streams", STREAMS)
        if req.op == "unsubscribe":
            keep = [x for x in s.streams() if x not in streams]
            period = s.state_period if "state" in keep else None
            self._set_streams(s, keep, period)
            return ok_reply(req.id, {"streams": s.streams()}), None
        rate = req.args.get("rate_hz", self.state_rate_hz)
        world = self.commands.sim
        wanted = req.args.get("vehicle")
        if wanted == ALL_VEHICLES:
            vehicles: tuple[str, ...] | None = tuple(world.vehicles)
        elif wanted is None:
            vehicles = None
        elif wanted in world.vehicles:
            vehicles = (wanted,)
        else:
            known = ", ".join(world.vehicles)
            return error_reply(
                req.id, "invalid_argument", f"no vehicle {wanted!r}; the vehicles are {known}"
            ), None
        result: dict[str, Any] = {"streams": list(streams), "rate_hz": rate if "state" in streams else None}
        if vehicles is not None:
            result["vehicles"] = list(vehicles)
        return ok_reply(req.id, result), functools.partial(self._subscribe, s, streams, 1.0 / rate, vehicles)

    def _subscribe(
        self, s: _Session, streams: tuple[str, ...], period: float, vehicles: tuple[str, ...] | None
    ) -> None:
        """Activate a subscription (called holding ``send_lock``, so the reply goes out first)."""
        s.vehicles = vehicles
        self._set_streams(s, streams, period if "state" in streams else None)
        s.sent_seq, s.next_state_at = 0, 0.0  # send the current state right away
        if s.task is None:
            s.task = asyncio.get_running_loop().create_task(self._stream(s))
        s.wake.set()

    def _set_streams(self, s: _Session, streams: Any, period: float | None) -> None:
        s.state_period = period
        s.events_on = "events" in streams
        if not s.events_on:
            s.events.clear()

    async def _stream(self, s: _Session) -> None:
        """Write pushed messages: queued events first, in order; then the latest state when due."""
        loop = asyncio.get_running_loop()
        try:
            while True:
                if s.events:
                    text = s.events.popleft()
                    async with s.send_lock:
                        await s.ws.send(text)
                    continue
                timeout = None
                awaiting = False
                if s.state_period is not None:
                    if self._state_seq != s.sent_seq:
                        now = loop.time()
                        if now >= s.next_state_at:
                            seq, texts = self._state_texts(s.vehicles)
                            s.sent_seq = seq
                            if texts:
                                # a fixed grid keeps the average rate; restart it after a stall
                                base = s.next_state_at if now - s.next_state_at < s.state_period else now
                                s.next_state_at = base + s.state_period
                                async with s.send_lock:
                                    for text in texts:
                                        await s.ws.send(text)
                            continue
                        timeout = s.next_state_at - now
                    else:
                        awaiting = True
                s.wake.clear()
                if awaiting:
                    s.awaiting_state = True
                    self._n_awaiting_state += 1
                try:
                    # a state published before the count went up did not wake us: look again
                    if not (awaiting and self._state_seq != s.sent_seq):
                        with contextlib.suppress(TimeoutError):
                            async with asyncio.timeout(timeout):
                                await s.wake.wait()
                finally:
                    if awaiting:
                        s.awaiting_state = False
                        self._n_awaiting_state -= 1
        except ConnectionClosed:
            pass
