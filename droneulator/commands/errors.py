"""What a refused command is: :class:`CommandError` with a machine-readable code from :data:`ERROR_CODES`.

The core (a vehicle refusing a goto below the ground), the command path (a flight locked by PX4) and
the transports (a WebSocket message that is not JSON) all answer with these codes, listed once here
and rendered into docs/api.md.
"""

from __future__ import annotations

#: every error code a reply can carry, with when it happens (rendered into docs/api.md)
ERROR_CODES: dict[str, str] = {
    "parse_error": "the message is not valid UTF-8 JSON (this includes binary frames holding anything else)",
    "invalid_request": "the JSON is not an object, `op` is missing or not a string, or `id` is neither "
    "an integer nor a string",
    "unknown_op": "`op` names no operation; the message lists the known ones",
    "invalid_argument": "a required field is missing, a field is not accepted by the op, a value has the "
    "wrong type (`true`/`false` are not numbers), or a number is `NaN`, `Infinity` or `-Infinity`",
    "out_of_range": "a number lies outside its allowed range (speed, duration, velocity limits, seed, "
    "rate_hz); the message gives the range",
    "below_ground": "a target altitude is not above the ground (z <= 0; a reset position may be z = 0)",
    "out_of_bounds": "a target lies outside the scene's flyable bounds (see `scene_info`)",
    "not_airborne": "`velocity`, `track`, `hold` or `land` while the motors are off: take off first",
    "crashed": "a flight command for a vehicle that crashed (contact model `crash`, docs/contact.md): "
    "its rotors stay stopped until a `reset` places it again",
    "flight_locked": "flight commands are refused because another controller (e.g. PX4) is in control; "
    "the message says why",
    "message_too_large": "the message is longer than the server's limit (64 KiB by default); it is "
    "discarded unread, so the reply's `id` is null",
    "unsupported": "`subscribe`/`unsubscribe` sent to a transport without streams (in-process use of "
    "`handle_request`; the WebSocket server always supports them), or `trigger` while the cameras shoot "
    "at their rate (`render.camera_trigger=rate`, the default)",
    "tank_empty": "`spray` on while the vehicle's spray tank is empty (refill with `spray_refill`); the "
    "flight goes on",
    "no_spray_system": "a spray op for a vehicle without a spray system (no `spray` section, or not "
    "running with spraying on)",
    "unauthorized": "the server asks for its access token (it is bound beyond loopback, or given one) "
    "and the connection's URL did not carry it (`?token=...`, docs/security.md): this is the only "
    "message the connection gets, `id` null, then it is closed (code 1008)",
    "rate_limited": "the connection sent more messages than the server's rate limit "
    "(`access.rate_hz` a second, `access.burst` at once); the message was not run, and the connection "
    "stays usable",
    "link_cut": "a flight command to a vehicle whose command link is cut (a `link_cut` fault, "
    "docs/faults.md): it was not delivered, as over a lost radio link; a command stream stops, so the "
    "vehicle holds after its stream timeout",
    "internal_error": "an unexpected failure inside the server; the message says what, the server "
    "keeps running and the traceback is logged",
}


class CommandError(ValueError):
    """A rejected command; ``code`` is one of :data:`ERROR_CODES`, the message says what to fix."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(f"{code}: {message}")
        self.code = code
        self.message = message
