"""Action and observation spaces of ``LVHeart-v0`` and the action ↔ parameter map.

Actions are physical parameters under identification (default (τ2, Sa, R2, R3, C, Cat), bounds in
:data:`lvenv.identification.ACTION_BOUNDS`). With ``action_mode="normalized"`` an action in
[−1, 1] maps onto the bounds through :class:`lvenv.identification.ParameterSpace` (log-uniformly
for parameters marked ``log``). Out-of-bounds actions are clipped (reported per member);
non-finite entries are replaced by the patient's own value and the member's episode ends
(``info["status"] == "invalid_action"``). Observation bounds come from :mod:`lvenv.metrics`.
"""

from __future__ import annotations

import dataclasses

import gymnasium
import jax.numpy as jnp
import numpy as np

from lvenv.identification import DEFAULT_ACTION_PARAMS, ParameterSpace
from lvenv.metrics import METRICS, OBS_NAMES
from lvenv.model import ModelParams
from lvenv.validation import choice

__all__ = ["ActionMap", "NamedBox", "observation_space", "ACTION_MODES"]

ACTION_MODES = ("physical", "normalized")


class NamedBox(gymnasium.spaces.Box):
    """A ``Box`` whose components carry names (``space.names``)."""

    def __init__(self, low, high, names, dtype=np.float64, seed=None):
        super().__init__(low=np.asarray(low, dtype), high=np.asarray(high, dtype), dtype=dtype, seed=seed)
        self.names = tuple(names)

    def __repr__(self) -> str:
        return f"NamedBox({', '.join(self.names)}; low={self.low}, high={self.high})"

    def __eq__(self, other) -> bool:
        return isinstance(other, NamedBox) and super().__eq__(other) and self.names == other.names


def observation_space() -> NamedBox:
    lo, hi = zip(*(METRICS[k].bounds for k in OBS_NAMES))
    return NamedBox(lo, hi, OBS_NAMES)


@dataclasses.dataclass(frozen=True)
class ActionMap:
    """Static (hashable) description of the action: the parameter space and the mode."""

    names: tuple[str, ...] = DEFAULT_ACTION_PARAMS
    mode: str = "physical"

    def __post_init__(self) -> None:
        choice("action_mode", self.mode, ACTION_MODES)
        object.__setattr__(self, "names", ParameterSpace.for_names(self.names).names)

    @property
    def space(self) -> ParameterSpace:
        """The parameters' :class:`~lvenv.identification.ParameterSpace` (full identification bounds)."""
        return ParameterSpace.for_names(self.names)

    def box(self) -> NamedBox:
        """The single-member action space: physical bounds, or [−1, 1] when normalised."""
        if self.mode == "normalized":
            return NamedBox(-np.ones(len(self.names)), np.ones(len(self.names)), self.names)
        return NamedBox(self.space.lower, self.space.upper, self.names)

    def current(self, heart: ModelParams) -> jnp.ndarray:
        """The members' current values of the action parameters, shape (N, k), physical units."""
        return jnp.stack([heart.get(name) for name in self.names], axis=1)

    def to_physical(self, action, heart: ModelParams):
        """Action (N, k) → (physical values, clipped per member, finite per member)."""
        action = jnp.asarray(action, jnp.result_type(float))
        entry_finite = jnp.isfinite(action)
        finite = jnp.all(entry_finite, axis=1)
        box = self.box()
        lo, hi = jnp.asarray(box.low), jnp.asarray(box.high)
        clipped = jnp.any(entry_finite & ((action < lo) | (action > hi)), axis=1)
        inside = jnp.clip(jnp.where(entry_finite, action, lo), lo, hi)
        physical = self.space.from_unit(0.5 * (inside + 1.0)) if self.mode == "normalized" else inside
        return jnp.where(entry_finite, physical, self.current(heart)), clipped, finite

    def to_action(self, x):
        """Physical values (N, k) → actions of this mode (host-side NumPy)."""
        return 2.0 * np.asarray(self.space.to_unit(np.asarray(x, float))) - 1.0 if self.mode == "normalized" else np.asarray(x, float)
