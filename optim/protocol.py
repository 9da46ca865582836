"""The ask / tell / stop / result protocol shared by every optimiser, and the one driver `run`.

Protocol (pycma style: Hansen N, Akimoto Y, Baudis P (2019) CMA-ES/pycma, doi:10.5281/zenodo.2559634):

    X = opt.ask(budget_left)      # (q, n) candidates in PHYSICAL units, 1 <= q <= opt.batch_size
    opt.tell(X, f, feasible, violation)
    reasons = opt.stop()          # dict of termination reasons -> value; empty while running
    res = opt.result              # OptimResult

Spaces. Every optimiser works internally in the unit cube u in [0, 1]^n,

    u = (x - lower) / (upper - lower),        x = lower + u * (upper - lower),

so step sizes (MADS poll size, CMA sigma, GP length scales) are fractions of the box. `ask`
returns and `tell` takes physical points x, so that a batch maps onto one vector-env step with no
further conversion.

Evaluations. A batch objective maps a (q, n) array to q objective values, optionally with a
feasibility mask and a relaxable constraint violation h >= 0 (see `BatchEvaluation`). A point is
infeasible when the mask says so or when f or h is NaN / infinite (a failed evaluation): it gets
the merit +inf and is never chosen as the best point (extreme barrier, Audet & Dennis 2006 §2).
For a feasible point the optimisers minimise the exact L1-penalty merit (Fletcher 1987, §14.3)

    phi(x) = f(x) + rho * h(x),      rho = `penalty` (default 1, h in objective units),

which has the constrained minimiser as its minimiser for rho above the constraint's Lagrange
multiplier. The merit is non-smooth where the constraint is active, which slows direct search
there; `optim.Mads` can instead treat h by the progressive barrier (`optim.barrier`).

Checkpoints. An optimiser is a deterministic function of its configuration (fingerprint: class,
bounds, batch size, seed, penalty, x0, options) and of the values it was told. A checkpoint is
therefore the evaluation log (x, f, feasible, violation, batch) plus the fingerprint, written in
the safe format of `lvenv.archive` (an .npz of arrays and JSON; no pickle). `resume` replays the
log into a fresh optimiser of the same configuration, checking that every replayed `ask`
returns exactly the logged points, so a resumed run reaches bit for bit the result of an
uninterrupted one; a checkpoint of another configuration, a damaged file, or a log that does not
replay (other code or platform) is refused with the path and what to do.
"""

from __future__ import annotations

import abc
import dataclasses
import json
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lvenv import archive

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

CHECKPOINT_FORMAT = "optim/2"
LOG_FIELDS = ("x", "f", "feasible", "violation", "batch")


class CheckpointError(archive.ArchiveError):
    """A checkpoint that cannot be resumed: damaged, of another configuration, or not replayable."""


@dataclasses.dataclass(frozen=True, eq=False)
class Bounds:
    """Box lower <= x <= upper in physical units, with optional parameter names for errors."""

    lower: FloatArray
    upper: FloatArray
    names: tuple[str, ...] | None = None

    def __post_init__(self) -> None:
        lower = np.array(self.lower, dtype=np.float64).reshape(-1)
        upper = np.array(self.upper, dtype=np.float64).reshape(-1)
        if lower.shape != upper.shape or lower.size == 0:
            raise ValueError(
                f"bounds: lower has {lower.size} entries and upper {upper.size}; "
                "they must be non-empty and equally long"
            )
        names = tuple(self.names) if self.names is not None else None
        if names is not None and len(names) != lower.size:
            raise ValueError(f"bounds: {len(names)} names for {lower.size} parameters")
        for i in range(lower.size):
            label = names[i] if names is not None else f"x[{i}]"
            if not (np.isfinite(lower[i]) and np.isfinite(upper[i])):
                raise ValueError(
                    f"bounds of {label} must be finite, got [{lower[i]}, {upper[i]}]"
                )
            if not lower[i] < upper[i]:
                raise ValueError(
                    f"bounds of {label}: lower = {lower[i]} must be < upper = {upper[i]}"
                )
        lower.flags.writeable = False
        upper.flags.writeable = False
        object.__setattr__(self, "lower", lower)
        object.__setattr__(self, "upper", upper)
        object.__setattr__(self, "names", names)

    @property
    def dimension(self) -> int:
        return int(self.lower.size)

    @property
    def width(self) -> FloatArray:
        return self.upper - self.lower

    def to_unit(self, x: ArrayLike) -> FloatArray:
        """u = (x - lower) / (upper - lower)."""
        return (np.asarray(x, dtype=np.float64) - self.lower) / self.width

    def from_unit(self, u: ArrayLike) -> FloatArray:
        """x = lower + u (upper - lower)."""
        return self.lower + np.asarray(u, dtype=np.float64) * self.width

    def __eq__(self, other: object) -> bool:
        return (
            isinstance(other, Bounds)
            and np.array_equal(self.lower, other.lower)
            and np.array_equal(self.upper, other.upper)
            and self.names == other.names
        )

    def __hash__(self) -> int:
        return hash((self.lower.tobytes(), self.upper.tobytes(), self.names))


