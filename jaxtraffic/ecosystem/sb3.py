"""``GainVectorEnv`` as a Stable-Baselines3 ``VecEnv`` (``pip install jaxtraffic[sb3]``).

SB3's ``DummyVecEnv`` steps its environments one by one in Python; ``SB3VecEnv`` hands the whole
batch to ``gym_env.GainVectorEnv``'s single jit-compiled, vmapped step and converts the result to
SB3's conventions: ``dones = terminated | truncated``, and for a finished environment
``infos[i]["terminal_observation"]`` (the last observation of the episode, from which SB3
bootstraps a truncated step) and ``infos[i]["TimeLimit.truncated"]``. Wrap it in SB3's
``VecMonitor`` for episode statistics (``ep_rew_mean``). See ``examples/sb3_ppo.py``.

    from jaxtraffic.ecosystem.sb3 import SB3VecEnv
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import VecMonitor
    venv = VecMonitor(SB3VecEnv(num_envs=64, n_points=51, horizon_s=10))
    PPO("MlpPolicy", venv, n_steps=100).learn(100_000)
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium.vector import AutoresetMode
from stable_baselines3.common.vec_env.base_vec_env import VecEnv

from jaxtraffic.ecosystem.gym_env import GainVectorEnv

__all__ = ["SB3VecEnv"]


class SB3VecEnv(VecEnv):
    """SB3 ``VecEnv`` over ``GainVectorEnv`` (``venv``, or one built from ``num_envs`` and ``config``, e.g.
    ``render_mode="rgb_array"``), which must reset finished environments within the step (``SAME_STEP``)."""

    def __init__(self, venv: GainVectorEnv | None = None, num_envs: int = 16, **config: Any):
        if venv is None:
            venv = GainVectorEnv(num_envs, autoreset_mode=AutoresetMode.SAME_STEP, **config)
        if venv.metadata["autoreset_mode"] != AutoresetMode.SAME_STEP:
            raise ValueError("SB3VecEnv needs a GainVectorEnv with autoreset_mode=SAME_STEP (SB3 resets in the step)")
        self.venv = venv
        self.render_mode = venv.render_mode
        super().__init__(self.venv.num_envs, self.venv.single_observation_space, self.venv.single_action_space)
        self._actions: np.ndarray | None = None

    def reset(self) -> np.ndarray:
        seed = self._seeds[0]  # one JAX key drives the whole batch: the first environment's seed
        obs, _ = self.venv.reset(seed=seed)
        self._reset_seeds()
        self._reset_options()
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = actions

    def step_wait(self):
        obs, rewards, term, trunc, info = self.venv.step(self._actions)
        dones = term | trunc
        infos: list[dict[str, Any]] = [{} for _ in range(self.num_envs)]
        for i in np.flatnonzero(dones):
            infos[i] = {"terminal_observation": info["final_obs"][i],
                        "TimeLimit.truncated": bool(trunc[i] and not term[i])}
        return obs, rewards, dones, infos

    def close(self) -> None:
        self.venv.close()

    def get_images(self) -> list[np.ndarray | None]:
        """One space-time picture per environment (``render_mode="rgb_array"``; SB3's ``render``)."""
        images = self.venv.render()
        return [None] * self.num_envs if images is None else list(images)

    def _count(self, indices) -> int:
        return len(list(self._get_indices(indices)))

    def get_attr(self, attr_name: str, indices=None) -> list[Any]:
        value = self.render_mode if attr_name == "render_mode" else getattr(self.venv, attr_name)
        return [value] * self._count(indices)

    def set_attr(self, attr_name: str, value: Any, indices=None) -> None:
        setattr(self.venv, attr_name, value)

    def env_method(self, method_name: str, *method_args, indices=None, **method_kwargs) -> list[Any]:
        return [getattr(self.venv, method_name)(*method_args, **method_kwargs)] * self._count(indices)

    def env_is_wrapped(self, wrapper_class, indices=None) -> list[bool]:
        return [False] * self._count(indices)
