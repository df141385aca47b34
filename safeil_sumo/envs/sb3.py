"""Stable-Baselines3 on the native vector env (the ``rl`` extra: ``pip install -e ".[rl]"``).

SB3 has its own ``VecEnv`` API with SAME-step autoreset (the new episode's first observation is
returned with ``done``), while :class:`~safeil_sumo.envs.vector.SafeILVectorEnv` restarts a
sub-env on the NEXT step (its vehicles enter SUMO during a step: see ``ClosedLoop.restart``).
:class:`SB3VecEnv` passes the terminal observation both as ``infos[i]["terminal_observation"]``
and as the observation SB3 starts the next episode from; the step after, the sub-env's action
is ignored and it returns the new episode's first observation with reward 0: one filler
transition per episode, which SB3 sees as the first of the new episode.

    from stable_baselines3 import PPO
    venv = gym.make_vec("safeil_sumo/Curved500-v0", num_envs=16,
                        vectorization_mode="vector_entry_point", action_level="control")
    PPO("MlpPolicy", SB3VecEnv(venv)).learn(4096)
"""

from __future__ import annotations

import numpy as np
from stable_baselines3.common.vec_env import VecEnv


class SB3VecEnv(VecEnv):
    """A Gymnasium 1.x ``VectorEnv`` with NEXT_STEP autoreset as an SB3 ``VecEnv``."""

    def __init__(self, venv) -> None:
        self.venv = venv
        super().__init__(venv.num_envs, venv.single_observation_space,
                         venv.single_action_space)
        self._actions: np.ndarray | None = None

    def reset(self):
        seed = self._seeds[0] if self._seeds and self._seeds[0] is not None else None
        obs, _ = self.venv.reset(seed=seed)
        self._reset_seeds()
        self._reset_options()
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = np.asarray(actions)

    def step_wait(self):
        obs, rewards, terminated, truncated, _ = self.venv.step(self._actions)
        dones = terminated | truncated
        infos: list[dict] = [{} for _ in range(self.num_envs)]
        for i in np.flatnonzero(dones):
            infos[i]["terminal_observation"] = obs[i].copy()
            infos[i]["TimeLimit.truncated"] = bool(truncated[i] and not terminated[i])
        return obs, rewards.astype(np.float32), dones, infos

    def close(self) -> None:
        self.venv.close()

    def get_attr(self, attr_name: str, indices=None) -> list:
        return [getattr(self.venv, attr_name)] * len(list(self._get_indices(indices)))

    def set_attr(self, attr_name: str, value, indices=None) -> None:
        setattr(self.venv, attr_name, value)

    def env_method(self, method_name: str, *method_args, indices=None, **method_kwargs) -> list:
        method = getattr(self.venv, method_name)
        return [method(*method_args, **method_kwargs)
                for _ in self._get_indices(indices)]

    def env_is_wrapped(self, wrapper_class, indices=None) -> list[bool]:
        return [False] * len(list(self._get_indices(indices)))
