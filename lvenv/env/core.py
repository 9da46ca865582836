"""Pure, batched environment dynamics: ``reset(key, params)`` and ``step(key, state, action, params)``.

gymnax style: parameters are passed in (so per-member patients are free), the PRNG key is an
argument (it only draws the optional measurement noise), and the Gymnasium classes in
:mod:`lvenv.env.vector` / :mod:`lvenv.env.single` jit ``step`` once and reset through it (a step
of members that all need a reset runs exactly ``reset``'s simulation); :mod:`lvenv.env.functional`
exposes both per member for JAX code that jits and vmaps the heart itself. There is no Python
loop over members and no host sync inside.

One step evaluates one parameter set per member to steady state with the LO heart
(:func:`lvenv.simulation.run_beats_parallel`; by default with the adaptive scheme and Anderson
acceleration), **warm-started** from that member's state at the end of its
previous step. In the closed loop the warm start is first shifted to the blood volume a cold
start with the new parameters would have (P_c and P_at move by ΔV / (C + Cat)), so the result
does not depend on the order in which parameter sets were visited, only the number of beats
to reach steady state does.

Reward (per member), with relative errors e_k = (o_k − t_k) / t_k over the patient's targets and
weights w_k normalised so that max_k w_k = 1 (host-side, :func:`env_params`)::

    reward = − Σ_k w_k e_k² / Σ_k w_k  −  Σ_b κ (d_b / s_b)²,   d_b = max(0, lo_b − o_b, o_b − hi_b),

that is −Σ_j r_j² over the residuals r of :func:`residuals` (κ = 1), computed on the noise-free model output, over the plausibility bands b in force
(:mod:`lvenv.plausibility`: mean aortic pressure 80–120 mmHg always, s = 80 mmHg; by default also
mean atrial pressure and EDP 4–25 mmHg, s = 25 mmHg; ``Config.plausibility``). ``mismatch`` = Σ_k w_k abs(e_k) / Σ_k w_k; an episode
terminates when it falls below the tolerance, or when the simulation fails or the action is not
finite (reward :data:`FAILURE_REWARD`, mismatch +inf). A failed member's observation is all
zeros (inside the observation space) and its named metrics in ``info["metrics"]`` are NaN; its
``status`` says why (:mod:`lvenv.status`). Autoreset: NEXT_STEP (the step after an episode ends
returns that member's reset observation, reward 0, and ignores its action), or DISABLED
(``Config.autoreset = False``: every step evaluates every member's action, as optimisers need).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from lvenv import lo_model
from lvenv.env.spaces import ActionMap
from lvenv.metrics import OBS_NAMES
from lvenv.model import ModelParams
from lvenv.params import stack
from lvenv.plausibility import Band, distance, distance_slope, resolve
from lvenv.simulation import DEFAULT_STEP_TOL, run_beats_parallel
from lvenv.status import INVALID_ACTION, is_usable
from lvenv.validation import InputError

__all__ = ["EnvParams", "EnvState", "Config", "reset", "step", "env_params", "check_model", "default_scheme", "residuals", "residual_slopes", "FAILURE_REWARD", "ENV_SCHEME", "ENV_ACCELERATION"]

FAILURE_REWARD = -10.0


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class EnvParams:
    """Per-member constants: the patient's heart, cold-start state, targets and weights."""

    heart: ModelParams  # leaves (N,); the multi-element heart's ElementParams (lvenv.lo_model)
    y_cold: jax.Array  # (n_states, N): 9 for the single cell
    targets: jax.Array  # (n_obs, N), 1 where untargeted
    weights: jax.Array  # (n_obs, N), 0 where untargeted


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class EnvState:
    y: jax.Array  # (n_states, N) LO-heart state at the end of the last step (the next step's warm start)
    steps: jax.Array  # (N,) steps taken in the current episode
    needs_reset: jax.Array  # (N,) the previous step ended this member's episode


#: The environment's integration defaults (:mod:`lvenv.simulation`): step-size control, and the
#: steady state by Anderson-accelerated beats. Everything that evaluates through the env uses them.
ENV_SCHEME = "adaptive"
ENV_ACCELERATION = "anderson"


def default_scheme(heart) -> str:
    """The env's integration scheme for a Heart's LO heart model: :data:`ENV_SCHEME`, or
    ``"fixed"`` for a multi-element heart (the adaptive scheme is the single cell's)."""
    return ENV_SCHEME if heart.elements is None else "fixed"


