"""Method registry: build an optimiser by name and run it on a batch objective.

`optim.minimize(venv, ...)` is meant to be a thin layer over `minimize_batch`: the vector env's
`step` on a (num_envs, n) action array is the batch objective, num_envs is the batch size.
"""

from __future__ import annotations

import os
from typing import Any

from numpy.typing import ArrayLike

from optim.cmaes import CmaEs, CmaOptions
from optim.kriging import Kriging, KrigingOptions
from optim.mads import Mads, MadsOptions
from optim.protocol import BatchObjective, Bounds, Callback, OptimResult, Optimizer, run

METHODS: dict[str, tuple[type[Optimizer], type]] = {
    "mads": (Mads, MadsOptions),
    "cma": (CmaEs, CmaOptions),
    "kriging": (Kriging, KrigingOptions),
}


def make_optimizer(
    method: str,
    bounds: Bounds,
    batch_size: int,
    seed: int = 0,
    x0: ArrayLike | None = None,
    penalty: float = 1.0,
    options: Any = None,
) -> Optimizer:
    """Optimiser for `method` in {"mads", "cma", "kriging"}; options must be its ``*Options`` type."""
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; choose one of {', '.join(map(repr, METHODS))}")
    cls, options_cls = METHODS[method]
    if options is not None and not isinstance(options, options_cls):
        raise TypeError(
            f"method {method!r} takes options of type {options_cls.__name__}, "
            f"got {type(options).__name__}"
        )
    return cls(bounds, batch_size, seed=seed, options=options, penalty=penalty, x0=x0)


def minimize_batch(
    batch_objective: BatchObjective,
    bounds: Bounds,
    method: str = "mads",
    budget: int = 1000,
    batch_size: int = 1,
    seed: int = 0,
    x0: ArrayLike | None = None,
    penalty: float = 1.0,
    options: Any = None,
    callback: Callback | None = None,
    checkpoint: str | os.PathLike[str] | None = None,
    progress: bool | None = None,
) -> OptimResult:
    """make_optimizer(...) then run(...); see `optim.protocol.run` for the loop and checkpoints."""
    opt = make_optimizer(method, bounds, batch_size, seed, x0, penalty, options)
    return run(
        opt, batch_objective, budget, callback=callback, checkpoint=checkpoint, progress=progress
    )
