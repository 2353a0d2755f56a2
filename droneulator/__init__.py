"""Droneulator: a UAV simulator (RotorPy dynamics, OpenGL sensors, ROS 2 over Zenoh, PX4 SITL).

Importing the package registers the Gymnasium environment ``droneulator/VineyardNav-v0`` when
Gymnasium is installed (by name only: the environment, torch and the renderer load on ``gym.make``).
"""

from importlib.util import find_spec

from droneulator.threads import sleeping_openmp_threads

sleeping_openmp_threads()  # before any parallel kernel loads libgomp

if find_spec("gymnasium") is not None:
    from droneulator.workflows.rl import register_envs

    register_envs()
