"""The WebSocket command protocol: one JSON request in, one JSON reply out.

A request is a JSON object ``{"id": 7, "op": "goto", "position": [3, 0, 2]}``; the reply echoes
``id`` and is either ``{"id": 7, "ok": true, "result": {...}}`` or
``{"id": 7, "ok": false, "error": {"code": "...", "message": "..."}}``.

This module is the wire format only: JSON in (:func:`parse_request`) and out (:func:`encode`). What the
ops are, how their fields are checked and what they run is :mod:`droneulator.commands`, shared with
every other command source. Nothing here imports the simulator, so clients can import it cheaply.
"""

from __future__ import annotations

import json
from collections.abc import Collection, Mapping
from typing import TYPE_CHECKING, Any

from droneulator.commands.errors import ERROR_CODES, CommandError
from droneulator.commands.ops import (
    ALL_VEHICLES,
    OPS,
    STREAMS,
    ExtraOp,
    Request,
    RequestError,
    encode,
    error_reply,
    execute,
    make_request,
    ok_reply,
    ops_markdown,
)

if TYPE_CHECKING:
    from droneulator.world import World

#: what a client catches for an ``ok: false`` reply: the command path's error, by the name clients know
ApiError = CommandError

__all__ = [
    "ALL_VEHICLES",
    "ERROR_CODES",
    "OPS",
    "STREAMS",
    "ApiError",
    "ExtraOp",
    "Request",
    "RequestError",
    "decode",
    "encode",
    "error_reply",
    "handle_request",
    "make_request",
    "ok_reply",
    "ops_markdown",
    "parse_request",
]


def decode(raw: str | bytes) -> Any:
    """Parse one message (text, or UTF-8 bytes from a binary frame); errors are ``parse_error``."""
    try:
        text = raw.decode("utf-8") if isinstance(raw, (bytes, bytearray, memoryview)) else raw
        return json.loads(text)
    except UnicodeDecodeError as e:
        raise RequestError(
            "parse_error", f"message is not UTF-8 text: {e.reason} at byte {e.start}"
        ) from None
    except RecursionError:
        raise RequestError("parse_error", "message is nested too deeply") from None
    except ValueError as e:  # JSONDecodeError, or an integer literal too long to convert
        raise RequestError("parse_error", f"message is not valid JSON: {e}") from None
    except TypeError:
        raise RequestError(
            "parse_error", f"a message must be text or bytes, got {type(raw).__name__}"
        ) from None


def parse_request(raw: str | bytes, extra_ops: Collection[str] = ()) -> Request:
    """Decode and validate one request; raises :class:`RequestError` carrying the id to echo."""
    msg = decode(raw)
    if not isinstance(msg, dict):
        raise RequestError("invalid_request", f"a request must be a JSON object, got {type(msg).__name__}")
    rid = msg.get("id")
    if isinstance(rid, bool) or not (rid is None or isinstance(rid, (int, str))):
        raise RequestError("invalid_request", "`id` must be an integer or a string")
    op = msg.get("op")
    if op is None:
        raise RequestError("invalid_request", "missing `op`", rid)
    if not isinstance(op, str):
        raise RequestError("invalid_request", "`op` must be a string", rid)
    return make_request(op, {k: v for k, v in msg.items() if k not in ("id", "op")}, rid, extra_ops)


def handle_request(
    sim: World | None,
    raw: str | bytes,
    extra_ops: Mapping[str, ExtraOp] | None = None,
    flight_locked: str | None = None,
) -> dict[str, Any]:
    """Parse, validate and execute one raw request; returns the reply and never raises."""
    try:
        request = parse_request(raw, extra_ops or ())
    except RequestError as e:
        return error_reply(e.request_id, e.code, e.message)
    return execute(sim, request, extra_ops, flight_locked)
