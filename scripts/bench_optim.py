"""Benchmark (JSON): our OrthoMADS against NOMAD 4, scipy and our other methods on the inverse problem.

Every method fits the same patients through the same vector env (one env per patient, num_envs
members, compiled once before timing), on the same search space (the unit cube of
`lvenv.identification.ParameterSpace`: log axes for τ2, Sa, R3, C, Cat), from the same start (the patient's own parameters), with the
same evaluation budget and the same objective (`optim.minimize`: f = −reward; NOMAD gets log10 f
unless `--nomad-objective raw`, MADS gets f and its kriging search picks f or log10 f per fit):

* mads    — `optim.minimize(venv, "mads")` (ours);
* nomad   — NOMAD 4 via PyNomad, DIRECTION_TYPE ORTHO 2N, BB_MAX_BLOCK_SIZE = num_envs
            (`optim.nomad_ref`), each block one env step;
* de      — scipy `differential_evolution`, population = num_envs (one generation = one env
            step, `vectorized=True, updating="deferred"`), polish off;
* nm      — scipy `minimize(method="Nelder-Mead")` with bounds: sequential, one point per env
            step (the other members repeat it);
* cma, kriging — ours, for reference.

Reported per (patient, method), medians over seeds: evaluations and wall time until the first
point with mean relative mismatch < target, the final mismatch, and the fraction of seeds that
reached the target. Wall time counts optimiser and env time from the start of the run.

    python scripts/bench_optim.py [--seeds 3] [--budget 480] [--methods mads nomad de nm cma] [--nomad-objective log]
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from lvenv.patients import builtin
from optim import minimize
from optim.fit import DEFAULT_OPTIONS, make_env, warm_up
from lvenv.identification import ParameterSpace
from optim.minimize import EnvObjective, patient_values, unit_bounds


class BudgetExhausted(Exception):
    pass


class Recorder:
    """Batch objective for foreign optimisers: splits any batch into env steps of <= num_envs
    points, records mismatch and elapsed time per evaluation, stops at the budget."""

    def __init__(self, venv, budget: int, log_objective: bool) -> None:
        self.inner = EnvObjective(venv, ParameterSpace.for_names(venv.unwrapped.action_names), log_objective)
        self.step = self.inner.objective()
        self.budget, self.n = budget, venv.unwrapped.num_envs
        self.mismatch: list[float] = []
        self.elapsed: list[float] = []
        self.start = time.perf_counter()

    def __call__(self, s: np.ndarray):
        s = np.atleast_2d(s)
        out_f, out_ok = [], []
        for i in range(0, len(s), self.n):
            chunk = s[i : i + self.n][: self.budget - len(self.mismatch)]
            if len(chunk) == 0:
                raise BudgetExhausted
            ev = self.step(chunk)
            self.mismatch.extend(self.inner.records[-1]["mismatch"].tolist())
            self.elapsed.extend([time.perf_counter() - self.start] * len(chunk))
            out_f.append(ev.f)
            out_ok.append(ev.feasible)
        return np.concatenate(out_f), np.concatenate(out_ok)

    def scalar(self, s: np.ndarray) -> float:
        f, ok = self(s[None])
        return float(f[0]) if ok[0] else 1e3

    def vector(self, s_t: np.ndarray) -> np.ndarray:
        f, ok = self(s_t.T)
        return np.where(ok, f, 1e3)


def to_target(mismatch: list[float], elapsed: list[float], target: float) -> dict:
    m = np.asarray(mismatch)
    hit = np.flatnonzero(m < target)
    return {
        "evaluations_to_target": int(hit[0]) + 1 if hit.size else None,
        "wall_time_to_target": float(elapsed[hit[0]]) if hit.size else None,
        "final_mismatch": float(np.min(m)) if m.size else None,
        "evaluations": int(m.size),
        "wall_time": float(elapsed[-1]) if elapsed else 0.0,
    }


def run_one(method: str, venv, budget: int, seed: int, target: float, nomad_log: bool = True) -> dict:
    if method in ("mads", "cma", "kriging"):
        res = minimize(venv, method, budget=budget, seed=seed, progress=False, **DEFAULT_OPTIONS[method])
        return to_target(res.history.mismatch.tolist(), res.history.elapsed.tolist(), target)
    venv.reset(seed=seed)
    # NOMAD evaluates its last block whole (it may pass MAX_BB_EVAL by less than a block)
    rec = Recorder(venv, budget + (venv.unwrapped.num_envs if method == "nomad" else 0), log_objective=method == "nomad" and nomad_log)
    space = rec.inner.space
    b = unit_bounds(space)
    own = patient_values(venv)
    s0 = space.to_unit(space.clip(np.array([own[n] for n in space.names])))
    try:
        if method == "nomad":
            from optim.nomad_ref import nomad_minimize

            nomad_minimize(lambda s: rec(s), b, budget, rec.n, seed=seed, x0=s0)
        elif method == "de":
            from scipy.optimize import differential_evolution
            from scipy.stats import qmc

            init = b.lower + qmc.LatinHypercube(d=b.dimension, rng=np.random.default_rng(seed)).random(rec.n) * b.width
            init[0] = s0
            differential_evolution(rec.vector, list(zip(b.lower, b.upper)), init=init, maxiter=budget // rec.n,
                                   vectorized=True, updating="deferred", polish=False, tol=0.0, rng=seed)
        elif method == "nm":
            from scipy.optimize import minimize as scipy_minimize

            scipy_minimize(rec.scalar, s0, method="Nelder-Mead", bounds=list(zip(b.lower, b.upper)),
                           options={"maxfev": budget, "xatol": 1e-8, "fatol": 1e-14})
        else:
            raise ValueError(f"unknown method {method!r}")
    except BudgetExhausted:
        pass
    return to_target(rec.mismatch, rec.elapsed, target)


def median_or_none(values: list) -> float | None:
    """Median over seeds, counting a miss as +inf; None when half or more missed."""
    v = np.array([np.inf if x is None else x for x in values], float)
    med = float(np.median(v))
    return med if np.isfinite(med) else None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--patients", nargs="+", default=["normal", "heart_failure"])
    ap.add_argument("--methods", nargs="+", default=["mads", "nomad", "de", "nm", "cma"])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--budget", type=int, default=480)
    ap.add_argument("--num-envs", type=int, default=16)
    ap.add_argument("--steps-per-beat", type=int, default=500)
    ap.add_argument("--target", type=float, default=0.03)
    ap.add_argument("--nomad-objective", choices=("log", "raw"), default="log", help="what NOMAD minimises: log10 f or f")
    ap.add_argument("--out", default=None, help="also write the JSON here")
    a = ap.parse_args()
    report = {"settings": vars(a), "results": {}}
    for name in a.patients:
        venv = make_env(builtin(name), a.num_envs, a.steps_per_beat)
        compile_time = warm_up(venv)
        report["results"][name] = {"compile_time": compile_time}
        for method in a.methods:
            runs = [run_one(method, venv, a.budget, seed, a.target, a.nomad_objective == "log") for seed in range(a.seeds)]
            report["results"][name][method] = {
                "median_evaluations_to_target": median_or_none([r["evaluations_to_target"] for r in runs]),
                "median_wall_time_to_target": median_or_none([r["wall_time_to_target"] for r in runs]),
                "reached": sum(r["evaluations_to_target"] is not None for r in runs) / len(runs),
                "median_final_mismatch": float(np.median([r["final_mismatch"] for r in runs])),
                "median_wall_time": float(np.median([r["wall_time"] for r in runs])),
                "runs": runs,
            }
        venv.close()
    text = json.dumps(report, indent=1)
    if a.out:
        with open(a.out, "w") as fh:
            fh.write(text)
    print(text)


if __name__ == "__main__":
    main()
