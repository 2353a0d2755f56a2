"""Workflow 3 (paper §III-C): reinforcement learning of vineyard navigation from a depth strip.

* :mod:`.env` is the Gymnasium environment ``droneulator/VineyardNav-v0``, stepping the in-process
  simulator in lockstep, one step per camera frame;
* :mod:`.multi` is the PettingZoo parallel environment ``droneulator_vineyard_nav_v0``: the same task
  for N vehicles sharing one world;
* :mod:`.remote` is the same environment driving a running ``droneulator run`` over WebSocket and Zenoh;
* :mod:`.backend` holds what both share (scene, camera, the state an observation needs);
* :mod:`.astar` holds the occupancy grid, A* and the per-episode goal distance field of the reward;
* :mod:`.train` and :mod:`.evaluate` train Stable-Baselines3 SAC and evaluate it with the paper's figures
  (optional extra ``droneulator[rl]``).

The environment id is registered by ``import droneulator`` whenever Gymnasium is installed, with an
entry-point string, so registering imports neither the environment nor its dependencies.
"""

from __future__ import annotations

ENV_ID = "droneulator/VineyardNav-v0"
ENTRY_POINT = "droneulator.workflows.rl.env:VineyardNavEnv"
VECTOR_ENTRY_POINT = "droneulator.workflows.rl.vector:VineyardNavVectorEnv"


def register_envs() -> bool:
    """Register :data:`ENV_ID` with Gymnasium (idempotent); False when Gymnasium is not installed."""
    try:
        from gymnasium.envs.registration import register, registry
    except ImportError:
        return False
    if ENV_ID not in registry:
        register(id=ENV_ID, entry_point=ENTRY_POINT, vector_entry_point=VECTOR_ENTRY_POINT)
    return True


register_envs()

__all__ = ["ENTRY_POINT", "ENV_ID", "VECTOR_ENTRY_POINT", "register_envs"]
