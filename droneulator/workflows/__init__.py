"""User-level workflows.

``photogrammetry/`` (capture, COLMAP), ``rl/`` (Gymnasium environment, SAC) and the demo client
(``droneulator run --demo``) work on the running simulator's public interfaces only (WebSocket API,
ROS 2 topics); ``demo`` and ``snapshot`` drive an in-process :class:`~droneulator.world.World` (``demo``
flies its first vehicle, ``world.vehicle()``).
"""
