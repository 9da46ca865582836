"""Calibration of the posterior on synthetic truths (issue 11 item 5): do 90 % intervals hold the truth 90 % of the time?

    python scripts/calibration.py [--truths 20] [--walkers 64] [--steps 200] [--chains 64] [--chain-steps 1200] [--out out/identify/calibration.json]

Draws ``--truths`` random parameter sets inside the identification bounds whose hearts meet every
plausibility band (``optim.fit``'s synthetic truths), simulates the built-in patients' four targets
(EF, ET, IVRT, pulse pressure) and adds Gaussian measurement noise of `optim.identify.NOISE`
(EF 0.05, times 10 ms, pressures 5 mmHg). Each noisy patient is fitted by MADS (480 evaluations,
weights (t/σ)² so that the objective is χ²) and its posterior sampled from that fit
(`optim.identify.posterior`, the model's own noise model and priors). Printed per parameter: the
fraction of truths inside their 90 % interval (calibrated: about 0.9; with 20 truths the binomial
standard error is 0.07) and the median interval width (fraction of the bound). JSON to ``--out``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
import time

import numpy as np

from lvenv.identification import DEFAULT_ACTION_PARAMS
from lvenv.patients import Patient, builtin
from optim.fit import _draw_truths, make_env
from optim.identify import NOISE, posterior
from optim.minimize import minimize

TARGETS = ("EF", "ET", "IVRT", "P_ao_pulse")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--truths", type=int, default=20)
    ap.add_argument("--walkers", type=int, default=64, help="the pilot ensemble's walkers")
    ap.add_argument("--steps", type=int, default=200, help="the pilot's steps")
    ap.add_argument("--chains", type=int, default=64, help="independent chains after the pilot (0: the pilot's walkers are the sample)")
    ap.add_argument("--chain-steps", type=int, default=1200)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", default="out/identify/calibration.json")
    a = ap.parse_args()
    rng = np.random.default_rng(a.seed)
    base = builtin("normal")
    truths, obs = _draw_truths(a.truths, rng, base, TARGETS)
    sigma = np.array([NOISE[k] for k in TARGETS])
    runs, inside = [], {n: [] for n in DEFAULT_ACTION_PARAMS}
    for i, (truth, o) in enumerate(zip(truths, obs)):
        t0 = time.perf_counter()
        noisy = o + sigma * rng.standard_normal(len(TARGETS))
        patient = Patient(f"truth {i}", base.heart, dict(zip(TARGETS, map(float, noisy))))
        venv = make_env(dataclasses.replace(patient, weights={k: (t / s) ** 2 for (k, t), s in zip(patient.targets.items(), sigma)}))
        fit = minimize(venv, "mads", budget=480, seed=a.seed + i, progress=False)
        venv.close()
        post = posterior(patient, start=fit.parameters, walkers=a.walkers, steps=a.steps, chains=a.chains, chain_steps=a.chain_steps, seed=a.seed + i)
        true = dict(zip(DEFAULT_ACTION_PARAMS, map(float, truth)))
        hit = {n: bool(post.interval_90[n][0] <= true[n] <= post.interval_90[n][1]) for n in DEFAULT_ACTION_PARAMS}
        for n in DEFAULT_ACTION_PARAMS:
            inside[n].append(hit[n])
        runs.append({"truth": true, "targets": patient.targets, "fit_mismatch": fit.mismatch, "interval_90": post.interval_90,
                     "widths": post.widths(), "inside": hit, "rhat": post.rhat, "acceptance": post.acceptance, "wall_s": time.perf_counter() - t0})
        print(f"truth {i:2d}: fit {100 * fit.mismatch:.2f} %, inside " + " ".join(f"{n} {'y' if hit[n] else 'N'}" for n in DEFAULT_ACTION_PARAMS)
              + f" (R-hat ≤ {max(post.rhat.values()):.2f}, {time.perf_counter() - t0:.0f} s)", flush=True)
    coverage = {n: float(np.mean(v)) for n, v in inside.items()}
    width = {n: float(np.median([r["widths"][n] for r in runs])) for n in DEFAULT_ACTION_PARAMS}
    print(f"\ncoverage of the 90 % intervals over {a.truths} noisy truths, and the median width (fraction of the bound)")
    print("| | " + " | ".join(DEFAULT_ACTION_PARAMS) + " | all |")
    print("|---|" + "---|" * (len(DEFAULT_ACTION_PARAMS) + 1))
    print("| coverage | " + " | ".join(f"{coverage[n]:.2f}" for n in DEFAULT_ACTION_PARAMS) + f" | {np.mean(list(coverage.values())):.2f} |")
    print("| width | " + " | ".join(f"{width[n]:.2f}" for n in DEFAULT_ACTION_PARAMS) + " | |")
    out = pathlib.Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"coverage": coverage, "median_width": width, "runs": runs, "options": vars(a)}, indent=2))
    print(f"JSON: {out}")


if __name__ == "__main__":
    main()
