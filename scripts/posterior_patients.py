"""Posteriors of the two built-in patients (issue 11 item 5): fit, sample, compare.

    python scripts/posterior_patients.py [--out out/identify] [--seed 0] [--sampler nuts] [--chains N] ...

Per built-in patient: a least-squares fit (`optim.lm.fit_lm`, budget 120, 4 starts), then the
posterior started at the fit (`optim.identify.posterior`, by default a differential-evolution
pilot, then independent Metropolis–Hastings chains; the sampler options change that). Printed as JSON: the fit, the
medians and 90 % credible intervals, the diagnostics (acceptance, τ, ESS, split R-hat), the
sampling wall time, and P(Sa_HF < Sa_N) and P(τ2_HF > τ2_N). The posterior pairs plot of both
patients goes to ``<out>/posterior_pairs.png`` and the JSON to ``<out>/posterior_patients.json``.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

from lvenv.identification import DEFAULT_ACTION_PARAMS, ParameterSpace
from lvenv.patients import builtin
from lvenv.plots import pairs_figure
from optim.identify import posterior, probability_lower
from optim.lm import fit_lm

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))  # the shared scripts/ module below
from scripts.posterior_options import add_sampler_options, sampler_options  # noqa: E402

PATIENTS = ("normal", "heart_failure")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=pathlib.Path, default=pathlib.Path("out/identify"))
    ap.add_argument("--seed", type=int, default=0)
    add_sampler_options(ap)
    a = ap.parse_args()
    summary, posts = {}, {}
    for name in PATIENTS:
        patient = builtin(name)
        t0 = time.perf_counter()
        fit = fit_lm(patient, budget=120, starts=4, seed=a.seed)
        t_fit = time.perf_counter() - t0
        t0 = time.perf_counter()
        post = posts[name] = posterior(patient, start=fit.parameters, seed=a.seed, **sampler_options(a))
        t_post = time.perf_counter() - t0
        summary[name] = {"fit": {"parameters": fit.parameters, "mismatch": fit.mismatch, "wall_s": t_fit},
                         "posterior": {**post.to_dict(), "wall_s": t_post}}
        print(f"# {name}: fit {100 * fit.mismatch:.3f} % ({t_fit:.0f} s); posterior {t_post:.0f} s, "
              f"max R-hat {max(post.rhat.values()):.4f}, min ESS {min(post.ess.values()):.0f}", flush=True)
    summary["P(Sa_HF < Sa_N)"] = probability_lower(posts["heart_failure"], posts["normal"], "Sa")
    summary["P(tau2_HF > tau2_N)"] = probability_lower(posts["normal"], posts["heart_failure"], "tau2")
    summary["posterior_wall_s_total"] = sum(summary[n]["posterior"]["wall_s"] for n in PATIENTS)
    a.out.mkdir(parents=True, exist_ok=True)
    space = ParameterSpace.for_names(DEFAULT_ACTION_PARAMS)
    figure = pairs_figure({n: posts[n].samples for n in PATIENTS}, a.out / "posterior_pairs.png", log=dict(zip(space.names, space.log)))
    (a.out / "posterior_patients.json").write_text(json.dumps(summary, indent=2))
    print(json.dumps({**summary, "figure": str(figure)}, indent=2))


if __name__ == "__main__":
    main()