@dataclasses.dataclass(frozen=True)
class BatchEvaluation:
    """Outcome of evaluating q points: f (q,), feasible (q,) bool, violation h (q,) >= 0."""

    f: FloatArray
    feasible: BoolArray
    violation: FloatArray

    @classmethod
    def coerce(
        cls,
        f: ArrayLike,
        q: int,
        feasible: ArrayLike | None = None,
        violation: ArrayLike | None = None,
    ) -> BatchEvaluation:
        """Check shapes and mark NaN / infinite values infeasible (a failed evaluation)."""
        f_arr = np.asarray(f, dtype=np.float64).reshape(-1)
        mask = np.ones(q, bool) if feasible is None else np.asarray(feasible, bool).reshape(-1)
        h = np.zeros(q) if violation is None else np.asarray(violation, np.float64).reshape(-1)
        for name, arr in (("f", f_arr), ("feasible", mask), ("violation", h)):
            if arr.size != q:
                raise ValueError(f"batch objective returned {arr.size} values of {name} for {q} points")
        mask = mask & np.isfinite(f_arr) & np.isfinite(h)
        h = np.where(np.isfinite(h), np.maximum(h, 0.0), np.inf)
        return cls(f=f_arr, feasible=mask, violation=h)

    @classmethod
    def from_objective_output(cls, out: Any, q: int) -> BatchEvaluation:
        """Accept `f`, `(f, feasible)`, `(f, feasible, violation)` or a `BatchEvaluation`."""
        if isinstance(out, BatchEvaluation):
            return cls.coerce(out.f, q, out.feasible, out.violation)
        if isinstance(out, tuple):
            if not 1 <= len(out) <= 3:
                raise ValueError(
                f"batch objective returned a tuple of {len(out)} items; expected 1 to 3"
            )
            return cls.coerce(*((out[0], q) + tuple(out[1:])))
        return cls.coerce(out, q)


@dataclasses.dataclass(frozen=True)
class History:
    """Every evaluation in order. x: (m, n) physical. merit: what the optimiser ranks by
    (f + penalty·h, or f where h = 0 under MADS's progressive barrier; inf if infeasible)."""

    x: FloatArray
    f: FloatArray
    feasible: BoolArray
    violation: FloatArray
    merit: FloatArray
    batch: NDArray[np.int64]  # index of the ask/tell round (vector-env step) of each evaluation


@dataclasses.dataclass(frozen=True)
class OptimResult:
    """Outcome of a run: x_best (physical) has the least merit, f_best is its raw objective.
    x_best is NaN and f_best inf when no feasible point was found."""

    x_best: FloatArray
    f_best: float
    merit_best: float
    evaluations: int
    batches: int
    history: History
    stop_reason: dict[str, float]
    wall_time: float  # s spent in ask + objective + tell, summed over resumed segments
    info: dict[str, float]  # method-specific state, e.g. MADS mesh and poll sizes


