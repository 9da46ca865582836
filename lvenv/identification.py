"""The physiological parameters under identification: their bounds and the one parameter space.

The Gymnasium action, the optimisers and every identification tool act on these; every other
parameter stays at the patient's value. Bounds are wide physiological ranges for an adult LV at
rest (internal units). ``log`` marks parameters spanning a decade or more, searched on a log scale.

:class:`ParameterSpace` is the only map between physical values and the unit cube used by the
normalised action, the optimisers and sensitivity analyses::

    u = ln(x / lo) / ln(hi / lo),   x = lo (hi / lo)^u        (log axes)
    u = (x − lo) / (hi − lo),       x = lo + u (hi − lo)       (linear axes)

It works on NumPy and on JAX arrays (inside jit too).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from lvenv.params import locate
from lvenv.units import mmhg_to_kpa
from lvenv.validation import InputError, real

__all__ = ["Bound", "ACTION_BOUNDS", "DEFAULT_ACTION_PARAMS", "OBSERVATION_TARGETS", "ParameterSpace", "LOGIT_EDGE", "to_logit", "from_logit"]


@dataclasses.dataclass(frozen=True)
class Bound:
    """Physical bounds [lo, hi] of one parameter, its units, log flag and meaning."""

    lo: float
    hi: float
    units: str
    log: bool
    doc: str


#: Physical bounds, unit, log flag and meaning of each identification parameter.
ACTION_BOUNDS: dict[str, Bound] = {
    "tau2": Bound(0.05, 0.6, "s", True, "Ca transient decay time constant"),
    "Sa": Bound(0.2, 4.0, "1", True, "contraction efficiency"),
    "R2": Bound(0.0, 0.05, "kPa·s/ml", False, "proximal aortic (characteristic) resistance"),
    "R3": Bound(0.02, 2.0, "kPa·s/ml", True, "peripheral resistance"),
    "C": Bound(1.0, 30.0, "ml/kPa", True, "arterial compliance"),
    "Cat": Bound(1.0, 200.0, "ml/kPa", True, "atrial compliance"),
}

#: The parameters under identification by default: τ2, Sa, R2, R3, C, Cat.
DEFAULT_ACTION_PARAMS = tuple(ACTION_BOUNDS)

#: Human resting targets at 60 bpm used for the reachability check (internal units).
OBSERVATION_TARGETS = {"EF": 0.60, "ET": 0.300, "IVRT": 0.080, "P_ao_sys": mmhg_to_kpa(120.0), "P_ao_dia": mmhg_to_kpa(75.0)}


@dataclasses.dataclass(frozen=True)
class ParameterSpace:
    """A box of named Heart parameters (physical units) with its unit-cube maps. Hashable.

    Build it with :meth:`for_names`; ``lower``/``upper`` default to :data:`ACTION_BOUNDS` and may
    be narrowed per parameter.
    """

    names: tuple[str, ...]
    lower: tuple[float, ...]
    upper: tuple[float, ...]
    log: tuple[bool, ...]

    @classmethod
    def for_names(cls, names: Sequence[str] = DEFAULT_ACTION_PARAMS, bounds: Mapping[str, tuple[float, float]] | None = None) -> ParameterSpace:
        """The space of ``names`` within :data:`ACTION_BOUNDS`, optionally narrowed by ``bounds``."""
        if isinstance(names, str) or not isinstance(names, Sequence):
            raise InputError(f"parameter names must be a sequence of names, got {names!r}")
        names = tuple(names)
        if not names:
            raise InputError("a parameter space needs at least one parameter")
        for name in names:
            if not isinstance(name, str) or name not in ACTION_BOUNDS:
                raise InputError(f"parameter {name!r} has no identification bounds; choose from {DEFAULT_ACTION_PARAMS}")
        if len(set(names)) != len(names):
            raise InputError(f"parameter names repeat: {names}")
        bounds = dict(bounds or {})
        if unknown := sorted(set(bounds) - set(names), key=str):
            raise InputError(f"bounds given for {unknown}, which are not among the parameters {names}")
        lower, upper = [], []
        for name in names:
            b = ACTION_BOUNDS[name]
            pair = bounds.get(name, (b.lo, b.hi))
            if isinstance(pair, (str, bytes)) or not isinstance(pair, Sequence) or len(pair) != 2:
                raise InputError(f"bounds of {name} = {pair!r} must be a pair (lower, upper) in {b.units}")
            lo = real(f"lower bound of {name}", pair[0], b.lo, b.hi)
            hi = real(f"upper bound of {name}", pair[1], b.lo, b.hi)
            if not lo < hi:
                raise InputError(f"bounds of {name} = [{lo:g}, {hi:g}] {b.units}: lower must be below upper")
            lower.append(lo)
            upper.append(hi)
        return cls(names, tuple(lower), tuple(upper), tuple(ACTION_BOUNDS[n].log for n in names))

    @property
    def dimension(self) -> int:
        return len(self.names)

    @property
    def units(self) -> tuple[str, ...]:
        return tuple(ACTION_BOUNDS[n].units for n in self.names)

    @property
    def parts(self) -> tuple[str, ...]:
        """Which part of the Heart holds each parameter (:func:`lvenv.params.locate`)."""
        return tuple(locate(n) for n in self.names)

    def _arrays(self, like):
        xp = jnp if isinstance(like, jax.Array) else np
        lo, hi, log = xp.asarray(self.lower), xp.asarray(self.upper), xp.asarray(self.log)
        safe_lo = xp.where(log, lo, 1.0)  # R2's lower bound is 0: never enters a log
        return xp, lo, hi, log, safe_lo

    def from_unit(self, u):
        """Unit-cube coordinates (..., k) → physical values, log-uniform on log axes."""
        xp, lo, hi, log, safe_lo = self._arrays(u)
        return xp.where(log, safe_lo * (hi / safe_lo) ** u, lo + (hi - lo) * u)

    def to_unit(self, x):
        """Physical values (..., k) → unit-cube coordinates (inverse of :meth:`from_unit`)."""
        xp, lo, hi, log, safe_lo = self._arrays(x)
        if xp is np:
            with np.errstate(divide="ignore", invalid="ignore"):
                return np.where(log, np.log(np.asarray(x, float) / safe_lo) / np.log(hi / safe_lo), (np.asarray(x, float) - lo) / (hi - lo))
        return jnp.where(log, jnp.log(x / safe_lo) / jnp.log(hi / safe_lo), (x - lo) / (hi - lo))

    def rate(self, x):
        """dx/du at physical values x (..., k): x ln(hi/lo) on log axes, hi − lo on linear ones
        (the chain rule from physical derivatives to unit-cube ones)."""
        xp, lo, hi, log, safe_lo = self._arrays(x)
        return xp.where(log, x * xp.log(hi / safe_lo), hi - lo)

    def clip(self, x):
        """Physical values clipped into the box."""
        xp, lo, hi, _, _ = self._arrays(x)
        return xp.clip(x, lo, hi)


#: Unit-cube points are kept this far from the faces before the logit (the samplers' coordinates).
LOGIT_EDGE = 1e-9


def to_logit(u: np.ndarray) -> np.ndarray:
    """Logit coordinates z = ln(u / (1 − u)) of unit-cube points ``u``, clipped :data:`LOGIT_EDGE` from the faces."""
    u = np.clip(u, LOGIT_EDGE, 1.0 - LOGIT_EDGE)
    return np.log(u) - np.log1p(-u)


def from_logit(z: np.ndarray) -> np.ndarray:
    """The unit-cube points of logit coordinates ``z``, kept :data:`LOGIT_EDGE` from the faces."""
    with np.errstate(over="ignore"):  # exp(−z) = inf far below the cube gives 0, clipped
        return np.clip(1.0 / (1.0 + np.exp(-z)), LOGIT_EDGE, 1.0 - LOGIT_EDGE)
