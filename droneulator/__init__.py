"""Droneulator: a UAV simulator (RotorPy dynamics, OpenGL sensors, ROS 2 over Zenoh, PX4 SITL).

Importing the package registers the Gymnasium environment ``droneulator/VineyardNav-v0`` when
Gymnasium is installed (by name only: the environment, torch and the renderer load on ``gym.make``).
"""

import os
from importlib.util import find_spec

# numba's OpenMP threads (the physics and the ray cast) sleep between parallel regions instead of spinning:
# no slower on an idle machine, and 1.3 to 6.8 times faster with another process keeping a core busy
# (docs/rl.md, "Measured: many worlds of many agents"). Set before libgomp loads; the environment wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

if find_spec("gymnasium") is not None:
    from droneulator.workflows.rl import register_envs

    register_envs()
