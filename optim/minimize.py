"""`minimize(venv, method, budget, ...)`: the inverse problem through the vector environment.

One optimiser round (`ask` of at most num_envs points) is one `venv.step`: the points are padded
to num_envs rows with copies of the last one (`optim.protocol.padded`), the extra rows are
discarded. The env must be built for optimisation, i.e.

    venv = gymnasium.make_vec("lvenv/LVHeart-v0", num_envs=N, patient=p,
                              autoreset_mode="Disabled", tolerance=0.0, max_episode_steps=None)

so that every step evaluates every member's action (DESIGN §2). All members must hold the same
patient.

Objective (what the optimisers minimise), per evaluated parameter set x:

    f(x) = −reward(x) = Σ_k w_k e_k² / Σ_k w_k  +  κ (d / P_lo)²,     e_k = (o_k − t_k) / t_k,

the env's reward (`lvenv.env.core`): the weighted mean squared relative error over the patient's
targets plus the soft penalty for mean central aortic pressure outside [P_lo, P_hi] =
[80, 120] mmHg (d = distance to the band, κ = 1). The aortic band is therefore a documented
penalty, not a progressive-barrier constraint (violation h = 0 for every point). A member that
fails (status other than "ok" / "not_converged", or a non-finite mismatch) is an infeasible point:
merit +inf, never the incumbent (extreme barrier, `optim.protocol`).

With `log_objective` (default for "kriging") the optimiser sees log10(f + 1e-12) instead of f:
the same minimiser and ranking, but a GP surrogate fitted to it no longer spends its variance on
the few bad points (f from ~1 down to 1e-6 over a fit), which made EGO far better here. MADS gets
f: its poll only compares values, and its kriging search chooses between f and log10 f itself
per fit (`optim.gp.fit_gp_or_log`), which ends its fits 1.7–3× closer than a GP on log10 f alone.
CMA-ES ranks, so it is unaffected; it gets f (pycma's tolfun then stays in f units).
`MinimizeResult.objective` and the history always hold f itself.

Search space (ours): the optimisers work in the unit cube of
`lvenv.identification.ParameterSpace`, in which parameters whose bound is marked `log` (τ2, Sa,
R3, C, Cat) are log-uniform and the others (R2) uniform, so that a fraction of the cube is a
relative change for the parameters spanning decades. Points are mapped to physical units (or to
[−1, 1] for an env in `action_mode="normalized"`) before the step.

Reported mismatch: `result.mismatch` is the env's `info["mismatch"]` at the best point,
Σ_k w_k abs(e_k) / Σ_k w_k, and `result.mismatch_per_target[k] = abs(e_k)`.

Checkpoint / resume: the checkpoint holds the optimiser's evaluation log (`optim.protocol`), the
env's state (`venv.get_state()`: each member's LO-heart state, from which the next step is
warm-started, so it is part of the objective's state), the evaluation records and the env's
configuration, in the safe format of `lvenv.archive`; it is written atomically after every
round. Starting `minimize` with an existing checkpoint of the same configuration replays the log
and reaches exactly the result of an uninterrupted run with the same seed; a damaged checkpoint
or one of another configuration is refused with its path (`optim.protocol.CheckpointError`).
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lvenv.env.vector import info_metrics
from lvenv.identification import ParameterSpace
from lvenv.metrics import OBS_NAMES
from lvenv.patients import Patient
from lvenv.status import is_usable
from lvenv.validation import InputError, integer
from optim.methods import METHODS, make_optimizer
from optim.protocol import (
    BatchEvaluation,
    Bounds,
    CheckpointError,
    FloatArray,
    OptimResult,
    Optimizer,
    load_checkpoint,
    padded,
    resume,
    run,
    save_checkpoint,
)

__all__ = ["EnvHistory", "MinimizeResult", "EnvObjective", "minimize", "patient_values", "unit_bounds"]

LOG_FLOOR = 1e-12
LOG_OBJECTIVE_METHODS = ("kriging",)
_RECORD_FIELDS = ("x", "f", "feasible", "mismatch", "obs", "status")


def unit_bounds(space: ParameterSpace) -> Bounds:
    """The optimisers' box: the unit cube of ``space``, with its parameter names."""
    return Bounds(np.zeros(space.dimension), np.ones(space.dimension), space.names)


