"""Benchmark and calibration of the shipped amortised posterior (optim.amortised); prints JSON.

    python scripts/bench_amortised.py [--truths 300] [--cohort 1000] [--samples 1000] [--repeats 3] [--mcmc 1] [--seed 7] [--bases KIND ...] [--artefact FILE]

Draws ``--truths`` held-out truths from optim.identify.posterior's prior over the artefact's heart
kinds (or ``--bases``, some of them) and heart-rate range (a seed the training did not use), adds the noise of
optim.identify.NOISE, and builds one patient per truth targeting EF, ET, IVRT and the pulse
pressure (the built-in patients' targets), repeated up to ``--cohort`` patients. Times
``optim.identify.amortised`` for the whole cohort at ``--samples`` samples each (the first call,
JIT compilation included, then ``--repeats`` more: their median wall and CPU seconds, CPU time being
steadier than wall time on a loaded machine), and ``optim.identify.posterior`` (MCMC, default
settings) for the first ``--mcmc`` patients in the same run; gives the ratio of the MCMC time per
patient to the amortised time per patient. Calibration on the truths: per parameter, the fraction
inside its equal-tailed 90 % interval, and the Kolmogorov–Smirnov p-value of the truths' ranks
among the samples against uniform (simulation-based calibration, Talts S et al.,
arXiv:1804.06788, 2018), and the fraction flagged out of distribution. Medians of the first
patients are printed beside the MCMC ones.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

import numpy as np
from scipy.stats import kstest

from lvenv import jitcache
from lvenv.identification import DEFAULT_ACTION_PARAMS
from optim import amortised
from optim.identify import amortised as amortised_posteriors, posterior


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--truths", type=int, default=300)
    parser.add_argument("--cohort", type=int, default=1000)
    parser.add_argument("--samples", type=int, default=1000)
    parser.add_argument("--repeats", type=int, default=3, help="timed calls after the first (default %(default)s)")
    parser.add_argument("--mcmc", type=int, default=1, help="patients also sampled by MCMC (default %(default)s)")
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--artefact", default=str(amortised.DEFAULT_ARTEFACT), help="the estimator (default: the shipped one)")
    parser.add_argument("--bases", nargs="+", default=None, choices=amortised.KINDS, help="heart kinds of the truths (default: the artefact's)")
    a = parser.parse_args()
    jitcache.enable()

    estimator = amortised.load(a.artefact)
    kinds = estimator.bases if a.bases is None else amortised.heart_kinds(a.bases)
    patients, truths, skipped = amortised.held_out_patients(estimator, a.truths, a.seed, bases=kinds)
    cohort = [dataclasses.replace(patients[j % len(patients)], name=f"row{j}") for j in range(a.cohort)]

    t = time.perf_counter()
    amortised_posteriors(cohort, n_samples=a.samples, estimator=estimator)
    first = time.perf_counter() - t
    walls, cpus = [], []
    for repeat in range(max(1, a.repeats)):
        t, c = time.perf_counter(), time.process_time()
        posts = amortised_posteriors(cohort, n_samples=a.samples, estimator=estimator, seed=1 + repeat)
        walls.append(time.perf_counter() - t)
        cpus.append(time.process_time() - c)
    seconds = float(np.median(walls))

    held = posts[: len(patients)]
    x = np.stack([np.stack([p.samples[n] for n in DEFAULT_ACTION_PARAMS], axis=1) for p in held])
    lo, hi = np.percentile(x, 5, axis=1), np.percentile(x, 95, axis=1)
    coverage = np.mean((truths >= lo) & (truths <= hi), axis=0)
    ranks = np.mean(x < truths[:, None, :], axis=1)
    ks = [float(kstest(ranks[:, j], "uniform").pvalue) for j in range(len(DEFAULT_ACTION_PARAMS))]

    mcmc = []
    for p in patients[: a.mcmc]:
        t, c = time.perf_counter(), time.process_time()
        m = posterior(p)
        mcmc.append({"patient": p.name, "seconds": time.perf_counter() - t, "cpu_seconds": time.process_time() - c, "median": m.median, "interval_90": m.interval_90,
                     "amortised_median": held[patients.index(p)].median, "amortised_interval_90": held[patients.index(p)].interval_90})
    mcmc_per_patient = float(np.mean([m["seconds"] for m in mcmc])) if mcmc else None
    mcmc_cpu_per_patient = float(np.mean([m["cpu_seconds"] for m in mcmc])) if mcmc else None
    per_patient = seconds / a.cohort
    print(json.dumps({
        "cohort": a.cohort, "samples": a.samples, "amortised_seconds": seconds, "amortised_seconds_all": walls,
        "amortised_cpu_seconds": float(np.median(cpus)), "amortised_cpu_seconds_all": cpus, "amortised_seconds_first_call": first,
        "amortised_seconds_per_patient": per_patient, "mcmc_seconds_per_patient": mcmc_per_patient,
        "mcmc_cpu_seconds_per_patient": mcmc_cpu_per_patient,
        "speedup_per_patient": (mcmc_per_patient / per_patient) if mcmc else None,
        "truths": len(truths), "bases": list(kinds), "skipped_truths": skipped, "targets": amortised.HELD_OUT_TARGETS,
        "coverage_90": dict(zip(DEFAULT_ACTION_PARAMS, map(float, coverage))), "rank_ks_p": dict(zip(DEFAULT_ACTION_PARAMS, ks)),
        "out_of_distribution": float(np.mean([p.out_of_distribution != "" for p in held])),
        "training": {k: estimator.meta["training"][k] for k in ("pairs", "best_validation_loss", "seconds")}, "mcmc": mcmc,
    }, indent=2, default=float))


if __name__ == "__main__":
    main()
