"""The paper's two validation studies of congruency training (DESIGN §3, Di Achille et al. 2020), and two of
ours on why the trained maps miss its unseen scenarios.

* :func:`generalisation` (their Fig. 7): the trained LO heart, maps frozen, against the oracle
  when one cell or circulation parameter at a time leaves its training value: Vmax factor
  (0.25–4), n0 (0.5–0.9), nA (1–10), τ2 (×1.1–2.0) and R1 (up to 0.1 kPa·s/ml), one beat under
  training condition ②. Reported per scenario: C (DESIGN §3, one run) and the largest pointwise
  error of P and V from the oracle's first step on (at t = 0 its wall carries no active tension
  yet, ``_errors``), each relative to the oracle trace's maximum. For a heart that carries a
  multi-element model (``Heart.elements``) the LO side is that heart (:mod:`lvenv.multielement`),
  for comparing candidate low-order hearts on the same oracle runs.
* :func:`retune` (ours): the same scenarios with the maps refitted on each scenario's own oracle
  beat (:func:`optim.congruency.fit_maps`). The retuned C is how close the model can come to that
  beat at all; the frozen C is how close it comes with the maps of the training beats. Their
  difference is the part of the miss that lies in the maps not carrying over to the scenario, not
  in the model.
* :func:`map_transfer` (ours): whether maps that follow the cell would carry over: the maps
  retuned at the training beat and at a point inside each scenario's axis (:data:`INTERIOR`),
  carried linearly to the scenario's end, and those at the end carried back to the interior point.
* :func:`multielement_table` (their Table 4): a single-element LO heart trained
  (:func:`optim.congruency.train`) to each 256-element model (parallel and series,
  :mod:`lvenv.multielement`) along four sweeps of ten values: Vmax factor 0.25–4, n0 0.5–0.9,
  nA 1–10, τ2 ×1.1–2.0.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np

import fe_oracle
from lvenv import presets
from lvenv.params import CellParams, Heart, LOParams
from lvenv.validation import InputError
from optim.congruency import ACTIVE_BOUNDS, MAP_NAMES, congruency, fit_maps, one_beat, passes_validation, train
from optim.diagnosis import decompose

__all__ = ["UNSEEN", "INTERIOR", "OUTER", "SWEEPS", "scenario", "generalisation", "retune", "map_transfer", "multielement_table"]

#: The ends of the unseen scenarios: parameter changes from the training values (τ2 as a factor).
UNSEEN: dict[str, dict[str, float]] = {
    "vmax_x0.25": {"vmax_factor": 0.25}, "vmax_x4": {"vmax_factor": 4.0},
    "n0_0.5": {"n0": 0.5}, "n0_0.9": {"n0": 0.9},
    "nA_1": {"nA": 1.0}, "nA_10": {"nA": 10.0},
    "tau2_x2": {"tau2_factor": 2.0}, "R1_0.1": {"R1": 0.1},
}

#: A point inside each unseen scenario's axis, between the training value and the scenario's end
#: (about halfway; Vmax's factor halfway on a log scale): scenario → (name, change).
INTERIOR: dict[str, tuple[str, dict[str, float]]] = {
    "vmax_x0.25": ("vmax_x0.5", {"vmax_factor": 0.5}), "vmax_x4": ("vmax_x2", {"vmax_factor": 2.0}),
    "n0_0.5": ("n0_0.6", {"n0": 0.6}), "n0_0.9": ("n0_0.8", {"n0": 0.8}),
    "nA_1": ("nA_3", {"nA": 3.0}), "nA_10": ("nA_7.5", {"nA": 7.5}),
    "tau2_x2": ("tau2_x1.5", {"tau2_factor": 1.5}), "R1_0.1": ("R1_0.05", {"R1": 0.05}),
}

#: A second point inside each unseen scenario's axis, about three quarters of the way from the
#: training value to the scenario's end (on a log scale for Vmax's factor), for maps that follow
#: the cell to second order (`scripts/smooth_maps.py --order 2`): scenario → (name, change).
OUTER: dict[str, tuple[str, dict[str, float]]] = {
    "vmax_x0.25": ("vmax_x0.35", {"vmax_factor": 0.35}), "vmax_x4": ("vmax_x2.8", {"vmax_factor": 2.8}),
    "n0_0.5": ("n0_0.55", {"n0": 0.55}), "n0_0.9": ("n0_0.85", {"n0": 0.85}),
    "nA_1": ("nA_2", {"nA": 2.0}), "nA_10": ("nA_8.75", {"nA": 8.75}),
    "tau2_x2": ("tau2_x1.75", {"tau2_factor": 1.75}), "R1_0.1": ("R1_0.075", {"R1": 0.075}),
}

#: Table 4's sweeps, ten values each (τ2 as a factor of the training value).
SWEEPS: dict[str, np.ndarray] = {
    "vmax_factor": np.geomspace(0.25, 4.0, 10),
    "n0": np.linspace(0.5, 0.9, 10),
    "nA": np.linspace(1.0, 10.0, 10),
    "tau2_factor": np.linspace(1.1, 2.0, 10),
}


def scenario(heart: Heart, change: Mapping[str, float]) -> Heart:
    """``heart`` under training condition ② with ``change`` applied (``tau2_factor`` scales τ2)."""
    change = dict(change)
    if "tau2_factor" in change:
        change["tau2"] = change.pop("tau2_factor") * float(heart.cell.tau2)
    return presets.training_condition(2, heart).replace(**change)


def _errors(tr: Mapping[str, np.ndarray], t: np.ndarray, v: np.ndarray, p: np.ndarray) -> dict[str, float]:
    """C and the largest pointwise errors of one LO beat (``t`` s, ``v`` ml, ``p`` kPa) against
    the oracle's traces ``tr``, each relative to the oracle trace's maximum. The pointwise errors
    skip the oracle's first sample: at t = 0 its wall carries no active tension yet (the FE
    beat's initial state, `fe_oracle.coupled_beat`), while the LO pressure at t = 0 already
    carries the tension of its cells at diastolic rest. The two differ there by that resting
    tension, which is large only where the cell's cooperativity is low (nA 1: 0.66 against
    about 2 kPa), and agree from the oracle's first step on."""
    c = float(np.sqrt(congruency(tr, t, v[None], p[None])[0]))
    after = tr["t"] > tr["t"][0]
    v = np.interp(tr["t"][after], t, v)
    p = np.interp(tr["t"][after], t, p)
    return {"C": c, "max_rel_error_V": float(np.max(np.abs(v - tr["V"][after])) / np.max(np.abs(tr["V"]))),
            "max_rel_error_P": float(np.max(np.abs(p - tr["P_lv"][after])) / np.max(np.abs(tr["P_lv"])))}