@dataclasses.dataclass(frozen=True)
class EnvHistory:
    """Every evaluation in order: x (m, k) physical parameters, f the objective (−reward),
    feasible, mismatch (inf where failed), observations (m, n_obs) internal units (columns
    `obs_names`), status strings, batch = index of the vector-env step, and elapsed = optimiser
    wall time (s) at the end of that evaluation's round."""

    names: tuple[str, ...]
    obs_names: tuple[str, ...]
    x: FloatArray
    f: FloatArray
    feasible: NDArray[np.bool_]
    mismatch: FloatArray
    observations: FloatArray
    status: NDArray[np.str_]
    batch: NDArray[np.int64]
    elapsed: FloatArray

    def best_mismatch_so_far(self) -> FloatArray:
        """Running minimum of the mismatch over the evaluations (inf before the first success)."""
        return np.minimum.accumulate(self.mismatch) if len(self.mismatch) else self.mismatch

    def to_target(self, target: float) -> tuple[int | None, float | None]:
        """(evaluations, wall time in s) until the first point with mismatch < target, or Nones."""
        hit = np.flatnonzero(self.mismatch < target)
        if not hit.size:
            return None, None
        return int(hit[0]) + 1, float(self.elapsed[hit[0]])


@dataclasses.dataclass(frozen=True)
class MinimizeResult:
    """Outcome of `minimize`. Internal units (kPa, ml, s); convert with `lvenv.units` for display.

    parameters: best parameter set by name (physical). observation: the env's observation there,
    by `OBS_NAMES`. mismatch: Σ w_k abs(e_k) / Σ w_k there (float; inf if no point succeeded).
    mismatch_per_target: abs(e_k) per target; relative_error: signed e_k. objective: f = −reward.
    wall_time: optimiser rounds (ask + env step + tell), summed over resumed segments; the first
    step on a fresh env includes its JIT compilation.
    """

    method: str
    patient: str
    parameters: dict[str, float]
    observation: dict[str, float]
    targets: dict[str, float]
    mismatch: float
    mismatch_per_target: dict[str, float]
    relative_error: dict[str, float]
    objective: float
    status: str
    evaluations: int
    batches: int
    wall_time: float
    stop_reason: dict[str, float]
    history: EnvHistory
    optim_result: OptimResult


def _unwrap(venv: Any) -> Any:
    return getattr(venv, "unwrapped", venv)


class EnvObjective:
    """Batch objective over a vector env: (q, k) unit-cube points of ``space``, q <= num_envs → one step.

    Keeps a record of every evaluation (observations, mismatch, status) for the result.
    """

    def __init__(self, venv: Any, space: ParameterSpace, log_objective: bool = False) -> None:
        env = _unwrap(venv)
        self.log_objective = bool(log_objective)
        self.venv = venv
        self.space = space
        self.num_envs = int(env.num_envs)
        self.action_map = env.config.actions
        self.records: list[dict[str, Any]] = []

    def _step(self, u: FloatArray) -> BatchEvaluation:
        x = self.space.clip(self.space.from_unit(u))  # the optimisers keep u in [0, 1]; clip guards rounding
        _, reward, _, _, info = self.venv.step(self.action_map.to_action(x))
        status = np.asarray(info["status"]).astype(str)
        mismatch = np.asarray(info["mismatch"], np.float64)
        feasible = is_usable(status) & np.isfinite(mismatch) & np.isfinite(reward)
        mismatch = np.where(feasible, mismatch, np.inf)
        obs = info_metrics(info)
        self.records.append(
            {"x": x, "f": -np.asarray(reward, np.float64), "feasible": feasible,
             "mismatch": mismatch, "obs": obs, "status": status}
        )
        return BatchEvaluation.coerce(self.merit(-np.asarray(reward, np.float64)), len(x), feasible)

    def merit(self, f: FloatArray) -> FloatArray:
        """What the optimiser sees: f = −reward, or log10(f + 1e-12) with `log_objective`."""
        if not self.log_objective:
            return f
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.log10(np.maximum(f, 0.0) + LOG_FLOOR)

    def objective(self) -> Callable[[FloatArray], BatchEvaluation]:
        """The padded batch objective handed to `optim.run`; records keep only the first q rows."""
        inner = padded(self._step, self.num_envs)

        def objective(s: FloatArray) -> BatchEvaluation:
            ev = inner(s)
            q = len(s)
            self.records[-1] = {k: v[:q] for k, v in self.records[-1].items()}
            return ev

        return objective


def _patient(venv: Any) -> Patient:
    patients = list(getattr(_unwrap(venv), "patients", []))
    if not patients:
        raise InputError("minimize needs an lvenv vector env (gymnasium.make_vec('lvenv/LVHeart-v0', ...))")
    if any(p != patients[0] for p in patients[1:]):
        raise InputError("minimize fits one patient: every member of the vector env must hold the same patient")
    return patients[0]


