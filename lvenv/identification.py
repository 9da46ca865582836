"""The physiological parameters under identification and their physical bounds (DESIGN §2).

The Gymnasium action and the inverse problem act on these; every other parameter stays at the
patient's value. Bounds are wide physiological ranges for an adult LV at rest (units internal).
``log`` marks parameters spanning a decade or more, searched on a log scale.
"""

from __future__ import annotations

import dataclasses

from lvenv.units import mmhg_to_kpa

__all__ = ["Bound", "ACTION_BOUNDS", "DEFAULT_ACTION_PARAMS", "OBSERVATION_TARGETS"]


@dataclasses.dataclass(frozen=True)
class Bound:
    lo: float
    hi: float
    units: str
    log: bool
    doc: str


ACTION_BOUNDS: dict[str, Bound] = {
    "tau2": Bound(0.05, 0.6, "s", True, "Ca transient decay time constant"),
    "Sa": Bound(0.2, 4.0, "1", True, "contraction efficiency"),
    "R2": Bound(0.0, 0.05, "kPa·s/ml", False, "proximal aortic (characteristic) resistance"),
    "R3": Bound(0.02, 2.0, "kPa·s/ml", True, "peripheral resistance"),
    "C": Bound(1.0, 30.0, "ml/kPa", True, "arterial compliance"),
    "Cat": Bound(1.0, 200.0, "ml/kPa", True, "atrial compliance"),
}

DEFAULT_ACTION_PARAMS = tuple(ACTION_BOUNDS)

#: Human resting targets at 60 bpm used for the reachability check (internal units).
OBSERVATION_TARGETS = {"EF": 0.60, "ET": 0.300, "IVRT": 0.080, "P_ao_sys": mmhg_to_kpa(120.0), "P_ao_dia": mmhg_to_kpa(75.0)}
