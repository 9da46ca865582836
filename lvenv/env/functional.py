"""The heart as pure JAX functions, gymnax style: ``reset(key, params)`` and ``step(key, state, action, params)``.

For JAX RL code that jits and vmaps the environment itself (no Gymnasium object, no host
round-trip)::

    from lvenv.env.functional import LVHeart

    env = LVHeart(steps_per_beat=500)                    # static settings
    params = env.params("heart_failure")                 # one member's patient (a PyTree)
    obs, state = jax.jit(env.reset)(key, params)
    obs, state, reward, done, info = jax.jit(env.step)(key, state, action, params)

    batch = env.params(["normal", "heart_failure"])      # or stack patients: leading axis = members
    obs, state = jax.vmap(env.reset)(keys, batch)        # vmap over members, patients, keys

The functions act on **one** member (``action`` of shape ``(k,)``, observation of shape
``(n_obs,)``) and are the same code as the Gymnasium environments (:mod:`lvenv.env.core`,
applied to a batch of one), so results agree with ``gymnasium.make_vec("lvenv/LVHeart-v0")``.
``done`` = terminated or truncated; there is no autoreset (call ``reset`` yourself).
``info`` holds ``metrics`` (NaN if the member failed), ``status`` (an :mod:`lvenv.status` code),
``mismatch``, ``converged``, ``beats``, ``clipped``, ``terminated``, ``truncated`` and
``parameters`` (the action parameters in physical units).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp

from lvenv.env import core
from lvenv.env.spaces import ActionMap, NamedBox, observation_space
from lvenv.identification import DEFAULT_ACTION_PARAMS
from lvenv.patients import resolve
from lvenv.plausibility import Band
from lvenv.plausibility import resolve as resolve_bands
from lvenv.simulation import DEFAULT_STEP_TOL, check_settings
from lvenv.validation import integer, real

__all__ = ["LVHeart"]


def _add_member_axis(tree):
    """Leaves of one member → a batch of one (batch-last: a trailing axis of size 1)."""
    return jax.tree.map(lambda x: jnp.asarray(x)[..., None], tree)


def _drop_member_axis(tree):
    return jax.tree.map(lambda x: x[..., 0], tree)


@dataclasses.dataclass(frozen=True)
class LVHeart:
    """Static settings of the functional environment (hashable: pass it to ``jit`` freely)."""

    action_params: tuple[str, ...] = DEFAULT_ACTION_PARAMS
    action_mode: str = "physical"
    steps_per_beat: int = 1000
    max_beats: int = 60
    rtol: float = 1e-4
    scheme: str = core.ENV_SCHEME
    step_tol: float = DEFAULT_STEP_TOL
    acceleration: str = core.ENV_ACCELERATION
    tolerance: float = 1e-3
    max_episode_steps: int | None = None
    obs_noise: float = 0.0
    plausibility: bool | tuple[Band, ...] = True  # the reward's bands (lvenv.plausibility.resolve)
    volume_trace: bool = False  # record the volume-trace frames (lvenv.env.core.Config)

    def __post_init__(self) -> None:
        settings = check_settings(steps_per_beat=self.steps_per_beat, max_beats=self.max_beats, rtol=self.rtol, scheme=self.scheme, step_tol=self.step_tol,
                                  acceleration=self.acceleration)
        del settings["beats"]  # the rest are Config fields
        max_steps = None if self.max_episode_steps is None else integer("max_episode_steps", self.max_episode_steps, 1)
        actions = ActionMap(self.action_params, self.action_mode)
        object.__setattr__(self, "action_params", actions.names)
        object.__setattr__(self, "_config", core.Config(
            actions=actions, **settings, tolerance=real("tolerance", self.tolerance, 0.0), max_episode_steps=max_steps,
            obs_noise=None if real("obs_noise", self.obs_noise, 0.0) == 0.0 else (float(self.obs_noise),) * len(observation_space().names),
            autoreset=False, plausibility=resolve_bands(self.plausibility), volume_trace=bool(self.volume_trace),
        ))

    @property
    def action_space(self) -> NamedBox:
        return self._config.actions.box()

    @property
    def observation_space(self) -> NamedBox:
        return observation_space()

    def params(self, patient: str | Any | Sequence[Any] = "normal") -> core.EnvParams:
        """A patient's parameters (:class:`~lvenv.env.core.EnvParams`): one member for a name,
        path, record or Patient; a leading member axis for a list (ready for ``jax.vmap``)."""
        patients = resolve(list(patient), len(patient)) if isinstance(patient, (list, tuple)) else resolve(patient, 1)
        core.check_model(patients, self.scheme)
        if isinstance(patient, (list, tuple)):
            return jax.tree.map(lambda x: jnp.moveaxis(jnp.asarray(x), -1, 0), core.env_params(patients))
        return _drop_member_axis(jax.tree.map(jnp.asarray, core.env_params(patients)))

    def reset(self, key: jax.Array, params: core.EnvParams) -> tuple[jax.Array, core.EnvState]:
        """The patient's own parameters at steady state from a cold start: ``(obs, state)``."""
        state, obs, _ = core.reset(key, _add_member_axis(params), self._config)
        return obs[0], _drop_member_axis(state)

    def step(self, key: jax.Array, state: core.EnvState, action: jax.Array, params: core.EnvParams):
        """One step: ``(obs, state, reward, done, info)`` (module docstring)."""
        state, obs, reward, terminated, truncated, info = core.step(
            key, _add_member_axis(state), jnp.asarray(action)[None, :], _add_member_axis(params), self._config)
        info = {k: v[0] for k, v in info.items()}
        info.update(terminated=terminated[0], truncated=truncated[0])
        return obs[0], _drop_member_axis(state), reward[0], terminated[0] | truncated[0], info
