"""Fit the built-in patients with MADS, CMA-ES, kriging and least squares with autodiff
Jacobians (lm); print the table (mmHg, ms). Beside the point fits, each patient's amortised
posterior (optim.amortised: median and 90 % interval per parameter; by default its flow draws
importance-weighted by the exact posterior density, optim.identify.amortised) and, from the two
patients' independent posterior draws, P(Sa_HF < Sa_N) and P(tau2_HF > tau2_N): what the data say about
the paper's question, where the four methods' point ratios disagree.

    python scripts/fit_patients.py [--budget 480] [--num-envs 16] [--out out/fit]
    python scripts/fit_patients.py --synthetic 10 --method cma     # synthetic recovery
    python scripts/fit_patients.py --fidelity [--fidelity-mesh 6]  # also check each patient's best fit against the 3-D oracle
    python scripts/fit_patients.py --fidelity --retune-maps        # and refit the maps on that FE beat: the model's own floor there
    python scripts/fit_patients.py --correct-maps 1 --methods cma  # fit again with the maps refitted on the FE beat, check again
    python scripts/fit_patients.py --correct-maps 1 --refit-passive # the passive maps refitted too
    python scripts/fit_patients.py --correct-maps 1 --aortic-weight 1 # the refits weigh the aortic pressure in
    python scripts/fit_patients.py --posterior-samples 0            # point fits only
    python scripts/fit_patients.py --importance 0                   # the flow's own draws, not reweighted
    python scripts/fit_patients.py --model series3 --fidelity      # the 3-cell series LO heart (lvenv.presets.LO_MODELS)

``--model``: the LO heart the patients' hearts carry (default the single cell). The env then runs
that model (a multi-element one with the fixed scheme at ``--steps-per-beat``); the amortised
posteriors, trained on the single cell, are shown for the single cell only.

``--retune-maps`` (with ``--fidelity``): {μ1, μ2, γ, delay} refitted on the FE beat at each
patient's best fit (`optim.congruency.check_fidelity` with ``retune``; MADS, 480 evaluations,
then least squares, a minute or two), and FE − LO shown again with the refitted maps. The
trained maps' miss less the refitted maps' miss is what maps trained at the fitted parameters
(a regression of the maps on the cell and the circulation) could recover; what stays is the LO
model's own floor at that heart.

``--correct-maps K`` (`optim.fit.corrected_fit`): K rounds of refitting the maps on the FE beat
at the patient's best fit and fitting the patient again with them (``--methods``), then the FE
check of the last fit: each round costs one FE run (``--fidelity-beats`` beats, about 2 min
each at h = 6 mm), one refit of the maps and one fit.

``--refit-passive`` (with ``--retune-maps`` or ``--correct-maps``): the refits move the passive
maps {α, β, a, b, c} too, each within its trained value ÷ and × 10
(`optim.congruency.map_refit`); a refit of the nine maps takes about a minute on one core.

``--aortic-weight W`` (with ``--retune-maps`` or ``--correct-maps``): the refits minimise
C² + W A², A the aortic pressure trace's misfit on the FE beat (`optim.congruency.fit_maps`),
not C² alone.

With ``--fidelity`` or ``--correct-maps``, each patient's checks are also written as a table,
with the command that made them, to ``<out>/fidelity_<patient>_<model>[_passive][_aorticW].md``
(`optim.report.fidelity_file`), which `lvenv report` shows on the inverse-problem page.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import math
import shlex
import sys
from pathlib import Path
from typing import NamedTuple

import numpy as np

from fe_oracle import DEFAULT_MESH_SIZE
from lvenv.cli import IMPORTANCE_PER_SAMPLE
from lvenv.identification import ACTION_BOUNDS
from lvenv.patients import builtin
from lvenv.presets import LO_MODELS
from lvenv.metrics import METRICS, display, header
from lvenv.plausibility import report, resolve
from optim.congruency import FIDELITY_TOLERANCE, Fidelity, check_fidelity, difference_unit, format_difference, map_refit
from optim.report import fidelity_file
from optim.fit import FitRow, corrected_fit, fit_patients, synthetic_recovery


def _show(name: str, value: float) -> str:
    return display(name, value, 1)


def _param(name: str, value: float) -> str:
    return f"{1000 * value:.0f}" if name == "tau2" else f"{value:.4g}"


def _param_head(name: str) -> str:
    """The column head of fitted parameter ``name``, with the units :func:`_param` shows it in."""
    return f"{name} ({'ms' if name == 'tau2' else ACTION_BOUNDS[name].units})"


class Check(NamedTuple):
    """One fidelity check of a patient's fit as the table shows it: which maps the heart carried
    (``maps``, in words), the fit (`optim.fit.FitRow`) and the oracle's check (`optim.congruency.Fidelity`)."""

    maps: str
    fit: FitRow
    fidelity: Fidelity


