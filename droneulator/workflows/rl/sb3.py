"""The native vector env as a Stable-Baselines3 ``VecEnv`` (:class:`SB3VectorEnv`).

SB3 has its own vector API (``step_async``/``step_wait``, one ``dones`` array, a list of info dicts with
``terminal_observation`` and ``TimeLimit.truncated``, autoreset in the same step). This adapter drives a
:class:`~droneulator.workflows.rl.vector.VineyardNavVectorEnv` in Gymnasium's ``SAME_STEP`` autoreset
mode, which is that contract, so no environment is copied or run in a subprocess.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from gymnasium.vector import AutoresetMode
from stable_baselines3.common.vec_env import VecEnv

from droneulator.workflows.rl.vector import VineyardNavVectorEnv

#: info keys copied into SB3's per-env info dicts (what VecMonitor and the callbacks read)
INFO_KEYS = ("is_success", "termination", "goal_distance")


class SB3VectorEnv(VecEnv):
    """``env`` (a :class:`VineyardNavVectorEnv` in ``SAME_STEP`` autoreset mode) seen as an SB3 VecEnv."""

    def __init__(self, env: VineyardNavVectorEnv) -> None:
        if env.autoreset_mode != AutoresetMode.SAME_STEP:
            raise ValueError("SB3 needs the vector env in SAME_STEP autoreset mode")
        self.env = env
        super().__init__(env.num_envs, env.single_observation_space, env.single_action_space)
        self._actions: np.ndarray | None = None

    def reset(self) -> np.ndarray:
        seeds = list(self._seeds)
        seed = None if all(s is None for s in seeds) else seeds
        obs, _ = self.env.reset(seed=seed, options=self._options[0] or None)
        self._reset_seeds()
        self._reset_options()
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = np.asarray(actions, dtype=np.float32).reshape(self.num_envs, -1)

    def step_wait(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[dict[str, Any]]]:
        assert self._actions is not None, "step_async first"
        obs, reward, term, trunc, info = self.env.step(self._actions)
        dones = term | trunc
        source = info.get("final_info", info)
        infos: list[dict[str, Any]] = []
        for i in range(self.num_envs):
            item = {key: (source if dones[i] else info)[key][i] for key in INFO_KEYS}
            if dones[i]:
                item["terminal_observation"] = info["final_obs"][i]
                item["TimeLimit.truncated"] = bool(trunc[i] and not term[i])
            infos.append(item)
        return obs, reward.astype(np.float32), dones, infos

    def close(self) -> None:
        self.env.close()

    def get_attr(self, attr_name: str, indices: Any = None) -> list[Any]:
        return [getattr(self.env, attr_name) for _ in self._get_indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: Any = None) -> None:
        setattr(self.env, attr_name, value)

    def env_method(self, method_name: str, *args: Any, indices: Any = None, **kwargs: Any) -> list[Any]:
        return [getattr(self.env, method_name)(*args, **kwargs) for _ in self._get_indices(indices)]

    def env_is_wrapped(self, wrapper_class: type, indices: Any = None) -> list[bool]:
        return [False for _ in self._get_indices(indices)]

    def _get_indices(self, indices: Any) -> Sequence[int]:
        if indices is None:
            return range(self.num_envs)
        return [indices] if isinstance(indices, int) else list(indices)
