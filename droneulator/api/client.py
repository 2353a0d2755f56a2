"""Synchronous client of the Droneulator WebSocket API, for scripts, tests and other processes.

Replies and pushed stream messages share one socket: a reply carries ``id`` and ``ok``, a pushed
message carries ``type``. Requests go out one at a time; pushed messages that arrive while a reply
is awaited are buffered, in order, for :meth:`DroneulatorClient.next_message`. One thread at a time
should use a client; open a second client to stream and command from different threads.

A server bound beyond loopback asks for its token (``token=``, sent as the URL's ``token`` query
parameter) and may speak ``wss://`` (``cafile=``: a certificate to trust besides the system's, e.g. a
self-signed one); see docs/security.md. Left unset, they come from the environment variables
``DRONEULATOR_TOKEN`` and ``DRONEULATOR_TLS_CA``, so that every workflow connecting by URL (capture,
plan, the RL remote backend) reaches such a server without an option of its own.
"""

from __future__ import annotations

import itertools
import json
import logging
import os
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import ExitStack
from typing import Any

from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from droneulator.api.access import client_ssl_context, with_token, without_token
from droneulator.api.protocol import ApiError

log = logging.getLogger(__name__)

__all__ = ["ApiError", "ConnectionLostError", "DroneulatorClient"]

#: environment variables a client takes its token and its trusted certificate from, when not given
TOKEN_ENV = "DRONEULATOR_TOKEN"
TLS_CA_ENV = "DRONEULATOR_TLS_CA"


class ConnectionLostError(ApiError):
    """The server closed the connection (code ``connection_closed``; the message gives the reason)."""

    def __init__(self, message: str) -> None:
        super().__init__("connection_closed", message)


def _json_default(o: Any) -> Any:
    if hasattr(o, "tolist"):  # numpy arrays and scalars
        return o.tolist()
    raise TypeError(f"{type(o).__name__} is not JSON serialisable")


