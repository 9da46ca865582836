"""The amortised posterior beside the MCMC one (issue 33 item 7); prints JSON.

    python scripts/compare_amortised.py [--truths 20] [--samples 4000] [--importance 8000] [--seed 7] [--bases KIND ...] [--artefact FILE]
        [--out out/compare] [sampler options]

For the built-in patients and ``--truths`` held-out simulated truths (optim.amortised.held_out_patients
over the heart kinds ``--bases``: EF, ET, IVRT and pulse pressure with the noise of optim.identify.NOISE), the amortised posterior
(optim.identify.amortised, ``--samples`` draws), the same importance-weighted (``--importance``
flow draws per patient reweighted by the exact posterior density, ``importance=``) and the MCMC one (optim.identify.posterior from the
patient's own values, the sampler options below). Per patient and parameter, in the unit-cube
coordinate of its identification bound (log scale on log axes, where the prior is flat):

* ``median_shift_sd``: |median_amortised − median_MCMC| / sd_MCMC (acceptance: ≤ 0.3);
* ``width_ratio``: the amortised 90 % interval's width over the MCMC one's (acceptance: 0.75–1.25).

Also, for each of the two amortised posteriors, the worst of each over the patients, the fraction
within the acceptance, the patients within it on every parameter and the seconds; the MCMC
seconds per patient and its largest split R-hat (all of it also in ``--out``/compare.json, which
``lvenv report`` shows on the calibration page); and ``pairs_<patient>.png`` in ``--out`` for the built-in patients (both posteriors
overlaid). MCMC costs about 100 s per patient on 2 quiet cores, so every finished patient's MCMC
posterior is checkpointed in ``--out``/mcmc.npz (:func:`lvenv.archive.save`): its samples (at
most :data:`KEPT` of them, unit-cube coordinates) and its seconds. The same command resumes after
an interruption, and a later estimator is compared with the same MCMC posteriors in seconds: the
checkpoint depends on the truths, the seed and the sampler only (it refuses other ones), never on
the estimator.
"""

from __future__ import annotations

import argparse
import json
import sys
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
#: At most this many MCMC samples per patient are kept in the checkpoint (a uniform random subset).
KEPT = 8000


def compare(ua: np.ndarray, um: np.ndarray) -> dict[str, dict[str, float]]:
    """``median_shift_sd`` and ``width_ratio`` per parameter of amortised samples ``ua`` against
    MCMC ones ``um`` (both (n, 6), unit-cube coordinates; module docstring)."""
    width = lambda u: np.percentile(u, 95, axis=0) - np.percentile(u, 5, axis=0)
    shift = np.abs(np.median(ua, axis=0) - np.median(um, axis=0)) / um.std(axis=0)
    ratio = width(ua) / width(um)
    return {n: {"median_shift_sd": float(s), "width_ratio": float(r)} for n, s, r in zip(DEFAULT_ACTION_PARAMS, shift, ratio)}


def unit_samples(p) -> np.ndarray:
    """A posterior's samples (n, 6) in the unit-cube coordinates of the identification bounds."""
    space = ParameterSpace.for_names(DEFAULT_ACTION_PARAMS)
    return space.to_unit(np.stack([p.samples[n] for n in space.names], axis=1))


def mcmc_posteriors(patients, out: Path, settings: dict, options: dict, seed: int) -> dict[str, dict]:
    """Each patient's MCMC posterior, from ``out``/mcmc.npz where it is there (same ``settings``),
    else sampled (:func:`optim.identify.posterior` with ``options``) and added to the checkpoint
    at once: patient name → {"samples" (unit cube), "seconds", "rhat"}."""
    path = out / "mcmc.npz"
    settings = json.loads(json.dumps(settings))
    arrays, records = {}, []
    if path.exists():
        arrays, meta = archive.load(path, "MCMC checkpoint")
        if meta.get("settings") != settings:
            raise archive.ArchiveError(f"MCMC checkpoint {str(path)!r} was written with settings {meta.get('settings')}, not {settings}; "
                                       "delete it or use another --out")
        records = meta["records"]
    done = {r["patient"]: {**r, "samples": arrays[r["patient"]]} for r in records}
    rng = np.random.default_rng(seed)
    for p in patients:
        if p.name in done:
            continue
        t = time.perf_counter()
        m = posterior(p, seed=seed, **options)
        u = unit_samples(m)
        u = u[np.sort(rng.choice(len(u), KEPT, replace=False))] if len(u) > KEPT else u
        done[p.name] = {"patient": p.name, "seconds": time.perf_counter() - t, "rhat": m.rhat, "samples": u}
        records = [{k: v for k, v in r.items() if k != "samples"} for r in done.values()]
        archive.save(path, {name: r["samples"] for name, r in done.items()}, {"settings": settings, "records": json.loads(json.dumps(records, default=float))})
        print(f"MCMC {p.name}: {done[p.name]['seconds']:.0f} s", file=sys.stderr, flush=True)
    return done