def print_fits(rows, plausibility: bool = True) -> None:
    names = list(rows[0].parameters)
    targets = list(rows[0].targets)
    heads = [_param_head(n) for n in names]
    tcols = [f"{header(t)} fit/target [err %]" for t in targets]
    print("patient        method   " + " | ".join(heads))
    for r in rows:
        print(f"{r.patient:14s} {r.method:8s} " + " | ".join(f"{_param(n, r.parameters[n]):>{len(h)}s}" for n, h in zip(names, heads)))
    print()
    shown = [b.metric for b in resolve(True)]  # reported whether or not their bands are in force
    bcols = [header(m) for m in shown]
    print("patient        method   " + " | ".join(tcols + bcols) + " | mismatch % | evals | wall s | evals/s to <3 %")
    for r in rows:
        cells = [f"{_show(t, r.observation[t])}/{_show(t, r.targets[t])} [{100 * r.mismatch_per_target[t]:.2f}]" for t in targets]
        checks = report(r.observation)  # against the documented bands, in the objective or not
        cells += [f"{_show(m, r.observation[m])}{'' if checks[m]['inside'] else ' OUT'}" for m in shown]
        to3 = "never" if r.evaluations_to_3pct is None else f"{r.evaluations_to_3pct}/{r.wall_time_to_3pct:.1f}"
        print(f"{r.patient:14s} {r.method:8s} " + " | ".join(f"{c:>{len(h)}s}" for c, h in zip(cells, tcols + bcols))
              + f" | {100 * r.mismatch:10.2f} | {r.evaluations:5d} | {r.wall_time:6.1f} | {to3}")
    print("OUT: outside " + ", ".join(b.describe() for b in resolve(True)) + " (lvenv.plausibility); in the objective: "
          + ", ".join(b.metric for b in resolve(plausibility)))
    compile_times = {(r.patient, "lm" if r.method == "lm" else "env"): r.compile_time for r in rows}
    print("\none-off JIT compilation (s, not in wall; the env's per patient, lm's warm-up run): "
          + ", ".join(f"{p} {kind} {v:.1f}" for (p, kind), v in compile_times.items()))
    if any(r.method == "lm" for r in rows):
        print("lm: each evaluation is a steady state and its tangents (optim.lm), at the fixed steps per beat; "
              "budget and starts: optim.fit.DEFAULT_OPTIONS")
    by = {(r.patient, r.method): r for r in rows}
    if {"normal", "heart_failure"} <= {r.patient for r in rows}:
        print("\nHF / N fitted parameter ratio per method:")
        for m in dict.fromkeys(r.method for r in rows):
            a, b = by.get(("normal", m)), by.get(("heart_failure", m))
            if a and b:
                print(f"  {m:8s} " + "  ".join(f"{n} ×{b.parameters[n] / a.parameters[n]:.2f}" if a.parameters[n] else f"{n} n/a" for n in names))


