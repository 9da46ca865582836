"""Where and why a trained LO heart misses its oracle: C split by phase of the beat and into timing and amplitude.

For one beat, with trapezoidal weights ω_j on the oracle's samples (`optim.congruency.residuals`),
the bracket of C² is a sum over samples::

    C_beat² = Σ_j ω_j [ (V_LO − V_FE)_j² / ‖V_FE‖² + (P_LO − P_FE)_j² / ‖P_FE‖² ]

so it splits exactly into the four windows the oracle's own valve events bound
(:func:`valve_events`): **upstroke** (mitral closing → aortic opening), **ejection** (aortic
opening → closing), **relaxation** (aortic closing → mitral opening) and **filling** (the rest).

**Timing against amplitude.** The LO traces shifted in time by τ (V_LO(t − τ), P_LO(t − τ),
held at their ends) give C_beat²(τ); the best shift τ* over ±:data:`MAX_SHIFT_S` says how much of
the error a pure delay of the LO beat would remove (``timing_share`` = 1 − C²(τ*) / C²(0)); what
is left, C(τ*), is the amplitude and shape error.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from lvenv.params import Arrangement, LOParams
from optim import congruency

__all__ = ["WINDOWS", "MAX_SHIFT_S", "SHIFT_STEP_S", "crossings", "valve_events", "window_masks", "decompose", "diagnose", "summary"]

WINDOWS = ("upstroke", "ejection", "relaxation", "filling")
#: Largest time shift of the LO beat tried (s), and the step of the search (s).
MAX_SHIFT_S, SHIFT_STEP_S = 0.1, 0.001


def crossings(t: np.ndarray, g: np.ndarray, rising: bool) -> np.ndarray:
    """Times where ``g`` changes sign upwards (``rising``) or downwards, linearly interpolated."""
    s = np.sign(g)
    idx = np.flatnonzero((s[:-1] <= 0) & (s[1:] > 0) if rising else (s[:-1] > 0) & (s[1:] <= 0))
    frac = g[idx] / (g[idx] - g[idx + 1])
    return t[idx] + frac * (t[idx + 1] - t[idx])


def valve_events(traces: Mapping[str, np.ndarray]) -> dict[str, float]:
    """The valve events of one beat (s) from its traces ``t``, ``P_lv``, ``P_at``, ``P_c``, in
    the order and by the rules of `lvenv.events`: ``mvc`` the last mitral closing before the
    aortic opening ``avo`` (the onset if closed from the start), ``avc`` the last aortic closing
    and ``mvo`` the first mitral opening after it; NaN where missing."""
    t, p_lv, p_at, p_c = (np.asarray(traces[k], float) for k in ("t", "P_lv", "P_at", "P_c"))
    aortic, mitral = p_lv - p_c, p_at - p_lv
    opens = crossings(t, aortic, rising=True)
    if not len(opens):
        return dict.fromkeys(("mvc", "avo", "avc", "mvo"), np.nan)
    avo = float(opens[0])
    closings = crossings(t, mitral, rising=False)
    before = closings[closings <= avo]
    mvc = float(before[-1]) if len(before) else float(t[0])
    shuts = crossings(t, aortic, rising=False)
    after = shuts[shuts > avo]
    avc = float(after[-1]) if len(after) else np.nan
    reopen = crossings(t, mitral, rising=True)
    later = reopen[reopen > avc] if np.isfinite(avc) else reopen[:0]
    return {"mvc": mvc, "avo": avo, "avc": avc, "mvo": float(later[0]) if len(later) else np.nan}


def window_masks(t: np.ndarray, events: Mapping[str, float]) -> dict[str, np.ndarray]:
    """Boolean masks of :data:`WINDOWS` over the samples ``t`` (s); each sample in exactly one."""
    t = np.asarray(t, float)
    bounds = {"upstroke": (events["mvc"], events["avo"]), "ejection": (events["avo"], events["avc"]),
              "relaxation": (events["avc"], events["mvo"])}
    masks = {name: (t >= lo) & (t < hi) for name, (lo, hi) in bounds.items()}
    masks["filling"] = ~(masks["upstroke"] | masks["ejection"] | masks["relaxation"])
    return masks


def _bracket_terms(oracle: Mapping[str, np.ndarray], t: np.ndarray, v: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Per-sample terms of C_beat² (module docstring), shape (samples,)."""
    r = congruency.residuals(oracle, t, v, p)[0]
    n = len(oracle["t"])
    return r[:n] ** 2 + r[n:] ** 2


def decompose(oracle: Mapping[str, np.ndarray], t: np.ndarray, v: np.ndarray, p: np.ndarray) -> dict[str, Any]:
    """One beat's C (``C``), the share of C² per window (``share``, summing to 1), the oracle's
    valve events (``events``, s), the best shift τ* (``shift_s``), C after it (``C_shifted``)
    and the share of C² a pure shift removes (``timing_share``). ``t``, ``v``, ``p``: one LO
    beat (s, ml, kPa)."""
    terms = _bracket_terms(oracle, t, v, p)
    total = float(np.sum(terms))
    events = valve_events(oracle)
    masks = window_masks(oracle["t"], events)
    shifts = np.arange(-MAX_SHIFT_S, MAX_SHIFT_S + SHIFT_STEP_S / 2, SHIFT_STEP_S)
    shifted = np.array([np.sum(_bracket_terms(oracle, np.asarray(t) + tau, v, p)) for tau in shifts])
    best = int(np.argmin(shifted))
    return {"C": float(np.sqrt(total)), "share": {w: float(np.sum(terms[m]) / total) for w, m in masks.items()}, "events": events,
            "shift_s": float(shifts[best]), "C_shifted": float(np.sqrt(shifted[best])), "timing_share": float(1.0 - shifted[best] / total)}


def diagnose(data: congruency.OracleData, lo: LOParams, steps_per_beat: int = 1000, arrangement: Arrangement | None = None) -> dict[str, Any]:
    """:func:`decompose` for each training beat of ``data`` with the LO heart ``lo`` (a
    multi-element one with ``arrangement``), and the share of the overall C² per window."""
    usable, t, v, p = congruency.lo_beats(data, [lo], steps_per_beat, arrangement)
    if not np.all(usable):
        raise RuntimeError(f"the LO heart has no usable beat under every training condition (usable: {usable.tolist()})")
    beats = {str(k): decompose(data.beats[k].traces, t[j], v[j], p[j]) for j, k in enumerate(congruency.CONDITIONS)}
    c2 = np.array([b["C"] ** 2 for b in beats.values()])
    overall = {w: float(np.sum([b["share"][w] * b["C"] ** 2 for b in beats.values()]) / np.sum(c2)) for w in WINDOWS}
    return {"beats": beats, "C": float(np.sqrt(np.mean(c2))), "share": overall}


def summary(results: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Median over anatomies of C, the window shares, the best shift and the timing share."""
    beats = [b for r in results for b in r["beats"].values()]
    return {"anatomies": len(results), "C_median": float(np.median([r["C"] for r in results])),
            "share_median": {w: float(np.median([r["share"][w] for r in results])) for w in WINDOWS},
            "shift_ms_median": float(1000 * np.median([b["shift_s"] for b in beats])),
            "timing_share_median": float(np.median([b["timing_share"] for b in beats]))}
