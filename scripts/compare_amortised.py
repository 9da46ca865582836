"""The amortised posterior beside the MCMC one (issue 33 item 7); prints JSON.

    python scripts/compare_amortised.py [--truths 20] [--samples 4000] [--seed 7] [--out out/compare] [sampler options]

For the built-in patients and ``--truths`` held-out simulated truths (optim.amortised.held_out_patients:
EF, ET, IVRT and pulse pressure with the noise of optim.identify.NOISE), the amortised posterior
(optim.identify.amortised, ``--samples`` draws) and the MCMC one (optim.identify.posterior from the
patient's own values, the sampler options below). Per patient and parameter, in the unit-cube
coordinate of its identification bound (log scale on log axes, where the prior is flat):

* ``median_shift_sd``: |median_amortised − median_MCMC| / sd_MCMC (acceptance: ≤ 0.3);
* ``width_ratio``: the amortised 90 % interval's width over the MCMC one's (acceptance: 0.75–1.25).

Also the worst of each over the patients, the fraction within the acceptance, the seconds of
each method, and ``pairs_<patient>.png`` in ``--out`` for the built-in patients (both posteriors
overlaid). MCMC costs about 100 s per patient on 2 quiet cores, so every finished patient is
checkpointed in ``--out``/checkpoint.npz (:func:`lvenv.archive.save_records`): the same command
resumes after an interruption, and refuses a checkpoint written with other settings or another
estimator.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from lvenv import archive, jitcache
from lvenv.identification import DEFAULT_ACTION_PARAMS, ParameterSpace
from lvenv.patients import BUILTIN, builtin
from lvenv.plots import pairs_figure
from optim import amortised
from optim.identify import amortised as amortised_posteriors, posterior
from posterior_options import add_sampler_options, sampler_options

#: Acceptance of issue 33: medians within this many MCMC posterior sd, widths within this ratio of 1.
MEDIAN_SD, WIDTH_RATIO = 0.3, 0.25


def compare(a, m) -> dict[str, dict[str, float]]:
    """``median_shift_sd`` and ``width_ratio`` per parameter of an amortised posterior ``a``
    against an MCMC one ``m`` (module docstring)."""
    space = ParameterSpace.for_names(DEFAULT_ACTION_PARAMS)
    ua, um = (space.to_unit(np.stack([p.samples[n] for n in space.names], axis=1)) for p in (a, m))
    width = lambda u: np.percentile(u, 95, axis=0) - np.percentile(u, 5, axis=0)
    shift = np.abs(np.median(ua, axis=0) - np.median(um, axis=0)) / um.std(axis=0)
    ratio = width(ua) / width(um)
    return {n: {"median_shift_sd": float(s), "width_ratio": float(r)} for n, s, r in zip(space.names, shift, ratio)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--truths", type=int, default=20)
    parser.add_argument("--samples", type=int, default=4000)
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--out", default="out/compare", help="folder of the pairs plots")
    add_sampler_options(parser)
    a = parser.parse_args()
    jitcache.enable()

    estimator = amortised.load()
    truths, _, _ = amortised.held_out_patients(estimator, a.truths, a.seed) if a.truths else ([], None, 0)
    patients = [builtin(n) for n in BUILTIN] + truths
    t = time.perf_counter()
    fast = amortised_posteriors(patients, n_samples=a.samples, estimator=estimator, seed=a.seed)
    amortised_seconds = time.perf_counter() - t
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    space = ParameterSpace.for_names(DEFAULT_ACTION_PARAMS)
    checkpoint = out / "checkpoint.npz"
    settings = {"truths": a.truths, "samples": a.samples, "seed": a.seed, "sampler": sampler_options(a),
                "estimator": {k: estimator.meta[k] for k in ("version", "training", "code_version")}}
    done = {r["patient"]: r for r in archive.load_records(checkpoint, settings)}
    for p, f in zip(patients, fast):
        if p.name in done:
            continue
        t = time.perf_counter()
        m = posterior(p, seed=a.seed, **sampler_options(a))
        seconds = time.perf_counter() - t
        done[p.name] = {"patient": p.name, "mcmc_seconds": seconds, "compare": compare(f, m),
                        "amortised": {"median": f.median, "interval_90": f.interval_90},
                        "mcmc": {"median": m.median, "interval_90": m.interval_90, "rhat": m.rhat}, "out_of_distribution": f.out_of_distribution}
        if p.name in BUILTIN:
            pairs_figure({"amortised": f.samples, "MCMC": m.samples}, out / f"pairs_{p.name}.png", log=dict(zip(space.names, space.log)))
        archive.save_records(checkpoint, json.loads(json.dumps(list(done.values()), default=float)), settings)
    rows = {p.name: done[p.name] for p in patients}
    mcmc_seconds = [r["mcmc_seconds"] for r in rows.values()]
    shift = np.array([[r["compare"][n]["median_shift_sd"] for n in space.names] for r in rows.values()])
    ratio = np.array([[r["compare"][n]["width_ratio"] for n in space.names] for r in rows.values()])
    print(json.dumps({
        "patients": len(patients), "truths": len(truths), "samples": a.samples, "sampler": sampler_options(a),
        "amortised_seconds": amortised_seconds, "mcmc_seconds_per_patient": float(np.mean(mcmc_seconds)),
        "worst_median_shift_sd": dict(zip(space.names, map(float, shift.max(axis=0)))),
        "width_ratio_range": {n: [float(lo), float(hi)] for n, lo, hi in zip(space.names, ratio.min(axis=0), ratio.max(axis=0))},
        "within_acceptance": {"median": float(np.mean(shift <= MEDIAN_SD)), "width": float(np.mean(np.abs(ratio - 1) <= WIDTH_RATIO))},
        "plots": sorted(str(q) for q in out.glob("pairs_*.png")), "per_patient": rows,
    }, indent=2, default=float))


if __name__ == "__main__":
    main()
