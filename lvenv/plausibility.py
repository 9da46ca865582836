"""Physiological plausibility: soft bands on beat metrics, in every fit's objective.

Four clinical targets cannot pin six parameters (README, "Identifiability"), so a fit can match
them while the heart fills at a pressure no patient survives. The env's reward
(:mod:`lvenv.env.core`) therefore subtracts, for each band b in force,

    κ (d_b / s_b)²,   d_b = max(0, lo_b − o_b, o_b − hi_b),   κ = 1,

where o_b is the band's metric at the member's steady state. Inside every band the penalty is 0,
so a plausible fit is unchanged. Bands (mmHg):

=============  ========  ======  ==========================================================
metric         lo–hi     s_b     source
=============  ========  ======  ==========================================================
P_ao_mean      80–120    80      the reward's aortic band (DESIGN §2); always on
P_at_mean      4–25      25      mean atrial (filling) pressure, see below; switchable
EDP            4–25      25      end-diastolic LV pressure, see below; switchable
=============  ========  ======  ==========================================================

The filling bands span what a living patient, healthy or in heart failure, can sustain. The
low end is that of the normal resting range (pulmonary capillary wedge and LV end-diastolic
pressure about 4–12 mmHg at catheterisation). The high end is where hydrostatic pulmonary
oedema begins: Guyton AC & Lindsey AW, Circ Res 7:649, 1959, found lung fluid accumulating once
left atrial pressure exceeded about 25 mmHg, the plasma colloid osmotic pressure. In this model
the mitral valve closes where P_lv = P_at, so EDP is the atrial pressure at that moment; P_at
peaks later, while the atrium fills against the closed valve, so P_at_mean ≥ EDP on a normal
beat. A healthy patient's mean atrial pressure above 12 mmHg is still *elevated*; the bands
only rule out what is impossible. Pass your own :class:`Band` tuple to narrow them.

Not built: a stroke-volume band for the body size. Patient records carry no body size, and the
LV geometry (fixed per patient) already sets the heart's scale.

``plausibility`` settings (env, :func:`optim.fit.make_env`, ``lvenv fit``, cohorts, LM, posterior):
``True`` (default) applies :data:`FILLING`; ``False`` only the aortic band; a sequence of
:class:`Band` replaces :data:`FILLING`.
"""

from __future__ import annotations

import dataclasses
import functools
import operator
from collections.abc import Mapping, Sequence

import jax.numpy as jnp

from lvenv.metrics import METRICS, OBS_NAMES
from lvenv.units import mmhg_to_kpa
from lvenv.validation import InputError

__all__ = ["Band", "AORTIC", "FILLING", "resolve", "distance", "distance_slope", "inside_bands", "report"]


@dataclasses.dataclass(frozen=True)
class Band:
    """``low`` ≤ ``metric`` ≤ ``high`` (internal units), penalised as κ (d / ``scale``)² outside."""

    metric: str
    low: float
    high: float
    scale: float

    def __post_init__(self) -> None:
        if self.metric not in OBS_NAMES:
            raise InputError(f"Band.metric = {self.metric!r} is not an observation; choose from {OBS_NAMES}")
        if not (self.low < self.high and self.scale > 0):
            raise InputError(f"Band({self.metric!r}): need low < high and scale > 0, got low={self.low}, high={self.high}, scale={self.scale}")

    @classmethod
    def mmhg(cls, metric: str, low: float, high: float, scale: float) -> Band:
        """A pressure band given in mmHg."""
        return cls(metric, float(mmhg_to_kpa(low)), float(mmhg_to_kpa(high)), float(mmhg_to_kpa(scale)))

    def holds(self, value):
        """lo ≤ ``value`` ≤ hi, elementwise (False where NaN)."""
        return (self.low <= value) & (value <= self.high)

    def describe(self) -> str:
        """``"P_at_mean 4–25 mmHg"`` (display units)."""
        m = METRICS[self.metric]
        return f"{self.metric} {m.to_display(self.low):g}–{m.to_display(self.high):g} {m.display_units}"


#: Mean aortic pressure band of the reward (DESIGN §2); always applied.
AORTIC = Band.mmhg("P_ao_mean", 80.0, 120.0, 80.0)
#: The switchable filling-pressure bands (module docstring).
FILLING = (Band.mmhg("P_at_mean", 4.0, 25.0, 25.0), Band.mmhg("EDP", 4.0, 25.0, 25.0))


def resolve(plausibility: bool | Sequence[Band]) -> tuple[Band, ...]:
    """The bands in force: the aortic band, then :data:`FILLING` (``True``), none (``False``) or the given ones."""
    if isinstance(plausibility, bool):
        return (AORTIC, *FILLING) if plausibility else (AORTIC,)
    bands = tuple(plausibility)
    if not all(isinstance(b, Band) for b in bands):
        raise InputError(f"plausibility = {plausibility!r}: give True, False or a sequence of lvenv.plausibility.Band")
    return (AORTIC, *bands)


def distance(band: Band, value):
    """d = max(0, lo − o, o − hi) (internal units), elementwise; NaN stays NaN."""
    return jnp.maximum(0.0, jnp.maximum(band.low - value, value - band.high))


def distance_slope(band: Band, value):
    """d d / d o: −1 below the band, +1 above it, 0 inside (elementwise)."""
    return jnp.where(value < band.low, -1.0, jnp.where(value > band.high, 1.0, 0.0))


def inside_bands(metrics: Mapping[str, object], plausibility: bool | Sequence[Band] = True):
    """Whether every band in force holds (elementwise; False where a metric is NaN)."""
    return functools.reduce(operator.and_, [b.holds(metrics[b.metric]) for b in resolve(plausibility)])


def report(observation: Mapping[str, float], plausibility: bool | Sequence[Band] = True) -> dict[str, dict[str, float | bool | str]]:
    """Per band in force: the value, the band's ends (display units, ``units``) and whether the value lies inside."""
    out = {}
    for b in resolve(plausibility):
        m = METRICS[b.metric]
        value = float(observation.get(b.metric, float("nan")))
        out[b.metric] = {"value": float(m.to_display(value)), "low": float(m.to_display(b.low)), "high": float(m.to_display(b.high)),
                         "units": m.display_units, "inside": bool(b.holds(value))}
    return out
