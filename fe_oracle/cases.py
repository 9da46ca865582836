"""Oracle cases: passive inflation Ⓟ and circulations (DESIGN §1.2), pure Python.

The geometries and the Table 2 training conditions come from :mod:`lvenv.presets`, so the FE
oracle and the LO heart are trained under identical circulations: open loop (constant atrial
pressure Pat, venous side at 0 kPa), R1 = 0.0015 kPa·s/ml, R2 = 0, P_c(0) = 10 kPa, and the
default HR and Rmv of :class:`lvenv.params.Circulation`::

    ①  Pat = 0.33 kPa,  R3 = 0.20 kPa·s/ml,  C = 8 ml/kPa
    ②  Pat = 0.66 kPa,  R3 = 0.05 kPa·s/ml,  C = 8 ml/kPa
    ③  Pat = 1.5 kPa,   R3 = 0.20 kPa·s/ml,  C = 8 ml/kPa
"""

from __future__ import annotations

import dataclasses

import lvenv  # noqa: F401
from lvenv import presets
from lvenv.params import Circulation
from lvenv.validation import InputError, integer, real

__all__ = ["Passive", "training_condition", "resolve_case", "N_UNLOADED", "HF_UNLOADED"]

N_UNLOADED = presets.N_UNLOADED
HF_UNLOADED = presets.HF_UNLOADED


@dataclasses.dataclass(frozen=True)
class Passive:
    """Passive inflation Ⓟ: cavity pressure 0 → ``p_max`` kPa, volume reported at ``n_points``
    pressures; with ``p_min`` < 0 also a deflation 0 → ``p_min`` (suction compressing the cavity
    below V0, which pins the compression branch of the LO law) at ``n_points`` pressures."""

    p_max: float = 4.0
    n_points: int = 9
    p_min: float = 0.0

    def __post_init__(self) -> None:
        real("Passive.p_max", self.p_max, 0.0, 40.0, lo_open=True)
        real("Passive.p_min", self.p_min, -10.0, 0.0)
        integer("Passive.n_points", self.n_points, 2)

    def pressures(self):
        """The sorted pressures (kPa) at which the volume is reported."""
        import numpy as np

        up = np.linspace(0.0, self.p_max, self.n_points)
        if self.p_min == 0.0:
            return up
        return np.concatenate([np.linspace(self.p_min, 0.0, self.n_points)[:-1], up])


def training_condition(k: int) -> Circulation:
    """The open-loop circulation of Table 2 condition ``k`` ∈ {1, 2, 3} (``lvenv.presets``)."""
    if k not in presets.TRAINING_CONDITIONS:
        raise InputError(f"training condition must be 1, 2 or 3, got {k!r}")
    return presets.training_condition(k).circulation


def resolve_case(case) -> Passive | Circulation:
    """``"passive"`` / :class:`Passive` / 1–3 / :class:`~lvenv.params.Circulation` → a case record."""
    if isinstance(case, str):
        if case == "passive":
            return Passive()
        raise InputError(f"case must be 'passive', 1, 2, 3, a Passive or a Circulation record, got {case!r}")
    if isinstance(case, (Passive, Circulation)):
        return case
    if isinstance(case, int) and not isinstance(case, bool):
        return training_condition(case)
    raise InputError(f"case must be 'passive', 1, 2, 3, a Passive or a Circulation record, got {case!r}")
