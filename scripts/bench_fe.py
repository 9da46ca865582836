"""Benchmark the FE oracle: passive inflation and a coupled beat (N, ②); prints one JSON object.

    python scripts/bench_fe.py [--mesh-sizes 6 4] [--repeats 3] [--beat-mesh-sizes 10 6] [--dt 0.005] [--skip-beat]
                               [--skip-passive]

Targets (2-core machine): passive inflation ≤ 20 s and a coarse active beat ≤ 3 min (issue 5);
the default-mesh beat (h = 6 mm) ≤ 60 s on one core (issue 29). Passive runs use the default and
the next finer mesh. The beat's ``--dt`` defaults to the oracle's (``fe_oracle.api.DEFAULT_DT``, the
step a campaign runs). Runs bypass the cache (``use_cache=False``); form
compilation is warmed up first so it is not counted. Passive timings are medians over
``--repeats`` runs; a beat is timed once. The beat's metrics come from
:func:`fe_oracle.metrics.beat_metrics` (internal units: ml, s, kPa).

A beat's ``breakdown_s`` splits its time (s) into the Jacobian and residual assemblies, the LU
factorisations and triangular solves (PETSc's event log), the cell update at the quadrature
points and the stretch interpolation (profiled methods of the coupled beat), and the rest;
``counts`` gives the LU factorisations (one per Jacobian assembled), residual assemblies and
triangular solves, and ``cpu_seconds`` the process's CPU time, steadier than the wall time on
a loaded machine.
Only :func:`fe_oracle.run` and method names are used, so the script times any checkout: run it
with ``PYTHONPATH`` set to each of two checkouts, alternately, for a paired before/after ratio.
"""

from __future__ import annotations

import argparse
import cProfile
import inspect
import json
import pstats
import time

import numpy as np

import dolfinx_solver  # noqa: F401  (must precede petsc4py)
from petsc4py import PETSc

import fe_oracle
from fe_oracle.api import DEFAULT_DT
from fe_oracle.cases import N_UNLOADED, Passive
from fe_oracle.metrics import beat_metrics


DEFAULT_MESH_MM = inspect.signature(fe_oracle.run).parameters["mesh_size"].default


def _passive(h: float, repeats: int) -> dict:
    seconds = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        res = fe_oracle.run(N_UNLOADED, "passive", mesh_size=h, use_cache=False)
        seconds.append(time.perf_counter() - t0)
    m = res.metadata
    return {
        "mesh_size_mm": h,
        "cells": m["cells"],
        "dofs": m["dofs"],
        "seconds_median": float(np.median(seconds)),
        "seconds": seconds,
        "setup_s": m["setup_s"],
        "newton_iterations": m["newton_iterations"],
        "V0_mesh_ml": m["V0_mesh_ml"],
        "V0_analytic_ml": m["V0_analytic_ml"],
        "V0_error": m["V0_mesh_ml"] / m["V0_analytic_ml"] - 1.0,
        "V_at_4kPa_ml": float(res.traces["V"][-1]),
        "target_s": 20.0,
    }


_PETSC_EVENTS = {
    "jacobian_assembly": ("SNESJacobianEval",),
    "residual_assembly": ("SNESFunctionEval",),
    "lu_factorisation": ("MatLUFactorSym", "MatLUFactorNum"),
    "triangular_solves": ("MatSolve",),
}
_PROFILED = {"cell_update": "_advance_cells", "stretch_interpolation": "stretch"}
_COUNTED = {"lu_factorisations": ("MatLUFactorNum",), "residual_assemblies": ("SNESFunctionEval",), "triangular_solves": ("MatSolve",)}


def _petsc_log(events, field: str) -> float:
    return sum(PETSc.Log.Event(name).getPerfInfo()[field] for name in events)


