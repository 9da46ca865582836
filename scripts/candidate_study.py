"""Candidate low-order hearts trained against the same FE runs (issue 30, item 2); JSON out.

    python scripts/candidate_study.py dataset [--anatomies H000 H001 ...] [--budget 480] [--out out/diagnosis]
    python scripts/candidate_study.py hearts [--hearts normal heart_failure] [--dt 0.005] [--mesh-size 6] [--no-unseen] [--budget 480] [--out out/diagnosis]
    python scripts/candidate_study.py retune [--hearts normal heart_failure] [--candidates single series3-onsets] [--budget 480] [--out out/diagnosis]

The candidates (`CANDIDATES`):

* **single**: the single-cell heart with its activation delay, as trained;
* **series-onsets**: 5 cells in series (sharing the pressure, equal volume shares) whose
  calcium transients start at the 5, 27.5, 50, 72.5 and 95 % quantiles of the wall's activation
  times, centred on their median (`lvenv.params.Arrangement.onsets`): the early cells
  stretch the late ones, which then pull harder (length dependence) and relax later, as the
  wall's most loaded points do (`scripts/wall_diagnosis.py`);
* **parallel-onsets**: the same 5 onsets with the cells in parallel (sharing the volume);
* **series3-onsets**: 3 cells in series with onsets at the 5, 50 and 95 % quantiles: fewer
  cells cost less per beat (`scripts/bench_candidates.py`), which the issue's cost goal (≤ 4×
  the single cell) needs; the model shipped as `lvenv.presets.LO_MODELS["series3"]`;
* **series2-onsets**, **series4-onsets**: 2 and 4 cells in series (quantiles evenly spaced over
  5–95 %), to see how C depends on the number of cells;
* **single-relax**, **series3-relax** (dataset mode only): the single cell, or series3-onsets,
  with a relaxation term: the LO cells' calcium transient decays with τ2 × r instead of the
  wall's τ2 (one more trained parameter, r; the delay shifts the whole transient, decay
  included, so a delay that matches the upstroke may relax the LO heart too late). r is chosen
  on `RELAX_GRID`, {μ1, μ2, γ, delay} refitted at each r;
* **single-filling**, **series3-filling**: with a filling term: the passive map's linear
  stiffness c (kPa), trained on the quasi-static inflation alone, refitted on the beats beside
  {μ1, μ2, γ, delay} (within [1.05 b²/(3a), 4c], where Ppass stays monotone): whether the
  error of relaxation and early filling is the passive map's;
* **series3-weights**: series3-onsets with unequal cells: the cells' weights w_ξ (each cell's
  passive stiffness and strength, `lvenv.multielement`: a region of the wall that is more or less
  loaded per unit of cavity pressure) linear over (1 − s, 1 + s), for each spread s of
  `WEIGHT_SPREADS` and each of the 6 ways to give the three onsets to the three cells, with
  {μ1, μ2, γ, delay} refitted at each (each fit logged); the best of the 18 is the candidate
  (about 4 min per heart). A fitted spread and order bound what volume shares set from the
  wall's stretch distribution could do;
* **series3-passive**: series3-onsets with the whole passive map {α, β, a, b, c} refitted on the
  beats beside {μ1, μ2, γ, delay}, each within a factor `optim.congruency.PASSIVE_FREEDOM` of its
  value fitted to the inflation: nine trained parameters, the most the LO maps can give on the
  beats, at the cost of the inflation curve (its RMS volume residual: the hearts table's
  "inflation", and the JSON).

The anatomy sets the onsets (`optim.congruency.wall_arrangement`, at the quantiles of
`lvenv.presets.onset_quantiles`; `fe_oracle.activation.activation_quantiles` on its oracle mesh:
meshing and the eikonal solve, seconds, no mechanics). Training refits only {μ1, μ2, γ, delay}
from the single cell's trained values (`optim.congruency.fit_active` with the arrangement, MADS
budget ``--budget``); the passive maps stay, but for the filling and passive candidates.

``dataset``: each anatomy of the campaign's dataset (`optim.campaign.oracle_data`: its FE
training beats, no FE run; default: the 5 held-out anatomies and the first 5 training ones), C
on its training beats and its C² per window of the beat (`optim.diagnosis`); writes
``--out``/candidates_dataset.md.

``hearts``: the built-in trained hearts (N, HF), trained on their own FE training beats
(`optim.congruency.oracle_data` at the oracle's mesh size ``--mesh-size``, default 6 mm, and time
step ``--dt``; FE runs cached; on another mesh the passive map is first refitted on that mesh's
inflation, and the single cell's maps are refitted too) and
then run, maps frozen, in the unseen scenarios of `optim.studies.UNSEEN`
(`optim.studies.generalisation` with the arrangement; ``--no-unseen`` skips them): C and the
largest pointwise pressure error per scenario, beside the issue's goals (training C ≤ 2 %;
unseen C ≤ 5 % and pressure error ≤ 10 %); with ``--dt`` or ``--mesh-size``, also C between the
oracle's own training beats at its defaults and at these. Writes ``--out``/candidates_hearts[_dt<ms>][_h<mm>].md and
.png (FE solid, the single cell dashed, each other candidate dotted).

``retune``: as ``hearts`` (default candidates: single and series3-onsets), then in each unseen
scenario the maps the candidate trains ({μ1, μ2, γ, delay}; series3-passive also its passive
map, in the same boxes, :func:`refitted`) refitted on that scenario's own FE beat
(`optim.studies.retune`, MADS budget ``--budget``, then least squares): C and the largest
pointwise pressure error with the maps frozen against both with the maps retuned. The retuned C
is how close the candidate can come to the scenario's beat at all; the gap between the two is
what the maps' not carrying over costs.
Then whether maps regressed on the cell would carry over (`optim.studies.map_transfer`): the
maps refitted at the training beat and at a point inside each scenario's axis
(`optim.studies.INTERIOR`, 8 more FE beats per heart, shipped), carried linearly to the
scenario's end, and back. Writes ``--out``/candidates_retune.md.

Each candidate costs about a minute per anatomy on one core. The hearts mode's FE runs at the
oracle's own time step and mesh ship with the package (`scripts/ship_fe_runs.py`); another ``--dt``
or ``--mesh-size`` costs a passive inflation and 3 FE beats per heart (8 more with the unseen
scenarios) when the cache is cold: about 6 min per beat at h = 4 mm on one core.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import pathlib
import sys
import time
from collections.abc import Iterator

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from lvenv import presets  # noqa: E402
from lvenv.params import Arrangement, Heart, LOParams  # noqa: E402
from lvenv.plots import generalisation_figure  # noqa: E402
from lvenv.trained import builtin  # noqa: E402
from optim import campaign, congruency, diagnosis  # noqa: E402
from optim.studies import UNSEEN, generalisation, map_transfer  # noqa: E402
from scripts.ship_fe_runs import add_oracle_arguments, oracle_options, oracle_setting  # noqa: E402
from scripts.train_presets import HEARTS  # noqa: E402

#: The multi-element candidates: name → (arrangement kind, cells).
ARRANGED = {"series-onsets": ("series", 5), "parallel-onsets": ("parallel", 5), "series3-onsets": ("series", 3),
            "series2-onsets": ("series", 2), "series4-onsets": ("series", 4)}
#: Candidates with more trained terms: name → (the candidate they extend, "relax", "filling", "weights" or "passive").
EXTENDED = {"single-relax": ("single", "relax"), "series3-relax": ("series3-onsets", "relax"),
            "single-filling": ("single", "filling"), "series3-filling": ("series3-onsets", "filling"),
            "series3-weights": ("series3-onsets", "weights"), "series3-passive": ("series3-onsets", "passive")}
#: The relaxation-term candidates (dataset mode only: the LO cell's τ2 is not an LO parameter).
RELAXED = tuple(name for name, (_, term) in EXTENDED.items() if term == "relax")
#: The decay factors r a relaxation-term candidate is trained over (the LO cell's τ2 is the wall's × r).
RELAX_GRID = (0.85, 0.9, 0.95, 1.0, 1.05)
#: The spreads s a weights candidate is trained over (its cells' w_ξ linear over 1 − s .. 1 + s).
WEIGHT_SPREADS = (0.1, 0.2, 0.3)
CANDIDATES = ("single", *ARRANGED, *EXTENDED)
#: The issue's goals: C on the training beats, C in an unseen scenario, its largest pressure error.
GOALS = {"training_C": 0.02, "unseen_C": 0.05, "unseen_pressure_error": 0.10}


def arrangement(name: str, data: congruency.OracleData, lo: LOParams) -> Arrangement | None:
    """The multi-element arrangement of candidate ``name`` with ``data``'s wall's onsets (None: the single cell)."""
    if name == "single":
        return None
    kind, cells = ARRANGED[name]
    return congruency.wall_arrangement(kind, cells, (1.0, 1.0) if kind == "series" else (lo.mu1, lo.mu1), data)


def refitted(name: str, trained: LOParams) -> tuple[tuple[str, ...], dict[str, tuple[float, float]] | None]:
    """The LO parameters candidate ``name`` trains, and the boxes of those outside
    `optim.congruency.ACTIVE_BOUNDS`, set from the single cell's ``trained`` maps (None: none)."""
    term = EXTENDED.get(name, (name, None))[1]
    if term == "filling":
        return (*congruency.MAP_NAMES, "c"), {"c": (1.05 * trained.b**2 / (3.0 * trained.a), 4.0 * trained.c)}
    return congruency.map_refit(trained, term == "passive")