class DroneulatorClient:
    """Blocking client: one method per op, plus stream helpers.

    Every op method returns the reply's ``result`` object and raises :class:`ApiError` (with the
    server's ``code`` and ``message``) when the reply has ``ok: false``, :class:`TimeoutError` when no
    reply comes within ``timeout`` seconds and :class:`ConnectionLostError` when the connection is gone.
    Arguments left as None are omitted, so the server applies its defaults. A server that wants a
    token and did not get ``token`` answers the first request with :class:`ApiError` ``unauthorized``
    and closes the connection.
    """

    def __init__(
        self,
        url: str = "ws://127.0.0.1:8765",
        timeout: float = 10.0,
        max_buffer: int = 10_000,
        token: str | None = None,
        cafile: str | None = None,
    ) -> None:
        token = token if token is not None else os.environ.get(TOKEN_ENV) or None
        cafile = cafile if cafile is not None else os.environ.get(TLS_CA_ENV) or None
        self.url = without_token(url)
        self.timeout = timeout
        self.max_buffer = max_buffer
        self._exit = ExitStack()  # connect() as a context manager works across websockets versions
        self._ws = self._exit.enter_context(
            connect(
                with_token(url, token),
                open_timeout=timeout,
                close_timeout=2.0,
                max_size=16 << 20,
                ssl=client_ssl_context(url, cafile),
            )
        )
        self._ids = itertools.count(1)
        self._buffer: deque[dict[str, Any]] = deque()
        self._streams: list[str] = []
        self._lock = threading.RLock()

    # ------------------------------------------------------------------ transport
    def _recv(self, timeout: float | None) -> dict[str, Any]:
        """Next message from the socket; raises TimeoutError or ConnectionLostError."""
        while True:
            try:
                raw = self._ws.recv(timeout)
            except ConnectionClosed as e:
                raise ConnectionLostError(str(e)) from None
            try:
                msg = json.loads(raw)
            except ValueError:
                log.warning("ignoring a message that is not JSON: %.80r", raw)
                continue
            if isinstance(msg, dict):
                return msg
            log.warning("ignoring a message that is not an object: %.80r", raw)

    @staticmethod
    def _is_pushed(msg: dict[str, Any]) -> bool:
        return "type" in msg and "ok" not in msg

    def _stash(self, msg: dict[str, Any]) -> None:
        """Buffer a pushed message; past ``max_buffer`` the oldest *state* message goes (events stay)."""
        self._buffer.append(msg)
        if len(self._buffer) > self.max_buffer:
            for i, m in enumerate(self._buffer):
                if m.get("type") == "state":
                    del self._buffer[i]
                    break

    def send_raw(self, data: str | bytes) -> None:
        """Send a message as is (text for str, binary for bytes), e.g. to probe error handling."""
        with self._lock:
            try:
                self._ws.send(data)
            except ConnectionClosed as e:
                raise ConnectionLostError(str(e)) from None

    def _last_word(self) -> ApiError | None:
        """The error a server sent before closing (``unauthorized``), once the connection is gone."""
        while True:
            try:
                msg = self._recv(0)
            except (ConnectionLostError, TimeoutError):
                return None
            if msg.get("ok") is False and msg.get("id") is None:
                err = msg.get("error") or {}
                return ApiError(str(err.get("code", "unknown")), str(err.get("message", "")))

    def request(self, op: str, **args: Any) -> dict[str, Any]:
        """Send ``op`` with ``args`` (None values omitted) and return the reply's ``result``."""
        with self._lock:
            rid = next(self._ids)
            payload = {"id": rid, "op": op, **{k: v for k, v in args.items() if v is not None}}
            try:
                self.send_raw(json.dumps(payload, default=_json_default))
            except ConnectionLostError as lost:
                raise self._last_word() or lost from None
            deadline = time.monotonic() + self.timeout
            while True:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise TimeoutError(f"no reply to {op!r} within {self.timeout} s")
                msg = self._recv(remaining)
                if self._is_pushed(msg):
                    self._stash(msg)
                    continue
                # id null: the server could not read the request (e.g. message_too_large)
                if msg.get("id") not in (rid, None):
                    log.debug("ignoring a stale reply %r", msg)
                    continue
                if msg.get("ok"):
                    return msg.get("result", {})
                err = msg.get("error") or {}
                raise ApiError(str(err.get("code", "unknown")), str(err.get("message", "")))

    # ------------------------------------------------------------------ ops
    # ``vehicle``: which vehicle of the world (by name; None: the first), as every flight op takes it
    def takeoff(self, altitude: float | None = None, vehicle: str | None = None) -> dict[str, Any]:
        """Climb to ``altitude`` m; result ``duration`` (s), ``t``."""
        return self.request("takeoff", altitude=altitude, vehicle=vehicle)

    def land(self, vehicle: str | None = None) -> dict[str, Any]:
        return self.request("land", vehicle=vehicle)

    def goto(
        self,
        position: Sequence[float] | Any,
        yaw: float | None = None,
        speed: float | None = None,
        duration: float | None = None,
        vehicle: str | None = None,
    ) -> dict[str, Any]:
        """Min-snap move to world ``position`` [x, y, z] m with final ``yaw`` rad; result ``duration``."""
        return self.request(
            "goto", position=position, yaw=yaw, speed=speed, duration=duration, vehicle=vehicle
        )

    def velocity(self, forward: float, yaw_rate: float, vehicle: str | None = None) -> dict[str, Any]:
        """Velocity mode: ``forward`` m/s along body x, ``yaw_rate`` rad/s, constant altitude."""
        return self.request("velocity", forward=forward, yaw_rate=yaw_rate, vehicle=vehicle)

    def rotors(
        self, rotor_speeds: Sequence[float] | Any, normalized: bool | None = None, vehicle: str | None = None
    ) -> dict[str, Any]:
        """One rotors command of a stream: four speeds, rad/s (thrusts in [0, 1] with ``normalized``)."""
        return self.request("rotors", rotor_speeds=rotor_speeds, normalized=normalized, vehicle=vehicle)

    def rates(
        self,
        thrust: float,
        body_rates: Sequence[float] | Any,
        normalized: bool | None = None,
        vehicle: str | None = None,
    ) -> dict[str, Any]:
        """One rates command of a stream: collective ``thrust`` N (a share with ``normalized``), body rates
        rad/s."""
        return self.request(
            "rates", thrust=thrust, body_rates=body_rates, normalized=normalized, vehicle=vehicle
        )

    def attitude(
        self,
        thrust: float,
        quaternion: Sequence[float] | Any = None,
        roll: float | None = None,
        pitch: float | None = None,
        yaw: float | None = None,
        normalized: bool | None = None,
        vehicle: str | None = None,
    ) -> dict[str, Any]:
        """One attitude command of a stream: collective ``thrust`` and a ``quaternion`` [x, y, z, w] or
        ``roll``, ``pitch``, ``yaw`` (rad)."""
        return self.request(
            "attitude",
            thrust=thrust,
            quaternion=quaternion,
            roll=roll,
            pitch=pitch,
            yaw=yaw,
            normalized=normalized,
            vehicle=vehicle,
        )

    def hold(self, vehicle: str | None = None) -> dict[str, Any]:
        return self.request("hold", vehicle=vehicle)

    def motors_off(self, vehicle: str | None = None) -> dict[str, Any]:
        return self.request("motors_off", vehicle=vehicle)

    def reset(
        self,
        scene: str | None = None,
        seed: int | None = None,
        position: Sequence[float] | Any = None,
        yaw: float | None = None,
        airborne: bool | None = None,
        vehicle: str | None = None,
        light: dict[str, Any] | None = None,
        vegetation: float | None = None,
    ) -> dict[str, Any]:
        """Restart every vehicle; ``light``: the light fields to change (None in it: that default);
        ``vegetation``: rebuild the scene with that vegetation density."""
        return self.request(
            "reset",
            scene=scene,
            seed=seed,
            vegetation=vegetation,
            position=position,
            yaw=yaw,
            airborne=airborne,
            vehicle=vehicle,
            light=light,
        )

    def state(self, vehicle: str | None = None) -> dict[str, Any]:
        """One vehicle's state (None: the first's); ``vehicle="*"``: ``{"vehicles": {name: state}}``."""
        return self.request("state", vehicle=vehicle)

    def scene_info(self) -> dict[str, Any]:
        return self.request("scene_info")

    def trigger(self, vehicle: str | None = None) -> dict[str, Any]:
        """One frame set of ``vehicle``'s cameras (``render.camera_trigger=command``); its stamp is in
        ``frame_stamp_ns``."""
        return self.request("trigger", vehicle=vehicle)

    def ping(self) -> dict[str, Any]:
        return self.request("ping")

    # ------------------------------------------------------------------ streams
    def subscribe(
        self,
        streams: Iterable[str] = ("state", "events"),
        rate_hz: float | None = None,
        vehicle: str | None = None,
    ) -> dict[str, Any]:
        """Receive pushed ``state`` (at most ``rate_hz``; of ``vehicle``, ``"*"`` for all, default the
        first) and/or ``event`` messages from now on."""
        result = self.request("subscribe", streams=list(streams), rate_hz=rate_hz, vehicle=vehicle)
        self._streams = list(result.get("streams", []))
        return result

    def unsubscribe(self, streams: Iterable[str] | None = None) -> dict[str, Any]:
        result = self.request("unsubscribe", streams=None if streams is None else list(streams))
        self._streams = list(result.get("streams", []))
        return result

    def next_message(self, timeout: float | None = None) -> dict[str, Any] | None:
        """The next pushed message (buffered first), or None after ``timeout`` s (default: the client's)."""
        return self._next(self.timeout if timeout is None else timeout)

    def _next(self, timeout: float | None) -> dict[str, Any] | None:
        with self._lock:
            if self._buffer:
                return self._buffer.popleft()
            deadline = None if timeout is None else time.monotonic() + timeout
            while True:
                remaining = None if deadline is None else max(0.0, deadline - time.monotonic())
                try:
                    msg = self._recv(remaining)
                except TimeoutError:
                    return None
                if self._is_pushed(msg):
                    return msg
                log.debug("ignoring a stale reply %r", msg)

    def messages(self, timeout: float | None = None) -> Iterator[dict[str, Any]]:
        """Pushed messages in order; ends when ``timeout`` s pass without one (None: wait forever)."""
        while (msg := self._next(timeout)) is not None:
            yield msg

    def wait_for_event(
        self, type: str, timeout: float | None = None, vehicle: str | None = None
    ) -> dict[str, Any]:
        """Consume pushed messages until an event of ``type`` (e.g. ``"arrived"``), of ``vehicle`` if
        given; needs ``events``.

        Messages read meanwhile (state, other events) are discarded. Raises TimeoutError.
        """
        timeout = self.timeout if timeout is None else timeout
        deadline = time.monotonic() + timeout
        while (remaining := deadline - time.monotonic()) > 0:
            msg = self._next(remaining)
            if msg is None or msg.get("type") != "event":
                continue
            event = msg["event"]
            if event.get("type") == type and (vehicle is None or event.get("vehicle") == vehicle):
                return event
        raise TimeoutError(f"no {type!r} event within {timeout} s")

    def wait_until(
        self,
        predicate: Callable[[dict[str, Any]], bool],
        timeout: float | None = None,
        poll_hz: float = 20.0,
        vehicle: str | None = None,
    ) -> dict[str, Any]:
        """The first state of ``vehicle`` (None: the first; dict as the ``state`` op returns) satisfying
        ``predicate``.

        Uses the ``state`` stream when subscribed to it (consuming pushed messages; states of other
        vehicles are skipped), else polls the ``state`` op at ``poll_hz``. Raises TimeoutError.
        """
        timeout = self.timeout if timeout is None else timeout
        deadline = time.monotonic() + timeout
        while (remaining := deadline - time.monotonic()) > 0:
            if "state" in self._streams:
                msg = self._next(remaining)
                if msg is None or msg.get("type") != "state":
                    continue
                state = msg["state"]
                if vehicle is not None and state.get("vehicle") != vehicle:
                    continue
            else:
                state = self.state(vehicle)
            if predicate(state):
                return state
            if "state" not in self._streams:
                time.sleep(min(1.0 / poll_hz, max(0.0, deadline - time.monotonic())))
        raise TimeoutError(f"state condition not met within {timeout} s")

    # ------------------------------------------------------------------ lifecycle
    def close(self) -> None:
        self._exit.close()

    def __enter__(self) -> DroneulatorClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
