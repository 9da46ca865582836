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
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = [
    "STATUS", "OK", "NOT_CONVERGED", "NONFINITE", "DIVERGED", "NO_VALVE_CYCLE", "NON_PHYSICAL",
    "INVALID_ACTION", "USABLE", "EF_MIN", "is_usable", "names",
]

STATUS = ("ok", "not_converged", "nonfinite", "diverged", "no_valve_cycle", "non_physical")
OK, NOT_CONVERGED, NONFINITE, DIVERGED, NO_VALVE_CYCLE, NON_PHYSICAL = range(len(STATUS))
INVALID_ACTION = 100
USABLE = ("ok", "not_converged")

#: A beat ejecting less than this fraction of its end-diastolic volume has no real ejection.
EF_MIN = 0.02

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


def names(codes: Any) -> np.ndarray:
    """Status names of integer codes (host-side)."""
    return np.array([_NAMES[int(c)] for c in np.ravel(codes)]).reshape(np.shape(codes))
