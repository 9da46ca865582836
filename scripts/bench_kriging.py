"""Benchmark (JSON): global EGO (before) against the trust-region kriging (after) on the inverse problem.

Both variants fit the same patients through the same vector env (`optim.fit.make_env`, one env
per patient, compiled once by `optim.fit.warm_up` before timing) with `optim.minimize(venv,
"kriging", budget, seed)`, over the same seeds:

* global — `KrigingOptions(trust_region=False)` with the options `optim.fit` used before the
           trust region (constant liar, no hyperparameter restarts, 256 candidates): the EGO
           of Jones et al. (1998), EI over the whole cube;
* trust_region — `KrigingOptions()` with `optim.fit.DEFAULT_OPTIONS["kriging"]`: TuRBO-1
           (Eriksson et al. 2019), batched Thompson sampling inside a trust region
           (`optim.kriging`).

Reported per (patient, variant): the median, min and max over seeds of the best mean relative
mismatch after each checkpoint's number of evaluations (`EnvHistory.best_mismatch_so_far`), and
the median wall time of a run in s (optimiser and env, JIT compilation excluded).

    python scripts/bench_kriging.py [--seeds 10] [--budget 480] [--checkpoints 48 480]
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from optim import minimize
from optim.fit import DEFAULT_OPTIONS, make_env, warm_up

VARIANTS: dict[str, dict] = {
    "global": {"strategy": "liar", "n_restarts": 0, "n_candidates": 256, "trust_region": False},
    "trust_region": dict(DEFAULT_OPTIONS["kriging"]),
}


def summary(values: list[float]) -> dict[str, float]:
    return {"median": float(np.median(values)), "min": float(np.min(values)), "max": float(np.max(values))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--patients", nargs="+", default=["normal", "heart_failure"])
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--budget", type=int, default=480)
    ap.add_argument("--checkpoints", nargs="+", type=int, default=[48, 480])
    ap.add_argument("--num-envs", type=int, default=16)
    ap.add_argument("--steps-per-beat", type=int, default=500)
    ap.add_argument("--out", default=None, help="also write the JSON here")
    a = ap.parse_args()
    if max(a.checkpoints) > a.budget:
        ap.error(f"checkpoints {a.checkpoints} exceed the budget {a.budget}")
    report = {"settings": vars(a), "options": {v: VARIANTS[v] for v in a.variants}, "results": {}}
    for patient in a.patients:
        venv = make_env(patient, a.num_envs, a.steps_per_beat)
        report["results"][patient] = {"compile_time": warm_up(venv)}
        for variant in a.variants:
            best = {c: [] for c in a.checkpoints}
            walls = []
            for seed in range(a.seeds):
                start = time.perf_counter()
                res = minimize(venv, "kriging", budget=a.budget, seed=seed, progress=False, **VARIANTS[variant])
                walls.append(time.perf_counter() - start)
                so_far = res.history.best_mismatch_so_far()
                for c in a.checkpoints:
                    best[c].append(float(so_far[c - 1]))
            report["results"][patient][variant] = {
                **{f"best_mismatch_after_{c}": summary(best[c]) for c in a.checkpoints},
                "median_wall_time": float(np.median(walls)),
                "per_seed": {f"best_mismatch_after_{c}": best[c] for c in a.checkpoints} | {"wall_time": walls},
            }
        venv.close()
    text = json.dumps(report, indent=1)
    if a.out:
        with open(a.out, "w") as fh:
            fh.write(text)
    print(text)


if __name__ == "__main__":
    main()
