"""``LVHeartEnv``: the single-member ``gymnasium.Env``, a shell over the same jitted core."""

from __future__ import annotations

from typing import Any

import gymnasium
import numpy as np

from lvenv.env.vector import LVHeartVectorEnv
from lvenv.validation import InputError, real_array

__all__ = ["LVHeartEnv"]


class LVHeartEnv(gymnasium.Env):
    """One LO heart; arguments as :class:`~lvenv.env.vector.LVHeartVectorEnv` (``num_envs`` = 1).

    Truncation comes from Gymnasium's ``TimeLimit`` (``max_episode_steps`` of the registration).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 1}

    def __init__(self, render_mode: str | None = None, **kwargs: Any):
        kwargs.setdefault("max_episode_steps", None)
        self._vec = LVHeartVectorEnv(num_envs=1, render_mode=render_mode, **kwargs)
        self.render_mode = render_mode
        self.action_space = self._vec.single_action_space
        self.observation_space = self._vec.single_observation_space
        self.action_names = self._vec.action_names
        self.obs_names = self._vec.obs_names
        self.patient = self._vec.patients[0]

    @staticmethod
    def _one(info: dict[str, Any]) -> dict[str, Any]:
        out = {k: (v[0].item() if isinstance(v[0], np.generic) else v[0]) for k, v in info.items() if not k.startswith("_") and k != "parameters"}
        out["parameters"] = {k: float(v[0]) for k, v in info["parameters"].items()}
        return out

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if seed is None:
            seed = int(self.np_random.integers(2**31 - 1))
        obs, info = self._vec.reset(seed=seed, options=options)
        return obs[0], self._one(info)

    def step(self, action):
        arr = real_array("action", action)
        if arr.shape != (len(self.action_names),):
            raise InputError(f"action has shape {arr.shape}; expected ({len(self.action_names)},) with entries {self.action_names}")
        obs, reward, terminated, truncated, info = self._vec.step(arr[None])
        return obs[0], float(reward[0]), bool(terminated[0]), bool(truncated[0]), self._one(info)

    def render(self):
        return self._vec.render()