def generalisation(heart: Heart, scenarios: Mapping[str, Mapping[str, float]] = UNSEEN, backend: str = "dolfinx", *,
                   steps_per_beat: int = 1000, progress: bool | None = None, **oracle_options: Any) -> list[dict[str, Any]]:
    """One row per scenario: its name, the change, C, the pointwise errors, the oracle's cache key,
    and the traces of both (for figures: ``lo`` with ``t``, ``V``, ``P_lv``). The LO beats run as
    one batch, of the model ``heart`` carries (``Heart.elements``: the single cell or a
    multi-element heart; ``oracle_options`` keep ``arrangement`` for the multielement oracle)."""
    hearts = {name: scenario(heart, change) for name, change in scenarios.items()}
    status, t, v, p, _ = one_beat(list(hearts.values()), steps_per_beat)
    traces = [{"t": t[i], "V": v[i], "P_lv": p[i]} for i in range(len(hearts))]
    rows = []
    for i, (name, h) in enumerate(hearts.items()):
        oracle = fe_oracle.run(h.geometry, h.circulation, backend, cell=h.cell, progress=progress, **oracle_options)
        rows.append({"scenario": name, "change": dict(scenarios[name]), **_errors(oracle.traces, traces[i]["t"], traces[i]["V"], traces[i]["P_lv"]),
                     "lo_status": str(status[i]), "oracle_key": oracle.metadata["key"], "oracle": oracle.traces, "lo": traces[i]})
    return rows