def print_posteriors(patients, n_samples: int, seed: int, importance: int) -> None:
    """Each patient's amortised posterior (median [5 %, 95 %]; tau2 in ms), its ``importance`` flow
    draws reweighted by the exact posterior where > 0, and, for N and HF, P(Sa_HF < Sa_N) and
    P(tau2_HF > tau2_N) over all pairs of their independent draws (optim.identify.probability_lower)."""
    from optim.identify import identify_patients
    from optim.identify import probability_lower

    answers = {a.patient: a for a in identify_patients([builtin(p) for p in patients], n_samples, seed=seed, importance=importance)}
    names = list(ACTION_BOUNDS)
    heads = [_param_head(n) for n in names]
    cells = {p: [f"{_param(n, a.posterior.median[n])} [{_param(n, a.posterior.interval_90[n][0])}, {_param(n, a.posterior.interval_90[n][1])}]"
                 for n in names] if a.posterior is not None else ["—"] * len(names) for p, a in answers.items()}
    widths = [max(len(h), *(len(c[j]) for c in cells.values())) for j, h in enumerate(heads)]
    how = f"{importance} flow draws importance-weighted by the exact posterior, {n_samples} resampled" if importance else f"{n_samples} flow draws"
    print(f"\namortised posterior (optim.amortised, {how}): median [90 % interval]")
    print("patient        " + " | ".join(f"{h:>{w}s}" for h, w in zip(heads, widths)))
    for p, a in answers.items():
        print(f"{p:14s} " + " | ".join(f"{c:>{w}s}" for c, w in zip(cells[p], widths)))
    for p, a in answers.items():
        if importance and a.posterior is not None:
            print(f"{p}: importance weights' effective sample size {a.posterior.weights_ess:.0f} of {importance}, "
                  f"Pareto k {a.posterior.pareto_k:.2f}")
        if a.flag:
            print(f"{p}: FLAGGED, not to be trusted: {a.flag}")
    n, hf = answers.get("normal"), answers.get("heart_failure")
    if n is not None and hf is not None and n.posterior is not None and hf.posterior is not None:
        print(f"P(Sa_HF < Sa_N) = {probability_lower(hf.posterior, n.posterior, 'Sa'):.3f}   "
              f"P(tau2_HF > tau2_N) = {probability_lower(n.posterior, hf.posterior, 'tau2'):.3f}   "
              "(independent posteriors of the two patients, over all pairs of draws)")
        print("python scripts/compare_amortised.py measures how closely the flow's draws, and the importance-weighted ones, "
              "match the MCMC posterior (medians in MCMC sd, interval widths)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--patients", nargs="+", default=["normal", "heart_failure"])
    ap.add_argument("--model", choices=list(LO_MODELS), default="single", help="the LO heart model (lvenv.presets.LO_MODELS)")
    ap.add_argument("--methods", nargs="+", default=["mads", "cma", "kriging", "lm"])
    ap.add_argument("--budget", type=int, default=None, help="evaluations per fit of the env methods (480; synthetic: 1600); lm has its own (optim.fit.DEFAULT_OPTIONS)")
    ap.add_argument("--num-envs", type=int, default=16)
    ap.add_argument("--steps-per-beat", type=int, default=1000, help="500 is faster; IVRT then moves by 1–2 %%")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="out/fit", help="folder for the PV-loop plots")
    ap.add_argument("--synthetic", type=int, default=0, metavar="N", help="instead: synthetic recovery of N random truths")
    ap.add_argument("--method", default="cma", help="method of the synthetic recovery")
    ap.add_argument("--fidelity", action="store_true", help="run the 3-D oracle at each patient's best fit (optim.congruency.check_fidelity)")
    ap.add_argument("--fidelity-mesh", type=float, default=DEFAULT_MESH_SIZE, help="FE mesh size h (mm) of the fidelity check")
    ap.add_argument("--fidelity-beats", type=int, default=2, help="FE beats from the LO steady state")
    ap.add_argument("--retune-maps", action="store_true",
                    help="with --fidelity: refit {mu1, mu2, gamma, delay} on each FE beat and compare again (the model's own floor there)")
    ap.add_argument("--correct-maps", type=int, default=0, metavar="K",
                    help="K rounds of: maps refitted on the FE beat at the best fit, the patient fitted again with them; then the FE check")
    ap.add_argument("--refit-passive", action="store_true",
                    help="with --retune-maps or --correct-maps: refit the passive maps {alpha, beta, a, b, c} too, each within its trained "
                         "value ÷ and × optim.congruency.PASSIVE_FREEDOM")
    ap.add_argument("--aortic-weight", type=float, default=0.0, metavar="W",
                    help="with --retune-maps or --correct-maps: the refits minimise C^2 + W A^2, A the aortic pressure's misfit on the FE beat")
    ap.add_argument("--no-plausibility", dest="plausibility", action="store_false",
                    help="drop the filling-pressure bands (mean atrial pressure, EDP) from the objective")
    ap.add_argument("--posterior-samples", type=int, default=4000, metavar="N",
                    help="draws of each patient's amortised posterior (0: none; default %(default)s)")
    ap.add_argument("--importance", type=int, default=None, metavar="N",
                    help="flow draws per patient reweighted by the exact posterior (one simulation each; 0: the flow's draws as they are; "
                         f"default: {IMPORTANCE_PER_SAMPLE} per posterior sample)")
    a = ap.parse_args()
    if a.retune_maps and not a.fidelity:
        ap.error("--retune-maps refits the maps on the fidelity check's FE beat: it needs --fidelity")
    if a.refit_passive and not (a.retune_maps or a.correct_maps):
        ap.error("--refit-passive refits the passive maps with the others: it needs --retune-maps or --correct-maps")
    if not (math.isfinite(a.aortic_weight) and a.aortic_weight >= 0):
        ap.error(f"--aortic-weight {a.aortic_weight}: the weight must be a finite number >= 0")
    if a.aortic_weight and not (a.retune_maps or a.correct_maps):
        ap.error("--aortic-weight weighs the aortic pressure into the refits of the maps: it needs --retune-maps or --correct-maps")
    if a.correct_maps < 0:
        ap.error(f"--correct-maps {a.correct_maps}: the number of correction rounds must be >= 0")
    if a.synthetic:
        rep = synthetic_recovery(a.synthetic, a.method, a.num_envs, a.budget or 1600, a.seed, a.steps_per_beat)
        print(f"synthetic recovery, {a.method}, {a.synthetic} truths, budget {a.budget or 1600}, {rep.wall_time:.0f} s")
        print(f"refitted mismatch: median {100 * np.median(rep.mismatch):.3f} %, max {100 * np.max(rep.mismatch):.3f} %; "
              f"largest single-target error {100 * np.max(rep.max_error):.3f} %")
        print("parameter | fit vs truth: median, max error | identifiable | local null share: median, min")
        print("          | (|ln fit/truth|; R2 |Δ|/range) |              | (0 = pinned by the targets, 1 = free)")
        for j, n in enumerate(rep.names):
            err, null = rep.log_error[:, j], rep.null_share[:, j]
            print(f"{n:9s} | {np.median(err):14.3f} {np.max(err):8.3f}   | {str(rep.identifiable[n]):12s} |"
                  f" {np.median(null):10.2f} {np.min(null):5.2f}")
        print(f"singular values of d ln(targets)/du (median over truths): {np.round(np.median(rep.singular_values, 0), 2)}")
        return
    patients = [builtin(name, a.model) for name in a.patients]
    rows = fit_patients(patients, a.methods, a.num_envs, a.budget or 480, a.seed, a.out, a.steps_per_beat, plausibility=a.plausibility)
    table = io.StringIO()
    with contextlib.redirect_stdout(table):
        if a.model != "single":
            print(f"LO heart model: {a.model} ({patients[0].heart.elements})\n")
        print_fits(rows, a.plausibility)
        if a.posterior_samples and a.model != "single":
            print(f"\n(no amortised posterior: the flow is trained on the single-cell heart, not on model {a.model!r})")
        elif a.posterior_samples:
            print_posteriors(a.patients, a.posterior_samples, a.seed, a.importance if a.importance is not None else IMPORTANCE_PER_SAMPLE * a.posterior_samples)
    print(table.getvalue(), end="")
    Path(a.out, "fits.txt").write_text(table.getvalue())  # for `lvenv report`
    worst = max(r.mismatch for r in rows)
    print(f"\nworst mismatch {100 * worst:.2f} % (goal < 3 %); plots in {a.out}/"
          if math.isfinite(worst) else "\nsome fit found no valid point")
    if a.correct_maps:
        checks = print_corrected(rows, a)
    elif a.fidelity:
        checks = print_fidelity(rows, a.fidelity_mesh, a.fidelity_beats, a.model, a.retune_maps, a.refit_passive, a.aortic_weight)
    else:
        return
    command = shlex.join(["python", "scripts/fit_patients.py", *sys.argv[1:]])
    for patient, patient_checks in checks.items():
        path = Path(a.out, fidelity_file(patient, a.model, a.refit_passive, a.aortic_weight))
        path.write_text(fidelity_markdown(patient_checks, command, a.fidelity_mesh, a.fidelity_beats))
        print(f"{patient}: the checks' table is in {path}")