def relaxed(data: congruency.OracleData, r: float) -> congruency.OracleData:
    """``data`` with the LO cells' calcium decay time constant τ2 × ``r`` (the FE beats unchanged)."""
    return dataclasses.replace(data, cell=dataclasses.replace(data.cell, tau2=data.cell.tau2 * r))


def train(data: congruency.OracleData, trained: LOParams, names, budget: int, refit_single: bool = False) -> dict:
    """Each candidate of ``names`` on ``data`` (its wall's onsets, :func:`arrangement`), from the
    single cell's ``trained`` maps (the single cell keeps them unless ``refit_single``): name →
    (maps, C per training beat, arrangement, seconds, decay factor r: 1 but for :data:`RELAXED`,
    the best of :data:`RELAX_GRID`)."""
    out = {}
    for name in names:
        t0 = time.perf_counter()
        base, term = EXTENDED.get(name, (name, None))
        arr = arrangement(base, data, trained)
        r = 1.0
        if term == "relax":
            fits = {r: congruency.fit_active(relaxed(data, r), trained, congruency.MAP_NAMES, budget=budget, arrangement=arr) for r in RELAX_GRID}
            r = min(fits, key=lambda k: congruency.overall(fits[k][1]))
            lo, c = fits[r]
        elif term == "weights":
            arrs = [dataclasses.replace(arr, spread=(1.0 - s, 1.0 + s), onsets=tuple(arr.onsets[i] for i in order))
                    for order in itertools.permutations(range(arr.n_elements)) for s in WEIGHT_SPREADS]
            fits = []
            for a in arrs:
                fits.append(congruency.fit_active(data, trained, congruency.MAP_NAMES, budget=budget, arrangement=a))
                cells = ", ".join(f"{w:.1f} at {1000 * t:+.0f} ms" for w, t in zip(a.element_values(), a.element_onsets()))
                print(f"{data.geometry} {name}: w {cells}: C {100 * congruency.overall(fits[-1][1]):.2f} %", file=sys.stderr, flush=True)
            best = min(range(len(fits)), key=lambda i: congruency.overall(fits[i][1]))
            (lo, c), arr = fits[best], arrs[best]
        elif term in ("filling", "passive"):
            maps, box = refitted(name, trained)
            lo, c = congruency.fit_active(data, trained, maps, budget=budget, arrangement=arr, bounds=box)
        elif arr is None and refit_single:
            lo, c = congruency.fit_active(data, trained, congruency.MAP_NAMES, budget=budget)
        elif arr is None:
            lo, c = trained, congruency.run_congruency(data, [trained])[0]
        else:
            lo, c = congruency.fit_active(data, trained, congruency.MAP_NAMES, budget=budget, arrangement=arr)
        out[name] = (lo, c, arr, time.perf_counter() - t0, r)
        print(f"{data.geometry} {name}: C {100 * congruency.overall(c):.2f} % (r {r:g})", file=sys.stderr, flush=True)
    return out