class Optimizer(abc.ABC):
    """Base class: bounds, batch size, history, incumbent, and the ask/tell bookkeeping.

    Subclasses implement `_ask_unit`, `_tell_unit`, `_stop` and optionally `_info`, working in
    the unit cube with merits (inf = infeasible). All random state lives in `self.rng` (or is
    saved explicitly), so pickling the object captures the whole run state.
    """

    def __init__(
        self,
        bounds: Bounds,
        batch_size: int,
        seed: int,
        penalty: float = 1.0,
        x0: ArrayLike | None = None,
    ) -> None:
        if not isinstance(bounds, Bounds):
            raise TypeError("bounds must be an optim.Bounds")
        if int(batch_size) < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        if not penalty >= 0:
            raise ValueError(f"penalty must be >= 0, got {penalty}")
        self.bounds = bounds
        self.batch_size = int(batch_size)
        self.seed = int(seed)
        self.penalty = float(penalty)
        self.rng = np.random.default_rng(self.seed)
        n = bounds.dimension
        if x0 is None:
            self.u0 = np.full(n, 0.5)
        else:
            x0_arr = np.asarray(x0, np.float64).reshape(-1)
            if x0_arr.size != n:
                raise ValueError(f"x0 has {x0_arr.size} entries, bounds have {n}")
            if np.any(x0_arr < bounds.lower) or np.any(x0_arr > bounds.upper):
                raise ValueError(f"x0 = {x0_arr.tolist()} lies outside the bounds")
            self.u0 = bounds.to_unit(x0_arr)
        self.wall_time = 0.0
        self._pending_x: FloatArray | None = None
        self._pending_u: FloatArray | None = None
        self._batches = 0
        self._records: list[tuple[FloatArray, BatchEvaluation, FloatArray, int]] = []
        self._evaluations = 0
        self._best_merit = np.inf

    # ---------------------------------------------------------------- subclass interface
    @abc.abstractmethod
    def _ask_unit(self, max_points: int) -> FloatArray:
        """Return (q, n) unit-cube points, 0 <= q <= max_points; q = 0 means it cannot go on."""

    @abc.abstractmethod
    def _tell_unit(self, u: FloatArray, merit: FloatArray, evaluation: BatchEvaluation) -> None:
        """Absorb the merits (inf = infeasible) of the points returned by the last `_ask_unit`."""

    def _merit(self, evaluation: BatchEvaluation) -> FloatArray:
        """phi = f + penalty · h for feasible points, +inf otherwise."""
        ev = evaluation
        merit = np.where(ev.feasible, ev.f + self.penalty * ev.violation, np.inf)
        return np.where(np.isnan(merit), np.inf, merit)

    @abc.abstractmethod
    def _stop(self) -> dict[str, float]:
        """Method-specific termination reasons."""

    def _info(self) -> dict[str, float]:
        return {}

    @abc.abstractmethod
    def options_fingerprint(self) -> tuple[Any, ...]:
        """Everything that defines the run; a checkpoint is only resumed by an equal one."""

    # ---------------------------------------------------------------- public protocol
    @property
    def dimension(self) -> int:
        return self.bounds.dimension

    @property
    def evaluations(self) -> int:
        return self._evaluations

    @property
    def min_budget(self) -> int:
        """Smallest useful budget: one batch (one CMA generation for CMA-ES)."""
        return self.batch_size

    @property
    def best_merit(self) -> float:
        return float(self._best_merit)

    def fingerprint(self) -> tuple[Any, ...]:
        return (
            type(self).__name__,
            self.bounds,
            self.batch_size,
            self.seed,
            self.penalty,
            tuple(self.u0.tolist()),
            self.options_fingerprint(),
        )

    def ask(self, budget_left: int | None = None) -> FloatArray:
        """Next batch, (q, n) physical, q <= min(batch_size, budget_left); q = 0: cannot go on."""
        if self._pending_x is not None:
            raise RuntimeError("ask() called twice without tell()")
        limit = self.batch_size if budget_left is None else min(self.batch_size, int(budget_left))
        if limit < 1 or self._stop():
            return np.empty((0, self.dimension))
        u = np.asarray(self._ask_unit(limit), np.float64).reshape(-1, self.dimension)
        if len(u) > limit:
            raise AssertionError(f"{type(self).__name__} asked {len(u)} > {limit} points")
        if len(u) == 0:
            return np.empty((0, self.dimension))
        x = np.clip(self.bounds.from_unit(u), self.bounds.lower, self.bounds.upper)
        self._pending_u, self._pending_x = u, x
        return x.copy()

    def tell(
        self,
        x: ArrayLike,
        f: ArrayLike | BatchEvaluation,
        feasible: ArrayLike | None = None,
        violation: ArrayLike | None = None,
    ) -> None:
        """Report f (and optionally the feasibility mask and violation h) for the last ask."""
        if self._pending_x is None or self._pending_u is None:
            raise RuntimeError("tell() without a preceding ask()")
        x_arr = np.asarray(x, np.float64)
        if x_arr.shape != self._pending_x.shape or not np.array_equal(x_arr, self._pending_x):
            raise ValueError("tell() must receive exactly the points returned by the last ask()")
        q = len(x_arr)
        if isinstance(f, BatchEvaluation):
            ev = BatchEvaluation.from_objective_output(f, q)
        else:
            ev = BatchEvaluation.coerce(f, q, feasible, violation)
        merit = self._merit(ev)
        u = self._pending_u
        self._records.append((x_arr.copy(), ev, merit, self._batches))
        self._evaluations += q
        self._best_merit = min(self._best_merit, float(np.min(merit)))
        self._pending_x = self._pending_u = None
        self._batches += 1
        self._tell_unit(u, merit, ev)

    def stop(self) -> dict[str, float]:
        """Termination reasons as data (empty dict: keep going)."""
        return dict(self._stop())

    def history(self) -> History:
        n = self.dimension
        if not self._records:
            e = np.empty(0)
            return History(np.empty((0, n)), e, e.astype(bool), e, e, e.astype(np.int64))
        return History(
            x=np.concatenate([r[0] for r in self._records]),
            f=np.concatenate([r[1].f for r in self._records]),
            feasible=np.concatenate([r[1].feasible for r in self._records]),
            violation=np.concatenate([r[1].violation for r in self._records]),
            merit=np.concatenate([r[2] for r in self._records]),
            batch=np.concatenate([np.full(len(r[0]), r[3], np.int64) for r in self._records]),
        )

    @property
    def result(self) -> OptimResult:
        h = self.history()
        if not np.isfinite(self._best_merit):
            x_best, f_best = np.full(self.dimension, np.nan), np.inf
        else:
            i = int(np.argmin(h.merit))
            x_best, f_best = h.x[i].copy(), float(h.f[i])
        return OptimResult(
            x_best=x_best,
            f_best=f_best,
            merit_best=float(self._best_merit),
            evaluations=len(h.f),
            batches=self._batches,
            history=h,
            stop_reason=self.stop(),
            wall_time=self.wall_time,
            info=self._info(),
        )


