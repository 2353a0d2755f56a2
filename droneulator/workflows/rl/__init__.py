"""Workflow 3 (paper §III-C): reinforcement learning of vineyard navigation from a depth strip.

* :mod:`.env` is the Gymnasium environment ``droneulator/VineyardNav-v0`` (registered on import),
  stepping the in-process simulator in lockstep, one step per camera frame;
* :mod:`.remote` is the same environment driving a running ``droneulator run`` over WebSocket and Zenoh;
* :mod:`.astar` holds the occupancy grid, A* and the per-episode goal distance field of the reward;
* :mod:`.train` and :mod:`.evaluate` train Stable-Baselines3 SAC and evaluate it with the paper's figures
  (optional extra ``droneulator[rl]``).
"""

ENV_ID = "droneulator/VineyardNav-v0"

try:  # droneulator.config imports .config from here: the core must load without the rl extra
    from gymnasium.envs.registration import register, registry
except ModuleNotFoundError:
    pass
else:
    if ENV_ID not in registry:
        register(id=ENV_ID, entry_point="droneulator.workflows.rl.env:VineyardNavEnv")

__all__ = ["ENV_ID"]