def print_fidelity(rows, mesh_size: float, beats: int, model: str = "single", retune_maps: bool = False,
                   refit_passive: bool = False, aortic_weight: float = 0.0) -> dict[str, list[Check]]:
    """The 3-D oracle at each patient's best fit (of the LO heart ``model``): LO, FE and their
    difference per target; with ``retune_maps`` also FE − LO with the maps refitted on that FE beat
    (with ``refit_passive``, the passive maps too: `optim.congruency.map_refit`; with
    ``aortic_weight``, weighing the aortic pressure in).
    Returns each patient's check."""
    checks = {}
    for patient in dict.fromkeys(r.patient for r in rows):
        best = min((r for r in rows if r.patient == patient), key=lambda r: r.mismatch)
        heart = builtin(patient, model).heart.replace(**best.parameters)
        names, bounds = map_refit(heart.lo, refit_passive)
        rep = check_fidelity(heart, mesh_size=mesh_size, beats=beats, retune=names if retune_maps else (), bounds=bounds,
                             aortic_weight=aortic_weight)
        print_check(f"fidelity of {patient} ({best.method} fit) against the 3-D oracle (h = {mesh_size:g} mm, {beats} beats)",
                    {n: getattr(heart.lo, n) for n in names}, rep)
        checks[patient] = [Check("trained", best, rep)]
    return checks