def window_c2(data: congruency.OracleData, lo: LOParams, arr: Arrangement | None) -> dict:
    """C² of each window of the beat (:data:`optim.diagnosis.WINDOWS`) of the LO heart ``lo`` on ``data``."""
    split = diagnosis.diagnose(data, lo, arrangement=arr)
    return {w: split["C"] ** 2 * share for w, share in split["share"].items()}


def _summary(data: congruency.OracleData, lo: LOParams, c: np.ndarray, seconds: float, r: float, arr: Arrangement | None) -> dict:
    """A trained candidate's C, its maps, its cells' weights w_ξ and onsets (ms; cells in series),
    and the RMS volume residual of its passive heart on the oracle's inflation (ml)."""
    cells = {} if arr is None or arr.kind != "series" else {"weights": arr.element_values().tolist(), "cell_onsets_ms": (1000 * arr.element_onsets()).tolist()}
    return {"C": float(congruency.overall(c)), "C_beats": c.tolist(), "seconds": seconds, "relax": r, **cells,
            "inflation_rms_ml": float(np.sqrt(np.mean(congruency.passive_residual(data, lo, arr) ** 2))),
            **{k: getattr(lo, k) for k in (*congruency.MAP_NAMES, *congruency.PASSIVE_NAMES)}}


def dataset_mode(args, command: str) -> dict:
    rows = [r for r in campaign.read_index(campaign.DATASET) if r["status"] == "accepted"]
    if args.anatomies:
        unknown = sorted(set(args.anatomies) - {r["id"] for r in rows})
        if unknown:
            sys.exit(f"--anatomies {unknown}: not accepted anatomies of {campaign.DATASET}")
        rows = [r for r in rows if r["id"] in args.anatomies]
    else:
        rows = [r for r in rows if r["split"] == "heldout"] + [r for r in rows if r["split"] == "train"][:5]
    results = []
    for row in rows:
        data = campaign.oracle_data(campaign.DATASET, row["id"])
        trained = LOParams(**{f.name: row[f.name] for f in dataclasses.fields(LOParams)})
        fits = train(data, trained, args.candidates, args.budget)
        results.append({"id": row["id"], "onsets_ms": [1000 * x for x in congruency.wall_arrangement("series", 5, (1.0, 1.0), data).onsets],
                        **{name: {**_summary(data, lo, c, s, r, arr), "window_C2": window_c2(relaxed(data, r), lo, arr)}
                           for name, (lo, c, arr, s, r) in fits.items()}})
    medians = {name: float(np.median([r[name]["C"] for r in results])) for name in args.candidates}
    windows = {name: {w: float(np.median([r[name]["window_C2"][w] for r in results])) for w in diagnosis.WINDOWS} for name in args.candidates}
    lines = [f"Made by `{command}`: each candidate trained on each anatomy's own FE training beats (campaign dataset, "
             f"{oracle_setting()}; no FE run). C on the training beats, in %.", "",
             "Median over the anatomies: " + ", ".join(f"{n} {100 * m:.2f} %" for n, m in medians.items()) + ".", "",
             "| anatomy | 5 cells' onsets (ms) | " + " | ".join(args.candidates) + " |", "|---|---|" + "---|" * len(args.candidates)]
    cell = lambda fit: f"{100 * fit['C']:.2f}" + (f" (r {fit['relax']:g})" if fit["relax"] != 1.0 else "")
    lines += [f"| {r['id']} | {', '.join(f'{x:+.0f}' for x in r['onsets_ms'])} | " + " | ".join(cell(r[n]) for n in args.candidates) + " |"
              for r in results]
    lines += ["", "Where the error sits: C² of each window of the beat (`optim.diagnosis`; valve events of the FE beat), median over the "
              "anatomies, × 10⁻⁴ (the medians of the windows need not add up to the median C²).", "",
              "| candidate | " + " | ".join(diagnosis.WINDOWS) + " |", "|---|" + "---|" * len(diagnosis.WINDOWS)]
    lines += [f"| {n} | " + " | ".join(f"{1e4 * windows[n][w]:.1f}" for w in diagnosis.WINDOWS) + " |" for n in args.candidates]
    (args.out / "candidates_dataset.md").write_text("\n".join(lines) + "\n")
    return {"median_C": medians, "median_window_C2": windows, "anatomies": results}


