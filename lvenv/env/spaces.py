"""Action and observation spaces of ``LVHeart-v0`` and the action ↔ parameter map.

Actions are physical parameters under identification (default (τ2, Sa, R2, R3, C, Cat), bounds in
:data:`lvenv.identification.ACTION_BOUNDS`). With ``action_mode="normalized"`` an action in
[−1, 1] maps onto the bounds, log-uniformly for parameters marked ``log``. Out-of-bounds actions
are clipped (reported per member); non-finite entries are replaced by the patient's own value
and the member's episode ends (``info["status"] == "invalid_action"``).
"""

from __future__ import annotations

import dataclasses

import gymnasium
import jax.numpy as jnp
import numpy as np

from lvenv.identification import ACTION_BOUNDS, DEFAULT_ACTION_PARAMS
from lvenv.params import CellParams, Circulation, LOParams
from lvenv.patients import OBS_NAMES

__all__ = ["ActionMap", "NamedBox", "observation_space", "OBS_BOUNDS"]

_PARTS = (("lo", LOParams), ("cell", CellParams), ("circ", Circulation))

#: Observation bounds (internal units): EF 1, durations s, volumes ml, pressures kPa.
OBS_BOUNDS = {
    "EF": (0.0, 1.0), "IVCT": (0.0, 3.0), "ET": (0.0, 3.0), "IVRT": (0.0, 3.0), "filling_time": (0.0, 3.0),
    "EDV": (0.0, 1e5), "ESV": (0.0, 1e5),
    "P_ao_sys": (-200.0, 200.0), "P_ao_dia": (-200.0, 200.0), "P_ao_pulse": (0.0, 400.0), "P_ao_mean": (-200.0, 200.0),
}


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
    lo, hi = zip(*(OBS_BOUNDS[k] for k in OBS_NAMES))
    return NamedBox(lo, hi, OBS_NAMES)


def _location(name: str) -> tuple[str, str]:
    for part, cls in _PARTS:
        if name in {f.name for f in dataclasses.fields(cls)}:
            return part, name
    raise ValueError(f"action parameter {name!r} is not a Heart parameter")


@dataclasses.dataclass(frozen=True)
class ActionMap:
    """Static (hashable) description of the action: names, bounds, scale and mode."""

    names: tuple[str, ...] = DEFAULT_ACTION_PARAMS
    mode: str = "physical"

    def __post_init__(self) -> None:
        if self.mode not in ("physical", "normalized"):
            raise ValueError(f"action_mode must be 'physical' or 'normalized', got {self.mode!r}")
        if not self.names:
            raise ValueError("action_params must name at least one parameter")
        for name in self.names:
            if name not in ACTION_BOUNDS:
                raise ValueError(f"action parameter {name!r} has no identification bounds; choose from {tuple(ACTION_BOUNDS)}")
        if len(set(self.names)) != len(self.names):
            raise ValueError(f"action_params has duplicates: {self.names}")

    @property
    def locations(self) -> tuple[tuple[str, str], ...]:
        return tuple(_location(n) for n in self.names)

    @property
    def lower(self) -> np.ndarray:
        return np.array([ACTION_BOUNDS[n].lo for n in self.names])

    @property
    def upper(self) -> np.ndarray:
        return np.array([ACTION_BOUNDS[n].hi for n in self.names])

    def space(self) -> NamedBox:
        if self.mode == "normalized":
            return NamedBox(-np.ones(len(self.names)), np.ones(len(self.names)), self.names)
        return NamedBox(self.lower, self.upper, self.names)

    def from_unit(self, u):
        """Unit cube → physical values, log-uniform where the bound says so."""
        lo, hi = jnp.asarray(self.lower), jnp.asarray(self.upper)
        log = jnp.asarray([ACTION_BOUNDS[n].log for n in self.names])
        safe_lo = jnp.where(log, lo, 1.0)
        return jnp.where(log, safe_lo * (hi / safe_lo) ** u, lo + (hi - lo) * u)

    def to_unit(self, x):
        """Physical values → unit cube (inverse of :meth:`from_unit`)."""
        lo, hi = np.asarray(self.lower), np.asarray(self.upper)
        log = np.asarray([ACTION_BOUNDS[n].log for n in self.names])
        safe_lo = np.where(log, lo, 1.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(log, np.log(np.asarray(x) / safe_lo) / np.log(hi / safe_lo), (np.asarray(x) - lo) / (hi - lo))

    def current(self, heart) -> jnp.ndarray:
        """The members' current values of the action parameters, shape (N, k), physical units."""
        parts = {"lo": heart.lo, "cell": heart.cell, "circ": heart.circ}
        return jnp.stack([getattr(parts[part], field) for part, field in self.locations], axis=1)

    def to_physical(self, action, heart):
        """Action (N, k) → (physical values, clipped per member, finite per member)."""
        action = jnp.asarray(action, jnp.result_type(float))
        entry_finite = jnp.isfinite(action)
        finite = jnp.all(entry_finite, axis=1)
        box = self.space()
        lo, hi = jnp.asarray(box.low), jnp.asarray(box.high)
        clipped = jnp.any(entry_finite & ((action < lo) | (action > hi)), axis=1)
        inside = jnp.clip(jnp.where(entry_finite, action, lo), lo, hi)
        physical = self.from_unit(0.5 * (inside + 1.0)) if self.mode == "normalized" else inside
        return jnp.where(entry_finite, physical, self.current(heart)), clipped, finite