def print_corrected(rows, a) -> dict[str, list[Check]]:
    """``--correct-maps``: each patient's rounds of `optim.fit.corrected_fit` from its best fit in
    ``rows``; returns each patient's checks, one per round."""
    checks = {}
    for patient in dict.fromkeys(r.patient for r in rows):
        best = min((r for r in rows if r.patient == patient), key=lambda r: r.mismatch)
        rounds = corrected_fit(builtin(patient, a.model), a.methods, a.correct_maps, first=best, beats=a.fidelity_beats,
                               num_envs=a.num_envs, budget=a.budget or 480, seed=a.seed, steps_per_beat=a.steps_per_beat,
                               plausibility=a.plausibility, passive=a.refit_passive, aortic_weight=a.aortic_weight, mesh_size=a.fidelity_mesh)
        checks[patient] = []
        for r, step in enumerate(rounds):
            source = "trained" if r == 0 else f"refitted on round {r - 1}'s FE beat"
            checks[patient].append(Check(f"round {r}: {source}", step.fit, step.fidelity))
            print_check(f"{patient}, round {r} (maps {source}; {step.fit.method} fit, mismatch {100 * step.fit.mismatch:.2f} %) "
                        f"against the 3-D oracle (h = {a.fidelity_mesh:g} mm, {a.fidelity_beats} beats)", step.maps, step.fidelity,
                        step.fit.parameters)
    return checks


