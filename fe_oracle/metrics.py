"""Per-beat metrics of an oracle run (DESIGN §1.5), by the LO heart's own valve-event detector."""

from __future__ import annotations

import math

import numpy as np

import lvenv  # noqa: F401  (float64)
from lvenv import events, status

from fe_oracle.result import OracleResult

__all__ = ["beat_metrics"]


def beat_metrics(result: OracleResult, beat: int = -1) -> dict[str, float | str]:
    """EF, EDV, ESV, SV, IVCT, ET, IVRT, filling time, peak P_lv, aortic pressures, CO of one beat.

    Internal units (ml, s, kPa, ml/s), from :func:`lvenv.events.beat_metrics` applied to the
    samples of complete beat ``beat`` (default: the last) of a coupled run; valve events are located by
    linear interpolation between time steps. ``status`` is the beat's :mod:`lvenv.status` name, judged
    as the LO heart's: ``no_valve_cycle`` without the full valve cycle (mitral closes, aortic opens,
    aortic closes, mitral opens), ``nonfinite`` for a NaN metric, ``non_physical`` for a beat that
    fails :func:`lvenv.status.is_physical`, else ``ok``. Only an ``ok`` beat has numbers: every
    metric of another is NaN. ``valid`` is 1.0 for an ``ok`` beat, else 0.0.
    """
    if result.metadata.get("case") != "beat":
        raise ValueError("beat metrics need a coupled run (case 1–3 or a Circulation), not passive inflation")
    period = float(result.metadata["period_s"])
    tr = result.traces
    n_beats = int(np.floor(tr["t"][-1] / period + 1e-9))  # complete beats only
    if n_beats < 1:
        raise ValueError(f"the run covers {tr['t'][-1]:.3g} s, less than one beat ({period:.3g} s)")
    k = range(n_beats)[beat]
    onset = k * period
    window = (tr["t"] >= onset - 1e-9) & (tr["t"] <= onset + period + 1e-9)
    metrics, valid = events.beat_metrics(*(np.asarray(tr[name][window]) for name in ("t", "V", "P_lv", "P_at", "P_c", "P_ao")), period)
    out = {name: float(value) for name, value in metrics.items()}
    if not bool(valid):
        code = status.NO_VALVE_CYCLE
    elif not all(math.isfinite(value) for value in out.values()):
        code = status.NONFINITE
    else:
        code = status.OK if bool(status.is_physical(out)) else status.NON_PHYSICAL
    usable = code == status.OK
    return {**{name: value if usable else math.nan for name, value in out.items()}, "valid": float(usable), "status": status.STATUS[code]}