def _timed_beat(h: float, dt: float):
    """(result, wall s, CPU s, breakdown in s, operation counts) of one beat."""
    PETSc.Log.begin()
    before = {key: _petsc_log(events, "time") for key, events in _PETSC_EVENTS.items()}
    counts_before = {key: _petsc_log(events, "count") for key, events in _COUNTED.items()}
    profile = cProfile.Profile()
    t0, cpu0 = time.perf_counter(), time.process_time()
    try:
        res = profile.runcall(fe_oracle.run, N_UNLOADED, 2, mesh_size=h, dt=dt, use_cache=False)
    finally:
        seconds, cpu_seconds = time.perf_counter() - t0, time.process_time() - cpu0
    breakdown = {key: _petsc_log(events, "time") - before[key] for key, events in _PETSC_EVENTS.items()}
    stats = pstats.Stats(profile).stats
    for key, name in _PROFILED.items():
        breakdown[key] = sum(row[3] for (_, _, function), row in stats.items() if function == name)
    breakdown["other"] = seconds - sum(breakdown.values())
    counts = {key: int(_petsc_log(events, "count") - counts_before[key]) for key, events in _COUNTED.items()}
    return res, seconds, cpu_seconds, breakdown, counts


def _beat(h: float, dt: float) -> dict:
    t0 = time.perf_counter()
    out = {"mesh_size_mm": h, "dt_s": dt, "target_s": 60.0 if h == DEFAULT_MESH_MM else 180.0}
    try:
        res, seconds, cpu_seconds, breakdown, counts = _timed_beat(h, dt)
    except fe_oracle.OracleDidNotConverge as err:
        return dict(out, converged=False, failed_at_s=err.time, last_residual=err.residual, seconds=time.perf_counter() - t0)
    m = res.metadata
    metrics = beat_metrics(res)
    return dict(
        out,
        converged=True,
        seconds=seconds,
        cpu_seconds=cpu_seconds,
        breakdown_s=breakdown,
        counts=counts,
        cells=m["cells"],
        steps=m["steps"],
        fe_solves=m["fe_solves"],
        newton_iterations=m["newton_iterations"],
        **{k: metrics[k] for k in ("EDV", "ESV", "EF", "P_lv_peak", "IVCT", "ET", "IVRT", "valid")},
        stretch_range=[m["stretch_min"], m["stretch_max"]],
        stretch_p01_p99=[m["stretch_p01"], m["stretch_p99"]],
        activation_time_max_s=m["activation_time_max_s"],
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mesh-sizes", type=float, nargs="+", default=[6.0, 4.0], help="passive inflation mesh sizes h (mm): default and finer")
    parser.add_argument("--repeats", type=int, default=3, help="passive runs per mesh size (median reported)")
    parser.add_argument("--beat-mesh-sizes", type=float, nargs="+", default=[10.0, 6.0], help="coupled beat mesh sizes h (mm): coarse and finer")
    parser.add_argument("--dt", type=float, default=DEFAULT_DT["dolfinx"], help="beat time step (s; default %(default)s)")
    parser.add_argument("--skip-beat", action="store_true")
    parser.add_argument("--skip-passive", action="store_true")
    args = parser.parse_args()
    fe_oracle.run(N_UNLOADED, Passive(p_max=0.25, n_points=2), mesh_size=10.0, use_cache=False)  # warm-up: JIT
    report = {"fe_oracle": fe_oracle.__file__, "passive": [] if args.skip_passive else [_passive(h, args.repeats) for h in args.mesh_sizes]}
    if len(report["passive"]) >= 2:
        v = [r["V_at_4kPa_ml"] for r in report["passive"]]
        report["mesh_convergence_V4_change"] = abs(v[1] - v[0]) / v[1]
    if not args.skip_beat:
        fe_oracle.run(N_UNLOADED, 2, mesh_size=10.0, dt=args.dt, duration=2 * args.dt, use_cache=False)  # warm-up: active forms
        report["beat"] = [_beat(h, args.dt) for h in args.beat_mesh_sizes]
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
