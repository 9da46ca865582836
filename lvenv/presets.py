"""Named parameter sets: the paper's N and HF hearts and the Table 2 training conditions.

Geometry: Table 1 unloaded configurations. LO parameters: the paper's trained values (DESIGN §1
table, "Table 3"). Cell defaults: :class:`lvenv.params.CellParams` (README, "Cell defaults").
Circulation defaults (closed loop, 60 bpm): README, "Circulation defaults".
"""

from __future__ import annotations

from lvenv.geometry import Geometry
from lvenv.params import Circulation, Heart, LOParams

__all__ = ["normal", "heart_failure", "training_condition", "TRAINING_CONDITIONS", "N_UNLOADED", "HF_UNLOADED", "N_END_DIASTOLE", "HF_END_DIASTOLE"]

N_UNLOADED = Geometry(Rb=35.0, L=9.6, Z=54.0, H=12.0, e=0.70, C0=-53.0)
HF_UNLOADED = Geometry(Rb=38.0, L=10.0, Z=49.0, H=7.7, e=0.66, C0=-64.0)
N_END_DIASTOLE = Geometry(Rb=38.0, L=8.2, Z=52.0, H=11.0, e=0.76, C0=-61.0)
HF_END_DIASTOLE = Geometry(Rb=42.0, L=8.2, Z=49.0, H=6.0, e=0.71, C0=-78.0)

N_LO = LOParams(mu1=0.191, mu2=0.183, gamma=4.97, alpha=0.640, beta=1.39, a=1.70, b=-1.41, c=1.64)
HF_LO = LOParams(mu1=0.190, mu2=0.173, gamma=5.17, alpha=0.571, beta=1.47, a=1.77, b=-1.47, c=1.61)

#: Table 2: k -> (Pat kPa, R3 kPa·s/ml, C ml/kPa); R1 = 0.0015 kPa·s/ml and R2 = 0 throughout.
TRAINING_CONDITIONS = {1: (0.33, 0.20, 8.0), 2: (0.66, 0.05, 8.0), 3: (1.5, 0.20, 8.0)}
TRAINING_R1 = 0.0015
TRAINING_PC0 = 10.0


def normal() -> Heart:
    """Healthy heart N (F 77): unloaded geometry, trained LO maps, default cell and circulation."""
    return Heart(geometry=N_UNLOADED, lo=N_LO, circulation=Circulation())


def heart_failure() -> Heart:
    """Heart-failure heart HF (M 77, no infarct): unloaded geometry and trained LO maps."""
    return Heart(geometry=HF_UNLOADED, lo=HF_LO, circulation=Circulation())


def training_condition(k: int, base: Heart | None = None) -> Heart:
    """``base`` (default :func:`normal`) under Table 2 condition ``k`` ∈ {1, 2, 3}.

    Open loop: constant atrial pressure Pat, venous side at 0 kPa, R1 = 0.0015, R2 = 0, and the
    training protocol's initial capacitor pressure P_c(0) = 10 kPa. Simulate one beat from the
    default initial state (``lvenv.simulate(heart, beats=1)``).
    """
    if k not in TRAINING_CONDITIONS:
        raise ValueError(f"training condition k = {k!r} is not one of {sorted(TRAINING_CONDITIONS)}")
    pat, r3, c = TRAINING_CONDITIONS[k]
    base = normal() if base is None else base
    return base.replace(Pat=pat, R3=r3, C=c, R1=TRAINING_R1, R2=0.0, Pc0=TRAINING_PC0, closed_loop=0.0)