@dataclasses.dataclass(frozen=True)
class Config:
    """Static settings (hashable, closed over by jit)."""

    actions: ActionMap
    steps_per_beat: int = 1000
    max_beats: int = 60
    rtol: float = 1e-4
    scheme: str = ENV_SCHEME
    step_tol: float = DEFAULT_STEP_TOL
    acceleration: str = ENV_ACCELERATION
    tolerance: float = 1e-3
    max_episode_steps: int | None = None
    obs_noise: tuple[float, ...] | None = None  # relative std of the measurement noise per observation
    plausibility: tuple[Band, ...] = resolve(True)  # the bands of the reward (lvenv.plausibility.resolve)
    volume_trace: bool = False  # record the volume-trace frames (else their metrics are NaN, their observations 0)
    autoreset: bool = True  # NEXT_STEP autoreset; False: DISABLED (ended members keep being evaluated)


def _with_action(heart: ModelParams, values: jax.Array, actions: ActionMap) -> ModelParams:
    """Replace the action parameters of every member (values (N, k), physical units)."""
    return heart.replace(**{name: values[:, i] for i, name in enumerate(actions.names)})


def _conserve_volume(y: jax.Array, y_cold: jax.Array, heart: ModelParams) -> jax.Array:
    """Shift P_c and P_at so the closed-loop volume equals the cold start's for these params."""
    circ = heart.circ
    i_v, i_pc, i_pat = lo_model.circulation_index(heart)
    volume = lambda s: s[i_v] + circ.C * s[i_pc] + circ.Cat * s[i_pat]
    shift = circ.closed_loop * (volume(y_cold) - volume(y)) / (circ.C + circ.Cat)
    return y.at[i_pc].add(shift).at[i_pat].add(shift)


def _observe(out) -> jax.Array:
    """Named metrics (N, n_obs): NaN where the member failed."""
    return jnp.stack([out["metrics"][k] for k in OBS_NAMES], axis=1)


def _observation(metrics: jax.Array, usable: jax.Array) -> jax.Array:
    """What the agent sees: the metrics, or zeros for a failed member and for metrics not
    computed (the volume-trace frames without ``Config.volume_trace``), kept inside the space."""
    return jnp.where(usable[:, None] & jnp.isfinite(metrics), metrics, 0.0)


def residuals(obs, targets, weights, metrics: Mapping[str, Any], bands: Sequence[Band]):
    """The objective as residuals r, shared by the reward (−Σ_j r_j², module docstring) and the
    least-squares fit (:func:`optim.lm.fit_lm`, which minimises Σ_j r_j²).

    ``obs``, ``targets``, ``weights``: (..., K) observed and target values of K metrics (internal
    units) and their weights w_k ≥ 0 (0: untargeted; the observation may then be NaN);
    ``metrics``: the bands' metrics by name, (...) each; ``bands``: :mod:`lvenv.plausibility`
    bands. Returns r (..., K + B) = (sqrt(ŵ_k) e_k over k, d_b / s_b over b), with e_k =
    (o_k − t_k) / t_k and ŵ_k = w_k / Σ_j w_j, and the mismatch Σ_k ŵ_k abs(e_k) (...).
    Works on NumPy and JAX arrays (JAX arrays out)."""
    rel = jnp.where(weights > 0.0, (obs - targets) / targets, 0.0)  # an untargeted metric may be NaN (frames not recorded)
    share = weights / jnp.sum(weights, axis=-1, keepdims=True)
    r = _columns(jnp.sqrt(share) * rel, [distance(b, metrics[b.metric]) / b.scale for b in bands])
    return r, jnp.sum(share * jnp.abs(rel), axis=-1)


def residual_slopes(targets, weights, metrics: Mapping[str, Any], bands: Sequence[Band]):
    """∂r_j / ∂o_j of :func:`residuals` (..., K + B), each residual depending on one metric:
    sqrt(ŵ_k) / t_k for a target, (d d_b / d o_b) / s_b for a band
    (:func:`lvenv.plausibility.distance_slope`)."""
    share = weights / jnp.sum(weights, axis=-1, keepdims=True)
    return _columns(jnp.sqrt(share) / targets, [distance_slope(b, metrics[b.metric]) / b.scale for b in bands])


def _columns(per_target, per_band):
    """(..., K) target columns and B band values (...) as one (..., K + B) array, broadcast."""
    shape = jnp.broadcast_shapes(jnp.shape(per_target)[:-1], *(jnp.shape(d) for d in per_band))
    return jnp.concatenate([jnp.broadcast_to(per_target, shape + jnp.shape(per_target)[-1:]),
                            *(jnp.broadcast_to(d, shape)[..., None] for d in per_band)], axis=-1)


def _score(obs: jax.Array, params: EnvParams, config: Config):
    r, mismatch = residuals(obs, params.targets.T, params.weights.T, dict(zip(OBS_NAMES, obs.T)), config.plausibility)
    return -jnp.sum(r**2, axis=1), mismatch


def _noisy(obs: jax.Array, key: jax.Array, config: Config) -> jax.Array:
    if config.obs_noise is None:
        return obs
    eps = jax.random.normal(key, obs.shape, obs.dtype)
    return obs * (1.0 + jnp.asarray(config.obs_noise, obs.dtype) * eps)


