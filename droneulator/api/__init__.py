"""WebSocket command API: a JSON protocol (:mod:`.protocol`), its server (:mod:`.server`, run inside
the dynamics process) and a synchronous client (:mod:`.client`). See docs/api.md.

Importing this package does not import the simulator, so clients stay light.
"""

from droneulator.api.client import ConnectionLostError, DroneulatorClient
from droneulator.api.protocol import ERROR_CODES, OPS, ApiError, handle_request
from droneulator.api.server import ApiServer
from droneulator.commands import CommandPath

__all__ = [
    "ERROR_CODES",
    "OPS",
    "ApiError",
    "ApiServer",
    "CommandPath",
    "ConnectionLostError",
    "DroneulatorClient",
    "handle_request",
]