def _check_env(venv: Any) -> None:
    env = _unwrap(venv)
    if env.config.autoreset:
        raise InputError(
            "minimize needs autoreset_mode='Disabled' (every step must evaluate every member); "
            "build the env with gymnasium.make_vec(..., autoreset_mode='Disabled', tolerance=0.0)"
        )
    if env.config.max_episode_steps is not None:
        raise InputError("minimize needs max_episode_steps=None")


def _options(method: str, options: dict[str, Any]) -> Any:
    options_cls = METHODS[method][1]
    fields = {f.name for f in dataclasses.fields(options_cls)}
    if unknown := sorted(set(options) - fields):
        raise TypeError(
            f"method {method!r} has no option(s) {unknown}; {options_cls.__name__} fields: {sorted(fields)}"
        )
    return options_cls(**options)


def _env_key(venv: Any, patient: Patient) -> dict[str, Any]:
    """The env's configuration as JSON, stored in and compared against a checkpoint."""
    c = _unwrap(venv).config
    return {"actions": list(c.actions.names), "mode": c.actions.mode, "steps_per_beat": c.steps_per_beat,
            "max_beats": c.max_beats, "rtol": c.rtol, "obs_noise": None if c.obs_noise is None else list(c.obs_noise),
            "num_envs": int(_unwrap(venv).num_envs), "patient": patient.to_dict()}


def minimize(
    venv: Any,
    method: str = "mads",
    budget: int = 1000,
    seed: int = 0,
    callback: Callable[[Optimizer], bool | None] | None = None,
    checkpoint: str | os.PathLike[str] | None = None,
    progress: bool | None = None,
    x0: Mapping[str, float] | None = None,
    bounds: Mapping[str, tuple[float, float]] | None = None,
    log_objective: bool | None = None,
    **options: Any,
) -> MinimizeResult:
    """Fit the env's action parameters to its patient's targets; see the module docstring.

    Args:
        venv: an `lvenv/LVHeart-v0` vector env (autoreset Disabled, no truncation), one patient.
        method: "mads" (OrthoMADS + kriging search), "cma" (CMA-ES) or "kriging" (batch EGO).
        budget: maximum number of evaluations (parameter sets); must cover one batch (num_envs
            points; one CMA generation).
        seed: seeds the optimiser and `venv.reset`.
        callback: `callback(optimizer)` after every round (one env step); True stops the run.
        checkpoint: file written after every round; an existing one is resumed.
        progress: tqdm bar (None: only on a terminal).
        x0: start point by name (default: the patient's own values, clipped into the bounds).
        bounds: narrower physical bounds by name, e.g. {"C": (5.0, 20.0)}.
        log_objective: optimise log10(f + 1e-12) (None: True for "kriging" only).
        **options: fields of the method's options (`MadsOptions`, `CmaOptions`, `KrigingOptions`),
            plus `penalty` (weight of a violation h; unused here since h = 0).

    Raises ValueError for an unknown method, a budget below one batch, bad bounds, or an env not
    built for optimisation; TypeError for an unknown option.
    """
    if not isinstance(method, str) or method not in METHODS:
        raise InputError(f"unknown method {method!r}; choose one of {', '.join(map(repr, METHODS))}")
    budget, seed = integer("budget", budget, 1), integer("seed", seed, 0)
    penalty = float(options.pop("penalty", 1.0))
    opts = _options(method, options)
    patient = _patient(venv)
    _check_env(venv)
    env = _unwrap(venv)
    space = ParameterSpace.for_names(env.action_names, bounds)
    start = patient_values(venv)
    if x0 is not None:
        if unknown := sorted(set(x0) - set(space.names)):
            raise InputError(f"x0 names {unknown}, which are not action parameters {space.names}")
        start.update({k: float(v) for k, v in x0.items()})
    u_start = space.to_unit(space.clip(np.array([start[n] for n in space.names], float)))
    opt = make_optimizer(method, unit_bounds(space), env.num_envs, seed=seed, x0=u_start, penalty=penalty, options=opts)
    if budget < opt.min_budget:
        raise InputError(
            f"budget = {budget} evaluations is below one batch of {opt.min_budget} "
            f"({method} with num_envs = {env.num_envs})"
        )
    if log_objective is None:
        log_objective = method in LOG_OBJECTIVE_METHODS
    objective = EnvObjective(venv, space, log_objective)
    venv.reset(seed=seed)
    env_key = _env_key(venv, patient)
    elapsed: list[float] = []
    path = Path(checkpoint) if checkpoint is not None else None
    if path is not None and path.exists():
        saved = load_checkpoint(path)
        if saved.meta["user"].get("env") != env_key:
            raise CheckpointError(
                f"checkpoint {str(path)!r} was written for a different env or patient "
                "(parameters, settings, num_envs or targets); delete it or use the same settings"
            )
        opt = resume(opt, saved)
        objective.records = _split_records(saved.extra)
        elapsed = saved.extra["elapsed"].tolist()
        venv.set_state({k[len("env."):]: v for k, v in saved.extra.items() if k.startswith("env.")})

    def after_round(o: Optimizer) -> bool | None:
        elapsed.append(o.wall_time)
        if path is not None:
            extra = {f"record.{k}": np.concatenate([r[k] for r in objective.records]) for k in _RECORD_FIELDS}
            extra["record.sizes"] = np.array([len(r["x"]) for r in objective.records])
            extra["elapsed"] = np.array(elapsed)
            extra.update({f"env.{k}": v for k, v in venv.get_state().items()})
            save_checkpoint(path, o, budget, extra, {"env": env_key, "method": method})
        return callback(o) if callback is not None else None

    res = run(opt, objective.objective(), budget, callback=after_round, progress=progress)
    return _result(method, patient, space, objective.records, elapsed, res)