def trained_hearts(args, oracle: dict) -> Iterator[tuple[str, Heart, congruency.OracleData, dict]]:
    """Each built-in heart of ``--hearts``, its name, its FE training data and its ``--candidates``
    trained on them (the oracle's options ``oracle``; :func:`train`). On another mesh than the
    trained maps', the passive map is refitted on that mesh's inflation first
    (:func:`optim.congruency.fit_passive`), and the single cell's {μ1, μ2, γ, delay} too."""
    for heart_name in args.hearts:
        heart = getattr(presets, heart_name)()
        data = congruency.oracle_data(heart.geometry, cell=heart.cell, progress=False, **oracle)
        start, remeshed = builtin(heart_name).lo, "mesh_size" in oracle
        if remeshed:
            start = congruency.fit_passive(data, start)[0]
        yield heart_name, heart, data, train(data, start, args.candidates, args.budget, refit_single=remeshed)


def oracle_change(data: congruency.OracleData, default: congruency.OracleData) -> list[float]:
    """C (1) between each training beat of ``default`` (the oracle at its own mesh and time step)
    and the same beat of ``data`` (the oracle at other options), per condition: how much of a
    candidate's C the oracle's own discretisation could be."""
    out = []
    for k in congruency.CONDITIONS:
        base = default.beats[k].traces
        out.append(float(np.sqrt(congruency.congruency(data.beats[k].traces, np.asarray(base["t"]), np.asarray(base["V"])[None], np.asarray(base["P_lv"])[None])[0])))
    return out


