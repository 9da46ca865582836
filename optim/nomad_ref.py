"""Reference runs of NOMAD 4 (Audet, Le Digabel, Rochon Montplaisir, Tribes 2022, ACM TOMS
48(3):35) through PyNomad, with the same batch-objective interface as `optim.run`.

NOMAD polls with `DIRECTION_TYPE ORTHO 2N` (OrthoMADS) and hands its trial points to the
objective in blocks of at most `BB_MAX_BLOCK_SIZE = batch_size` (one vector-env step per block).
It works on the unit cube like `optim.Mads`, and minimises the same merit
f + penalty · h with failed points reported as failed evaluations. NOMAD's own search steps
(speculative, quadratic models, Nelder-Mead) stay on unless `params` turns them off; they submit
small blocks, which is part of what a wall-time comparison through a vector env measures.
NOMAD evaluates its last block whole, so it may exceed `budget` by less than one block.
PyNomad is the optional `nomad` extra (`pip install PyNomadBBO`) and is imported lazily.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from optim.protocol import BatchEvaluation, BatchObjective, Bounds, History, OptimResult


def nomad_minimize(
    batch_objective: BatchObjective,
    bounds: Bounds,
    budget: int,
    batch_size: int,
    seed: int = 0,
    x0: ArrayLike | None = None,
    penalty: float = 1.0,
    params: Sequence[str] = (),
) -> OptimResult:
    """Run NOMAD (ORTHO 2N, block evaluation) and return an `OptimResult` with its history."""
    try:
        import PyNomad
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError(
            "nomad_minimize needs PyNomad: pip install 'lvenv[nomad]' (PyNomadBBO)"
        ) from exc
    if budget < batch_size:
        raise ValueError(f"budget = {budget} evaluations is below one batch of {batch_size}")
    n = bounds.dimension
    u0 = np.full(n, 0.5) if x0 is None else bounds.to_unit(np.asarray(x0, np.float64))
    records: list[tuple[np.ndarray, BatchEvaluation, np.ndarray]] = []
    errors: list[BaseException] = []

    def bb_block(block: Any) -> list[bool]:
        q = block.size()
        points = [block.get_x(k) for k in range(q)]
        u = np.array([[p.get_coord(i) for i in range(n)] for p in points], dtype=np.float64)
        x = np.clip(bounds.from_unit(u), bounds.lower, bounds.upper)
        try:
            ev = BatchEvaluation.from_objective_output(batch_objective(x), q)
        except BaseException as exc:  # surfaced after NOMAD returns
            errors.append(exc)
            return [False] * q
        merit = np.where(ev.feasible, ev.f + penalty * ev.violation, np.inf)
        records.append((x, ev, merit))
        for p, m, ok in zip(points, merit, ev.feasible):
            if ok:
                p.setBBO(repr(float(m)).encode("UTF-8"))
        return [bool(ok) for ok in ev.feasible]

    settings = [
        "BB_OUTPUT_TYPE OBJ",
        f"MAX_BB_EVAL {int(budget)}",
        "DIRECTION_TYPE ORTHO 2N",
        f"BB_MAX_BLOCK_SIZE {int(batch_size)}",
        f"SEED {int(seed)}",
        "DISPLAY_DEGREE 0",
        *params,
    ]
    start = time.perf_counter()
    out = PyNomad.optimize(bb_block, u0.tolist(), [0.0] * n, [1.0] * n, settings)
    wall = time.perf_counter() - start
    if errors:
        raise errors[0]
    if records:
        hx = np.concatenate([r[0] for r in records])
        hf = np.concatenate([r[1].f for r in records])
        feas = np.concatenate([r[1].feasible for r in records])
        viol = np.concatenate([r[1].violation for r in records])
        merit = np.concatenate([r[2] for r in records])
        batch = np.concatenate([np.full(len(r[0]), i, np.int64) for i, r in enumerate(records)])
    else:
        hx, batch = np.empty((0, n)), np.empty(0, np.int64)
        hf, feas, viol, merit = (np.empty(0) for _ in range(4))
    history = History(hx, hf, feas.astype(bool), viol, merit, batch)
    finite = np.isfinite(merit)
    if finite.any():
        i = int(np.argmin(np.where(finite, merit, np.inf)))
        x_best, f_best, m_best = hx[i].copy(), float(hf[i]), float(merit[i])
    else:
        x_best, f_best, m_best = np.full(n, np.nan), np.inf, np.inf
    return OptimResult(
        x_best=x_best,
        f_best=f_best,
        merit_best=m_best,
        evaluations=len(hf),
        batches=len(records),
        history=history,
        stop_reason={str(out.get("stop_reason", "nomad")): float(out.get("run_flag", 0))},
        wall_time=wall,
        info={"nomad_evaluations": float(out.get("nb_evals", len(hf)))},
    )
