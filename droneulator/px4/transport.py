"""PX4's TCP side of the link: the listening socket, vetting new connections, and MAVLink framing.

PX4's ``simulator_mavlink`` connects as a TCP *client* to port ``4560 + N``. One PX4 at a time: while
the connected PX4 is alive (it sent data within ``LINK_SILENCE_S``, or owes no answer because nothing
was sent to it since its last message) a new connection is closed at once, so a second client cannot
take the vehicle from it. Any other connection (no PX4 connected, or the connected one silent: paused
in a debugger, stopped, or dead without closing) is a *candidate*: it is sent nothing and is handed to
the link only once it has shown it is a PX4 with a HEARTBEAT from ``MAV_AUTOPILOT_PX4``, which PX4's
simulator_mavlink sends the moment it connects; one that shows none within ``CANDIDATE_TIMEOUT_S`` is
closed. So a stray client can neither take the link from a paused PX4, which resumes into it (PX4's
simulator_mavlink never reconnects), nor lock the API's flight commands as a "PX4" on an empty port.

Frames are checked by pymavlink's parser; :class:`Framer` only finds where they start, so that garbage
costs its own bytes and not a valid frame after it (see :meth:`Framer.feed`).
"""

from __future__ import annotations

import contextlib
import logging
import math
import socket
import time
from collections.abc import Collection
from dataclasses import dataclass, field
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

from droneulator.logs import LogThrottle

log = logging.getLogger(__name__)

#: a connection whose PX4 left sensor data unanswered this long (wall time) may be replaced by a new one
LINK_SILENCE_S = 1.0
#: a new connection is closed when it shows no PX4 HEARTBEAT within this (wall s)
CANDIDATE_TIMEOUT_S = 3.0
#: at most this many connections wait to show they are a PX4 at once; more are closed
MAX_CANDIDATES = 4
SEND_TIMEOUT_S = 5.0

_STX = bytes([mavlink.PROTOCOL_MARKER_V2, mavlink.PROTOCOL_MARKER_V1])


def pack_next(mav: mavlink.MAVLink, msg: Any) -> bytes:
    """``msg`` packed with ``mav``'s identity and its next sequence number. pymavlink's ``pack`` stamps the
    codec's ``seq`` but only ``send`` advances it: packed alone, every message would carry the same number,
    which a receiver (PX4's ``updateRxStats``, ArduPilot's link statistics) counts as 255 lost messages
    each. Not thread-safe: one codec per sender, packed under its sender's lock."""
    data = msg.pack(mav)
    mav.seq = (mav.seq + 1) % 256
    return data


def _next_stx(buf: bytearray, start: int) -> int | None:
    """Index of the next byte at or after ``start`` that can begin a MAVLink 1 or 2 frame."""
    hits = [i for i in (buf.find(stx, start) for stx in _STX) if i >= 0]
    return min(hits) if hits else None


def _parse_frame(data: bytes) -> tuple[Any, int] | bool | None:
    """pymavlink's parser on a frame starting at ``data[0]``: ``(message, frame length)``, None while
    the frame is incomplete, or False when pymavlink rejects it (checksum, unknown message, flags)."""
    parser = mavlink.MAVLink(None)
    parser.robust_parsing = True
    msg = parser.parse_char(data)
    if msg is None:
        return None
    if isinstance(msg, mavlink.MAVLink_bad_data):
        return False
    return msg, len(data) - parser.buf_len()


class Framer:
    """The bytes received on one connection, cut into the MAVLink messages they hold.

    pymavlink's own stream parser is not used as is: it drops a rejected frame's whole claimed length
    and waits for an incomplete (bogus) frame to complete, and in lockstep PX4 sends one message and
    waits, so a valid frame after garbage would never be read.
    """

    def __init__(self, errors: LogThrottle) -> None:
        self.buf = bytearray()
        self._errors = errors

    def clear(self) -> None:
        self.buf.clear()

    def feed(self, data: bytes) -> list[Any]:
        """Complete MAVLink messages received so far with ``data`` (removed from the buffer).

        Bytes that cannot start a valid frame are dropped with a logged error. A rejected frame
        costs one byte, not its claimed length, and an incomplete frame is given up once a valid
        frame starts after it, so a valid message inside (or after) a run of garbage is still found.
        """
        buf = self.buf
        buf += data
        out: list[Any] = []
        while buf:
            found = None
            keep = len(buf)
            p = _next_stx(buf, 0)
            while p is not None:
                parsed = _parse_frame(bytes(buf[p:]))
                if parsed is None:
                    keep = min(keep, p)
                elif parsed is not False:
                    found = (p, *parsed)
                    break
                p = _next_stx(buf, p + 1)
            if found is None:
                if keep:
                    self._garbage(keep)
                    del buf[:keep]
                return out
            p, msg, n = found
            if p:
                self._garbage(p)
            del buf[: p + n]
            out.append(msg)
        return out

    def _garbage(self, n: int) -> None:
        self._errors.error("garbage", "discarded %d bytes from PX4 that are not valid MAVLink", n)