def hearts_mode(args, command: str) -> dict:
    results, figure_rows = [], []
    oracle = oracle_options(args)
    scenarios = {} if args.no_unseen else UNSEEN
    suffix = ("" if args.dt is None else f"_dt{1000 * args.dt:g}ms") + ("" if args.mesh_size is None else f"_h{args.mesh_size:g}mm")
    for heart_name, heart, data, fits in trained_hearts(args, oracle):
        entry = {"heart": heart_name, "candidates": {}}
        if oracle:
            entry["oracle_change"] = oracle_change(data, congruency.oracle_data(heart.geometry, cell=heart.cell, progress=False))
        traces = {}
        for name, (lo, c, arr, seconds, factor) in fits.items():
            rows = generalisation(dataclasses.replace(heart, lo=lo, elements=arr), scenarios, progress=False, **oracle) if scenarios else []
            entry["candidates"][name] = {"training": _summary(data, lo, c, seconds, factor, arr),
                                         "unseen": {r["scenario"]: {k: r[k] for k in ("C", "max_rel_error_P", "max_rel_error_V", "lo_status")} for r in rows}}
            traces[name] = rows
        results.append(entry)
        for i, r in enumerate(traces[args.candidates[0]]):
            figure_rows.append({**r, "heart": heart_name, "candidates": {n: traces[n][i]["lo"] for n in args.candidates[1:]}})
    unseen_text = (", then run with its maps frozen in the unseen scenarios (one beat under condition ②, one parameter changed), "
                   "given as C / largest pressure error (both %). " if scenarios else "; no unseen scenario run. ")
    lines = [f"Made by `{command}`: each candidate trained on the heart's own FE training beats ({oracle_setting(args)})" + unseen_text +
             f"Goals: training C ≤ {100 * GOALS['training_C']:g} %, unseen C ≤ {100 * GOALS['unseen_C']:g} % and largest pressure "
             f"error ≤ {100 * GOALS['unseen_pressure_error']:g} %. Inflation: the RMS volume residual of the candidate's passive map on "
             "the FE's quasi-static inflation curve. The weights candidate's cells: weight w at onset (relative to the median "
             "activation time).", "",
             "| " + " | ".join(["heart", "candidate", "training C (① ② ③)", "inflation (ml)", *scenarios, "worst unseen C",
                                "worst pressure error"]) + " |",
             "|---|---|---|---|" + "---|" * len(scenarios) + "---|---|"]
    for entry in results:
        for name, cand in entry["candidates"].items():
            unseen = cand["unseen"]
            beats = " ".join(f"{100 * x:.1f}" for x in cand["training"]["C_beats"])
            worst = (f"{100 * max(u['C'] for u in unseen.values()):.1f} | {100 * max(u['max_rel_error_P'] for u in unseen.values()):.0f}"
                     if unseen else "– | –")
            training = cand["training"]
            label = name
            if any(w != 1.0 for w in training.get("weights", ())):
                label += " (w " + ", ".join(f"{w:.1f} at {t:+.0f} ms" for w, t in zip(training["weights"], training["cell_onsets_ms"])) + ")"
            cells = [entry["heart"], label, f"{100 * cand['training']['C']:.2f} ({beats})", f"{cand['training']['inflation_rms_ml']:.2f}",
                     *(f"{100 * unseen[s]['C']:.1f} / {100 * unseen[s]['max_rel_error_P']:.0f}" for s in scenarios), worst]
            lines.append("| " + " | ".join(cells) + " |")
    if oracle:
        lines += ["", f"The oracle's own change: C between its training beats at its default ({oracle_setting()}) and these "
                  "(① ② ③, %): " + "; ".join(f"{e['heart']} " + " ".join(f"{100 * x:.2f}" for x in e["oracle_change"]) for e in results) + "."]
    name = f"candidates_hearts{suffix}"
    (args.out / f"{name}.md").write_text("\n".join(lines) + "\n")
    if figure_rows:
        generalisation_figure(figure_rows, args.out / f"{name}.png", columns=len(scenarios))
    return {"hearts": results}