def _evaluate(heart: ModelParams, y0: jax.Array, config: Config):
    return run_beats_parallel(heart, y0, config.rtol, steps=config.steps_per_beat, max_beats=config.max_beats, steady=True, record=False,
                              scheme=config.scheme, step_tol=config.step_tol, acceleration=config.acceleration,
                              volume_trace=config.volume_trace)


def reset(key: jax.Array, params: EnvParams, config: Config):
    """Every member at its patient's own parameters, simulated to steady state from a cold start.

    Returns ``(state, obs, info)``; ``key`` draws the measurement noise of ``obs``.
    """
    out = _evaluate(params.heart, params.y_cold, config)
    metrics = _observe(out)
    n = metrics.shape[0]
    state = EnvState(y=out["y"], steps=jnp.zeros((n,), jnp.int32), needs_reset=jnp.zeros((n,), bool))
    info = {"metrics": metrics, "status": out["status"], "converged": out["converged"], "beats": out["beats"], "steps": out["steps"], "parameters": config.actions.current(params.heart)}
    return state, _noisy(_observation(metrics, is_usable(out["status"])), key, config), info


def step(key: jax.Array, state: EnvState, action: jax.Array, params: EnvParams, config: Config):
    """One environment step for all members (see module docstring).

    Returns ``(state, obs, reward, terminated, truncated, info)``; ``key`` draws the
    measurement noise of ``obs``.
    """
    values, clipped, finite = config.actions.to_physical(action, params.heart)
    fresh = state.needs_reset
    heart = _with_action(params.heart, values, config.actions)
    heart = jax.tree.map(lambda default, acted: jnp.where(fresh, default, acted), params.heart, heart)
    y_start = jnp.where(fresh, params.y_cold, state.y)
    y_start = _conserve_volume(y_start, params.y_cold, heart)
    out = _evaluate(heart, y_start, config)
    metrics = _observe(out)
    reward, mismatch = _score(metrics, params, config)
    sim_ok = is_usable(out["status"])
    invalid = ~finite & ~fresh
    failed = (~sim_ok | invalid) & ~fresh
    status = jnp.where(invalid, INVALID_ACTION, out["status"])
    reward = jnp.where(failed, FAILURE_REWARD, jnp.where(fresh, 0.0, reward))
    steps = jnp.where(fresh, 0, state.steps + 1)
    terminated = ~fresh & (failed | (mismatch < config.tolerance))
    at_limit = jnp.zeros_like(fresh) if config.max_episode_steps is None else steps >= config.max_episode_steps
    truncated = ~fresh & ~terminated & at_limit
    new_state = EnvState(y=out["y"], steps=steps, needs_reset=(terminated | truncated) & config.autoreset)
    shown = sim_ok & ~invalid  # a rejected action's stand-in simulation is not reported
    info = {
        "metrics": jnp.where(shown[:, None], metrics, jnp.nan),
        "status": status,
        "converged": out["converged"],
        "beats": out["beats"],
        "steps": out["steps"],
        "mismatch": jnp.where(sim_ok & finite, mismatch, jnp.inf),
        "clipped": clipped & ~fresh,
        "reset": fresh,
        "parameters": config.actions.current(heart),
    }
    return new_state, _noisy(_observation(metrics, shown), key, config), reward, terminated, truncated, info


def check_model(patients, scheme: str) -> None:
    """InputError unless the patients' hearts share one LO heart model (``Heart.elements``'s
    :meth:`~lvenv.params.Arrangement.model_key`; their walls' onsets may differ) that ``scheme``
    integrates (a multi-element heart: the fixed scheme only)."""
    models = {None if p.heart.elements is None else p.heart.elements.model_key() for p in patients}
    if len(models) > 1:
        raise InputError(f"the patients' hearts carry different LO heart models (kind, n_elements, spread: {sorted(map(repr, models))}); "
                         "one env holds one model")
    lo_model.check_scheme(patients[0].heart.elements, scheme)


def env_params(patients) -> EnvParams:
    """Host-side NumPy: stack the patients' hearts, cold starts, targets and weights (batch-last).

    Each member's weights are divided by their maximum, so Σ w ≥ 1 and huge weights cannot
    overflow (the reward and mismatch are invariant to a common scale of the weights).
    """
    heart = lo_model.core_params(stack([p.heart for p in patients]))
    y_cold = lo_model.initial_state(heart)
    targets = np.array([[p.targets.get(k, 1.0) for k in OBS_NAMES] for p in patients]).T
    weights = np.array([[p.weight(k) for k in OBS_NAMES] for p in patients]).T
    return EnvParams(heart, y_cold, targets, weights / weights.max(axis=0, keepdims=True))
