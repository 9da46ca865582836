"""Physiological reachability: can the identification parameters reach human resting values?

A deliberately simple demonstration search (batched CMA-ES from ``cma`` over the
:data:`~lvenv.identification.ACTION_BOUNDS` mapped to [0, 1], log scale where marked) on the
steady-state, closed-loop LO heart. The product optimisers live in :mod:`optim`.
"""

from __future__ import annotations

import dataclasses

import cma
import numpy as np

from lvenv.identification import ACTION_BOUNDS, DEFAULT_ACTION_PARAMS, OBSERVATION_TARGETS
from lvenv.params import Heart
from lvenv.simulation import simulate

__all__ = ["ReachResult", "to_physical", "search"]

_FAILED = 1e3


def to_physical(u: np.ndarray, names: tuple[str, ...]) -> np.ndarray:
    """Map unit-cube coordinates ``u`` (..., len(names)) onto the physical bounds."""
    u = np.clip(np.asarray(u, float), 0.0, 1.0)
    out = np.empty_like(u)
    for i, name in enumerate(names):
        b = ACTION_BOUNDS[name]
        out[..., i] = b.lo * (b.hi / b.lo) ** u[..., i] if b.log else b.lo + (b.hi - b.lo) * u[..., i]
    return out


@dataclasses.dataclass(frozen=True)
class ReachResult:
    params: dict[str, float]
    metrics: dict[str, float]
    relative_error: dict[str, float]
    evaluations: int


def search(
    base: Heart,
    targets: dict[str, float] = OBSERVATION_TARGETS,
    names: tuple[str, ...] = DEFAULT_ACTION_PARAMS,
    *,
    seed: int = 0,
    popsize: int = 64,
    max_iterations: int = 80,
    ftarget: float = 1e-6,
    max_beats: int = 60,
) -> ReachResult:
    """Find values of ``names`` within bounds whose steady state matches ``targets``.

    Minimises the mean squared relative error over the targets; members that fail to simulate
    count as infeasible. Returns the best point, its metrics and per-target relative errors.
    """

    def hearts(u):
        return [base.replace(**dict(zip(names, x))) for x in to_physical(u, names)]

    def objective(u):
        res = simulate(hearts(u), max_beats=max_beats, rtol=1e-4, traces=False)
        err = np.mean([((res.metrics[k] - t) / t) ** 2 for k, t in targets.items()], axis=0)
        return np.where(res.status_code <= 1, err, _FAILED)

    es = cma.CMAEvolutionStrategy(np.full(len(names), 0.5), 0.25, {"popsize": popsize, "bounds": [0, 1], "seed": seed + 1, "verbose": -9, "ftarget": ftarget, "maxiter": max_iterations})
    while not es.stop():
        u = np.asarray(es.ask())
        es.tell(list(u), list(objective(u)))
    best_u = np.asarray(es.result.xbest)
    best = simulate(hearts(best_u[None])[0], max_beats=max_beats, rtol=1e-4, traces=False)
    params = dict(zip(names, map(float, to_physical(best_u, names))))
    return ReachResult(
        params=params,
        metrics={k: float(v) for k, v in best.metrics.items()},
        relative_error={k: float((best.metrics[k] - t) / t) for k, t in targets.items()},
        evaluations=int(es.result.evaluations),
    )
