"""Calibration of the posterior on synthetic truths (issue 11 item 5): do 90 % intervals hold the truth 90 % of the time?

    python scripts/calibration.py [--truths 20] [--draw prior|bands] [--walkers 64] [--steps 200] [--chains 64] [--chain-steps 1200] [--out out/identify/calibration.json]

Takes about 3 minutes per truth on 2 cores. Each finished truth is saved to ``--out`` with
``.ckpt.npz`` appended (:func:`lvenv.archive.save_records`); a rerun with the same settings
resumes after the last one saved, and the checkpoint is removed at the end.

Draws ``--truths`` random parameter sets and simulates the built-in patients' four targets (EF,
ET, IVRT, pulse pressure) at each. ``--draw prior`` (default) draws them from the posterior's own
prior (`optim.identify.prior_draws`: uniform in the identification bounds times the soft
plausibility factor, by rejection), as simulation-based calibration requires: exact posteriors
then cover 90 % of the truths whatever the model. ``--draw bands`` draws them uniformly inside the
bounds with every plausibility band met as a hard limit and EF in [0.3, 0.75] (``optim.fit``'s
synthetic truths; the README's first runs), a narrower population than the prior. Then it adds
Gaussian measurement noise of `optim.identify.NOISE`
(EF 0.05, times 10 ms, pressures 5 mmHg), drawn per truth from (seed, truth index). Each noisy patient is fitted by MADS (480 evaluations,
weights (t/σ)² so that the objective is χ²) and its posterior sampled from that fit
(`optim.identify.posterior`, the model's own noise model and priors). Printed per parameter: the
fraction of truths inside their equal-tailed 90 % interval (calibrated: about 0.9; with 20 truths
the binomial standard error is 0.07), the probability of so few or fewer hits if the intervals
were calibrated (binomial, p = 0.9), the same for the 90 % highest-density interval
(``Posterior.highest_density``, which reaches a bound the samples pile against), and the median
width of the equal-tailed interval (fraction of the bound). Each truth's posterior quantile (the
fraction of samples below it; uniform over truths for a calibrated posterior, Talts S et al.,
arXiv:1804.06788, 2018) goes to the JSON at ``--out``, with its density quantile: the fraction
of 512 posterior samples (all, if fewer) whose posterior density (`optim.identify.log_density`)
lies below the truth's. That too is uniform if calibrated; a truth outside its intervals whose
density quantile is high sits in a region of high posterior density that the sampler did not
visit. ``--seed`` picks the truths and their noise: a second seed is an independent check. A
truth whose noisy targets are no valid patient record
(``lvenv.patients.Patient``: EF ≤ 0 for a prior heart that barely ejects) is skipped, reported
and listed in the JSON, and the next candidate takes its place. That conditions the data on
being valid, which the posterior does not know: a small departure, for hearts whose EF lies
within a few σ of 0.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
import sys
import time

import numpy as np
from scipy.stats import binom

from lvenv.archive import load_records, save_records
from lvenv.identification import DEFAULT_ACTION_PARAMS
from lvenv.patients import Patient, builtin
from lvenv.validation import InputError
from optim.fit import draw_truths, make_env
from optim.identify import chi2_weighted, log_density, measurement_sd, posterior, prior_draws
from optim.minimize import minimize

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))  # the shared scripts/ module below
from scripts.posterior_options import add_sampler_options, sampler_options  # noqa: E402

TARGETS = ("EF", "ET", "IVRT", "P_ao_pulse")
DENSITY_SAMPLES = 512  # posterior samples whose density the truth's is ranked against
SPARE = 2  # candidate truths drawn per truth wanted, for those skipped


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--truths", type=int, default=20)
    add_sampler_options(ap)
    ap.add_argument("--draw", choices=("prior", "bands"), default="prior",
                    help="truths from the posterior's prior (default) or uniform inside the hard plausibility bands")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", default="out/identify/calibration.json")
    a = ap.parse_args()
    base = builtin("normal")
    ordered = dataclasses.replace(base, targets={k: base.targets[k] for k in TARGETS})  # observation columns in TARGETS order
    candidates = SPARE * a.truths
    if a.draw == "prior":
        truths, obs = prior_draws(candidates, ordered, seed=a.seed)
    else:
        drawn = draw_truths(candidates, np.random.default_rng(a.seed), base.heart)
        truths, obs = drawn.parameters, drawn.observations(TARGETS)
    checkpoint = pathlib.Path(a.out + ".ckpt.npz")
    settings = {k: v for k, v in vars(a).items() if k != "out"}
    runs = load_records(checkpoint, settings)
    if runs:
        print(f"resuming after {len(runs)} truths from {checkpoint}", flush=True)
    i = runs[-1]["index"] + 1 if runs else 0
    while len(runs) < a.truths:
        if i == candidates:
            raise RuntimeError(f"only {len(runs)} of {candidates} candidate truths had valid noisy targets")
        t0 = time.perf_counter()
        sigma = measurement_sd(dict(zip(TARGETS, map(float, obs[i]))))  # of the true values
        noisy = obs[i] + sigma * np.random.default_rng([a.seed, i]).standard_normal(len(TARGETS))
        try:
            patient = Patient(f"truth {i}", base.heart, dict(zip(TARGETS, map(float, noisy))))
        except InputError as error:
            print(f"truth {i:2d}: skipped, its noisy targets are no patient record ({error})", flush=True)
            i += 1
            continue
        venv = make_env(chi2_weighted(patient))
        fit = minimize(venv, "mads", budget=480, seed=a.seed + i, progress=False)
        venv.close()
        post = posterior(patient, start=fit.parameters, seed=a.seed + i, **sampler_options(a))
        true = dict(zip(DEFAULT_ACTION_PARAMS, map(float, truths[i])))
        hdi = post.highest_density(0.9)
        contains = lambda interval: {n: bool(interval[n][0] <= true[n] <= interval[n][1]) for n in DEFAULT_ACTION_PARAMS}
        hit = contains(post.interval_90)
        picked = np.random.default_rng([a.seed, i, 1]).choice(len(post.samples["tau2"]), min(DENSITY_SAMPLES, len(post.samples["tau2"])), replace=False)
        rows = np.vstack([[truths[i]], np.stack([post.samples[n][picked] for n in DEFAULT_ACTION_PARAMS], axis=1)])
        density = log_density(patient, rows)
        runs.append({"index": i, "truth": true, "targets": patient.targets, "fit_mismatch": fit.mismatch, "interval_90": post.interval_90,
                     "widths": post.widths(), "inside": hit, "hdi_90": hdi, "inside_hdi": contains(hdi),
                     "quantile": {n: float(np.mean(post.samples[n] < true[n])) for n in DEFAULT_ACTION_PARAMS},
                     "density_quantile": float(np.mean(density[1:] < density[0])),
                     "rhat": post.rhat, "acceptance": post.acceptance, "wall_s": time.perf_counter() - t0})
        save_records(checkpoint, runs, settings)
        print(f"truth {i:2d}: fit {100 * fit.mismatch:.2f} %, inside " + " ".join(f"{n} {'y' if hit[n] else 'N'}" for n in DEFAULT_ACTION_PARAMS)
              + f" (R-hat ≤ {max(post.rhat.values()):.3f}, {time.perf_counter() - t0:.0f} s)", flush=True)
        i += 1
    coverage = {key: {n: float(np.mean([r[key][n] for r in runs])) for n in DEFAULT_ACTION_PARAMS} for key in ("inside", "inside_hdi")}
    # P(so few hits or fewer | calibrated 90 % intervals)
    tail = {key: {n: float(binom.cdf(round(c * a.truths), a.truths, 0.9)) for n, c in cov.items()} for key, cov in coverage.items()}
    width = {n: float(np.median([r["widths"][n] for r in runs])) for n in DEFAULT_ACTION_PARAMS}
    density_quantiles = sorted(r["density_quantile"] for r in runs)
    skipped = sorted(set(range(runs[-1]["index"] + 1)) - {r["index"] for r in runs})
    print(f"\ncoverage of the 90 % intervals over {a.truths} noisy truths (P: so few hits or fewer if calibrated), and the median width (fraction of the bound)")
    print("| | " + " | ".join(DEFAULT_ACTION_PARAMS) + " | all |")
    print("|---|" + "---|" * (len(DEFAULT_ACTION_PARAMS) + 1))
    for key, label in (("inside", "equal-tailed"), ("inside_hdi", "highest-density")):
        print(f"| {label} | " + " | ".join(f"{coverage[key][n]:.2f} (P {tail[key][n]:.2f})" for n in DEFAULT_ACTION_PARAMS)
              + f" | {np.mean(list(coverage[key].values())):.2f} |")
    print("| width | " + " | ".join(f"{width[n]:.2f}" for n in DEFAULT_ACTION_PARAMS) + " | |")
    print("the truths' posterior density quantiles (uniform if calibrated; near 1: an unexplored mode holds the truth): "
          + " ".join(f"{q:.2f}" for q in density_quantiles))
    out = pathlib.Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"coverage": coverage["inside"], "coverage_hdi": coverage["inside_hdi"], "binomial_tail": tail,
                               "median_width": width, "density_quantiles": density_quantiles, "skipped": skipped, "runs": runs, "options": vars(a)}, indent=2))
    checkpoint.unlink()
    print(f"JSON: {out}")


if __name__ == "__main__":
    main()