def frozen_to_retuned(results: list[dict], measure: str) -> list[str]:
    """A markdown table of ``measure`` (``C`` or ``P_error``) in each unseen scenario, frozen →
    retuned (%), one row per heart and candidate of ``results``, and the worst of each."""
    lines = ["| heart | candidate | " + " | ".join(UNSEEN) + " | worst, frozen → retuned |", "|---|---|" + "---|" * (len(UNSEEN) + 1)]
    for r in results:
        u = r["unseen"]
        cells = [f"{100 * u[s][f'{measure}_frozen']:.1f} → {100 * u[s][f'{measure}_retuned']:.1f}" for s in UNSEEN]
        worst = " → ".join(f"{100 * max(x[f'{measure}_{k}'] for x in u.values()):.1f}" for k in ("frozen", "retuned"))
        lines.append(f"| {r['heart']} | {r['candidate']} | " + " | ".join(cells) + f" | {worst} |")
    return lines


def retune_mode(args, command: str) -> dict:
    results = []
    for heart_name, heart, data, fits in trained_hearts(args, {}):
        for name, (lo, c, arr, seconds, factor) in fits.items():
            t0 = time.perf_counter()
            maps, box = refitted(name, builtin(heart_name).lo)
            rows = map_transfer(dataclasses.replace(heart, lo=lo, elements=arr), UNSEEN, names=maps, budget=args.budget, progress=False, bounds=box)
            keep = ("C_frozen", "C_retuned", "P_error_frozen", "P_error_retuned", "C_extrapolated", "retuned", "where_frozen", "where_retuned", "interior")
            results.append({"heart": heart_name, "candidate": name, "training": _summary(data, lo, c, seconds, factor, arr), "retune_seconds": time.perf_counter() - t0,
                            "unseen": {r["scenario"]: {k: r[k] for k in keep} for r in rows}})
    lines = [f"Made by `{command}`: each candidate trained on the heart's own FE training beats ({oracle_setting()}), then in each "
             "unseen scenario C with its maps frozen → C with the maps it trains refitted on that scenario's own FE beat "
             "(`optim.studies.retune`; {μ1, μ2, γ, delay}, and also the passive map for series3-passive), both %. "
             "The second is how close the candidate comes to the beat at all; the gap is what "
             f"the trained maps' not carrying over costs. Goal: unseen C ≤ {100 * GOALS['unseen_C']:g} %.", "",
             *frozen_to_retuned(results, "C")]
    lines += ["", "The largest pointwise pressure error (relative to the FE beat's peak), frozen → retuned (%): the retuned maps "
              f"minimise C, not this error. Goal: ≤ {100 * GOALS['unseen_pressure_error']:g} %.", "", *frozen_to_retuned(results, "P_error")]
    lines += ["", "The retuned maps, each over the trained value (μ1 / μ2; γ and the delay in the JSON):", "",
              "| heart | candidate | " + " | ".join(UNSEEN) + " |", "|---|---|" + "---|" * len(UNSEEN)]
    for r in results:
        ratio = lambda s, n: r["unseen"][s]["retuned"][n] / r["training"][n]
        lines.append(f"| {r['heart']} | {r['candidate']} | " + " | ".join(f"{ratio(s, 'mu1'):.2f} / {ratio(s, 'mu2'):.2f}" for s in UNSEEN) + " |")
    lines += ["", "Where the frozen maps miss: the window of the beat (`optim.diagnosis`) with the largest share of C², and the "
              "share a pure time shift removes:", "",
              "| heart | candidate | " + " | ".join(UNSEEN) + " |", "|---|---|" + "---|" * len(UNSEEN)]
    for r in results:
        def where(s: str) -> str:
            w = r["unseen"][s]["where_frozen"]
            top = max(w["share"], key=w["share"].get)
            return f"{top} {100 * w['share'][top]:.0f} %, shift {max(0.0, 100 * w['timing_share']):.0f} %"
        lines.append(f"| {r['heart']} | {r['candidate']} | " + " | ".join(where(s) for s in UNSEEN) + " |")
    lines += ["", "Maps carried along each scenario's axis (`optim.studies.map_transfer`), as a regression of the maps on the cell "
              "would carry them: at the scenario's end, C frozen / with the maps extrapolated linearly from those refitted at the "
              "training beat and at the interior point / refitted; at the interior point, C frozen / with the maps interpolated "
              "from those at the training beat and the end / refitted (%):", "",
              "| heart | candidate | " + " | ".join(UNSEEN) + " | worst end: frozen / extrapolated / refitted |", "|---|---|" + "---|" * (len(UNSEEN) + 1)]
    for r in results:
        u = r["unseen"]
        def carried(s: str) -> str:
            inner = u[s]["interior"]
            return (f"{100 * u[s]['C_frozen']:.1f} / {100 * u[s]['C_extrapolated']:.1f} / {100 * u[s]['C_retuned']:.1f}; "
                    f"{inner['scenario']}: {100 * inner['C_frozen']:.1f} / {100 * inner['C_interpolated']:.1f} / {100 * inner['C_retuned']:.1f}")
        worst = " / ".join(f"{100 * np.max([x[k] for x in u.values()]):.1f}" for k in ("C_frozen", "C_extrapolated", "C_retuned"))
        lines.append(f"| {r['heart']} | {r['candidate']} | " + " | ".join(carried(s) for s in UNSEEN) + f" | {worst} |")
    (args.out / "candidates_retune.md").write_text("\n".join(lines) + "\n")
    return {"results": results}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("mode", choices=("dataset", "hearts", "retune"))
    parser.add_argument("--anatomies", nargs="+", help="dataset mode: dataset ids (default: the held-out anatomies and the first 5 training ones)")
    parser.add_argument("--hearts", nargs="+", choices=sorted(HEARTS), default=sorted(HEARTS), help="hearts and retune modes: the built-in hearts")
    parser.add_argument("--candidates", nargs="+", choices=CANDIDATES,
                        help="default: every candidate (hearts mode: but the relaxation-term ones; retune mode: single and series3-onsets)")
    add_oracle_arguments(parser, "hearts mode: ")
    parser.add_argument("--no-unseen", action="store_true", help="hearts mode: the training beats only")
    parser.add_argument("--budget", type=int, default=480, help="MADS evaluations per active fit")
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("out/diagnosis"))
    args = parser.parse_args()
    if args.candidates is None:
        args.candidates = ["single", "series3-onsets"] if args.mode == "retune" else [n for n in CANDIDATES if args.mode == "dataset" or n not in RELAXED]
    if args.mode != "dataset" and set(args.candidates) & set(RELAXED):
        parser.error(f"--candidates {sorted(set(args.candidates) & set(RELAXED))}: the relaxation-term candidates run in the dataset mode only "
                     "(the unseen scenarios would run their LO cell with the wall's τ2)")
    if args.mode != "hearts" and (args.dt is not None or args.mesh_size is not None or args.no_unseen):
        parser.error("--dt, --mesh-size and --no-unseen are options of the hearts mode: the dataset mode reads the campaign's FE traces "
                     "and the retune mode runs the unseen scenarios, both at the oracle's own time step and mesh")
    args.out.mkdir(parents=True, exist_ok=True)
    command = "python scripts/candidate_study.py " + " ".join(sys.argv[1:])
    result = {"dataset": dataset_mode, "hearts": hearts_mode, "retune": retune_mode}[args.mode](args, command)
    print(json.dumps({"mode": args.mode, "budget": args.budget, "onset_quantiles": {n: presets.onset_quantiles(c) for n, (_, c) in ARRANGED.items()}, **result}, indent=1, default=float))


if __name__ == "__main__":
    main()
