"""Outcome of a simulated member: one table of status codes, and one test of usability.

==================  ====  ===========================================================================
status              code  meaning
==================  ====  ===========================================================================
``ok``              0     steady state reached (or the fixed beats run) with a physical beat
``not_converged``   1     a physical beat, but the beat-to-beat change stayed above ``rtol``
``nonfinite``       2     the state or a metric became NaN / infinite
``diverged``        3     the state left its physical range (V ≤ 0 or V > 20 V0, abs(P) > 200 kPa)
``no_valve_cycle``  4     the last beat lacked the full valve sequence (or ejected a negative volume)
``non_physical``    5     a full valve cycle, but a non-physical beat: ESV ≤ 0, EF > 1, or no
                          real ejection (EF < :data:`EF_MIN`)
``invalid_action``  100   environment only: the action held a non-finite entry
==================  ====  ===========================================================================

Only ``ok`` and ``not_converged`` are *usable*: their metrics are reported; every other status
masks the member's metrics to NaN, is an infeasible point for the optimisers and ends the
member's episode in the environment.

What is non-physical, and what is an extreme heart told truthfully. The atrium and the arterial
Windkessel are linear capacitors: below zero transmural pressure they keep "holding" a negative
stressed volume and pull blood by suction, where a real atrium, vein or artery collapses. So a
beat whose end-diastolic pressure, mean atrial pressure or diastolic aortic pressure is negative
(e.g. R3 = 10 kPa·s/ml, 45× the default: the blood pools behind R3 and the atrium runs at
−21 mmHg) is outside the model's validity: ``non_physical``. A very high pressure (a mean aortic
pressure of 250 mmHg from a strong heart against a high resistance) breaks no law of the model:
the LV's active tension bounds it, volumes stay positive and blood is conserved. It is the
model's answer for an extreme heart, reported ``ok``; whether a patient could live with it is
the business of :mod:`lvenv.plausibility` and the fits' bands, and pressures beyond
200 kPa are ``diverged``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

__all__ = [
    "STATUS", "OK", "NOT_CONVERGED", "NONFINITE", "DIVERGED", "NO_VALVE_CYCLE", "NON_PHYSICAL",
    "INVALID_ACTION", "USABLE", "EF_MIN", "P_MIN", "is_usable", "is_physical", "names",
]

STATUS = ("ok", "not_converged", "nonfinite", "diverged", "no_valve_cycle", "non_physical")
OK, NOT_CONVERGED, NONFINITE, DIVERGED, NO_VALVE_CYCLE, NON_PHYSICAL = range(len(STATUS))
INVALID_ACTION = 100
USABLE = ("ok", "not_converged")

#: A beat ejecting less than this fraction of its end-diastolic volume has no real ejection.
EF_MIN = 0.02
#: Lowest end-diastolic, mean atrial and diastolic aortic pressure of a physical beat (kPa).
P_MIN = 0.0

_NAMES = {**dict(enumerate(STATUS)), INVALID_ACTION: "invalid_action"}


def is_usable(status: Any):
    """Whether a status (name or code; scalar, NumPy or JAX array) has usable metrics.

    Traceable: on a JAX integer array it returns a JAX boolean array.
    """
    if isinstance(status, str):
        return status in USABLE
    kind = getattr(getattr(status, "dtype", None), "kind", None)
    if kind in ("U", "S", "O") or (kind is None and not isinstance(status, (int, np.integer))):
        return np.isin(np.asarray(status).astype(str), USABLE)
    return (status == OK) | (status == NOT_CONVERGED)


def is_physical(metrics: Mapping[str, Any]):
    """Whether beats with a full valve cycle are physical (module docstring): ESV > 0,
    :data:`EF_MIN` ≤ EF ≤ 1, and EDP, P_at_mean and P_ao_dia ≥ :data:`P_MIN` (internal units).

    Elementwise over NumPy or JAX arrays of the metrics (traceable); NaN is not physical.
    """
    m = metrics
    return ((m["ESV"] > 0.0) & (m["EF"] <= 1.0) & (m["EF"] >= EF_MIN)
            & (m["EDP"] >= P_MIN) & (m["P_at_mean"] >= P_MIN) & (m["P_ao_dia"] >= P_MIN))


def names(codes: Any) -> np.ndarray:
    """Status names of integer codes (host-side)."""
    return np.array([_NAMES[int(c)] for c in np.ravel(codes)]).reshape(np.shape(codes))
