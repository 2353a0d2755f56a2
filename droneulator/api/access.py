"""Who may use the WebSocket servers (the API and the UI's ``/ws``), over what, and how fast.

* **Token.** A server bound beyond loopback (``0.0.0.0``, a LAN address) only serves clients that give
  its token, as the ``token`` query parameter of the WebSocket URL (``ws://host:8765/?token=T``): a query
  parameter because a browser's ``WebSocket`` cannot set headers, and because the check then happens
  before the connection reads a single request. A client without it, or with another, gets one
  ``unauthorized`` error reply and the connection closes (code 1008): no state, no images, no
  subscriptions. On loopback the token is asked for only when one is configured.
* **TLS.** With ``access.tls_cert`` and ``access.tls_key`` (PEM files) the servers speak ``wss://``
  (and the UI ``https://``), with Python's :mod:`ssl`.
* **Rate limit.** Each connection has a token bucket (``access.rate_hz`` sustained, ``access.burst`` at
  once); a message past it is answered ``rate_limited`` and not run, so a flooding client cannot queue
  work in front of the others.

See docs/security.md.
"""

from __future__ import annotations

import hmac
import ipaddress
import secrets
import ssl
import time
from urllib.parse import parse_qsl, urlencode, urlsplit, urlunsplit

#: the query parameter of the WebSocket URL that carries the token
TOKEN_PARAM = "token"
#: WebSocket close code after an ``unauthorized`` reply (policy violation)
UNAUTHORIZED_CLOSE = 1008


def is_loopback(host: str) -> bool:
    """True for an address only this machine reaches (127.0.0.0/8, ::1, ``localhost``); False for every
    interface (``0.0.0.0``, ``::``, ``""``), a LAN address or any other name."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def generate_token() -> str:
    """A new random token (32 URL-safe characters, 192 bits)."""
    return secrets.token_urlsafe(24)


def needs_token(host: str, token: str | None) -> bool:
    """Whether a server on ``host`` with configured ``token`` must ask clients for one."""
    return token is not None or not is_loopback(host)


def url_token(path: str) -> str | None:
    """The token of a request path or URL (``/?token=T``), None when it carries none."""
    for key, value in parse_qsl(urlsplit(path).query, keep_blank_values=True):
        if key == TOKEN_PARAM:
            return value
    return None


def token_matches(expected: str, given: str | None) -> bool:
    """``given`` is ``expected``, compared in constant time."""
    return given is not None and hmac.compare_digest(expected.encode(), given.encode())


def with_token(url: str, token: str | None) -> str:
    """``url`` with ``token`` as its ``token`` query parameter (replacing one there); unchanged for None."""
    if token is None:
        return url
    parts = urlsplit(url)
    query = [(k, v) for k, v in parse_qsl(parts.query, keep_blank_values=True) if k != TOKEN_PARAM]
    query.append((TOKEN_PARAM, token))
    return urlunsplit(parts._replace(path=parts.path or "/", query=urlencode(query)))


def without_token(url: str) -> str:
    """``url`` with its token replaced by ``***``, for logs and error messages."""
    if url_token(url) is None:
        return url
    parts = urlsplit(url)
    query = [(k, "***" if k == TOKEN_PARAM else v) for k, v in parse_qsl(parts.query, keep_blank_values=True)]
    return urlunsplit(parts._replace(query=urlencode(query, safe="*")))


def server_ssl_context(cert: str | None, key: str | None) -> ssl.SSLContext | None:
    """A TLS server context from PEM ``cert`` (chain) and ``key``; None when neither is given.

    It sends no TLS 1.3 session tickets. A ticket arrives after the handshake, so a client that reads
    in one thread while it writes its first request in another (websockets' sync client, ours) has
    OpenSSL process it in ``SSL_read`` during an ``SSL_write`` on the same connection, which OpenSSL
    does not support: about one handshake in 400 with two cores busy hung until its timeout (or
    failed with an internal SSL error). Without tickets nothing but the server's replies reaches the
    client; the cost is no session resumption, a full handshake per connection.
    """
    if cert is None and key is None:
        return None
    if cert is None or key is None:
        raise ValueError("TLS needs both access.tls_cert and access.tls_key")
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    ctx.num_tickets = 0
    ctx.load_cert_chain(cert, key)
    return ctx


def client_ssl_context(url: str, cafile: str | None = None) -> ssl.SSLContext | None:
    """For a ``wss://`` URL: the default verifying context, trusting ``cafile`` (a self-signed
    certificate, say) besides the system's; None for ``ws://``."""
    if not url.startswith("wss://"):
        return None
    return ssl.create_default_context(cafile=cafile)


class TokenBucket:
    """``rate`` tokens a second up to ``burst``; each message takes one (``take`` False: over the limit)."""

    def __init__(self, rate: float, burst: int) -> None:
        if not rate > 0 or burst < 1:
            raise ValueError(f"a rate limit needs rate > 0 and burst >= 1, got {rate}, {burst}")
        self.rate = float(rate)
        self.burst = float(burst)
        self.tokens = float(burst)
        self.stamp = time.monotonic()
        #: messages refused so far
        self.refused = 0

    def take(self, now: float | None = None) -> bool:
        now = time.monotonic() if now is None else now
        self.tokens = min(self.burst, self.tokens + max(0.0, now - self.stamp) * self.rate)
        self.stamp = max(self.stamp, now)
        if self.tokens >= 1.0:
            self.tokens -= 1.0
            return True
        self.refused += 1
        return False