def fidelity_markdown(checks: list[Check], command: str, mesh_size: float, beats: int) -> str:
    """One patient's fidelity ``checks`` as a markdown table: per check C and FE − LO per target
    (OUT: outside `optim.congruency.FIDELITY_TOLERANCE`), and the fitted parameters; a check with
    maps refitted on its FE beat has a second row with them. Headed by ``command``."""
    names = list(checks[0].fit.parameters)
    heads = ["maps", "fit", "C", *(f"{METRICS[t].label} ({difference_unit(t)})" for t in FIDELITY_TOLERANCE),
             *map(_param_head, names)]
    tolerance = ", ".join(f"{METRICS[t].label} {format_difference(t, bound)[1:]} {difference_unit(t)}" for t, (_, bound) in FIDELITY_TOLERANCE.items())
    lines = [f"Command: `{command}`. FE − LO at each fit (h = {mesh_size:g} mm, the last of {beats} FE beats against the LO "
             f"steady state); OUT: outside ± ({tolerance}).", "",
             "| " + " | ".join(heads) + " |", "|" + "---|" * len(heads)]
    for check in checks:
        fitted = [_param(n, check.fit.parameters[n]) for n in names]
        how = f"{check.fit.method}, mismatch {100 * check.fit.mismatch:.2f} %"
        compared = [(check.maps, check.fidelity.C, check.fidelity.rows, check.fidelity.within)]
        if (again := check.fidelity.retuned) is not None:
            compared.append(("refitted on this FE beat", again["C"], again["rows"], again["within"]))
        for maps, c, diffs, within in compared:
            cells = [f"{format_difference(t, diffs[t][2])}{'' if within[t] else ' OUT'}" for t in FIDELITY_TOLERANCE]
            lines.append("| " + " | ".join([maps, how, f"{100 * c:.2f} %", *cells, *fitted]) + " |")
    return "\n".join(lines) + "\n"


def print_check(title: str, maps: dict, rep, parameters: dict | None = None) -> None:
    """One fidelity check ``rep`` (`optim.congruency.Fidelity`) of a heart with the maps ``maps``
    (fitted ``parameters``, if given): C, and LO, FE and FE − LO per target, also with the maps
    refitted on the FE beat if it has them."""
    print(f"\n{title}: C {100 * rep.C:.2f} %, {'within' if rep.ok else 'OUTSIDE'} tolerance")
    if parameters is not None:
        print("  fit: " + ", ".join(f"{n} {_param(n, v)}{' ms' if n == 'tau2' else ''}" for n, v in parameters.items()))
    again = rep.retuned
    if again is not None:
        print(f"  maps refitted on this FE beat ({', '.join(f'{n} {v:.4g}' for n, v in again['lo'].items())}; "
              f"before: {', '.join(f'{n} {maps[n]:.4g}' for n in again['lo'])}): C {100 * again['C']:.2f} %")
    for name, (lo, fe, diff) in rep.rows.items():
        line = f"  {header(name):18s} LO {_show(name, lo):>7s}  FE {_show(name, fe):>7s}  FE − LO {format_difference(name, diff, unit=True):>12s}  {'ok' if rep.within[name] else 'OUT'}"
        if again is not None:
            line += f"  | refitted maps: FE − LO {format_difference(name, again['rows'][name][2], unit=True):>12s}  {'ok' if again['within'][name] else 'OUT'}"
        print(line)


if __name__ == "__main__":
    main()