def retune(heart: Heart, scenarios: Mapping[str, Mapping[str, float]] = UNSEEN, backend: str = "dolfinx", *,
           names: Sequence[str] = MAP_NAMES, budget: int = 480, steps_per_beat: int = 1000, progress: bool | None = None,
           bounds: Mapping[str, tuple[float, float]] | None = None, **oracle_options: Any) -> list[dict[str, Any]]:
    """One row per scenario: its name, C and the largest pointwise pressure error (``P_error_*``,
    as :func:`generalisation`'s) with ``heart``'s maps frozen and with the LO parameters ``names``
    refitted to that scenario's own oracle beat by :func:`optim.congruency.fit_maps` (MADS
    ``budget`` evaluations from the frozen maps, then least squares, within
    :data:`~optim.congruency.ACTIVE_BOUNDS` and ``bounds``, which a name outside them, e.g. a
    passive map's, needs), with the refitted values, and where each miss
    sits (``where_frozen``, ``where_retuned``: the share of C² per window of the beat and the
    share a pure time shift removes, :func:`optim.diagnosis.decompose`) and the oracle's traces
    (``oracle``). The heart keeps its model (``Heart.elements``)."""
    rows = []
    for name, change in scenarios.items():
        target = scenario(heart, change)
        oracle = fe_oracle.run(target.geometry, target.circulation, backend, cell=target.cell, progress=progress, **oracle_options)

        def hearts(lo: LOParams, change=change) -> list[Heart]:
            return [scenario(dataclasses.replace(heart, lo=lo), change)]

        lo, _ = fit_maps(hearts, [oracle.traces], heart.lo, names, budget=budget, steps_per_beat=steps_per_beat, progress=progress, bounds=bounds)
        _, t, v, p, _ = one_beat([*hearts(heart.lo), *hearts(lo)], steps_per_beat)
        frozen, retuned = (decompose(oracle.traces, t[i], v[i], p[i]) for i in (0, 1))
        p_frozen, p_retuned = (_errors(oracle.traces, t[i], v[i], p[i])["max_rel_error_P"] for i in (0, 1))
        rows.append({"scenario": name, "change": dict(change), "C_frozen": frozen["C"], "C_retuned": retuned["C"],
                     "P_error_frozen": p_frozen, "P_error_retuned": p_retuned,
                     "where_frozen": {k: frozen[k] for k in ("share", "timing_share")}, "where_retuned": {k: retuned[k] for k in ("share", "timing_share")},
                     "retuned": {n: float(getattr(lo, n)) for n in names}, "frozen": {n: float(getattr(heart.lo, n)) for n in names},
                     "oracle_key": oracle.metadata["key"], "oracle": oracle.traces})
    return rows


def _position(heart: Heart, change: Mapping[str, float]) -> float:
    """How far ``change`` (one parameter) moves ``heart`` from its training condition ② along the
    scenario's axis: the parameter's change (Vmax's factor on a log scale, as :data:`SWEEPS`)."""
    ((name, value),) = change.items()
    if name == "tau2_factor":
        return value - 1.0
    start = presets.training_condition(2, heart).get(name)
    return float(np.log(value / start)) if name == "vmax_factor" else value - start


