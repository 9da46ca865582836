"""``LVHeartVectorEnv``: N LO hearts stepped as one jitted, vmapped-by-layout batch (DESIGN §2).

A thin stateful shell around :mod:`lvenv.env.core`: the pure ``reset``/``step`` are jitted once
(per static configuration, shared by all instances); a step is one device call plus one
transfer of its results. Members may hold
different patients (``patient=[...]``), so one env can fit a cohort. Batches are padded to a
multiple of the device count and sharded over the CPU cores or GPUs (:mod:`lvenv.devices`).
"""

from __future__ import annotations

import collections
import functools
from typing import Any, Sequence

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
from gymnasium.vector import AutoresetMode
from gymnasium.vector.utils import batch_space

from lvenv.devices import shard_members
from lvenv.env import core
from lvenv.env.spaces import ActionMap, observation_space
from lvenv.identification import DEFAULT_ACTION_PARAMS
from lvenv.patients import OBS_NAMES, Patient, resolve
from lvenv.simulation import STATUS

__all__ = ["LVHeartVectorEnv", "status_names", "TRACES"]

#: Traces of the jitted reset/step per static configuration. Jitting once at module level lets
#: every env with the same configuration and size share one compiled step.
TRACES: collections.Counter = collections.Counter()


def _counted(fn):
    @functools.wraps(fn)
    def traced(*args, config):
        TRACES[config] += 1  # runs only while JAX traces
        return fn(*args, config=config)

    return traced


_reset_jit = jax.jit(_counted(core.reset), static_argnames="config")
_step_jit = jax.jit(_counted(core.step), static_argnames="config")


def status_names(codes: np.ndarray) -> np.ndarray:
    """Status codes → strings (:data:`lvenv.STATUS`, plus ``"invalid_action"``)."""
    names = {i: s for i, s in enumerate(STATUS)} | {core.INVALID_ACTION: "invalid_action"}
    return np.array([names[int(c)] for c in np.ravel(codes)]).reshape(np.shape(codes))