@dataclass
class Candidate:
    """A connection that has not shown it is a PX4 yet: it is sent nothing and becomes the link (replacing
    a silent PX4, if one is connected) only once it has (a HEARTBEAT from ``MAV_AUTOPILOT_PX4``)."""

    sock: socket.socket
    address: str
    since: float
    framer: Framer
    msgs: list[Any] = field(default_factory=list)
    px4: bool = False


class ConnectionLostError(Exception):
    """PX4's connection failed or was closed by PX4; the message says why."""


class Transport:
    """The sockets of one PX4 link on ``(host, port)``: the listener, PX4's connection, the candidates.

    It knows TCP and MAVLink frames only; the link decides what a message means, and when a connection
    is dropped (:meth:`disconnect`) or a vetted candidate installed (:meth:`adopt`).
    """

    def __init__(self, host: str, port: int) -> None:
        self.host, self._port = host, port
        self.listener: socket.socket | None = None
        self.listening = False
        self.conn: socket.socket | None = None
        self.peer = ""
        self._errors = LogThrottle(log, period=1.0)
        self.framer = Framer(self._errors)
        self.candidates: list[Candidate] = []
        #: wall time of the first batch sent since PX4's last data (None: PX4 owes no answer)
        self._unanswered_since: float | None = None

    # ------------------------------------------------------------------ the listener
    def bind(self) -> None:
        """Take the port (idempotent); bound but not listening, it refuses connections."""
        if self.listener is not None:
            return
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind((self.host, self._port))
            sock.setblocking(False)
        except OSError:
            sock.close()
            raise
        self.listener = sock

    def listen(self) -> bool:
        """Let PX4 connect; True if it could not before."""
        assert self.listener is not None
        if self.listening:
            return False
        self.listener.listen(1)
        self.listening = True
        return True

    @property
    def port(self) -> int:
        if self.listener is None:
            raise RuntimeError("PX4Link is not listening: call start() first")
        return int(self.listener.getsockname()[1])

    def close(self) -> None:
        """Close every candidate and the listener (PX4's connection is the link's to drop first)."""
        for c in list(self.candidates):
            self.close_candidate(c, "the link closed")
        if self.listener is not None:
            self.listener.close()
            self.listener = None
            self.listening = False

    def sockets(self) -> list[Any]:
        """Every socket to wait on: the listener, PX4's connection, the candidates'."""
        assert self.listener is not None
        socks: list[Any] = [self.listener] if self.conn is None else [self.listener, self.conn]
        return socks + [c.sock for c in self.candidates]

    # ------------------------------------------------------------------ PX4's connection
    def adopt(self, conn: socket.socket, address: str, framer: Framer | None = None) -> None:
        """Make ``conn`` PX4's connection, with the bytes a candidate left unframed (``framer``)."""
        conn.setblocking(True)
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        conn.settimeout(SEND_TIMEOUT_S)
        self.conn, self.peer = conn, address
        self.framer = framer if framer is not None else Framer(self._errors)
        self._unanswered_since = None

    def disconnect(self) -> bool:
        """Close PX4's connection; True if there was one."""
        conn, self.conn = self.conn, None
        if conn is not None:
            with contextlib.suppress(OSError):
                conn.close()
        self.framer.clear()
        self._unanswered_since = None
        return conn is not None

    def receive(self) -> list[Any]:
        """The messages PX4's connection has for us (none when the read would block).

        Raises :class:`ConnectionLostError` when the connection failed or PX4 closed it."""
        assert self.conn is not None
        try:
            data = self.conn.recv(65536)
        except (BlockingIOError, InterruptedError, TimeoutError):
            return []
        except OSError as exc:
            raise ConnectionLostError(f"receive failed: {exc}") from exc
        if not data:
            raise ConnectionLostError("PX4 closed the connection")
        self._unanswered_since = None
        return self.framer.feed(data)

    def send(self, data: bytes) -> None:
        """Send ``data`` to PX4 (nothing without a connection); raises :class:`ConnectionLostError`."""
        if self.conn is None:
            return
        try:
            self.conn.sendall(data)
        except OSError as exc:
            raise ConnectionLostError(f"send failed: {exc}") from exc
        if self._unanswered_since is None:
            self._unanswered_since = time.monotonic()

    def silence(self) -> float:
        """Wall seconds the connected PX4 has left sensor data unanswered (0 while it owes nothing)."""
        since = self._unanswered_since
        return 0.0 if since is None else time.monotonic() - since

    # ------------------------------------------------------------------ vetting new connections
    def accept(self) -> None:
        """Accept a connection: closed at once while PX4 is alive, else a candidate."""
        assert self.listener is not None
        try:
            conn, addr = self.listener.accept()
        except OSError:
            return
        address = f"{addr[0]}:{addr[1]}"
        silent = self.silence() if self.conn is not None else math.inf
        if silent <= LINK_SILENCE_S or len(self.candidates) >= MAX_CANDIDATES:
            with contextlib.suppress(OSError):
                conn.close()
            log.warning(
                "refused a PX4 connection from %s: %s",
                address,
                f"PX4 at {self.peer} is connected and alive (silent {silent:.2f} s)"
                if silent <= LINK_SILENCE_S
                else f"{MAX_CANDIDATES} connections already wait to show they are a PX4",
            )
            return
        # PX4's simulator_mavlink sends a HEARTBEAT the moment it connects ("to initiate the SITL
        # simulator"): until a connection has, it is sent nothing and owns nothing, so a stray client
        # can neither take a paused PX4's link nor lock the API's flight commands as a "PX4"
        conn.setblocking(False)
        self.candidates.append(Candidate(conn, address, time.monotonic(), Framer(self._errors)))
        if self.conn is not None:
            log.warning(
                "PX4 at %s has been silent for %.1f s; the connection from %s replaces it once it shows "
                "it is a PX4 (a HEARTBEAT from MAV_AUTOPILOT_PX4) and is sent nothing until then",
                self.peer,
                silent,
                address,
            )

    def receive_candidates(self, readable: Collection[Any]) -> None:
        """Read what the candidates among ``readable`` sent, noting a PX4 HEARTBEAT."""
        for c in list(self.candidates):
            if c.sock in readable:
                self._receive_candidate(c)

    def _receive_candidate(self, c: Candidate) -> None:
        try:
            data = c.sock.recv(65536)
        except (BlockingIOError, InterruptedError, TimeoutError):
            return
        except OSError as exc:
            self.close_candidate(c, f"receive failed: {exc}")
            return
        if not data:
            self.close_candidate(c, "it closed before showing it is a PX4")
            return
        for msg in c.framer.feed(data):
            c.msgs.append(msg)
            if msg.get_type() == "HEARTBEAT" and msg.autopilot == mavlink.MAV_AUTOPILOT_PX4 and not c.px4:
                c.px4 = True
                log.info("the waiting connection from %s sent a PX4 HEARTBEAT", c.address)

    def close_candidate(self, c: Candidate, reason: str) -> None:
        self.candidates.remove(c)
        # logged before the close, so that whoever sees the connection end can read why
        log.warning("closed the waiting connection from %s: %s", c.address, reason)
        with contextlib.suppress(OSError):
            c.sock.close()

    def review_candidates(self) -> Candidate | None:
        """The first candidate that showed it is a PX4, taken off the list, to replace a silent PX4 (or
        none); the rest are closed when PX4 speaks again (it was paused, not dead) or when they show no
        PX4 HEARTBEAT in time."""
        now = time.monotonic()
        if self.conn is not None and self.silence() <= LINK_SILENCE_S:
            for c in list(self.candidates):
                self.close_candidate(c, f"PX4 at {self.peer} is alive and keeps the link")
            return None
        for c in list(self.candidates):
            if not c.px4 and now - c.since > CANDIDATE_TIMEOUT_S:
                self.close_candidate(c, f"no PX4 HEARTBEAT within {CANDIDATE_TIMEOUT_S:.0f} s")
        ready = [c for c in self.candidates if c.px4]
        if not ready:
            return None
        self.candidates.remove(ready[0])
        return ready[0]