def summary(posteriors, patients, mcmc: dict[str, dict], seconds: float) -> dict:
    """The acceptance figures of ``posteriors`` (one per patient) against the MCMC ones."""
    rows = {p.name: {"compare": compare(unit_samples(f), mcmc[p.name]["samples"]), "median": f.median, "interval_90": f.interval_90,
                     "ess": f.weights_ess, "pareto_k": f.pareto_k, "out_of_distribution": f.out_of_distribution}
            for p, f in zip(patients, posteriors)}
    shift = np.array([[r["compare"][n]["median_shift_sd"] for n in DEFAULT_ACTION_PARAMS] for r in rows.values()])
    ratio = np.array([[r["compare"][n]["width_ratio"] for n in DEFAULT_ACTION_PARAMS] for r in rows.values()])
    agree = (shift <= MEDIAN_SD) & (np.abs(ratio - 1) <= WIDTH_RATIO)
    return {"seconds": seconds, "worst_median_shift_sd": dict(zip(DEFAULT_ACTION_PARAMS, map(float, shift.max(axis=0)))),
            "width_ratio_range": {n: [float(lo), float(hi)] for n, lo, hi in zip(DEFAULT_ACTION_PARAMS, ratio.min(axis=0), ratio.max(axis=0))},
            "within_acceptance": {"median": float(np.mean(shift <= MEDIAN_SD)), "width": float(np.mean(np.abs(ratio - 1) <= WIDTH_RATIO)),
                                  "patients_all_parameters": int(np.sum(agree.all(axis=1)))},
            "per_patient": rows}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--truths", type=int, default=20)
    parser.add_argument("--samples", type=int, default=4000)
    parser.add_argument("--importance", type=int, default=8000, help="flow draws per patient of the importance-weighted posterior (0: none)")
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--artefact", default=str(amortised.DEFAULT_ARTEFACT), help="the estimator (default: the shipped one)")
    parser.add_argument("--bases", nargs="+", default=None, choices=amortised.KINDS,
                        help="heart kinds of the truths (default: all of the estimator's)")
    parser.add_argument("--out", default="out/compare", help="folder of the MCMC checkpoint and the pairs plots")
    add_sampler_options(parser)
    a = parser.parse_args()
    jitcache.enable()

    estimator = amortised.load(a.artefact)
    kinds = estimator.bases if a.bases is None else amortised.heart_kinds(a.bases)
    truths, _, _ = amortised.held_out_patients(estimator, a.truths, a.seed, bases=kinds) if a.truths else ([], None, 0)
    patients = [builtin(n) for n in BUILTIN] + truths
    methods = {}
    for name, importance in (("amortised", 0), ("importance", a.importance)):
        if name == "amortised" or importance:
            t = time.perf_counter()
            methods[name] = (amortised_posteriors(patients, n_samples=a.samples, estimator=estimator, seed=a.seed, importance=importance),
                             time.perf_counter() - t)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    space = ParameterSpace.for_names(DEFAULT_ACTION_PARAMS)
    settings = {"truths": a.truths, "seed": a.seed, "sampler": sampler_options(a),
                "prior": {"bases": list(kinds), "heart_rate": list(estimator.heart_rate)}}
    mcmc = mcmc_posteriors(patients, out, settings, sampler_options(a), a.seed)
    for p, f in zip(patients, methods["amortised"][0]):
        if p.name in BUILTIN:
            physical = space.from_unit(mcmc[p.name]["samples"])
            pairs_figure({"amortised": f.samples, "MCMC": {n: physical[:, j] for j, n in enumerate(space.names)}},
                         out / f"pairs_{p.name}.png", log=dict(zip(space.names, space.log)))
    result = {
        "patients": len(patients), "truths": len(truths), "samples": a.samples, "importance_draws": a.importance, "sampler": sampler_options(a),
        "mcmc_seconds_per_patient": float(np.mean([mcmc[p.name]["seconds"] for p in patients])),
        "mcmc_rhat_max": float(max(max(mcmc[p.name]["rhat"].values()) for p in patients)),
        **{name: summary(posts, patients, mcmc, seconds) for name, (posts, seconds) in methods.items()},
        "plots": sorted(str(q) for q in out.glob("pairs_*.png")),
        "command": "python scripts/compare_amortised.py " + " ".join(sys.argv[1:]),
    }
    text = json.dumps(result, indent=2, default=float)
    archive.write_text(out / "compare.json", text)
    print(text)


if __name__ == "__main__":
    main()