class LVHeartVectorEnv(gymnasium.vector.VectorEnv):
    """Vectorised ``lvenv/LVHeart-v0``; see :mod:`lvenv.env.core` for dynamics and reward.

    Args:
        num_envs: members N.
        patient: built-in name, :class:`~lvenv.patients.Patient`, record dict, or a list with one
            per member.
        action_params: names of the parameters under identification (default τ2, Sa, R2, R3, C, Cat).
        action_mode: ``"physical"`` (bounds of :mod:`lvenv.identification`) or ``"normalized"`` ([−1, 1]).
        max_episode_steps: truncation (``None``: never).
        tolerance: terminate when the mean relative mismatch falls below it.
        obs_noise: relative standard deviation of Gaussian measurement noise (scalar or per
            observation); drawn from the env's own key.
        steps_per_beat, max_beats, rtol: LO-heart integration (:func:`lvenv.simulate`).
        autoreset_mode: ``NEXT_STEP`` (default) or ``DISABLED`` (every step evaluates every
            member's action; what optimisers use).
    """

    metadata = {"autoreset_mode": AutoresetMode.NEXT_STEP, "render_modes": ["rgb_array"], "render_fps": 1}

    def __init__(
        self,
        num_envs: int = 1,
        patient: str | Patient | dict | Sequence = "normal",
        action_params: Sequence[str] = DEFAULT_ACTION_PARAMS,
        action_mode: str = "physical",
        max_episode_steps: int | None = 200,
        tolerance: float = 1e-3,
        obs_noise: float | Sequence[float] = 0.0,
        steps_per_beat: int = 1000,
        max_beats: int = 60,
        rtol: float = 1e-4,
        render_mode: str | None = None,
        autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP,
    ):
        if num_envs < 1:
            raise ValueError(f"num_envs = {num_envs} must be ≥ 1")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode = {render_mode!r}; supported: None, 'rgb_array'")
        autoreset_mode = AutoresetMode(autoreset_mode)
        if autoreset_mode not in (AutoresetMode.NEXT_STEP, AutoresetMode.DISABLED):
            raise ValueError(f"autoreset_mode = {autoreset_mode.value!r}; supported: NextStep, Disabled")
        self.metadata = {**self.metadata, "autoreset_mode": autoreset_mode}
        noise = np.broadcast_to(np.asarray(obs_noise, float), (len(OBS_NAMES),))
        if np.any(~np.isfinite(noise) | (noise < 0)):
            raise ValueError(f"obs_noise = {obs_noise!r} must be finite and ≥ 0")
        self.num_envs = num_envs
        self.render_mode = render_mode
        self.patients = resolve(patient, num_envs)
        self.config = core.Config(
            actions=ActionMap(tuple(action_params), action_mode), steps_per_beat=steps_per_beat, max_beats=max_beats,
            rtol=rtol, tolerance=tolerance, max_episode_steps=max_episode_steps,
            obs_noise=tuple(map(float, noise)) if np.any(noise > 0) else None,
            autoreset=autoreset_mode == AutoresetMode.NEXT_STEP,
        )
        self.single_action_space = self.config.actions.space()
        self.action_space = batch_space(self.single_action_space, num_envs)
        self.single_observation_space = observation_space()
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_names = self.config.actions.names
        self.obs_names = OBS_NAMES
        self._params, self._padded = shard_members(core.env_params(self.patients), num_envs)
        self._state: core.EnvState | None = None
        self._parameters: np.ndarray | None = None  # (num_envs, k) action parameters of the last step

    @property
    def trace_count(self) -> int:
        """How often the jitted reset/step were traced for this env's configuration (all instances)."""
        return TRACES[self.config]

    def _reset(self, params, key):
        return _reset_jit(params, key, config=self.config)

    def _step(self, state, action, params):
        return _step_jit(state, action, params, config=self.config)

    def _info(self, raw: dict[str, Any]) -> dict[str, Any]:
        metrics = np.asarray(raw["metrics"])[: self.num_envs]
        info: dict[str, Any] = {name: metrics[:, i] for i, name in enumerate(OBS_NAMES)}
        info["status"] = status_names(np.asarray(raw["status"])[: self.num_envs])
        for key in ("converged", "beats", "mismatch", "clipped", "reset"):
            if key in raw:
                info[key] = np.asarray(raw[key])[: self.num_envs]
        info["parameters"] = dict(zip(self.action_names, np.asarray(raw["parameters"])[: self.num_envs].T))
        for key in list(info):
            if key != "parameters":
                info["_" + key] = np.ones(self.num_envs, bool)
        return info

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Reset every member: its patient's own parameters simulated to steady state from a cold start."""
        super().reset(seed=seed)
        if seed is None:
            seed = int(self.np_random.integers(2**31 - 1))
        state, obs, info = self._reset(self._params, jax.random.PRNGKey(seed))
        self._state = state
        obs, info = jax.device_get((obs, info))
        self._parameters = np.asarray(info["parameters"])[: self.num_envs]
        return np.asarray(obs)[: self.num_envs], self._info(info)

    def step(self, actions):
        if self._state is None:
            raise gymnasium.error.ResetNeeded("call reset() before step()")
        actions = np.asarray(actions, dtype=np.float64).reshape(self.num_envs, len(self.action_names))
        actions, _ = shard_members(actions, self.num_envs, batch_axis_of=lambda leaf: 0)
        state, obs, reward, terminated, truncated, info = self._step(self._state, actions, self._params)
        self._state = state
        obs, reward, terminated, truncated, info = jax.device_get((obs, reward, terminated, truncated, info))
        n = self.num_envs
        self._parameters = np.asarray(info["parameters"])[:n]
        return np.asarray(obs)[:n], np.asarray(reward)[:n], np.asarray(terminated)[:n], np.asarray(truncated)[:n], self._info(info)

    def member_heart(self, i: int):
        """Member i's Heart at its current parameters (host-side, for plotting or re-simulation)."""
        if self._parameters is None:
            return self.patients[i].heart
        return self.patients[i].heart.replace(**{k: float(v) for k, v in zip(self.action_names, self._parameters[i])})

    def member_state(self, i: int) -> np.ndarray:
        """Member i's LO-heart state (9,) at the end of its last step."""
        return np.asarray(jax.device_get(self._state.y))[:, i]

    def render(self):
        """``rgb_array``: PV loop and P/V traces of member 0 at its current parameters."""
        if self.render_mode != "rgb_array" or self._state is None:
            return None
        from lvenv.env.render import pv_image

        return pv_image(self.member_heart(0), self.member_state(0), self.patients[0], self.config.steps_per_beat)