BatchObjective = Callable[[FloatArray], Any]
Callback = Callable[[Optimizer], bool | None]


def _plain(value: Any) -> Any:
    """A fingerprint as plain JSON values (tuples → lists, arrays → lists, Bounds → dict)."""
    if isinstance(value, Bounds):
        return {"lower": value.lower.tolist(), "upper": value.upper.tolist(), "names": None if value.names is None else list(value.names)}
    if isinstance(value, (tuple, list)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return value


@dataclasses.dataclass(frozen=True)
class Checkpoint:
    """A checkpoint read back: the evaluation log, extra arrays of the caller, and metadata."""

    path: Path
    log: dict[str, np.ndarray]
    extra: dict[str, np.ndarray]
    meta: dict[str, Any]


def save_checkpoint(
    path: str | os.PathLike[str],
    optimizer: Optimizer,
    budget: int,
    extra: dict[str, ArrayLike] | None = None,
    meta: dict[str, Any] | None = None,
) -> None:
    """Write the optimiser's evaluation log, the run's ``budget`` (what each `ask` was offered),
    and a caller's ``extra`` arrays and JSON ``meta``, atomically in the safe format of
    `lvenv.archive` (see the module docstring)."""
    h = optimizer.history()
    arrays = {name: getattr(h, name) for name in LOG_FIELDS}
    arrays.update({f"extra.{k}": np.asarray(v) for k, v in (extra or {}).items()})
    info = {"format": CHECKPOINT_FORMAT, "fingerprint": _plain(optimizer.fingerprint()), "budget": int(budget),
            "wall_time": optimizer.wall_time, "user": meta or {}}
    archive.save(path, arrays, info)


def load_checkpoint(path: str | os.PathLike[str]) -> Checkpoint:
    """Read a checkpoint; `CheckpointError` (with the path and what to do) if it is unusable."""
    try:
        arrays, meta = archive.load(path, "checkpoint")
    except archive.ArchiveError as err:
        raise CheckpointError(str(err)) from None
    if meta.get("format") != CHECKPOINT_FORMAT or any(name not in arrays for name in LOG_FIELDS):
        raise CheckpointError(
            f"checkpoint {str(path)!r} is not an optim checkpoint of format {CHECKPOINT_FORMAT}; "
            "delete it or move it away to start afresh"
        )
    log = {name: arrays[name] for name in LOG_FIELDS}
    extra = {name[len("extra."):]: v for name, v in arrays.items() if name.startswith("extra.")}
    return Checkpoint(Path(path), log, extra, meta)


def resume(optimizer: Optimizer, checkpoint: Checkpoint) -> Optimizer:
    """Replay `checkpoint`'s log into `optimizer` (fresh, same configuration) and return it."""
    where = str(checkpoint.path)
    if optimizer.evaluations:
        raise ValueError("resume() needs a fresh optimiser")
    if json.loads(json.dumps(_plain(optimizer.fingerprint()))) != checkpoint.meta["fingerprint"]:
        raise CheckpointError(
            f"checkpoint {where!r} was written by a different optimiser configuration "
            f"({checkpoint.meta['fingerprint'][0]}, seed {checkpoint.meta['fingerprint'][3]}); "
            "delete it or use the same settings"
        )
    log = checkpoint.log
    for b in np.unique(log["batch"]):
        rows = log["batch"] == b
        x = optimizer.ask(int(checkpoint.meta["budget"]) - optimizer.evaluations)
        if x.shape != log["x"][rows].shape or not np.array_equal(x, log["x"][rows]):
            raise CheckpointError(
                f"checkpoint {where!r} does not replay: batch {int(b)} asks other points than it logged "
                "(written by other code or on another platform); delete it to start afresh"
            )
        optimizer.tell(x, BatchEvaluation(log["f"][rows], log["feasible"][rows], log["violation"][rows]))
    optimizer.wall_time = float(checkpoint.meta["wall_time"])
    return optimizer


def _interactive() -> bool:
    return bool(getattr(sys.stderr, "isatty", lambda: False)())


def run(
    optimizer: Optimizer,
    batch_objective: BatchObjective,
    budget: int,
    callback: Callback | None = None,
    checkpoint: str | os.PathLike[str] | None = None,
    progress: bool | None = None,
) -> OptimResult:
    """Drive `optimizer` with `batch_objective` until it stops or `budget` evaluations are used.

    Each round is one `ask` (at most `batch_size` points: one vector-env step), one call of
    `batch_objective(X)` and one `tell`. With `checkpoint`, the evaluation log is saved after every
    round; if the file exists when `run` starts, the run resumes from it and reaches exactly the
    result of an uninterrupted run (module docstring). `callback(optimizer)` runs after each round; returning True
    stops the run (reason "callback"). `progress=None` shows a tqdm bar only on a terminal.
    """
    budget = int(budget)
    if budget < optimizer.min_budget:
        raise ValueError(
            f"budget = {budget} evaluations is below one batch of {optimizer.min_budget}"
        )
    opt = optimizer
    if checkpoint is not None and Path(checkpoint).exists():
        opt = resume(optimizer, load_checkpoint(checkpoint))
    show = _interactive() if progress is None else bool(progress)
    bar = None
    if show:
        from tqdm.auto import tqdm

        bar = tqdm(total=budget, initial=opt.evaluations, unit="eval", desc=type(opt).__name__)
    reasons: dict[str, float] = {}
    try:
        while True:
            reasons = opt.stop()
            if reasons:
                break
            t0 = time.perf_counter()
            x = opt.ask(budget - opt.evaluations)
            if len(x) == 0:
                reasons = opt.stop() or {"budget": float(budget)}
                break
            ev = BatchEvaluation.from_objective_output(batch_objective(x), len(x))
            opt.tell(x, ev)
            opt.wall_time += time.perf_counter() - t0
            if checkpoint is not None:
                save_checkpoint(checkpoint, opt, budget)
            if bar is not None:
                bar.update(len(x))
                bar.set_postfix(best=f"{opt.best_merit:.4g}")
            if callback is not None and callback(opt) is True:
                reasons = {"callback": float(opt.evaluations)}
                break
    finally:
        if bar is not None:
            bar.close()
    res = opt.result
    return dataclasses.replace(res, stop_reason={**res.stop_reason, **reasons})


def padded(batch_objective: BatchObjective, num_envs: int) -> BatchObjective:
    """Wrap an objective that needs exactly `num_envs` rows: pad with copies of the last row."""

    def objective(x: FloatArray) -> BatchEvaluation:
        q = len(x)
        if q > num_envs:
            raise ValueError(f"{q} points for {num_envs} environments")
        full = np.concatenate([x, np.repeat(x[-1:], num_envs - q, axis=0)])
        ev = BatchEvaluation.from_objective_output(batch_objective(full), num_envs)
        return BatchEvaluation(ev.f[:q], ev.feasible[:q], ev.violation[:q])

    return objective
