"""Benchmark cohort fitting (`optim.cohort`, all patients in one env) against fitting the same
patients one after another with `optim.minimize`, in the same run (JSON out).

    python scripts/bench_cohort.py [--patients 48] [--reports out/cohort/reports.csv]

Both sides use CMA-ES with λ = 8, the same budget (640 evaluations) and the same per-patient stop
(mismatch below 1 %). The baseline is what a user without `optim.cohort` would write: one
8-member env (steps to steady state, at most 60 beats per step) and `minimize(..., callback=stop
at 1 %)` per patient, the env compiled once beforehand. Reported: wall time, patients per second,
the ratio (cohort / baseline), and the median and 95th percentile of the mismatch of each.
The cohort side includes its compilation; the baseline's compilation is reported apart.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import gymnasium
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from optim.cohort import CohortOptions, distribution, fit_reports, read_reports  # noqa: E402
from optim.fit import make_env, warm_up  # noqa: E402
from optim.minimize import minimize  # noqa: E402
from scripts import make_cohort  # noqa: E402


class _BestMismatch(gymnasium.vector.VectorWrapper):
    """Keeps the lowest mismatch any step has returned since the last reset."""

    def reset(self, **kwargs):
        self.best = np.inf
        return super().reset(**kwargs)

    def step(self, actions):
        out = super().step(actions)
        self.best = min(self.best, float(np.min(out[4]["mismatch"])))
        return out


def baseline(reports, options: CohortOptions) -> dict:
    venv = _BestMismatch(make_env(reports[0].patient, options.candidates, options.steps_per_beat))
    compile_time = warm_up(venv)
    start = time.perf_counter()
    mismatch, evaluations = [], []
    for report in reports:
        venv.reset(options={"patient": report.patient})
        res = minimize(venv, "cma", budget=options.budget, seed=options.seed, progress=False, sigma0=options.sigma0,
                       restarts=10**6, callback=lambda opt: venv.best < options.stop_mismatch)
        mismatch.append(res.mismatch)
        evaluations.append(res.evaluations)
    wall = time.perf_counter() - start
    venv.close()
    return {"wall_time_s": wall, "compile_time_s": compile_time, "patients_per_s": len(reports) / wall,
            "mismatch": distribution(mismatch), "median_evaluations": float(np.median(evaluations))}


def cohort(reports, options: CohortOptions) -> dict:
    start = time.perf_counter()
    results = fit_reports(reports, options)
    wall = time.perf_counter() - start
    return {"wall_time_s": wall, "patients_per_s": len(reports) / wall, "mismatch": distribution([r["mismatch"] for r in results]),
            "median_evaluations": float(np.median([r["evaluations"] for r in results])), "status": sorted({r["status"] for r in results})}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--patients", type=int, default=48)
    parser.add_argument("--reports", type=Path, default=None, help="a report CSV (default: a synthetic one, seed 7)")
    args = parser.parse_args(argv)
    path = args.reports
    if path is None:
        rows, _ = make_cohort.draw(args.patients, seed=7)
        path = Path(tempfile.mkdtemp()) / "reports.csv"
        make_cohort.write(rows, path)
    reports = read_reports(path).rows[: args.patients]
    options = CohortOptions()
    ours = cohort(reports, options)
    base = baseline(reports, options)
    json.dump({"patients": len(reports), "options": options.to_dict(), "cohort": ours, "one_after_another": base,
               "speed_ratio": ours["patients_per_s"] / base["patients_per_s"]}, sys.stdout, indent=2)
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
