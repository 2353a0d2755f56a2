"""The command path: what every command source (WebSocket, ROS, the planner, the UI, PX4's ownership)
shares. :mod:`.errors` says what a refusal is, :mod:`.ops` what each command is (fields, rules, what it
runs; docs/api.md is generated from it), :mod:`.path` how one reaches the simulator (validation, the
flight lock, the simulation lock, rejections logged once per burst). Nothing here imports the simulator,
so the transports and clients can use it cheaply.
"""

from droneulator.commands.errors import ERROR_CODES, CommandError
from droneulator.commands.ops import OPS, Request, RequestError, execute, make_request
from droneulator.commands.path import CommandPath

__all__ = [
    "ERROR_CODES",
    "OPS",
    "CommandError",
    "CommandPath",
    "Request",
    "RequestError",
    "execute",
    "make_request",
]