def map_transfer(heart: Heart, scenarios: Mapping[str, Mapping[str, float]] = UNSEEN, backend: str = "dolfinx", *,
                 names: Sequence[str] = MAP_NAMES, budget: int = 480, steps_per_beat: int = 1000,
                 progress: bool | None = None, bounds: Mapping[str, tuple[float, float]] | None = None,
                 **oracle_options: Any) -> list[dict[str, Any]]:
    """Do the maps follow the cell smoothly enough to be regressed on it? :func:`retune` at the
    training beat (condition ②), at each scenario's end and at its :data:`INTERIOR` point; then,
    along each scenario's axis (:func:`_position`), the maps at the end extrapolated linearly from
    the training and interior points' retuned maps, and the maps at the interior point
    interpolated from the training and end points' maps. One row per scenario: its
    :func:`retune` row (the end) with ``C_extrapolated``, and ``interior``: the interior point's
    name, ``C_frozen``, ``C_interpolated`` and ``C_retuned``. Carried maps out of
    :data:`~optim.congruency.ACTIVE_BOUNDS` and ``bounds`` (as :func:`retune`) are clipped into
    them; where the carried passive maps fail `lvenv.params.validate` (a Ppass that is not
    monotone), that C is NaN."""
    unknown = sorted(set(scenarios) - set(INTERIOR))
    if unknown:
        raise InputError(f"scenarios {unknown} have no point inside their axis; map_transfer takes those of INTERIOR: {sorted(INTERIOR)}")
    interior = {INTERIOR[s][0]: INTERIOR[s][1] for s in scenarios}
    rows = {r["scenario"]: r for r in retune(heart, {"training": {}, **scenarios, **interior}, backend, names=names, budget=budget,
                                                    steps_per_beat=steps_per_beat, progress=progress, bounds=bounds, **oracle_options)}
    box = {**ACTIVE_BOUNDS, **(bounds or {})}
    lower, upper = (np.array([box[n][i] for n in names]) for i in (0, 1))

    def maps(name: str) -> np.ndarray:
        return np.array([rows[name]["retuned"][n] for n in names])

    def carried(name: str, values: np.ndarray) -> Heart:
        lo = dataclasses.replace(heart.lo, **dict(zip(names, map(float, np.clip(values, lower, upper)))))
        return scenario(dataclasses.replace(heart, lo=lo), rows[name]["change"])

    # per scenario: its end with the extrapolated maps, its interior point with the interpolated ones
    beats = []
    for name, change in scenarios.items():
        inner = INTERIOR[name][0]
        w = _position(heart, change) / _position(heart, rows[inner]["change"])
        beats += [(name, maps("training") + w * (maps(inner) - maps("training"))), (inner, maps("training") + (maps(name) - maps("training")) / w)]
    hearts = [carried(name, values) for name, values in beats]
    valid = [passes_validation(h) for h in hearts]
    _, t, v, p, _ = one_beat([h if ok else scenario(heart, rows[name]["change"]) for h, ok, (name, _) in zip(hearts, valid, beats)], steps_per_beat)
    c = [_errors(rows[name]["oracle"], t[i], v[i], p[i])["C"] if valid[i] else np.nan for i, (name, _) in enumerate(beats)]
    out = []
    for j, name in enumerate(scenarios):
        inner = INTERIOR[name][0]
        out.append({**rows[name], "C_extrapolated": c[2 * j],
                    "interior": {"scenario": inner, "C_frozen": rows[inner]["C_frozen"], "C_retuned": rows[inner]["C_retuned"], "C_interpolated": c[2 * j + 1]}})
    return out


def multielement_table(geometry=presets.N_UNLOADED, arrangements: Iterable[str] = ("parallel", "series"),
                       sweeps: Mapping[str, Iterable[float]] = SWEEPS, *, budget: int = 480, progress: bool | None = None,
                       **oracle_options: Any) -> list[dict[str, Any]]:
    """One row per (arrangement, sweep, value): C of a single-element LO heart trained to the
    256-element model with that cell (Table 3 maps for the 256 elements; the delay trained only
    when C ≥ 1 % without it)."""
    rows = []
    base = CellParams()
    for kind in arrangements:
        for name, values in sweeps.items():
            for value in values:
                change = {"tau2": float(value) * base.tau2} if name == "tau2_factor" else {name: float(value)}
                cell = dataclasses.replace(base, **change)
                trained = train(geometry, "multielement", cell=cell, arrangement=kind, budget=budget, progress=progress, **oracle_options)
                rows.append({"arrangement": kind, "sweep": name, "value": float(value), **trained.congruency,
                             "delay": trained.lo.delay, "C_without_delay": None if trained.congruency_without_delay is None else trained.congruency_without_delay["C"]})
    return rows