def _split_records(extra: dict[str, np.ndarray]) -> list[dict[str, Any]]:
    """The per-round evaluation records of a checkpoint (inverse of the concatenation in `minimize`)."""
    cuts = np.cumsum(extra["record.sizes"])[:-1]
    split = {k: np.split(extra[f"record.{k}"], cuts) for k in _RECORD_FIELDS}
    return [{k: split[k][i] for k in _RECORD_FIELDS} for i in range(len(extra["record.sizes"]))]


def patient_values(venv: Any) -> dict[str, float]:
    """The patient's own values of the env's action parameters (physical units), by name."""
    heart = _patient(venv).heart
    return {name: float(heart.get(name)) for name in _unwrap(venv).action_names}


def _result(
    method: str,
    patient: Patient,
    space: ParameterSpace,
    records: list[dict[str, Any]],
    elapsed: list[float],
    res: OptimResult,
) -> MinimizeResult:
    k = len(space.names)
    if records:
        cat = {key: np.concatenate([r[key] for r in records]) for key in records[0]}
        batch = np.concatenate([np.full(len(r["x"]), i, np.int64) for i, r in enumerate(records)])
        times = np.concatenate([np.full(len(r["x"]), elapsed[i]) for i, r in enumerate(records)])
    else:
        cat = {"x": np.empty((0, k)), "f": np.empty(0), "feasible": np.empty(0, bool),
               "mismatch": np.empty(0), "obs": np.empty((0, len(OBS_NAMES))), "status": np.empty(0, str)}
        batch, times = np.empty(0, np.int64), np.empty(0)
    history = EnvHistory(space.names, OBS_NAMES, cat["x"], cat["f"], cat["feasible"], cat["mismatch"],
                         cat["obs"], cat["status"], batch, times)
    merit = np.where(history.feasible, history.f, np.inf)
    targets = dict(patient.targets)
    if np.isfinite(merit).any():
        i = int(np.argmin(merit))
        parameters = dict(zip(space.names, map(float, history.x[i])))
        observation = dict(zip(OBS_NAMES, map(float, history.observations[i])))
        rel = {t: (observation[t] - v) / v for t, v in targets.items()}
        mismatch, objective, status = float(history.mismatch[i]), float(history.f[i]), str(history.status[i])
    else:
        parameters = dict.fromkeys(space.names, float("nan"))
        observation = dict.fromkeys(OBS_NAMES, float("nan"))
        rel = dict.fromkeys(targets, float("nan"))
        mismatch, objective, status = float("inf"), float("inf"), "failed"
    return MinimizeResult(
        method=method,
        patient=patient.name,
        parameters=parameters,
        observation=observation,
        targets=targets,
        mismatch=mismatch,
        mismatch_per_target={t: abs(e) for t, e in rel.items()},
        relative_error=rel,
        objective=objective,
        status=status,
        evaluations=res.evaluations,
        batches=res.batches,
        wall_time=res.wall_time,
        stop_reason=res.stop_reason,
        history=history,
        optim_result=res,
    )
