"""Optimisers behind one ask/tell protocol: OrthoMADS with kriging search, CMA-ES, kriging/EGO.

    bounds = Bounds(lower, upper, names)                 # physical units
    opt = make_optimizer("mads" | "cma" | "kriging", bounds, batch_size=num_envs, seed=0)
    res = run(opt, batch_objective, budget, callback=None, checkpoint=None, progress=None)

`batch_objective(X)` takes a (q, n) array of physical points, q <= batch_size (one vector-env
step; wrap with `padded` if the env needs exactly num_envs rows), and returns f (q,), or
(f, feasible), or (f, feasible, violation), or a `BatchEvaluation`. NaN / inf values and
feasible = False are failed points, never a crash. See `optim.protocol` for the merit and the
checkpoint contract.

Through the heart's vector env (DESIGN §2): `minimize(venv, method, budget, seed, ...)` returns a
`MinimizeResult` (best parameters and observation by name, mismatch per target, history);
`optim.fit.fit_patients` runs the inverse problem for the built-in patients.
"""

from optim.barrier import ProgressiveBarrier
from optim.cmaes import CmaEs, CmaOptions
from optim.kriging import Kriging, KrigingOptions
from optim.mads import Mads, MadsOptions
from optim.methods import METHODS, make_optimizer, minimize_batch
from optim.minimize import EnvHistory, MinimizeResult, minimize
from optim.protocol import (
    BatchEvaluation,
    Bounds,
    CheckpointError,
    History,
    OptimResult,
    Optimizer,
    load_checkpoint,
    padded,
    resume,
    run,
    save_checkpoint,
)

__all__ = [
    "METHODS",
    "BatchEvaluation",
    "Bounds",
    "CheckpointError",
    "CmaEs",
    "CmaOptions",
    "EnvHistory",
    "History",
    "Kriging",
    "KrigingOptions",
    "Mads",
    "MadsOptions",
    "MinimizeResult",
    "OptimResult",
    "Optimizer",
    "ProgressiveBarrier",
    "load_checkpoint",
    "make_optimizer",
    "minimize",
    "minimize_batch",
    "padded",
    "resume",
    "run",
    "save_checkpoint",
]
